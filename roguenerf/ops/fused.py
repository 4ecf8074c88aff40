"""Inference fast paths that compute the same function as the plain PyTorch layers.

On the CPU, oneDNN (mkldnn) can apply an activation inside a linear or convolution kernel
(one pass over the output instead of two) and runs skinny linears (16-128 channels, ~1e5
tokens: the Uformer's shape) faster than MKL's ``addmm``. PyTorch exposes these kernels as
``torch.ops.mkldnn._linear_pointwise`` / ``_convolution_pointwise`` (what TorchInductor
generates for CPU). They have no autograd formula, so they are used only when no gradient is
being recorded, on float32 CPU tensors, and when the build has them; otherwise the helpers
fall back to ``F.linear`` / ``conv`` followed by the activation. The fused and plain paths
agree to float32 rounding (``tests/unit/roguenerf/native/test_fastpath.py``).

:func:`~roguenerf.fastpath.reference_mode` switches every fast path of the package off
(fused kernels here, fused attention, channels-last layout, shared per-target work in the
enhancer), giving the plain implementation to test and benchmark the fast one against; the
body is chosen by :func:`roguenerf.ops.backend.pick`.

Dimension letters: C channels; ``...`` any leading dimensions.
"""

from __future__ import annotations

import functools

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from roguenerf import native
from roguenerf.fastpath import layout_enabled
from roguenerf.ops.backend import Body, as_channels_last, pick

__all__ = ["cat_channels", "cat_channels_last", "channels_last", "conv2d", "conv3x3", "conv_act", "linear",
           "linear_add", "mkldnn_fused_available"]


@functools.lru_cache(maxsize=1)
def mkldnn_fused_available() -> bool:
    """Whether this torch build has oneDNN and its fused pointwise linear / conv ops (checked once)."""
    if not torch.backends.mkldnn.is_available():
        return False
    try:
        x = torch.ones(2, 4)
        w = torch.ones(3, 4)
        with torch.no_grad():
            y = torch.ops.mkldnn._linear_pointwise(x, w, None, "gelu", [], "none")
            z = torch.ops.mkldnn._convolution_pointwise(
                torch.ones(1, 2, 3, 3), torch.ones(2, 1, 3, 3), None, [1, 1], [1, 1], [1, 1], 2,
                "leaky_relu", [0.01], "")
        return bool(torch.allclose(y, F.gelu(x @ w.T)) and z.shape == (1, 2, 3, 3))
    except (AttributeError, RuntimeError, NotImplementedError):
        return False


def _fused(x: Tensor) -> bool:
    return pick(x, allow_native=False).fast and mkldnn_fused_available()


def linear(x: Tensor, layer: nn.Linear, activation: str = "none") -> Tensor:
    """``act(layer(x))`` for ``(..., C_in) -> (..., C_out)``; activation "none" or "gelu" (exact erf)."""
    if _fused(x):
        shape = x.shape
        y = torch.ops.mkldnn._linear_pointwise(x.reshape(-1, shape[-1]), layer.weight, layer.bias,
                                               activation, [], "none" if activation == "gelu" else "")
        return y.view(*shape[:-1], y.shape[-1])
    y = layer(x)
    return F.gelu(y) if activation == "gelu" else y


def linear_add(x: Tensor, layer: nn.Linear, other: Tensor) -> Tensor:
    """``layer(x) + other`` (``other`` shaped as the result), the sum fused into the linear
    kernel on the fast path."""
    if _fused(x) and other.is_contiguous():
        shape = x.shape
        y = torch.ops.mkldnn._linear_pointwise.binary(x.reshape(-1, shape[-1]), other.reshape(-1, other.shape[-1]),
                                                      layer.weight, layer.bias, "add")
        return y.view(other.shape)
    return layer(x) + other


def conv2d(x: Tensor, conv: nn.Conv2d, activation: str = "none", slope: float = 0.01) -> Tensor:
    """``act(conv(x))``; activation "none", "gelu" (exact erf) or "leaky_relu" (with ``slope``).

    The fused path keeps the memory format of ``x`` (channels-last in, channels-last out).
    """
    if (_fused(x) and conv.padding_mode == "zeros" and isinstance(conv.padding, tuple)
            and x.ndim == 4):
        scalars = [slope] if activation == "leaky_relu" else []
        algorithm = "none" if activation == "gelu" else ""
        return torch.ops.mkldnn._convolution_pointwise(
            x, conv.weight, conv.bias, list(conv.padding), list(conv.stride), list(conv.dilation),
            conv.groups, activation, scalars, algorithm)
    y = conv(x)
    if activation == "gelu":
        return F.gelu(y)
    if activation == "leaky_relu":
        return F.leaky_relu(y, slope)
    return y


def channels_last(x: Tensor) -> Tensor:
    """``x`` in channels-last layout on the fast path (4-D tensors), unchanged otherwise."""
    if x.ndim == 4 and pick(x, allow_native=False).fast:
        return x.contiguous(memory_format=torch.channels_last)
    return x


def conv_act(block: nn.Sequential, x: Tensor) -> Tensor:
    """``block`` = Sequential(Conv2d, LeakyReLU[, Conv2d, LeakyReLU ...]) applied to ``x``, each
    pair fused on the fast path (channels-last out)."""
    if not pick(x, allow_native=False).fast:
        return nn.Sequential.forward(block, x)  # (not block(x): a subclass's forward may call this)
    x = channels_last(x)
    for i in range(0, len(block), 2):
        x = conv2d(x, block[i], "leaky_relu", block[i + 1].negative_slope)
    return x


# Probe once at import, so that the probe's tiny ops never land inside a caller's FLOP count
# or profile.
mkldnn_fused_available()


def conv3x3(x: Tensor, conv: nn.Conv2d, weight: Tensor | None = None, bias: Tensor | None = None) -> Tensor:
    """``conv(x)``; with ``weight`` ``(Co, Cin, 3, 3)`` (and ``bias``) instead of the layer's own,
    ``conv2d(x[:, :Cin], weight, bias)`` with the layer's padding: ``x`` may hold more channels
    than ``Cin``, which are ignored (read in place by the kernel, zero weights in torch). The C
    kernel (:func:`roguenerf.native.conv3x3`, channels-last out) where it applies, else torch."""
    if weight is None:
        weight, bias = conv.weight, conv.bias
        own = True
    else:
        own = False
    if pick(x) is Body.NATIVE and native.conv3x3_supported(conv):
        return native.conv3x3(as_channels_last(x), weight, bias)
    if own:
        return conv(x)
    extra = x.shape[1] - weight.shape[1]
    if extra:
        weight = torch.cat([weight, weight.new_zeros(weight.shape[0], extra, *weight.shape[2:])], dim=1)
    return F.conv2d(x, weight, bias, padding=conv.padding)


def cat_channels_last(tensors: list[Tensor]) -> Tensor:
    """``torch.cat(tensors, dim=1)`` written straight into a channels-last tensor (one copy;
    ``torch.cat`` alone returns NCHW when a one-channel input is among channels-last ones).
    With gradient (``out=`` has no autograd formula): the concatenation, then one layout copy."""
    if torch.is_grad_enabled() and any(t.requires_grad for t in tensors):
        return torch.cat(tensors, dim=1).contiguous(memory_format=torch.channels_last)
    b, _, h, w = tensors[0].shape
    out = torch.empty(b, sum(t.shape[1] for t in tensors), h, w, dtype=tensors[0].dtype,
                      device=tensors[0].device, memory_format=torch.channels_last)
    return torch.cat(tensors, dim=1, out=out)


def cat_channels(tensors: list[Tensor], like: Tensor) -> Tensor:
    """``torch.cat(tensors, dim=1)``, channels-last where that layout applies to ``like``
    (:func:`roguenerf.fastpath.layout_enabled`: float32 CPU outside reference mode, also with
    gradient: oneDNN's convolutions are faster on it)."""
    return cat_channels_last(tensors) if layout_enabled(like) else torch.cat(tensors, dim=1)
