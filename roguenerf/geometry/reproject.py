"""3D alignment: reproject neighbour features into the target view (section 3.3) (STUB)."""

from __future__ import annotations

from dataclasses import dataclass

from torch import Tensor

DEFAULT_LENIENCY = 0.25
DEPTH_EPS = 1e-6


@dataclass
class Reprojection:
    features: Tensor
    """``(B, C, H, W)`` neighbour features sampled at the projected points, times ``valid``."""
    valid: Tensor
    """``(B, 1, H, W)`` float 0/1: finite target depth > eps, z_{k->i} > eps, projection inside the
    neighbour image, neighbour depth known there, and the visibility test passed."""
    depth: Tensor
    """``(B, 1, H, W)`` D_{i->k}: the neighbour's own depth sampled at the projected point
    (0 where not valid)."""
    coords: Tensor
    """``(B, H, W, 2)`` projected pixel coordinates (x, y) in the neighbour image (pixel units,
    centre of pixel (0,0) at (0,0)); 0 where not finite."""


def reproject(
    src_features: Tensor,
    src_depth: Tensor | None,
    dst_depth: Tensor,
    src_K: Tensor,
    dst_K: Tensor,
    world_from_src: Tensor,
    world_from_dst: Tensor,
    *,
    leniency: float = DEFAULT_LENIENCY,
    eps: float = DEPTH_EPS,
) -> Reprojection:
    """Warp ``src`` (neighbour i) features into the ``dst`` (target k) view using target depth.

    x_{k->i} = K_i C_i^{-1} C_k K_k^{-1} [x_k, 1] (C = world_from_cam), bilinear sampling
    with zero padding, vis = H(1 - z_{k->i} / z_i + leniency). Without ``src_depth`` the
    visibility test is skipped (every in-image, in-front point is visible).

    Args:
        src_features: ``(B, C, Hs, Ws)``.
        src_depth: ``(B, 1, Hs, Ws)`` z-depth of the neighbour view, or None.
        dst_depth: ``(B, 1, H, W)`` z-depth of the target view.
        src_K, dst_K: ``(B, 3, 3)`` pixel-centre convention (see package docstring).
        world_from_src, world_from_dst: ``(B, 4, 4)`` OpenCV camera-to-world.
    Returns:
        :class:`Reprojection`. Outputs and gradients are finite for any input depth
        (NaN/inf/zero/negative are treated as missing); invalid K raises InputError.
    """
    raise NotImplementedError
