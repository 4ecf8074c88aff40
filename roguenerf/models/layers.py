"""Building blocks: conv encoders and the geometry-aware attention (paper sections 3.3, 3.5).

Imports nothing from the rest of the package but :mod:`roguenerf.ops` and its switches.
Dimension letters: B batch, C channels, H x W image size, F feature channels.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from roguenerf import ops

LEAKY_SLOPE = 0.01
"""Leaky ReLU slope of every conv block (supplementary, implementation details)."""


def he_init(module: nn.Module) -> nn.Module:
    """He (Kaiming) normal init for leaky-ReLU layers, zero biases, applied to every conv/linear."""
    for m in module.modules():
        if isinstance(m, (nn.Conv2d, nn.Linear)):
            nn.init.kaiming_normal_(m.weight, a=LEAKY_SLOPE, nonlinearity="leaky_relu")
            if m.bias is not None:
                nn.init.zeros_(m.bias)
    return module


def zero_init(layer: nn.Module) -> nn.Module:
    """Zero weight and bias: the layer outputs exactly 0 until trained."""
    nn.init.zeros_(layer.weight)
    if getattr(layer, "bias", None) is not None:
        nn.init.zeros_(layer.bias)
    return layer


def act() -> nn.Module:
    return nn.LeakyReLU(LEAKY_SLOPE)


class ConvEncoder(nn.Sequential):
    """conv_I / conv_H: two 3x3 convs (zero padding) with leaky ReLU, full resolution.

    ``(B, in_channels, H, W) -> (B, features, H, W)``.
    """

    def __init__(self, *, in_channels: int = 3, features: int = 64):
        super().__init__(
            nn.Conv2d(in_channels, features, 3, padding=1),
            act(),
            nn.Conv2d(features, features, 3, padding=1),
            act(),
        )
        he_init(self)

    def forward(self, x: Tensor) -> Tensor:
        return ops.conv_act(self, x)


def receptive_radius(module: nn.Module) -> int:
    """Receptive radius r of a stack of stride-1 convolutions with "same" zero padding and
    pointwise layers (conv_H): an output pixel depends on the input pixels at most r away.

    Sum over the Conv2d layers of ``dilation * (kernel - 1) / 2``. Raises ValueError for a
    layer whose output grid is not its input grid (stride, asymmetric or non-"same" padding,
    non-zero padding mode) or a sub-module that is neither a Conv2d nor parameter-free.
    """
    radius = 0
    for name, m in module.named_modules():
        if isinstance(m, nn.Conv2d):
            reach = [d * (k - 1) for k, d in zip(m.kernel_size, m.dilation)]
            if (any(s != 1 for s in m.stride) or any(r % 2 for r in reach) or m.padding_mode != "zeros"
                    or (m.padding != "same" and tuple(m.padding) != tuple(r // 2 for r in reach))):
                raise ValueError(f"{name}: expected a stride-1 'same' zero-padded convolution, got {m}")
            radius += max(reach) // 2
        elif m is not module and next(m.parameters(recurse=False), None) is not None:
            raise ValueError(f"{name}: {type(m).__name__} has parameters; its reach is unknown")
    return radius


conv_act = ops.conv_act
"""``block`` = Sequential(Conv2d, LeakyReLU) applied to ``x``, fused on the fast path (channels-last out)."""


cat_channels_last = ops.cat_channels_last
"""``torch.cat(tensors, dim=1)`` written straight into a channels-last tensor (:mod:`roguenerf.ops.fused`)."""


class PixelAttention(nn.Module):
    """psi_pix = sigmoid(conv(act(conv([H', I^f, D_{i->k}, D_k])))), one weight per pixel.

    Args of forward:
        neighbour: ``(B, F, H, W)`` aligned neighbour features H'.
        target: ``(B, F, H, W)`` target features I^f.
        neighbour_depth: ``(B, 1, H, W)`` D_{i->k}, normalised (see Enhancer).
        target_depth: ``(B, 1, H, W)`` D_k, normalised.
    Returns:
        ``(B, 1, H, W)`` in (0, 1).
    """

    def __init__(self, *, features: int = 64, hidden: int = 32):
        super().__init__()
        self.net = he_init(nn.Sequential(
            nn.Conv2d(2 * features + 2, hidden, 3, padding=1),
            act(),
            nn.Conv2d(hidden, 1, 3, padding=1),
        ))

    def forward(self, neighbour: Tensor, target: Tensor, neighbour_depth: Tensor,
                target_depth: Tensor) -> Tensor:
        x = torch.cat([neighbour, target, neighbour_depth, target_depth], dim=1)
        return torch.sigmoid(self.net(x))

    # The first conv is linear in its input, so conv([H', I^f, D_i, D_k]) =
    # conv_nb([H', D_i]) + conv_tg([I^f, D_k]) + bias. The target term is the same for every
    # neighbour: the enhancer computes it once per forward (fast path, no gradient).

    def target_term(self, target: Tensor, target_depth: Tensor) -> Tensor:
        """``(B, hidden, H, W)``: the first conv's response to [I^f, D_k] plus its bias."""
        conv = self.net[0]
        f = target.shape[1]
        weight = torch.cat([conv.weight[:, f:2 * f], conv.weight[:, 2 * f + 1:]], dim=1)
        x = [target, target_depth]
        x = ops.cat_channels(x, like=target)
        return ops.conv3x3(x, conv, weight, conv.bias)

    def neighbour_term(self, neighbour_and_depth: Tensor) -> Tensor:
        """``(B, hidden, H, W)``: the first conv's response to [H', D_i] (no bias), from a buffer
        ``(B, F + 1 + extra, H, W)`` whose channels after D_i are ignored (read in place)."""
        conv = self.net[0]
        f = (conv.weight.shape[1] - 2) // 2
        weight = torch.cat([conv.weight[:, :f], conv.weight[:, 2 * f:2 * f + 1]], dim=1)
        return ops.conv3x3(neighbour_and_depth, conv, weight)

    def from_target_term(self, neighbour_and_depth: Tensor, term: Tensor) -> Tensor:
        """psi_pix from [H', D_i, ...] ``(B, F + 1 + extra, H, W)`` and :meth:`target_term`
        (equal to :meth:`forward`; channels after D_i are ignored, so a buffer holding more
        channels is used without copying). ``neighbour_and_depth`` may also hold k neighbours
        of each of the B targets, ``(k * B, ...)`` neighbour-major: the one target term serves
        them all; returns ``(k * B, 1, H, W)``."""
        hidden = self.neighbour_term(neighbour_and_depth)
        k = hidden.shape[0] // term.shape[0]
        if k * term.shape[0] != hidden.shape[0]:
            raise ValueError(f"neighbour batch {hidden.shape[0]} is not a multiple of the target batch {term.shape[0]}")
        if k > 1:
            hidden.view(k, *term.shape).add_(term)
        else:
            hidden.add_(term)
        hidden = F.leaky_relu(hidden, self.net[1].negative_slope)
        return torch.sigmoid(ops.conv2d(hidden, self.net[2]))


CAMERA_INPUTS = 9
"""Camera attention input: Euler angles of neighbour and target (3 + 3) and the neighbour's
position relative to the target divided by the scene scale (3)."""


class CameraAttention(nn.Module):
    """psi_cam = sigmoid(fc(act(fc(x)))), one weight per neighbour image.

    ``(B, CAMERA_INPUTS) -> (B, 1)`` in (0, 1).
    """

    def __init__(self, *, hidden: int = 32):
        super().__init__()
        self.net = he_init(nn.Sequential(nn.Linear(CAMERA_INPUTS, hidden), act(), nn.Linear(hidden, 1)))

    def forward(self, x: Tensor) -> Tensor:
        return torch.sigmoid(self.net(x))
