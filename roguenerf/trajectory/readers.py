"""Camera paths (trajectories) as users' files give them, and the frames rendered along them.

A path is a list of cameras (:class:`CameraPath`, from nerfstudio's ``camera_path.json``, a
transforms-style list, Inria 3DGS's ``cameras.json`` or COLMAP's ``images.txt`` / ``.bin``:
:func:`read_camera_path`, detected by content) plus, in a folder, each frame's render and depth
(:func:`find_path_frames`). :func:`smooth_path` makes one through key poses.

A new camera-path format is one reader here and one detection line in :func:`read_camera_path`
(and its file name in :data:`CAMERA_FILES` when uploads may carry it).
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from pathlib import Path

import torch
from torch import Tensor

from roguenerf.errors import InputError
from roguenerf.imageio import read_json

CAMERA_FILES = ("camera_path.json", "cameras.json", "transforms.json", "images.txt")
"""Where :func:`find_camera_file` looks for a path's cameras in an uploaded folder (first found)."""


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
    data = read_json(path, lambda message: _fail(path, message), missing="camera path file not found",
                     unreadable="cannot read the camera path")
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
        order.sort(key=lambda n: natural_key(data[n]["img_name"]))
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


def natural_key(name: str):
    """Sort key of a name with its digit runs as numbers (``frame_2`` before ``frame_10``)."""
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", name)]


def find_path_frames(folder: str | Path, count: int | None = None) -> list[tuple[Path, Path]]:
    """``(render, depth)`` file pairs of a path's frames, in natural order of their names.

    Layouts: ``rgb/`` + ``depth/`` (or ``raw-depth/``, as the export readers accept), or one
    folder with ``NAME.png`` + ``NAME.npy`` (any depth format of :func:`~roguenerf.imageio.read_depth`).
    """
    from roguenerf.data.exports import (
        DEPTH_FOLDERS,
        DEPTH_SUFFIXES,
        IMAGE_SUFFIXES,
        RGB_FOLDERS,
        files_by_stem,
        first_folder,
    )

    folder = Path(folder)
    if not folder.is_dir():
        raise InputError(f"frames folder {folder} does not exist or is not a folder")
    rgb_dir, depth_dir = first_folder(folder, RGB_FOLDERS), first_folder(folder, DEPTH_FOLDERS)
    if rgb_dir is None or depth_dir is None:
        rgb_dir = depth_dir = folder
    rgbs = files_by_stem(rgb_dir, IMAGE_SUFFIXES)
    depth_suffixes = tuple(s for s in DEPTH_SUFFIXES if s != ".png") if rgb_dir == depth_dir else DEPTH_SUFFIXES
    depths = files_by_stem(depth_dir, depth_suffixes)
    names = sorted(set(rgbs) & set(depths), key=natural_key)
    missing = sorted(set(rgbs) ^ set(depths), key=natural_key)
    if missing:
        raise InputError(f"{folder}: frames without both a render and a depth: {', '.join(missing[:5])}"
                         + (" ..." if len(missing) > 5 else ""))
    if not names:
        raise InputError(f"{folder}: no frames found (expected rgb/ + depth/, or NAME.png + NAME.npy pairs)")
    if count is not None and len(names) != count:
        raise InputError(f"{folder}: {len(names)} frames, but the camera path has {count} cameras")
    return [(rgbs[n], depths[n]) for n in names]


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
