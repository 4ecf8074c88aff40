"""COLMAP sparse models (``sparse/0/{cameras,images,points3D}.{bin,txt}``) in and out.

The dataset layout Inria's ``gaussian-splatting``, gsplat's ``simple_trainer`` and nerfstudio
(``ns-process-data``) train on: ``DATA/images/`` plus ``DATA/sparse/0/`` (or ``DATA/sparse/``).
Both of COLMAP's encodings are read and written (the text form one line per record, the
binary form little-endian with ``uint64`` counts, as COLMAP's own ``model_converter`` writes
them); :func:`read_colmap` turns the model into our conventions:

* COLMAP stores **world-to-camera** poses: a unit quaternion ``qvec`` (**w first**) and
  ``tvec``, with OpenCV camera axes (x right, y down, z forward). We return the OpenCV
  **camera-to-world** ``world_from_cam = [R^T | -R^T t]`` in float64.
* COLMAP's image coordinates put the centre of the upper-left pixel at (0.5, 0.5), our
  pixel-centre convention (:mod:`roguenerf.geometry.cameras`): ``cx, cy`` pass unchanged.
* Only ``SIMPLE_PINHOLE`` and ``PINHOLE`` cameras are read (or a distortion model whose
  coefficients are all exactly 0). Any other model is refused with a message that says to
  undistort first (``colmap image_undistorter``), as 3DGS trainers require.
* Views are sorted by COLMAP image name (Python string order), as gsplat's ``Parser`` and
  Inria's ``readColmapSceneInfo`` sort them before taking every 8th view as a test view.

No dependency: the formats are small. ``pycolmap`` (an optional dependency, when installed)
reads the same files; ``tests/unit/roguenerf/data/test_colmap.py`` checks the two agree.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from roguenerf.errors import InputError, SceneFormatError

CAMERA_MODELS: dict[str, tuple[int, int]] = {
    "SIMPLE_PINHOLE": (0, 3),
    "PINHOLE": (1, 4),
    "SIMPLE_RADIAL": (2, 4),
    "RADIAL": (3, 5),
    "OPENCV": (4, 8),
    "OPENCV_FISHEYE": (5, 8),
    "FULL_OPENCV": (6, 12),
    "FOV": (7, 5),
    "SIMPLE_RADIAL_FISHEYE": (8, 4),
    "RADIAL_FISHEYE": (9, 5),
    "THIN_PRISM_FISHEYE": (10, 12),
    "RAD_TAN_THIN_PRISM_FISHEYE": (11, 16),
}
"""COLMAP camera model name -> (model id, number of parameters)."""
_MODEL_BY_ID = {mid: (name, n) for name, (mid, n) in CAMERA_MODELS.items()}
# Models whose parameters start with focal(s) and principal point, then distortion terms:
# name -> (number of focal lengths, index of the first distortion parameter).
_PINHOLE_PREFIX = {
    "SIMPLE_PINHOLE": (1, 3),
    "PINHOLE": (2, 4),
    "SIMPLE_RADIAL": (1, 3),
    "RADIAL": (1, 3),
    "OPENCV": (2, 4),
    "OPENCV_FISHEYE": (2, 4),
    "FULL_OPENCV": (2, 4),
    "SIMPLE_RADIAL_FISHEYE": (1, 3),
    "RADIAL_FISHEYE": (1, 3),
    "THIN_PRISM_FISHEYE": (2, 4),
    "RAD_TAN_THIN_PRISM_FISHEYE": (2, 4),
}
MODEL_FILES = ("cameras", "images", "points3D")
UNDISTORT_HINT = (
    "undistort the images first, as 3DGS trainers require: `colmap image_undistorter --image_path "
    "DATA/images --input_path DATA/sparse/0 --output_path DATA_undistorted --output_type COLMAP`, "
    "then use DATA_undistorted (its images/ and sparse/) as the dataset"
)


@dataclass
class ColmapCamera:
    id: int
    model: str
    width: int
    height: int
    params: tuple[float, ...]


@dataclass
class ColmapImage:
    id: int
    qvec: tuple[float, float, float, float]
    """World-to-camera rotation as a quaternion, w first."""
    tvec: tuple[float, float, float]
    """World-to-camera translation."""
    camera_id: int
    name: str
    xys: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    """``(P, 2)`` float64 keypoints (pixel-centre convention)."""
    point3D_ids: np.ndarray = field(default_factory=lambda: np.zeros((0,), dtype=np.int64))
    """``(P,)`` int64, -1 where a keypoint has no 3D point."""


@dataclass
class ColmapPoints:
    ids: np.ndarray
    """``(N,)`` int64."""
    xyz: np.ndarray
    """``(N, 3)`` float64 world positions."""
    rgb: np.ndarray
    """``(N, 3)`` uint8."""
    error: np.ndarray
    """``(N,)`` float64 reprojection error (pixels)."""
    tracks: list[np.ndarray] | None = None
    """Per point ``(L, 2)`` int32 (image id, keypoint index); None when not read."""

    @classmethod
    def empty(cls) -> ColmapPoints:
        return cls(
            np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3), np.uint8), np.zeros(0), []
        )


@dataclass
class ColmapModel:
    """A COLMAP sparse model as stored (ids, world-to-camera quaternions)."""

    cameras: dict[int, ColmapCamera]
    images: dict[int, ColmapImage]
    points: ColmapPoints | None = None
    source: Path | None = None
    """The folder it was read from."""
    format: str = "bin"
    """``"bin"`` or ``"txt"``."""


@dataclass
class ColmapDataset:
    """A COLMAP dataset in our conventions; index ``i`` is the ``i``-th view in name order."""

    root: Path
    """The dataset folder (holding ``images/`` and ``sparse/``)."""
    sparse_dir: Path
    names: list[str]
    """Image names as COLMAP has them (relative to the image folder), sorted."""
    image_paths: list[Path]
    K: Tensor
    """``(M, 3, 3)`` float64, pixel-centre convention, for the images in ``image_paths``."""
    world_from_cam: Tensor
    """``(M, 4, 4)`` float64 OpenCV camera-to-world."""
    widths: list[int]
    heights: list[int]
    image_ids: list[int]
    camera_ids: list[int]
    format: str = "bin"
    points_xyz: Tensor | None = None
    """``(N, 3)`` float64 sparse points (when read with ``points=True``)."""
    points_rgb: Tensor | None = None
    """``(N, 3)`` uint8."""

    def __len__(self) -> int:
        return len(self.names)

    @property
    def stems(self) -> list[str]:
        """View names for our scenes: the file stems, or (when two stems collide) the name
        without its suffix, ``/`` replaced by ``_``."""
        return view_names(self.names)


def view_names(names: list[str]) -> list[str]:
    """Our view names for COLMAP image names (see :attr:`ColmapDataset.stems`)."""
    stems = [Path(n).stem for n in names]
    if len(set(stems)) == len(stems):
        return stems
    return [str(Path(n).with_suffix("")).replace("\\", "/").replace("/", "_") for n in names]


# -- rotations ------------------------------------------------------------------------------


def qvec_to_rotmat(qvec) -> np.ndarray:
    """``(3, 3)`` float64 rotation of a quaternion ``(w, x, y, z)`` (normalised first)."""
    q = np.asarray(qvec, dtype=np.float64)
    norm = float(np.linalg.norm(q))
    if not math.isfinite(norm) or norm < 1e-12:
        raise InputError(f"qvec: expected a non-zero finite quaternion, got {q.tolist()}")
    w, x, y, z = q / norm
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def rotmat_to_qvec(R) -> np.ndarray:
    """Unit quaternion ``(w, x, y, z)`` with ``w >= 0`` of a rotation matrix (Shepperd's method)."""
    R = np.asarray(R, dtype=np.float64)
    trace = R[0, 0] + R[1, 1] + R[2, 2]
    if trace > 0:
        s = 2.0 * math.sqrt(1.0 + trace)
        q = [0.25 * s, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s]
    elif R[0, 0] > R[1, 1] and R[0, 0] > R[2, 2]:
        s = 2.0 * math.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2])
        q = [(R[2, 1] - R[1, 2]) / s, 0.25 * s, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s]
    elif R[1, 1] > R[2, 2]:
        s = 2.0 * math.sqrt(1.0 + R[1, 1] - R[0, 0] - R[2, 2])
        q = [(R[0, 2] - R[2, 0]) / s, (R[0, 1] + R[1, 0]) / s, 0.25 * s, (R[1, 2] + R[2, 1]) / s]
    else:
        s = 2.0 * math.sqrt(1.0 + R[2, 2] - R[0, 0] - R[1, 1])
        q = [(R[1, 0] - R[0, 1]) / s, (R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, 0.25 * s]
    q = np.asarray(q)
    q = q / np.linalg.norm(q)
    return -q if q[0] < 0 else q


def world_from_cam_of(qvec, tvec) -> np.ndarray:
    """OpenCV camera-to-world ``(4, 4)`` float64 of COLMAP's world-to-camera ``qvec``, ``tvec``."""
    R = qvec_to_rotmat(qvec)
    t = np.asarray(tvec, dtype=np.float64)
    out = np.eye(4)
    out[:3, :3] = R.T
    out[:3, 3] = -R.T @ t
    return out


def colmap_pose_of(world_from_cam) -> tuple[np.ndarray, np.ndarray]:
    """COLMAP's ``(qvec, tvec)`` (world-to-camera, w first) of an OpenCV camera-to-world pose."""
    pose = np.asarray(world_from_cam, dtype=np.float64)
    R = pose[:3, :3].T
    return rotmat_to_qvec(R), -R @ pose[:3, 3]


# -- locating -------------------------------------------------------------------------------


def _model_format(folder: Path) -> str | None:
    for ext in ("bin", "txt"):
        if all((folder / f"{name}.{ext}").is_file() for name in ("cameras", "images")):
            return ext
    return None


def find_sparse_dir(path: str | Path) -> Path:
    """The folder holding ``cameras`` and ``images`` (``.bin`` or ``.txt``) of a dataset.

    ``path`` may be the dataset (``sparse/0`` then ``sparse`` are tried) or the model folder.
    Raises :class:`~roguenerf.errors.SceneFormatError` naming the places looked at.
    """
    path = Path(path)
    if path.is_file() and path.stem in MODEL_FILES:
        path = path.parent
    for candidate in (path, path / "sparse" / "0", path / "sparse"):
        if candidate.is_dir() and _model_format(candidate):
            return candidate
    sparse = path / "sparse"
    if sparse.is_dir():
        models = sorted(p.name for p in sparse.iterdir() if p.is_dir() and _model_format(p))
        if models:
            return sparse / models[0]
    raise SceneFormatError(
        path,
        "no COLMAP model: expected cameras and images (.bin or .txt) in "
        "sparse/0/, sparse/ or the folder itself",
    )


def is_colmap_dataset(path: str | Path) -> bool:
    """True when :func:`find_sparse_dir` finds a model at ``path``."""
    try:
        find_sparse_dir(path)
    except SceneFormatError:
        return False
    return True


# -- reading --------------------------------------------------------------------------------


class _Reader:
    def __init__(self, path: Path):
        self.path = path
        try:
            self.data = path.read_bytes()
        except OSError as exc:
            raise SceneFormatError(path, f"cannot read ({exc})") from None
        self.pos = 0

    def take(self, fmt: str, what: str):
        size = struct.calcsize("<" + fmt)
        if self.pos + size > len(self.data):
            raise SceneFormatError(self.path, f"truncated at byte {self.pos} while reading {what}")
        out = struct.unpack_from("<" + fmt, self.data, self.pos)
        self.pos += size
        return out

    def array(self, dtype, count: int, what: str) -> np.ndarray:
        dt = np.dtype(dtype).newbyteorder("<")
        size = dt.itemsize * count
        if count < 0 or self.pos + size > len(self.data):
            raise SceneFormatError(self.path, f"truncated at byte {self.pos} while reading {what}")
        out = np.frombuffer(self.data, dtype=dt, count=count, offset=self.pos)
        self.pos += size
        return out

    def name(self, what: str) -> str:
        end = self.data.find(b"\x00", self.pos)
        if end < 0:
            raise SceneFormatError(self.path, f"truncated at byte {self.pos} while reading {what}")
        raw = self.data[self.pos : end]
        self.pos = end + 1
        try:
            return raw.decode("utf-8")
        except UnicodeDecodeError:
            raise SceneFormatError(self.path, f"{what}: the name is not UTF-8") from None

    def done(self) -> None:
        if self.pos != len(self.data):
            raise SceneFormatError(
                self.path, f"{len(self.data) - self.pos} unexpected bytes at the end"
            )


def _check_camera(path: Path, cam: ColmapCamera, where: str) -> None:
    if cam.model not in CAMERA_MODELS:
        raise SceneFormatError(path, f"{where}: unknown camera model {cam.model!r}")
    n = CAMERA_MODELS[cam.model][1]
    if len(cam.params) != n:
        raise SceneFormatError(
            path, f"{where}: model {cam.model} has {n} parameters, got {len(cam.params)}"
        )
    if cam.width <= 0 or cam.height <= 0:
        raise SceneFormatError(
            path, f"{where}: expected a positive size, got {cam.width}x{cam.height}"
        )
    if not all(math.isfinite(p) for p in cam.params):
        raise SceneFormatError(path, f"{where}: parameters contain NaN or inf")


def _read_cameras_bin(path: Path) -> dict[int, ColmapCamera]:
    r = _Reader(path)
    (count,) = r.take("Q", "the camera count")
    cameras = {}
    for n in range(count):
        cam_id, model_id, width, height = r.take("iiQQ", f"camera {n}")
        if model_id not in _MODEL_BY_ID:
            raise SceneFormatError(path, f"camera {cam_id}: unknown camera model id {model_id}")
        model, n_params = _MODEL_BY_ID[model_id]
        params = r.take("d" * n_params, f"camera {cam_id} parameters")
        if cam_id in cameras:
            raise SceneFormatError(path, f"camera {n}: camera id {cam_id} appears twice")
        cameras[cam_id] = ColmapCamera(cam_id, model, int(width), int(height), tuple(params))
    r.done()
    return cameras


def _read_images_bin(path: Path, keypoints: bool) -> dict[int, ColmapImage]:
    r = _Reader(path)
    (count,) = r.take("Q", "the image count")
    images = {}
    for n in range(count):
        values = r.take("idddddddi", f"image {n}")
        image_id, qvec, tvec, camera_id = values[0], values[1:5], values[5:8], values[8]
        name = r.name(f"image {image_id} name")
        (n_points,) = r.take("Q", f"image {image_id} keypoint count")
        block = r.array(
            [("x", "f8"), ("y", "f8"), ("id", "i8")], n_points, f"image {image_id} keypoints"
        )
        if image_id in images:
            raise SceneFormatError(path, f"image {n}: image id {image_id} appears twice")
        image = ColmapImage(image_id, tuple(qvec), tuple(tvec), camera_id, name)
        if keypoints:
            image.xys = np.stack([block["x"], block["y"]], axis=-1).astype(np.float64)
            image.point3D_ids = block["id"].astype(np.int64)
        images[image_id] = image
    r.done()
    return images


def _read_points_bin(path: Path, tracks: bool) -> ColmapPoints:
    r = _Reader(path)
    (count,) = r.take("Q", "the point count")
    head = struct.Struct("<QdddBBBdQ")
    room = len(r.data) - r.pos
    if count > room // head.size:  # before allocating: a corrupt count would ask for exabytes
        raise SceneFormatError(
            path,
            f"the header claims {count} points, but the file's {room} bytes after it hold at most "
            f"{room // head.size} ({head.size} bytes each): the file is truncated or not a COLMAP "
            "points3D.bin",
        )
    ids = np.empty(count, np.int64)
    xyz = np.empty((count, 3))
    rgb = np.empty((count, 3), np.uint8)
    error = np.empty(count)
    all_tracks = [] if tracks else None
    data = r.data
    for n in range(count):
        if r.pos + head.size > len(data):
            raise SceneFormatError(path, f"truncated at byte {r.pos} while reading point {n}")
        pid, x, y, z, cr, cg, cb, err, length = head.unpack_from(data, r.pos)
        r.pos += head.size
        ids[n], xyz[n], rgb[n], error[n] = pid, (x, y, z), (cr, cg, cb), err
        track = r.array("i4", 2 * length, f"point {pid} track")
        if all_tracks is not None:
            all_tracks.append(track.reshape(-1, 2).copy())
    r.done()
    return ColmapPoints(ids, xyz, rgb, error, all_tracks)


def _text_lines(path: Path) -> list[tuple[int, str]]:
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise SceneFormatError(path, f"cannot read ({exc})") from None
    return [
        (n + 1, line.strip())
        for n, line in enumerate(text.splitlines())
        if not line.lstrip().startswith("#")
    ]


def _numbers(path: Path, tokens: list[str], kind, lineno: int, what: str) -> list:
    try:
        return [kind(t) for t in tokens]
    except ValueError:
        raise SceneFormatError(
            path, f"line {lineno}: {what}: expected numbers, got {' '.join(tokens)!r}"
        ) from None


def _read_cameras_txt(path: Path) -> dict[int, ColmapCamera]:
    cameras = {}
    for lineno, line in _text_lines(path):
        if not line:
            continue
        tokens = line.split()
        if len(tokens) < 4:
            raise SceneFormatError(
                path, f"line {lineno}: expected CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]"
            )
        cam_id, width, height = _numbers(
            path, [tokens[0], tokens[2], tokens[3]], int, lineno, "id and size"
        )
        params = _numbers(path, tokens[4:], float, lineno, "parameters")
        if cam_id in cameras:
            raise SceneFormatError(path, f"line {lineno}: camera id {cam_id} appears twice")
        cameras[cam_id] = ColmapCamera(cam_id, tokens[1], width, height, tuple(params))
    return cameras


def _read_images_txt(path: Path, keypoints: bool) -> dict[int, ColmapImage]:
    lines = _text_lines(path)
    images = {}
    i = 0
    while i < len(lines):
        lineno, line = lines[i]
        if not line:
            i += 1
            continue
        tokens = line.split()
        if len(tokens) < 10:
            raise SceneFormatError(
                path, f"line {lineno}: expected IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME"
            )
        image_id, camera_id = _numbers(path, [tokens[0], tokens[8]], int, lineno, "ids")
        pose = _numbers(path, tokens[1:8], float, lineno, "qvec and tvec")
        image = ColmapImage(
            image_id, tuple(pose[:4]), tuple(pose[4:]), camera_id, " ".join(tokens[9:])
        )
        if image_id in images:
            raise SceneFormatError(path, f"line {lineno}: image id {image_id} appears twice")
        images[image_id] = image
        # The keypoint line follows (empty when there are none); files written by hand sometimes
        # leave it out, so a line that reads as the next image's header is not taken for it.
        points_lineno, points_line = lines[i + 1] if i + 1 < len(lines) else (lineno + 1, "")
        if _is_image_header(points_line):
            i += 1
            continue
        if keypoints and points_line:
            values = points_line.split()
            if len(values) % 3:
                raise SceneFormatError(
                    path, f"line {points_lineno}: expected X Y POINT3D_ID triples"
                )
            arr = np.array(_numbers(path, values, float, points_lineno, "keypoints")).reshape(-1, 3)
            image.xys, image.point3D_ids = arr[:, :2], arr[:, 2].astype(np.int64)
        i += 2
    return images


def _is_image_header(line: str) -> bool:
    """IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME: a keypoint line is numbers only."""
    tokens = line.split()
    if len(tokens) < 10:
        return False
    try:
        float(tokens[9])
    except ValueError:
        return True
    return False


def _read_points_txt(path: Path, tracks: bool) -> ColmapPoints:
    ids, xyz, rgb, error, all_tracks = [], [], [], [], []
    for lineno, line in _text_lines(path):
        if not line:
            continue
        tokens = line.split()
        if len(tokens) < 8 or (len(tokens) - 8) % 2:
            raise SceneFormatError(
                path, f"line {lineno}: expected POINT3D_ID X Y Z R G B ERROR TRACK[]"
            )
        ids.append(_numbers(path, tokens[:1], int, lineno, "id")[0])
        xyz.append(_numbers(path, tokens[1:4], float, lineno, "position"))
        rgb.append(_numbers(path, tokens[4:7], int, lineno, "colour"))
        error.append(_numbers(path, tokens[7:8], float, lineno, "error")[0])
        if tracks:
            all_tracks.append(
                np.array(_numbers(path, tokens[8:], int, lineno, "track"), np.int32).reshape(-1, 2)
            )
    return ColmapPoints(
        np.array(ids, np.int64),
        np.array(xyz, np.float64).reshape(-1, 3),
        np.array(rgb, np.uint8).reshape(-1, 3),
        np.array(error, np.float64),
        all_tracks if tracks else None,
    )


def read_colmap_model(
    path: str | Path, *, points: bool = True, keypoints: bool = False, format: str | None = None
) -> ColmapModel:
    """Read a COLMAP sparse model as stored (binary preferred when both forms are there).

    Args:
        path: the model folder, or a dataset holding ``sparse/0`` / ``sparse``.
        points: read ``points3D`` too (without tracks); absent file -> no points.
        keypoints: keep each image's 2D keypoints (large; off by default).
        format: ``"bin"`` or ``"txt"`` to read that encoding when a folder holds both.
    """
    folder = find_sparse_dir(path)
    fmt = _model_format(folder)
    if format is not None:
        if format not in ("bin", "txt"):
            raise InputError(f"format: expected 'bin' or 'txt', got {format!r}")
        if not all((folder / f"{name}.{format}").is_file() for name in ("cameras", "images")):
            raise SceneFormatError(folder, f"expected cameras.{format} and images.{format}")
        fmt = format
    if fmt == "bin":
        cameras = _read_cameras_bin(folder / "cameras.bin")
        images = _read_images_bin(folder / "images.bin", keypoints)
    else:
        cameras = _read_cameras_txt(folder / "cameras.txt")
        images = _read_images_txt(folder / "images.txt", keypoints)
    pts = None
    if points:
        pfile = folder / f"points3D.{fmt}"
        if pfile.is_file():
            pts = _read_points_bin(pfile, False) if fmt == "bin" else _read_points_txt(pfile, False)
    for cam in cameras.values():
        _check_camera(folder / f"cameras.{fmt}", cam, f"camera {cam.id}")
    return ColmapModel(cameras=cameras, images=images, points=pts, source=folder, format=fmt)


def pinhole_intrinsics(camera: ColmapCamera, source: Path | None = None) -> np.ndarray:
    """``(3, 3)`` float64 K of a pinhole camera (pixel-centre convention, as COLMAP's).

    A distortion model whose distortion coefficients are all exactly 0 counts as pinhole;
    anything else raises :class:`~roguenerf.errors.SceneFormatError` saying to undistort.
    """
    where = source if source is not None else Path("cameras")
    if camera.model not in _PINHOLE_PREFIX:
        raise SceneFormatError(
            where,
            f"camera {camera.id} uses the {camera.model} model, which this "
            f"reader does not support; {UNDISTORT_HINT}",
        )
    n_focal, first = _PINHOLE_PREFIX[camera.model]
    distortion = camera.params[first:]
    if any(p != 0.0 for p in distortion):
        raise SceneFormatError(
            where,
            f"camera {camera.id} uses the {camera.model} model with lens distortion "
            f"{[float(p) for p in distortion]}; the enhancer needs pinhole images: "
            f"{UNDISTORT_HINT}",
        )
    fx = camera.params[0]
    fy = camera.params[1] if n_focal == 2 else fx
    cx, cy = camera.params[n_focal], camera.params[n_focal + 1]
    if not (fx > 0 and fy > 0):
        raise SceneFormatError(
            where, f"camera {camera.id}: expected focal lengths > 0, got {fx}, {fy}"
        )
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def read_colmap(
    dataset_dir: str | Path,
    *,
    images: str | Path = "images",
    points: bool = False,
    check_files: bool = True,
) -> ColmapDataset:
    """Read a COLMAP dataset (``images/`` + ``sparse/0``) into our conventions.

    Args:
        dataset_dir: the dataset folder (or its model folder ``sparse/0``; the dataset is then
            the folder above ``sparse``).
        images: the image folder, relative to the dataset (``images_2`` for gsplat's
            ``--data-factor 2``) or absolute.
        points: also return the sparse points (``points_xyz``, ``points_rgb``).
        check_files: every image must exist; its size is read from its header (no decoding)
            and, when it differs from the camera's by a common factor (a downscaled copy), ``K``
            is scaled to it (as gsplat's parser does).
    Raises:
        SceneFormatError: a malformed or missing file, a camera with lens distortion, an image
            whose camera is missing, a missing image file.
    """
    from roguenerf.geometry.cameras import check_pose

    dataset_dir = Path(dataset_dir)
    if not dataset_dir.exists():
        raise SceneFormatError(dataset_dir, "no such file or folder")
    if dataset_dir.is_file():
        dataset_dir = dataset_dir.parent
    model = read_colmap_model(dataset_dir, points=points)
    sparse_dir = model.source
    root = dataset_dir
    if sparse_dir == dataset_dir:  # given the model folder itself
        if sparse_dir.parent.name == "sparse":
            root = sparse_dir.parent.parent
        elif sparse_dir.name == "sparse":
            root = sparse_dir.parent
    image_dir = Path(images) if Path(images).is_absolute() else root / images
    if check_files and not image_dir.is_dir():
        found = sorted(p.name for p in root.iterdir() if p.is_dir() and p.name.startswith("images"))
        raise SceneFormatError(image_dir, "image folder not found (--images " + str(images) + "); "
                               + (f"image folders in {root}: {', '.join(found)}: pass one with --images" if found
                                  else f"{root} holds no images* folder: pass the folder of the photos with --images"))
    cam_file = sparse_dir / f"cameras.{model.format}"
    img_file = sparse_dir / f"images.{model.format}"
    if not model.images:
        raise SceneFormatError(img_file, "holds no registered image")

    ordered = sorted(model.images.values(), key=lambda im: im.name)
    seen: dict[str, int] = {}
    names, paths, Ks, poses, widths, heights = [], [], [], [], [], []
    intrinsics_of: dict[int, np.ndarray] = {}
    for image in ordered:
        if image.name in seen:
            raise SceneFormatError(
                img_file,
                f"images {seen[image.name]} and {image.id} have the same name {image.name!r}",
            )
        seen[image.name] = image.id
        camera = model.cameras.get(image.camera_id)
        if camera is None:
            raise SceneFormatError(
                img_file,
                f"image {image.id} ({image.name}) uses camera {image.camera_id}, "
                f"which {cam_file.name} does not hold",
            )
        if camera.id not in intrinsics_of:
            intrinsics_of[camera.id] = pinhole_intrinsics(camera, cam_file)
        K = intrinsics_of[camera.id].copy()
        width, height = camera.width, camera.height
        path = image_dir / image.name
        if check_files:
            width, height, K = _image_geometry(path, camera, K)
        try:
            pose = world_from_cam_of(image.qvec, image.tvec)
        except InputError as exc:
            raise SceneFormatError(img_file, f"image {image.id} ({image.name}): {exc}") from None
        if not np.isfinite(pose).all():
            raise SceneFormatError(img_file, f"image {image.id} ({image.name}): non-finite pose")
        names.append(image.name)
        paths.append(path)
        Ks.append(K)
        poses.append(pose)
        widths.append(width)
        heights.append(height)
    world_from_cam = check_pose(torch.from_numpy(np.stack(poses)), f"{img_file.name} poses")
    dataset = ColmapDataset(
        root=root,
        sparse_dir=sparse_dir,
        names=names,
        image_paths=paths,
        K=torch.from_numpy(np.stack(Ks)),
        world_from_cam=world_from_cam,
        widths=widths,
        heights=heights,
        image_ids=[im.id for im in ordered],
        camera_ids=[im.camera_id for im in ordered],
        format=model.format,
    )
    if points and model.points is not None:
        dataset.points_xyz = torch.from_numpy(model.points.xyz.copy())
        dataset.points_rgb = torch.from_numpy(model.points.rgb.copy())
    return dataset


def _image_geometry(path: Path, camera: ColmapCamera, K: np.ndarray) -> tuple[int, int, np.ndarray]:
    from roguenerf.imageio import read_image_size

    if not path.is_file():
        raise SceneFormatError(
            path,
            "missing image (named in the COLMAP model); pass the image folder "
            "with --images if it is not DATA/images",
        )
    try:
        width, height = read_image_size(path)
    except InputError as exc:
        raise SceneFormatError(path, str(exc)) from None
    if (width, height) == (camera.width, camera.height):
        return width, height, K
    sx, sy = width / camera.width, height / camera.height
    if abs(sx - sy) * max(camera.width, camera.height) > 1.0:
        raise SceneFormatError(
            path,
            f"image is {width}x{height} but its COLMAP camera {camera.id} is "
            f"{camera.width}x{camera.height} (aspect differs)",
        )
    K = K.copy()
    K[0] *= sx
    K[1] *= sy
    K[2] = (0.0, 0.0, 1.0)
    return width, height, K


# -- writing --------------------------------------------------------------------------------


def _fmt(x: float) -> str:
    return repr(float(x))


def write_colmap_model(folder: str | Path, model: ColmapModel, *, binary: bool = True) -> Path:
    """Write ``cameras``, ``images`` and ``points3D`` (binary or text) into ``folder`` (created)."""
    from roguenerf.imageio import atomic_write

    folder = Path(folder)
    pts = model.points if model.points is not None else ColmapPoints.empty()
    for cam in model.cameras.values():
        _check_camera(folder / "cameras", cam, f"camera {cam.id}")
    folder.mkdir(parents=True, exist_ok=True)
    if binary:
        out = [struct.pack("<Q", len(model.cameras))]
        for cam in model.cameras.values():
            out.append(
                struct.pack("<iiQQ", cam.id, CAMERA_MODELS[cam.model][0], cam.width, cam.height)
            )
            out.append(struct.pack("<" + "d" * len(cam.params), *cam.params))
        atomic_write(folder / "cameras.bin", b"".join(out))
        out = [struct.pack("<Q", len(model.images))]
        for im in model.images.values():
            out.append(struct.pack("<idddddddi", im.id, *im.qvec, *im.tvec, im.camera_id))
            out.append(im.name.encode("utf-8") + b"\x00")
            out.append(struct.pack("<Q", len(im.xys)))
            block = np.zeros(len(im.xys), dtype=[("x", "<f8"), ("y", "<f8"), ("id", "<i8")])
            if len(im.xys):
                block["x"], block["y"], block["id"] = im.xys[:, 0], im.xys[:, 1], im.point3D_ids
            out.append(block.tobytes())
        atomic_write(folder / "images.bin", b"".join(out))
        out = [struct.pack("<Q", len(pts.ids))]
        for n in range(len(pts.ids)):
            track = pts.tracks[n] if pts.tracks else np.zeros((0, 2), np.int32)
            out.append(
                struct.pack(
                    "<QdddBBBdQ",
                    int(pts.ids[n]),
                    *map(float, pts.xyz[n]),
                    *map(int, pts.rgb[n]),
                    float(pts.error[n]),
                    len(track),
                )
            )
            out.append(np.asarray(track, "<i4").tobytes())
        atomic_write(folder / "points3D.bin", b"".join(out))
        return folder
    lines = [
        "# Camera list with one line of data per camera:",
        "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]",
        f"# Number of cameras: {len(model.cameras)}",
    ]
    for cam in model.cameras.values():
        lines.append(
            " ".join(
                [str(cam.id), cam.model, str(cam.width), str(cam.height), *map(_fmt, cam.params)]
            )
        )
    atomic_write(folder / "cameras.txt", ("\n".join(lines) + "\n").encode())
    lines = [
        "# Image list with two lines of data per image:",
        "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME",
        "#   POINTS2D[] as (X, Y, POINT3D_ID)",
        f"# Number of images: {len(model.images)}",
    ]
    for im in model.images.values():
        lines.append(
            " ".join(
                [str(im.id), *map(_fmt, im.qvec), *map(_fmt, im.tvec), str(im.camera_id), im.name]
            )
        )
        lines.append(
            " ".join(
                f"{_fmt(x)} {_fmt(y)} {int(p)}"
                for (x, y), p in zip(im.xys, im.point3D_ids, strict=True)
            )
        )
    atomic_write(folder / "images.txt", ("\n".join(lines) + "\n").encode())
    lines = [
        "# 3D point list with one line of data per point:",
        "#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)",
        f"# Number of points: {len(pts.ids)}",
    ]
    for n in range(len(pts.ids)):
        track = pts.tracks[n] if pts.tracks else np.zeros((0, 2), np.int32)
        lines.append(
            " ".join(
                [
                    str(int(pts.ids[n])),
                    *map(_fmt, pts.xyz[n]),
                    *(str(int(c)) for c in pts.rgb[n]),
                    _fmt(pts.error[n]),
                    *(f"{int(a)} {int(b)}" for a, b in track),
                ]
            )
        )
    atomic_write(folder / "points3D.txt", ("\n".join(lines) + "\n").encode())
    return folder


def _sizes(value, m: int, name: str, what: str) -> list[int]:
    """One size per view from ``value`` (one for all or one per view), checked."""
    values = [value] * m if np.ndim(value) == 0 else list(value)
    if len(values) != m:
        raise InputError(
            f"{name}: expected one {what} for all views or one per view ({m}), got {len(values)}"
        )
    for i, v in enumerate(values):
        ok = isinstance(v, (int, np.integer)) and not isinstance(v, bool) and v > 0
        if not ok:
            where = name if np.ndim(value) == 0 else f"{name}[{i}]"
            raise InputError(f"{where}: expected a positive integer size in pixels, got {v!r}")
    return [int(v) for v in values]


def write_colmap(
    folder: str | Path,
    *,
    names: list[str],
    K,
    world_from_cam,
    widths: list[int] | int,
    heights: list[int] | int,
    binary: bool = True,
    points_xyz=None,
    points_rgb=None,
) -> Path:
    """Write views in our conventions as a COLMAP model (PINHOLE cameras, one per distinct
    intrinsics and size) into ``folder`` (e.g. ``DATA/sparse/0``); the inverse of
    :func:`read_colmap`.

    Args:
        K: ``(3, 3)`` or ``(M, 3, 3)``; world_from_cam: ``(M, 4, 4)`` OpenCV camera-to-world.
        widths, heights: one per view or one for all.
        points_xyz, points_rgb: optional ``(N, 3)`` sparse points (float, uint8).
    Raises:
        InputError: before anything is written, for what COLMAP cannot represent: a pose that is
            not a rigid camera-to-world matrix (checked as :func:`as_world_from_cam` does: a
            reflection, a scaled rotation, a bottom row other than ``0 0 0 1``), intrinsics that
            are not finite or have a focal length <= 0, sizes that are not positive integers or
            not one per view.
    """
    from roguenerf.geometry.cameras import as_world_from_cam, check_intrinsics

    # Everything is checked before anything is written: COLMAP stores a rotation as a unit
    # quaternion, so a reflection or a scaled rotation would read back as another pose.
    m = len(names)
    poses = np.asarray(
        world_from_cam.double() if isinstance(world_from_cam, Tensor) else world_from_cam,
        dtype=np.float64,
    )
    if poses.shape != (m, 4, 4):
        raise InputError(f"world_from_cam: expected shape ({m}, 4, 4), got {poses.shape}")
    poses = as_world_from_cam(torch.from_numpy(poses)).numpy()
    Ks = np.asarray(K.double() if isinstance(K, Tensor) else K, dtype=np.float64)
    if Ks.shape == (3, 3):
        Ks = np.broadcast_to(Ks, (m, 3, 3))
    if Ks.shape != (m, 3, 3):
        raise InputError(f"K: expected shape (3, 3) or ({m}, 3, 3), got {Ks.shape}")
    check_intrinsics(torch.from_numpy(np.array(Ks)))
    widths = _sizes(widths, m, "widths", "width")
    heights = _sizes(heights, m, "heights", "height")
    cameras: dict[int, ColmapCamera] = {}
    by_key: dict[tuple, int] = {}
    images: dict[int, ColmapImage] = {}
    for i, name in enumerate(names):
        k = Ks[i]
        if abs(k[0, 1]) > 0:
            raise InputError(f"K[{i}]: COLMAP's pinhole cameras have no skew, got {k[0, 1]}")
        params = (float(k[0, 0]), float(k[1, 1]), float(k[0, 2]), float(k[1, 2]))
        key = (params, int(widths[i]), int(heights[i]))
        if key not in by_key:
            by_key[key] = len(by_key) + 1
            cameras[by_key[key]] = ColmapCamera(by_key[key], "PINHOLE", key[1], key[2], params)
        qvec, tvec = colmap_pose_of(poses[i])
        images[i + 1] = ColmapImage(
            i + 1, tuple(map(float, qvec)), tuple(map(float, tvec)), by_key[key], name
        )
    pts = None
    if points_xyz is not None:
        xyz = np.asarray(points_xyz, dtype=np.float64).reshape(-1, 3)
        rgb = (
            np.asarray(points_rgb, dtype=np.uint8).reshape(-1, 3)
            if points_rgb is not None
            else np.full((len(xyz), 3), 128, np.uint8)
        )
        pts = ColmapPoints(
            np.arange(1, len(xyz) + 1, dtype=np.int64),
            xyz,
            rgb,
            np.zeros(len(xyz)),
            [np.zeros((0, 2), np.int32)] * len(xyz),
        )
    return write_colmap_model(folder, ColmapModel(cameras, images, pts), binary=binary)


# -- splits and scenes ----------------------------------------------------------------------

TRAINER_TEST_EVERY = 8
"""Inria (``--eval``, ``llffhold``) and gsplat (``--test-every``) hold out every 8th view."""


def read_split_file(path: str | Path) -> set[str]:
    """Test-view names from a split file: JSON ``{"train": [...], "test": [...]}`` (as our
    ``splits.json``) or text with one test image name per line (Inria's ``sparse/0/test.txt``)."""
    import json

    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise SceneFormatError(path, "missing split file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise SceneFormatError(path, f"cannot read ({exc})") from None
    if path.suffix.lower() == ".json":
        try:
            doc = json.loads(text)
        except json.JSONDecodeError as exc:
            raise SceneFormatError(path, f"invalid JSON: {exc}") from None
        if not isinstance(doc, dict) or not isinstance(doc.get("test", []), list):
            raise SceneFormatError(path, 'expected {"train": [...], "test": [...]}')
        return {str(n) for n in doc.get("test", []) + doc.get("val", [])}
    return {line.strip() for line in text.splitlines() if line.strip() and not line.startswith("#")}


def split_views(
    names: list[str], *, test_every: int = 0, split_file: str | Path | None = None
) -> list[str]:
    """``"train"`` / ``"test"`` per view, the trainers' way.

    ``names`` are sorted first (as Inria and gsplat sort them); with ``test_every = N > 0`` the
    views at positions ``0, N, 2N, ...`` of that order are test views (Inria's ``--eval``,
    gsplat's ``--test-every``); ``0`` keeps every view for training. A ``split_file`` (see
    :func:`read_split_file`) wins: its names match a view by COLMAP name, file name or stem; a
    name that matches no view raises :class:`~roguenerf.errors.SceneFormatError`.
    """
    if test_every < 0:
        raise InputError(f"test_every: expected >= 0, got {test_every}")
    if split_file is not None:
        wanted = read_split_file(split_file)
        keys = [{n, Path(n).name, Path(n).stem} for n in names]
        unknown = sorted(w for w in wanted if not any(w in k for k in keys))
        if unknown:
            raise SceneFormatError(
                split_file,
                f"names no view of the dataset: {', '.join(unknown[:5])}"
                + (" ..." if len(unknown) > 5 else ""),
            )
        return ["test" if k & wanted else "train" for k in keys]
    rank = {name: i for i, name in enumerate(sorted(names))}
    return ["test" if test_every and rank[n] % test_every == 0 else "train" for n in names]


def colmap_scene(
    dataset_dir: str | Path,
    *,
    images: str | Path = "images",
    test_every: int = 0,
    split_file: str | Path | None = None,
    check_files: bool = True,
):
    """A :class:`~roguenerf.data.scene.Scene` of a COLMAP dataset's photos (no renders yet),
    views in name order, split by :func:`split_views`; ``scene.meta["format"] == "colmap"``."""
    from roguenerf.data.scene import Frame, Scene

    data = read_colmap(dataset_dir, images=images, check_files=check_files)
    splits = split_views(data.names, test_every=test_every, split_file=split_file)
    frames = [
        Frame(
            name=name,
            world_from_cam=data.world_from_cam[i],
            K=data.K[i],
            width=data.widths[i],
            height=data.heights[i],
            split=splits[i],
            image_path=data.image_paths[i],
        )
        for i, name in enumerate(data.stems)
    ]
    meta = {"format": "colmap", "source": str(data.sparse_dir), "colmap_names": list(data.names)}
    return Scene(root=data.root, frames=frames, meta=meta)
