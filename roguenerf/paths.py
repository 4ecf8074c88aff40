"""Camera paths: enhance every frame of a rendered path, write an MP4, measure flicker.

Legend: T frames, (H, W) render size.

A path is a list of cameras (:class:`CameraPath`, from nerfstudio's ``camera_path.json`` or a
transforms-style list) plus, in a folder, each frame's render and depth. :func:`enhance_path`
enhances the frames one by one with one :class:`~roguenerf.inference.SceneEnhancer` (each
training photo's features are computed once for the whole path), writes each enhanced frame
atomically as it is done (an interrupted run resumes after the last written frame), then
encodes ``enhanced.mp4`` and ``side_by_side.mp4`` (render | enhanced, each half labelled)
frame by frame.

**Flicker** (:func:`pair_flicker`): for consecutive frames t, t+1, frame t is reprojected into
t+1 with t+1's depth, t's depth (visibility) and both poses (:func:`~roguenerf.reprojection.reproject`,
with its validity mask); the figure is the mean absolute RGB difference over the valid pixels.
The same mask is used for the renders, the enhanced frames and, where both frames coincide with
views that have photos, the photos. Memory is bounded: two frames are held at a time.
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
import re
import time
from dataclasses import dataclass, field
from pathlib import Path

import torch
from torch import Tensor

from roguenerf.errors import CameraMismatchError, InputError, PathCancelled

log = logging.getLogger("roguenerf.paths")

FRAME_FOLDER = "frames"
STATE_FILE = "path_state.json"
FLICKER_FILE = "flicker.json"
VIDEO_FILE = "enhanced.mp4"
SIDE_BY_SIDE_FILE = "side_by_side.mp4"
CAMERA_FILES = ("camera_path.json", "cameras.json", "transforms.json", "images.txt")
"""Where :func:`find_camera_file` looks for a path's cameras in an uploaded folder (first found)."""
POSE_MATCH_TOL = 1e-5
"""A path camera "is" a scene view (and has its photo) when rotation and position agree to this
(position relative to the scene's extent)."""


@dataclass
class CameraPath:
    world_from_cam: Tensor
    """``(T, 4, 4)`` float64 OpenCV camera-to-world, in the scene's pose units."""
    K: Tensor
    """``(T, 3, 3)`` float64, pixel-centre convention."""
    width: int
    height: int
    fps: float = 24.0
    source: str = "transforms"
    """``"nerfstudio"`` (camera_path.json), ``"transforms"``, ``"inria"`` (3DGS ``cameras.json``)
    or ``"colmap"`` (``images.txt`` / ``images.bin`` with the cameras file beside it)."""
    labels: list[str] = field(default_factory=list)
    """How messages name each camera: ``camera_path[3]`` or ``frames[3] (NAME)``."""
    names: list[str] = field(default_factory=list)
    """Each camera's image name (file stem) where the file gives one (Inria ``img_name``, COLMAP's
    image names), else empty: how :func:`~roguenerf.splats.importer.import_3dgs` matches a path
    camera with the dataset view it is."""

    def label(self, t: int) -> str:
        return self.labels[t] if t < len(self.labels) else f"camera {t}"

    def __len__(self) -> int:
        return int(self.world_from_cam.shape[0])


def _fail(path: Path, message: str):
    return InputError(f"{path}: {message}")


def read_camera_path(path: str | Path, *, dataparser=None) -> CameraPath:
    """Read nerfstudio's ``camera_path.json`` or a transforms-style list of cameras.

    nerfstudio: ``{"render_height", "render_width", "fps", "camera_path": [{"camera_to_world":
    16 numbers (row-major, OpenGL), "fov": vertical degrees, "aspect"}]}``; focal
    ``H / 2 / tan(fov / 2)``, principal point at the centre (as ``ns-render camera-path``). Its
    poses are in the model's world: ``dataparser`` (a
    :class:`~roguenerf.data.exports.DataparserTransform`) maps them to the dataset's.

    Transforms style: ``{"frames": [...]}`` or a bare list of frames, each with
    ``transform_matrix`` (OpenGL 4x4) and ``fl_x, fl_y, cx, cy, w, h`` (per frame or top level);
    poses already in the scene's units.

    Inria 3DGS ``cameras.json`` (what ``train.py`` writes next to the model): a list of
    ``{"id", "img_name", "width", "height", "position", "rotation", "fx", "fy"}``, where
    ``rotation`` (3x3) and ``position`` are the OpenCV **camera-to-world** rotation and camera
    centre (``camera_to_JSON`` inverts COLMAP's world-to-camera), the principal point at the
    image centre; cameras in the dataset's order, the natural order of ``img_name`` (``train.py``
    lists the test cameras first, which as a path would jump back and forth), else in list order.

    COLMAP ``images.txt`` (or ``images.bin``) with ``cameras.txt`` / ``cameras.bin`` beside it:
    world-to-camera ``qvec`` (w first) and ``tvec`` per image, pinhole cameras; cameras in
    image-name order (:mod:`roguenerf.data.colmap`).

    Poses of these two are in the dataset's own units, as the scene imported from it.
    Every error names the file and the camera's position in it.
    """
    from roguenerf.geometry.cameras import check_intrinsics

    path = Path(path)
    if path.suffix.lower() in (".txt", ".bin"):
        return _read_colmap_path(path)
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise _fail(path, "camera path file not found") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise _fail(path, f"cannot read the camera path ({exc})") from None
    if _is_inria_cameras(data):
        return _read_inria_cameras(path, data)
    poses, Ks, labels = [], [], []
    if isinstance(data, dict) and "camera_path" in data:
        source = "nerfstudio"
        cams = data["camera_path"]
        try:
            height, width = int(data["render_height"]), int(data["render_width"])
        except (KeyError, TypeError, ValueError):
            raise _fail(path, "nerfstudio camera path: missing render_height / render_width") from None
        if not isinstance(cams, list) or not cams:
            raise _fail(path, "camera_path: expected a non-empty list of cameras")
        for n, cam in enumerate(cams):
            label = _camera_label("camera_path", n, cam)
            try:
                c2w = torch.tensor(cam["camera_to_world"], dtype=torch.float64)
                c2w = c2w.reshape(-1, 4) if c2w.numel() in (12, 16) else c2w
                fov = float(cam["fov"])
            except (KeyError, TypeError, ValueError, RuntimeError):
                raise _fail(path, f"{label}: expected camera_to_world (16 numbers) and fov") from None
            if not 0 < fov < 180:
                raise _fail(path, f"{label}.fov: expected degrees in (0, 180), got {fov}")
            focal = height / 2 / math.tan(math.radians(fov) / 2)
            poses.append(_camera_pose(path, c2w, label))
            labels.append(label)
            Ks.append(torch.tensor([[focal, 0, width / 2], [0, focal, height / 2], [0, 0, 1]], dtype=torch.float64))
        fps = float(data.get("fps", 24.0) or 24.0)
    else:
        source = "transforms"
        frames = data.get("frames") if isinstance(data, dict) else data
        top = data if isinstance(data, dict) else {}
        if not isinstance(frames, list) or not frames:
            raise _fail(path, "expected nerfstudio's camera_path.json or {\"frames\": [...]} with transform_matrix")
        sizes = set()
        for n, fr in enumerate(frames):
            if not isinstance(fr, dict):
                raise _fail(path, f"frames[{n}]: expected an object")
            label = _camera_label("frames", n, fr)
            try:
                c2w = torch.tensor(fr["transform_matrix"], dtype=torch.float64)
                get = {k: fr.get(k, top.get(k)) for k in ("fl_x", "fl_y", "cx", "cy", "w", "h")}
                if get["fl_y"] is None:
                    get["fl_y"] = get["fl_x"]
                fx, fy, cx, cy = (float(get[k]) for k in ("fl_x", "fl_y", "cx", "cy"))
                sizes.add((int(get["w"]), int(get["h"])))
            except (KeyError, TypeError, ValueError, RuntimeError):
                raise _fail(path, f"{label}: expected transform_matrix (4x4) and fl_x, fl_y, cx, cy, w, h") from None
            poses.append(_camera_pose(path, c2w, label))
            labels.append(label)
            Ks.append(torch.tensor([[fx, 0, cx], [0, fy, cy], [0, 0, 1]], dtype=torch.float64))
        if len(sizes) != 1:
            raise _fail(path, f"all frames of a path must have one size, got {sorted(sizes)}")
        width, height = sizes.pop()
        fps = float(top.get("fps", 24.0) or 24.0)
    if width < 1 or height < 1:
        raise _fail(path, f"render size must be positive, got {width}x{height}")
    world_from_cam = torch.stack(poses)
    for K, label in zip(Ks, labels, strict=True):
        try:
            check_intrinsics(K, f"{label} intrinsics")
        except InputError as exc:
            raise _fail(path, str(exc)) from None
    K = torch.stack(Ks)
    if dataparser is not None:
        world_from_cam = dataparser.to_dataset(world_from_cam)
    if not (math.isfinite(fps) and 0 < fps <= 240):
        raise _fail(path, f"fps: expected a number in (0, 240], got {fps}")
    return CameraPath(world_from_cam=world_from_cam, K=K, width=width, height=height, fps=fps, source=source,
                      labels=labels)


def _camera_label(key: str, n: int, entry) -> str:
    """``camera_path[3]`` or ``frames[3] (frame_00004.png)``: how errors name a path camera."""
    name = None
    if isinstance(entry, dict):
        for k in ("name", "file_path", "image_path"):
            if isinstance(entry.get(k), str) and entry[k]:
                name = entry[k]
                break
    return f"{key}[{n}]" + (f" ({name})" if name else "")


def _camera_pose(path: Path, gl: Tensor, label: str) -> Tensor:
    """One path camera's OpenGL 4x4 / 3x4 pose -> validated OpenCV 4x4 (errors name the camera)."""
    from roguenerf.geometry.cameras import as_world_from_cam, opengl_to_opencv

    try:
        pose = as_world_from_cam(gl, label)
        return opengl_to_opencv(pose)
    except InputError as exc:
        raise _fail(path, str(exc)) from None


def _is_inria_cameras(data) -> bool:
    return (isinstance(data, list) and bool(data) and isinstance(data[0], dict)
            and "rotation" in data[0] and "position" in data[0])


def _checked_path(path: Path, poses: list[Tensor], Ks: list[Tensor], sizes: list[tuple[int, int]],
                  labels: list[str], source: str, names: list[str] | None = None) -> CameraPath:
    """One size, proper rotations, valid intrinsics; errors name the camera (``labels``)."""
    from roguenerf.geometry.cameras import as_world_from_cam, check_intrinsics

    if len(set(sizes)) != 1:
        first = sizes[0]
        n = next(i for i, size in enumerate(sizes) if size != first)
        raise _fail(path, f"{labels[n]} is {sizes[n][0]}x{sizes[n][1]}, {labels[0]} is {first[0]}x{first[1]}: "
                          "all cameras of a path must have one size")
    checked = []
    for n, (pose, K) in enumerate(zip(poses, Ks, strict=True)):
        try:
            checked.append(as_world_from_cam(pose, f"{labels[n]} pose"))
            check_intrinsics(K, f"{labels[n]} intrinsics")
        except InputError as exc:
            raise _fail(path, str(exc)) from None
    width, height = sizes[0]
    if width < 1 or height < 1:
        raise _fail(path, f"render size must be positive, got {width}x{height}")
    return CameraPath(world_from_cam=torch.stack(checked), K=torch.stack(Ks), width=width, height=height,
                      fps=24.0, source=source, labels=list(labels), names=list(names or []))


def _read_inria_cameras(path: Path, data: list) -> CameraPath:
    poses, Ks, sizes, labels = [], [], [], []
    order = list(range(len(data)))
    named = all(isinstance(cam, dict) and isinstance(cam.get("img_name"), str) for cam in data)
    if named:  # the dataset's order: train.py writes the test cameras first
        order.sort(key=lambda n: _natural_key(data[n]["img_name"]))
    for n in order:
        cam = data[n]
        label = f"cameras[{n}]"
        if isinstance(cam, dict) and isinstance(cam.get("img_name"), str):
            label += f" ({cam['img_name']})"
        try:
            if not isinstance(cam, dict):
                raise TypeError
            rotation = torch.tensor(cam["rotation"], dtype=torch.float64)
            position = torch.tensor(cam["position"], dtype=torch.float64)
            width, height = cam["width"], cam["height"]
            if not all(isinstance(v, int) and not isinstance(v, bool) for v in (width, height)):
                raise TypeError
            fx, fy = float(cam["fx"]), float(cam["fy"])
        except (KeyError, TypeError, ValueError, RuntimeError):
            raise _fail(path, f"{label}: expected Inria's camera entry: rotation (3x3), position (3), "
                              "width, height (integers), fx, fy") from None
        if rotation.shape != (3, 3) or position.shape != (3,):
            raise _fail(path, f"{label}: expected rotation 3x3 and position of 3 numbers, got "
                              f"{tuple(rotation.shape)} and {tuple(position.shape)}")
        pose = torch.eye(4, dtype=torch.float64)
        pose[:3, :3], pose[:3, 3] = rotation, position
        poses.append(pose)
        Ks.append(torch.tensor([[fx, 0, width / 2], [0, fy, height / 2], [0, 0, 1]], dtype=torch.float64))
        sizes.append((width, height))
        labels.append(label)
    names = [data[n]["img_name"] for n in order] if named else None
    return _checked_path(path, poses, Ks, sizes, labels, "inria", names)


def _read_colmap_path(path: Path) -> CameraPath:
    from roguenerf.data.colmap import pinhole_intrinsics, read_colmap_model, world_from_cam_of
    from roguenerf.errors import SceneFormatError

    fmt = path.suffix.lower()[1:]
    if path.stem != "images":
        raise _fail(path, "expected a camera path (.json) or COLMAP's images.txt / images.bin")
    if not path.is_file():
        raise _fail(path, "camera path file not found")
    if not (path.parent / f"cameras.{fmt}").is_file():
        raise _fail(path, f"COLMAP images.{fmt} needs its cameras.{fmt} beside it (the intrinsics)")
    try:
        model = read_colmap_model(path.parent, points=False, format=fmt)
    except SceneFormatError as exc:
        raise InputError(str(exc)) from None
    if not model.images:
        raise _fail(path, "holds no camera")
    poses, Ks, sizes, labels = [], [], [], []
    for n, image in enumerate(sorted(model.images.values(), key=lambda im: im.name)):
        label = f"camera {n} (image {image.id}, {image.name})"
        camera = model.cameras.get(image.camera_id)
        if camera is None:
            raise _fail(path, f"{label}: its camera {image.camera_id} is not in cameras.{fmt}")
        try:
            Ks.append(torch.from_numpy(pinhole_intrinsics(camera, path.parent / f"cameras.{fmt}")))
            poses.append(torch.from_numpy(world_from_cam_of(image.qvec, image.tvec)))
        except InputError as exc:
            raise _fail(path, f"{label}: {exc}") from None
        sizes.append((camera.width, camera.height))
        labels.append(label)
    names = [Path(image.name).stem for image in sorted(model.images.values(), key=lambda im: im.name)]
    return _checked_path(path, poses, Ks, sizes, labels, "colmap", names)


def find_camera_file(folder: str | Path) -> Path:
    """The camera path file of an uploaded path folder (one of :data:`CAMERA_FILES`)."""
    folder = Path(folder)
    for name in CAMERA_FILES:
        if (folder / name).is_file():
            return folder / name
    raise InputError(f"no camera path found: expected one of {', '.join(CAMERA_FILES)} at the top level, "
                     "beside rgb/ and depth/")


def _natural_key(name: str):
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", name)]


def find_path_frames(folder: str | Path, count: int | None = None) -> list[tuple[Path, Path]]:
    """``(render, depth)`` file pairs of a path's frames, in natural order of their names.

    Layouts: ``rgb/`` + ``depth/`` (or ``raw-depth/``, as the export readers accept), or one
    folder with ``NAME.png`` + ``NAME.npy`` (any depth format of :func:`~roguenerf.imageio.read_depth`).
    """
    from roguenerf.data.exports import DEPTH_FOLDERS, DEPTH_SUFFIXES, IMAGE_SUFFIXES, RGB_FOLDERS, _index, _pick

    folder = Path(folder)
    if not folder.is_dir():
        raise InputError(f"frames folder {folder} does not exist or is not a folder")
    rgb_dir, depth_dir = _pick(folder, RGB_FOLDERS), _pick(folder, DEPTH_FOLDERS)
    if rgb_dir is None or depth_dir is None:
        rgb_dir = depth_dir = folder
    rgbs = _index(rgb_dir, IMAGE_SUFFIXES)
    depth_suffixes = tuple(s for s in DEPTH_SUFFIXES if s != ".png") if rgb_dir == depth_dir else DEPTH_SUFFIXES
    depths = _index(depth_dir, depth_suffixes)
    names = sorted(set(rgbs) & set(depths), key=_natural_key)
    missing = sorted(set(rgbs) ^ set(depths), key=_natural_key)
    if missing:
        raise InputError(f"{folder}: frames without both a render and a depth: {', '.join(missing[:5])}"
                         + (" ..." if len(missing) > 5 else ""))
    if not names:
        raise InputError(f"{folder}: no frames found (expected rgb/ + depth/, or NAME.png + NAME.npy pairs)")
    if count is not None and len(names) != count:
        raise InputError(f"{folder}: {len(names)} frames, but the camera path has {count} cameras")
    return [(rgbs[n], depths[n]) for n in names]


def pair_flicker(images_t: list[Tensor | None], images_t1: list[Tensor | None], depth_t: Tensor, depth_t1: Tensor,
                 K_t: Tensor, K_t1: Tensor, pose_t: Tensor, pose_t1: Tensor) -> tuple[list[float | None], float]:
    """Mean absolute error of each image of frame t reprojected into frame t+1, on valid pixels.

    Args:
        images_t, images_t1: lists of ``(3, H, W)`` images (or None, skipped) of the two frames,
            paired by position (e.g. [render, enhanced, photo]).
        depth_t, depth_t1: ``(1, H, W)`` z-depth of the two frames.
        K_t, K_t1: ``(3, 3)``; pose_t, pose_t1: ``(4, 4)`` OpenCV camera-to-world.
    Returns:
        ``(errors, valid_fraction)``; an error is None when its images are missing or no pixel is valid.
    """
    from roguenerf.reprojection import reproject

    present = [i for i, (a, b) in enumerate(zip(images_t, images_t1)) if a is not None and b is not None]
    out: list[float | None] = [None] * len(images_t)
    if not present:
        return out, 0.0
    src = torch.cat([images_t[i] for i in present])[None].float()
    with torch.inference_mode():
        rp = reproject(src, depth_t[None].float(), depth_t1[None].float(), K_t.float(), K_t1.float(),
                       pose_t.double(), pose_t1.double())
    valid = rp.valid[0, 0] > 0
    fraction = float(valid.float().mean())
    if not bool(valid.any()):
        return out, fraction
    for k, i in enumerate(present):
        diff = (rp.features[0, 3 * k:3 * k + 3] - images_t1[i].float()).abs().mean(0)
        out[i] = float(diff[valid].mean())
    return out, fraction


def _quantise(image: Tensor) -> Tensor:
    """What an 8-bit PNG of ``image`` reads back as (flicker is measured on what was written)."""
    return (image.clamp(0, 1) * 255).round() / 255


def _match_views(scene, camera_path: CameraPath) -> list[int | None]:
    """Scene index of the view each path camera coincides with (same pose and intrinsics), or None."""
    poses = scene.poses()
    Ks = scene.intrinsics()
    extent = float((poses[:, :3, 3] - poses[:, :3, 3].mean(0)).norm(dim=-1).max()) or 1.0
    out: list[int | None] = []
    for pose, K in zip(camera_path.world_from_cam, camera_path.K):
        dt = (poses[:, :3, 3] - pose[:3, 3]).norm(dim=-1) / extent
        dr = (poses[:, :3, :3] - pose[:3, :3]).abs().amax(dim=(-2, -1))
        dk = (Ks - K).abs().amax(dim=(-2, -1))
        ok = (dt < POSE_MATCH_TOL) & (dr < POSE_MATCH_TOL) & (dk < 1e-3)
        hits = [i for i in ok.nonzero().flatten().tolist()
                if (scene.frames[i].width, scene.frames[i].height) == (camera_path.width, camera_path.height)
                and scene.frames[i].image_path is not None]
        out.append(hits[0] if hits else None)
    return out


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
    """The checks :func:`enhance_path` runs before any frame is enhanced, on their own: the
    frames' depth type (z vs ray) and :func:`check_camera_path`, reading the frames it needs from
    ``frames`` (:func:`find_path_frames`). Raises :class:`~roguenerf.errors.CameraMismatchError`
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


@dataclass
class PathResult:
    output: Path
    frames: int
    enhanced_now: int
    """Frames enhanced by this call (the rest were already there: resumed)."""
    seconds: float
    video: Path | None
    side_by_side: Path | None
    flicker: dict = field(default_factory=dict)
    """What :data:`FLICKER_FILE` holds: per-pair and mean flicker, per-frame PSNR where photos exist."""
    cached_views: int = 0
    warnings: list[str] = field(default_factory=list)
    """What went on with ``force=True`` (:func:`check_camera_path`'s message)."""


def _fingerprint(camera_path: CameraPath, pairs: list[tuple[Path, Path]], checkpoint_id: str, options: dict) -> str:
    h = hashlib.sha256()
    h.update(camera_path.world_from_cam.numpy().tobytes())
    h.update(camera_path.K.numpy().tobytes())
    for rgb, depth in pairs:
        for p in (rgb, depth):
            st = p.stat()
            h.update(f"{p.name}:{st.st_size}".encode())
    h.update(checkpoint_id.encode())
    h.update(json.dumps(options, sort_keys=True).encode())
    return h.hexdigest()


def check_path_output(output: str | Path) -> None:
    """``enhance_path``'s output may be new, empty, or an earlier run's (its resume state): any
    other folder is refused, since its ``frames/``, videos and flicker report would be written over
    (and frames already there taken for enhanced ones)."""
    output = Path(output)
    if not output.exists():
        return
    if not output.is_dir():
        raise InputError(f"output: {output} exists and is not a folder; choose a new folder")
    if any(output.iterdir()) and not (output / STATE_FILE).is_file():
        raise InputError(f"output: {output} exists and is not empty: it holds other files, not an earlier "
                         "enhance-path output (which would be resumed); choose a new folder")


def enhance_path(
    scene,
    enhancer,
    camera_path: CameraPath,
    frames: str | Path,
    output: str | Path,
    *,
    depth_type: str = "z",
    depth_scale: float = 1.0,
    background: str = "zero",
    video: bool = True,
    quality: int = 20,
    fps: float | None = None,
    checkpoint_id: str = "",
    progress=None,
    should_stop=None,
    force: bool = False,
    force_hint: str = "force=True",
) -> PathResult:
    """Enhance every frame of a camera path; write frames, MP4s and the flicker report.

    Args:
        scene: the registered :class:`~roguenerf.data.scene.Scene` (its training photos are the
            neighbours; a path camera that coincides with one of its views gets that view's photo
            for the PSNR gain and photo flicker, and never uses it as a neighbour).
        enhancer: a :class:`~roguenerf.inference.SceneEnhancer` of ``scene`` (its feature cache
            serves the whole path).
        camera_path: the cameras, in the scene's pose units (:func:`read_camera_path`).
        frames: folder of the frames' renders and depths (:func:`find_path_frames`).
        output: folder for ``frames/NNNNN.png``, the MP4s, :data:`FLICKER_FILE` and the resume
            state. A folder holding another path's frames is refused.
        depth_type, depth_scale, background: how the frames' depth files are stored (see
            :func:`roguenerf.data.exports.import_renders`).
        video: write ``enhanced.mp4`` and ``side_by_side.mp4`` (needs PyAV).
        quality: x264 CRF, 0..51 (lower is better).
        fps: frame rate; default the camera path's.
        checkpoint_id: anything naming the model's weights (part of the resume fingerprint).
        progress: ``callback(done, total)`` per frame.
        should_stop: ``() -> bool`` polled between frames; True raises
            :class:`~roguenerf.errors.PathCancelled` (frames written so far are kept).
        force: go on when :func:`check_camera_path` finds that the path does not fit the scene
            (its message is logged and kept in ``PathResult.warnings``); otherwise that is an
            :class:`~roguenerf.errors.CameraMismatchError`, before any frame is enhanced (:func:`check_path`).
        force_hint: how that error tells the caller to force it (the CLI: ``--force``; the service:
            its ``force`` field).
    """
    from roguenerf.data.exports import background_to_unknown
    from roguenerf.geometry.cameras import ray_to_z_depth
    from roguenerf.imageio import atomic_write, finite_for_json, read_depth, read_image, write_png
    from roguenerf.metrics import psnr
    from roguenerf.video import Mp4Writer, check_quality, require_av, side_by_side

    start = time.perf_counter()
    check_path_output(output)
    if depth_type not in ("z", "ray"):
        raise InputError(f"depth_type: expected 'z' or 'ray', got {depth_type!r}")
    if not (isinstance(depth_scale, (int, float)) and math.isfinite(depth_scale) and depth_scale > 0):
        raise InputError(f"depth_scale: expected a finite number > 0, got {depth_scale!r}")
    check_quality(quality)
    if video:
        require_av()
    fps = camera_path.fps if fps is None else fps
    pairs = find_path_frames(frames, len(camera_path))
    matches = _match_views(scene, camera_path)
    total = len(pairs)

    def load_frame(t: int) -> tuple[Tensor, Tensor]:
        rgb_path, depth_path = pairs[t]
        render = read_image(rgb_path)
        if render.shape[1:] != (camera_path.height, camera_path.width):
            raise InputError(f"{rgb_path}: render is {render.shape[2]}x{render.shape[1]}, the camera path says "
                             f"{camera_path.width}x{camera_path.height}")
        depth = read_depth(depth_path, scale=float(depth_scale))
        if depth.shape[1:] != render.shape[1:]:
            raise InputError(f"{depth_path}: depth is {depth.shape[2]}x{depth.shape[1]}, its render "
                             f"{render.shape[2]}x{render.shape[1]}")
        depth = background_to_unknown(depth, background)
        if depth_type == "ray":
            depth = ray_to_z_depth(depth.double(), camera_path.K[t]).float()
        return render, depth

    warnings = check_path(scene, camera_path, frames, depth_type=depth_type, depth_scale=depth_scale,
                          background=background, neighbours=max(1, enhancer.num_neighbours or 1), force=force,
                          override=force_hint)

    output = Path(output)
    frame_dir = output / FRAME_FOLDER
    output.mkdir(parents=True, exist_ok=True)  # frames/ only once the state marks the folder as ours
    # The enhancer's options too (EnhanceOptions.fingerprint, with the count they resolve to for
    # this model): frames made with another neighbour rule, colour reach, trust or pose refinement
    # (a changed default after an upgrade) must not be mixed into this video.
    options = {"depth_type": depth_type, "depth_scale": depth_scale, "background": background,
               "neighbours": enhancer.num_neighbours, "near_extra": enhancer.near_extra,
               "enhance": enhancer.options.fingerprint()}
    fingerprint = _fingerprint(camera_path, pairs, checkpoint_id, options)
    state_path = output / STATE_FILE
    if state_path.is_file():
        try:
            previous = json.loads(state_path.read_text()).get("fingerprint")
        except (OSError, json.JSONDecodeError):
            previous = None
        if previous != fingerprint:
            raise InputError(f"{output} holds the frames of another path, model or setting; "
                             "choose another output folder or delete it")
    else:
        atomic_write(state_path, json.dumps({"fingerprint": fingerprint, "frames": len(pairs)}).encode())
    frame_dir.mkdir(exist_ok=True)
    per_pair, per_frame = [], []
    prev = None
    done_now = 0
    for t in range(total):
        if should_stop is not None and should_stop():
            raise PathCancelled(t)
        render, depth = load_frame(t)
        out_png = frame_dir / f"{t:05d}.png"
        if out_png.is_file():
            enhanced = read_image(out_png)
        else:
            match = matches[t]
            exclude = match if match is not None and scene.frames[match].split == "train" else None
            result = enhancer.enhance(render, depth, camera_path.K[t], camera_path.world_from_cam[t], exclude=exclude)
            write_png(out_png, result.image)
            enhanced = _quantise(result.image)
            done_now += 1
        photo = scene.photo(matches[t]) if matches[t] is not None else None
        row = {"frame": t, "view": scene.frames[matches[t]].name if matches[t] is not None else None}
        if photo is not None:
            row["render_psnr"] = float(psnr(render[None], photo[None])[0])
            row["enhanced_psnr"] = float(psnr(enhanced[None], photo[None])[0])
            row["gain_db"] = row["enhanced_psnr"] - row["render_psnr"]
        per_frame.append(row)
        current = (render, enhanced, photo, depth, camera_path.K[t], camera_path.world_from_cam[t])
        if prev is not None:
            errors, fraction = pair_flicker(list(prev[:3]), list(current[:3]), prev[3], depth, prev[4], current[4],
                                            prev[5], current[5])
            per_pair.append({"from": t - 1, "to": t, "render": errors[0], "enhanced": errors[1],
                             "photo": errors[2], "valid_fraction": fraction})
        prev = current
        if progress is not None:
            progress(t + 1, total)
    report = summarise_flicker(per_pair, per_frame)
    report["frames"] = total
    atomic_write(output / FLICKER_FILE, json.dumps(finite_for_json(report), indent=1).encode())

    video_path = sbs_path = None
    if video:
        video_path, sbs_path = output / VIDEO_FILE, output / SIDE_BY_SIDE_FILE
        with Mp4Writer(video_path, fps=fps, crf=quality) as enhanced_video, \
                Mp4Writer(sbs_path, fps=fps, crf=quality) as side_video:
            for t in range(total):
                enhanced = read_image(frame_dir / f"{t:05d}.png")
                render = read_image(pairs[t][0])
                enhanced_video.write(enhanced)
                side_video.write(side_by_side(render, enhanced))
    return PathResult(output=output, frames=total, enhanced_now=done_now, seconds=time.perf_counter() - start,
                      video=video_path, side_by_side=sbs_path, flicker=report, cached_views=enhancer.cached_views(),
                      warnings=warnings)


def summarise_flicker(per_pair: list[dict], per_frame: list[dict]) -> dict:
    """Means over the pairs (and the frames with photos) of :func:`enhance_path`'s rows."""
    def mean(values):
        values = [v for v in values if v is not None and math.isfinite(v)]
        return sum(values) / len(values) if values else None

    render = mean(p["render"] for p in per_pair)
    enhanced = mean(p["enhanced"] for p in per_pair)
    with_photo = [f for f in per_frame if "gain_db" in f]
    return {
        "flicker": {"render": render, "enhanced": enhanced, "photo": mean(p["photo"] for p in per_pair),
                    "ratio": (enhanced / render) if render and enhanced is not None else None,
                    "pairs": len(per_pair), "pairs_with_photos": sum(p["photo"] is not None for p in per_pair)},
        "psnr": {"frames_with_photos": len(with_photo),
                 "render": mean(f["render_psnr"] for f in with_photo),
                 "enhanced": mean(f["enhanced_psnr"] for f in with_photo),
                 "mean_gain_db": mean(f["gain_db"] for f in with_photo)},
        "per_pair": per_pair,
        "per_frame": per_frame,
    }


def smooth_path(key_poses: Tensor, steps: int, *, closed: bool = False) -> Tensor:
    """A smooth camera path through ``key_poses`` ``(M, 4, 4)`` or ``(M, 3, 4)`` (camera-to-world,
    validated by :func:`~roguenerf.geometry.cameras.as_world_from_cam`: non-finite, reflected or
    scaled rotations are refused naming the key): ``steps``
    frames per segment, positions on a Catmull-Rom spline, rotations by quaternion slerp. Frame
    ``k * steps`` is key pose ``k`` exactly (those frames have the key views' photos).

    Returns ``(T, 4, 4)`` float64, ``T = (M - 1) * steps + 1`` (``M * steps`` when ``closed``).
    """
    from kornia.geometry.conversions import quaternion_to_rotation_matrix, rotation_matrix_to_quaternion

    from roguenerf.geometry.cameras import as_world_from_cam

    if isinstance(steps, bool) or not isinstance(steps, int) or steps < 1:
        raise InputError(f"steps: expected an integer >= 1, got {steps!r}")
    key = torch.as_tensor(key_poses)
    if key.ndim != 3:
        raise InputError(f"key_poses: expected shape (M, 4, 4) or (M, 3, 4), got {tuple(key.shape)}")
    key = as_world_from_cam(key.to(torch.float64) if key.is_floating_point() else key, "key_poses")
    m = key.shape[0]
    if m < 2:
        raise InputError(f"key_poses: expected at least 2 poses, got {m}")
    quats = rotation_matrix_to_quaternion(key[:, :3, :3].contiguous())  # (M, 4) w, x, y, z
    for i in range(1, m):  # same hemisphere as the previous key: the short way round
        if float((quats[i] * quats[i - 1]).sum()) < 0:
            quats[i] = -quats[i]
    positions = key[:, :3, 3]
    segments = m if closed else m - 1
    out = []
    for s in range(segments):
        a, b = s, (s + 1) % m
        p0 = positions[(a - 1) % m] if (closed or a > 0) else positions[a]
        p3 = positions[(b + 1) % m] if (closed or b < m - 1) else positions[b]
        qa, qb = quats[a], quats[b] if float((quats[a] * quats[b]).sum()) >= 0 else -quats[b]
        for k in range(steps):
            u = k / steps
            p = 0.5 * ((2 * positions[a]) + (-p0 + positions[b]) * u
                       + (2 * p0 - 5 * positions[a] + 4 * positions[b] - p3) * u * u
                       + (-p0 + 3 * positions[a] - 3 * positions[b] + p3) * u ** 3)
            dot = float((qa * qb).sum())
            if dot > 0.9995:
                q = qa + u * (qb - qa)
            else:
                theta = math.acos(max(-1.0, min(1.0, dot)))
                q = (math.sin((1 - u) * theta) * qa + math.sin(u * theta) * qb) / math.sin(theta)
            q = q / q.norm()
            pose = torch.eye(4, dtype=torch.float64)
            pose[:3, :3] = quaternion_to_rotation_matrix(q[None])[0] if k else key[a, :3, :3]
            pose[:3, 3] = p if k else positions[a]
            out.append(pose)
    if not closed:
        out.append(key[-1].clone())
    return torch.stack(out)
