"""Synthetic inputs for the model tests (test_model, test_fastpath, test_native, test_profiling,
test_tiling, test_inference, test_colour, test_trust, ...): a target camera facing a wall and
neighbours beside it, random weights for the layers that start at zero, textured images and a
stand-in enhancer with a known colour bias."""

from __future__ import annotations

import math

import torch

from roguenerf.models import NeighbourBatch, build_enhancer
from roguenerf.models.enhancer import Enhancer


def pose(t, yaw: float = 0.0) -> torch.Tensor:
    """OpenCV camera-to-world ``(4, 4)``: rotation about the y axis by ``yaw``, position ``t``."""
    c, s = math.cos(yaw), math.sin(yaw)
    P = torch.eye(4)
    P[:3, :3] = torch.tensor([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])
    P[:3, 3] = torch.tensor(t, dtype=torch.float32)
    return P


def make_views(model: Enhancer, *, b: int = 1, n: int = 2, h: int = 48, w: int = 64, seed: int = 0,
               unit: float = 1.0, photos: torch.Tensor | None = None):
    """A target camera at the origin facing a wall at z ~ 4 and ``n`` neighbours a little to
    the side, all seeing most of the wall (so the reprojection is mostly valid).

    Returns render ``(b, 3, h, w)``, depth ``(b, 1, h, w)``, K ``(b, 3, 3)``, pose ``(b, 4, 4)``
    and a :class:`NeighbourBatch` with neighbour images of the same size. ``unit`` scales every
    length (depths and translations).
    """
    g = torch.Generator().manual_seed(seed)
    K = torch.tensor([[0.9 * w, 0.0, w / 2], [0.0, 0.9 * w, h / 2], [0.0, 0.0, 1.0]])
    render = torch.rand(b, 3, h, w, generator=g)
    depth = (4.0 + 0.2 * torch.rand(b, 1, h, w, generator=g)) * unit
    target = pose([0.0, 0.0, 0.0]).expand(b, 4, 4).clone()
    if photos is None:
        photos = torch.rand(n, 3, h, w, generator=g)
    if model.conv_H is not None and n:
        feats = model.encode_neighbours(photos)
    else:
        feats = torch.zeros(n, model.config.features, h, w)
    nposes = [pose([0.15 * (j + 1) * (-1) ** j * unit, 0.05 * j * unit, 0.02 * j * unit], yaw=0.02 * j)
              for j in range(n)]
    nposes = torch.stack(nposes) if n else torch.zeros(0, 4, 4)
    ndepth = 4.0 * unit * torch.ones(n, 1, h, w)
    nb = NeighbourBatch(features=feats[None].expand(b, -1, -1, -1, -1),
                        depth=ndepth[None].expand(b, -1, -1, -1, -1),
                        K=K.expand(b, n, 3, 3), world_from_cam=nposes[None].expand(b, -1, -1, -1))
    return render, depth, K.expand(b, 3, 3), target, nb


def randomise(model: Enhancer, std: float = 0.05, seed: int = 0) -> Enhancer:
    """Give the zero-initialised layers (output projection, flow increment head) small random
    weights, so that every part of the model influences the output."""
    g = torch.Generator().manual_seed(seed)
    layers = [model.uformer.output_proj if model.uformer is not None else model.to_rgb]
    if model.flow is not None:
        layers.append(model.flow.to_delta[-1])
    with torch.no_grad():
        for layer in layers:
            layer.weight.copy_(torch.randn(layer.weight.shape, generator=g) * std)
    return model


def perturbed_micro(seed: int = 0, **overrides) -> Enhancer:
    """A 'micro' enhancer with every weight perturbed. A fresh enhancer is the identity
    (zero-initialised residual); the perturbation makes outputs depend on the neighbours, so
    differences are visible."""
    torch.manual_seed(seed)
    model = build_enhancer("micro", **overrides)
    with torch.no_grad():
        for p in model.parameters():
            p.add_(0.05 * torch.randn_like(p))
    return model


def textured(seed: int, h: int = 48, w: int = 64) -> torch.Tensor:
    """A random ``(1, 3, h, w)`` image in [0.2, 0.8]."""
    g = torch.Generator().manual_seed(seed)
    return (0.2 + 0.6 * torch.rand(1, 3, h, w, generator=g)).clamp(0, 1)


class Biased(torch.nn.Module):
    """A stand-in enhancer that returns the render a little too bright."""

    def __init__(self, model, bias: torch.Tensor):
        super().__init__()
        self.inner, self.bias, self.config = model, bias, model.config

    def forward(self, render, depth, K, pose, batch):
        return render + self.bias.view(1, 3, 1, 1)

    def encode_neighbours(self, photos):
        return self.inner.encode_neighbours(photos)

    def neighbour_source(self, features, depth):
        return self.inner.neighbour_source(features, depth)


class KernelCalls:
    """The names of the C kernels (``roguenerf.native``) run inside the ``with`` block, in
    ``names`` (proves the native path ran, or that a refused call ran none)."""

    def __enter__(self):
        from roguenerf import native

        self.names: list[str] = []
        native.on_call = lambda name, nbytes: self.names.append(name)
        return self

    def __exit__(self, *exc):
        from roguenerf import native

        native.on_call = None
