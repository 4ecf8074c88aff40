"""Degradation simulator: deterministic, each step has a known effect, missing depth stays missing."""

from __future__ import annotations

import math

import kornia
import pytest
import torch

from roguenerf.data.degrade import Degradation, _pose_error
from roguenerf.data.toy import make_toy_scene, make_toy_world, render_toy_view, toy_camera_path, toy_intrinsics
from roguenerf.errors import InputError
from roguenerf.metrics import psnr

H, W = 24, 32
OFF = dict(blur_sigma=(0, 0), noise=(0, 0), pose_noise_deg=0, pose_noise_trans=0, depth_noise=0,
           haze=(0, 0), defocus=(0, 0), color_shift=0)


@pytest.fixture(scope="module")
def views():
    world = make_toy_world(1)
    K = toy_intrinsics(H, W)
    poses = toy_camera_path(world, 3, seed=1)
    photos, depths = zip(*(render_toy_view(world, p, K, H, W) for p in poses))
    return torch.stack(photos).float(), torch.stack(depths).float(), K


def _gen(seed=0):
    return torch.Generator().manual_seed(seed)


def test_deterministic_per_generator(views):
    photos, depths, K = views
    deg = Degradation()
    r1, d1 = deg(photos, depths, _gen(5), K=K)
    r2, d2 = deg(photos, depths, _gen(5), K=K)
    r3, _ = deg(photos, depths, _gen(6), K=K)
    assert torch.equal(r1, r2) and torch.equal(d1, d2)
    assert not torch.equal(r1, r3)
    assert r1.shape == photos.shape and d1.shape == depths.shape
    assert r1.min() >= 0 and r1.max() <= 1
    assert 20 < psnr(r1, photos).min() and psnr(r1, photos).max() < 40  # NeRF-like, not destroyed


def test_all_off_is_identity(views):
    photos, depths, _ = views
    renders, out_depths = Degradation(**OFF)(photos, depths, _gen())
    assert torch.equal(renders, photos.clamp(0, 1)) and torch.equal(out_depths, depths)


def test_blur_equals_kornia_gaussian(views):
    photos, depths, _ = views
    renders, _ = Degradation(**{**OFF, "blur_sigma": (1.0, 1.0)})(photos, depths, _gen())
    expected = kornia.filters.gaussian_blur2d(photos, (7, 7), (1.0, 1.0), border_type="reflect")
    assert torch.allclose(renders, expected.clamp(0, 1), atol=1e-6)


def test_noise_std_and_colour_shift_affine(views):
    photos, depths, _ = views
    flat = torch.full_like(photos, 0.5)
    renders, _ = Degradation(**{**OFF, "noise": (0.05, 0.05)})(flat, depths, _gen())
    assert (renders - flat).std().item() == pytest.approx(0.05, rel=0.1)
    mid = photos * 0.4 + 0.3  # stays inside [0, 1] after a small shift
    shifted, _ = Degradation(**{**OFF, "color_shift": 0.05})(mid, depths, _gen())
    for i in range(mid.shape[0]):
        for c in range(3):
            x, y = mid[i, c].flatten(), shifted[i, c].flatten()
            A = torch.stack([x, torch.ones_like(x)], dim=1)
            coef = torch.linalg.lstsq(A, y[:, None]).solution
            assert (A @ coef - y[:, None]).abs().max() < 1e-5  # an affine map per channel
            assert not torch.allclose(coef.flatten(), torch.tensor([1.0, 0.0]))


def test_haze_toward_background_where_far_or_missing():
    photos = torch.full((1, 3, 4, 4), 0.2)
    depth = torch.linspace(1, 10, 16).view(1, 1, 4, 4).clone()
    depth[0, 0, 3, 3] = 0.0  # missing
    depth[0, 0, 3, 2] = float("nan")  # missing
    deg = Degradation(**{**OFF, "haze": (0.5, 0.5)}, background=(1.0, 0.0, 1.0))
    renders, out_depth = deg(photos, depth, _gen())
    bg = torch.tensor([1.0, 0.0, 1.0])
    assert torch.allclose(renders[0, :, 3, 3], 0.5 * 0.2 + 0.5 * bg)
    assert torch.allclose(renders[0, :, 3, 2], 0.5 * 0.2 + 0.5 * bg)
    assert torch.allclose(renders[0, :, 0, 0], torch.full((3,), 0.2))  # nearest pixel: no haze
    assert out_depth[0, 0, 3, 3] == 0 and torch.isnan(out_depth[0, 0, 3, 2])


def test_defocus_keeps_in_focus_plane_sharp(views):
    photos, _, _ = views
    flat_depth = torch.full((photos.shape[0], 1, H, W), 3.0)
    renders, _ = Degradation(**{**OFF, "defocus": (1.5, 1.5)})(photos, flat_depth, _gen())
    assert torch.allclose(renders, photos)
    step = flat_depth.clone()
    step[..., W // 2 :] = 30.0
    renders, _ = Degradation(**{**OFF, "defocus": (1.5, 1.5)})(photos, step, _gen())
    changed = (renders - photos).abs().amax(dim=1)
    for i in range(photos.shape[0]):
        # the focus plane is one of the two depths: that half is unchanged, the other blurred
        halves = [changed[i, :, : W // 2].amax().item(), changed[i, :, W // 2 :].amax().item()]
        assert min(halves) < 1e-6 < 1e-2 < max(halves)


def test_depth_noise_smooth_relative_and_missing_kept(views):
    photos, depths, _ = views
    depths = depths.clone()
    depths[0, 0, 0, 0] = 0.0
    depths[1, 0, 5, 5] = float("nan")
    _, noisy = Degradation(**{**OFF, "depth_noise": 0.02})(photos, depths, _gen())
    known = torch.isfinite(depths) & (depths > 0)
    rel = (noisy / depths - 1)[known]
    assert 0 < rel.abs().max() < 0.02 * 5
    assert noisy[0, 0, 0, 0] == 0 and torch.isnan(noisy[1, 0, 5, 5])
    ratio = noisy[2, 0] / depths[2, 0]
    first = (ratio[:, 1:] - ratio[:, :-1]).abs().mean()
    second = (ratio[:, 2:] - 2 * ratio[:, 1:-1] + ratio[:, :-2]).abs().mean()
    assert second < 0.5 * first  # piecewise-linear field (kinks every W/4 px); white noise: ~1.7 x


def test_pose_error_rotation_shifts_by_focal_tan(views):
    _, _, K = views
    K = K.float()
    ramp = torch.linspace(0, 1, W).view(1, 1, 1, W).expand(1, 3, H, W).contiguous()
    depth = torch.full((1, 1, H, W), 4.0)
    known = torch.ones_like(depth, dtype=torch.bool)
    theta = math.radians(1.0)
    rot = torch.tensor([[0.0, theta, 0.0]])  # about the camera's y axis
    out, out_depth = _pose_error(ramp, depth, known, K[None], rot, torch.zeros(1, 3))
    fx, cx = K[0, 0].item(), K[0, 2].item()
    u = W // 2 + 3
    a = (u + 0.5 - cx) / fx  # the pixel's ray (a, 0, 1), rotated about y, projected into the exact view
    x = cx + fx * (a * math.cos(theta) + math.sin(theta)) / (math.cos(theta) - a * math.sin(theta))
    expected = (x - 0.5) / (W - 1)  # the ramp's value at image coordinate x (pixel centres at +0.5)
    assert out[0, 0, H // 2, u].item() == pytest.approx(expected, abs=1e-5)
    # depth of the plane seen from a rotated camera: z' = z cos(theta) +- a small term
    assert out_depth[0, 0, H // 2, u].item() == pytest.approx(4.0, rel=0.01)
    out, _ = _pose_error(ramp, depth, known, K[None], torch.zeros(1, 3), torch.tensor([[0.1, 0.0, 0.0]]))
    # translating by +0.1 along x at depth 4 moves the content by fx * 0.1 / 4 pixels
    expected = (cx + fx * (a + 0.1 / 4) - 0.5) / (W - 1)
    assert out[0, 0, H // 2, u].item() == pytest.approx(expected, abs=1e-5)


def test_invalid_arguments():
    with pytest.raises(InputError, match="blur_sigma"):
        Degradation(blur_sigma=(2.0, 1.0))
    with pytest.raises(InputError, match="pose_noise_deg"):
        Degradation(pose_noise_deg=-1)
    with pytest.raises(InputError, match="background"):
        Degradation(background=(2.0, 0, 0))
    deg = Degradation()
    with pytest.raises(InputError, match=r"photos: expected a float \(M, 3, H, W\)"):
        deg(torch.zeros(3, H, W), torch.zeros(1, H, W), _gen())
    with pytest.raises(InputError, match=r"depths: expected shape \(1, 1, 24, 32\)"):
        deg(torch.zeros(1, 3, H, W), torch.zeros(1, 1, H, W + 1), _gen())
    with pytest.raises(InputError, match="generator"):
        deg(torch.zeros(1, 3, H, W), torch.zeros(1, 1, H, W), None)


def test_toy_scene_with_degradation(tmp_path):
    scene = make_toy_scene(tmp_path / "toy", n_train=3, n_test=1, height=H, width=W, degradation=Degradation())
    i = scene.indices("train")[0]
    value = psnr(scene.render(i)[None], scene.photo(i)[None]).item()
    assert 18 < value < 40
