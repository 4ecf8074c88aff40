"""Enhance large images in overlapping tiles with bounded memory and no visible seams.

Each tile gets the crop of the target render and depth and the target intrinsics with the
principal point shifted by the tile offset; the neighbours stay whole (their features are
reprojected into the tile's camera). Tile offsets are multiples of the model's
``tile_alignment`` where the tile size allows, so the flow network's 1/8 pooling grid and the
Uformer's padding / window grid match those of the whole image. The scene scale (median
target depth) is computed once on the whole image and passed to every tile.

Blending: along each axis, inside the overlap of two neighbouring tiles, a tile's weight is 1
for the first quarter of the overlap (seen from its own interior), falls as a half cosine
over the middle half and is 0 in the quarter nearest its own border, where the tile lacks
context. The two weights sum to 1; 2-D weights are products. A pixel that both tiles see at
least ``overlap / 4`` away from their borders is therefore reproduced exactly whenever the
model's receptive field is under ``overlap / 4`` (see tests/unit/roguenerf/models/test_tiling.py).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from roguenerf.errors import InputError


def tile_starts(size: int, tile: int, overlap: int, align: int = 1) -> list[int]:
    """Start offsets of the tiles along one axis; tile j covers ``[s_j, min(s_j + tile, size))``.

    The stride is ``tile - overlap`` rounded down to a multiple of ``align`` (falling back to
    smaller alignments 8 and 1 when that leaves nothing), and the last tile reaches ``size``.
    """
    if size <= tile:
        return [0]
    stride = 0
    for a in (align, 8, 1):
        stride = (tile - overlap) // a * a
        if stride > 0:
            break
    starts = [0]
    while starts[-1] + tile < size:
        starts.append(starts[-1] + stride)
    return starts


def _ramp(n: int, device, dtype) -> Tensor:
    """``(n,)`` weights for an overlap of n pixels, from 1 (own interior) to 0 (own border)."""
    t = (torch.arange(n, device=device, dtype=torch.float64) + 0.5) / n
    # 1 on [0, 1/4), half cosine over [1/4, 3/4), 0 on [3/4, 1].
    u = ((t - 0.25) * 2).clamp(0, 1)
    return (0.5 * (1 + torch.cos(math.pi * u))).to(dtype)


def axis_weights(starts: list[int], tile: int, size: int, device, dtype) -> list[Tensor]:
    """Per tile, ``(length,)`` blending weights along one axis (see the module docstring)."""
    ends = [min(s + tile, size) for s in starts]
    weights = []
    for j, (s, e) in enumerate(zip(starts, ends)):
        wgt = torch.ones(e - s, device=device, dtype=dtype)
        if j + 1 < len(starts):
            o = e - starts[j + 1]
            wgt[e - s - o:] *= _ramp(o, device, dtype)
        if j > 0:
            o = ends[j - 1] - s
            wgt[:o] *= _ramp(o, device, dtype).flip(0)
        weights.append(wgt)
    return weights


def enhance_tiled(model, render: Tensor, depth: Tensor, K: Tensor, world_from_cam: Tensor, neighbours,
                  *, tile: int = 256, overlap: int = 32, progress=None) -> Tensor:
    """Enhance ``render`` tile by tile (same result shape as ``model(render, depth, K, ...)``).

    Args:
        model: an :class:`~roguenerf.models.enhancer.Enhancer`.
        render: ``(B, 3, H, W)``; depth: ``(B, 1, H, W)``; K: ``(B, 3, 3)``;
        world_from_cam: ``(B, 4, 4)``; neighbours: NeighbourBatch or None (used whole by every
            tile), or a callable ``(depth_tile, K_tile) -> NeighbourBatch | None`` giving each
            tile its own neighbours (e.g. only the crops of large photos the tile sees).
        tile: tile side in pixels (>= 16); overlap: pixels shared by neighbouring tiles
            (0 <= overlap < tile).
        progress: optional ``callback(done, total)`` called after every tile.
    Returns:
        ``(B, 3, H, W)``.
    """
    if not isinstance(tile, int) or tile < 16:
        raise InputError(f"tile: expected an integer >= 16, got {tile!r}")
    if not isinstance(overlap, int) or not 0 <= overlap < tile:
        raise InputError(f"overlap: expected an integer in [0, tile={tile}), got {overlap!r}")
    if render.ndim != 4 or depth.ndim != 4 or depth.shape[-2:] != render.shape[-2:]:
        raise InputError(f"render, depth: expected (B, 3, H, W) and (B, 1, H, W), got "
                         f"{tuple(render.shape)} and {tuple(depth.shape)}")
    b, _, h, w = render.shape
    provider = neighbours if callable(neighbours) else (lambda depth_tile, K_tile: neighbours)
    if h <= tile and w <= tile:
        return model(render, depth, K, world_from_cam, provider(depth, K))
    align = getattr(model, "tile_alignment", 1)
    ys, xs = tile_starts(h, tile, overlap, align), tile_starts(w, tile, overlap, align)
    wy = axis_weights(ys, tile, h, render.device, render.dtype)
    wx = axis_weights(xs, tile, w, render.device, render.dtype)
    K = K.expand(b, 3, 3) if K.ndim == 2 else K
    scale = model.depth_scale(depth)
    out = torch.zeros_like(render)
    total = render.new_zeros(1, 1, h, w)
    done = 0
    for y0, wgt_y in zip(ys, wy):
        for x0, wgt_x in zip(xs, wx):
            y1, x1 = y0 + wgt_y.numel(), x0 + wgt_x.numel()
            K_tile = K.clone()
            K_tile[:, 0, 2] -= x0
            K_tile[:, 1, 2] -= y0
            depth_tile = depth[..., y0:y1, x0:x1]
            pred = model(render[..., y0:y1, x0:x1], depth_tile, K_tile, world_from_cam,
                         provider(depth_tile, K_tile), depth_scale=scale)
            wgt = wgt_y[:, None] * wgt_x[None, :]
            out[..., y0:y1, x0:x1] += pred * wgt
            total[..., y0:y1, x0:x1] += wgt
            done += 1
            if progress is not None:
                progress(done, len(ys) * len(xs))
    return out / total
