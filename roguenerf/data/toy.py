"""Toy scenes with exact geometry: textured planes and boxes, rendered by analytic ray casting.

World frame: z up, a floor at z = 0, a back wall at y = ``wall_y`` facing -y, 1-3 boxes
standing on the floor around the origin, and a far backdrop sphere so every ray hits
something (depth is finite everywhere). Every surface carries a solid (3D) texture made of
a few smooth sinusoids, so the colour is exact at any point and bilinear warping of a render
is accurate. Rays go through pixel centres (u + 0.5, v + 0.5) with direction
``R K^-1 [u + 0.5, v + 0.5, 1]``, whose camera z is 1: the hit parameter is the z-depth.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import Tensor

from roguenerf.errors import InputError
from roguenerf.geometry.cameras import check_intrinsics, check_pose, intrinsics_matrix

_WAVES = 4
_MISS = float("inf")


@dataclass
class ToyWorld:
    wall_y: float
    """The back wall is the plane y = wall_y."""
    boxes: Tensor
    """``(N, 7)`` float64: centre (x, y, z), half sizes (x, y, z), yaw about z (radians)."""
    sky_radius: float
    """Radius of the backdrop sphere centred at ``centre``."""
    centre: Tensor
    """``(3,)`` float64 point the camera paths look at."""
    base: Tensor
    """``(S, 3)`` mean colour per surface (floor, wall, boxes..., sky)."""
    freqs: Tensor
    """``(S, K, 3)`` wave vectors of the solid textures (cycles per world unit)."""
    phases: Tensor
    """``(S, K, 3)`` per-channel phases."""
    amps: Tensor
    """``(S, K)`` wave amplitudes."""


def _uniform(g: torch.Generator, lo: float, hi: float, *shape: int) -> Tensor:
    return lo + (hi - lo) * torch.rand(*shape, generator=g, dtype=torch.float64)


def make_toy_world(seed: int) -> ToyWorld:
    """A random toy world (deterministic in ``seed``): floor, back wall, 1-3 boxes, backdrop."""
    g = torch.Generator().manual_seed(int(seed))
    n_boxes = int(torch.randint(1, 4, (1,), generator=g))
    boxes = []
    for i in range(n_boxes):
        half = _uniform(g, 0.25, 0.6, 3)
        # Spread the boxes along x so they overlap in the images without intersecting.
        cx = (i - (n_boxes - 1) / 2) * 1.4 + float(_uniform(g, -0.2, 0.2, 1))
        cy = float(_uniform(g, -0.6, 0.6, 1))
        yaw = float(_uniform(g, -0.6, 0.6, 1))
        boxes.append(torch.tensor([cx, cy, float(half[2]), float(half[0]), float(half[1]), float(half[2]), yaw]))
    S = 2 + n_boxes + 1
    directions = torch.randn(S, _WAVES, 3, generator=g, dtype=torch.float64)
    directions = directions / directions.norm(dim=-1, keepdim=True)
    freqs = directions * _uniform(g, 0.3, 1.0, S, _WAVES, 1)
    # The floor is seen at grazing angles, where its texture is compressed most on screen.
    freqs[0] *= 0.4
    return ToyWorld(
        wall_y=float(_uniform(g, 2.0, 3.0, 1)),
        boxes=torch.stack(boxes).double(),
        sky_radius=40.0,
        centre=torch.tensor([0.0, 0.0, 0.4], dtype=torch.float64),
        base=_uniform(g, 0.25, 0.75, S, 3),
        freqs=freqs,
        phases=_uniform(g, 0.0, 2 * math.pi, S, _WAVES, 3),
        amps=_uniform(g, 0.04, 0.12, S, _WAVES),
    )


def _rot_z(angle: float) -> Tensor:
    c, s = math.cos(angle), math.sin(angle)
    return torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)


def _safe_div(num: Tensor, den: Tensor) -> Tensor:
    tiny = torch.where(den >= 0, 1e-300, -1e-300)
    return num / torch.where(den == 0, tiny, den)


def cast_rays(world: ToyWorld, origins: Tensor, dirs: Tensor) -> tuple[Tensor, Tensor]:
    """Nearest hit of rays ``origins + t * dirs`` (t > 0).

    Args:
        origins: ``(N, 3)`` or ``(3,)`` float64.
        dirs: ``(N, 3)`` float64 (any length; ``t`` is in units of it).
    Returns:
        ``t`` ``(N,)`` and the surface index ``(N,)`` (0 floor, 1 wall, 2.. boxes, last sky).
    """
    origins = origins.double().expand_as(dirs)
    dirs = dirs.double()
    hits = []
    t_floor = _safe_div(-origins[:, 2], dirs[:, 2])
    hits.append(torch.where(t_floor > 1e-9, t_floor, _MISS))
    t_wall = _safe_div(world.wall_y - origins[:, 1], dirs[:, 1])
    hits.append(torch.where(t_wall > 1e-9, t_wall, _MISS))
    for box in world.boxes:
        rot = _rot_z(float(box[6]))
        o_local = (origins - box[:3]) @ rot  # rows times R = R^T applied to each row
        d_local = dirs @ rot
        half = box[3:6]
        t1 = _safe_div(-half - o_local, d_local)
        t2 = _safe_div(half - o_local, d_local)
        t_near = torch.minimum(t1, t2).amax(dim=-1)
        t_far = torch.maximum(t1, t2).amin(dim=-1)
        hit = (t_far >= t_near) & (t_near > 1e-9)
        hits.append(torch.where(hit, t_near, _MISS))
    rel = origins - world.centre
    a = (dirs * dirs).sum(-1)
    b = (dirs * rel).sum(-1)
    c = (rel * rel).sum(-1) - world.sky_radius**2
    t_sky = (-b + torch.sqrt((b * b - a * c).clamp_min(0.0))) / a
    hits.append(torch.where(t_sky > 1e-9, t_sky, _MISS))
    t_all = torch.stack(hits, dim=-1)
    t, surface = t_all.min(dim=-1)
    return t, surface


def shade(world: ToyWorld, points: Tensor, surface: Tensor) -> Tensor:
    """Colour ``(N, 3)`` in [0, 1] of the solid texture of ``surface`` ``(N,)`` at ``points`` ``(N, 3)``."""
    freqs, phases, amps = world.freqs[surface], world.phases[surface], world.amps[surface]
    arg = 2 * math.pi * torch.einsum("nkd,nd->nk", freqs, points)[..., None] + phases
    colour = world.base[surface] + (amps[..., None] * torch.sin(arg)).sum(dim=1)
    return colour.clamp(0.0, 1.0)


def render_toy_view(
    world: ToyWorld, world_from_cam: Tensor, K: Tensor, height: int, width: int
) -> tuple[Tensor, Tensor]:
    """Render a toy world exactly from one camera.

    Args:
        world_from_cam: ``(4, 4)`` OpenCV camera-to-world.
        K: ``(3, 3)`` pixel-centre convention.
    Returns:
        ``rgb`` ``(3, H, W)`` float32 in [0, 1] and ``depth`` ``(1, H, W)`` float32 z-depth (> 0 everywhere).
    """
    if int(height) < 1 or int(width) < 1:
        raise InputError(f"height, width: expected >= 1, got {height}x{width}")
    pose = check_pose(world_from_cam, "world_from_cam").double()
    K = check_intrinsics(K).double()
    if pose.shape != (4, 4) or K.shape != (3, 3):
        raise InputError(f"expected world_from_cam (4, 4) and K (3, 3), got {tuple(pose.shape)} and {tuple(K.shape)}")
    v, u = torch.meshgrid(
        torch.arange(height, dtype=torch.float64) + 0.5, torch.arange(width, dtype=torch.float64) + 0.5, indexing="ij"
    )
    pix = torch.stack([u, v, torch.ones_like(u)], dim=-1).reshape(-1, 3)
    dirs_cam = pix @ torch.linalg.inv(K).T  # camera z = 1
    dirs = dirs_cam @ pose[:3, :3].T
    origin = pose[:3, 3]
    t, surface = cast_rays(world, origin, dirs)
    rgb = shade(world, origin + t[:, None] * dirs, surface)
    rgb = rgb.T.reshape(3, height, width).float()
    depth = t.reshape(1, height, width).float()
    return rgb, depth


def look_at(eye: Tensor, target: Tensor, up: Tensor | None = None) -> Tensor:
    """OpenCV camera-to-world ``(4, 4)`` float64 at ``eye`` ``(3,)`` looking at ``target`` ``(3,)`` (world z up)."""
    eye, target = eye.double(), target.double()
    up = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64) if up is None else up.double()
    forward = target - eye
    forward = forward / forward.norm()
    right = torch.linalg.cross(forward, up)
    if right.norm() < 1e-9:
        raise InputError("look_at: the viewing direction is parallel to 'up'")
    right = right / right.norm()
    down = torch.linalg.cross(forward, right)
    pose = torch.eye(4, dtype=torch.float64)
    pose[:3, :3] = torch.stack([right, down, forward], dim=-1)
    pose[:3, 3] = eye
    return pose


def toy_camera_path(world: ToyWorld, n: int, *, seed: int = 0, kind: str = "forward") -> Tensor:
    """``(n, 4, 4)`` float64 OpenCV camera-to-world poses looking at the scene.

    ``kind="forward"``: LLFF-like, cameras spread over a small patch in front of the scene
    (about 1.2 x 0.6 units at distance ~4.5), all looking at ``world.centre`` with a little
    jitter. ``kind="orbit"``: an arc of azimuths in [-60, 60] deg around the scene at radius
    ~4, heights 1-2.5 (object-centric, with large rotations between views).
    """
    if n < 0:
        raise InputError(f"n: expected >= 0, got {n}")
    g = torch.Generator().manual_seed(int(seed) + 7919)
    poses = []
    for i in range(n):
        frac = (i + 0.5) / max(n, 1)
        if kind == "forward":
            offset = torch.tensor([1.2 * (frac - 0.5), -4.5, 1.3 + 0.6 * float(_uniform(g, -0.5, 0.5, 1))])
            offset[0] += float(_uniform(g, -0.1, 0.1, 1))
            target = world.centre + _uniform(g, -0.15, 0.15, 3)
        elif kind == "orbit":
            azimuth = math.radians(-60 + 120 * frac + float(_uniform(g, -5, 5, 1)))
            radius = 4.0 + float(_uniform(g, -0.3, 0.3, 1))
            height = float(_uniform(g, 1.0, 2.5, 1))
            offset = torch.tensor([radius * math.sin(azimuth), -radius * math.cos(azimuth), height])
            target = world.centre
        else:
            raise InputError(f"kind: expected 'forward' or 'orbit', got {kind!r}")
        poses.append(look_at(world.centre + offset.double(), target))
    if not poses:
        return torch.empty(0, 4, 4, dtype=torch.float64)
    return torch.stack(poses)


def toy_intrinsics(height: int, width: int) -> Tensor:
    """``(3, 3)`` float64 K with a ~58 deg horizontal field of view, principal point at the image centre."""
    f = 0.9 * width
    return intrinsics_matrix(f, f, width / 2, height / 2, dtype=torch.float64)


def make_toy_scene(
    root,
    *,
    seed: int = 0,
    n_train: int = 8,
    n_test: int = 2,
    height: int = 48,
    width: int = 64,
    degradation=None,
    kind: str = "forward",
):
    """Render a toy scene and write it as a scene folder at ``root``; returns ``load_scene(root)``.

    Photos are exact renders; the "radiance-field renders" are ``degradation(photos, depths,
    generator)`` when given (it returns ``(renders, depths)``), else the photos blurred by a
    Gaussian (sigma 1 px) with exact depths. Test views are spread evenly along the path.
    """
    from kornia.filters import gaussian_blur2d

    from roguenerf.data.readers import load_scene
    from roguenerf.data.writers import write_scene_folder

    if n_train < 1 or n_test < 0:
        raise InputError(f"n_train, n_test: expected >= 1 and >= 0, got {n_train}, {n_test}")
    world = make_toy_world(seed)
    total = n_train + n_test
    poses = toy_camera_path(world, total, seed=seed, kind=kind)
    test_ids = {round((j + 0.5) * total / n_test) for j in range(n_test)} if n_test else set()
    test_ids = {min(i, total - 1) for i in test_ids}
    while len(test_ids) < n_test:  # only when rounding collides on tiny paths
        test_ids.add(next(i for i in range(total) if i not in test_ids))
    K = toy_intrinsics(height, width)
    photos, depths = zip(*(render_toy_view(world, pose, K, height, width) for pose in poses))
    photos, depths = torch.stack(photos), torch.stack(depths)
    generator = torch.Generator().manual_seed(int(seed))
    if degradation is None:
        renders = gaussian_blur2d(photos, (5, 5), (1.0, 1.0), border_type="replicate").clamp(0, 1)
        render_depths = depths
    else:
        renders, render_depths = degradation(photos, depths, generator)
    names, splits = [], []
    n_tr = n_te = 0
    for i in range(total):
        if i in test_ids:
            names.append(f"test_{n_te:03d}")
            splits.append("test")
            n_te += 1
        else:
            names.append(f"train_{n_tr:03d}")
            splits.append("train")
            n_tr += 1
    write_scene_folder(Path(root), names=names, photos=photos, renders=renders, depths=render_depths,
                       world_from_cam=poses, K=K, splits=splits)
    return load_scene(Path(root))
