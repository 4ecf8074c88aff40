"""Camera conventions, validation and Euler angles: known answers and clear errors."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from roguenerf.errors import InputError
from roguenerf.geometry import (
    check_intrinsics,
    check_pose,
    euler_angles,
    intrinsics_matrix,
    llff_to_opencv,
    opencv_to_opengl,
    opengl_to_opencv,
    ray_to_z_depth,
    scale_intrinsics,
    wrap_angle,
)
from roguenerf.geometry.cameras import ORTHONORMAL_TOL
from roguenerf.geometry.euler import angular_distance, euler_distance
from tests.geometry_helpers import zyx


def test_lego_backprojection_matches_readme(lego_dir):
    """Our conventions (OpenGL->OpenCV, pixel centres at +0.5, z-depth) reproduce the README formula."""
    meta = json.loads((lego_dir / "transforms.json").read_text())
    frame = meta["frames"][0]
    depth = np.load(lego_dir / frame["depth_path"], allow_pickle=False)
    gl = np.asarray(frame["transform_matrix"], dtype=np.float64)
    fx, fy, cx, cy = (meta.get(k, frame.get(k)) for k in ("fl_x", "fl_y", "cx", "cy"))
    H, W = depth.shape
    v, u = np.mgrid[0:H, 0:W]
    z = depth.astype(np.float64)
    readme_cam = np.stack([(u + 0.5 - cx) / fx * z, -(v + 0.5 - cy) / fy * z, -z, np.ones_like(z)], -1)
    readme_world = readme_cam @ gl.T

    K = intrinsics_matrix(fx, fy, cx, cy, dtype=torch.float64)
    pose = opengl_to_opencv(torch.from_numpy(gl))
    pix = torch.stack([torch.from_numpy(u + 0.5), torch.from_numpy(v + 0.5), torch.ones(H, W, dtype=torch.float64)], -1)
    cam = (pix @ torch.linalg.inv(K).T) * torch.from_numpy(z)[..., None]
    ours = cam @ pose[:3, :3].T + pose[:3, 3]
    assert np.abs(ours.numpy() - readme_world[..., :3]).max() < 1e-9
    # and the projection of those points lands back on the pixel centres
    cam_from_world = torch.linalg.inv(pose)  # Blender's stored rotations are orthonormal only to ~1e-7
    back = ours @ cam_from_world[:3, :3].T + cam_from_world[:3, 3]
    uvw = back @ K.T
    uv = uvw[..., :2] / uvw[..., 2:]
    assert torch.allclose(uv[..., 0], pix[..., 0], atol=1e-9)
    assert torch.allclose(uv[..., 1], pix[..., 1], atol=1e-9)


def test_opengl_opencv_round_trip_and_axes():
    gl = torch.eye(4, dtype=torch.float64)
    gl[:3, :3] = zyx(0.3, -0.2, 1.1)
    gl[:3, 3] = torch.tensor([1.0, 2.0, 3.0])
    cv = opengl_to_opencv(gl)
    # the OpenCV viewing axis (+z) is the OpenGL -z axis, the image "down" (+y) is OpenGL -y
    assert torch.allclose(cv[:3, 2], -gl[:3, 2])
    assert torch.allclose(cv[:3, 1], -gl[:3, 1])
    assert torch.allclose(cv[:3, 0], gl[:3, 0])
    assert torch.equal(cv[:3, 3], gl[:3, 3])
    assert torch.equal(opencv_to_opengl(cv), gl)
    assert opengl_to_opencv(gl[:3]).shape == (3, 4)


def test_llff_columns_down_right_back():
    R_cv = zyx(0.1, 0.5, -0.7)
    t = torch.tensor([0.5, -1.0, 2.0], dtype=torch.float64)
    right, down, forward = R_cv.unbind(-1)
    llff = torch.stack([down, right, -forward, t], -1)[None]
    out = llff_to_opencv(llff)
    assert out.shape == (1, 4, 4)
    assert torch.allclose(out[0, :3, :3], R_cv)
    assert torch.equal(out[0, :3, 3], t)
    assert torch.equal(out[0, 3], torch.tensor([0, 0, 0, 1.0], dtype=torch.float64))


def test_intrinsics_and_scaling_pixel_centre():
    K = intrinsics_matrix(100.0, 90.0, 32.0, 24.0)
    assert K.shape == (3, 3) and K.dtype == torch.float32
    # halving a 64x48 image: the centre (32, 24) maps to (16, 12); pixel-centre convention has no 0.5 shift
    K2 = scale_intrinsics(K, 0.5, 0.5)
    assert torch.allclose(K2, torch.tensor([[50.0, 0, 16.0], [0, 45.0, 12.0], [0, 0, 1]]))
    batched = intrinsics_matrix(torch.tensor([1.0, 2.0]), 3.0, 4.0, 5.0)
    assert batched.shape == (2, 3, 3)


@pytest.mark.parametrize("fx", [0.0, -5.0, float("nan"), float("inf")])
def test_intrinsics_reject_bad_focal(fx):
    with pytest.raises(InputError, match="K"):
        intrinsics_matrix(fx, 10.0, 1.0, 1.0)


def test_check_intrinsics_errors_name_argument():
    with pytest.raises(InputError, match="src_K.*fx > 0"):
        check_intrinsics(torch.tensor([[-1.0, 0, 0], [0, 1, 0], [0, 0, 1]]), "src_K")
    with pytest.raises(InputError, match="last row"):
        check_intrinsics(torch.tensor([[1.0, 0, 0], [0, 1, 0], [0, 1, 1]]))
    with pytest.raises(InputError, match=r"\(\.\.\., 3, 3\)"):
        check_intrinsics(torch.eye(4))
    with pytest.raises(InputError, match="floating"):
        check_intrinsics(torch.eye(3, dtype=torch.int64))


def test_check_pose_reorthonormalises_within_tolerance():
    pose = torch.eye(4, dtype=torch.float64)
    pose[:3, :3] = zyx(0.2, 0.3, 0.4)
    noisy = pose.clone()
    noisy[:3, :3] += 2e-4 * torch.tensor([[1.0, -1, 0.5], [0.3, 0.2, -1], [0, 1, 1]], dtype=torch.float64)
    err_before = (noisy[:3, :3].T @ noisy[:3, :3] - torch.eye(3, dtype=torch.float64)).abs().max()
    assert 1e-5 < err_before < ORTHONORMAL_TOL
    fixed = check_pose(noisy)
    R = fixed[:3, :3]
    assert torch.allclose(R.T @ R, torch.eye(3, dtype=torch.float64), atol=1e-12)
    assert (R - pose[:3, :3]).abs().max() < 1e-3
    assert torch.equal(check_pose(pose), pose)  # exact rotations stay untouched


def test_check_pose_rejects_beyond_tolerance_and_reflections():
    bad = torch.eye(4)
    bad[0, 0] = 1.1
    with pytest.raises(InputError, match="world_from_src: expected an orthonormal rotation"):
        check_pose(bad, "world_from_src")
    reflect = torch.diag(torch.tensor([1.0, 1.0, -1.0, 1.0]))
    with pytest.raises(InputError, match="det"):
        check_pose(reflect)
    nan = torch.eye(4)
    nan[0, 3] = float("nan")
    with pytest.raises(InputError, match="non-finite"):
        check_pose(nan)
    last = torch.eye(4)
    last[3, 0] = 1.0
    with pytest.raises(InputError, match="last row"):
        check_pose(last)


def test_ray_to_z_depth_known_answer():
    K = intrinsics_matrix(2.0, 2.0, 1.0, 1.0, dtype=torch.float64)
    ray = torch.full((2, 2), 3.0, dtype=torch.float64)
    z = ray_to_z_depth(ray, K)
    # every pixel centre of a 2x2 image is (+-0.5, +-0.5) from the principal point: x = y = 0.25
    assert torch.allclose(z, torch.full((2, 2), 3.0 / math.sqrt(1 + 2 * 0.25**2), dtype=torch.float64))
    weird = torch.tensor([[0.0, -1.0], [float("nan"), float("inf")]])
    assert torch.equal(ray_to_z_depth(weird, K.float()), torch.zeros(2, 2))


def test_wrap_angle():
    a = torch.tensor([0.0, math.pi, -math.pi, 3 * math.pi / 2, -3 * math.pi / 2, 7.0], dtype=torch.float64)
    w = wrap_angle(a)
    assert (w >= -math.pi).all() and (w <= math.pi).all()
    assert torch.allclose(torch.cos(w), torch.cos(a)) and torch.allclose(torch.sin(w), torch.sin(a), atol=1e-12)
    assert torch.allclose(w[3], torch.tensor(-math.pi / 2, dtype=torch.float64))


@pytest.mark.parametrize("angles", [(0.1, 0.2, 0.3), (-2.5, 1.2, 3.0), (3.0, -1.5, -3.1), (0.0, 0.0, math.pi)])
def test_euler_round_trip(angles):
    R = zyx(*angles)
    e = euler_angles(R)
    assert torch.allclose(zyx(*e.tolist()), R, atol=1e-9)
    diff = wrap_angle(e - torch.tensor(angles, dtype=torch.float64))
    assert torch.allclose(diff, torch.zeros(3, dtype=torch.float64), atol=1e-9)


@pytest.mark.parametrize("pitch", [math.pi / 2, -math.pi / 2])
def test_euler_gimbal_lock_convention(pitch):
    R = zyx(0.4, pitch, 1.0)
    e = euler_angles(R)
    assert torch.isfinite(e).all()
    assert e[0] == 0.0  # roll is set to 0 at gimbal lock
    assert torch.allclose(e[1], torch.tensor(pitch, dtype=torch.float64))
    assert torch.allclose(zyx(*e.tolist()), R, atol=1e-9)  # still the same rotation


@pytest.mark.parametrize("pitch", [math.pi / 2, -math.pi / 2])
def test_angular_distance_sensible_at_gimbal_lock(pitch):
    locked = zyx(0.4, pitch, 1.0)
    nearby = zyx(0.4 + 0.01, pitch - math.copysign(1e-3, pitch), 1.0 - 0.01)  # a slightly perturbed copy
    different = zyx(0.4, pitch - math.copysign(0.6, pitch), 1.0)
    # the paper's raw Euler difference jumps here (roll 0 vs 0.41): the reason for the robust measure
    assert euler_distance(locked, nearby) > 0.2
    near, far = angular_distance(locked, nearby), angular_distance(locked, different)
    assert near < 0.02
    assert far > 0.15
    assert angular_distance(locked, locked) == 0.0


def test_axis_angle_to_matrix_is_kornias_and_exact_near_zero():
    import kornia

    from roguenerf.geometry.noise import axis_angle_to_matrix

    g = torch.Generator().manual_seed(5)
    axes = torch.nn.functional.normalize(torch.randn(64, 3, generator=g, dtype=torch.float64), dim=-1)
    angles = torch.cat([torch.logspace(-9, -3, 16, dtype=torch.float64),
                        torch.linspace(0.01, 3.1, 48, dtype=torch.float64)])
    rotvec = axes * angles[:, None]
    R = axis_angle_to_matrix(rotvec.reshape(8, 8, 3))
    assert R.shape == (8, 8, 3, 3) and R.dtype == torch.float64
    R = R.reshape(64, 3, 3)
    expected = kornia.geometry.conversions.axis_angle_to_rotation_matrix(rotvec)
    assert torch.allclose(R, expected, atol=1e-12, rtol=0)
    eye = torch.eye(3, dtype=torch.float64).expand(64, 3, 3)
    assert torch.allclose(R @ R.transpose(-1, -2), eye, atol=1e-14, rtol=0)  # proper rotations
    assert torch.allclose(torch.linalg.det(R), torch.ones(64, dtype=torch.float64), atol=1e-14, rtol=0)
    # the angle about z: a quarter turn takes x to y, and a rotation keeps its own axis
    quarter = axis_angle_to_matrix(torch.tensor([0.0, 0.0, math.pi / 2], dtype=torch.float64))
    assert torch.allclose(quarter @ torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64),
                          torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64), atol=1e-15)
    assert torch.allclose((R @ axes[..., None])[..., 0], axes, atol=1e-14, rtol=0)
    assert torch.equal(axis_angle_to_matrix(torch.zeros(3)), torch.eye(3, dtype=torch.float64))
