"""Non-rigid refinement (paper section 3.4): a lightweight iterative flow network.

FlexHDR-style (Catley-Chandar et al. 2022): both feature maps are average-pooled to 1/8
resolution and encoded; a convolutional GRU then predicts flow increments for a few
iterations from [neighbour features warped by the current flow, target features, current
flow]. The increment head is zero-initialised, so an untrained network predicts flow 0 and
the refinement starts as the identity. The 1/8 flow is upsampled bilinearly (values x 8).

Flow units: pixels of the map being warped, (dx, dy); ``warp(x, flow)[p] = x[p + flow[p]]``
with pixel centres at integer + 0.5 in ``grid_sample``'s ``align_corners=False`` frame, which
is also the frame of the bilinear upsampling, so the two agree.

Dimension letters: B batch, F feature channels, H x W full resolution, h x w = 1/8 resolution.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from roguenerf import ops
from roguenerf.models.layers import act, conv_act, he_init, zero_init

FLOW_STRIDE = ops.flow.STRIDE
"""The flow is estimated at 1/FLOW_STRIDE resolution."""


flow_warp = ops.warp
"""Backward-warp ``x`` ``(B, C, H, W)`` by ``flow`` ``(B, 2, H, W)`` (:func:`roguenerf.ops.flow.warp`)."""


def upsample_flow(flow: Tensor, height: int, width: int) -> Tensor:
    """``(B, 2, h, w)`` flow at 1/8 resolution -> ``(B, 2, height, width)`` (values x 8)."""
    return ops.upsample_flow(flow, height, width)


class ConvGRU(nn.Module):
    """Convolutional GRU cell: ``h (B, C, h, w), x (B, Cx, h, w) -> h' (B, C, h, w)``."""

    def __init__(self, *, hidden: int, inputs: int):
        super().__init__()
        self.to_z = nn.Conv2d(hidden + inputs, hidden, 3, padding=1)
        self.to_r = nn.Conv2d(hidden + inputs, hidden, 3, padding=1)
        self.to_q = nn.Conv2d(hidden + inputs, hidden, 3, padding=1)

    def forward(self, h: Tensor, x: Tensor) -> Tensor:
        hx = torch.cat([h, x], dim=1)
        z, r = ops.gru_gates(hx, self.to_z, self.to_r)
        q = torch.tanh(self.to_q(torch.cat([r * h, x], dim=1)))
        return (1 - z) * h + z * q


class FlowRefiner(nn.Module):
    """Flow from aligned neighbour features to target features.

    Args of forward:
        neighbour: ``(B, F [+ extra], H, W)`` 3D-aligned neighbour features H_{i->k} (channels
            beyond F are ignored: a buffer that also holds the depth is used without copying).
        target: ``(B, F, H, W)`` target features I^f.
    Returns:
        ``(B, 2, H, W)`` flow in full-resolution pixels; ``flow_warp(neighbour, flow)`` aligns.
    """

    def __init__(self, *, features: int = 64, hidden: int = 64, iters: int = 4):
        super().__init__()
        self.iters = iters
        self.encode = nn.Sequential(
            nn.Conv2d(features, hidden, 3, padding=1), act(),
            nn.Conv2d(hidden, hidden, 3, padding=1), act(),
        )
        self.to_input = nn.Sequential(nn.Conv2d(2 * hidden + 2, hidden, 3, padding=1), act())
        self.gru = ConvGRU(hidden=hidden, inputs=hidden)
        self.to_delta = nn.Sequential(nn.Conv2d(hidden, hidden, 3, padding=1), act(),
                                      nn.Conv2d(hidden, 2, 3, padding=1))
        he_init(self)
        zero_init(self.to_delta[-1])

    def forward(self, neighbour: Tensor, target: Tensor, target_low: Tensor | None = None) -> Tensor:
        """``neighbour`` may hold k neighbours of each target, ``(k * B, ...)`` neighbour-major
        (row ``j * B + i`` is neighbour j of target i): the target is encoded once and its
        encoding shared by the k (same values and gradients as k calls); ``(k * B, 2, H, W)``."""
        b, _, height, width = target.shape
        k, rest = divmod(neighbour.shape[0], b)
        if rest or k < 1:
            raise ValueError(f"neighbour batch {neighbour.shape[0]} is not a multiple of the target batch {b}")
        if target_low is None:
            low = self._encode(torch.cat([neighbour[:, :target.shape[1]], target], dim=0))
            nb, tg = low[:k * b], low[k * b:]
        else:
            nb, tg = self._encode(neighbour), target_low
        if k > 1:
            tg = tg.repeat(k, 1, 1, 1)
        return self._iterate(nb, tg, height, width)

    def batched(self, neighbours: list[Tensor], target_low: Tensor, height: int, width: int, *,
                upsample: bool = True) -> list[Tensor]:
        """Flows for several neighbours of one target at once: ``neighbours`` N tensors
        ``(B, F [+ extra], H, W)``, ``target_low`` from :meth:`encode_target` -> N flows
        ``(B, 2, H, W)``. Equal to N calls of :meth:`forward`; the 1/8-resolution network runs
        on a batch of N * B (larger, faster convolutions). ``upsample=False``: the flows at
        1/8 resolution ``(B, 2, h, w)``, before :func:`upsample_flow`."""
        n = len(neighbours)
        pooled = torch.cat([self._pool(x) for x in neighbours], dim=0)
        nb = self._encode_low(pooled)
        tg = ops.channels_last(target_low.repeat(n, 1, 1, 1))  # repeat gives NCHW; the convs want NHWC
        return list(self._iterate(nb, tg, height, width, upsample=upsample).chunk(n, dim=0))

    def _iterate(self, nb: Tensor, tg: Tensor, height: int, width: int, *, upsample: bool = True) -> Tensor:
        hidden = torch.tanh(tg)
        flow = tg.new_zeros(tg.shape[0], 2, *tg.shape[-2:])
        for _ in range(self.iters):
            x = conv_act(self.to_input, torch.cat([flow_warp(nb, flow), tg, flow], dim=1))
            hidden = self.gru(hidden, x)
            flow = flow + self.to_delta(hidden)
        return upsample_flow(flow, height, width) if upsample else flow

    def encode_target(self, target: Tensor) -> Tensor:
        """``(B, hidden, h, w)`` 1/8-resolution encoding of the target; pass it to :meth:`forward`
        as ``target_low`` to encode the target once for all neighbours (same result)."""
        return self._encode(target)

    def _pool(self, x: Tensor) -> Tensor:
        """``(B, C, H, W)`` -> ``(B, F, h, w)``: edge-padded to a multiple of 8, averaged, first F channels."""
        return ops.pool_flow(x, self.encode[0].in_channels)

    def _encode_low(self, low: Tensor) -> Tensor:
        return conv_act(self.encode[2:], conv_act(self.encode[:2], low))

    def _encode(self, x: Tensor) -> Tensor:
        return self._encode_low(self._pool(x))
