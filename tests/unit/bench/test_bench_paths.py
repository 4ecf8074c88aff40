"""bench/paths.py's field loading: a path camera placed at a scene view renders, with the fitted
field and the fitter's own ray bounds, exactly what the fit wrote for that view (grid, hash and
splats)."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from bench.paths import frame_renderer, load_field, ray_bounds, render_frame
from roguefit import PRESETS, FitConfig, make_pairs
from roguefit.splats import SplatConfig
from roguenerf.data.readers import load_scene
from roguenerf.metrics import psnr
from tests.fit_helpers import write_photo_set

CONFIGS = {
    "grid": FitConfig(resolution=40, features=0, steps=30, minutes=None, rays=1024, samples=48, prune_every=10),
    "hash": dataclasses.replace(PRESETS["hash"], resolution=32, hash_levels=4, hash_log2_table=14, steps=30,
                                rays=1024, samples=48, prune_every=10),
}


@pytest.mark.parametrize("kind", ["grid", pytest.param("hash", marks=pytest.mark.slow)])  # fitting a hash field
def test_a_path_camera_at_a_view_renders_what_the_fit_wrote(tmp_path, kind):
    root = tmp_path / "photos"
    write_photo_set(root, views=9)
    out = tmp_path / "pairs"
    make_pairs(root, out, CONFIGS[kind])
    scene = load_scene(out)
    field, samples = load_field(out)
    assert type(field).__name__ == {"grid": "GridField", "hash": "HashField"}[kind]
    bounds = ray_bounds(out, scene)
    for i in (scene.indices("test")[0], scene.indices("train")[1]):
        frame = scene.frames[i]
        near, far = bounds(frame.world_from_cam)
        assert 0 < near < far
        rgb, depth = render_frame(field, samples, frame.K.to(torch.float64), frame.world_from_cam.to(torch.float64),
                                  frame.width, frame.height, near, far)
        assert float(psnr(rgb[None], scene.render(i)[None])[0]) > 45  # 8-bit PNG rounding only
        assert torch.allclose(depth, scene.depth(i), rtol=1e-4, atol=1e-4)


@pytest.mark.parametrize("kind", ["grid", "splat"])
def test_every_kind_renders_a_path_camera_at_a_view_as_the_fit_did(tmp_path, kind):
    root = tmp_path / "photos"
    write_photo_set(root, views=9)
    out = tmp_path / "pairs"
    config = CONFIGS["grid"] if kind == "grid" else SplatConfig(steps=40, scale=1, init_points=500,
                                                                checkpoint_every=20)
    make_pairs(root, out, config)
    scene = load_scene(out)
    render = frame_renderer(out, scene)
    for i in (scene.indices("test")[0], scene.indices("train")[1]):
        frame = scene.frames[i]
        rgb, depth = render(frame.K, frame.world_from_cam, frame.width, frame.height)
        assert rgb.shape == (3, frame.height, frame.width) and depth.shape == (1, frame.height, frame.width)
        assert float(psnr(rgb[None], scene.render(i)[None])[0]) > 45  # 8-bit PNG rounding only
        assert torch.allclose(depth, scene.depth(i), rtol=1e-4, atol=1e-4)


@pytest.mark.slow
def test_path_speed_alternates_frame_by_frame_and_the_temporal_filter(tmp_path):
    import json

    from bench import path_speed

    root = tmp_path / "photos"
    write_photo_set(root, views=9)
    make_pairs(root, tmp_path / "pairs", CONFIGS["grid"])
    out = tmp_path / "res" / "speed"
    assert path_speed.main(["--fit", str(tmp_path / "pairs"), "--work", str(tmp_path / "work"), "--keys", "2",
                            "--steps", "2", "--repeats", "2", "--model-every", "1,3", "--resample", "bicubic,bilinear",
                            "--force", "--output", str(out)]) == 0
    summary = json.loads((tmp_path / "res" / "speed.json").read_text())
    assert summary["frames"] == 3 and summary["repeats"] == 2
    fps = summary["frames_per_second"]
    modes = ["on", "on/bilinear", "on/k3", "on/k3/bilinear"]  # the shipped values are not named
    assert list(fps) == ["off", *modes] and all(v > 0 for v in fps.values())
    assert summary["speed_ratio"] == pytest.approx({m: fps[m] / fps["off"] for m in modes})
    import csv

    rows = list(csv.DictReader(open(tmp_path / "res" / "speed.csv")))
    assert [r["temporal"] for r in rows] == ["off", *modes] * 2
    assert all(r["gains"] for r in rows)  # frames 0 and 2 sit on views with photos
    # model_every 1 carries nothing (k3: frames 1 and 2 carried where frame 0 sees enough of them)
    assert {r["carried_share"] for r in rows if "k3" not in r["temporal"]} == {"0.0"}
    assert {r["flicker_ratio"] for r in rows if r["temporal"] == "off"} != {r["flicker_ratio"] for r in rows
                                                                           if r["temporal"] == "on"}
    assert (tmp_path / "res" / "speed.png").is_file()
    # the rejection of the last frame where the renders disagree, off beside the shipped one
    assert path_speed.main(["--fit", str(tmp_path / "pairs"), "--work", str(tmp_path / "work"), "--keys", "2",
                            "--steps", "2", "--repeats", "1", "--reject", "0.04,0", "--force", "--output",
                            str(tmp_path / "res" / "reject")]) == 0
    summary = json.loads((tmp_path / "res" / "reject.json").read_text())
    assert list(summary["frames_per_second"]) == ["off", "on", "on/reject0"]
    # carrying between the model frames (shipped) beside after the last one; nothing to carry at K = 1
    assert path_speed.main(["--fit", str(tmp_path / "pairs"), "--work", str(tmp_path / "work"), "--keys", "2",
                            "--steps", "2", "--repeats", "1", "--model-every", "1,3", "--carry-between", "on,off",
                            "--carry-share", "0,1000", "--force", "--output", str(tmp_path / "res" / "between")]) == 0
    summary = json.loads((tmp_path / "res" / "between.json").read_text())
    assert list(summary["frames_per_second"]) == ["off", "on", "on/k3", "on/k3/between-off", "on/k3/share1000",
                                                  "on/k3/share1000/between-off"]
    assert all(v > 0 for v in summary["flicker_ratio_sharpened"].values())
    # each frame a gate judged (frame:agreement/change dB, c where carried): none without a gate, and
    # none on this 3-frame path, where the frames between see too little of the model frames
    rows = list(csv.DictReader(open(tmp_path / "res" / "between.csv")))
    assert [r["carry_tests"] for r in rows] == [""] * 6 and {r["carried_share"] for r in rows} == {"0.0"}
    # the path of the scene's views (every frame has a photo, each judged); a carry gate at K = 1,
    # where nothing is carried, runs once, as the shipped values
    assert path_speed.main(["--fit", str(tmp_path / "pairs"), "--work", str(tmp_path / "work"), "--keys", "3",
                            "--photo-path", "--repeats", "1", "--model-every", "1,2", "--carry-agreement", "0,30",
                            "--both-ways", "off", "--force", "--output", str(tmp_path / "res" / "photos")]) == 0
    summary = json.loads((tmp_path / "res" / "photos.json").read_text())
    assert list(summary["frames_per_second"]) == ["off", "on/both-ways-off", "on/k2/both-ways-off",
                                                  "on/k2/agree30/both-ways-off"]
    rows = list(csv.DictReader(open(tmp_path / "res" / "photos.csv")))
    assert {r["frames"] for r in rows} == {"3"}
    assert all([g.split(":")[0] for g in r["gains"].split()] == ["0", "1", "2"] for r in rows)
    # each run's carried frames with photos against frame by frame's gain there (the row's gains)
    off = path_speed.frame_gains(rows[0])
    for r in rows[1:]:
        diffs = [g - off[t][0] for t, (g, carried) in path_speed.frame_gains(r).items() if carried]
        assert int(r["carried_with_photo"]) == len(diffs)
        assert (r["worst_carried_db"] == "" if not diffs else float(r["worst_carried_db"]) == pytest.approx(
            min(diffs), abs=1e-3))
        assert summary["worst_carried_db"][r["temporal"]] == (float(r["worst_carried_db"]) if diffs else None)
    assert any(int(r["carried_with_photo"]) for r in rows[1:])
    assert rows[0].get("carried_with_photo", "") == ""  # frame by frame: nothing to judge
    # the blend's weights beside the shipped ones; each run counts the pairs whose neighbours changed
    assert path_speed.main(["--fit", str(tmp_path / "pairs"), "--work", str(tmp_path / "work"), "--keys", "2",
                            "--steps", "2", "--repeats", "1", "--weight", "0.5,0.75", "--change-frames", "0,3",
                            "--force", "--output", str(tmp_path / "res" / "weights")]) == 0
    summary = json.loads((tmp_path / "res" / "weights.json").read_text())
    assert list(summary["frames_per_second"]) == ["off", "on/w0.5", "on/w0.5/cf3", "on", "on/cf3"]
    rows = list(csv.DictReader(open(tmp_path / "res" / "weights.csv")))
    assert len({r["neighbour_changes"] for r in rows}) == 1 and int(rows[0]["neighbour_changes"]) >= 0
    # an older revision's TemporalFilter beside this checkout's, alternated: HEAD's is this one's, so
    # the same frames (flicker and gain), each run's CPU seconds kept
    import subprocess

    head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                          check=True).stdout.strip()
    assert path_speed.main(["--fit", str(tmp_path / "pairs"), "--work", str(tmp_path / "work"), "--keys", "2",
                            "--steps", "2", "--repeats", "2", "--model-every", "3", "--filter-before", "HEAD",
                            "--force", "--output", str(tmp_path / "res" / "before")]) == 0
    rows = list(csv.DictReader(open(tmp_path / "res" / "before.csv")))
    assert [r["temporal"] for r in rows] == ["off", "on/k3", f"on/k3@{head}", "off", f"on/k3@{head}", "on/k3"]
    for field in ("flicker_ratio", "gain_db", "carried_share"):
        assert len({r[field] for r in rows if r["temporal"] != "off"}) == 1
    assert all(float(r["cpu_seconds"]) > 0 for r in rows)
    summary = json.loads((tmp_path / "res" / "before.json").read_text())
    assert set(summary["cpu_seconds"]) == {"off", "on/k3", f"on/k3@{head}"}
    # a revision from before TemporalConfig.fade_along (b1222f1): its filter runs under this checkout's
    # enhance_path, and this checkout's with the plain fade makes its frames
    assert path_speed.main(["--fit", str(tmp_path / "pairs"), "--work", str(tmp_path / "work"), "--keys", "2",
                            "--steps", "2", "--repeats", "1", "--fade-along", "off", "--filter-before", "b1222f1",
                            "--force", "--output", str(tmp_path / "res" / "plain")]) == 0
    rows = list(csv.DictReader(open(tmp_path / "res" / "plain.csv")))
    assert [r["temporal"] for r in rows] == ["off", "on/fade-along-off", "on/fade-along-off@b1222f1"]
    for field in ("flicker_ratio", "gain_db"):
        assert len({r[field] for r in rows if r["temporal"] != "off"}) == 1


@pytest.mark.slow
def test_flicker_sharpness_shows_a_consistent_sharpening_as_flicker(tmp_path):
    """The same unsharp mask on every frame of a path scores more flicker the stronger it is,
    a blur less; low-passing the difference takes most of it away."""
    import json

    from bench import flicker_sharpness

    root = tmp_path / "photos"
    write_photo_set(root, views=9)
    make_pairs(root, tmp_path / "pairs", CONFIGS["grid"])
    out = tmp_path / "res" / "sharp"
    assert flicker_sharpness.main(["--fit", str(tmp_path / "pairs"), "--work", str(tmp_path / "work"), "--keys", "2",
                                   "--steps", "3", "--amounts", "1,3", "--output", str(out)]) == 0
    ratio = json.loads((tmp_path / "res" / "sharp.json").read_text())["ratio"]
    plain, low = ratio["plain"], ratio["lowpass"]
    assert plain["render"] == low["render"] == 1.0
    assert 1.0 < plain["unsharp 1"] < plain["unsharp 3"] and plain["blur"] < 1.0
    assert low["unsharp 3"] < plain["unsharp 3"]
    assert (tmp_path / "res" / "sharp.csv").is_file() and (tmp_path / "res" / "sharp.png").is_file()
    with pytest.raises(SystemExit, match="amounts"):
        flicker_sharpness.main(["--fit", str(tmp_path / "pairs"), "--amounts", "0"])
