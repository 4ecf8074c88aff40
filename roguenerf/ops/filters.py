"""Small image filters of the pose fits, the colour stage and the temporal filter, each with two
bodies: plain torch convolutions (every body but the reference) and kornia's filters or torch's
pooling (the reference, inside :func:`~roguenerf.fastpath.reference_mode`; the ground truth of
``tests/unit/roguenerf/test_filters.py``).

The torch bodies of the blur and the gradient exist for the start-up time, not the filtering:
importing kornia imports all of it (augmentation, feature, contrib ...), 0.2-0.3 s of a one-view
command's wall-clock on 2 cores, and these two filters are all that a request needs of it. Any dtype and device.
Legend: B batch, C channels, (H, W) image size.
"""

from __future__ import annotations

import functools

import torch
import torch.nn.functional as F
from torch import Tensor

from roguenerf.ops.backend import Body, pick


@functools.lru_cache(maxsize=32)
def _gaussian_taps(size: int, sigma: float) -> Tensor:
    """``(size,)`` float64 normalised Gaussian taps centred on the middle one (kornia's kernel:
    ``exp(-x^2 / (2 sigma^2))`` at integer offsets, divided by its sum)."""
    x = torch.arange(size, dtype=torch.float64) - size // 2
    taps = torch.exp(-x.square() / (2.0 * sigma * sigma))
    return taps / taps.sum()


def _separable(x: Tensor, taps: Tensor, border: str) -> Tensor:
    """``x`` ``(B, C, H, W)`` filtered by the symmetric ``taps`` along the width, then the height,
    each channel on its own, edges padded by ``border`` (torch's ``F.pad`` mode: replicate, reflect).

    All ``B * C`` channels of one depthwise convolution per axis, channels-last on the CPU:
    oneDNN's depthwise kernel gave the bits of one single-channel convolution per channel on the
    AVX-512 machine it was measured on, 2-6x faster from 3 channels on (3 x 378 x 504, sigma 2:
    6.6 -> 3.0 ms; 12 channels 42 -> 7 ms); the tests hold it to kornia's within 2e-6."""
    b, c, h, w = x.shape
    n, k = b * c, taps.numel()
    taps = taps.to(x.device, x.dtype)
    padded = F.pad(x.reshape(1, n, h, w), (k // 2, k // 2, k // 2, k // 2), mode=border)
    if n > 1 and padded.is_cpu:
        padded = padded.contiguous(memory_format=torch.channels_last)
    across = taps.view(1, 1, 1, k).expand(n, 1, 1, k).contiguous()
    down = taps.view(1, 1, k, 1).expand(n, 1, k, 1).contiguous()
    out = F.conv2d(F.conv2d(padded, across, groups=n), down, groups=n)
    return out.contiguous().reshape(b, c, h, w)  # row-major, as before, whatever the layout inside


def gaussian_blur(x: Tensor, size: int, sigma: float, *, border: str = "replicate") -> Tensor:
    """``x`` ``(B, C, H, W)`` blurred by a ``size`` x ``size`` Gaussian of ``sigma`` pixels,
    edges padded by ``border`` (``replicate`` or ``reflect``): kornia's
    ``gaussian_blur2d(x, (size, size), (sigma, sigma), border_type=border)``, separably.
    ``size`` odd."""
    if size < 1 or size % 2 == 0:
        raise ValueError(f"gaussian_blur: expected an odd size, got {size}")
    if pick(x) is Body.REFERENCE:
        from kornia.filters import gaussian_blur2d

        return gaussian_blur2d(x, (size, size), (sigma, sigma), border_type=border)
    return _separable(x, _gaussian_taps(int(size), float(sigma)), border)


def box_sum3(x: Tensor) -> Tensor:
    """``x`` ``(B, C, H, W)`` summed over each pixel's 3 x 3 neighbourhood, zeros beyond the edges.
    The reference body is ``F.avg_pool2d`` (times 9); the other, the depthwise convolutions of
    :func:`gaussian_blur`, is 5-8x faster on the CPU (2 x 1080 x 1920: 53 -> 7-11 ms)."""
    if pick(x) is Body.REFERENCE:
        return F.avg_pool2d(x, 3, stride=1, padding=1) * 9
    return _separable(x, torch.ones(3, dtype=torch.float64), "constant")


def spatial_gradient(x: Tensor) -> Tensor:
    """``(B, C, 2, H, W)``: the central differences ``(x[u + 1] - x[u - 1]) / 2`` along the width
    (index 0) and the height (index 1), edges repeated: kornia's
    ``spatial_gradient(x, mode="diff", order=1, normalized=True)``."""
    if pick(x) is Body.REFERENCE:
        from kornia.filters import spatial_gradient as kornia_gradient

        return kornia_gradient(x, mode="diff", order=1, normalized=True)
    b, c, h, w = x.shape
    p = F.pad(x.reshape(b * c, 1, h, w), (1, 1, 1, 1), mode="replicate")[:, 0]
    gx = (p[:, 1:-1, 2:] - p[:, 1:-1, :-2]) * 0.5
    gy = (p[:, 2:, 1:-1] - p[:, :-2, 1:-1]) * 0.5
    return torch.stack([gx, gy], dim=1).reshape(b, c, 2, h, w)
