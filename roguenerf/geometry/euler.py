"""Euler angles of rotation matrices (STUB)."""

from __future__ import annotations

from torch import Tensor


def wrap_angle(angle: Tensor) -> Tensor:
    """Wrap angles (radians) into [-pi, pi]."""
    raise NotImplementedError


def euler_angles(R: Tensor) -> Tensor:
    """Euler angles ``(..., 3)`` (roll, pitch, yaw; radians) of rotations ``(..., 3, 3)``.

    Finite at gimbal lock (pitch = +-pi/2): the convention there is stated in the docstring
    of the implementation and tested.
    """
    raise NotImplementedError
