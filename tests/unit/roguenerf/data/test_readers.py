"""Readers: each format round-trips a toy scene; lego loads; every bad file is named."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from roguenerf.data.readers import load_scene
from roguenerf.data.toy import make_toy_world, render_toy_view, toy_camera_path, toy_intrinsics
from roguenerf.data.writers import write_scene_folder
from roguenerf.errors import InputError, SceneFormatError
from roguenerf.geometry.cameras import opencv_to_opengl

H, W, M = 24, 32, 5
EIGHT_BIT = 0.5 / 255 + 1e-6


@pytest.fixture(scope="module")
def toy_views():
    world = make_toy_world(3)
    poses = toy_camera_path(world, M, seed=3)
    K = toy_intrinsics(H, W)
    photos, depths = zip(*(render_toy_view(world, p, K, H, W) for p in poses))
    photos = torch.stack(photos).float().clamp(0, 1)
    depths = torch.stack(depths).float()
    renders = (photos * 0.9 + 0.05).clamp(0, 1)
    return {"photos": photos, "renders": renders, "depths": depths, "poses": poses, "K": K}


def _write_folder(root, toy_views, **over):
    kwargs = dict(
        names=[f"v{i}" for i in range(M)],
        photos=toy_views["photos"],
        renders=toy_views["renders"],
        depths=toy_views["depths"],
        world_from_cam=toy_views["poses"],
        K=toy_views["K"],
        splits=["train", "train", "test", "train", "test"],
    )
    kwargs.update(over)
    return write_scene_folder(root, **kwargs)


def _u8(image: torch.Tensor) -> np.ndarray:
    return np.round(image.clamp(0, 1).numpy() * 255).astype(np.uint8).transpose(1, 2, 0)


# -- scene folder -------------------------------------------------------------------------


def test_scene_folder_round_trip(tmp_path, toy_views):
    root = _write_folder(tmp_path / "s", toy_views)
    scene = load_scene(root)
    assert scene.meta["format"] == "scene-folder"
    assert [f.name for f in scene.frames] == [f"v{i}" for i in range(M)]
    assert scene.indices("train") == [0, 1, 3] and scene.indices("test") == [2, 4]
    assert torch.allclose(scene.poses(), toy_views["poses"], atol=1e-12)
    assert torch.allclose(scene.intrinsics(), toy_views["K"].expand(M, 3, 3), atol=1e-12)
    for i in range(M):
        assert (scene.photo(i) - toy_views["photos"][i]).abs().max() <= EIGHT_BIT
        assert (scene.render(i) - toy_views["renders"][i]).abs().max() <= EIGHT_BIT
        assert torch.equal(scene.depth(i), toy_views["depths"][i])
    assert scene.has_renders and scene.has_depths


def test_scene_folder_per_frame_intrinsics_round_trip(tmp_path, toy_views):
    K = toy_views["K"].expand(M, 3, 3).clone()
    K[:, 0, 0] += torch.arange(M, dtype=K.dtype)
    scene = load_scene(_write_folder(tmp_path / "s", toy_views, K=K))
    assert torch.equal(scene.intrinsics(), K)


def test_transforms_json_path_accepted(tmp_path, toy_views):
    root = _write_folder(tmp_path / "s", toy_views)
    assert len(load_scene(root / "transforms.json")) == M


def test_lego_loads_lazily_with_opencv_poses(lego_dir):
    scene = load_scene(lego_dir)
    assert len(scene._cache) == 0, "loading a scene must not decode any pixels"
    assert len(scene.indices("train")) == 100 and len(scene.indices("test")) == 25
    assert scene.frames[0].name == "train_r_0" and (scene.frames[0].width, scene.frames[0].height) == (200, 200)
    gl = torch.tensor(json.loads((lego_dir / "transforms.json").read_text())["frames"][0]["transform_matrix"],
                      dtype=torch.float64)
    expected = gl * torch.tensor([1.0, -1.0, -1.0, 1.0], dtype=torch.float64)
    assert torch.allclose(scene.poses()[0], expected, atol=1e-6)
    # OpenCV: the camera's +z (third column) is the Blender camera's viewing direction -z
    assert torch.allclose(scene.poses()[0][:3, 2], -gl[:3, 2], atol=1e-6)
    K = scene.intrinsics()[0]
    assert K[0, 2] == 100.0 and K[0, 0] == pytest.approx(277.77775779844205)


# -- nerfstudio ---------------------------------------------------------------------------


def _write_nerfstudio(root: Path, toy_views, *, depth: str = "png", extra: dict | None = None, frame_extra=None):
    root.mkdir(parents=True)
    (root / "images").mkdir()
    (root / "depth").mkdir()
    K = toy_views["K"]
    frames = []
    for i in range(M):
        Image.fromarray(_u8(toy_views["photos"][i])).save(root / f"images/frame_{i:05d}.png")
        frame = {
            "file_path": f"images/frame_{i:05d}.png",
            "transform_matrix": opencv_to_opengl(toy_views["poses"][i]).tolist(),
        }
        if depth == "png":
            mm = np.round(toy_views["depths"][i, 0].numpy() * 1000).astype(np.uint16)
            Image.fromarray(mm).save(root / f"depth/frame_{i:05d}.png")
            frame["depth_file_path"] = f"depth/frame_{i:05d}.png"
        elif depth == "npy":
            np.save(root / f"depth/frame_{i:05d}.npy", toy_views["depths"][i, 0].numpy())
            frame["depth_file_path"] = f"depth/frame_{i:05d}.npy"
        frame.update((frame_extra or {}).get(i, {}))
        frames.append(frame)
    data = {"camera_model": "OPENCV", "fl_x": float(K[0, 0]), "fl_y": float(K[1, 1]), "cx": float(K[0, 2]),
            "cy": float(K[1, 2]), "w": W, "h": H, "frames": frames}
    data.update(extra or {})
    (root / "transforms.json").write_text(json.dumps(data))
    return root


def test_nerfstudio_mm_png_depth_round_trip(tmp_path, toy_views):
    scene = load_scene(_write_nerfstudio(tmp_path / "ns", toy_views))
    assert scene.meta["format"] == "nerfstudio"
    assert not scene.has_renders and scene.has_depths
    assert scene.indices("train") == list(range(M))  # no split information: all train
    assert torch.allclose(scene.poses(), toy_views["poses"], atol=1e-12)
    for i in range(M):
        assert (scene.depth(i) - toy_views["depths"][i]).abs().max() <= 0.0005 + 1e-6
        assert (scene.photo(i) - toy_views["photos"][i]).abs().max() <= EIGHT_BIT
    with pytest.raises(InputError, match="has no radiance-field render"):
        scene.render(0)


def test_nerfstudio_npy_depth_with_unit_scale(tmp_path, toy_views):
    # nerfstudio multiplies .npy depth by depth_unit_scale_factor too
    root = _write_nerfstudio(tmp_path / "ns", toy_views, depth="npy", extra={"depth_unit_scale_factor": 1.0})
    scene = load_scene(root)
    assert torch.allclose(scene.depth(1), toy_views["depths"][1])
    data = json.loads((root / "transforms.json").read_text())
    del data["depth_unit_scale_factor"]
    (root / "transforms.json").write_text(json.dumps(data))
    assert torch.allclose(load_scene(root).depth(1), toy_views["depths"][1] * 1e-3)


def test_ray_depth_converted_to_z_by_hand(tmp_path, toy_views):
    root = _write_nerfstudio(tmp_path / "ns", toy_views, depth=None, extra={"depth_unit_scale_factor": 1.0})
    data = json.loads((root / "transforms.json").read_text())
    # principal point on the centre of pixel (row 2, col 3)
    data.update({"fl_x": 20.0, "fl_y": 25.0, "cx": 3.5, "cy": 2.5})
    for i, frame in enumerate(data["frames"]):
        np.save(root / f"depth/frame_{i:05d}.npy", np.full((H, W), 5.0, dtype=np.float32))
        frame["depth_file_path"] = f"depth/frame_{i:05d}.npy"
    (root / "transforms.json").write_text(json.dumps(data))
    z_scene = load_scene(root)
    ray_scene = load_scene(root, depth_type="ray")
    assert torch.equal(z_scene.depth(0), torch.full((1, H, W), 5.0))
    depth = ray_scene.depth(0)[0]
    assert depth[2, 3].item() == pytest.approx(5.0, abs=1e-6)
    x, y = (0.5 - 3.5) / 20.0, (0.5 - 2.5) / 25.0
    assert depth[0, 0].item() == pytest.approx(5.0 / math.sqrt(1 + x * x + y * y), rel=1e-6)
    x, y = (W - 0.5 - 3.5) / 20.0, (H - 0.5 - 2.5) / 25.0
    assert depth[-1, -1].item() == pytest.approx(5.0 / math.sqrt(1 + x * x + y * y), rel=1e-6)
    # the JSON key does the same as the argument
    data["depth_type"] = "ray"
    (root / "transforms.json").write_text(json.dumps(data))
    assert torch.equal(load_scene(root).depth(0), ray_scene.depth(0))


def test_nerfstudio_splits_from_lists_file_and_key(tmp_path, toy_views):
    root = _write_nerfstudio(
        tmp_path / "a", toy_views,
        extra={"train_filenames": [f"images/frame_{i:05d}.png" for i in (0, 1, 2)],
               "val_filenames": ["images/frame_00003.png"], "test_filenames": ["images/frame_00004.png"]},
    )
    assert load_scene(root).indices("test") == [3, 4]
    root = _write_nerfstudio(tmp_path / "b", toy_views)
    (root / "splits.json").write_text(json.dumps({"train": ["frame_00000", "frame_00002"], "test": ["frame_00001"],
                                                  "val": ["frame_00003", "frame_00004"]}))
    assert load_scene(root).indices("test") == [1, 3, 4]
    root = _write_nerfstudio(tmp_path / "c", toy_views, frame_extra={1: {"split": "test"}, 2: {"split": "val"}})
    assert load_scene(root).indices("test") == [1, 2]


def test_per_frame_intrinsics_override_top_level(tmp_path, toy_views):
    root = _write_nerfstudio(tmp_path / "ns", toy_views, frame_extra={2: {"fl_x": 99.0, "cx": 10.0}})
    K = load_scene(root).intrinsics()
    assert K[2, 0, 0] == 99.0 and K[2, 0, 2] == 10.0 and K[2, 1, 1] == toy_views["K"][1, 1]
    assert torch.equal(K[0], toy_views["K"])


def test_missing_w_h_read_from_image_header(tmp_path, toy_views):
    root = _write_nerfstudio(tmp_path / "ns", toy_views)
    data = json.loads((root / "transforms.json").read_text())
    del data["w"], data["h"]
    (root / "transforms.json").write_text(json.dumps(data))
    frame = load_scene(root).frames[0]
    assert (frame.width, frame.height) == (W, H)


# -- LLFF ---------------------------------------------------------------------------------


def _write_llff(root: Path, toy_views, factor: int = 2):
    """LLFF data at full size 2H x 2W (focal doubled) with images_<factor>/ at H x W."""
    folder = root / f"images_{factor}"
    folder.mkdir(parents=True)
    (root / "images").mkdir()
    rows = []
    for i in range(M):
        Image.fromarray(_u8(toy_views["photos"][i])).save(folder / f"IMG_{i:04d}.png")
        photo = Image.fromarray(_u8(toy_views["photos"][i]))
        photo.resize((W * factor, H * factor)).save(root / f"images/IMG_{i:04d}.png")
        c2w = toy_views["poses"][i].numpy()
        # OpenCV columns (right, down, forward) -> LLFF (down, right, back)
        block = np.stack([c2w[:3, 1], c2w[:3, 0], -c2w[:3, 2], c2w[:3, 3]], axis=1)
        hwf = np.array([[H * factor], [W * factor], [float(toy_views["K"][0, 0]) * factor]])
        rows.append(np.concatenate([np.concatenate([block, hwf], axis=1).ravel(), [1.0, 20.0]]))
    np.save(root / "poses_bounds.npy", np.stack(rows))
    return root


def test_llff_round_trip(tmp_path, toy_views):
    root = _write_llff(tmp_path / "llff", toy_views)
    scene = load_scene(root, llff_factor=2, llff_hold=2)
    assert scene.meta["format"] == "llff" and not scene.has_renders and not scene.has_depths
    assert torch.allclose(scene.poses(), toy_views["poses"], atol=1e-12)
    assert torch.allclose(scene.intrinsics(), toy_views["K"].expand(M, 3, 3), atol=1e-12)
    assert scene.indices("test") == [0, 2, 4]
    assert (scene.photo(3) - toy_views["photos"][3]).abs().max() <= EIGHT_BIT
    assert scene.meta["bounds"].shape == (M, 2)
    with pytest.raises(InputError, match="no depth map"):
        scene.depth(0)
    full = load_scene(root / "poses_bounds.npy")
    assert (full.frames[0].width, full.frames[0].height) == (2 * W, 2 * H)
    assert torch.allclose(full.intrinsics()[0], toy_views["K"] * torch.tensor([[2, 2, 2], [2, 2, 2], [1, 1, 1.0]]))
    assert full.indices("test") == [0]  # llff_hold=8


# -- bad files ----------------------------------------------------------------------------


def _edit_json(root: Path, edit) -> Path:
    path = root / "transforms.json"
    data = json.loads(path.read_text())
    edit(data)
    path.write_text(json.dumps(data))
    return path


def _expect(path, match, root, **kw):
    with pytest.raises(SceneFormatError, match=match) as info:
        load_scene(root, **kw)
    assert info.value.path == str(path)
    assert str(path) in str(info.value)


@pytest.mark.parametrize(
    ("edit", "match"),
    [
        (lambda d: d.pop("frames"), "missing key 'frames'"),
        (lambda d: d["frames"][1].pop("transform_matrix"), r"frames\[1\]: missing key 'transform_matrix'"),
        (lambda d: d["frames"][1].pop("file_path"), r"frames\[1\]: missing key 'file_path'"),
        (lambda d: d.pop("fl_x"), "missing key 'fl_x'"),
        (lambda d: d.update(fl_x=-3.0), "fx > 0"),
        (lambda d: d["frames"][2].update(transform_matrix=[[1, 0, 0], [0, 1, 0], [0, 0, 1]]),
         r"expected shape \(4, 4\), got \(3, 3\)"),
        (lambda d: d["frames"][0]["transform_matrix"][0].__setitem__(3, float("nan")), "NaN or inf"),
        (lambda d: d["frames"][0]["transform_matrix"][0].__setitem__(0, 3.0), "orthonormal"),
        (lambda d: d["frames"][0].update(split="banana"), "expected 'train' or 'test'"),
        (lambda d: d["frames"][3].update(file_path="images/v0.png"), "same name 'v0'"),
        (lambda d: d.update(camera_model="OPENCV_FISHEYE"), "not supported"),
        (lambda d: d.update(w=W + 1), r"the scene says 33x24"),
    ],
)
def test_bad_transforms_json_named(tmp_path, toy_views, edit, match):
    root = _write_folder(tmp_path / "s", toy_views)
    path = _edit_json(root, edit)
    # the size mismatch is reported against the image file, everything else against the JSON
    if "scene says" in match:
        path = root / "images" / "v0.png"
    _expect(path, match, root)


def test_invalid_json_named(tmp_path, toy_views):
    root = _write_folder(tmp_path / "s", toy_views)
    (root / "transforms.json").write_text("{ not json")
    _expect(root / "transforms.json", "invalid JSON", root)


def test_missing_and_corrupt_files_named(tmp_path, toy_views):
    root = _write_folder(tmp_path / "s", toy_views)
    (root / "renders" / "v2.png").unlink()
    _expect(root / "renders" / "v2.png", "missing file", root)
    root = _write_folder(tmp_path / "t", toy_views)
    (root / "images" / "v1.png").write_bytes(b"GIF89a....")
    _expect(root / "images" / "v1.png", "not a PNG or JPEG", root)


def test_depth_shape_mismatch_named(tmp_path, toy_views):
    root = _write_folder(tmp_path / "s", toy_views)
    np.save(root / "depths" / "v3.npy", np.ones((H, W + 2), dtype=np.float32))
    _expect(root / "depths" / "v3.npy", "depth is 34x24 \\(WxH\\), the scene says 32x24", root)
    np.save(root / "depths" / "v3.npy", np.ones((H, W), dtype=np.complex64))
    _expect(root / "depths" / "v3.npy", "real float or integer", root)


def test_size_mismatch_caught_on_load_when_headers_not_checked(tmp_path, toy_views):
    root = _write_folder(tmp_path / "s", toy_views)
    Image.new("RGB", (W, H + 1)).save(root / "images" / "v4.png")
    scene = load_scene(root, check_files=False)
    with pytest.raises(SceneFormatError, match="image is 32x25 \\(WxH\\), the scene says 32x24") as info:
        scene.photo(4)
    assert info.value.path == str(root / "images" / "v4.png")


def test_not_a_scene_and_missing_path(tmp_path):
    _expect(tmp_path, "not a scene", tmp_path)
    _expect(tmp_path / "nowhere", "no such file", tmp_path / "nowhere")


def test_bad_llff_named(tmp_path, toy_views):
    root = _write_llff(tmp_path / "a", toy_views)
    pb = root / "poses_bounds.npy"
    good = np.load(pb)
    np.save(pb, good[:, :15])
    _expect(pb, r"\(N, 17\) array", root)
    bad = good.copy()
    bad[2, 3] = np.inf
    np.save(pb, bad)
    _expect(pb, "row 2 .* NaN or inf", root)
    bad = good.copy()
    bad[1, 15:] = [5.0, 1.0]
    np.save(pb, bad)
    _expect(pb, "view 1: bounds", root)
    np.save(pb, good)
    (root / "images" / "IMG_0000.png").unlink()
    _expect(root / "images", "holds 4 images, poses_bounds.npy has 5", root)
    shutil.rmtree(root / "images_2")
    _expect(root / "images_2", "missing image folder", root, llff_factor=2)
    pb.write_bytes(b"\x80\x04not a npy")
    _expect(pb, "not a valid .npy", root)
