"""Camera conventions and validation.

Internally every pose is an OpenCV camera-to-world ``world_from_cam`` (x right, y down,
z forward) and every ``K`` uses the pixel-centre convention: the centre of pixel (row v,
col u) sits at (u + 0.5, v + 0.5) in K's image coordinates (nerfstudio / COLMAP /
``../shared/data/lego``).
"""

from __future__ import annotations

import torch
from torch import Tensor

from roguenerf.errors import InputError
from roguenerf.geometry.depth import known_depth_mask

ORTHONORMAL_TOL = 1e-3
"""Rotations with ``max|R^T R - I| <= ORTHONORMAL_TOL`` are re-orthonormalised (SVD); worse ones raise."""

_FLIP_YZ = (1.0, -1.0, -1.0)


def _check_tensor(x, name: str, trailing: tuple[int, ...] | None = None) -> Tensor:
    if not isinstance(x, Tensor):
        raise InputError(f"{name}: expected a torch.Tensor, got {type(x).__name__}")
    if not x.is_floating_point():
        raise InputError(f"{name}: expected a floating-point tensor, got dtype {x.dtype}")
    if trailing is not None and tuple(x.shape[-len(trailing) :]) != trailing:
        want = ", ".join(str(t) for t in trailing)
        raise InputError(f"{name}: expected shape (..., {want}), got {tuple(x.shape)}")
    return x


def opengl_to_opencv(world_from_cam: Tensor) -> Tensor:
    """OpenGL/Blender/nerfstudio camera-to-world (x right, y up, -z forward) to OpenCV.

    Args:
        world_from_cam: ``(..., 4, 4)`` or ``(..., 3, 4)``.
    Returns:
        Same shape, OpenCV convention (columns 1 and 2 of the rotation negated).
    """
    _check_tensor(world_from_cam, "world_from_cam")
    if world_from_cam.shape[-1] != 4 or world_from_cam.shape[-2] not in (3, 4):
        got = tuple(world_from_cam.shape)
        raise InputError(f"world_from_cam: expected shape (..., 4, 4) or (..., 3, 4), got {got}")
    flip = world_from_cam.new_tensor((*_FLIP_YZ, 1.0))
    return world_from_cam * flip


def opencv_to_opengl(world_from_cam: Tensor) -> Tensor:
    """Inverse of :func:`opengl_to_opencv` (the operation is its own inverse)."""
    return opengl_to_opencv(world_from_cam)


def llff_to_opencv(poses: Tensor) -> Tensor:
    """LLFF ``poses_bounds.npy`` rotation columns (down, right, back) to OpenCV camera-to-world.

    Args:
        poses: ``(N, 3, 4)`` LLFF camera-to-world (the 3x5 blocks without the hwf column).
    Returns:
        ``(N, 4, 4)`` OpenCV camera-to-world.
    """
    _check_tensor(poses, "poses", (3, 4))
    if poses.ndim != 3:
        raise InputError(f"poses: expected shape (N, 3, 4), got {tuple(poses.shape)}")
    down, right, back, t = poses.unbind(-1)
    top = torch.stack([right, down, -back, t], dim=-1)
    bottom = poses.new_tensor((0.0, 0.0, 0.0, 1.0)).expand(poses.shape[0], 1, 4)
    return torch.cat([top, bottom], dim=-2)


def intrinsics_matrix(fx, fy, cx, cy, *, dtype=torch.float32) -> Tensor:
    """Build ``K`` ``(3, 3)`` (or ``(B, 3, 3)`` for tensor inputs); raises InputError if fx/fy <= 0 or non-finite.

    ``cx, cy`` are in the pixel-centre convention (an image of width W has its centre at W / 2).
    """
    fx, fy, cx, cy = (torch.as_tensor(v, dtype=dtype) for v in (fx, fy, cx, cy))
    fx, fy, cx, cy = torch.broadcast_tensors(fx, fy, cx, cy)
    zero, one = torch.zeros_like(fx), torch.ones_like(fx)
    K = torch.stack(
        [
            torch.stack([fx, zero, cx], -1),
            torch.stack([zero, fy, cy], -1),
            torch.stack([zero, zero, one], -1),
        ],
        -2,
    )
    return check_intrinsics(K, "K")


def scale_intrinsics(K: Tensor, sx: float, sy: float) -> Tensor:
    """Intrinsics of the same camera after resizing the image by (sx, sy), pixel-centre aware.

    With pixel centres at half-integers the image edges are at 0 and W, so resizing scales
    ``fx, cx`` by ``sx`` and ``fy, cy`` by ``sy`` with no half-pixel offset.

    Args:
        K: ``(..., 3, 3)``.
    """
    check_intrinsics(K)
    if not (sx > 0 and sy > 0):
        raise InputError(f"scale_intrinsics: expected positive scale factors, got sx={sx}, sy={sy}")
    scale = K.new_tensor([[sx, sx, sx], [sy, sy, sy], [1.0, 1.0, 1.0]])
    return K * scale


def check_intrinsics(K: Tensor, name: str = "K") -> Tensor:
    """Validate ``(..., 3, 3)`` intrinsics: finite, fx > 0, fy > 0, last row (0, 0, 1).

    Returns ``K`` unchanged; raises :class:`~roguenerf.errors.InputError` naming ``name``.
    """
    _check_tensor(K, name, (3, 3))
    if not torch.isfinite(K).all():
        raise InputError(f"{name}: expected finite intrinsics, got non-finite values")
    fx, fy = K[..., 0, 0], K[..., 1, 1]
    if (fx <= 0).any() or (fy <= 0).any():
        raise InputError(
            f"{name}: expected focal lengths fx > 0 and fy > 0, "
            f"got fx={fx.min().item():g}, fy={fy.min().item():g} (min)"
        )
    last = K[..., 2, :]
    if not torch.allclose(last, last.new_tensor((0.0, 0.0, 1.0)).expand_as(last), atol=1e-6):
        raise InputError(f"{name}: expected last row (0, 0, 1), got {last.reshape(-1, 3)[0].tolist()}")
    return K


def check_pose(world_from_cam: Tensor, name: str = "pose", tol: float = ORTHONORMAL_TOL) -> Tensor:
    """Validate ``(..., 4, 4)`` or ``(..., 3, 4)`` camera-to-world: finite, last row
    (0, 0, 0, 1), det(R) = +1, rotation orthonormal within ``tol`` (then re-orthonormalised
    with SVD; beyond it InputError). A 3x4 pose (the form most tools print) gets the row
    (0, 0, 0, 1) appended.

    Returns the (possibly re-orthonormalised) ``(..., 4, 4)`` pose, same dtype.
    """
    _check_tensor(world_from_cam, name)
    if world_from_cam.ndim < 2 or tuple(world_from_cam.shape[-2:]) not in ((4, 4), (3, 4)):
        raise InputError(f"{name}: expected a 4x4 or 3x4 camera-to-world matrix, shape (..., 4, 4) or "
                         f"(..., 3, 4), got {tuple(world_from_cam.shape)}")
    if world_from_cam.shape[-2] == 3:
        bottom = world_from_cam.new_tensor((0.0, 0.0, 0.0, 1.0)).expand(*world_from_cam.shape[:-2], 1, 4)
        world_from_cam = torch.cat([world_from_cam, bottom], dim=-2)
    if not torch.isfinite(world_from_cam).all():
        raise InputError(f"{name}: expected a finite 4x4 camera-to-world matrix, got non-finite values")
    last = world_from_cam[..., 3, :]
    if not torch.allclose(last, last.new_tensor((0.0, 0.0, 0.0, 1.0)).expand_as(last), atol=1e-6):
        raise InputError(f"{name}: expected last row (0, 0, 0, 1), got {last.reshape(-1, 4)[0].tolist()}")
    R = world_from_cam[..., :3, :3].double()
    eye = torch.eye(3, dtype=R.dtype, device=R.device)
    err = (R.transpose(-1, -2) @ R - eye).abs().amax(dim=(-2, -1))
    if (err > tol).any():
        raise InputError(
            f"{name}: expected an orthonormal rotation (max|R^T R - I| <= {tol:g}), got {err.max().item():.3g}"
        )
    if (torch.linalg.det(R) <= 0).any():
        raise InputError(
            f"{name}: expected a rotation with det(R) = +1, got a reflection (det = -1); mixed-up axis convention?"
        )
    # Only touch poses that are visibly off: an exact rotation stays bit-identical.
    needs_fix = err > 32 * torch.finfo(world_from_cam.dtype).eps
    if not needs_fix.any():
        return world_from_cam
    U, _, Vh = torch.linalg.svd(R)
    fixed = (U @ Vh).to(world_from_cam.dtype)
    out = world_from_cam.clone()
    out[..., :3, :3] = torch.where(needs_fix[..., None, None], fixed, world_from_cam[..., :3, :3])
    return out


def as_world_from_cam(x, name: str = "world_from_cam", tol: float = ORTHONORMAL_TOL) -> Tensor:
    """The one validation of camera-to-world poses for every entry that takes them.

    Accepts ``(4, 4)`` / ``(..., 4, 4)`` and ``(3, 4)`` / ``(..., 3, 4)`` (padded with the row
    ``0 0 0 1``), as a tensor or anything :func:`torch.as_tensor` takes (lists, NumPy; made
    float64; integer tensors too). Refuses, with :class:`~roguenerf.errors.InputError` naming
    ``name`` and the index of the first bad pose in a batch: bool/complex dtypes, other shapes,
    non-finite values, a bottom row other than ``0 0 0 1``, a reflection (det -1: mixed-up axis
    convention) and a scaled or sheared rotation (``max|R^T R - I| > tol``). Rotations within
    ``tol`` are re-orthonormalised (:func:`check_pose`); float64 stays float64.
    """
    if not isinstance(x, Tensor):
        try:
            x = torch.as_tensor(x, dtype=torch.float64)
        except (TypeError, ValueError, RuntimeError) as exc:
            raise InputError(f"{name}: expected a 4x4 or 3x4 matrix of numbers ({exc})") from None
    if x.dtype == torch.bool or x.is_complex():
        raise InputError(f"{name}: expected a real-valued pose, got dtype {x.dtype}")
    if not x.is_floating_point():
        x = x.to(torch.float64)  # integer poses (an identity written as ints) are exact
    if x.ndim < 2 or x.shape[-1] != 4 or x.shape[-2] not in (3, 4):
        raise InputError(f"{name}: expected a 4x4 or 3x4 camera-to-world matrix, shape (..., 4, 4) or "
                         f"(..., 3, 4), got {tuple(x.shape)}")
    if x.shape[-2] == 3:
        bottom = x.new_tensor((0.0, 0.0, 0.0, 1.0)).expand(*x.shape[:-2], 1, 4)
        x = torch.cat([x, bottom], dim=-2)
    flat = x.reshape(-1, 4, 4)
    batched = x.ndim > 2

    def where(i: int) -> str:
        return f"{name}[{i}]" if batched else name

    finite = torch.isfinite(flat).flatten(1).all(dim=1)
    if not bool(finite.all()):
        i = int((~finite).nonzero()[0])
        raise InputError(f"{where(i)}: expected a finite camera-to-world matrix, got non-finite values (NaN or inf)")
    last = flat[:, 3, :]
    bad = (last - last.new_tensor((0.0, 0.0, 0.0, 1.0))).abs().amax(dim=1) > 1e-6
    if bool(bad.any()):
        i = int(bad.nonzero()[0])
        raise InputError(f"{where(i)}: expected bottom row (0, 0, 0, 1), got {flat[i, 3].tolist()}")
    R = flat[:, :3, :3].double()
    det = torch.linalg.det(R)
    err = (R.transpose(-1, -2) @ R - torch.eye(3, dtype=R.dtype)).abs().amax(dim=(-2, -1))
    bad = det <= 0
    if bool(bad.any()):
        i = int(bad.nonzero()[0])
        raise InputError(f"{where(i)}: expected a proper rotation (det +1), got det {float(det[i]):.3g}: a "
                         "reflection (mixed-up axis convention, e.g. OpenGL vs OpenCV with one axis flipped)")
    bad = err > tol
    if bool(bad.any()):
        i = int(bad.nonzero()[0])
        scale = float(det[i]) ** (1 / 3)
        raise InputError(f"{where(i)}: expected an orthonormal rotation (max|R^T R - I| <= {tol:g}), got "
                         f"{float(err[i]):.3g} (det {float(det[i]):.3g}: a scaled or sheared rotation; "
                         f"scale {scale:.3g} belongs in the translation and depth, not in R)")
    return check_pose(x, name, tol)


def relative_pose(world_from_a: Tensor, world_from_b: Tensor) -> Tensor:
    """``a_from_b = C_a^-1 C_b`` of two rigid camera-to-world poses, formed in **float64**.

    ``R = R_a^T R_b``, ``t = R_a^T (t_b - t_a)``: the translations are subtracted first, so two
    cameras 5e6 units from the origin and a few units apart give their relative pose to
    float64 rounding (1e-9), whatever dtype the caller casts the result to afterwards. Cast
    poses to float32 only *after* this step. Inputs ``(..., 4, 4)`` broadcast; returns float64.
    """
    A = world_from_a.to(torch.float64)
    B = world_from_b.to(torch.float64)
    R_a_T = A[..., :3, :3].transpose(-1, -2)
    rot = R_a_T @ B[..., :3, :3]
    trans = R_a_T @ (B[..., :3, 3:] - A[..., :3, 3:])
    # rot carries the broadcast batch shape (torch.broadcast_shapes would import torch._refs and
    # sympy on its first call: 0.65 s of every command's start-up).
    out = torch.zeros((*rot.shape[:-2], 4, 4), dtype=torch.float64, device=A.device)
    out[..., :3, :3] = rot
    out[..., :3, 3:] = trans
    out[..., 3, 3] = 1.0
    return out


def pixel_rays(K: Tensor, size: tuple[int, int]) -> Tensor:
    """``(H, W, 3)`` float64 ``K^-1 [u + 0.5, v + 0.5, 1]`` through every pixel centre (z = 1 for
    a K without a third-row twist): times a z-depth map, each pixel's 3-D point in its camera."""
    h, w = size
    v, u = torch.meshgrid(torch.arange(h, dtype=torch.float64) + 0.5, torch.arange(w, dtype=torch.float64) + 0.5,
                          indexing="ij")
    return torch.stack([u, v, torch.ones_like(u)], dim=-1) @ torch.linalg.inv(K.to(torch.float64)).T


def ray_to_z_depth(ray_depth: Tensor, K: Tensor) -> Tensor:
    """Convert distance along the ray to z-depth: ``z = d / ||K^-1 [u+0.5, v+0.5, 1]||``.

    Args:
        ray_depth: ``(..., H, W)``; unknown depth (:mod:`roguenerf.geometry.depth`) is returned as 0.
        K: ``(3, 3)`` or ``(..., 3, 3)`` broadcastable.
    Returns:
        ``(..., H, W)`` z-depth.
    """
    _check_tensor(ray_depth, "ray_depth")
    check_intrinsics(K)
    if ray_depth.ndim < 2:
        raise InputError(f"ray_depth: expected shape (..., H, W), got {tuple(ray_depth.shape)}")
    H, W = ray_depth.shape[-2:]
    K = K.to(ray_depth.dtype)
    u = torch.arange(W, dtype=ray_depth.dtype) + 0.5
    v = torch.arange(H, dtype=ray_depth.dtype) + 0.5
    fx, fy, cx, cy = (K[..., i, j][..., None, None] for i, j in ((0, 0), (1, 1), (0, 2), (1, 2)))
    skew = K[..., 0, 1][..., None, None]
    y = (v[:, None] - cy) / fy
    x = (u[None, :] - cx - skew * y) / fx
    norm = torch.sqrt(x * x + y * y + 1.0)
    known = known_depth_mask(ray_depth)
    return torch.where(known, torch.nan_to_num(ray_depth, nan=0.0, posinf=0.0, neginf=0.0) / norm, 0.0)
