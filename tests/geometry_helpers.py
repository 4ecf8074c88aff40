"""Rotations with known angles for the geometry tests (test_geometry, test_neighbours,
test_numerics, test_reproject, test_inference, test_enhance_select, test_temporal)."""

from __future__ import annotations

import math

import torch


def rot_x(a):
    c, s = math.cos(a), math.sin(a)
    return torch.tensor([[1, 0, 0], [0, c, -s], [0, s, c]], dtype=torch.float64)


def rot_y(a):
    c, s = math.cos(a), math.sin(a)
    return torch.tensor([[c, 0, s], [0, 1, 0], [-s, 0, c]], dtype=torch.float64)


def rot_z(a):
    c, s = math.cos(a), math.sin(a)
    return torch.tensor([[c, -s, 0], [s, c, 0], [0, 0, 1]], dtype=torch.float64)


def zyx(roll, pitch, yaw):
    return rot_z(yaw) @ rot_y(pitch) @ rot_x(roll)


def turned(pose: torch.Tensor, degrees: float, axis: int = 1) -> torch.Tensor:
    """``pose`` rotated in place by ``degrees`` about its own camera axis ``axis``."""
    a = math.radians(degrees)
    R = torch.eye(3, dtype=torch.float64)
    i, j = [k for k in range(3) if k != axis]
    R[i, i], R[i, j], R[j, i], R[j, j] = math.cos(a), -math.sin(a), math.sin(a), math.cos(a)
    out = pose.clone().to(torch.float64)
    out[:3, :3] = out[:3, :3] @ R
    return out
