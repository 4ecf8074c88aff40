"""Toy scenes: exact analytic depth, any pose and K, camera paths, and the scene-folder round trip."""

from __future__ import annotations

import math

import pytest
import torch

from roguenerf.data.toy import (
    make_toy_scene,
    make_toy_world,
    render_toy_view,
    toy_camera_path,
    toy_intrinsics,
)
from roguenerf.errors import InputError
from roguenerf.geometry import check_pose, intrinsics_matrix


def _pose(right, down, forward, eye):
    P = torch.eye(4, dtype=torch.float64)
    P[:3, :3] = torch.tensor([right, down, forward], dtype=torch.float64).T
    P[:3, 3] = torch.tensor(eye, dtype=torch.float64)
    return P


def test_render_shapes_range_and_determinism():
    world = make_toy_world(0)
    pose = toy_camera_path(world, 3, seed=0)[1]
    K = toy_intrinsics(48, 64)
    rgb, depth = render_toy_view(world, pose, K, 48, 64)
    assert rgb.shape == (3, 48, 64) and rgb.dtype == torch.float32
    assert depth.shape == (1, 48, 64) and depth.dtype == torch.float32
    assert rgb.min() >= 0 and rgb.max() <= 1 and rgb.std() > 0.05
    assert torch.isfinite(depth).all() and (depth > 0).all()
    rgb2, depth2 = render_toy_view(make_toy_world(0), pose, K, 48, 64)
    assert torch.equal(rgb, rgb2) and torch.equal(depth, depth2)
    assert not torch.equal(render_toy_view(make_toy_world(1), pose, K, 48, 64)[0], rgb)


def test_floor_depth_is_exact_from_above():
    """A camera 1.3 units above the floor, looking straight down, far from the boxes: z = 1.3 everywhere."""
    world = make_toy_world(2)
    down_pose = _pose((1, 0, 0), (0, -1, 0), (0, 0, -1), (20.0, -3.0, 1.3))
    _, depth = render_toy_view(world, down_pose, toy_intrinsics(12, 16), 12, 16)
    torch.testing.assert_close(depth, torch.full_like(depth, 1.3), atol=1e-6, rtol=0)


def test_wall_depth_is_exact_head_on():
    world = make_toy_world(3)
    facing = _pose((1, 0, 0), (0, 0, -1), (0, 1, 0), (0.0, world.wall_y - 1.5, 6.0))
    _, depth = render_toy_view(world, facing, toy_intrinsics(12, 16), 12, 16)
    torch.testing.assert_close(depth, torch.full_like(depth, 1.5), atol=1e-6, rtol=0)


def test_any_intrinsics_pixel_centre_crop():
    """Rendering a crop with a shifted principal point gives exactly that crop of the full render."""
    world = make_toy_world(0)
    pose = toy_camera_path(world, 1, seed=3, kind="orbit")[0]
    K = intrinsics_matrix(50.0, 40.0, 33.0, 21.0, dtype=torch.float64)
    rgb, depth = render_toy_view(world, pose, K, 40, 60)
    r0, c0, h, w = 7, 11, 9, 13
    K_crop = K.clone()
    K_crop[0, 2] -= c0
    K_crop[1, 2] -= r0
    rgb_c, depth_c = render_toy_view(world, pose, K_crop, h, w)
    torch.testing.assert_close(rgb_c, rgb[:, r0 : r0 + h, c0 : c0 + w], atol=1e-6, rtol=0)
    torch.testing.assert_close(depth_c, depth[:, r0 : r0 + h, c0 : c0 + w], atol=1e-6, rtol=1e-6)


@pytest.mark.parametrize("kind", ["forward", "orbit"])
def test_camera_paths_look_at_the_scene(kind):
    world = make_toy_world(4)
    poses = toy_camera_path(world, 10, seed=4, kind=kind)
    assert poses.shape == (10, 4, 4) and poses.dtype == torch.float64
    check_pose(poses, tol=1e-9)
    eyes = poses[:, :3, 3]
    to_centre = world.centre - eyes
    to_centre = to_centre / to_centre.norm(dim=-1, keepdim=True)
    cos = (poses[:, :3, 2] * to_centre).sum(-1)
    assert (cos > math.cos(math.radians(5))).all()
    assert (eyes[:, 2] > 0.5).all() and (eyes[:, 1] < world.wall_y).all()
    forwards = poses[:, :3, 2]
    spread = torch.rad2deg(torch.acos((forwards[0] * forwards[-1]).sum().clamp(-1, 1)))
    if kind == "forward":
        assert spread < 25
    else:
        assert spread > 80
    assert torch.equal(toy_camera_path(world, 10, seed=4, kind=kind), poses)


def test_bad_arguments():
    world = make_toy_world(0)
    with pytest.raises(InputError, match="kind"):
        toy_camera_path(world, 2, kind="spiral")
    with pytest.raises(InputError, match="fx > 0"):
        render_toy_view(world, torch.eye(4), torch.tensor([[0.0, 0, 1], [0, 1, 1], [0, 0, 1]]), 2, 2)
    with pytest.raises(InputError, match="height, width"):
        render_toy_view(world, torch.eye(4), toy_intrinsics(2, 2), 0, 2)


def test_make_toy_scene_round_trip(tmp_path):
    scene = make_toy_scene(tmp_path / "toy", seed=5, n_train=5, n_test=2, height=24, width=32)
    assert len(scene.indices("train")) == 5 and len(scene.indices("test")) == 2
    world = make_toy_world(5)
    poses = toy_camera_path(world, 7, seed=5)
    torch.testing.assert_close(scene.poses(), poses, atol=1e-6, rtol=0)
    K = toy_intrinsics(24, 32)
    for i in (0, scene.indices("test")[0]):
        photo, depth = render_toy_view(world, poses[i], K, 24, 32)
        torch.testing.assert_close(scene.photo(i), photo, atol=1 / 255, rtol=0)  # 8-bit PNG
        torch.testing.assert_close(scene.depth(i), depth)
        torch.testing.assert_close(scene.intrinsics()[i], K)
        render = scene.render(i)
        assert render.shape == (3, 24, 32)
        assert 0.003 < (render - photo).abs().mean() < 0.1  # blurred, not a copy


def test_make_toy_scene_uses_degradation(tmp_path):
    calls = []

    def darken(photos, depths, generator):
        calls.append((photos.shape, depths.shape, isinstance(generator, torch.Generator)))
        return photos * 0.5, depths * 1.1

    scene = make_toy_scene(tmp_path / "toy", seed=0, n_train=3, n_test=1, height=12, width=16, degradation=darken)
    assert calls == [((4, 3, 12, 16), (4, 1, 12, 16), True)]
    torch.testing.assert_close(scene.render(0), scene.photo(0) * 0.5, atol=1.5 / 255, rtol=0)
    _, depth = render_toy_view(make_toy_world(0), scene.poses()[0], toy_intrinsics(12, 16), 12, 16)
    torch.testing.assert_close(scene.depth(0), depth * 1.1)
