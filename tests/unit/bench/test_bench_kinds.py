"""bench/kinds.py's pieces with known answers: the downscaled photo set, the noisy scene (training
poses only), the per-condition summary."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
import torch
from PIL import Image

from bench import kinds
from roguenerf.data.toy import make_toy_scene
from roguenerf.geometry.noise import camera_spread
from tests.fit_helpers import write_photo_set


def test_downscaled_photo_set_scales_images_and_intrinsics(tmp_path):
    write_photo_set(tmp_path / "src", views=4)
    out = kinds.downscaled_photo_set(tmp_path / "src", tmp_path / "half", 2)
    src, half = (json.loads((p / "transforms.json").read_text()) for p in (tmp_path / "src", out))
    assert (half["w"], half["h"]) == (20, 15)
    assert half["fl_x"] == pytest.approx(src["fl_x"] / 2) and half["cy"] == pytest.approx(src["cy"] / 2)
    assert [f["transform_matrix"] for f in half["frames"]] == [f["transform_matrix"] for f in src["frames"]]
    assert Image.open(out / half["frames"][0]["file_path"]).size == (20, 15)
    assert kinds.downscaled_photo_set(tmp_path / "src", tmp_path / "same", 1) == tmp_path / "src"


def test_noisy_scene_moves_only_the_training_poses(tmp_path):
    scene = make_toy_scene(tmp_path / "toy", seed=1, n_train=6, n_test=2, height=24, width=32)
    noisy = kinds.noisy_scene(scene, 1.0, 0.1, seed=3)
    train, test = scene.indices("train"), scene.indices("test")
    assert torch.equal(noisy.poses(test), scene.poses(test))
    moved = (noisy.poses(train)[:, :3, 3] - scene.poses(train)[:, :3, 3]).norm(dim=-1)
    assert (moved > 0).all() and float(moved.max()) < 0.1 * camera_spread(scene.poses(train)) * 5
    assert torch.equal(noisy.render(train[0]), scene.render(train[0]))
    again = kinds.noisy_scene(scene, 1.0, 0.1, seed=3)
    assert torch.equal(again.poses(), noisy.poses())  # one fixed draw per seed


def test_summary_means_worst_view_and_flip_counts():
    def row(view, gain, flip_change, stage="zero-shot", deg=0.0):
        return {"scene": "s", "kind": "hash", "stage": stage, "minutes": 0.0, "noise_deg": deg, "noise_share": 0.0,
                "view": view, "render_psnr": 20.0, "gain_db": gain, "render_flip": 0.2, "flip_change": flip_change}

    rows = [row("a", 1.0, -0.01), row("b", -0.5, 0.02), row("a", 0.2, -0.03, deg=0.5)]
    out = kinds.summary(rows)
    assert len(out) == 2
    assert out[0]["gain_db"] == pytest.approx(0.25) and out[0]["worst_view_gain_db"] == -0.5
    assert out[0]["views_flip_better"] == 1 and out[0]["flip_change"] == pytest.approx(0.005)
    assert out[1]["noise_deg"] == 0.5 and out[1]["views"] == 1 and not math.isnan(out[1]["gain_db"])


def test_the_neighbour_sweep_is_its_own_condition_and_plots(tmp_path):
    def row(view, gain, n, stage="zero-shot", minutes=0.0):
        return {"scene": "s", "kind": "hash", "stage": stage, "minutes": minutes, "noise_deg": 0.0,
                "noise_share": 0.0, "neighbours": n, "model_neighbours": 2, "view": view, "render_psnr": 20.0,
                "gain_db": gain, "render_flip": 0.2, "flip_change": -0.01, "checkpoint": "c.safetensors",
                "machine": "m", "commit": "abc", "date": "2026-11-26"}

    rows = [row("a", 1.0, 2), row("b", 0.0, 2), row("a", 2.0, 4), row("b", 1.0, 4),
            row("a", 3.0, 2, "finetune 1 min", 1.0), row("b", 2.0, 2, "finetune 1 min", 1.0)]
    out = {(m["stage"], m["neighbours"]): m for m in kinds.summary(rows)}
    assert set(out) == {("zero-shot", 2), ("zero-shot", 4), ("finetune 1 min", 2)}
    assert out["zero-shot", 2]["gain_db"] == pytest.approx(0.5) and out["zero-shot", 4]["gain_db"] == pytest.approx(1.5)
    assert out["zero-shot", 4]["worst_view_gain_db"] == 1.0
    png = kinds.plot(rows, tmp_path / "kinds.png")
    assert png.is_file() and png.stat().st_size > 10_000


def test_compare_puts_checkpoints_side_by_side_per_kind_scene_and_noise(tmp_path):
    from bench import kinds_compare

    def run(name, checkpoint, kind, gains):
        rows = [{"scene": s, "checkpoint": checkpoint, "commit": "abc"} for s, _, _ in gains]
        means = [{"scene": s, "kind": kind, "stage": "zero-shot", "minutes": 0.0, "noise_deg": d, "noise_share": d / 10,
                  "neighbours": 2, "model_neighbours": 2, "views": 3, "render_psnr": 20.0, "gain_db": g,
                  "worst_view_gain_db": g - 1, "flip_change": -0.01, "views_flip_better": 3} for s, d, g in gains]
        path = tmp_path / name
        path.write_text(json.dumps({"rows": rows, "means": means}))
        return path

    paths = [run("a.json", "/x/old.safetensors", "hash", [("s", 0.0, 1.0), ("s", 0.25, -0.5)]),
             run("b.json", "/x/new.safetensors", "hash", [("s", 0.0, 0.8), ("s", 0.25, 0.3)]),
             run("c.json", "/x/new.safetensors", "splat", [("t", 0.0, 0.2)])]
    rows = kinds_compare.compare_rows(paths)
    assert kinds_compare.zero_shot(rows, 0.0, 0.0) == {("hash", "s"): {"old": 1.0, "new": 0.8},
                                                       ("splat", "t"): {"new": 0.2}}
    assert kinds_compare.zero_shot(rows, 0.25, 0.025) == {("hash", "s"): {"old": -0.5, "new": 0.3}}
    assert kinds_compare.main([*map(str, paths), "--output", str(tmp_path / "cmp")]) == 0
    assert (tmp_path / "cmp.png").stat().st_size > 10_000 and len((tmp_path / "cmp.csv").read_text().splitlines()) == 6


def test_output_stem_keeps_a_dot_in_its_name_and_the_fine_tune_options_their_own_stage(tmp_path, monkeypatch):
    """``--output DIR/hash_ft0.6`` writes hash_ft0.6.{csv,json,png} (not hash_ft0.*), and a fine-tune
    with ``--finetune-depth-noise`` is a condition of its own."""
    def row(view, gain, stage, minutes):
        return {"scene": "s", "kind": "hash", "stage": stage, "minutes": minutes, "noise_deg": 0.0,
                "noise_share": 0.0, "neighbours": 2, "model_neighbours": 2, "view": view, "render_psnr": 20.0,
                "gain_db": gain, "render_flip": 0.2, "flip_change": -0.01, "checkpoint": "c.safetensors",
                "machine": "m", "commit": "abc", "date": "2026-11-26"}

    rows = [row("a", 1.0, "finetune 10 min", 10.0), row("a", 0.5, "finetune 10 min, depth noise 0.6", 10.0)]
    monkeypatch.setattr(kinds, "run", lambda args: (rows, []))
    monkeypatch.setattr(kinds.sys, "argv", ["kinds.py"])
    assert kinds.main(["--kind", "hash", "--scenes", "can_clip", "--noise", "", "--finetune-depth-noise", "0.6",
                       "--output", str(tmp_path / "hash_ft0.6")]) == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["hash_ft0.6.csv", "hash_ft0.6.json", "hash_ft0.6.png"]
    means = json.loads((tmp_path / "hash_ft0.6.json").read_text())["means"]
    assert sorted(m["gain_db"] for m in means) == [0.5, 1.0]


def test_every_bench_output_keeps_a_dot_in_its_name(tmp_path):
    """``beside`` replaces only a .csv/.json/.png ending: ``Path.with_suffix`` would turn
    ``run_0.5`` into ``run_0.png`` and two runs would overwrite each other's plots."""
    from bench import kinds_compare
    from bench.common import beside

    assert beside(Path("r/run_0.5"), ".png") == Path("r/run_0.5.png")
    assert beside(Path("r/run_0.5.csv"), ".json") == Path("r/run_0.5.json")
    assert beside(Path("r/stages.csv"), ".csv") == Path("r/stages.csv")
    assert beside(Path("r/kinds.png"), "_quick") == Path("r/kinds_quick")
    means = [{"scene": "s", "kind": "hash", "stage": "zero-shot", "minutes": 0.0, "noise_deg": 0.0, "noise_share": 0.0,
              "neighbours": 2, "model_neighbours": 2, "views": 3, "render_psnr": 20.0, "gain_db": 0.5,
              "worst_view_gain_db": 0.1, "flip_change": -0.01, "views_flip_better": 3}]
    run = tmp_path / "a.json"
    run.write_text(json.dumps({"rows": [{"scene": "s", "checkpoint": "/x/c.safetensors", "commit": "abc"}],
                               "means": means}))
    for output in ("cmp_0.5", "cmp_0.6.csv"):
        assert kinds_compare.main([str(run), "--output", str(tmp_path / output)]) == 0
    assert sorted(p.name for p in tmp_path.glob("cmp*")) == ["cmp_0.5.csv", "cmp_0.5.png", "cmp_0.6.csv", "cmp_0.6.png"]


def test_colour_cache_tag_names_what_differs_from_the_cached_setting():
    """Rows cached as ``_colourfield`` were measured with local_sigma 8: another setting must not
    read them back (it would report the old setting's figures as its own)."""
    from roguenerf.enhance.colour import ColourConfig

    assert kinds.colour_cache_tag(ColourConfig(local_sigma=8.0)) == "_colourfield"
    assert kinds.colour_cache_tag(ColourConfig(local_sigma=3.0)) == "_colourfield_local_sigma3"
    assert kinds.colour_cache_tag(ColourConfig(local_sigma=8.0, min_share=0.05)) == "_colourfield_min_share0.05"


def test_the_fine_tune_options_reach_the_fine_tune_and_name_its_cache(tmp_path, monkeypatch):
    """``--finetune-render-warp 4`` fine-tunes with ``TrainConfig.render_warp`` 4 into a folder and a
    cache of its own (``10min_warp4``), so a run without it is never read back as one with it; the
    same for ``--finetune-neighbour-renders`` (``10min_drawn0.5``)."""
    import roguenerf.checkpoint
    import roguenerf.data.readers
    import roguenerf.training

    class Model:
        config = type("Config", (), {"num_neighbours": 2})()

    seen = {}

    def fake_finetune(scene, output, *, checkpoint, config):
        seen.update(output=output, warp=config.render_warp, depth=config.depth_noise, minutes=config.minutes,
                    drawn=config.neighbour_renders)
        raise StopIteration  # stop before evaluating the tuned model

    def fake_cached(path, measure):
        seen.setdefault("caches", []).append(path.name)
        return [{"gain_db": 0.0, "flip_change": 0.0, "stage": "zero-shot", "noise_deg": 0.0, "noise_share": 0.0}] \
            if path.name.startswith("zero_shot") else measure()

    monkeypatch.setattr(kinds, "downscaled_photo_set", lambda src, dst, scale: dst)
    monkeypatch.setattr(kinds, "fit_pairs", lambda *a, **k: {"steps": 1, "fit_seconds": 0.0, "render_seconds": 0.0,
                                                              "train": {"psnr": 20.0}, "test": None})
    monkeypatch.setattr(kinds, "cached_rows", fake_cached)
    monkeypatch.setattr(roguenerf.data.readers, "load_scene", lambda path: "scene")
    monkeypatch.setattr(roguenerf.checkpoint, "load_checkpoint", lambda path: (Model(), {}))
    monkeypatch.setattr(roguenerf.training, "finetune", fake_finetune)
    args = kinds.parse_args(["--kind", "splat", "--scenes", "ollie", "--noise", "", "--finetune", "10",
                             "--finetune-render-warp", "4", "--runs", str(tmp_path)])
    with pytest.raises(StopIteration):
        kinds.measure_scene(args, "ollie", tmp_path / "default.safetensors", {}, "splat_s1")
    assert (seen["warp"], seen["depth"], seen["minutes"]) == (4.0, 0.0, 10.0)
    assert seen["output"].name == "10min_warp4"
    assert seen["caches"][-1].startswith("finetune_10min_warp4")
    args = kinds.parse_args(["--kind", "splat", "--scenes", "ollie", "--noise", "", "--finetune", "10",
                             "--finetune-neighbour-renders", "0.5", "--runs", str(tmp_path)])
    with pytest.raises(StopIteration):
        kinds.measure_scene(args, "ollie", tmp_path / "default.safetensors", {}, "splat_s1")
    assert (seen["warp"], seen["drawn"], seen["output"].name) == (0.0, 0.5, "10min_drawn0.5")
    assert seen["caches"][-1].startswith("finetune_10min_drawn0.5")
