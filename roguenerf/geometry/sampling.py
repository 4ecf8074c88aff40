"""Bilinear sampling at pixel coordinates, channels-last in and out (CPU inference fast path).

``F.grid_sample`` on the CPU returns NCHW whatever its input layout, and a later conversion
to channels-last costs as much as the sampling. Here each output pixel's four bilinear taps
become one ``F.embedding_bag(mode="sum")`` row with per-sample weights over the source viewed
as a ``(B * Hs * Ws, C)`` table: a single fused gather + weighted sum whose output rows are
the channels-last output. Same function as ``grid_sample(mode="bilinear")`` up to float32
rounding of the weights (tests/test_fastpath.py); forward only (no gradient to the source).

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
    x1, y1 = x0 + 1, y0 + 1
    base = (torch.arange(b, device=source.device) * (hs * ws)).view(b, 1, 1)
    index, weight = [], []
    for xi, yi, wgt in ((x0, y0, wx0 * wy0), (x1, y0, wx1 * wy0), (x0, y1, wx0 * wy1), (x1, y1, wx1 * wy1)):
        inside = (xi >= 0) & (xi < ws) & (yi >= 0) & (yi < hs)
        index.append(base + yi.clamp(0, hs - 1) * ws + xi.clamp(0, ws - 1))
        weight.append(torch.where(inside, wgt, 0.0))
    index = torch.stack(index, dim=-1).view(-1, 4)
    weight = torch.stack(weight, dim=-1).view(-1, 4).to(source.dtype)
    out = F.embedding_bag(index, table, per_sample_weights=weight, mode="sum")
    return out.view(b, h, w, c).permute(0, 3, 1, 2)
