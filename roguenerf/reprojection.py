"""3D alignment: reproject neighbour features into the target view (section 3.3).

Legend: B batch, C channels, (H, W) target image, (Hs, Ws) neighbour ("src") image.

Built from kornia's ``create_meshgrid``, ``transform_points`` and ``remap`` plus our own
validity mask. This module checks the inputs; :func:`roguenerf.ops.reproject.reproject` holds
the projection, sampling and masking bodies (fused kernel, torch fast path, reference).
``kornia.geometry.depth.warp_frame_depth`` is not used: it takes one K for both views, samples
points behind the camera and fills zero depth from the principal point.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

from roguenerf import ops
from roguenerf.errors import InputError
from roguenerf.geometry.cameras import check_intrinsics, check_pose, pixel_rays, relative_pose
from roguenerf.geometry.depth import DEPTH_EPS, MAX_DEPTH, known_depth_mask  # noqa: F401 (re-exported)
from roguenerf.ops.reproject import known_filled

DEFAULT_LENIENCY = 0.25


@dataclass
class Reprojection:
    features: Tensor
    """``(B, C, H, W)`` neighbour features sampled at the projected points, times ``valid``."""
    valid: Tensor
    """``(B, 1, H, W)`` float 0/1: target depth known (:mod:`roguenerf.geometry.depth`),
    z_{k->i} > eps, projection inside the neighbour image, neighbour depth known there, and the
    visibility test passed."""
    depth: Tensor
    """``(B, 1, H, W)`` D_{i->k}: the neighbour's own depth sampled at the projected point
    (0 where not valid). Without ``src_depth`` it is z_{k->i}, the target point's depth in the
    neighbour camera."""
    coords: Tensor
    """``(B, H, W, 2)`` projected pixel coordinates (x, y) in the neighbour image (pixel units,
    centre of pixel (0,0) at (0,0)); 0 where the point is not finite or not in front of the
    neighbour camera (z_{k->i} <= eps)."""
    packed: Tensor | None = None
    """Fast path only (no gradient, CPU, with ``src_depth``): ``(B, C + 2, H, W)`` channels-last
    buffer of which ``features``, ``depth`` and ``valid`` are the channel views, in that order."""


def _batched(x: Tensor, name: str, trailing: tuple[int, int], batch: int) -> Tensor:
    """``x`` as ``(batch, *trailing)``: a single matrix is shared by the whole batch."""
    if x.ndim == 2:
        x = x.unsqueeze(0)
    if x.ndim != 3 or tuple(x.shape[-2:]) != trailing or x.shape[0] not in (1, batch):
        want = f"({batch}, {trailing[0]}, {trailing[1]}) or ({trailing[0]}, {trailing[1]})"
        raise InputError(f"{name}: expected shape {want}, got {tuple(x.shape)}")
    return x.expand(batch, *trailing)


def _check_image(x, name: str, channels: int | None = None) -> Tensor:
    if not isinstance(x, Tensor) or not x.is_floating_point():
        got = x.dtype if isinstance(x, Tensor) else type(x).__name__
        raise InputError(f"{name}: expected a floating-point tensor, got {got}")
    c = "C" if channels is None else str(channels)
    if x.ndim != 4 or (channels is not None and x.shape[1] != channels) or x.shape[-1] == 0 or x.shape[-2] == 0:
        raise InputError(f"{name}: expected shape (B, {c}, H, W) with H, W >= 1, got {tuple(x.shape)}")
    return x


def sampling_source(src_features: Tensor, src_depth: Tensor | None, *, eps: float = DEPTH_EPS) -> Tensor:
    """What :func:`reproject` samples from the neighbour: ``(B, C [+ 2], Hs, Ws)``.

    The features, then (with ``src_depth``) the known depth (0 where unknown) and the known
    mask (0/1). Channels-last on the CPU when no gradient is recorded: PyTorch's CPU
    ``grid_sample`` is 2-4x faster on that layout, with identical results. It depends only on
    the neighbour, so a caller enhancing many views computes it once per neighbour and passes
    it to :func:`reproject` as ``source``.
    """
    _check_image(src_features, "src_features")
    dtype = torch.float64 if src_features.dtype == torch.float64 else torch.float32
    stack = [src_features.to(dtype)]
    if src_depth is not None:
        _check_image(src_depth, "src_depth", 1)
        src_known, src_z = known_filled(src_depth.to(dtype), eps)
        stack += [torch.where(src_known, src_z, 0.0), src_known.to(dtype)]
    return ops.pack_channels(stack, like=src_features)


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
    source: Tensor | None = None,
    validated: bool = False,
) -> Reprojection:
    """Warp ``src`` (neighbour i) features into the ``dst`` (target k) view using target depth.

    x_{k->i} = K_i C_i^{-1} C_k K_k^{-1} [x_k, 1] (C = world_from_cam), bilinear sampling,
    vis = H(1 - z_{k->i} / z_i + leniency). Without ``src_depth`` the visibility test is
    skipped (every in-image, in-front point is visible).

    "Inside the neighbour image" means inside its pixel area: x in [-0.5, Ws - 0.5],
    y in [-0.5, Hs - 0.5] (pixel centres at integers); in the outer half pixel the edge pixel
    is repeated rather than blended with zeros. Everything outside is invalid and 0. The
    neighbour depth z_i is the bilinear mean over the known neighbour pixels and counts as
    known where they carry at least half of the bilinear weight. Depth is known where
    :func:`~roguenerf.geometry.depth.known_depth_mask` says so (finite, ``eps < z < MAX_DEPTH``).
    The relative pose C_i^-1 C_k is formed in float64 from the poses as given and only then
    cast to the features' dtype: pass float64 poses when the cameras are far from the origin
    (UTM / ECEF coordinates, 1e6 units), since float32 cannot even store such positions.

    Args:
        src_features: ``(B, C, Hs, Ws)``.
        src_depth: ``(B, 1, Hs, Ws)`` z-depth of the neighbour view, or None.
        dst_depth: ``(B, 1, H, W)`` z-depth of the target view.
        src_K, dst_K: ``(B, 3, 3)`` or ``(3, 3)``, pixel-centre convention (see package docstring).
        world_from_src, world_from_dst: ``(B, 4, 4)`` or ``(4, 4)`` OpenCV camera-to-world.
        source: :func:`sampling_source` of ``src_features`` and ``src_depth`` when the caller
            has it already (it is then not rebuilt; it must match them).
        validated: the intrinsics and poses have been through
            :func:`~roguenerf.geometry.cameras.check_intrinsics` / :func:`~roguenerf.geometry.cameras.check_pose`
            already (the enhancer checks all its neighbours at once): they are not checked again.
    Returns:
        :class:`Reprojection`. Outputs and gradients are finite for any input depth
        (NaN/inf/zero/negative are treated as missing); invalid K or poses raise InputError.
    """
    B, C, Hs, Ws = _check_images(src_features, src_depth, dst_depth)
    if not (leniency == leniency and abs(leniency) != float("inf")):
        raise InputError(f"leniency: expected a finite number, got {leniency}")
    if not eps > 0:
        raise InputError(f"eps: expected eps > 0, got {eps}")
    dtype = torch.float64 if src_features.dtype == torch.float64 else torch.float32
    if not validated:
        src_K, dst_K = check_intrinsics(src_K, "src_K"), check_intrinsics(dst_K, "dst_K")
        world_from_src = check_pose(world_from_src, "world_from_src")
        world_from_dst = check_pose(world_from_dst, "world_from_dst")
    device = src_features.device
    src_K = _batched(src_K, "src_K", (3, 3), B).to(device, dtype)
    dst_K = _batched(dst_K, "dst_K", (3, 3), B).to(device, dtype)
    world_from_src = _batched(world_from_src, "world_from_src", (4, 4), B)
    world_from_dst = _batched(world_from_dst, "world_from_dst", (4, 4), B)
    # float64 here: with both cameras 5e6 units from the origin, float32 would lose the geometry.
    src_from_dst64 = relative_pose(world_from_src, world_from_dst).to(device)
    if source is None:
        source = sampling_source(src_features, src_depth, eps=eps)
    else:
        want = (B, C + (2 if src_depth is not None else 0), Hs, Ws)
        if tuple(source.shape) != want:
            raise InputError(f"source: expected shape {want} (sampling_source of the neighbour), "
                             f"got {tuple(source.shape)}")
        source = source.to(dtype)
    features, valid, depth, coords, packed = ops.reproject(
        dst_depth, source, src_from_dst64, src_K, dst_K, channels=C, with_depth=src_depth is not None,
        out_dtype=src_features.dtype, eps=eps, leniency=leniency)
    return Reprojection(features=features, valid=valid, depth=depth, coords=coords, packed=packed)


def sample_at(images: Tensor, coords: Tensor, *, mode: str = "bilinear") -> Tensor:
    """``images`` ``(B, C, Hs, Ws)`` sampled at ``coords`` ``(B, H, W, 2)`` (pixel units, centres
    at integers: :attr:`Reprojection.coords`), the edge pixel repeated beyond the centres (as
    :func:`reproject` samples inside the image's pixel area); ``mode`` ``bilinear`` (what
    :func:`reproject` gives) or ``bicubic``. ``(B, C, H, W)``, to be read where the reprojection
    is valid."""
    h, w = images.shape[-2:]
    grid = torch.stack([(coords[..., 0] + 0.5) / w * 2 - 1, (coords[..., 1] + 0.5) / h * 2 - 1], dim=-1)
    return F.grid_sample(images, grid.to(images.dtype), mode=mode, padding_mode="border", align_corners=False)


def _check_images(src_features: Tensor, src_depth: Tensor | None, dst_depth: Tensor) -> tuple[int, int, int, int]:
    """The image arguments of :func:`reproject` checked: ``(B, C, Hs, Ws)`` of ``src_features``."""
    _check_image(src_features, "src_features")
    _check_image(dst_depth, "dst_depth", 1)
    B, C, Hs, Ws = src_features.shape
    if dst_depth.shape[0] != B:
        raise InputError(f"dst_depth: expected batch size {B} (as src_features), got {dst_depth.shape[0]}")
    if src_depth is not None:
        _check_image(src_depth, "src_depth", 1)
        if tuple(src_depth.shape) != (B, 1, Hs, Ws):
            got = tuple(src_depth.shape)
            raise InputError(f"src_depth: expected shape {(B, 1, Hs, Ws)} (as src_features), got {got}")
    return B, C, Hs, Ws


SPLAT_SURFACE = 0.01
"""Relative depth within which two points landing on one pixel count as the same surface in
:func:`splat_view`: the one nearer the pixel's centre is drawn, not the one a hair nearer the
camera."""


def splat_view(image: Tensor, depth: Tensor, src_K: Tensor, dst_K: Tensor, world_from_src: Tensor,
               world_from_dst: Tensor, size: tuple[int, int], *, eps: float = DEPTH_EPS,
               surface: float = SPLAT_SURFACE) -> tuple[Tensor, Tensor, Tensor]:
    """Draw one view's image into another camera through its own depth (a forward warp).

    Each source pixel with known z-depth becomes a 3D point (through its pixel centre, float64);
    seen from the destination camera it is drawn into the 2 x 2 pixels around where it lands
    (so a view a little nearer the scene shows no cracks; a point exactly on a pixel centre
    draws that pixel alone). Of the points on one pixel the nearest surface wins (a z-buffer);
    within ``surface`` relative depth of the nearest, the point nearest the pixel's centre
    (then the higher source index). Unlike :func:`reproject`,
    which reads the source through the *destination's* depth, what sits in front in the source
    view stays in front: a field's floaters, painted to look right from its own camera, land
    where a new camera would see them.

    Args:
        image: ``(C, Hs, Ws)``; depth ``(1, Hs, Ws)`` its z-depth (unknown: NaN, inf, <= eps).
        src_K, dst_K: ``(3, 3)`` pixel-centre convention; world_from_src, world_from_dst ``(4, 4)``
            OpenCV camera-to-world.
        size: ``(H, W)`` of the destination.
    Returns:
        ``image`` ``(C, H, W)`` (0 where no point lands), ``depth`` ``(1, H, W)`` z-depth in the
        destination camera (0 there), ``hit`` ``(1, H, W)`` bool.
    """
    if (not isinstance(image, Tensor) or not isinstance(depth, Tensor) or image.ndim != 3
            or tuple(depth.shape) != (1, *image.shape[1:])):
        def shape(x) -> str:
            return str(tuple(x.shape)) if isinstance(x, Tensor) else type(x).__name__

        raise InputError(f"image, depth: expected (C, Hs, Ws) and (1, Hs, Ws) tensors, got {shape(image)} "
                         f"and {shape(depth)}")
    _check_image(image[None], "image")
    _check_image(depth[None], "depth", 1)
    h, w = (int(x) for x in size)
    if h < 1 or w < 1:
        raise InputError(f"size: expected a positive (H, W), got {size}")
    src_K = check_intrinsics(src_K, "src_K").to(torch.float64)
    dst_K = check_intrinsics(dst_K, "dst_K").to(torch.float64)
    dst_from_src = relative_pose(check_pose(world_from_dst, "world_from_dst"),
                                 check_pose(world_from_src, "world_from_src"))
    c, hs, ws = image.shape
    z = depth.reshape(-1).to(torch.float64)
    known = known_depth_mask(z, eps=eps)
    pts = pixel_rays(src_K, (hs, ws)).reshape(-1, 3).T * torch.where(known, z, 1.0)
    pts = dst_from_src[:3, :3] @ pts + dst_from_src[:3, 3:]
    uvw = dst_K @ pts
    z_dst = pts[2]
    front = known & (z_dst > eps) & torch.isfinite(uvw).all(dim=0)
    x = uvw[0] / torch.where(front, z_dst, 1.0) - 0.5  # pixel centres at integers
    y = uvw[1] / torch.where(front, z_dst, 1.0) - 0.5
    source = torch.nonzero(front).squeeze(1)
    x, y, z_dst = x[source], y[source], z_dst[source]
    x0, y0 = torch.floor(x), torch.floor(y)
    cand_x = torch.cat([x0, x0 + 1, x0, x0 + 1])
    cand_y = torch.cat([y0, y0, y0 + 1, y0 + 1])
    cand_z = z_dst.repeat(4)
    cand_src = source.repeat(4)
    dx, dy = (cand_x - x.repeat(4)).abs(), (cand_y - y.repeat(4)).abs()
    near = dx ** 2 + dy ** 2
    # a point on a pixel centre (to float64 rounding) draws only that pixel
    reach = 1.0 - 1e-9
    inside = (cand_x >= 0) & (cand_x <= w - 1) & (cand_y >= 0) & (cand_y <= h - 1) & (dx < reach) & (dy < reach)
    cand_x, cand_y, cand_z, cand_src, near = (t[inside] for t in (cand_x, cand_y, cand_z, cand_src, near))
    index = (cand_y * w + cand_x).long()
    nearest = torch.full((h * w,), torch.inf, dtype=torch.float64).scatter_reduce(0, index, cand_z, "amin")
    front_surface = cand_z <= nearest[index] * (1.0 + surface)
    index, cand_src, near = index[front_surface], cand_src[front_surface], near[front_surface]
    closest = torch.full((h * w,), torch.inf, dtype=torch.float64).scatter_reduce(0, index, near, "amin")
    best = near <= closest[index]
    owner = torch.full((h * w,), -1, dtype=torch.int64).scatter_reduce(0, index[best], cand_src[best], "amax")
    hit = owner >= 0
    taken = owner.clamp(min=0)
    out = image.reshape(c, -1)[:, taken] * hit.to(image.dtype)
    # the owner's own depth in the destination camera (the same point may land on several pixels)
    z_of = torch.zeros(hs * ws, dtype=torch.float64)
    z_of[source] = z_dst
    out_depth = torch.where(hit, z_of[taken], 0.0).to(depth.dtype)
    return out.reshape(c, h, w), out_depth.reshape(1, h, w), hit.reshape(1, h, w)
