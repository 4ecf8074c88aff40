"""3D alignment: reproject neighbour features into the target view (section 3.3).

Legend: B batch, C channels, (H, W) target image, (Hs, Ws) neighbour ("src") image.

Built from kornia's ``create_meshgrid``, ``transform_points`` and ``remap`` plus our own
validity mask. ``kornia.geometry.depth.warp_frame_depth`` is not used: it takes one K for
both views, samples points behind the camera and fills zero depth from the principal point.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import torch
from kornia.geometry.grid import create_meshgrid
from kornia.geometry.linalg import transform_points
from kornia.geometry.transform import remap
from torch import Tensor

from roguenerf import native
from roguenerf.errors import InputError
from roguenerf.fastpath import fast_enabled, in_previous_fast_path
from roguenerf.geometry.cameras import check_intrinsics, check_pose, relative_pose
from roguenerf.geometry.depth import DEPTH_EPS, MAX_DEPTH, known_depth_mask  # noqa: F401 (re-exported)
from roguenerf.geometry.sampling import bilinear_sample

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


def _pixel_centres(h: int, w: int, device, dtype) -> Tensor:
    """``(1, H, W, 3)`` homogeneous pixel centres ``(u + 0.5, v + 0.5, 1)``, cached per size (read-only)."""
    with torch.inference_mode(False), torch.no_grad():
        return _make_pixel_centres(h, w, str(device), dtype)


@functools.lru_cache(maxsize=16)
def _make_pixel_centres(h: int, w: int, device: str, dtype) -> Tensor:
    pix = create_meshgrid(h, w, normalized_coordinates=False, device=device, dtype=dtype) + 0.5
    return torch.cat([pix, torch.ones_like(pix[..., :1])], dim=-1)


def _known(depth: Tensor, eps: float) -> tuple[Tensor, Tensor]:
    """Mask of known depth (:func:`~roguenerf.geometry.depth.known_depth_mask`) and the depth
    with every unknown entry replaced by 1.

    Replacing (rather than masking afterwards) keeps NaN/inf out of every later division,
    so their gradients stay finite.
    """
    known = known_depth_mask(depth, eps=eps)
    return known, torch.where(known, torch.nan_to_num(depth, nan=1.0, posinf=1.0, neginf=1.0), 1.0)


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
        src_known, src_z = _known(src_depth.to(dtype), eps)
        stack += [torch.where(src_known, src_z, 0.0), src_known.to(dtype)]
    if fast_enabled(src_features):
        b, _, h, w = src_features.shape
        out = torch.empty(b, sum(t.shape[1] for t in stack), h, w, dtype=dtype, device=src_features.device,
                          memory_format=torch.channels_last)
        return torch.cat(stack, dim=1, out=out)
    return torch.cat(stack, dim=1)


def _project(dst_depth: Tensor, src_from_dst: Tensor, src_K: Tensor, dst_K: Tensor, src_size: tuple[int, int],
             eps: float, dtype) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Target pixels into the neighbour: ``valid`` ``(B, H, W)`` bool (known target depth, in
    front, inside), ``coords`` ``(B, H, W, 2)``, ``sample_at`` (coords, 0 where not valid) and
    ``z_proj`` ``(B, H, W)`` (1 where not in front)."""
    B, H, W = dst_depth.shape[0], *dst_depth.shape[-2:]
    Hs, Ws = src_size
    device = dst_depth.device
    dst_known, z = _known(dst_depth.to(dtype), eps)
    # The pinhole maths with K is plain torch: kornia's (un)project helpers ignore K's skew
    # and put pixel centres at integers (ours are at +0.5).
    pix_h = _pixel_centres(H, W, device, dtype)  # (1, H, W, 3)
    rays = torch.einsum("bij,bhwj->bhwi", torch.linalg.inv(dst_K), pix_h.expand(B, -1, -1, -1))
    pts_dst = rays * z[:, 0, :, :, None]  # (B, H, W, 3)
    pts_src = transform_points(src_from_dst, pts_dst.reshape(B, H * W, 3)).reshape(B, H, W, 3)

    uvw = torch.einsum("bij,bhwj->bhwi", src_K, pts_src)
    z_proj = pts_src[..., 2]
    in_front = torch.isfinite(uvw).all(dim=-1) & (z_proj > eps)
    # Sanitise before dividing, so NaN/inf never meet a zero gradient (0 * inf = NaN).
    uvw = torch.where(in_front[..., None], uvw, 0.0)
    z_proj = torch.where(in_front, z_proj, 1.0)
    coords = uvw[..., :2] / z_proj[..., None] - 0.5  # (B, H, W, 2), pixel centres at integers
    x, y = coords.unbind(-1)
    inside = (x >= -0.5) & (x <= Ws - 0.5) & (y >= -0.5) & (y <= Hs - 0.5)
    valid = dst_known[:, 0] & in_front & inside
    coords = torch.where(in_front[..., None], coords, 0.0)
    sample_at = torch.where(valid[..., None], coords, 0.0)
    return valid, coords, sample_at, z_proj


def _projection_terms(src_from_dst: Tensor, src_K: Tensor, dst_K: Tensor,
                      size: tuple[int, int]) -> tuple[Tensor, Tensor, Tensor]:
    """The pinhole chain of :func:`_project_fast`, composed in float64 from float64 ``(B, 4, 4)``
    and ``(B, 3, 3)`` matrices: float32 per-row ``(B, 3, H)`` and per-column ``(B, 3, W)`` terms
    and the offset ``(B, 3)``, so that for (x numerator, y numerator, z) at pixel (u, v) with
    depth z: ``(rows[:, i, v] + cols[:, i, u]) * z + offset[:, i]``."""
    H, W = size
    device = src_from_dst.device
    rot, trans = src_from_dst[:, :3, :3], src_from_dst[:, :3, 3]
    ray = rot @ torch.linalg.inv(dst_K)  # (B, 3, 3): point in the neighbour camera per unit depth
    M = torch.cat([src_K[:, :2] @ ray, ray[:, 2:]], dim=1)  # rows: x numerator, y numerator, z
    c = torch.cat([(src_K[:, :2] @ trans[..., None])[..., 0], trans[:, 2:]], dim=1)  # (B, 3)
    u = torch.arange(W, device=device, dtype=torch.float64) + 0.5
    v = torch.arange(H, device=device, dtype=torch.float64) + 0.5
    cols = (M[:, :, 0, None] * u).to(torch.float32)  # (B, 3, W)
    rows = (M[:, :, 1, None] * v + M[:, :, 2, None]).to(torch.float32)  # (B, 3, H)
    return rows, cols, c.to(torch.float32)


def _project_fast(dst_depth: Tensor, src_from_dst: Tensor, src_K: Tensor, dst_K: Tensor,
                  src_size: tuple[int, int], eps: float) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """:func:`_project` in fewer passes over the image (fast path: float32, no gradient).

    The pinhole chain is linear in the target pixel for a fixed depth, so it is composed once
    per batch item in float64: ``x_num = z * (K_i R K_k^-1)_0 . [u, v, 1] + (K_i t)_0`` (and
    y, and ``z_proj`` with ``R K_k^-1``); each map is then a few broadcast operations of a
    per-row and a per-column term, with no ``(B, H, W, 3)`` intermediates. Same function, to
    float32 rounding of the coordinates (the plain path rounds each factor to float32 instead).
    """
    Hs, Ws = src_size
    dst_known, z = _known(dst_depth, eps)
    z = z[:, 0]
    rows, cols, c = _projection_terms(src_from_dst, src_K, dst_K, tuple(dst_depth.shape[-2:]))

    def along(i: int) -> Tensor:  # z * (M_i . [u, v, 1]) + c_i, (B, H, W)
        return torch.add(rows[:, i, :, None], cols[:, i, None, :]).mul_(z).add_(c[:, i, None, None])

    z_proj = along(2)
    x, y = along(0), along(1)
    in_front = torch.isfinite(x) & torch.isfinite(y) & torch.isfinite(z_proj) & (z_proj > eps)
    z_proj = torch.where(in_front, z_proj, 1.0)
    x = torch.where(in_front, x, 0.0).div_(z_proj).sub_(0.5)
    y = torch.where(in_front, y, 0.0).div_(z_proj).sub_(0.5)
    inside = (x >= -0.5) & (x <= Ws - 0.5) & (y >= -0.5) & (y <= Hs - 0.5)
    valid = dst_known[:, 0] & in_front & inside
    x = torch.where(in_front, x, 0.0)
    y = torch.where(in_front, y, 0.0)
    coords = torch.stack([x, y], dim=-1)
    sample_at = torch.stack([torch.where(valid, x, 0.0), torch.where(valid, y, 0.0)], dim=-1)
    return valid, coords, sample_at, z_proj


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
    _check_image(src_features, "src_features")
    _check_image(dst_depth, "dst_depth", 1)
    B, C, Hs, Ws = src_features.shape
    H, W = dst_depth.shape[-2:]
    if dst_depth.shape[0] != B:
        raise InputError(f"dst_depth: expected batch size {B} (as src_features), got {dst_depth.shape[0]}")
    if src_depth is not None:
        _check_image(src_depth, "src_depth", 1)
        if tuple(src_depth.shape) != (B, 1, Hs, Ws):
            got = tuple(src_depth.shape)
            raise InputError(f"src_depth: expected shape {(B, 1, Hs, Ws)} (as src_features), got {got}")
    if not (leniency == leniency and abs(leniency) != float("inf")):
        raise InputError(f"leniency: expected a finite number, got {leniency}")
    if not eps > 0:
        raise InputError(f"eps: expected eps > 0, got {eps}")
    dtype = torch.float64 if src_features.dtype == torch.float64 else torch.float32
    device = src_features.device

    if not validated:
        src_K, dst_K = check_intrinsics(src_K, "src_K"), check_intrinsics(dst_K, "dst_K")
        world_from_src = check_pose(world_from_src, "world_from_src")
        world_from_dst = check_pose(world_from_dst, "world_from_dst")
    src_K = _batched(src_K, "src_K", (3, 3), B).to(device, dtype)
    dst_K = _batched(dst_K, "dst_K", (3, 3), B).to(device, dtype)
    world_from_src = _batched(world_from_src, "world_from_src", (4, 4), B)
    world_from_dst = _batched(world_from_dst, "world_from_dst", (4, 4), B)
    # float64 here: with both cameras 5e6 units from the origin, float32 would lose the geometry.
    src_from_dst64 = relative_pose(world_from_src, world_from_dst).to(device)
    src_from_dst = src_from_dst64.to(dtype)

    if source is None:
        source = sampling_source(src_features, src_depth, eps=eps)
    else:
        want = (B, C + (2 if src_depth is not None else 0), Hs, Ws)
        if tuple(source.shape) != want:
            raise InputError(f"source: expected shape {want} (sampling_source of the neighbour), "
                             f"got {tuple(source.shape)}")
        source = source.to(dtype)
    if (src_depth is not None and dtype == torch.float32 and src_features.dtype == torch.float32
            and native.enabled(dst_depth) and native.enabled(source)):
        # One fused pass: projection, sampling, visibility and masking (same operations).
        rows, cols, offset = _projection_terms(src_from_dst64, src_K.to(torch.float64),
                                               dst_K.to(torch.float64), (H, W))
        packed, coords = native.reproject(dst_depth, rows, cols, offset, source, eps=eps, max_depth=MAX_DEPTH,
                                          leniency=leniency)
        return Reprojection(features=packed[:, :C], valid=packed[:, C + 1:], depth=packed[:, C:C + 1],
                            coords=coords, packed=packed)
    if fast_enabled(dst_depth) and dtype == torch.float32 and not in_previous_fast_path():
        valid, coords, sample_at, z_proj = _project_fast(
            dst_depth, src_from_dst64,
            src_K.to(torch.float64), dst_K.to(torch.float64), (Hs, Ws), eps)
    else:
        valid, coords, sample_at, z_proj = _project(dst_depth, src_from_dst, src_K, dst_K, (Hs, Ws), eps, dtype)
    # align_corners=True: kornia normalises pixel maps as "centre of pixel 0 at -1"; border
    # padding only matters in the outer half pixel, everything further out is invalid.
    if fast_enabled(source):
        sampled = bilinear_sample(source, sample_at[..., 0], sample_at[..., 1], padding="border")
    else:
        sampled = remap(
            source,
            sample_at[..., 0],
            sample_at[..., 1],
            mode="bilinear",
            padding_mode="border",
            align_corners=True,
        )
    features = sampled[:, :C]
    if src_depth is not None:
        weight = sampled[:, C + 1]
        src_seen = weight >= 0.5
        z_i = sampled[:, C] / torch.where(src_seen, weight, 1.0)
        visible = z_proj <= (1.0 + leniency) * z_i
        valid = valid & src_seen & visible
        depth = z_i
    else:
        depth = z_proj
    valid = valid[:, None]
    if src_depth is not None and sampled.is_contiguous(memory_format=torch.channels_last) \
            and sampled.dtype == src_features.dtype and fast_enabled(sampled):
        # Fast path: mask in place, keeping features, depth and mask in the one channels-last
        # buffer that the enhancer's next stages read whole (no concatenation copies).
        features.masked_fill_(~valid, 0.0)
        sampled[:, C:C + 1] = torch.where(valid, depth[:, None], 0.0)
        sampled[:, C + 1:] = valid
        return Reprojection(features=features, valid=sampled[:, C + 1:], depth=sampled[:, C:C + 1],
                            coords=coords.to(src_features.dtype), packed=sampled)
    return Reprojection(
        features=torch.where(valid, features, 0.0).to(src_features.dtype),
        valid=valid.to(src_features.dtype),
        depth=torch.where(valid, depth[:, None], 0.0).to(src_features.dtype),
        coords=coords.to(src_features.dtype),
    )
