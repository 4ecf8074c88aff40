"""Synthetic inputs for the model tests (test_model, test_fastpath, test_native, test_profiling,
test_tiling): a target camera facing a wall and neighbours beside it, and random weights for the
layers that start at zero."""

from __future__ import annotations

import math

import torch

from roguenerf.models import NeighbourBatch
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
