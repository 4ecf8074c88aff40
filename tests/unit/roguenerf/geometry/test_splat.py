"""splat_view: one view's image drawn into another camera through its own depth (a forward warp
with a z-buffer), against known answers."""

from __future__ import annotations

import pytest
import torch

from roguenerf.errors import InputError
from roguenerf.reprojection import reproject, splat_view

H, W, F = 30, 40, 50.0
K = torch.tensor([[F, 0.0, W / 2], [0.0, F, H / 2], [0.0, 0.0, 1.0]])
EYE = torch.eye(4, dtype=torch.float64)


def _moved(x: float = 0.0, y: float = 0.0, z: float = 0.0) -> torch.Tensor:
    pose = EYE.clone()
    pose[:3, 3] = torch.tensor([x, y, z], dtype=torch.float64)
    return pose


def test_the_same_camera_gives_the_image_back():
    image, depth = torch.rand(3, H, W), torch.rand(1, H, W) + 1.0
    out, out_depth, hit = splat_view(image, depth, K, K, EYE, EYE, (H, W))
    assert torch.equal(out, image) and bool(hit.all())
    torch.testing.assert_close(out_depth, depth)


def test_a_sideways_camera_shifts_a_plane_and_leaves_the_uncovered_strip():
    image, depth = torch.rand(3, H, W), torch.full((1, H, W), 2.0)
    # 0.08 to the right at depth 2: the scene moves F * 0.08 / 2 = 2 pixels to the left
    out, out_depth, hit = splat_view(image, depth, K, K, EYE, _moved(x=0.08), (H, W))
    torch.testing.assert_close(out[:, :, :-2], image[:, :, 2:])
    assert bool(hit[..., :-2].all()) and not bool(hit[..., -2:].any())
    assert float(out[..., -2:].abs().max()) == 0.0 and float(out_depth[..., -2:].abs().max()) == 0.0


def test_the_nearer_surface_wins_and_keeps_its_depth():
    image, depth = torch.rand(3, H, W), torch.full((1, H, W), 2.0)
    depth[:, 10:20, 10:20] = 1.0  # a square in front: it moves 4 pixels, the plane behind it 2
    out, out_depth, hit = splat_view(image, depth, K, K, EYE, _moved(x=0.08), (H, W))
    torch.testing.assert_close(out[:, 10:20, 6:16], image[:, 10:20, 10:20])
    assert torch.equal(out_depth[:, 10:20, 6:16], torch.ones(1, 10, 10))
    assert not bool(hit[:, 10:20, 16:18].any())  # the plane the square hid in the source: a hole
    torch.testing.assert_close(out[:, 10:20, 18:20], image[:, 10:20, 20:22])  # the plane beside it


def test_unknown_depth_draws_nothing_and_a_nearer_camera_leaves_no_cracks():
    image, depth = torch.rand(3, H, W), torch.full((1, H, W), 2.0)
    depth[:, :, :5] = float("nan")
    depth[:, :2] = 0.0
    _, _, hit = splat_view(image, depth, K, K, EYE, EYE, (H, W))
    assert not bool(hit[..., :5].any()) and not bool(hit[:, :2].any()) and bool(hit[:, 2:, 5:].all())
    # 10 % nearer: the plane grows by 1.11x; the 2 x 2 footprint fills between the points
    _, _, hit = splat_view(torch.rand(3, H, W), torch.full((1, H, W), 2.0), K, K, EYE, _moved(z=0.2), (H, W))
    assert bool(hit.all())


def test_drawing_forward_agrees_with_reading_back_through_the_destination_depth():
    """On a tilted plane seen by two cameras, drawing the source forward and reading it back
    through the destination's depth (reproject) put the same source pixel on each destination
    pixel, to the nearest point's sub-pixel offset."""
    v, u = torch.meshgrid(torch.arange(H) + 0.5, torch.arange(W) + 0.5, indexing="ij")
    image = torch.stack([u, v, u + v])  # each pixel's coordinates: what is drawn says where it came from
    world_from_dst = _moved(x=0.05, y=-0.03)

    def plane_depth(pose):  # z = 2 + 0.2 x in world coordinates, seen from a camera at pose
        ray_x = (torch.arange(W, dtype=torch.float64) + 0.5 - W / 2) / F
        z = (2.0 + 0.2 * float(pose[0, 3])) / (1.0 - 0.2 * ray_x)
        return z.expand(H, W)[None].to(torch.float32)

    src_depth, dst_depth = plane_depth(EYE), plane_depth(world_from_dst)
    drawn, drawn_depth, hit = splat_view(image, src_depth, K, K, EYE, world_from_dst, (H, W))
    read = reproject(image[None], src_depth[None], dst_depth[None], K, K, EYE, world_from_dst)
    both = hit[0] & read.valid[0, 0].bool()
    both[:2], both[-2:], both[:, :2], both[:, -2:] = False, False, False, False
    assert int(both.sum()) > 0.7 * H * W
    # the nearest point against the exact spot (bilinear on a ramp): within a pixel, half on average
    error = (drawn - read.features[0])[:2, both].abs()
    assert float(error.max()) < 1.0 and float(error.mean()) < 0.4
    torch.testing.assert_close(drawn_depth[0][both], dst_depth[0][both], rtol=2e-2, atol=0)


def test_bad_inputs_are_refused():
    image, depth = torch.rand(3, H, W), torch.rand(1, H, W) + 1.0
    with pytest.raises(InputError, match="image, depth"):
        splat_view(image, depth[:, :5], K, K, EYE, EYE, (H, W))
    with pytest.raises(InputError, match="image, depth"):
        splat_view(image[None], depth, K, K, EYE, EYE, (H, W))
    with pytest.raises(InputError, match="image, depth.*list"):
        splat_view(image, [[1.0]], K, K, EYE, EYE, (H, W))
    with pytest.raises(InputError, match="floating-point"):
        splat_view(image.to(torch.uint8), depth, K, K, EYE, EYE, (H, W))
    with pytest.raises(InputError, match="size"):
        splat_view(image, depth, K, K, EYE, EYE, (0, W))
    with pytest.raises(InputError, match="dst_K"):
        splat_view(image, depth, K, torch.zeros(3, 3), EYE, EYE, (H, W))
