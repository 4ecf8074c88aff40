"""The pixel attention's tail and the max / min pooling over neighbours (the enhancer's fast path).

Dimension letters: B batch, F feature channels, (H, W) target size, Cs channels of a packed
neighbour buffer [features, depth, ...].
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from roguenerf import native
from roguenerf.ops.backend import Body, as_channels_last, as_contiguous, pick
from roguenerf.profiling import stage


def pool(aligned: Tensor, pooled: Tensor | None, low: Tensor | None, spread: bool) -> tuple[Tensor, Tensor | None]:
    """One more neighbour ``aligned`` ``(B, F, H, W)`` into the running max ``pooled`` (and with
    ``spread`` the running min ``low``), in place; None starts them (``low`` as a copy: the max
    is written into the first neighbour's map)."""
    if spread:
        low = aligned.clone() if low is None else torch.minimum(low, aligned, out=low)
    pooled = aligned if pooled is None else torch.maximum(pooled, aligned, out=pooled)
    return pooled, low


def attend_pool(pixel_attention: nn.Module, buf: Tensor, term: Tensor, camera: Tensor, features: int,
                pooled: Tensor | None, low: Tensor | None, *, spread: bool) -> tuple[Tensor, Tensor | None]:
    """One neighbour weighted and pooled: ``a = buf[:, :features] * camera * psi_pix`` with
    ``psi_pix = pixel_attention.from_target_term(buf, term)``, then :func:`pool` of ``a``.

    ``buf`` ``(B, Cs, H, W)`` [features, normalised depth, ...]; ``term`` the pixel attention's
    target term; ``camera`` ``(B, 1)`` the camera attention's weight. Times the weighting as
    the "attention" stage and the torch body's pooling as "fusion"; the C kernel
    (:func:`roguenerf.native.attend_pool`) does both in one pass, all "attention"."""
    pa = pixel_attention
    if pick(buf) is Body.NATIVE:
        with stage("attention"):
            return native.attend_pool(as_channels_last(pa.neighbour_term(buf)), as_channels_last(term), pa.net[2],
                                      pa.net[1].negative_slope, as_contiguous(camera.detach()), as_channels_last(buf),
                                      features, pooled, low, spread=spread)
    with stage("attention"):
        psi_pix = pa.from_target_term(buf, term)
        # buf first: the product keeps its channels-last layout (same values).
        aligned = buf[:, :features] * (camera[:, :, None, None] * psi_pix)
    with stage("fusion"):
        return pool(aligned, pooled, low, spread)
