"""Readers for the scene formats users have, all returning one :class:`Scene`.

:func:`load_scene` autodetects:

* **Scene folder** (the format of ``../shared/data/lego``): ``transforms.json`` in nerfstudio
  style whose frames carry ``render_path`` and/or ``depth_path`` (float32 ``.npy`` z-depth in
  pose units) and ``split``.
* **nerfstudio dataset**: ``transforms.json`` whose frames may carry ``depth_file_path``
  (16-bit PNG or ``.npy``, multiplied by ``depth_unit_scale_factor``, default 1e-3 as in
  nerfstudio, i.e. millimetres). Depth is z-depth unless ``depth_type`` says ``"ray"``
  (top-level or per-frame key, or the ``depth_type`` argument, which wins). Splits come from
  the ``train_filenames`` / ``val_filenames`` / ``test_filenames`` lists of nerfstudio, a
  ``splits.json`` file next to ``transforms.json`` (``{"train": [...], "test": [...]}``), a
  per-frame ``"split"`` key, or else every view is ``train``. Validation views count as test.
* **COLMAP dataset** (``images/`` + ``sparse/0/{cameras,images,points3D}.bin`` or ``.txt``):
  the photos and poses only, every view ``train`` (:func:`roguenerf.data.colmap.colmap_scene`
  takes the trainers' splits); renders come with ``import-gsplat`` / ``import-3dgs``.
* **LLFF**: ``poses_bounds.npy`` (N x 17: a 3x5 block per view, rotation columns down, right,
  back, then H, W, focal; near/far bounds) with images in ``images/`` or ``images_<factor>/``.
  Poses stay in their own units (bounds are only validated and kept in ``scene.meta``);
  every ``llff_hold``-th view (default 8, the usual LLFF protocol) is ``test``.

Both JSON formats: OpenGL camera-to-world ``transform_matrix`` (converted to OpenCV),
intrinsics ``fl_x, fl_y, cx, cy, w, h`` at the top level with per-frame overrides, pixel-centre
convention. Pixels are not decoded while loading: only image and ``.npy`` headers are read to
check sizes, so loading is fast and every malformed file is named in a
:class:`~roguenerf.errors.SceneFormatError`.
"""

from __future__ import annotations

import json
import math
import warnings
from pathlib import Path

import numpy as np
import torch

from roguenerf.data.scene import Frame, Scene
from roguenerf.errors import InputError, SceneFormatError
from roguenerf.geometry.cameras import check_intrinsics, check_pose, llff_to_opencv, opengl_to_opencv

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")
NERFSTUDIO_DEPTH_SCALE = 1e-3
"""nerfstudio's default ``depth_unit_scale_factor`` (depth stored in millimetres)."""


def load_scene(
    path: str | Path,
    *,
    depth_type: str | None = None,
    llff_factor: int | None = None,
    llff_hold: int = 8,
    check_files: bool = True,
    confine: bool = False,
) -> Scene:
    """Load a scene folder, a nerfstudio dataset or an LLFF dataset (format autodetected).

    Args:
        path: the folder, its ``transforms.json`` or its ``poses_bounds.npy``.
        depth_type: ``"z"`` or ``"ray"`` overrides what the files say (JSON formats).
        llff_factor: read ``images_<factor>/`` (LLFF); None uses ``images/``.
        llff_hold: every ``llff_hold``-th LLFF view is a test view (0: all train).
        check_files: read each image/depth header to check that it exists, is decodable and has
            the size the metadata states (no pixels are decoded).
        confine: refuse file paths that lead outside the scene's folder (absolute, ``..``,
            symbolic links): for scenes from someone else, e.g. an uploaded zip, whose
            ``transforms.json`` could otherwise name any file of the machine.
    Raises:
        SceneFormatError: naming the offending file and what is wrong with it.
    """
    if depth_type not in (None, "z", "ray"):
        raise InputError(f"depth_type must be 'z', 'ray' or None, got {depth_type!r}")
    path = Path(path)
    if not path.exists():
        raise SceneFormatError(path, "no such file or folder")
    if path.is_file():
        if path.name == "poses_bounds.npy":
            return _load_llff(path, llff_factor, llff_hold, check_files)
        if path.suffix == ".json":
            return _load_transforms(path, depth_type, check_files, confine)
        raise SceneFormatError(path, "expected a scene folder, a transforms.json or a poses_bounds.npy")
    if (path / "transforms.json").is_file():
        return _load_transforms(path / "transforms.json", depth_type, check_files, confine)
    if (path / "poses_bounds.npy").is_file():
        return _load_llff(path / "poses_bounds.npy", llff_factor, llff_hold, check_files)
    from roguenerf.data.colmap import colmap_scene, is_colmap_dataset

    if is_colmap_dataset(path):
        if confine:
            raise SceneFormatError(path, "a COLMAP dataset is not a scene folder: import it first")
        return colmap_scene(path, check_files=check_files)
    raise SceneFormatError(
        path, "not a scene: expected transforms.json (scene folder / nerfstudio), poses_bounds.npy (LLFF) "
        "or a COLMAP model (sparse/0/)"
    )


# -- transforms.json (scene folder and nerfstudio) ---------------------------------------


def _load_transforms(json_path: Path, depth_type: str | None, check_files: bool, confine: bool = False) -> Scene:
    root = json_path.parent

    def _resolve(root: Path, relative: str) -> Path:
        path = _resolve_path(root, relative)
        if confine:
            inside = root.resolve()
            if not path.resolve().is_relative_to(inside):
                raise SceneFormatError(json_path, f"{where}: {relative!r} leads outside the scene folder")
        return path

    try:
        text = json_path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise SceneFormatError(json_path, f"cannot read ({exc})") from None
    try:
        data = json.loads(text)
    except json.JSONDecodeError as exc:
        raise SceneFormatError(json_path, f"invalid JSON: {exc}") from None
    if not isinstance(data, dict):
        raise SceneFormatError(json_path, f"expected a JSON object at the top level, got {type(data).__name__}")
    frames_json = data.get("frames")
    if not isinstance(frames_json, list) or not frames_json:
        raise SceneFormatError(json_path, "missing key 'frames' (a non-empty list of views)")

    model = data.get("camera_model", "OPENCV")
    if model not in ("OPENCV", "PINHOLE", "SIMPLE_PINHOLE"):
        raise SceneFormatError(json_path, f"camera_model {model!r} is not supported (pinhole/OPENCV only)")
    scene_folder = any(isinstance(f, dict) and ("render_path" in f or "depth_path" in f) for f in frames_json)
    splits = _split_lists(json_path, data)

    frames = []
    distorted = False
    for n, fj in enumerate(frames_json):
        where = f"frames[{n}]"
        if not isinstance(fj, dict):
            raise SceneFormatError(json_path, f"{where}: expected an object, got {type(fj).__name__}")
        file_path = _get(json_path, fj, "file_path", where, str)
        image_path = _resolve(root, file_path)
        name = Path(file_path).stem

        cam = {}
        for key in ("fl_x", "fl_y", "cx", "cy"):
            value = fj.get(key, data.get(key))
            if key == "fl_y" and value is None:
                value = cam.get("fl_x")
            if value is None:
                raise SceneFormatError(json_path, f"{where}: missing key {key!r} (per frame or top level)")
            cam[key] = _number(json_path, value, f"{where}.{key}")
        distorted |= any(
            abs(float(fj.get(k, data.get(k, 0.0)) or 0.0)) > 0 for k in ("k1", "k2", "k3", "k4", "p1", "p2")
        )
        width, height = fj.get("w", data.get("w")), fj.get("h", data.get("h"))
        if width is None or height is None:
            if not check_files:
                raise SceneFormatError(json_path, f"{where}: missing 'w'/'h' (needed when check_files=False)")
            width, height = _image_size(image_path)
        width = _int(json_path, width, f"{where}.w")
        height = _int(json_path, height, f"{where}.h")

        K = torch.tensor(
            [[cam["fl_x"], 0.0, cam["cx"]], [0.0, cam["fl_y"], cam["cy"]], [0.0, 0.0, 1.0]], dtype=torch.float64
        )
        try:
            check_intrinsics(K, f"{where} intrinsics")
        except InputError as exc:
            raise SceneFormatError(json_path, str(exc)) from None
        pose = _pose(json_path, fj, where)

        split = _frame_split(json_path, fj, file_path, name, splits, where)
        render_path = depth_path = None
        if "render_path" in fj:
            render_path = _resolve(root, _get(json_path, fj, "render_path", where, str))
        if scene_folder:
            depth_key, scale = "depth_path", 1.0
        else:
            depth_key = "depth_file_path"
            scale = _number(
                json_path, data.get("depth_unit_scale_factor", NERFSTUDIO_DEPTH_SCALE), "depth_unit_scale_factor"
            )
            if scale <= 0:
                raise SceneFormatError(json_path, f"depth_unit_scale_factor must be > 0, got {scale}")
        if depth_key in fj:
            depth_path = _resolve(root, _get(json_path, fj, depth_key, where, str))
        dtype = depth_type or fj.get("depth_type", data.get("depth_type", "z"))
        if dtype not in ("z", "ray"):
            raise SceneFormatError(json_path, f"{where}: depth_type must be 'z' or 'ray', got {dtype!r}")
        frames.append(
            Frame(
                name=name,
                world_from_cam=pose,
                K=K,
                width=width,
                height=height,
                split=split,
                image_path=image_path,
                render_path=render_path,
                depth_path=depth_path,
                depth_scale=scale,
                depth_type=dtype,
            )
        )
    if distorted:
        warnings.warn(
            f"{json_path}: lens distortion coefficients are ignored (the enhancer assumes pinhole "
            "images; undistort them first for exact reprojection)",
            stacklevel=3,
        )
    _check_unique(json_path, frames)
    if check_files:
        for frame in frames:
            _check_frame_files(frame)
    meta = {"format": "scene-folder" if scene_folder else "nerfstudio", "source": str(json_path)}
    return Scene(root=root, frames=frames, meta=meta)


def _get(json_path: Path, obj: dict, key: str, where: str, kind: type):
    if key not in obj:
        raise SceneFormatError(json_path, f"{where}: missing key {key!r}")
    value = obj[key]
    if not isinstance(value, kind):
        raise SceneFormatError(json_path, f"{where}.{key}: expected {kind.__name__}, got {type(value).__name__}")
    return value


def _number(json_path: Path, value, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise SceneFormatError(json_path, f"{where}: expected a finite number, got {value!r}")
    return float(value)


def _int(json_path: Path, value, where: str) -> int:
    if isinstance(value, float) and value.is_integer():
        value = int(value)
    if isinstance(value, bool) or not isinstance(value, int) or value <= 0:
        raise SceneFormatError(json_path, f"{where}: expected a positive integer, got {value!r}")
    return value


def _resolve_path(root: Path, relative: str) -> Path:
    path = Path(relative)
    path = path if path.is_absolute() else root / path
    if not path.exists():
        # A name written decomposed (NFD: macOS) whose file was stored composed (NFC: what the
        # service's upload writes), or the reverse.
        import unicodedata

        for form in ("NFC", "NFD"):
            other = Path(unicodedata.normalize(form, str(path)))
            if other != path and other.exists():
                return other
    return path


def _pose(json_path: Path, fj: dict, where: str) -> torch.Tensor:
    matrix = fj.get("transform_matrix")
    if matrix is None:
        raise SceneFormatError(json_path, f"{where}: missing key 'transform_matrix'")
    try:
        gl = np.asarray(matrix, dtype=np.float64)
    except (TypeError, ValueError):
        raise SceneFormatError(json_path, f"{where}.transform_matrix: expected a 4x4 array of numbers") from None
    if gl.shape == (3, 4):
        gl = np.concatenate([gl, [[0.0, 0.0, 0.0, 1.0]]])
    if gl.shape != (4, 4):
        raise SceneFormatError(json_path, f"{where}.transform_matrix: expected shape (4, 4), got {gl.shape}")
    if not np.isfinite(gl).all():
        raise SceneFormatError(json_path, f"{where}.transform_matrix: contains NaN or inf")
    try:
        return check_pose(opengl_to_opencv(torch.from_numpy(gl)), f"{where}.transform_matrix")
    except InputError as exc:
        raise SceneFormatError(json_path, str(exc)) from None


def _split_lists(json_path: Path, data: dict) -> dict[str, set[str]] | None:
    """Split membership by file path and stem, from nerfstudio keys or a splits.json."""
    lists: dict[str, list] = {}
    for split, keys in (("train", ("train_filenames",)), ("test", ("val_filenames", "test_filenames"))):
        for key in keys:
            if key in data:
                if not isinstance(data[key], list):
                    raise SceneFormatError(json_path, f"{key}: expected a list of file names")
                lists.setdefault(split, []).extend(data[key])
    splits_file = json_path.parent / "splits.json"
    if not lists and splits_file.is_file():
        try:
            sj = json.loads(splits_file.read_text(encoding="utf-8"))
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise SceneFormatError(splits_file, f"invalid JSON: {exc}") from None
        if not isinstance(sj, dict) or not set(sj) <= {"train", "val", "test"}:
            raise SceneFormatError(splits_file, 'expected {"train": [...], "test": [...]} (optional "val")')
        for split, names in sj.items():
            if not isinstance(names, list):
                raise SceneFormatError(splits_file, f"{split}: expected a list of names")
            lists.setdefault("train" if split == "train" else "test", []).extend(names)
    if not lists:
        return None
    return {
        split: {str(n) for n in names} | {Path(str(n)).stem for n in names} for split, names in lists.items()
    }


def _frame_split(json_path, fj, file_path, name, splits, where) -> str:
    if splits is not None:
        for split in ("test", "train"):
            members = splits.get(split, set())
            if file_path in members or name in members:
                return split
        if "train" not in splits:
            return "train"
        if "test" not in splits:
            return "test"
        raise SceneFormatError(json_path, f"{where}: view {file_path!r} is in none of the split lists")
    split = fj.get("split", "train")
    if split == "val":
        split = "test"
    if split not in ("train", "test"):
        raise SceneFormatError(json_path, f"{where}.split: expected 'train' or 'test', got {split!r}")
    return split


def _check_unique(source: Path, frames: list[Frame]) -> None:
    seen: dict[str, int] = {}
    for n, frame in enumerate(frames):
        if frame.name in seen:
            raise SceneFormatError(
                source,
                f"views {seen[frame.name]} and {n} have the same name {frame.name!r} (file stems must be unique)",
            )
        seen[frame.name] = n


def _image_size(path: Path) -> tuple[int, int]:
    from roguenerf.imageio import read_image_size

    if not path.is_file():
        raise SceneFormatError(path, "missing file")
    try:
        return read_image_size(path)
    except InputError as exc:
        raise SceneFormatError(path, _strip(exc, path)) from None


def _check_frame_files(frame: Frame) -> None:
    for path in (frame.image_path, frame.render_path):
        if path is None:
            continue
        width, height = _image_size(path)
        if (width, height) != (frame.width, frame.height):
            raise SceneFormatError(
                path, f"image is {width}x{height} (WxH), the scene says {frame.width}x{frame.height}"
            )
    if frame.depth_path is not None:
        height, width = _depth_size(frame.depth_path)
        if (width, height) != (frame.width, frame.height):
            raise SceneFormatError(
                frame.depth_path, f"depth is {width}x{height} (WxH), the scene says {frame.width}x{frame.height}"
            )


def _depth_size(path: Path) -> tuple[int, int]:
    """``(H, W)`` from a depth file's header (``.npy`` header or PNG IHDR) without reading data
    (compressed formats, which have no such header, are decoded)."""
    if not path.is_file():
        raise SceneFormatError(path, "missing file")
    with open(path, "rb") as f:
        head = f.read(8)
        f.seek(0)
        if head.startswith(b"\x93NUMPY"):
            try:
                version = np.lib.format.read_magic(f)
                read = np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
                shape, _, dtype = read(f)
            except (ValueError, EOFError, OSError) as exc:
                raise SceneFormatError(path, f"not a valid .npy file ({exc})") from None
            if dtype.hasobject or dtype.kind not in "fiu":
                raise SceneFormatError(path, f"depth dtype must be a real float or integer type, got {dtype}")
            if len(shape) == 3 and shape[0] == 1:
                shape = shape[1:]
            elif len(shape) == 3 and shape[2] == 1:
                shape = shape[:2]
            if len(shape) != 2:
                raise SceneFormatError(path, f"depth shape must be (H, W), (1, H, W) or (H, W, 1), got {tuple(shape)}")
            return int(shape[0]), int(shape[1])
        if not head.startswith(b"\x89PNG"):
            # .npy.gz, .npz, TIFF: no cheap header to read; decode once (bounded by max_pixels).
            from roguenerf.imageio import read_depth

            try:
                depth = read_depth(path)
            except InputError as exc:
                raise SceneFormatError(path, _strip(exc, path)) from None
            return int(depth.shape[1]), int(depth.shape[2])
    width, height = _image_size(path)
    return height, width


def _strip(exc: Exception, path: Path) -> str:
    message = str(exc)
    prefix = f"{path}: "
    return message[len(prefix):] if message.startswith(prefix) else message


# -- LLFF ---------------------------------------------------------------------------------


def _load_llff(pb_path: Path, factor: int | None, hold: int, check_files: bool) -> Scene:
    root = pb_path.parent
    try:
        array = np.load(pb_path, allow_pickle=False)
    except (ValueError, OSError, EOFError) as exc:
        raise SceneFormatError(pb_path, f"not a valid .npy array ({exc})") from None
    if array.ndim != 2 or array.shape[1] != 17 or array.shape[0] == 0 or array.dtype.kind not in "fiu":
        raise SceneFormatError(pb_path, f"expected a numeric (N, 17) array, got {array.dtype} {array.shape}")
    array = array.astype(np.float64)
    if not np.isfinite(array).all():
        bad = int(np.nonzero(~np.isfinite(array).all(axis=1))[0][0])
        raise SceneFormatError(pb_path, f"row {bad} (view {bad}) contains NaN or inf")
    n = array.shape[0]
    blocks = array[:, :15].reshape(n, 3, 5)
    hwf = blocks[:, :, 4]
    bounds = array[:, 15:17]
    if (hwf <= 0).any():
        raise SceneFormatError(pb_path, "hwf column (height, width, focal) must be positive")
    if (bounds[:, 0] <= 0).any() or (bounds[:, 1] <= bounds[:, 0]).any():
        bad = int(np.nonzero((bounds[:, 0] <= 0) | (bounds[:, 1] <= bounds[:, 0]))[0][0])
        raise SceneFormatError(pb_path, f"view {bad}: bounds must satisfy 0 < near < far, got {bounds[bad].tolist()}")
    if hold < 0:
        raise InputError(f"llff_hold must be >= 0, got {hold}")

    folder = root / ("images" if factor is None else f"images_{int(factor)}")
    if not folder.is_dir():
        raise SceneFormatError(folder, "missing image folder")
    files = sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
    if len(files) != n:
        raise SceneFormatError(folder, f"holds {len(files)} images, poses_bounds.npy has {n} views")

    try:
        poses = llff_to_opencv(torch.from_numpy(blocks[:, :, :4].copy()))
        poses = check_pose(poses, "poses_bounds.npy poses")
    except InputError as exc:
        raise SceneFormatError(pb_path, str(exc)) from None

    frames = []
    for i, image_path in enumerate(files):
        full_h, full_w, focal = hwf[i]
        if check_files:
            width, height = _image_size(image_path)
        else:
            div = 1 if factor is None else factor
            width, height = int(round(full_w / div)), int(round(full_h / div))
        if check_files and (abs(width * full_h - height * full_w) > max(full_w, full_h)):
            raise SceneFormatError(
                image_path,
                f"image is {width}x{height} but poses_bounds.npy says {full_w:g}x{full_h:g} (aspect differs)",
            )
        sx, sy = width / full_w, height / full_h
        K = torch.tensor(
            [[focal * sx, 0.0, width / 2.0], [0.0, focal * sy, height / 2.0], [0.0, 0.0, 1.0]], dtype=torch.float64
        )
        split = "test" if hold > 0 and i % hold == 0 else "train"
        frames.append(
            Frame(
                name=image_path.stem,
                world_from_cam=poses[i],
                K=K,
                width=width,
                height=height,
                split=split,
                image_path=image_path,
            )
        )
    _check_unique(folder, frames)
    meta = {"format": "llff", "source": str(pb_path), "bounds": torch.from_numpy(bounds)}
    return Scene(root=root, frames=frames, meta=meta)
