"""Real spherical harmonics to degree 3 with Inria's 3DGS constants and sign convention."""

from __future__ import annotations

import torch
from torch import Tensor

from roguenerf.errors import InputError

C0 = 0.28209479177387814
C1 = 0.4886025119029199
C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154, -0.4570457994644658,
      1.445305721320277, -0.5900435899266435)


def sh_basis(degree: int, dirs: Tensor) -> Tensor:
    """``(..., (degree + 1)²)`` basis values at unit directions ``dirs`` ``(..., 3)``."""
    if degree not in (0, 1, 2, 3):
        raise InputError(f"SH degree: expected 0..3, got {degree}")
    x, y, z = dirs.unbind(-1)
    out = [torch.full_like(x, C0)]
    if degree > 0:
        out += [-C1 * y, C1 * z, -C1 * x]
    if degree > 1:
        xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
        out += [C2[0] * xy, C2[1] * yz, C2[2] * (2 * zz - xx - yy), C2[3] * xz, C2[4] * (xx - yy)]
    if degree > 2:
        out += [C3[0] * y * (3 * xx - yy), C3[1] * xy * z, C3[2] * y * (4 * zz - xx - yy),
                C3[3] * z * (2 * zz - 3 * xx - 3 * yy), C3[4] * x * (4 * zz - xx - yy),
                C3[5] * z * (xx - yy), C3[6] * x * (xx - 3 * yy)]
    return torch.stack(out, dim=-1)


def eval_sh(sh: Tensor, dirs: Tensor, degree: int | None = None) -> Tensor:
    """Colour ``(N, 3)`` of coefficients ``sh`` ``(N, K, 3)`` seen along ``dirs`` ``(N, 3)``
    (from the camera to the Gaussian; normalised here): ``max(Σ_k c_k Y_k(d) + 0.5, 0)``.

    ``degree`` defaults to the file's (``K = (degree + 1)²``); a lower one uses the first terms.
    """
    k = sh.shape[-2]
    if degree is None:
        degree = {1: 0, 4: 1, 9: 2, 16: 3}.get(k, -1)
    if degree < 0 or (degree + 1) ** 2 > k:
        raise InputError(f"eval_sh: {k} coefficients per channel cannot give degree {degree}")
    d = dirs / dirs.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    basis = sh_basis(degree, d)
    colour = (basis[..., :, None] * sh[..., : basis.shape[-1], :]).sum(-2)
    return (colour + 0.5).clamp_min(0.0)
