"""Camera conventions and validation (STUB: signatures are the contract)."""

from __future__ import annotations

import torch
from torch import Tensor

ORTHONORMAL_TOL = 1e-3
"""Rotations with ``max|R^T R - I| <= ORTHONORMAL_TOL`` are re-orthonormalised (SVD); worse ones raise."""


def opengl_to_opencv(world_from_cam: Tensor) -> Tensor:
    """OpenGL/Blender/nerfstudio camera-to-world (x right, y up, -z forward) to OpenCV.

    Args:
        world_from_cam: ``(..., 4, 4)`` or ``(..., 3, 4)``.
    Returns:
        Same shape, OpenCV convention (columns 1 and 2 of the rotation negated).
    """
    raise NotImplementedError


def opencv_to_opengl(world_from_cam: Tensor) -> Tensor:
    """Inverse of :func:`opengl_to_opencv` (the operation is its own inverse)."""
    raise NotImplementedError


def llff_to_opencv(poses: Tensor) -> Tensor:
    """LLFF ``poses_bounds.npy`` rotation columns (down, right, back) to OpenCV camera-to-world.

    Args:
        poses: ``(N, 3, 4)`` LLFF camera-to-world (the 3x5 blocks without the hwf column).
    Returns:
        ``(N, 4, 4)`` OpenCV camera-to-world.
    """
    raise NotImplementedError


def intrinsics_matrix(fx, fy, cx, cy, *, dtype=torch.float32) -> Tensor:
    """Build ``K`` ``(3, 3)`` (or ``(B, 3, 3)`` for tensor inputs); raises InputError if fx/fy <= 0 or non-finite."""
    raise NotImplementedError


def scale_intrinsics(K: Tensor, sx: float, sy: float) -> Tensor:
    """Intrinsics of the same camera after resizing the image by (sx, sy), pixel-centre aware."""
    raise NotImplementedError


def check_intrinsics(K: Tensor, name: str = "K") -> Tensor:
    """Validate ``(..., 3, 3)`` intrinsics: finite, fx > 0, fy > 0, last row (0, 0, 1).

    Returns ``K`` unchanged; raises :class:`~roguenerf.errors.InputError` naming ``name``.
    """
    raise NotImplementedError


def check_pose(world_from_cam: Tensor, name: str = "pose", tol: float = ORTHONORMAL_TOL) -> Tensor:
    """Validate ``(..., 4, 4)`` camera-to-world: finite, last row (0, 0, 0, 1), det(R) = +1,
    rotation orthonormal within ``tol`` (then re-orthonormalised with SVD; beyond it InputError).

    Returns the (possibly re-orthonormalised) pose, same dtype.
    """
    raise NotImplementedError


def ray_to_z_depth(ray_depth: Tensor, K: Tensor) -> Tensor:
    """Convert distance along the ray to z-depth: ``z = d / ||K^-1 [u+0.5, v+0.5, 1]||``.

    Args:
        ray_depth: ``(..., H, W)``; non-finite / <= 0 stays "unknown" (returned as 0).
        K: ``(3, 3)`` or ``(..., 3, 3)`` broadcastable.
    """
    raise NotImplementedError
