"""Poses that are a little wrong: random rigid perturbations of cameras (float64).

Real poses are off (COLMAP's error, a camera optimiser that moves them on purpose), so a user's
renders often match poses slightly different from the dataset's. Training with perturbed
neighbour poses (``TrainConfig.neighbour_pose_noise``) and the pose-noise sweep of
``bench/kinds.py`` both use :func:`perturb_poses`, with the convention of
:class:`~roguenerf.data.degrade.Degradation`: ``rotation_deg`` and ``translation`` are RMS sizes of
the whole rotation angle and displacement (each axis gets ``1/sqrt(3)`` of them), and a
translation given as a share is of :func:`camera_spread`.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from roguenerf.errors import InputError


def camera_spread(world_from_cam: Tensor) -> float:
    """The cameras' spread: RMS distance of the centres ``(M, 4, 4)[:, :3, 3]`` from their mean
    (float64; 0 for one camera)."""
    centres = world_from_cam[..., :3, 3].to(torch.float64).reshape(-1, 3)
    if centres.shape[0] == 0:
        raise InputError("camera_spread: expected at least one camera, got none")
    return float((centres - centres.mean(dim=0)).pow(2).sum(dim=1).mean().sqrt())


def axis_angle_to_matrix(rotvec: Tensor) -> Tensor:
    """Axis-angle vectors ``(..., 3)`` (radians) -> proper rotations ``(..., 3, 3)``, in float64
    (Rodrigues: ``I + sin(t)/t [w]x + (1 - cos(t))/t^2 [w]x^2``, the two factors by their Taylor
    series below 1e-4 rad, where float64 is exact to their third term; kornia's
    ``axis_angle_to_rotation_matrix`` is the tests' reference; plain torch here, because the pose
    fits call it on every step and importing kornia costs a command 0.3 s)."""
    w = rotvec.to(torch.float64)
    x, y, z = w.unbind(-1)
    zero = torch.zeros_like(x)
    skew = torch.stack([zero, -z, y, z, zero, -x, -y, x, zero], dim=-1).reshape(*w.shape[:-1], 3, 3)
    t2 = w.square().sum(-1)
    t = t2.sqrt()
    small = t < 1e-4
    safe_t = torch.where(small, torch.ones_like(t), t)
    a = torch.where(small, 1.0 - t2 / 6.0, torch.sin(safe_t) / safe_t)
    b = torch.where(small, 0.5 - t2 / 24.0, (1.0 - torch.cos(safe_t)) / safe_t.square())
    eye = torch.eye(3, dtype=torch.float64, device=w.device)
    return eye + a[..., None, None] * skew + b[..., None, None] * (skew @ skew)


def perturb_poses(world_from_cam: Tensor, rotation_deg: float, translation: float,
                  generator: torch.Generator | None = None) -> Tensor:
    """Each camera ``(..., 4, 4)`` turned about its own centre by a random rotation and moved by a
    random displacement: ``R' = R exp([w]x)``, ``t' = t + d``, with ``w`` and ``d`` Gaussian,
    ``E|w|^2 = radians(rotation_deg)^2`` and ``E|d|^2 = translation^2`` (pose units).

    Returns float64 poses (rotations proper to float64 rounding). Draws ``6 x cameras`` normal
    numbers from ``generator`` whatever the sizes (zero sizes return the poses unchanged, as float64).
    """
    if not (math.isfinite(rotation_deg) and rotation_deg >= 0 and math.isfinite(translation) and translation >= 0):
        raise InputError(f"pose noise: expected finite sizes >= 0, got {rotation_deg} deg and {translation}")
    poses = world_from_cam.to(torch.float64)
    shape = poses.shape[:-2]
    draws = torch.randn(*shape, 6, generator=generator, dtype=torch.float64)
    if rotation_deg == 0 and translation == 0:
        return poses.clone()
    w = draws[..., :3] * (math.radians(rotation_deg) / math.sqrt(3.0))
    d = draws[..., 3:] * (translation / math.sqrt(3.0))
    out = poses.clone()
    out[..., :3, :3] = poses[..., :3, :3] @ axis_angle_to_matrix(w)
    out[..., :3, 3] = poses[..., :3, 3] + d
    return out
