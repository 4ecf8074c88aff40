"""Euler angles of rotation matrices and the angular distance used for neighbour selection."""

from __future__ import annotations

import math

import torch
from torch import Tensor

GIMBAL_EPS = 1e-6
"""Below this ``cos(pitch)`` the rotation is treated as gimbal-locked (roll set to 0)."""


def wrap_angle(angle: Tensor) -> Tensor:
    """Wrap angles (radians) into [-pi, pi]."""
    return torch.remainder(angle + math.pi, 2 * math.pi) - math.pi


def euler_angles(R: Tensor) -> Tensor:
    """Euler angles ``(..., 3)`` (roll, pitch, yaw; radians) of rotations ``(..., 3, 3)``.

    Convention: ``R = Rz(yaw) @ Ry(pitch) @ Rx(roll)`` (intrinsic z-y'-x'', as in aviation),
    roll and yaw in [-pi, pi], pitch in [-pi/2, pi/2].

    Gimbal lock (``cos(pitch) < GIMBAL_EPS``, pitch = +-pi/2): only ``yaw -+ roll`` is
    determined; we return roll = 0 and put the whole in-plane angle into
    ``yaw = atan2(-R[0, 1], R[1, 1])``. Euler angles therefore jump there (a rotation with
    pitch 89.99 deg and roll 30 deg is close to one with pitch 90 deg and roll 0);
    :func:`angular_distance` is built to stay sensible across that jump.
    """
    r00, r01 = R[..., 0, 0], R[..., 0, 1]
    r10, r11 = R[..., 1, 0], R[..., 1, 1]
    r20, r21, r22 = R[..., 2, 0], R[..., 2, 1], R[..., 2, 2]
    cos_pitch = torch.sqrt(r00 * r00 + r10 * r10)
    # atan2 of (sin, cos) instead of asin(-r20): exact at +-pi/2 and no NaN when |r20| > 1 by rounding.
    pitch = torch.atan2(-r20, cos_pitch)
    locked = cos_pitch < GIMBAL_EPS
    roll = torch.where(locked, torch.zeros_like(r00), torch.atan2(r21, r22))
    yaw = torch.where(locked, torch.atan2(-r01, r11), torch.atan2(r10, r00))
    return torch.stack([roll, pitch, yaw], dim=-1)


def euler_distance(R_a: Tensor, R_b: Tensor) -> Tensor:
    """The paper's dist_ang: ``mean |wrap(euler(R_a) - euler(R_b))|`` over the three angles.

    Args:
        R_a, R_b: ``(..., 3, 3)`` broadcastable.
    Returns:
        ``(...)`` radians.
    """
    return wrap_angle(euler_angles(R_a) - euler_angles(R_b)).abs().mean(dim=-1)


def angular_distance(R_a: Tensor, R_b: Tensor) -> Tensor:
    """Angular distance for neighbour ranking, robust at gimbal lock.

    ``min(euler_distance(R_a, R_b), mean |euler(R_a^T R_b)|)``. Why the minimum: small Euler
    differences always mean close rotations (Euler -> R is Lipschitz), so the paper's
    measure can only overstate a distance, and it does so where Euler angles jump (pitch
    near +-90 deg, or roll/yaw near +-pi before wrapping). The Euler angles of the relative
    rotation are continuous around the identity, so near-identical rotations always get a
    small distance. Wherever the paper's term is the smaller one it is used unchanged.

    Args:
        R_a, R_b: ``(..., 3, 3)`` broadcastable.
    Returns:
        ``(...)`` radians, ``>= 0``, ``0`` for identical rotations.
    """
    relative = R_a.transpose(-1, -2) @ R_b
    rel = euler_angles(relative).abs().mean(dim=-1)
    return torch.minimum(euler_distance(R_a, R_b), rel)


def rotation_angle(R_a: Tensor, R_b: Tensor | None = None) -> Tensor:
    """The geodesic angle between two rotations, in degrees: the angle of ``R_a^T R_b`` (of
    ``R_a`` itself when ``R_b`` is None).

    Args:
        R_a, R_b: ``(..., 3, 3)`` broadcastable.
    Returns:
        ``(...)`` degrees in [0, 180]; computed in the inputs' dtype (pass float64 near 0).
    """
    relative = R_a if R_b is None else R_a.transpose(-1, -2) @ R_b
    cos = ((relative.diagonal(dim1=-2, dim2=-1).sum(-1) - 1) / 2).clamp(-1, 1)
    return torch.rad2deg(torch.acos(cos))
