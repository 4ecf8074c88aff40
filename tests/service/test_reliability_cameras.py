"""Depth, poses and intrinsics at /enhance.

Depth ``.npy`` is never unpickled; wrong dtype / shape -> 422; NaN, inf, zero and negative
depth mean "unknown" (fine in part, 422 when nearly all of it); bad poses and intrinsics ->
422; a view no neighbour sees -> the render enhanced without neighbours plus a header; a
non-finite model output is never encoded (500 with the reason, logged).
"""

from __future__ import annotations

import io
import json
import logging

import numpy as np
import pytest
import torch

from tests.reliability_helpers import (
    assert_error,
    assert_healthy,
    npy,
    pickled_npy,
    post_enhance,
    read_png,
)


def _opencv_camera(s, index: int = 6, pose=None) -> dict:
    frame = s.scene.frames[index]
    K = frame.K
    pose = frame.world_from_cam.to(torch.float64) if pose is None else pose
    return {"transform_matrix": pose.tolist(), "convention": "opencv", "fl_x": float(K[0, 0]),
            "fl_y": float(K[1, 1]), "cx": float(K[0, 2]), "cy": float(K[1, 2]), "depth_type": "z"}


def _send(s, *, depth=None, camera=None, render=None, **extra):
    view = s.view()
    return post_enhance(s.client, s.scene_id, render=view["render"] if render is None else render,
                        depth=view["depth"] if depth is None else depth,
                        camera=_opencv_camera(s) if camera is None else camera, **extra)


@pytest.fixture(scope="module")
def depth(s) -> np.ndarray:
    """The view's true z-depth (48, 64) float32."""
    return np.load(io.BytesIO(s.view()["depth"]), allow_pickle=False).reshape(48, 64)


# ----------------------------------------------------------------------------- depth
def test_pickled_depth_is_refused_and_never_unpickled(s, tmp_path):
    marker = tmp_path / "unpickled-marker"
    payload = pickled_npy(marker)
    # The payload is live: numpy with allow_pickle=True would create the marker.
    before = s.stored()
    message = assert_error(_send(s, depth=payload), 422, "invalid_input")
    assert message.startswith("depth:") and ("object" in message.lower() or "pickle" in message.lower())
    assert not marker.exists()
    assert s.stored() == before
    np.load(io.BytesIO(payload), allow_pickle=True)
    assert marker.exists()


@pytest.mark.parametrize("name, array", [
    ("complex", np.ones((48, 64), np.complex64)),
    ("string", np.full((48, 64), "1", dtype="<U1")),
    ("structured", np.zeros((48, 64), dtype=[("z", "<f4"), ("w", "<f4")])),
    ("3d", np.ones((2, 48, 64), np.float32)),
    ("flat", np.ones((48 * 64,), np.float32)),
    ("4d", np.ones((1, 1, 48, 64), np.float32)),
    ("hwc2", np.ones((48, 64, 2), np.float32)),
    ("scalar", np.float32(1.0)),
])
def test_wrong_depth_dtype_or_shape_is_422(s, name, array):
    before = s.stored()
    message = assert_error(_send(s, depth=npy(np.asarray(array))), 422)
    assert message.startswith("depth"), message
    assert s.stored() == before


def test_depth_with_a_trailing_channel_is_read_as_nerfstudio_writes_it(s):
    """(H, W, 1), the shape of nerfstudio's raw-depth, is the same depth as (H, W)."""
    plain = np.load(io.BytesIO(s.view()["depth"]))
    assert plain.ndim == 2
    a, b = _send(s, depth=npy(plain)), _send(s, depth=npy(plain[..., None]))
    assert a.status_code == 200 and b.status_code == 200, (a.text, b.text)
    assert a.content == b.content


def test_depth_not_npy_or_png_is_422(s):
    assert_error(_send(s, depth=b"\x93NUMPY garbage"), 422)
    assert_error(_send(s, depth=b""), 422)


def test_nan_inf_zero_negative_depth_is_missing_not_fatal(s, depth):
    holes = depth.copy()
    rng = np.random.default_rng(0)
    idx = rng.permutation(holes.size)[: holes.size * 2 // 5].reshape(4, -1)
    flat = holes.reshape(-1)
    flat[idx[0]], flat[idx[1]], flat[idx[2]], flat[idx[3]] = np.nan, np.inf, 0.0, -3.0
    r = _send(s, depth=npy(holes))
    assert r.status_code == 200, r.text
    assert read_png(r.content).shape == (48, 64, 3)
    # The unknown pixels are treated exactly like zeros: same answer as all-zero holes.
    zeros = depth.copy().reshape(-1)
    zeros[idx.reshape(-1)] = 0.0
    same = _send(s, depth=npy(zeros.reshape(48, 64)))
    assert np.array_equal(read_png(r.content), read_png(same.content))


@pytest.mark.parametrize("fill", [np.nan, 0.0, -1.0, np.inf])
def test_nearly_all_missing_depth_is_422(s, depth, fill):
    before = s.stored()
    sparse = np.full_like(depth, fill)
    sparse[0, :10] = depth[0, :10]  # 10 of 3072 pixels (0.3 %) known
    message = assert_error(_send(s, depth=npy(sparse)), 422, "invalid_input")
    assert "10 of 3072" in message and "at least 1%" in message
    assert s.stored() == before


# ----------------------------------------------------------------------------- poses
def _with_pose(s, pose) -> dict:
    return {**_opencv_camera(s), "transform_matrix": pose}


@pytest.mark.parametrize("case, needle", [
    ("2x4", "4x4 or 3x4"), ("4x3", "4x4"), ("nan", "NaN"), ("inf", "NaN"), ("last_row", "last row"),
    ("reflection", "det"), ("scaled", "orthonormal"), ("sheared", "orthonormal"),
])
def test_bad_poses_are_422(s, case, needle):
    pose = s.scene.frames[6].world_from_cam.to(torch.float64).clone()
    if case == "2x4":  # 3x4 is accepted (tests/service/test_service_api.py); fewer rows are not
        value = pose[:2].tolist()
    elif case == "4x3":
        value = pose[:, :3].tolist()
    elif case in ("nan", "inf"):
        pose[1, 3] = float(case)
        value = pose.tolist()
    elif case == "last_row":
        pose[3] = torch.tensor([0.0, 0.0, 0.1, 1.0])
        value = pose.tolist()
    elif case == "reflection":
        pose[:3, 0] *= -1
        value = pose.tolist()
    elif case == "scaled":
        pose[:3, :3] *= 1.5
        value = pose.tolist()
    else:
        pose[0, 1] += 0.2
        value = pose.tolist()
    before = s.stored()
    camera = json.dumps(_with_pose(s, value))  # NaN/inf go out as the JSON extensions NaN/Infinity
    r = post_enhance(s.client, s.scene_id, render=s.view()["render"], depth=s.view()["depth"], camera=camera)
    message = assert_error(r, 422)
    assert needle.lower() in message.lower(), message
    assert s.stored() == before


def test_pose_rounding_noise_is_accepted(s):
    pose = s.scene.frames[6].world_from_cam.to(torch.float64).clone()
    pose[:3, :3] += 1e-6 * torch.randn(3, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    r = _send(s, camera=_with_pose(s, pose.tolist()))
    assert r.status_code == 200, r.text


@pytest.mark.parametrize("field, value", [
    ("fl_x", 0.0), ("fl_x", -50.0), ("fl_y", 0.0), ("fl_y", -1e-3), ("fl_x", "inf"), ("fl_y", "nan"),
    ("cx", "nan"), ("cy", "-inf"),
])
def test_bad_intrinsics_are_422(s, field, value):
    camera = _opencv_camera(s)
    camera[field] = float(value)
    before = s.stored()
    r = post_enhance(s.client, s.scene_id, render=s.view()["render"], depth=s.view()["depth"],
                     camera=json.dumps(camera))
    message = assert_error(r, 422)
    assert "camera" in message or field in message, message
    assert s.stored() == before


# ----------------------------------------------------------------------------- no neighbours
def test_view_no_neighbour_sees_is_the_render_enhanced_alone(s, tmp_path):
    from roguenerf import SceneEnhancer, load_checkpoint
    from roguenerf.imageio import read_depth, read_image, write_png

    frame = s.scene.frames[6]
    # Turned 180 degrees about its y axis: every reprojected point lies behind the neighbours.
    turned = frame.world_from_cam.to(torch.float64) @ torch.diag(torch.tensor([-1.0, 1.0, -1.0, 1.0],
                                                                               dtype=torch.float64))
    # A camera no training photo sees is taken for a wrong pose first (issue 49: refused, with
    # the way to go on); forced, it is enhanced without neighbours, and the note says both.
    refused = _send(s, camera=_opencv_camera(s, pose=turned))
    assert refused.status_code == 422 and refused.json()["error"]["code"] == "wrong_world", refused.text
    assert "to enhance it anyway: force=true" in refused.json()["error"]["message"]
    r = _send(s, camera=_opencv_camera(s, pose=turned), force="true")
    assert r.status_code == 200, r.text
    assert r.headers["X-Enhance-Note"].startswith("forced: the camera does not fit the scene")
    assert r.headers["X-Enhance-Note"].endswith("; no neighbour sees this view: enhanced without neighbours")
    assert r.headers["X-Neighbours"] == ""
    # Known answer: the library with the same checkpoint and no neighbours at all.
    (tmp_path / "c.safetensors").write_bytes(s.checkpoint)
    model, _ = load_checkpoint(tmp_path / "c.safetensors")
    alone = SceneEnhancer(s.scene, model, num_neighbours=0)
    render = read_image(s.view()["render"])
    expected = alone.enhance(render, read_depth(s.view()["depth"]), frame.K, turned)
    assert expected.neighbours == []
    got = read_png(r.content)
    assert np.array_equal(got, read_png(write_png(None, expected.image)))
    # Not mirrored: the answer is near the render, far from its left-right mirror.
    ref = (render.permute(1, 2, 0).numpy() * 255).round()
    assert np.abs(got - ref).mean() < np.abs(got - ref[:, ::-1]).mean() / 2


# ----------------------------------------------------------------------------- model output
def test_non_finite_model_output_is_500_logged_never_encoded(s, tmp_path, caplog):
    from roguenerf import build_enhancer, save_checkpoint

    torch.manual_seed(0)
    model = build_enhancer("micro", num_neighbours=2)
    with torch.no_grad():
        for p in model.parameters():
            p.mul_(1e30)  # finite weights (loadable) whose products overflow to inf / NaN
    broken = save_checkpoint(tmp_path / "broken.safetensors", model).read_bytes()
    r = s.client.post("/scenes", files={"archive": ("a.zip", s.zip), "checkpoint": ("c", broken)})
    assert r.status_code == 201, r.text
    sid = r.json()["id"]
    view = s.view()
    with caplog.at_level(logging.ERROR, logger="roguenerf.service"):
        r = post_enhance(s.client, sid, render=view["render"], depth=view["depth"], camera=view["camera"])
    message = assert_error(r, 500, "enhance_failed")
    assert "non-finite" in message
    assert r.headers["content-type"].startswith("application/json")
    assert any("non-finite" in rec.getMessage() for rec in caplog.records)
    assert_healthy(s.client)
    assert s.client.delete(f"/scenes/{sid}").status_code == 204
