"""The normal equations of the neighbour pose fit's Gauss-Newton step (roguenerf.enhance.align):
the fused C kernel, or the torch reference (its ground truth)."""

from __future__ import annotations

import torch
from torch import Tensor

from roguenerf import native
from roguenerf.ops.backend import Body, as_contiguous, pick


def normal_equations(points: Tensor, sampled: Tensor, render: Tensor, use: Tensor, photo_from_cam: Tensor,
                     K: Tensor, c: float) -> tuple[Tensor, Tensor]:
    """``A`` ``(6, 6)`` and ``b`` ``(6,)`` float64 of one damped Gauss-Newton step (IRLS weights
    of the Charbonnier penalty ``c``), summed over the pixels ``use`` ``(N,)`` bool marks.

    ``points`` ``(N, 3)`` float32: the target's points (target frame); ``photo_from_cam``
    ``(4, 4)``: the neighbour pose being fitted; ``K`` ``(3, 3)``: the neighbour's intrinsics;
    ``sampled`` ``(9, N)``: the neighbour's colour and x, y gradients sampled at the points'
    projections; ``render`` ``(3, N)``. With ``J_c = gx_c ju + gy_c jv`` (a row per pixel and
    channel; ``ju``, ``jv`` the derivatives of the projection by the motion's 6 numbers: a
    rotation, then a move, in the neighbour's frame), ``A = sum_c J_c^T w J_c`` and
    ``b = sum_c J_c^T w r_c``. The kernel sums in double (handed back through float32); the
    reference in float32 matmuls."""
    R, t = photo_from_cam[:3, :3].float(), photo_from_cam[:3, 3].float()
    Kp = K.float()
    if pick(points, sampled, render) is Body.NATIVE:
        pose = torch.cat([R, t[:, None]], dim=1)
        return native.gauss_newton(as_contiguous(points), as_contiguous(sampled), as_contiguous(render),
                                   use.float(), pose.contiguous(), Kp.contiguous(), c)
    return reference(points, sampled, render, use, R, t, Kp, c)


def reference(points: Tensor, sampled: Tensor, render: Tensor, use: Tensor, R: Tensor, t: Tensor, Kp: Tensor,
              c: float) -> tuple[Tensor, Tensor]:
    """Over every pixel with weight 0 where a pixel is not used (no gather of the used ones),
    the normal equations summed per pixel before the colour channels are: ``sum_c J_c^T w J_c =
    ju^T (w sum_c gx_c^2) ju + ju^T (w sum_c gx_c gy_c) jv + jv^T (...) ju + jv^T (w sum_c gy_c^2) jv``."""
    P = torch.addmm(t, points, R.T)  # (N, 3) target points in the neighbour camera
    q = P @ Kp.T
    inv_z = torch.where(use, 1.0 / q[:, 2], 0.0)[:, None]  # 0 where not used: finite everywhere
    du = (Kp[0] - q[:, 0:1] * inv_z * Kp[2]) * inv_z  # (N, 3) d(u)/dP
    dv = (Kp[1] - q[:, 1:2] * inv_z * Kp[2]) * inv_z
    # dP/d(rotation j) = e_j x P, and a . (e_j x P) = (P x a)_j; dP/d(move) = identity.
    ju = torch.cat([torch.linalg.cross(P, du), du], dim=1)  # (N, 6)
    jv = torch.cat([torch.linalg.cross(P, dv), dv], dim=1)
    gx, gy = sampled[3:6], sampled[6:9]
    r = sampled[:3] - render  # (3, N)
    weight = torch.where(use, 1.0 / (r.square().sum(0) + c * c).sqrt(), 0.0)  # (N,)
    xx, xy, yy = ((gx * gx).sum(0) * weight, (gx * gy).sum(0) * weight, (gy * gy).sum(0) * weight)
    A = ju.T @ (xx[:, None] * ju + xy[:, None] * jv) + jv.T @ (xy[:, None] * ju + yy[:, None] * jv)
    b = ju.T @ ((r * gx).sum(0) * weight) + jv.T @ ((r * gy).sum(0) * weight)
    return A.double(), b.double()
