"""Reprojection of neighbour features into the target view: known answers, real data, hard cases."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from roguenerf.data.toy import cast_rays, make_toy_world, render_toy_view, toy_camera_path, toy_intrinsics
from roguenerf.errors import InputError
from roguenerf.geometry import intrinsics_matrix, opengl_to_opencv, scale_intrinsics
from roguenerf.reprojection import reproject
from tests.geometry_helpers import zyx

TOL = {torch.float32: dict(atol=1e-4, rtol=1e-4), torch.float64: dict(atol=1e-9, rtol=1e-9)}


def pose(R=None, t=(0.0, 0.0, 0.0), dtype=torch.float64):
    P = torch.eye(4, dtype=torch.float64)
    if R is not None:
        P[:3, :3] = R
    P[:3, 3] = torch.as_tensor(t, dtype=torch.float64)
    return P.to(dtype)


def grid(H, W, dtype=torch.float64):
    """``(H, W)`` x and y pixel-centre coordinates (integers)."""
    y, x = torch.meshgrid(torch.arange(H, dtype=dtype), torch.arange(W, dtype=dtype), indexing="ij")
    return x, y


def camera(H, W, f=10.0, dtype=torch.float64):
    return intrinsics_matrix(f, f, W / 2, H / 2, dtype=dtype)


# ---------------------------------------------------------------- known answers


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("batch", [1, 3])
def test_identity_pose_reprojects_unchanged(dtype, batch):
    H, W = 5, 7
    feats = torch.rand(batch, 4, H, W, dtype=dtype)
    depth = 1.0 + torch.rand(batch, 1, H, W, dtype=dtype)
    K = camera(H, W, dtype=dtype).expand(batch, 3, 3)
    P = pose(zyx(0.3, -0.4, 2.0), (1.0, -2.0, 0.5), dtype).expand(batch, 4, 4)
    out = reproject(feats, depth, depth, K, K, P, P)
    assert out.features.dtype == dtype and out.features.shape == (batch, 4, H, W)
    torch.testing.assert_close(out.features, feats, **TOL[dtype])
    torch.testing.assert_close(out.depth, depth, **TOL[dtype])
    assert torch.equal(out.valid, torch.ones(batch, 1, H, W, dtype=dtype))
    x, y = grid(H, W, dtype)
    torch.testing.assert_close(out.coords, torch.stack([x, y], -1).expand(batch, H, W, 2), **TOL[dtype])


@pytest.mark.parametrize("tx", [0.4, 0.26])
def test_translation_shifts_by_fx_tx_over_z(tx):
    """Fronto-parallel plane at z = 2, neighbour moved by tx along x: shift = fx * tx / z pixels."""
    H, W, f, z = 4, 9, 10.0, 2.0
    x, y = grid(H, W)
    ramp = (3.0 * x + 0.5 * y)[None, None]  # bilinear sampling of a linear ramp is exact
    depth = torch.full((1, 1, H, W), z, dtype=torch.float64)
    K = camera(H, W, f)
    out = reproject(ramp, depth, depth, K, K, pose(t=(tx, 0, 0)), pose())
    shift = f * tx / z
    torch.testing.assert_close(out.coords[0, ..., 0], x - shift)
    torch.testing.assert_close(out.coords[0, ..., 1], y)
    valid = out.valid[0, 0].bool()
    assert torch.equal(valid, (x - shift) >= -0.5)
    # in the outer half pixel (x in [-0.5, 0)) the edge pixel is repeated
    x_read = (x - shift).clamp_min(0.0)
    torch.testing.assert_close(out.features[0, 0][valid], (3.0 * x_read + 0.5 * y)[valid])
    assert (out.features[0, 0][~valid] == 0).all() and (out.depth[0, 0][~valid] == 0).all()
    torch.testing.assert_close(out.depth[0, 0][valid], torch.full_like(x[valid], z))


def test_neighbour_rotated_180_about_optical_axis_flips_image():
    H, W = 3, 5
    x, y = grid(H, W)
    img = torch.stack([x, y])[None]
    depth = torch.full((1, 1, H, W), 3.0, dtype=torch.float64)
    K = camera(H, W)
    out = reproject(img, depth, depth, K, K, pose(zyx(0, 0, math.pi)), pose())
    torch.testing.assert_close(out.coords[0], torch.stack([W - 1 - x, H - 1 - y], -1))
    torch.testing.assert_close(out.features[0], torch.stack([W - 1 - x, H - 1 - y]))
    assert out.valid.all()


def test_different_neighbour_resolution():
    """Same camera, neighbour image at twice the resolution: a linear image reads back exactly."""
    H, W = 4, 6
    K = camera(H, W)
    K_src = scale_intrinsics(K, 2.0, 2.0)
    xs, ys = grid(2 * H, 2 * W)
    # a linear function of the continuous image position (pixel-centre convention)
    src = ((xs + 0.5) / 2 + 10 * (ys + 0.5) / 2)[None, None]
    depth = torch.full((1, 1, H, W), 2.0, dtype=torch.float64)
    out = reproject(src, None, depth, K_src, K, pose(), pose())
    x, y = grid(H, W)
    torch.testing.assert_close(out.features[0, 0], (x + 0.5) + 10 * (y + 0.5))
    torch.testing.assert_close(out.coords[0], torch.stack([2 * x + 0.5, 2 * y + 0.5], -1))
    assert out.valid.all()
    torch.testing.assert_close(out.depth, depth)  # without src_depth: z_{k->i}


def test_visibility_heaviside_with_leniency():
    """z_{k->i} / z_i <= 1 + leniency passes, anything beyond fails (here: z_i >= 2 / 1.25 = 1.6)."""
    H, W = 2, 3
    K = camera(H, W)
    dst = torch.full((1, 1, H, W), 2.0, dtype=torch.float64)
    feats = torch.ones(1, 1, H, W, dtype=torch.float64)
    for z_i, expected in [(2.0, 1.0), (1.7, 1.0), (1.61, 1.0), (1.59, 0.0), (1.0, 0.0), (50.0, 1.0)]:
        src = torch.full((1, 1, H, W), z_i, dtype=torch.float64)
        out = reproject(feats, src, dst, K, K, pose(), pose())
        assert (out.valid == expected).all(), z_i
    src = torch.full((1, 1, H, W), 1.0, dtype=torch.float64)
    assert reproject(feats, src, dst, K, K, pose(), pose(), leniency=1.0).valid.all()


# ---------------------------------------------------------------- real and toy data


def test_lego_consistency_matches_readme(lego_dir: Path):
    """test_r_0 into train_r_79 with the rendered depths: the README's figures."""
    meta = json.loads((lego_dir / "transforms.json").read_text())
    frames = {Path(f["file_path"]).stem: f for f in meta["frames"]}

    def load(name):
        f = frames[name]
        depth = torch.from_numpy(np.load(lego_dir / f["depth_path"], allow_pickle=False))[None, None]
        return depth, opengl_to_opencv(torch.tensor(f["transform_matrix"]))

    dst_depth, dst_pose = load("test_r_0")
    src_depth, src_pose = load("train_r_79")
    K = intrinsics_matrix(meta["fl_x"], meta["fl_y"], meta["cx"], meta["cy"])
    feats = torch.zeros(1, 1, *src_depth.shape[-2:])
    plain = reproject(feats, None, dst_depth, K, K, src_pose, dst_pose)
    # the README counts points between the outermost pixel centres ([0, W-1]) as inside
    c = plain.coords[0]
    inside = ((c >= 0) & (c <= 199)).all(-1).double().mean().item()
    assert inside == pytest.approx(0.972, abs=0.001)
    both = reproject(feats, src_depth, dst_depth, K, K, src_pose, dst_pose, leniency=1e9)
    seen = both.valid.bool()
    rel = ((plain.depth - both.depth).abs() / both.depth)[seen]
    assert rel.median().item() == pytest.approx(0.0373, abs=0.0005)
    assert (rel < 0.05).double().mean().item() == pytest.approx(0.585, abs=0.002)


def _surface_ids(world, world_from_cam, K, H, W):
    y, x = torch.meshgrid(torch.arange(H) + 0.5, torch.arange(W) + 0.5, indexing="ij")
    pix = torch.stack([x, y, torch.ones_like(x)], -1).reshape(-1, 3).double()
    dirs = pix @ torch.linalg.inv(K).T @ world_from_cam[:3, :3].T
    return cast_rays(world, world_from_cam[:3, 3], dirs)[1].reshape(H, W)


def test_toy_warp_is_accurate_where_visible():
    world = make_toy_world(1)
    poses = toy_camera_path(world, 8, seed=1, kind="orbit")
    H, W = 48, 64
    K = toy_intrinsics(H, W)
    a_rgb, a_depth = render_toy_view(world, poses[2], K, H, W)
    b_rgb, b_depth = render_toy_view(world, poses[3], K, H, W)
    ids = _surface_ids(world, poses[2], K, H, W)
    onehot = F.one_hot(ids, world.base.shape[0]).permute(2, 0, 1).float()
    # Exact depth needs little leniency; 0.25 lets points 20% behind an occluder through.
    stacked = torch.cat([a_rgb, onehot])[None]
    out = reproject(stacked, a_depth[None], b_depth[None], K, K, poses[2], poses[3], leniency=0.05)
    valid = out.valid[0, 0].bool()
    # pixels whose bilinear footprint in A straddles two surfaces blend their colours: no warp can fix that
    single_surface = out.features[0, 3:].amax(0) > 1 - 1e-5
    err = ((out.features[0, :3] - b_rgb) ** 2).mean(0)
    psnr_clean = -10 * math.log10(err[valid & single_surface].mean().item())
    psnr_all = -10 * math.log10(err[valid].mean().item())
    assert valid.double().mean() > 0.8
    assert (valid & single_surface).sum() > 0.9 * valid.sum()
    assert psnr_clean >= 40.0, psnr_clean
    assert psnr_all >= 30.0, psnr_all


def test_toy_occluded_pixels_are_invisible():
    world = make_toy_world(1)
    poses = toy_camera_path(world, 8, seed=1, kind="orbit")
    H, W = 48, 64
    K = toy_intrinsics(H, W)
    ia, ib = 1, 4
    a_rgb, a_depth = render_toy_view(world, poses[ia], K, H, W)
    _, b_depth = render_toy_view(world, poses[ib], K, H, W)
    out = reproject(a_rgb[None], a_depth[None], b_depth[None], K, K, poses[ia], poses[ib])

    # ground truth from the ray caster: is anything between A's centre and B's surface point?
    y, x = torch.meshgrid(torch.arange(H) + 0.5, torch.arange(W) + 0.5, indexing="ij")
    pix = torch.stack([x, y, torch.ones_like(x)], -1).reshape(-1, 3).double()
    points = (pix @ torch.linalg.inv(K).T) * b_depth.double().reshape(-1, 1) @ poses[ib][:3, :3].T + poses[ib][:3, 3]
    eye = poses[ia][:3, 3]
    t_hit, _ = cast_rays(world, eye, points - eye)
    depth_ratio = (1.0 / t_hit).reshape(1, 1, H, W)  # z_{B->A} / z of the first surface A sees
    in_a = (points - eye) @ poses[ia][:3, :3] @ K.T
    uv = in_a[:, :2] / in_a[:, 2:]
    in_image = ((uv >= 0).all(-1) & (uv[:, 0] <= W) & (uv[:, 1] <= H)).reshape(1, 1, H, W)
    occluded = (depth_ratio > 1.35) & in_image
    # away from occluder silhouettes (bilinear depth there blends both surfaces)
    occluded_core = -F.max_pool2d(-occluded.double(), 3, 1, 1) > 0
    seen_in_a = (depth_ratio <= 1 + 1e-6) & in_image
    visible = out.valid.bool()
    assert occluded_core.sum() > 100
    assert not (visible & occluded_core).any()
    assert (visible & seen_in_a).sum() >= 0.99 * seen_in_a.sum()


# ---------------------------------------------------------------- hard cases


def _finite_with_grads(feats, src_depth, dst_depth, K_src, K_dst, P_src, P_dst, **kw):
    feats = feats.clone().requires_grad_(True)
    dst_depth = dst_depth.clone().requires_grad_(True)
    out = reproject(feats, src_depth, dst_depth, K_src, K_dst, P_src, P_dst, **kw)
    for name in ("features", "valid", "depth", "coords"):
        assert torch.isfinite(getattr(out, name)).all(), name
    (out.features.square().sum() + out.depth.sum() + out.coords.sum()).backward()
    assert torch.isfinite(feats.grad).all()
    assert torch.isfinite(dst_depth.grad).all()
    return out, feats.grad, dst_depth.grad


BAD_DEPTHS = {
    "zero": lambda d: torch.zeros_like(d),
    "nan": lambda d: torch.where(torch.rand_like(d) < 0.5, float("nan"), d),
    "inf": lambda d: torch.where(torch.rand_like(d) < 0.5, float("inf"), d),
    "neginf": lambda d: torch.full_like(d, -float("inf")),
    "negative": lambda d: -d,
    "huge": lambda d: torch.full_like(d, 3e38),
}


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("kind", sorted(BAD_DEPTHS))
@pytest.mark.parametrize("where", ["dst", "src"])
def test_missing_depth_is_invalid_with_finite_grads(kind, where, dtype):
    torch.manual_seed(0)
    H, W = 4, 6
    good = 1.0 + torch.rand(2, 1, H, W, dtype=dtype)
    bad = BAD_DEPTHS[kind](good)
    K = camera(H, W, dtype=dtype)
    P_src = pose(zyx(0.05, 0, 0), (0.1, 0, 0), dtype)
    src, dst = (good, bad) if where == "dst" else (bad, good)
    out, _, _ = _finite_with_grads(torch.rand(2, 3, H, W, dtype=dtype), src, dst, K, K, P_src, pose(dtype=dtype))
    bad_px = ~(torch.isfinite(bad) & (bad > 0) & (bad < 1e10))
    if where == "dst":
        assert not out.valid.bool()[bad_px].any()
    if kind in ("zero", "negative", "neginf", "huge"):
        assert not out.valid.any() and not out.features.any()


def test_every_point_behind_neighbour():
    H, W = 4, 5
    K = camera(H, W)
    depth = torch.full((1, 1, H, W), 2.0, dtype=torch.float64)
    behind = pose(zyx(0, 0, 0), (0, 0, 5.0))  # neighbour 5 units ahead, same direction: the plane at z=2 is behind it
    out, _, _ = _finite_with_grads(torch.rand(1, 3, H, W, dtype=torch.float64), depth, depth, K, K, behind, pose())
    assert not out.valid.any() and not out.features.any() and not out.depth.any()
    assert not out.coords.any()


def test_neighbour_facing_the_other_way():
    """Rotated 180 deg about the vertical axis at the same centre: everything is behind it."""
    H, W = 3, 4
    K = camera(H, W)
    depth = torch.full((1, 1, H, W), 2.0, dtype=torch.float64)
    feats = torch.rand(1, 2, H, W, dtype=torch.float64)
    out, _, _ = _finite_with_grads(feats, depth, depth, K, K, pose(zyx(0, math.pi, 0)), pose())
    assert not out.valid.any()


def _small_pair():
    """A 4 x 6 float64 view pair: K, features, a depth in [1.5, 2.5), the neighbour's pose
    relative to the target, and the reprojection with the target at the origin."""
    H, W = 4, 6
    K = camera(H, W)
    feats = torch.rand(1, 3, H, W, dtype=torch.float64)
    depth = 1.5 + torch.rand(1, 1, H, W, dtype=torch.float64)
    rel = pose(zyx(0.05, 0.02, -0.03), (0.1, -0.05, 0.02))
    ref = reproject(feats, depth, depth, K, K, rel, pose())
    return K, feats, depth, rel, ref


@pytest.mark.parametrize("pitch", [math.pi / 2, -math.pi / 2])
def test_gimbal_lock_rig_gives_same_answer(pitch):
    """Turning the whole rig to pitch +-90 deg changes nothing relative between the cameras."""
    K, feats, depth, rel, ref = _small_pair()
    rig = pose(zyx(0.3, pitch, 1.2), (1.0, 2.0, 3.0))
    out, _, _ = _finite_with_grads(feats, depth, depth, K, K, rig @ rel, rig)
    torch.testing.assert_close(out.coords, ref.coords)
    torch.testing.assert_close(out.features, ref.features)
    assert torch.equal(out.valid, ref.valid)


def test_huge_translations_keep_precision_in_float32():
    H, W = 4, 6
    K = camera(H, W, dtype=torch.float32)
    feats = torch.rand(1, 3, H, W)
    depth = 1.5 + torch.rand(1, 1, H, W)
    rel = pose(zyx(0.05, 0.02, -0.03), (0.1, -0.05, 0.02), torch.float64)
    far = pose(t=(1e4, -1e4, 1e4))
    ref = reproject(feats, depth, depth, K, K, rel, pose())
    # float64 poses with float32 images: the relative pose is exact
    out, _, _ = _finite_with_grads(feats, depth, depth, K, K, far @ rel, far)
    assert (out.coords - ref.coords).abs().max() < 1e-4
    assert torch.equal(out.valid, ref.valid)
    # float32 poses: storing 1e4 in float32 already moves each camera by up to 5e-4 units,
    # i.e. up to fx * 1e-3 / z = 0.007 px here; the computation adds nothing on top
    out, _, _ = _finite_with_grads(feats, depth, depth, K, K, (far @ rel).float(), far.float())
    assert (out.coords - ref.coords).abs().max() < 7e-3
    # a neighbour 1e4 units away sees nothing of a plane at 2 units
    out, _, _ = _finite_with_grads(feats, depth, depth, K, K, far.float(), pose(dtype=torch.float32))
    assert not out.valid.any()


@pytest.mark.parametrize("shape", [(1, 1), (3, 5)])
def test_tiny_images(shape):
    H, W = shape
    K = camera(H, W)
    feats = torch.rand(2, 3, H, W, dtype=torch.float64)
    depth = torch.full((2, 1, H, W), 2.0, dtype=torch.float64)
    out, _, _ = _finite_with_grads(feats, depth, depth, K, K, pose(), pose())
    torch.testing.assert_close(out.features, feats)
    assert out.valid.all()
    out, _, _ = _finite_with_grads(feats, depth, depth, K, K, pose(t=(0.05, 0, 0)), pose())
    assert out.features.shape == (2, 3, H, W)


@pytest.mark.parametrize("fx", [0.0, -10.0])
def test_bad_focal_length_raises(fx):
    K_bad = torch.tensor([[fx, 0, 2.0], [0, 10.0, 2.0], [0, 0, 1]], dtype=torch.float64)
    d = torch.ones(1, 1, 4, 4, dtype=torch.float64)
    with pytest.raises(InputError, match=r"src_K: expected focal lengths fx > 0"):
        reproject(d, d, d, K_bad, camera(4, 4), pose(), pose())
    with pytest.raises(InputError, match=r"dst_K"):
        reproject(d, d, d, camera(4, 4), K_bad, pose(), pose())


def test_non_orthonormal_rotation():
    K, feats, depth, rel, ref = _small_pair()
    slightly = rel.clone()
    slightly[:3, :3] *= 1 + 2e-4  # scale error within ORTHONORMAL_TOL (1e-3)
    out = reproject(feats, depth, depth, K, K, slightly, pose())
    torch.testing.assert_close(out.coords, ref.coords, atol=1e-6, rtol=0)
    badly = rel.clone()
    badly[:3, :3] *= 1.01
    with pytest.raises(InputError, match=r"world_from_src: expected an orthonormal rotation"):
        reproject(feats, depth, depth, K, K, badly, pose())


def test_shape_errors_name_the_argument():
    d = torch.ones(1, 1, 4, 4)
    K = camera(4, 4, dtype=torch.float32)
    P = torch.eye(4)
    with pytest.raises(InputError, match=r"dst_depth: expected shape \(B, 1, H, W\)"):
        reproject(d, d, torch.ones(1, 2, 4, 4), K, K, P, P)
    with pytest.raises(InputError, match=r"dst_depth: expected batch size 1"):
        reproject(d, d, torch.ones(2, 1, 4, 4), K, K, P, P)
    with pytest.raises(InputError, match=r"src_depth: expected shape"):
        reproject(d, torch.ones(1, 1, 3, 4), d, K, K, P, P)
    with pytest.raises(InputError, match=r"world_from_dst: expected shape"):
        reproject(d, d, d, K, K, P, torch.eye(4).expand(3, 4, 4))
    with pytest.raises(InputError, match=r"src_features: expected shape \(B, C, H, W\) with H, W >= 1"):
        reproject(torch.ones(1, 1, 0, 4), None, d, K, K, P, P)


# ---------------------------------------------------------------- gradcheck


def test_gradcheck_features():
    H, W = 4, 5
    K = camera(H, W)
    src_depth = 1.5 + torch.rand(1, 1, H, W, dtype=torch.float64)
    dst_depth = 1.5 + torch.rand(1, 1, H, W, dtype=torch.float64)
    P = pose(zyx(0.02, -0.03, 0.01), (0.07, 0.03, 0.0))
    feats = torch.rand(1, 2, H, W, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda f: reproject(f, src_depth, dst_depth, K, K, P, pose()).features, (feats,))


def test_gradcheck_target_depth():
    """Away from kinks: projected coordinates are far from integers, visibility far from its threshold."""
    H, W = 3, 4
    K = camera(H, W)
    depth = torch.full((1, 1, H, W), 2.0, dtype=torch.float64)
    depth = depth + 0.01 * torch.arange(H * W, dtype=torch.float64).reshape(1, 1, H, W)
    P = pose(t=(0.07, 0.05, 0.0))  # shifts of about 0.35 and 0.25 px
    x, y = grid(H, W)
    feats = torch.stack([x * x + y, torch.sin(x) * y])[None]  # not linear, so the gradient is not constant
    src_depth = torch.full((1, 1, H, W), 2.1, dtype=torch.float64)
    out = reproject(feats, src_depth, depth, K, K, P, pose())
    frac = out.coords - out.coords.floor()
    assert out.valid.sum() >= 8 and ((frac > 0.1) & (frac < 0.9))[out.valid[0].bool()].all()

    def f(d):
        r = reproject(feats, src_depth, d, K, K, P, pose())
        return r.features, r.depth, r.coords

    assert torch.autograd.gradcheck(f, (depth.clone().requires_grad_(True),))
