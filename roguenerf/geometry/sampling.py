"""Bilinear sampling at pixel coordinates, channels-last in and out (CPU inference fast path).

``F.grid_sample`` on the CPU returns NCHW whatever its input layout, and a later conversion
to channels-last costs as much as the sampling. Here each output pixel's four bilinear taps
become one ``F.embedding_bag(mode="sum")`` row with per-sample weights over the source viewed
as a ``(B * Hs * Ws, C)`` table: a single fused gather + weighted sum whose output rows are
the channels-last output. Same function as ``grid_sample(mode="bilinear")`` up to float32
rounding of the weights (tests/unit/roguenerf/native/test_fastpath.py); forward only (no gradient to the source).

Coordinates are pixel units with pixel centres at integers (x right, y down).
Dimension letters: B batch, C channels, (Hs, Ws) source size, (H, W) output size.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from roguenerf.errors import InputError


def bilinear_sample(source: Tensor, x: Tensor, y: Tensor, *, padding: str = "zeros") -> Tensor:
    """Sample ``source`` ``(B, C, Hs, Ws)`` at ``x``, ``y`` ``(B, H, W)``: ``(B, C, H, W)`` channels-last.

    padding: "zeros" (taps outside the image weigh 0, as grid_sample's zeros padding) or
    "border" (coordinates clamped into the image first, as grid_sample's border padding).
    Coordinates must be finite.
    """
    if padding not in ("zeros", "border"):
        raise InputError(f"padding: expected 'zeros' or 'border', got {padding!r}")
    b, c, hs, ws = source.shape
    h, w = x.shape[-2:]
    table = source.permute(0, 2, 3, 1).reshape(b * hs * ws, c)  # free when source is channels-last
    if padding == "border":
        x = x.clamp(0, ws - 1)
        y = y.clamp(0, hs - 1)
    x0f, y0f = x.floor(), y.floor()
    wx1, wy1 = x - x0f, y - y0f
    wx0, wy0 = 1.0 - wx1, 1.0 - wy1
    x0, y0 = x0f.long(), y0f.long()
    if padding == "zeros":
        # A tap outside the image weighs 0: masked per axis (the tap's weight is the product).
        wx0 = torch.where((x0 >= 0) & (x0 < ws), wx0, 0.0)
        wx1 = torch.where((x0 >= -1) & (x0 < ws - 1), wx1, 0.0)
        wy0 = torch.where((y0 >= 0) & (y0 < hs), wy0, 0.0)
        wy1 = torch.where((y0 >= -1) & (y0 < hs - 1), wy1, 0.0)
    # With border padding the coordinates lie in the image: only x1 = ws (or y1 = hs) can fall
    # outside, where its weight x - x0 is exactly 0; the clamped index keeps the gather inside.
    x0c, x1c = x0.clamp(0, ws - 1), (x0 + 1).clamp_(0, ws - 1)
    base = (torch.arange(b, device=source.device) * (hs * ws)).view(b, 1, 1)
    row0 = y0.clamp(0, hs - 1).mul_(ws).add_(base)
    row1 = (y0 + 1).clamp_(0, hs - 1).mul_(ws).add_(base)
    # Taps (x0, y0), (x1, y0), (x0, y1), (x1, y1), written in place into one (B, H, W, 4) table.
    index = torch.empty(b, h, w, 4, dtype=torch.int64, device=source.device)
    weight = torch.empty(b, h, w, 4, dtype=source.dtype, device=source.device)
    for k, (row, col, wy, wx) in enumerate(((row0, x0c, wy0, wx0), (row0, x1c, wy0, wx1),
                                            (row1, x0c, wy1, wx0), (row1, x1c, wy1, wx1))):
        torch.add(row, col, out=index[..., k])
        torch.mul(wx, wy, out=weight[..., k])
    out = F.embedding_bag(index.view(-1, 4), table, per_sample_weights=weight.view(-1, 4), mode="sum")
    return out.view(b, h, w, c).permute(0, 3, 1, 2)

