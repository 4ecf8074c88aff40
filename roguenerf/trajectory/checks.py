"""Does a camera path (or one view's camera) live in the scene's world? Checks run before any
frame is enhanced: :func:`check_camera_path`, :func:`check_camera` (one camera) and
:func:`check_path` (those and the frames' depth type, reading the frames they need).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import Tensor

from roguenerf.errors import CameraMismatchError, InputError
from roguenerf.trajectory.readers import CameraPath, find_path_frames

log = logging.getLogger("roguenerf.paths")


FAR_FACTOR = 3.0
"""A path camera farther than this many scene sizes from every scene camera is "far" (scene
size: the larger of the cameras' spread and their median known depth)."""
MIN_SEEN = 0.25
"""A path camera "sees" the scene when at least this share of its probed known-depth pixels land,
at the depth they have there, in a training photo it would use (a right path: ~all of them on the
toy scenes; one in the model's world without its dataparser transform: ~9 %; flipped axes: 0)."""
DEPTH_AGREEMENT = 0.05
"""A training view sees a path pixel's surface point when its own depth there agrees to this
(relative): a path in the wrong space puts its points in free space or behind surfaces."""
CHECK_FRAMES = 12
"""How many path cameras (evenly spread, first and last included) :func:`check_camera_path` probes."""
CHECK_PIXELS = 64 * 64
"""Pixels probed per path camera (a regular subsample of its depth)."""


@dataclass
class PathCheck:
    """What :func:`check_camera_path` found; ``problem`` is None when the path looks right."""

    checked: list[int]
    seen: dict[int, float]
    """Path camera -> share of its probed pixels seen consistently by a training photo (None: no known depth)."""
    distance: dict[int, float]
    """Path camera -> distance to the nearest scene camera, in scene sizes."""
    lost: list[int]
    far: list[int]
    worst: int | None
    problem: str | None = None
    warning: str | None = None
    cause: str | None = None
    """The likeliest cause when ``problem`` or ``warning`` is set (:class:`~roguenerf.errors.CameraMismatchError`)."""


def _probe(depth: Tensor, K: Tensor, pixels: int = CHECK_PIXELS) -> tuple[Tensor, Tensor]:
    """A regular subsample of ``depth`` ``(1, H, W)`` and its intrinsics (pixel-centre exact)."""
    h, w = depth.shape[-2:]
    step = max(1, int((h * w / pixels) ** 0.5))
    sub = depth[..., ::step, ::step]
    K_sub = K.to(torch.float64).clone()
    K_sub[:2] /= step
    K_sub[0, 2] += 0.5 - 0.5 / step
    K_sub[1, 2] += 0.5 - 0.5 / step
    return sub, K_sub


def _consistent(points: Tensor, depth: Tensor, K: Tensor, world_from_cam: Tensor, tol: float) -> Tensor:
    """Which world ``points`` ``(N, 3)`` float64 a view sees where its own depth says a surface is:
    in front, inside the image, ``|z - depth| <= tol * depth`` at the nearest pixel."""
    from roguenerf.geometry import known_depth_mask

    pose = world_from_cam.to(torch.float64)
    cam = (points - pose[:3, 3]) @ pose[:3, :3]
    z = cam[:, 2]
    front = z > 1e-9
    zs = torch.where(front, z, torch.ones_like(z))
    K = K.to(torch.float64)
    u = K[0, 0] * cam[:, 0] / zs + K[0, 1] * cam[:, 1] / zs + K[0, 2]
    v = K[1, 1] * cam[:, 1] / zs + K[1, 2]
    h, w = depth.shape[-2:]
    inside = front & (u >= 0) & (u < w) & (v >= 0) & (v < h)
    col = u.clamp(0, w - 1).floor().long()
    row = v.clamp(0, h - 1).floor().long()
    d = depth.reshape(h, w).to(torch.float64)[row, col]
    known = known_depth_mask(d)
    return inside & known & ((z - d).abs() <= tol * d.abs())


def _held_out_seen(scene, train: list[int], train_depths: dict, neighbours: int, views: int = 3) -> list[float]:
    """:func:`_seen_share` of up to ``views`` of the scene's held-out views that have a depth
    (the field's own novel-view renders), evenly spread."""
    held = [i for i in scene.indices("test") if scene.frames[i].depth_path is not None]
    held = held[:: max(1, len(held) // views)][:views]
    out = []
    for i in held:
        frame = scene.frames[i]
        share = _seen_share(scene, train, train_depths, scene.depth(i).float(), frame.K,
                            frame.world_from_cam.to(torch.float64), neighbours)
        if share is not None:
            out.append(share)
    return out


def _seen_share(scene, train: list[int], train_depths: dict, depth: Tensor, K: Tensor, pose: Tensor,
                neighbours: int) -> float | None:
    """Share of the probed known-depth pixels of one camera whose surface point some chosen
    training view sees at its own depth (within :data:`DEPTH_AGREEMENT`)."""
    from roguenerf.geometry import known_depth_mask, select_neighbours

    sub, K_sub = _probe(depth, K)
    z = sub.reshape(-1).to(torch.float64)
    known = known_depth_mask(z)
    if not bool(known.any()):
        return None
    h, w = sub.shape[-2:]
    v, u = torch.meshgrid(torch.arange(h, dtype=torch.float64) + 0.5, torch.arange(w, dtype=torch.float64) + 0.5,
                          indexing="ij")
    y = (v.reshape(-1) - K_sub[1, 2]) / K_sub[1, 1]
    x = (u.reshape(-1) - K_sub[0, 2] - K_sub[0, 1] * y) / K_sub[0, 0]
    cam = torch.stack([x, y, torch.ones_like(x)], -1)[known] * z[known, None]
    pose = pose.to(torch.float64)
    points = cam @ pose[:3, :3].T + pose[:3, 3]
    poses = scene.poses(train).to(torch.float64)
    picked = select_neighbours(pose, poses, min(neighbours, len(train)), candidates=max(8, neighbours))
    seen = torch.zeros(points.shape[0], dtype=torch.bool)
    for p in picked.tolist():
        i = train[p]
        if i not in train_depths:
            train_depths[i] = scene.depth(i).float()
        seen |= _consistent(points, train_depths[i], scene.frames[i].K, poses[p], DEPTH_AGREEMENT)
    return float(seen.sum()) / float(known.sum())


def _depth_type_problem(scene, camera_path: CameraPath, raw_of, given: str, frames: int = 4) -> str | None:
    """:func:`~roguenerf.data.exports.check_depth_type` for a path: a few frames' stored depth
    against the z-depth of the training view nearest each (the scene's depth is z already)."""
    from roguenerf.data.exports import check_depth_type, depth_type_problem

    train = scene.indices("train")
    T = len(camera_path)
    if not train or T == 0:
        return None
    poses = scene.poses(train).to(torch.float64)
    pairs = []
    for t in sorted({round(k * (T - 1) / max(frames - 1, 1)) for k in range(min(frames, T))}):
        pose = camera_path.world_from_cam[t].to(torch.float64)
        near = int((poses[:, :3, 3] - pose[:3, 3]).norm(dim=-1).argmin())
        i = train[near]
        pairs.append(((raw_of(t).double(), camera_path.K[t], pose),
                      (scene.depth(i).double(), scene.frames[i].K, poses[near])))
    check = check_depth_type(pairs, b_is_z=True)
    return depth_type_problem(check, given, "the path's depths", "its frames and the nearest training views")


def _convention(source: str) -> tuple[str, str]:
    """How a camera file of ``source`` format is read, and how to convert poses of the other convention."""
    if source == "inria":
        return ("Inria's cameras.json is read as OpenCV camera-to-world (rotation and position, as 3DGS's "
                "train.py writes them)", "convert OpenGL poses (columns 1 and 2 negated)")
    if source == "colmap":
        return ("COLMAP's images.txt / images.bin is read as OpenCV world-to-camera (qvec, tvec, as COLMAP "
                "writes them)", "convert OpenGL poses (columns 1 and 2 of camera-to-world negated)")
    return ("camera paths and transforms-style lists are read as OpenGL (nerfstudio, Blender)",
            "convert OpenCV poses (columns 1 and 2 negated)")


def check_camera_path(scene, camera_path: CameraPath, depth_of, *, neighbours: int = 4,
                      frames: int = CHECK_FRAMES, override: str = "--force (force=True)") -> PathCheck:
    """Does the path live in the scene's world? A cheap check before any enhancement.

    A path in another coordinate space (a nerfstudio ``camera_path.json`` in the model's world
    read without the model's ``dataparser_transforms.json``, OpenGL axes read as OpenCV or the
    reverse, other units) enhances nothing and says nothing: its cameras see none of the training
    photos. For up to ``frames`` path cameras (evenly spread) this measures the distance to the
    nearest scene camera and which share of ~:data:`CHECK_PIXELS` pixels of the frame's depth
    (``depth_of(t) -> (1, H, W)`` z-depth) the training photos the enhancer would pick see
    at their own depth.

    ``problem`` is set when a checked camera is farther than :data:`FAR_FACTOR` scene sizes from
    every scene camera and does not see the photos (or has no known depth to tell), or when at
    least half of the checked cameras with known depth see less than :data:`MIN_SEEN` of their
    pixels; ``warning`` when fewer do. Both name the worst camera
    (index and label) and the likely causes; ``cause`` the likeliest (see
    :class:`~roguenerf.errors.CameraMismatchError`): the other axis convention or another unit
    when the worst camera, flipped or rescaled, sees the photos. ``override`` is how the caller
    goes on anyway (named in the messages). A path with ``source == "camera"`` is one view's
    camera (:func:`check_camera`) and is worded so.
    """
    from roguenerf.geometry import known_depth_mask
    from roguenerf.geometry.cameras import opengl_to_opencv

    train = scene.indices("train")
    if not train:
        raise InputError("the scene has no training views: a camera path has nothing to be enhanced with")
    one = camera_path.source == "camera"
    T = len(camera_path)
    n = max(1, min(frames, T))
    checked = sorted({round(k * (T - 1) / max(n - 1, 1)) for k in range(n)})
    positions = scene.poses().to(torch.float64)[:, :3, 3]
    spread = float((positions - positions.mean(0)).norm(dim=-1).max())
    train_depths: dict[int, Tensor] = {}
    medians = []
    for i in train[:: max(1, len(train) // 8)][:8]:
        train_depths[i] = scene.depth(i).float()
        d = train_depths[i][known_depth_mask(train_depths[i])]
        if d.numel():
            medians.append(float(d.median()))
    size = max(spread, sorted(medians)[len(medians) // 2] if medians else 0.0) or 1.0
    seen: dict[int, float | None] = {}
    distance: dict[int, float] = {}
    depths = {}
    for t in checked:
        pose = camera_path.world_from_cam[t]
        distance[t] = float((positions - pose[:3, 3]).norm(dim=-1).min()) / size
        depths[t] = depth_of(t)
        seen[t] = _seen_share(scene, train, train_depths, depths[t], camera_path.K[t], pose, neighbours)
    # Far and not seeing the scene (or without depth to tell): a camera that is far but sees the
    # training photos at their depth is a wide shot of the right world.
    far = [t for t in checked if distance[t] > FAR_FACTOR and (seen[t] is None or seen[t] < MIN_SEEN)]
    with_depth = [t for t in checked if seen[t] is not None]
    lost = [t for t in with_depth if seen[t] < MIN_SEEN]
    worst = None
    if far:
        worst = max(far, key=lambda t: distance[t])
    elif lost:
        worst = min(lost, key=lambda t: (seen[t], -distance[t]))
    result = PathCheck(checked=checked, seen=seen, distance=distance, lost=lost, far=far, worst=worst)
    if worst is None:
        return result
    name = "the camera" if one else f"camera {worst} ({camera_path.label(worst)})"
    what = (f"{name} lies {distance[worst]:.1f} scene sizes from the nearest scene camera" if far else
            f"{name} sees almost none of the training photos (only "
            f"{100 * seen[worst]:.1f}% of its pixels land at their depth in the photos nearest it)")
    summary = ("" if one else
               f"{len(far)} of {len(checked)} checked cameras are far from the scene's cameras; worst: " if far else
               f"{len(lost)} of {len(with_depth)} checked cameras see almost none of the training photos; worst: ")
    causes = []
    cause = "world"
    if camera_path.source == "nerfstudio":
        causes.append("a nerfstudio camera_path.json is in the model's world: it needs the trained model's "
                      "dataparser_transforms.json (--dataparser-transforms, or put it in the scene folder)")
    # Would the other axis convention fit, or another unit? Then say so first.
    enough = max(2 * MIN_SEEN, 2 * (seen.get(worst) or 0.0))
    flipped = opengl_to_opencv(camera_path.world_from_cam[worst])
    share = _seen_share(scene, train, train_depths, depths[worst], camera_path.K[worst], flipped, neighbours)
    read_as, fix = _convention(camera_path.source)
    scaled = _rescaled_fit(scene, train, train_depths, depths[worst], camera_path.K[worst],
                           camera_path.world_from_cam[worst], neighbours, positions)
    if share is not None and share >= enough:
        cause = "convention"
        causes.insert(0, ("OpenGL vs OpenCV axes: with the y and z axes flipped this camera sees "
                          f"{100 * share:.0f}% of its pixels; " + (
                              "its pose is in the other convention (columns 1 and 2 negated)" if one else
                              f"{read_as}: {fix}")))
    elif scaled is not None and scaled[0] >= enough:
        cause = "scale"
        fit, factor, depth_too, here, typical = scaled
        causes.insert(0, (f"another unit: with its position{' and depth' if depth_too else ''} scaled by "
                          f"{factor:.3g} this camera sees {100 * fit:.0f}% of its pixels (it lies {here:.3g} from "
                          f"the world's origin, the scene's cameras about {typical:.3g}); give its pose"
                          f"{' and depth' if depth_too else ''} in the scene's units"))
    elif camera_path.source == "inria" and not one:
        causes.append(f"a rotation written world-to-camera (transposed) or with OpenGL axes ({read_as})")
    else:
        causes.append("OpenGL vs OpenCV axes (" + ("the pose's convention" if one else read_as) + ")")
        # Do the field's own renders of the scene's held-out views pass the same test? When none
        # does, the field's depth is off on every novel view (floaters), and the path may be right.
        own = _held_out_seen(scene, train, train_depths, neighbours) if not far else []
        if own and max(own) < MIN_SEEN:
            cause = "geometry"
            causes.insert(0, "the field's own geometry: its renders of the scene's held-out views fail this test "
                             f"too (at most {100 * max(own):.1f}% of their pixels land at their depth in the "
                             f"training photos), so its depth is off on novel views (e.g. floaters), whatever the "
                             f"{'camera' if one else 'path'}; with {override} it goes on, and the enhancer then keeps "
                             "little of its change where the neighbour photos disagree")
    causes.append(f"another coordinate space or unit than the scene's poses (e.g. the {'pose' if one else 'path'} "
                  "of another export, or depth in other units: depth_scale)")
    message = (f"the {'camera' if one else 'camera path'} does not fit the scene: {summary}{what}. Likely causes: "
               + "; ".join(causes))
    result.cause = cause
    if far or len(lost) * 2 >= max(len(with_depth), 1):
        result.problem = message
    else:
        result.warning = message
    return result


def _rescaled_fit(scene, train, train_depths, depth: Tensor, K: Tensor, pose: Tensor, neighbours: int,
                  positions: Tensor) -> tuple[float, float, bool, float, float] | None:
    """Would the camera see the photos in another unit? Its position (and depth) scaled by the
    ratio of the scene cameras' typical distance from the world's origin to its own, and by the
    power of ten nearest it: ``(share seen, factor, depth scaled too, its distance, typical)`` of
    the best try, or None when the distances agree within 1.5x."""
    here = float(pose[:3, 3].to(torch.float64).norm())
    typical = float(positions.norm(dim=-1).median())
    if not (here > 0 and typical > 0) or abs(math.log10(typical / here)) < math.log10(1.5):
        return None
    ratio = typical / here
    best = None
    for factor in {ratio, 10.0 ** round(math.log10(ratio))}:
        moved = pose.to(torch.float64).clone()
        moved[:3, 3] *= factor
        for depth_too in (False, True):
            share = _seen_share(scene, train, train_depths, depth * factor if depth_too else depth, K, moved,
                                neighbours)
            if share is not None and (best is None or share > best[0]):
                best = (share, factor, depth_too, here, typical)
    return best


def check_camera(scene, depth: Tensor, K: Tensor, world_from_cam: Tensor, *, neighbours: int = 4,
                 force: bool = False, override: str = "--force (force=True)") -> str | None:
    """Does one view's camera live in the scene's world? :func:`check_camera_path` for a single
    camera (``depth`` ``(1, H, W)`` z-depth, ``K``, OpenCV ``world_from_cam``), the test the
    service's ``/enhance`` runs before enhancing.

    Raises :class:`~roguenerf.errors.CameraMismatchError` (``cause``: ``"convention"``,
    ``"scale"``, ``"world"``) when its pixels land nowhere near the training photos' surfaces; with
    ``force``, or when the likeliest cause is the field's own geometry (its held-out renders fail
    the test too: the enhancer's trust handles that), returns that message instead (a warning).
    None when it fits, or when the scene has no training views to compare with.
    """
    from roguenerf.geometry import as_world_from_cam

    if not scene.indices("train"):
        return None
    pose = as_world_from_cam(torch.as_tensor(world_from_cam).to(torch.float64), "world_from_cam")
    h, w = depth.shape[-2:]
    single = CameraPath(world_from_cam=pose[None], K=torch.as_tensor(K).to(torch.float64)[None], width=int(w),
                        height=int(h), source="camera", labels=["the camera"])
    check = check_camera_path(scene, single, lambda t: depth, neighbours=neighbours, frames=1, override=override)
    if check.problem is None:
        return check.warning
    if force or check.cause == "geometry":
        log.warning("camera: %s", check.problem)
        return check.problem
    raise CameraMismatchError(check.problem, check.cause, override)


def check_path(scene, camera_path: CameraPath, frames: str | Path, *, depth_type: str = "z",
               depth_scale: float = 1.0, background: str = "zero", neighbours: int = 4, force: bool = False,
               override: str = "--force (force=True)") -> list[str]:
    """The checks :func:`~roguenerf.trajectory.enhance_path` runs before any frame is enhanced, on
    their own: the frames' depth type (z vs ray) and :func:`check_camera_path`, reading the frames
    it needs from ``frames`` (:func:`find_path_frames`). Raises :class:`~roguenerf.errors.CameraMismatchError`
    (its ``cause``, and ``override`` as the way to go on) unless ``force``; returns the warnings
    (with ``force``, the problems too). Nothing is written."""
    from roguenerf.data.exports import background_to_unknown
    from roguenerf.geometry.cameras import ray_to_z_depth
    from roguenerf.imageio import read_depth, read_image_size

    if depth_type not in ("z", "ray"):
        raise InputError(f"depth_type: expected 'z' or 'ray', got {depth_type!r}")
    if not (isinstance(depth_scale, (int, float)) and math.isfinite(depth_scale) and depth_scale > 0):
        raise InputError(f"depth_scale: expected a finite number > 0, got {depth_scale!r}")
    pairs = find_path_frames(frames, len(camera_path))

    def depth_of(t: int, *, raw: bool = False) -> Tensor:
        rgb_path, depth_path = pairs[t]
        width, height = read_image_size(rgb_path)
        if (width, height) != (camera_path.width, camera_path.height):
            raise InputError(f"{rgb_path}: render is {width}x{height}, the camera path says "
                             f"{camera_path.width}x{camera_path.height}")
        depth = background_to_unknown(read_depth(depth_path, scale=float(depth_scale)), background)
        if depth.shape[1:] != (height, width):
            raise InputError(f"{depth_path}: depth is {depth.shape[2]}x{depth.shape[1]}, its render "
                             f"{width}x{height}")
        if depth_type == "ray" and not raw:
            depth = ray_to_z_depth(depth.double(), camera_path.K[t]).float()
        return depth

    warnings: list[str] = []
    problem = _depth_type_problem(scene, camera_path, lambda t: depth_of(t, raw=True), depth_type)
    if problem is not None and not force:
        raise CameraMismatchError(problem, "depth_type", override)
    if problem is not None:
        log.warning("camera path: %s", problem)
        warnings.append(problem)
    check = check_camera_path(scene, camera_path, depth_of, neighbours=neighbours, override=override)
    if check.problem is not None and not force:
        raise CameraMismatchError(check.problem, check.cause, override)
    for message in (check.problem, check.warning):
        if message is not None:
            log.warning("camera path: %s", message)
            warnings.append(message)
    return warnings
