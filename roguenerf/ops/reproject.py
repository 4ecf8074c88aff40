"""Reprojection and sampling, each with its bodies: the fused C kernel (one pass), the torch fast
path (composed projection, gather sampling, masking in place) and the plain reference.

:func:`roguenerf.reprojection.reproject` checks its inputs and calls :func:`reproject`.
Legend: B batch, C feature channels, Cs channels of the sampling source, (H, W) target size,
(Hs, Ws) neighbour size.
"""

from __future__ import annotations

import functools

import torch
from torch import Tensor

from roguenerf import native
from roguenerf.geometry.depth import MAX_DEPTH, known_depth_mask
from roguenerf.geometry.sampling import bilinear_sample
from roguenerf.ops.backend import Body, as_channels_last, as_contiguous, pick


def known_filled(depth: Tensor, eps: float) -> tuple[Tensor, Tensor]:
    """Mask of known depth (:func:`~roguenerf.geometry.depth.known_depth_mask`) and the depth
    with every unknown entry replaced by 1.

    Replacing (rather than masking afterwards) keeps NaN/inf out of every later division,
    so their gradients stay finite.
    """
    known = known_depth_mask(depth, eps=eps)
    return known, torch.where(known, torch.nan_to_num(depth, nan=1.0, posinf=1.0, neginf=1.0), 1.0)


def pack_channels(stack: list[Tensor], like: Tensor) -> Tensor:
    """``stack`` concatenated along channels: into one channels-last buffer on the fast path
    (PyTorch's CPU ``grid_sample`` is 2-4x faster on that layout, same values), else plainly."""
    if pick(like).fast:
        b, _, h, w = stack[0].shape
        out = torch.empty(b, sum(t.shape[1] for t in stack), h, w, dtype=stack[0].dtype, device=stack[0].device,
                          memory_format=torch.channels_last)
        return torch.cat(stack, dim=1, out=out)
    return torch.cat(stack, dim=1)


def sample(source: Tensor, x: Tensor, y: Tensor, *, padding: str = "border") -> Tensor:
    """``source`` ``(B, Cs, Hs, Ws)`` sampled bilinearly at pixel coordinates ``x``, ``y``
    ``(B, H, W)`` (pixel centres at integers): gather sampling, channels-last, on the fast
    path; kornia's ``remap`` (``grid_sample``, align_corners=True) otherwise."""
    if pick(source).fast:
        return bilinear_sample(source, x, y, padding=padding)
    from kornia.geometry.transform import remap  # not imported on the fast path (0.3 s of start-up)

    return remap(source, x, y, mode="bilinear", padding_mode=padding, align_corners=True)


# --- the projection: target pixels into the neighbour ---------------------------------------

def _pixel_centres(h: int, w: int, device, dtype) -> Tensor:
    """``(1, H, W, 3)`` homogeneous pixel centres ``(u + 0.5, v + 0.5, 1)``, cached per size (read-only)."""
    with torch.inference_mode(False), torch.no_grad():
        return _make_pixel_centres(h, w, str(device), dtype)


@functools.lru_cache(maxsize=16)
def _make_pixel_centres(h: int, w: int, device: str, dtype) -> Tensor:
    from kornia.geometry.grid import create_meshgrid

    pix = create_meshgrid(h, w, normalized_coordinates=False, device=device, dtype=dtype) + 0.5
    return torch.cat([pix, torch.ones_like(pix[..., :1])], dim=-1)


def project_reference(dst_depth: Tensor, src_from_dst: Tensor, src_K: Tensor, dst_K: Tensor,
                      src_size: tuple[int, int], eps: float, dtype) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Target pixels into the neighbour: ``valid`` ``(B, H, W)`` bool (known target depth, in
    front, inside), ``coords`` ``(B, H, W, 2)``, ``sample_at`` (coords, 0 where not valid) and
    ``z_proj`` ``(B, H, W)`` (1 where not in front)."""
    from kornia.geometry.linalg import transform_points

    B, H, W = dst_depth.shape[0], *dst_depth.shape[-2:]
    Hs, Ws = src_size
    device = dst_depth.device
    dst_known, z = known_filled(dst_depth.to(dtype), eps)
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


def projection_terms(src_from_dst: Tensor, src_K: Tensor, dst_K: Tensor,
                     size: tuple[int, int]) -> tuple[Tensor, Tensor, Tensor]:
    """The pinhole chain of :func:`project_fast`, composed in float64 from float64 ``(B, 4, 4)``
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


def project_fast(dst_depth: Tensor, src_from_dst: Tensor, src_K: Tensor, dst_K: Tensor,
                 src_size: tuple[int, int], eps: float) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """:func:`project_reference` in fewer passes over the image (fast path: float32, no gradient).

    The pinhole chain is linear in the target pixel for a fixed depth, so it is composed once
    per batch item in float64: ``x_num = z * (K_i R K_k^-1)_0 . [u, v, 1] + (K_i t)_0`` (and
    y, and ``z_proj`` with ``R K_k^-1``); each map is then a few broadcast operations of a
    per-row and a per-column term, with no ``(B, H, W, 3)`` intermediates. Same function, to
    float32 rounding of the coordinates (the plain path rounds each factor to float32 instead).
    """
    Hs, Ws = src_size
    dst_known, z = known_filled(dst_depth, eps)
    z = z[:, 0]
    rows, cols, c = projection_terms(src_from_dst, src_K, dst_K, tuple(dst_depth.shape[-2:]))

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


# --- the whole reprojection ------------------------------------------------------------------

Result = tuple[Tensor, Tensor, Tensor, Tensor, Tensor | None]
"""features ``(B, C, H, W)``, valid ``(B, 1, H, W)``, depth ``(B, 1, H, W)``, coords
``(B, H, W, 2)`` and, on the fast paths, the packed channels-last buffer the first three are
channel views of (else None)."""


def reproject(dst_depth: Tensor, source: Tensor, src_from_dst64: Tensor, src_K: Tensor, dst_K: Tensor, *,
              channels: int, with_depth: bool, out_dtype, eps: float, leniency: float) -> Result:
    """One neighbour's :func:`sampling_source <roguenerf.geometry.sampling_source>` ``source``
    ``(B, Cs, Hs, Ws)`` (``channels`` features, then with ``with_depth`` its known depth and
    mask) into the target view of depth ``dst_depth`` ``(B, 1, H, W)``; ``src_from_dst64``
    ``(B, 4, 4)`` float64, ``src_K``, ``dst_K`` ``(B, 3, 3)`` in the source's dtype. The fused
    kernel where :func:`~roguenerf.ops.backend.pick` says NATIVE (with depth, float32),
    else the torch projection (fast or reference), :func:`sample` and the masking."""
    dtype = source.dtype
    if (with_depth and dtype == torch.float32 and out_dtype == torch.float32
            and pick(dst_depth, source) is Body.NATIVE):
        return _reproject_native(dst_depth, source, src_from_dst64, src_K, dst_K, channels, eps, leniency)
    size = tuple(source.shape[-2:])
    if pick(dst_depth).fast and dtype == torch.float32:
        valid, coords, sample_at, z_proj = project_fast(
            dst_depth, src_from_dst64, src_K.to(torch.float64), dst_K.to(torch.float64), size, eps)
    else:
        valid, coords, sample_at, z_proj = project_reference(
            dst_depth, src_from_dst64.to(dtype), src_K, dst_K, size, eps, dtype)
    # align_corners=True: kornia normalises pixel maps as "centre of pixel 0 at -1"; border
    # padding only matters in the outer half pixel, everything further out is invalid.
    sampled = sample(source, sample_at[..., 0], sample_at[..., 1], padding="border")
    return _mask(sampled, valid, coords, z_proj, channels, with_depth, out_dtype, leniency)


def _reproject_native(dst_depth: Tensor, source: Tensor, src_from_dst64: Tensor, src_K: Tensor, dst_K: Tensor,
                      channels: int, eps: float, leniency: float) -> Result:
    """One fused pass: projection, sampling, visibility and masking (same operations)."""
    rows, cols, offset = projection_terms(src_from_dst64, src_K.to(torch.float64), dst_K.to(torch.float64),
                                          tuple(dst_depth.shape[-2:]))
    packed, coords = native.reproject(as_contiguous(dst_depth), as_contiguous(rows), as_contiguous(cols),
                                      as_contiguous(offset), as_channels_last(source), eps=eps, max_depth=MAX_DEPTH,
                                      leniency=leniency)
    c = channels
    return packed[:, :c], packed[:, c + 1:], packed[:, c:c + 1], coords, packed


def _mask(sampled: Tensor, valid: Tensor, coords: Tensor, z_proj: Tensor, c: int, with_depth: bool, out_dtype,
          leniency: float) -> Result:
    """The visibility test (with the neighbour's depth) and the masking of the sampled channels."""
    features = sampled[:, :c]
    if with_depth:
        weight = sampled[:, c + 1]
        src_seen = weight >= 0.5
        z_i = sampled[:, c] / torch.where(src_seen, weight, 1.0)
        visible = z_proj <= (1.0 + leniency) * z_i
        valid = valid & src_seen & visible
        depth = z_i
    else:
        depth = z_proj
    valid = valid[:, None]
    if (with_depth and sampled.is_contiguous(memory_format=torch.channels_last) and sampled.dtype == out_dtype
            and pick(sampled).fast):
        # Fast path: mask in place, keeping features, depth and mask in the one channels-last
        # buffer that the enhancer's next stages read whole (no concatenation copies).
        features.masked_fill_(~valid, 0.0)
        sampled[:, c:c + 1] = torch.where(valid, depth[:, None], 0.0)
        sampled[:, c + 1:] = valid
        return features, sampled[:, c + 1:], sampled[:, c:c + 1], coords.to(out_dtype), sampled
    return (torch.where(valid, features, 0.0).to(out_dtype), valid.to(out_dtype),
            torch.where(valid, depth[:, None], 0.0).to(out_dtype), coords.to(out_dtype), None)
