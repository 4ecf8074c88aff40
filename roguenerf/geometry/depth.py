"""The one definition of "known depth", used by every part of the library and the service.

A depth value is **known** when it is finite and ``DEPTH_EPS < z < MAX_DEPTH``; everything
else (zero, negative, NaN, +-inf, tiny positive values such as the ~1e-40 a radiance field's
expected depth underflows to in empty space, and values so large that float32 geometry would
overflow) means "unknown" and is never used as a sample. Reprojection, the enhancer's scene
scale and depth normalisation, training, tiling, the degradation model, ray-to-z conversion
and the service's depth-coverage check all call :func:`known_depth_mask`.

With this rule the median known depth (the enhancer's scene scale) lies in
``(DEPTH_EPS, MAX_DEPTH)``, so ``1 / scale`` and ``depth / scale`` cannot overflow.
"""

from __future__ import annotations

import torch
from torch import Tensor

DEPTH_EPS = 1e-6
"""Depth at or below this (in pose units) is unknown."""

MAX_DEPTH = 1e10
"""Depth at or beyond this is unknown: it would overflow float32 geometry."""


def known_depth_mask(depth, *, eps: float = DEPTH_EPS):
    """Boolean mask of known depth (finite and ``eps < z < MAX_DEPTH``), same shape.

    Accepts a torch tensor (returns a bool tensor) or a NumPy array (returns a bool array).
    ``eps`` defaults to :data:`DEPTH_EPS`; only :func:`~roguenerf.reprojection.reproject`
    exposes it, for callers who know better.
    """
    if isinstance(depth, Tensor):
        if depth.dtype == torch.bool:  # a mask is not a depth map
            return torch.zeros(depth.shape, dtype=torch.bool, device=depth.device)
        # NaN fails both comparisons and +-inf one of them: no isfinite pass needed
        return (depth > eps) & (depth < MAX_DEPTH)
    import numpy as np

    values = np.asarray(depth)
    if values.dtype.kind not in "fiu":  # bool, object, complex: not a depth map
        return np.zeros(values.shape, dtype=bool)
    with np.errstate(invalid="ignore"):
        return np.isfinite(values) & (values > eps) & (values < MAX_DEPTH)


def known_depth(depth: Tensor, *, eps: float = DEPTH_EPS, fill: float = 0.0) -> Tensor:
    """``depth`` with every unknown entry (see :func:`known_depth_mask`) replaced by ``fill``.

    Replacing (rather than masking afterwards) keeps NaN/inf out of every later operation, so
    values and gradients stay finite.
    """
    known = known_depth_mask(depth, eps=eps)
    return torch.where(known, torch.nan_to_num(depth, nan=fill, posinf=fill, neginf=fill),
                       torch.as_tensor(fill, dtype=depth.dtype, device=depth.device))


def median_known_depth(depth: Tensor) -> Tensor:
    """``(B, 1, H, W)`` (or ``(B, ...)``) z-depth -> ``(B,)`` median over the known pixels, 1.0 where
    none is known. The result lies in ``(DEPTH_EPS, MAX_DEPTH)``: its reciprocal is finite."""
    d = depth.detach().flatten(1).to(torch.float64)
    d = torch.where(known_depth_mask(d), d, torch.nan)
    med = torch.nanmedian(d, dim=1).values
    return torch.where(torch.isfinite(med), med, torch.ones_like(med)).to(depth.dtype)
