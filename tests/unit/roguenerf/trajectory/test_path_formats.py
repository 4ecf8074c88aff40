"""Camera paths as 3DGS tools write them: Inria's cameras.json and COLMAP's images.txt / .bin."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from roguenerf.data.colmap import (
    ColmapCamera,
    ColmapImage,
    ColmapModel,
    write_colmap,
    write_colmap_model,
)
from roguenerf.data.toy import make_toy_world, toy_camera_path
from roguenerf.errors import InputError
from roguenerf.trajectory import find_camera_file, read_camera_path

W, H = 40, 30


@pytest.fixture(scope="module")
def poses():
    return toy_camera_path(make_toy_world(2), 6, seed=2, kind="orbit")


def _inria_entry(i, name, world_from_cam, fx, fy):
    """Inria's camera_to_JSON, step by step: Camera.R is the camera-to-world rotation (the
    transpose of COLMAP's world-to-camera one), Camera.T COLMAP's tvec; Rt = [R^T | T] is
    world-to-camera and its inverse (named W2C there) gives position and rotation."""
    c2w = world_from_cam.numpy()
    R = c2w[:3, :3]
    T = -R.T @ c2w[:3, 3]
    Rt = np.zeros((4, 4))
    Rt[:3, :3] = R.transpose()
    Rt[:3, 3] = T
    Rt[3, 3] = 1.0
    W2C = np.linalg.inv(Rt)
    return {"id": i, "img_name": name, "width": W, "height": H, "position": W2C[:3, 3].tolist(),
            "rotation": [x.tolist() for x in W2C[:3, :3]], "fy": fy, "fx": fx}


def test_inria_cameras_json(poses, tmp_path):
    cams = [_inria_entry(i, f"view_{i}", p, 33.0 + i, 34.0) for i, p in enumerate(poses)]
    (tmp_path / "cameras.json").write_text(json.dumps(cams))
    path = read_camera_path(tmp_path / "cameras.json")
    assert path.source == "inria" and len(path) == 6 and (path.width, path.height) == (W, H)
    assert (path.world_from_cam - poses).abs().max() < 1e-9
    for i in range(6):
        want = torch.tensor([[33.0 + i, 0, W / 2], [0, 34.0, H / 2], [0, 0, 1]], dtype=torch.float64)
        assert torch.equal(path.K[i], want)
    assert path.fps == 24.0
    assert find_camera_file(tmp_path) == tmp_path / "cameras.json"


def test_inria_cameras_json_errors_name_the_camera(poses, tmp_path):
    cams = [_inria_entry(i, f"view_{i}", p, 33.0, 33.0) for i, p in enumerate(poses)]
    bad = json.loads(json.dumps(cams))
    del bad[3]["fx"]
    (tmp_path / "a.json").write_text(json.dumps(bad))
    with pytest.raises(InputError, match=r"cameras\[3\] \(view_3\).*fx"):
        read_camera_path(tmp_path / "a.json")
    bad = json.loads(json.dumps(cams))
    bad[4]["rotation"] = (-np.asarray(bad[4]["rotation"])).tolist()  # a reflection
    (tmp_path / "b.json").write_text(json.dumps(bad))
    with pytest.raises(InputError, match=r"cameras\[4\] \(view_4\) pose.*det"):
        read_camera_path(tmp_path / "b.json")
    bad = json.loads(json.dumps(cams))
    bad[2]["width"] = 80
    (tmp_path / "c.json").write_text(json.dumps(bad))
    with pytest.raises(InputError, match=r"cameras\[2\] \(view_2\) is 80x30.*one size"):
        read_camera_path(tmp_path / "c.json")


@pytest.mark.parametrize("binary", [False, True])
def test_colmap_images_file(poses, tmp_path, binary):
    names = [f"frame_{i:03d}.png" for i in range(6)]
    K = torch.tensor([[35.0, 0, 20.25], [0, 36.0, 14.75], [0, 0, 1]], dtype=torch.float64)
    order = [4, 1, 5, 0, 3, 2]  # the model's order is not the path's: names order it
    write_colmap(tmp_path, names=[names[i] for i in order], K=K, world_from_cam=poses[order],
                 widths=W, heights=H, binary=binary)
    path = read_camera_path(tmp_path / ("images.bin" if binary else "images.txt"))
    assert path.source == "colmap" and (path.width, path.height) == (W, H)
    assert (path.world_from_cam - poses).abs().max() < 1e-9
    assert (path.K - K).abs().max() < 1e-12
    if not binary:
        assert find_camera_file(tmp_path) == tmp_path / "images.txt"


def test_colmap_images_file_known_answer_and_errors(tmp_path):
    (tmp_path / "cameras.txt").write_text("1 PINHOLE 40 30 35 36 20 15\n2 OPENCV 40 30 35 36 20 15 0.1 0 0 0\n")
    c, s = math.cos(math.pi / 4), math.sin(math.pi / 4)
    (tmp_path / "images.txt").write_text(f"1 {c!r} 0 0 {s!r} 1 2 3 1 b.png\n\n2 1 0 0 0 0 0 0 1 a.png\n\n")
    path = read_camera_path(tmp_path / "images.txt")
    want = torch.tensor([[0.0, 1, 0, -2], [-1, 0, 0, 1], [0, 0, 1, -3], [0, 0, 0, 1]], dtype=torch.float64)
    assert torch.equal(path.world_from_cam[0], torch.eye(4, dtype=torch.float64))  # a.png first
    assert (path.world_from_cam[1] - want).abs().max() < 1e-12
    # A distorted camera: refused, naming the camera of the path and saying to undistort.
    (tmp_path / "images.txt").write_text("1 1 0 0 0 0 0 0 1 a.png\n\n2 1 0 0 0 0 0 0 2 b.png\n\n")
    with pytest.raises(InputError, match=r"camera 1 \(image 2, b.png\).*image_undistorter"):
        read_camera_path(tmp_path / "images.txt")
    (tmp_path / "cameras.txt").unlink()
    with pytest.raises(InputError, match="needs its cameras.txt"):
        read_camera_path(tmp_path / "images.txt")


def test_colmap_sizes_must_agree(tmp_path):
    cams = {1: ColmapCamera(1, "PINHOLE", 40, 30, (35.0, 35.0, 20.0, 15.0)),
            2: ColmapCamera(2, "PINHOLE", 64, 48, (35.0, 35.0, 32.0, 24.0))}
    ims = {1: ColmapImage(1, (1.0, 0, 0, 0), (0.0, 0, 0), 1, "a.png"),
           2: ColmapImage(2, (1.0, 0, 0, 0), (0.0, 0, 1), 2, "b.png")}
    write_colmap_model(tmp_path, ColmapModel(cams, ims), binary=False)
    with pytest.raises(InputError, match=r"camera 1 \(image 2, b.png\) is 64x48.*one size"):
        read_camera_path(tmp_path / "images.txt")


@pytest.mark.slow
def test_enhance_path_cli_same_frames_from_every_camera_format(tmp_path):
    """The same path given as a transforms list, Inria's cameras.json and COLMAP's images.txt
    enhances to byte-identical frames (the readers agree end to end)."""
    from kornia.filters import gaussian_blur2d
    from typer.testing import CliRunner

    from roguecli import app
    from roguenerf.data.toy import make_toy_scene, render_toy_view
    from roguenerf.geometry import opencv_to_opengl
    from roguenerf.imageio import write_png
    from roguenerf.trajectory import smooth_path

    h, w = 24, 32
    scene = make_toy_scene(tmp_path / "scene", seed=4, n_train=6, n_test=1, height=h, width=w, kind="orbit")
    world = make_toy_world(4)
    poses = smooth_path(scene.poses([1, 2, 3]), 2)
    K = scene.frames[0].K
    (tmp_path / "frames" / "rgb").mkdir(parents=True)
    (tmp_path / "frames" / "depth").mkdir()
    names = [f"frame_{t}" for t in range(len(poses))]
    for name, pose in zip(names, poses, strict=True):
        rgb, z = render_toy_view(world, pose, K, h, w)
        render = gaussian_blur2d(rgb[None], (5, 5), (1.0, 1.0), border_type="replicate")[0].clamp(0, 1)
        write_png(tmp_path / "frames" / "rgb" / f"{name}.png", render)
        np.save(tmp_path / "frames" / "depth" / f"{name}.npy", z[0].numpy())
    fx, fy = float(K[0, 0]), float(K[1, 1])
    assert float(K[0, 2]) == w / 2 and float(K[1, 2]) == h / 2  # Inria's principal point
    (tmp_path / "transforms.json").write_text(json.dumps({
        "fl_x": fx, "fl_y": fy, "cx": w / 2, "cy": h / 2, "w": w, "h": h,
        "frames": [{"transform_matrix": opencv_to_opengl(p).tolist()} for p in poses]}))
    inria = [_inria_entry(i, n, p, fx, fy) for i, (n, p) in enumerate(zip(names, poses, strict=True))]
    for cam in inria:
        cam["width"], cam["height"] = w, h
    (tmp_path / "cameras.json").write_text(json.dumps(inria))
    write_colmap(tmp_path / "colmap", names=[f"{n}.png" for n in names], K=K, world_from_cam=poses,
                 widths=w, heights=h, binary=False)
    runner = CliRunner()
    frames = {}
    for label, cameras in (("transforms", tmp_path / "transforms.json"), ("inria", tmp_path / "cameras.json"),
                           ("colmap", tmp_path / "colmap" / "images.txt")):
        out = tmp_path / f"out_{label}"
        r = runner.invoke(app, ["enhance-path", str(tmp_path / "scene"), "--frames", str(tmp_path / "frames"),
                                "--cameras", str(cameras), "--output", str(out), "--no-video"])
        assert r.exit_code == 0, r.output
        frames[label] = [p.read_bytes() for p in sorted((out / "frames").iterdir())]
    assert len(frames["transforms"]) == len(poses)
    assert frames["inria"] == frames["transforms"] and frames["colmap"] == frames["transforms"]


def test_inria_cameras_json_is_read_in_image_name_order(poses, tmp_path):
    """Inria's train.py lists the test cameras first (every 8th view, here every 4th): read in the
    dataset's order (natural order of img_name), the path is smooth; labels keep the file position."""
    names = [f"view_{i}" for i in range(6)]
    order = [0, 4, 1, 2, 3, 5]
    cams = [_inria_entry(j, names[i], poses[i], 33.0, 34.0) for j, i in enumerate(order)]
    (tmp_path / "cameras.json").write_text(json.dumps(cams))
    path = read_camera_path(tmp_path / "cameras.json")
    assert (path.world_from_cam - poses).abs().max() < 1e-9
    assert path.names == names
    assert path.label(1) == "cameras[2] (view_1)" and path.label(4) == "cameras[1] (view_4)"
