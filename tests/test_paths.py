"""Camera paths: nerfstudio camera_path.json in, enhanced frames + MP4 out, flicker measured, resumable."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch
from kornia.filters import gaussian_blur2d
from typer.testing import CliRunner

from roguenerf.checkpoint import default_checkpoint_path, load_checkpoint
from roguenerf.cli import app
from roguenerf.data.exports import DATAPARSER_FILE, DataparserTransform, write_depth_like
from roguenerf.data.toy import make_toy_scene, make_toy_world, render_toy_view, toy_camera_path
from roguenerf.errors import InputError, PathCancelled
from roguenerf.geometry import opencv_to_opengl
from roguenerf.imageio import write_png
from roguenerf.inference import SceneEnhancer
from roguenerf.paths import (
    FLICKER_FILE,
    enhance_path,
    pair_flicker,
    read_camera_path,
    smooth_path,
)
from roguenerf.video import read_video_info

H, W, SEED, STEPS = 24, 32, 4, 3
PARSER = DataparserTransform(
    transform=torch.tensor([[0.0, -1.0, 0.0, 0.3], [1.0, 0.0, 0.0, -0.5], [0.0, 0.0, 1.0, 1.0]], dtype=torch.float64),
    scale=0.5)


def _ray_norm(K):
    u = torch.arange(W, dtype=torch.float64) + 0.5
    v = torch.arange(H, dtype=torch.float64) + 0.5
    return torch.sqrt(((u[None] - K[0, 2]) / K[0, 0]) ** 2 + ((v[:, None] - K[1, 2]) / K[1, 1]) ** 2 + 1)


@pytest.fixture(scope="module")
def toy_path(tmp_path_factory):
    """A toy scene, and a smooth path through three of its views with renders no photo was taken from."""
    root = tmp_path_factory.mktemp("path")
    scene = make_toy_scene(root / "scene", seed=SEED, n_train=6, n_test=1, height=H, width=W, kind="orbit")
    (root / "scene" / DATAPARSER_FILE).write_text(json.dumps(PARSER.to_json()))
    world = make_toy_world(SEED)
    assert torch.equal(toy_camera_path(world, 7, seed=SEED, kind="orbit"), scene.poses())
    keys = scene.poses([1, 2, 3])
    poses = smooth_path(keys, STEPS)
    K = scene.frames[0].K
    (root / "frames" / "rgb").mkdir(parents=True)
    (root / "frames" / "depth").mkdir()
    cams = []
    for t, pose in enumerate(poses):
        rgb, z = render_toy_view(world, pose, K, H, W)
        render = gaussian_blur2d(rgb[None], (5, 5), (1.0, 1.0), border_type="replicate")[0].clamp(0, 1)
        write_png(root / "frames" / "rgb" / f"frame_{t}.png", render)
        # nerfacto-like: distance along the ray, gzip'd (H, W, 1) as ns-render writes raw depth.
        write_depth_like(root / "frames" / "depth" / f"frame_{t}.npy.gz", (z[0].double() * _ray_norm(K)).numpy(),
                         kind="npy.gz")
        model_pose = PARSER.to_model(opencv_to_opengl(pose))
        fov = math.degrees(2 * math.atan(H / 2 / float(K[1, 1])))
        cams.append({"camera_to_world": model_pose.flatten().tolist(), "fov": fov, "aspect": W / H})
    (root / "camera_path.json").write_text(json.dumps(
        {"camera_type": "perspective", "render_height": H, "render_width": W, "fps": 12, "camera_path": cams}))
    return {"root": root, "scene": scene, "poses": poses}


@pytest.fixture(scope="module")
def enhancer(toy_path):
    model, _ = load_checkpoint(default_checkpoint_path())
    return SceneEnhancer(toy_path["scene"], model)


def test_nerfstudio_camera_path_maps_back_to_scene_poses(toy_path):
    cp = read_camera_path(toy_path["root"] / "camera_path.json", dataparser=PARSER)
    assert len(cp) == len(toy_path["poses"]) == 2 * STEPS + 1
    assert (cp.width, cp.height, cp.fps, cp.source) == (W, H, 12, "nerfstudio")
    torch.testing.assert_close(cp.world_from_cam, toy_path["poses"], rtol=0, atol=1e-9)
    torch.testing.assert_close(cp.K[0], toy_path["scene"].frames[0].K, rtol=1e-9, atol=1e-9)
    # smooth_path passes through its key poses and keeps rotations rotations.
    torch.testing.assert_close(toy_path["poses"][STEPS], toy_path["scene"].poses([2])[0])
    R = toy_path["poses"][:, :3, :3]
    torch.testing.assert_close(R.transpose(1, 2) @ R, torch.eye(3, dtype=torch.float64).expand_as(R))


def test_flicker_is_zero_for_a_static_world_and_positive_for_noise(toy_path):
    scene = toy_path["scene"]
    a, b = scene.indices("train")[:2]
    photos = [scene.photo(a)], [scene.photo(b)]
    args = (scene.depth(a), scene.depth(b), scene.frames[a].K, scene.frames[b].K,
            scene.frames[a].world_from_cam, scene.frames[b].world_from_cam)
    (clean,), fraction = pair_flicker(*photos, *args)
    assert fraction > 0.3 and clean < 0.03  # exact geometry: only resampling error
    noisy = [(scene.photo(a) + 0.1 * torch.randn(3, H, W, generator=torch.Generator().manual_seed(0))).clamp(0, 1)]
    (worse,), _ = pair_flicker(noisy, photos[1], *args)
    assert worse > clean + 0.03
    (none,), _ = pair_flicker([None], photos[1], *args)
    assert none is None


def test_enhance_path_writes_video_flicker_and_resumes(toy_path, enhancer, tmp_path):
    root, scene = toy_path["root"], toy_path["scene"]
    cp = read_camera_path(root / "camera_path.json", dataparser=PARSER)
    out = tmp_path / "out"
    calls = []
    result = enhance_path(scene, enhancer, cp, root / "frames", out, depth_type="ray", quality=23,
                          progress=lambda d, t: calls.append((d, t)))
    T = len(cp)
    assert result.frames == result.enhanced_now == T and calls[-1] == (T, T)
    assert sorted(p.name for p in (out / "frames").iterdir()) == [f"{t:05d}.png" for t in range(T)]
    info = read_video_info(result.video)
    assert (info["frames"], info["width"], info["height"], info["codec"]) == (T, W, H, "h264")
    side = read_video_info(result.side_by_side)
    assert (side["frames"], side["width"], side["height"]) == (T, 2 * W, H)
    report = json.loads((out / FLICKER_FILE).read_text())
    assert report["frames"] == T and report["flicker"]["pairs"] == T - 1
    for pair in report["per_pair"]:
        assert pair["valid_fraction"] > 0.3 and pair["render"] > 0 and pair["enhanced"] > 0
    # Frames 0, STEPS, 2 * STEPS sit on scene views 1..3: they have photos and a PSNR gain figure.
    with_photos = [f["frame"] for f in report["per_frame"] if "gain_db" in f]
    assert with_photos == [0, STEPS, 2 * STEPS]
    assert [report["per_frame"][t]["view"] for t in with_photos] == [scene.frames[i].name for i in (1, 2, 3)]
    assert report["psnr"]["frames_with_photos"] == 3 and math.isfinite(report["psnr"]["mean_gain_db"])
    assert report["flicker"]["ratio"] == pytest.approx(report["flicker"]["enhanced"] / report["flicker"]["render"])
    # The path's training photos were encoded once, for the whole path.
    assert 0 < result.cached_views <= len(scene.indices("train"))

    # Interrupted: two frames lost, then a cancel after the first of them; a re-run finishes the rest.
    first = (out / "frames" / "00002.png").read_bytes()
    (out / "frames" / "00002.png").unlink()
    (out / "frames" / "00005.png").unlink()
    asked = iter([False, False, False, True])
    with pytest.raises(PathCancelled):
        enhance_path(scene, enhancer, cp, root / "frames", out, depth_type="ray", quality=23,
                     should_stop=lambda: next(asked))
    assert (out / "frames" / "00002.png").is_file() and not (out / "frames" / "00005.png").exists()
    again = enhance_path(scene, enhancer, cp, root / "frames", out, depth_type="ray", quality=23, video=False)
    assert again.enhanced_now == 1 and (out / "frames" / "00002.png").read_bytes() == first
    assert again.flicker["flicker"] == pytest.approx(report["flicker"])
    # Another setting into the same folder is refused instead of mixing frames.
    with pytest.raises(InputError, match="another path"):
        enhance_path(scene, enhancer, cp, root / "frames", out, depth_type="z", video=False)


def test_enhance_path_cli(toy_path, tmp_path):
    root = toy_path["root"]
    runner = CliRunner()
    args = ["enhance-path", str(root / "scene"), "--frames", str(root / "frames"), "--cameras",
            str(root / "camera_path.json"), "--output", str(tmp_path / "cli"), "--depth-type", "ray", "--no-video"]
    result = runner.invoke(app, args)
    assert result.exit_code == 0, result.output
    assert "flicker" in result.output and "frames have photos" in result.output
    report = json.loads((tmp_path / "cli" / FLICKER_FILE).read_text())
    assert report["frames"] == 2 * STEPS + 1
    bad = runner.invoke(app, args[:-1] + ["--quality", "99"])
    assert bad.exit_code == 2 and "--quality" in bad.output and "Traceback" not in bad.output
    (tmp_path / "empty").mkdir()
    wrong = runner.invoke(app, [*args[:3], str(tmp_path / "empty"), *args[4:]])
    assert wrong.exit_code == 2 and "no frames found" in wrong.output


def test_bad_camera_paths_are_named(tmp_path):
    bad = tmp_path / "p.json"
    bad.write_text(json.dumps({"render_height": 4, "render_width": 4, "camera_path": [{"fov": 50}]}))
    with pytest.raises(InputError, match="camera_to_world"):
        read_camera_path(bad)
    bad.write_text("{")
    with pytest.raises(InputError, match="cannot read"):
        read_camera_path(bad)
    ours = tmp_path / "t.json"
    pose = np.eye(4).tolist()
    ours.write_text(json.dumps({"fl_x": 10, "cx": 2, "cy": 2, "w": 4, "h": 4,
                                "frames": [{"transform_matrix": pose}, {"transform_matrix": pose}]}))
    cp = read_camera_path(ours)
    assert len(cp) == 2 and cp.source == "transforms" and (cp.width, cp.height) == (4, 4)


def test_paths_and_exports_import_no_service_stack_no_fitter_no_av():
    import subprocess
    import sys

    code = ("import sys, roguenerf.paths, roguenerf.data.exports, roguenerf.video; "
            "print(sorted(m for m in ('fastapi', 'huey', 'uvicorn', 'roguefit', 'av', 'service', 'workers') "
            "if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=120)
    assert out.stdout.strip() == "[]", out.stdout + out.stderr
