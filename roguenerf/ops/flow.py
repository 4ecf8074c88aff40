"""The flow refinement's operations with several bodies: the backward warp, the 1/8 pool, the
upsampling + warp (+ depth normalisation) and the GRU's gates.

Dimension letters: B batch, C channels, (H, W) full size, (h, w) the flow's 1/8 size.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from roguenerf import native
from roguenerf.geometry.sampling import bilinear_sample
from roguenerf.ops.backend import Body, as_channels_last, as_contiguous, pick

STRIDE = 8
"""The flow network's resolution step (the C kernels' pool and upsampling use it)."""


def warp(x: Tensor, flow: Tensor) -> Tensor:
    """Backward-warp ``x`` ``(B, C, H, W)`` by ``flow`` ``(B, 2, H, W)`` (pixels, (dx, dy)).

    Bilinear, zero outside the image. Returns ``(B, C, H, W)``: gather sampling, channels-last,
    on the fast path (finite flows), ``grid_sample`` otherwise.
    """
    _, _, h, w = x.shape
    ys = torch.arange(h, device=x.device, dtype=x.dtype)
    xs = torch.arange(w, device=x.device, dtype=x.dtype)
    if pick(x).fast and torch.isfinite(flow).all():
        return bilinear_sample(x, xs[None, None, :] + flow[:, 0], ys[None, :, None] + flow[:, 1], padding="zeros")
    gx = (2.0 * (xs[None, None, :] + flow[:, 0]) + 1.0) / w - 1.0
    gy = (2.0 * (ys[None, :, None] + flow[:, 1]) + 1.0) / h - 1.0
    grid = torch.stack([gx, gy], dim=-1)
    return F.grid_sample(x, grid, mode="bilinear", padding_mode="zeros", align_corners=False)


def upsample(flow: Tensor, height: int, width: int) -> Tensor:
    """``(B, 2, h, w)`` flow at 1/8 resolution -> ``(B, 2, height, width)`` (values x 8)."""
    up = F.interpolate(flow, scale_factor=STRIDE, mode="bilinear", align_corners=False)
    return up[..., :height, :width] * STRIDE


def upsample_warp(x: Tensor, flow_low: Tensor, *, depth_scale: Tensor | None = None, depth_channel: int = 0,
                  depth_max: float = 0.0) -> tuple[Tensor, bool]:
    """``warp(x, upsample(flow_low, H, W))`` for ``x`` ``(B, C, H, W)``; with ``depth_scale``
    ``(B,)``, the C kernel also writes channel ``depth_channel`` as ``clamp(v / scale, 0,
    depth_max)``. Returns the warped ``x`` and whether that normalisation was done (only by
    the kernel: the caller normalises otherwise). The kernel where it applies and the flow is
    finite, else the torch bodies."""
    h, w = x.shape[-2:]
    if pick(x) is Body.NATIVE:
        warped = native.flow_warp(as_channels_last(x), as_contiguous(flow_low), depth_scale=as_contiguous(depth_scale),
                                  depth_channel=depth_channel, depth_max=depth_max)
        if warped is not None:  # None: a non-finite flow, which the torch body handles
            return warped, depth_scale is not None
    return warp(x, upsample(flow_low, h, w)), False


def pool(x: Tensor, channels: int) -> Tensor:
    """``(B, C, H, W)`` -> ``(B, channels, h, w)``: edge-padded to a multiple of 8, averaged,
    first ``channels`` channels."""
    if pick(x) is Body.NATIVE:
        return native.pool8(as_channels_last(x), channels)
    ph, pw = -x.shape[-2] % STRIDE, -x.shape[-1] % STRIDE
    if ph or pw:
        x = F.pad(x, (0, pw, 0, ph), mode="replicate")
    return F.avg_pool2d(x, STRIDE)[:, :channels]


def gru_gates(hx: Tensor, to_z: nn.Conv2d, to_r: nn.Conv2d) -> tuple[Tensor, Tensor]:
    """The ConvGRU's update and reset gates ``sigmoid(to_z(hx))``, ``sigmoid(to_r(hx))``; on
    the fast path one convolution with both gates' filters (same values)."""
    if pick(hx).fast:
        weight = torch.cat([to_z.weight, to_r.weight])
        bias = torch.cat([to_z.bias, to_r.bias])
        z, r = torch.sigmoid(F.conv2d(hx, weight, bias, padding=1)).chunk(2, dim=1)
        return z, r
    return torch.sigmoid(to_z(hx)), torch.sigmoid(to_r(hx))
