"""The :class:`Gaussians` of a 3D Gaussian splatting scene, stored as Inria's ``point_cloud.ply`` does.

Parameters are kept in their raw (optimised) form: ``opacity`` a logit, ``log_scales`` natural
logarithms, ``quats`` un-normalised quaternions ``(w, x, y, z)``, ``sh`` the spherical-harmonic
coefficients ``(N, K, 3)`` with ``K = (degree + 1)²`` (coefficient 0 is Inria's ``f_dc``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import torch
from torch import Tensor

from roguenerf.errors import InputError

SH_COEFFS = {0: 1, 1: 4, 2: 9, 3: 16}
"""Coefficients per colour channel for each SH degree."""


def sh_degree_of(coeffs: int) -> int:
    """The SH degree with ``coeffs`` coefficients per channel (1, 4, 9 or 16)."""
    for degree, k in SH_COEFFS.items():
        if k == coeffs:
            return degree
    raise InputError(f"sh: expected 1, 4, 9 or 16 coefficients per channel (degree 0..3), got {coeffs}")


@dataclass
class Gaussians:
    """N anisotropic 3D Gaussians (world coordinates, the dataset's pose units)."""

    means: Tensor
    """``(N, 3)`` centres."""
    sh: Tensor
    """``(N, K, 3)`` SH coefficients, K in {1, 4, 9, 16}; colour = SH(direction) + 0.5, clamped >= 0."""
    opacity: Tensor
    """``(N,)`` logits (opacity = sigmoid)."""
    log_scales: Tensor
    """``(N, 3)`` natural logarithms of the standard deviations along the local axes."""
    quats: Tensor
    """``(N, 4)`` rotations as quaternions ``(w, x, y, z)``, normalised where used."""

    def __post_init__(self) -> None:
        n = self.means.shape[0] if self.means.ndim == 2 else -1
        want = {"means": (n, 3), "opacity": (n,), "log_scales": (n, 3), "quats": (n, 4)}
        for name, shape in want.items():
            value = getattr(self, name)
            if not isinstance(value, Tensor) or tuple(value.shape) != shape or n < 0:
                got = tuple(value.shape) if isinstance(value, Tensor) else type(value).__name__
                raise InputError(f"Gaussians.{name}: expected shape {shape if n >= 0 else (-1, 3)}, got {got}")
        if not isinstance(self.sh, Tensor) or self.sh.ndim != 3 or self.sh.shape[0] != n or self.sh.shape[2] != 3:
            got = tuple(self.sh.shape) if isinstance(self.sh, Tensor) else type(self.sh).__name__
            raise InputError(f"Gaussians.sh: expected shape ({n}, K, 3), got {got}")
        sh_degree_of(int(self.sh.shape[1]))
        for f in fields(self):
            if not getattr(self, f.name).is_floating_point():
                raise InputError(f"Gaussians.{f.name}: expected a float tensor, got {getattr(self, f.name).dtype}")

    def __len__(self) -> int:
        return int(self.means.shape[0])

    @property
    def sh_degree(self) -> int:
        return sh_degree_of(int(self.sh.shape[1]))

    def to(self, *args, **kwargs) -> Gaussians:
        return Gaussians(**{f.name: getattr(self, f.name).to(*args, **kwargs) for f in fields(self)})

    def detach(self) -> Gaussians:
        return Gaussians(**{f.name: getattr(self, f.name).detach() for f in fields(self)})

    def select(self, index: Tensor) -> Gaussians:
        """The Gaussians at ``index`` (bool mask or integer indices)."""
        return Gaussians(**{f.name: getattr(self, f.name)[index] for f in fields(self)})

    def check_finite(self, where: str = "gaussians") -> None:
        for f in fields(self):
            if not torch.isfinite(getattr(self, f.name)).all():
                raise InputError(f"{where}: {f.name} holds NaN or infinite values")


def logit(p: float | Tensor) -> float | Tensor:
    """Inverse of the sigmoid (for opacities written as Inria stores them)."""
    if isinstance(p, Tensor):
        return torch.log(p) - torch.log1p(-p)
    return math.log(p) - math.log1p(-p)


def quat_to_rotmat(quats: Tensor) -> Tensor:
    """``(N, 4)`` quaternions ``(w, x, y, z)`` (normalised here) -> ``(N, 3, 3)`` rotation matrices."""
    q = quats / quats.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    w, x, y, z = q.unbind(-1)
    return torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ], dim=-1).reshape(q.shape[:-1] + (3, 3))


def covariances(gaussians: Gaussians) -> Tensor:
    """``(N, 3, 3)`` world covariances ``R S Sᵀ Rᵀ`` with ``S = diag(exp(log_scales))``."""
    R = quat_to_rotmat(gaussians.quats)
    M = R * torch.exp(gaussians.log_scales)[:, None, :]
    return M @ M.transpose(1, 2)
