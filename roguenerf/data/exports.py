"""Renders and depths as nerfstudio and gsplat write them, turned into our scene folder.

Two tools, one function (:func:`import_renders`):

* **nerfstudio** (nerfacto, splatfacto): ``ns-render dataset --split train+test
  --rendered-output-names rgb raw-depth --output-path DIR`` writes ``DIR/<split>/rgb/NAME.jpg``
  (or ``.png``) and ``DIR/<split>/raw-depth/NAME.npy.gz``: a gzip-compressed ``(H, W, 1)``
  float32 array. nerfacto's depth is the expected *distance along the ray*; splatfacto's is
  z (gsplat's ``RGB+ED``). ns-render divides it by the dataparser's scale, so it is in the
  units of the dataset's own poses (``transforms.json``) already. The trained model's
  ``dataparser_transforms.json`` (``{"transform": 3x4, "scale": s}``) maps those poses to the
  model's world (``R' = T_R R``, ``t' = s (T_R t + T_t)``): needed for depth still in the
  model's units (``depth_units="model"``) and for camera paths drawn in nerfstudio's viewer
  (:mod:`roguenerf.trajectory`), so it is kept in the scene folder.
* **gsplat**: a folder ``DIR/rgb/NAME.png`` + ``DIR/depth/NAME.<ext>`` (or nerfstudio's
  split layout) written from ``rasterization(..., render_mode="RGB+ED")`` (z) or ``"ED"``
  (ray distance in newer gsplat). Pixels that no splat covers come out as 0 or as the map's
  maximum: both are made unknown (``background="max"``), never a real depth.

Depth files may be ``.npy``, ``.npy.gz``, ``.npz``, 16-bit PNG (times ``depth_scale``) or
32-bit float TIFF (Pillow, already a dependency; EXR is refused: no reader is a dependency),
see :func:`roguenerf.imageio.read_depth`. The output is a scene folder (photos and renders
copied byte for byte, depth converted to float32 z in pose units), written one view at a
time (bounded memory), ``transforms.json`` last.
"""

from __future__ import annotations

import json
import logging
import math
import re
import shutil
from dataclasses import dataclass
from pathlib import Path, PurePosixPath

import numpy as np
import torch
from torch import Tensor

from roguenerf.data.writers import camera_fields
from roguenerf.errors import InputError, SceneFormatError
from roguenerf.imageio import atomic_folder, read_json

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")
DEPTH_SUFFIXES = (".npy.gz", ".npy", ".npz", ".png", ".tif", ".tiff", ".exr")
RGB_FOLDERS = ("rgb", "renders", "render")
DEPTH_FOLDERS = ("raw-depth", "depth", "depths", "raw-expected_depth", "expected_depth")
SPLIT_FOLDERS = {"train": "train", "test": "test", "val": "test", "eval": "test"}
TOOLS = ("nerfstudio", "gsplat")
log = logging.getLogger("roguenerf.exports")
DATAPARSER_FILE = "dataparser_transforms.json"
"""Name of nerfstudio's dataparser file, next to the checkpoint and in our scene folder."""


@dataclass(frozen=True)
class DataparserTransform:
    """nerfstudio's dataparser transform: dataset poses -> the model's world.

    ``model_from_dataset`` applies ``R' = T_R R``, ``t' = s (T_R t + T_t)`` to a camera-to-world
    pose; :meth:`to_dataset` is its inverse. Both conventions (OpenGL / OpenCV) pass unchanged,
    since the axis flip multiplies on the right.
    """

    transform: Tensor
    """``(3, 4)`` float64: rotation ``T_R`` (orthonormal) and translation ``T_t``."""
    scale: float

    @classmethod
    def read(cls, path: str | Path) -> DataparserTransform:
        path = Path(path)
        data = read_json(path, lambda message: SceneFormatError(path, message), missing="missing file",
                         unreadable="cannot read")
        if not isinstance(data, dict) or "transform" not in data or "scale" not in data:
            raise SceneFormatError(path, 'expected {"transform": 3x4 matrix, "scale": number}')
        try:
            transform = torch.tensor(data["transform"], dtype=torch.float64)
            scale = float(data["scale"])
        except (TypeError, ValueError):
            raise SceneFormatError(path, "transform must be a 3x4 array of numbers, scale a number") from None
        if transform.shape == (4, 4):
            transform = transform[:3]
        if transform.shape != (3, 4) or not torch.isfinite(transform).all():
            raise SceneFormatError(path, f"transform: expected a finite 3x4 matrix, got shape {tuple(transform.shape)}")
        if not (math.isfinite(scale) and scale > 0):
            raise SceneFormatError(path, f"scale: expected a finite number > 0, got {scale}")
        R = transform[:, :3]
        if (R.T @ R - torch.eye(3, dtype=torch.float64)).abs().max() > 1e-4:
            raise SceneFormatError(path, "transform: its 3x3 part is not a rotation (nerfstudio's orientation "
                                         "methods only rotate; a scaling transform is not supported)")
        return cls(transform=transform, scale=scale)

    def to_dataset(self, world_from_cam: Tensor) -> Tensor:
        """``(..., 4, 4)`` camera-to-world in the model's world -> the dataset's (float64)."""
        pose = world_from_cam.to(torch.float64)
        R_T, t_T = self.transform[:, :3], self.transform[:, 3]
        out = pose.clone()
        out[..., :3, :3] = R_T.T @ pose[..., :3, :3]
        out[..., :3, 3] = (pose[..., :3, 3] / self.scale - t_T) @ R_T
        return out

    def to_model(self, world_from_cam: Tensor) -> Tensor:
        """Inverse of :meth:`to_dataset`."""
        pose = world_from_cam.to(torch.float64)
        R_T, t_T = self.transform[:, :3], self.transform[:, 3]
        out = pose.clone()
        out[..., :3, :3] = R_T @ pose[..., :3, :3]
        out[..., :3, 3] = self.scale * (pose[..., :3, 3] @ R_T.T + t_T)
        return out

    def to_json(self) -> dict:
        return {"transform": self.transform.tolist(), "scale": self.scale}


def _file_key(path: Path) -> tuple[str, str]:
    """``(stem, suffix)`` with the double suffix ``.npy.gz`` kept whole."""
    name = path.name
    lower = name.lower()
    for suffix in DEPTH_SUFFIXES + IMAGE_SUFFIXES:
        if lower.endswith(suffix):
            return name[: -len(suffix)], suffix
    return path.stem, path.suffix.lower()


def files_by_stem(folder: Path, suffixes: tuple[str, ...]) -> dict[str, Path]:
    """Files of ``folder`` (recursively) by stem; a stem found twice is ambiguous and dropped.
    What the render readers here and a camera path's frames (:func:`~roguenerf.trajectory.find_path_frames`)
    index their files with."""
    found: dict[str, Path] = {}
    twice: set[str] = set()
    for path in sorted(folder.rglob("*")):
        if not path.is_file() or path.name.startswith("."):
            continue
        stem, suffix = _file_key(path)
        if suffix not in suffixes:
            continue
        if stem in found:
            twice.add(stem)
        found[stem] = path
    for stem in twice:
        del found[stem]
    return found


def first_folder(folder: Path, names: tuple[str, ...]) -> Path | None:
    """The first of ``names`` that is a subfolder of ``folder`` (e.g. :data:`RGB_FOLDERS`), or None."""
    for name in names:
        if (folder / name).is_dir():
            return folder / name
    return None


def find_render_files(renders: str | Path) -> dict[str, tuple[Path, Path, str | None]]:
    """Map view name -> ``(rgb file, depth file, split or None)`` found under ``renders``.

    Layouts: nerfstudio's ``<split>/rgb/`` + ``<split>/raw-depth/`` (split from the folder,
    ``val`` counts as test), or flat ``rgb/`` + ``depth/`` (split from the dataset).
    """
    return _render_inventory(renders)[0]


def _render_inventory(renders: str | Path) -> tuple[dict[str, tuple[Path, Path, str | None]],
                                                     dict[str, tuple[Path, Path]], list[Path]]:
    """``(complete, half, depth_dirs)``: views with both files; views with only one of them
    (name -> (the file found, where the missing one was expected)); the depth folders searched."""
    renders = Path(renders)
    if not renders.is_dir():
        raise InputError(f"renders folder {renders} does not exist or is not a folder")
    groups: list[tuple[Path, str | None]] = []
    for name, split in SPLIT_FOLDERS.items():
        if (renders / name).is_dir():
            groups.append((renders / name, split))
    if not groups:
        groups = [(renders, None)]
    out: dict[str, tuple[Path, Path, str | None]] = {}
    half: dict[str, tuple[Path, Path]] = {}
    depth_dirs = []
    for folder, split in groups:
        rgb_dir, depth_dir = first_folder(folder, RGB_FOLDERS), first_folder(folder, DEPTH_FOLDERS)
        if rgb_dir is None or depth_dir is None:
            raise InputError(
                f"{folder}: expected a render folder ({' / '.join(RGB_FOLDERS)}) and a depth folder "
                f"({' / '.join(DEPTH_FOLDERS)}), e.g. from `ns-render dataset --rendered-output-names "
                "rgb raw-depth`")
        depth_dirs.append(depth_dir)
        rgbs, depths = files_by_stem(rgb_dir, IMAGE_SUFFIXES), files_by_stem(depth_dir, DEPTH_SUFFIXES)
        depth_suffix = next((_file_key(p)[1] for p in depths.values()), ".npy.gz")
        for stem, rgb in rgbs.items():
            if stem in depths:
                out.setdefault(stem, (rgb, depths[stem], split))
            else:
                half.setdefault(stem, (rgb, depth_dir / f"{stem}{depth_suffix}"))
        for stem, depth in depths.items():
            if stem not in rgbs:
                half.setdefault(stem, (depth, rgb_dir / f"{stem}.png"))
    for stem in out:
        half.pop(stem, None)
    return out, half, depth_dirs


INRIA_ITERATION = re.compile(r"^ours_(\d+)$")
GSPLAT_EVAL_IMAGE = re.compile(r"^(val|test|train)_step\d+_\d+\.png$")
NO_DEPTH_HINT = (
    "the enhancer needs a depth map per view, and this tool writes RGB only. Render RGB and depth "
    "from the trained splats instead: `roguenerf import-3dgs DATA --ply "
    "MODEL/point_cloud/iteration_30000/point_cloud.ply --output SCENE` (docs/splats.md)"
)


def find_indexed_renders(renders: str | Path) -> dict[str, list[tuple[Path, Path]]] | None:
    """Inria ``render.py`` output: ``MODEL/<split>/ours_<iteration>/renders/00000.png``, the
    ``i``-th camera of the split in name order (the latest iteration when several exist).

    Returns split -> ``[(render, depth)]`` in index order, or None when ``renders`` is not laid
    out that way. A depth folder beside ``renders/`` (``depth/``, any name of
    :data:`DEPTH_FOLDERS`, files named by index) is required: Inria writes none, and the
    :class:`InputError` says so and points to ``import-3dgs``. gsplat ``simple_trainer``'s eval
    images (``renders/val_step<N>_<i>.png``: photo and render side by side, no depth) are refused
    the same way.
    """
    renders = Path(renders)
    for folder in (renders, renders / "renders"):
        if folder.is_dir() and any(GSPLAT_EVAL_IMAGE.match(p.name) for p in folder.iterdir()):
            raise InputError(f"{folder}: gsplat simple_trainer's eval images (val_step<N>_<i>.png) "
                             f"hold the photo and the render side by side; {NO_DEPTH_HINT}")
    found: list[tuple[str, Path]] = []
    if INRIA_ITERATION.match(renders.name) and renders.parent.name in SPLIT_FOLDERS:
        found.append((SPLIT_FOLDERS[renders.parent.name], renders))
    else:
        for name, split in SPLIT_FOLDERS.items():
            folder = renders / name
            if not folder.is_dir():
                continue
            runs = [(int(m.group(1)), p) for p in folder.iterdir()
                    if p.is_dir() and (m := INRIA_ITERATION.match(p.name))]
            if runs:
                found.append((split, max(runs)[1]))
    found = [(split, folder) for split, folder in found if (folder / "renders").is_dir()]
    if not found:
        return None
    out: dict[str, list[tuple[Path, Path]]] = {}
    for split, folder in found:
        depth_dir = first_folder(folder, DEPTH_FOLDERS)
        if depth_dir is None:
            raise InputError(f"{folder}: Inria gaussian-splatting render.py output (renders/, gt/) has no "
                             f"depth; {NO_DEPTH_HINT}")
        rgbs = files_by_stem(folder / "renders", IMAGE_SUFFIXES)
        depths = files_by_stem(depth_dir, DEPTH_SUFFIXES)
        if not all(stem.isdigit() for stem in rgbs):
            return None
        missing = sorted(set(rgbs) - set(depths))
        if missing:
            raise InputError(f"{depth_dir}: no depth for the renders {', '.join(missing[:5])}")
        order = sorted(rgbs, key=int)
        if [int(stem) for stem in order] != list(range(len(order))):
            raise InputError(f"{folder / 'renders'}: expected renders numbered 0..{len(order) - 1} "
                             "(00000.png, 00001.png, ...)")
        out.setdefault(split, []).extend((rgbs[stem], depths[stem]) for stem in order)
    return out


def background_to_unknown(depth: Tensor, background: str) -> Tensor:
    """Make the no-surface pixels of a rendered depth unknown (0).

    ``"zero"``: only 0 (and what :func:`~roguenerf.geometry.depth.known_depth_mask` already
    refuses). ``"max"``: also every pixel holding the map's maximum value when at least two do
    (gsplat, saturated 16-bit PNG: no splat -> the largest value; a real surface is not flat at
    the bit-exact maximum).
    """
    if background not in ("zero", "max"):
        raise InputError(f"background: expected 'zero' or 'max', got {background!r}")
    if background == "max":
        finite = torch.isfinite(depth)
        if bool(finite.any()):
            top = depth[finite].max()
            at_top = depth == top
            if int(at_top.sum()) >= 2:
                depth = torch.where(at_top, torch.zeros_like(depth), depth)
    return depth


def _photo_for_size(frame, dataset_root: Path, width: int, height: int) -> Path:
    """The photo of ``frame`` at the render's size: the listed file, or nerfstudio's downscaled
    copy in ``images_<f>/`` (what ``--downscale-factor`` reads)."""
    from roguenerf.imageio import read_image_size

    path = frame.image_path
    w, h = read_image_size(path)
    if (w, h) == (width, height):
        return path
    factor = w / width
    rel = path.relative_to(dataset_root) if path.is_relative_to(dataset_root) else Path(path.name)
    if rel.parts and factor > 1 and abs(factor - round(factor)) < 1e-6:
        candidate = dataset_root / f"{rel.parts[0]}_{round(factor)}" / Path(*rel.parts[1:])
        if candidate.is_file() and read_image_size(candidate) == (width, height):
            return candidate
    raise SceneFormatError(path, f"photo is {w}x{h} but its render is {width}x{height}, and no downscaled "
                                 f"copy (e.g. {rel.parts[0] if rel.parts else 'images'}_2/) of that size exists")


def import_renders(
    dataset: str | Path,
    renders: str | Path,
    output: str | Path,
    *,
    tool: str = "nerfstudio",
    depth_type: str | None = None,
    depth_scale: float = 1.0,
    depth_units: str = "dataset",
    dataparser_transforms: str | Path | None = None,
    background: str | None = None,
    images: str | Path = "images",
    test_every: int | None = None,
    split_file: str | Path | None = None,
    progress=None,
    skip_missing: bool = False,
    check_depth: bool = True,
    hints: dict[str, str] | None = None,
):
    """Write a scene folder from a dataset (poses + photos) and a tool's renders.

    Args:
        dataset: a nerfstudio dataset (folder or its ``transforms.json``) or a COLMAP dataset
            (``images/`` + ``sparse/0``, :mod:`roguenerf.data.colmap`); its poses are the
            scene's poses, its photos the scene's photos.
        renders: the tool's output: named by view (see :func:`find_render_files`), or Inria's
            numbered ``<split>/ours_<iter>/renders/`` with a depth folder beside it (see
            :func:`find_indexed_renders`).
        output: the scene folder to write: new, empty, or an earlier import (replaced whole).
            Written atomically: built in a temporary sibling folder, renamed at the end; a failed
            import leaves no folder.
        tool: ``"nerfstudio"`` or ``"gsplat"``; picks the defaults below.
        depth_type: ``"ray"`` (nerfacto, gsplat ``ED``) or ``"z"`` (splatfacto, gsplat
            ``RGB+ED``); default ray for nerfstudio, z for gsplat.
        depth_scale: multiplies stored depth first (e.g. 0.001 for millimetre PNGs).
        depth_units: ``"dataset"`` (ns-render: already divided by the dataparser scale) or
            ``"model"`` (still in the model's world: divided by the scale here; needs the
            dataparser transforms).
        dataparser_transforms: the trained model's ``dataparser_transforms.json``; copied into
            the scene folder for camera paths drawn in nerfstudio's viewer.
        background: ``"zero"`` or ``"max"`` (see :func:`background_to_unknown`); default max for
            gsplat, zero for nerfstudio.
        images: the COLMAP dataset's image folder (``images_2`` for a 2x downscaled copy).
        test_every: held-out views, the trainers' way (:func:`~roguenerf.data.colmap.split_views`:
            names sorted, every ``test_every``-th from the first is ``test``; 8 is Inria's
            ``--eval`` and gsplat's default); 0: all train. None: a COLMAP dataset's every 8th
            view (as ``import_3dgs``'s ``hold``; with Inria's numbered renders, theirs: 8 when
            there are test renders, else 0); a nerfstudio dataset's own split.
        split_file: test-view names (JSON ``{"train": [...], "test": [...]}`` or one name per
            line, as Inria's ``sparse/0/test.txt``); wins over ``test_every``.
        progress: ``callback(done, total)`` per view.
        skip_missing: import the views that have both files and skip (with a warning) those
            missing their render or depth; otherwise a missing file is an InputError naming it.
        check_depth: refuse a ``depth_type`` that disagrees with the depths themselves
            (:func:`check_depth_type`: neighbouring views' depths must agree under it).
        hints: how the errors name the switches above to the caller: ``{"skip_missing": ...,
            "check_depth": ...}``; default their Python keywords (the CLI: its flags).
    Returns:
        The written scene, loaded (:func:`~roguenerf.data.readers.load_scene`);
        ``scene.meta["skipped_views"]`` lists the views skipped.
    """
    from roguenerf.data.readers import load_scene

    hints = {"skip_missing": "skip_missing=True", "check_depth": "check_depth=False", **(hints or {})}
    if tool not in TOOLS:
        raise InputError(f"tool: expected one of {', '.join(TOOLS)}, got {tool!r}")
    depth_type = depth_type or ("ray" if tool == "nerfstudio" else "z")
    if depth_type not in ("z", "ray"):
        raise InputError(f"depth_type: expected 'z' or 'ray', got {depth_type!r}")
    background = background or ("max" if tool == "gsplat" else "zero")
    if depth_units not in ("dataset", "model"):
        raise InputError(f"depth_units: expected 'dataset' or 'model', got {depth_units!r}")
    if not (isinstance(depth_scale, (int, float)) and math.isfinite(depth_scale) and depth_scale > 0):
        raise InputError(f"depth_scale: expected a finite number > 0, got {depth_scale!r}")
    parser = DataparserTransform.read(dataparser_transforms) if dataparser_transforms is not None else None
    if depth_units == "model":
        if parser is None:
            raise InputError("depth_units='model' needs the model's dataparser_transforms.json (its scale)")
        depth_scale = depth_scale / parser.scale

    dataset = Path(dataset)
    if not dataset.exists():
        raise InputError(f"dataset {dataset} does not exist")
    from roguenerf.data.colmap import TRAINER_TEST_EVERY, colmap_scene, is_colmap_dataset, split_views

    indexed = find_indexed_renders(renders)
    if test_every is None and indexed is not None and "test" in indexed:
        test_every = TRAINER_TEST_EVERY  # Inria wrote test renders: it was trained with --eval
    if dataset.is_dir() and not (dataset / "transforms.json").is_file() and is_colmap_dataset(dataset):
        source = colmap_scene(dataset, images=images, check_files=True)
    else:
        source = load_scene(dataset, check_files=False)
    if source.meta.get("format") not in ("nerfstudio", "colmap"):
        raise InputError(f"{dataset}: expected a nerfstudio dataset (transforms.json with the photos' poses) "
                         f"or a COLMAP dataset (images/ + sparse/0/), got a {source.meta.get('format')} scene")
    if test_every is None and split_file is None and source.meta.get("format") == "colmap":
        # The trainers' --eval split (import-3dgs's default too); Inria's numbered renders without
        # test renders: trained without it.
        test_every = 0 if indexed is not None else TRAINER_TEST_EVERY
    if test_every is not None or split_file is not None:
        names = source.meta.get("colmap_names") or [f.name for f in source.frames]
        for frame, split in zip(source.frames, split_views(names, test_every=test_every or 0,
                                                            split_file=split_file), strict=True):
            frame.split = split
    if indexed is not None:
        found, half = _match_indexed(indexed, source, renders), {}
    else:
        found, half, _ = _render_inventory(renders)
    frames = [f for f in source.frames if f.name in found]
    if not frames:
        some = ", ".join(sorted(found)[:3]) or "none"
        raise InputError(f"no render of {renders} matches a view of {dataset} by name "
                         f"(views: {', '.join(f.name for f in source.frames[:3])}, ...; renders: {some})")
    missing = []  # (view, what is missing)
    for f in source.frames:
        if f.name in found:
            continue
        if f.name in half:
            missing.append((f.name, str(half[f.name][1])))
        else:
            missing.append((f.name, f"its render and depth (no {f.name}.* under {renders})"))
    if missing and not skip_missing:
        listed = "; ".join(f"{name}: {what}" for name, what in missing[:5])
        more = f" (and {len(missing) - 5} more)" if len(missing) > 5 else ""
        raise InputError(f"{len(missing)} of {len(source.frames)} views of {dataset} lack a file: missing "
                         f"{listed}{more}. Render them, or pass {hints['skip_missing']} to "
                         "import the others without them")
    if missing:
        log.warning("skipped %d views without a render or depth: %s", len(missing),
                    ", ".join(name for name, _ in missing))
    if check_depth:
        # Multi-view consistency: the depth type given must make neighbouring views agree.
        check = check_depth_type(_depth_type_views(source, frames, found, depth_scale, background))
        problem = depth_type_problem(check, depth_type, "the depths", "neighbouring views")
        if problem is not None:
            raise InputError(f"{problem}; to import them as given anyway: {hints['check_depth']}")
    final = Path(output)
    # Built in a temporary sibling folder and renamed at the end: a failed import (a bad depth
    # file half-way) leaves no half-written scene folder behind.
    with atomic_folder(final, replaceable=_is_import, owned=written_files) as output:
        _write_import(source, frames, found, output, tool=tool, dataset=dataset, renders=renders,
                      depth_type=depth_type, depth_scale=depth_scale, background=background,
                      parser=parser, skipped=[name for name, _ in missing], progress=progress)
    scene = load_scene(final)
    scene.meta["skipped_views"] = [name for name, _ in missing]
    return scene


DEPTH_TYPE_PIXELS = 4000
"""Pixels per view that :func:`check_depth_type` reprojects into the view's neighbour."""
DEPTH_TYPE_VIEWS = 6
"""Views (each paired with its nearest view by position) :func:`check_depth_type` looks at."""


@dataclass
class DepthTypeCheck:
    """Multi-view consistency of a depth type (:func:`check_depth_type`)."""

    errors: dict
    """``{"z": e_z, "ray": e_ray}``: median ``|z_reprojected - z_neighbour| / z_neighbour``."""
    pixels: int
    likely: str | None
    """``"z"`` / ``"ray"`` when the data clearly side with one hypothesis, else None (inconclusive)."""
    beta: float = float("nan")
    """The fitted share of the predicted ray-distance error in the z hypothesis' residuals: ~0 for
    z-depth, ~1 for ray distance (see :func:`check_depth_type`)."""
    beta_se: float = float("nan")
    """Its standard error."""


def _sample_depth(depth: Tensor, u: Tensor, v: Tensor) -> tuple[Tensor, Tensor]:
    """Bilinear depth at continuous pixel coordinates (pixel centres at +0.5) and whether all four
    taps are known."""
    from roguenerf.geometry import known_depth_mask

    h, w = depth.shape[-2:]
    known = known_depth_mask(depth).to(torch.float64)
    d = torch.where(known > 0, depth.to(torch.float64), 0.0)
    grid = torch.stack([2 * u / w - 1, 2 * v / h - 1], -1)[None, None]
    stack = torch.cat([d.reshape(1, 1, h, w), known.reshape(1, 1, h, w)], 1)
    out = torch.nn.functional.grid_sample(stack, grid, mode="bilinear", padding_mode="zeros",
                                          align_corners=False)[0, :, 0]
    return out[0], out[1] > 1 - 1e-9


def depth_residuals(z_a: Tensor, K_a: Tensor, pose_a: Tensor, z_b: Tensor, K_b: Tensor, pose_b: Tensor,
                    pick: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Signed relative residuals ``(z - z_b(u', v')) / z_b`` of view a's pixels ``pick`` (flat
    indices) lifted with z-depth ``z_a`` ``(1, H, W)`` and projected into view b, where they are
    valid (in front, inside b, b's bilinear z-depth known at all four taps), the points' depth
    ``z`` in b and the ray-length factor ``sqrt(1 + x^2 + y^2)`` of b at ``(u', v')``."""
    K_a, K_b = K_a.to(torch.float64), K_b.to(torch.float64)
    pose_a, pose_b = pose_a.to(torch.float64), pose_b.to(torch.float64)
    w = z_a.shape[-1]
    v = (pick // w).to(torch.float64) + 0.5
    u = (pick % w).to(torch.float64) + 0.5
    y = (v - K_a[1, 2]) / K_a[1, 1]
    x = (u - K_a[0, 2] - K_a[0, 1] * y) / K_a[0, 0]
    rays = torch.stack([x, y, torch.ones_like(x)], -1)
    points = (rays * z_a.double().reshape(-1)[pick, None]) @ pose_a[:3, :3].T + pose_a[:3, 3]
    cam = (points - pose_b[:3, 3]) @ pose_b[:3, :3]
    z = cam[:, 2]
    front = z > 1e-9
    zs = torch.where(front, z, torch.ones_like(z))
    ub = K_b[0, 0] * cam[:, 0] / zs + K_b[0, 1] * cam[:, 1] / zs + K_b[0, 2]
    vb = K_b[1, 1] * cam[:, 1] / zs + K_b[1, 2]
    hb, wb = z_b.shape[-2:]
    d, ok = _sample_depth(z_b.reshape(hb, wb), ub, vb)
    ok = ok & front & (ub >= 0.5) & (ub <= wb - 0.5) & (vb >= 0.5) & (vb <= hb - 0.5)
    yb = (vb - K_b[1, 2]) / K_b[1, 1]
    xb = (ub - K_b[0, 2] - K_b[0, 1] * yb) / K_b[0, 0]
    return (z - d) / torch.where(ok, d, torch.ones_like(d)), ok, z, torch.sqrt(xb * xb + yb * yb + 1)


def _ray_factor(K: Tensor, pick: Tensor, w: int) -> Tensor:
    K = K.to(torch.float64)
    y = ((pick // w).to(torch.float64) + 0.5 - K[1, 2]) / K[1, 1]
    x = ((pick % w).to(torch.float64) + 0.5 - K[0, 2] - K[0, 1] * y) / K[0, 0]
    return torch.sqrt(x * x + y * y + 1)


def _known_pick(depth: Tensor, generator: torch.Generator, pixels: int) -> Tensor:
    from roguenerf.geometry import known_depth_mask

    known = known_depth_mask(depth).reshape(-1).nonzero()[:, 0]
    return known[torch.randperm(known.numel(), generator=generator)[:pixels]]


def _pair_residuals(raw_a: Tensor, K_a: Tensor, pose_a: Tensor, raw_b: Tensor, K_b: Tensor, pose_b: Tensor,
                    generator: torch.Generator, pixels: int, *,
                    b_is_z: bool = False) -> tuple[Tensor, Tensor, Tensor]:
    """Paired residuals ``(r_z, r_ray)`` of view a's depth reprojected into view b, on the pixels
    valid under both hypotheses (``b_is_z``: view b holds z-depth whatever a holds), and ``g``:
    what ``r_z`` would be for noise-free ray distances (``n_a / n_b - 1``, or ``n_a - 1`` with
    ``b_is_z``; ``n`` the ray-length factor at the pixel in each view; 0 for z-depth)."""
    from roguenerf.geometry.cameras import ray_to_z_depth

    pick = _known_pick(raw_a, generator, pixels)
    out, valid = [], None
    for kind in ("z", "ray"):
        za = raw_a.double() if kind == "z" else ray_to_z_depth(raw_a.double(), K_a)
        zb = raw_b.double() if kind == "z" or b_is_z else ray_to_z_depth(raw_b.double(), K_b)
        r, ok, z_in_b, n_b = depth_residuals(za, K_a, pose_a, zb, K_b, pose_b, pick)
        out.append(r)
        valid = ok if valid is None else valid & ok
    # Ray distances taken as z put each point n_a times as far from camera a: its depth in b
    # becomes c + n_a (z_in_b - c), c = camera a's own depth in b; b's stored value is
    # n_b z_in_b (ray) or z_in_b (b_is_z). n_b from the ray hypothesis (the last one); z_in_b
    # replaced by its median, so that no pixel's depth noise enters the prediction (it would
    # correlate with that pixel's residual and bias the fit).
    pose_a, pose_b = pose_a.to(torch.float64), pose_b.to(torch.float64)
    c = float(((pose_a[:3, 3] - pose_b[:3, 3]) @ pose_b[:3, :3])[2])
    n_a = _ray_factor(K_a, pick, raw_a.shape[-1])
    z_typ = float(z_in_b[valid].median()) if bool(valid.any()) else 1.0
    g = (c + n_a * (z_typ - c)) / ((1.0 if b_is_z else n_b) * z_typ) - 1
    return out[0][valid], out[1][valid], g[valid]


DEPTH_TYPE_OUTLIER = 0.1
"""Pixels whose residual exceeds this (relative) under either hypothesis are left out of the fit
(occlusions, depth edges, floaters)."""


def check_depth_type(views, *, pixels: int = DEPTH_TYPE_PIXELS, seed: int = 0, b_is_z: bool = False) -> DepthTypeCheck:
    """Which depth type (z along the optical axis, or distance along the ray) makes the depths of
    neighbouring views agree? A cheap multi-view test: a few hundred pixels of each view are
    lifted to 3-D with its depth under each hypothesis and projected into the neighbour, whose
    depth (same hypothesis) must agree.

    Two tests. The medians of ``|r_z|`` and ``|r_ray|`` (relative residuals): the right type
    agrees to the depth's own accuracy, the wrong one is off by the change of the ray-length
    factor ``n = sqrt(1 + x^2 + y^2)`` between the views. Where depth noise hides that in the
    medians, its signature still shows: ray distances read as z would give each pixel the residual
    ``g`` (from ``n`` in both views and the baseline alone, no depth noise), so the z hypothesis'
    residuals are fitted as ``r_z = c + beta * g + noise`` (least squares, outliers beyond
    :data:`DEPTH_TYPE_OUTLIER` left out): ``beta`` is ~0 for z-depth and ~1 for ray distance, with a
    standard error that shrinks with the pixels.

    Args:
        views: pairs ``((raw_a, K_a, pose_a), (raw_b, K_b, pose_b))``: stored depth ``(1, H, W)``
            (unknown where :func:`~roguenerf.geometry.known_depth_mask` says so), ``(3, 3)``
            intrinsics, ``(4, 4)`` OpenCV camera-to-world.
        b_is_z: the second view of each pair holds z-depth whatever the hypothesis (a scene's
            training view, against which a camera path's frames are checked).
    Returns:
        :class:`DepthTypeCheck`: ``likely`` is set when ``beta`` is within 0.3 of one answer,
        at least 0.7 from the other, with a standard error under 0.1, or when one hypothesis'
        median ``|r|`` is under a third of the other's (which exceeds 0.3 %), and the two tests do
        not disagree (at least 50 pixels). On the toy scenes (exact depth, 58 deg field of view)
        both tests decide; on ``../shared/data/lego`` (a grid field's depth, 2 % noise, 40 deg) the
        fit finds ray distances (beta 0.87 +- 0.10) and leaves its true z-depth undecided (beta
        -2.2: the field's position-dependent depth error is as large as the z-vs-ray difference);
        undecided never refuses.
    """
    generator = torch.Generator().manual_seed(seed)
    rz, rr, gs = [], [], []
    for a, b in views:
        z_res, ray_res, g = _pair_residuals(*a, *b, generator, pixels, b_is_z=b_is_z)
        rz.append(z_res)
        rr.append(ray_res)
        gs.append(g)
    empty = torch.empty(0, dtype=torch.float64)
    r_z = torch.cat(rz) if rz else empty
    r_ray = torch.cat(rr) if rr else empty
    g_all = torch.cat(gs) if gs else empty
    errors = {"z": float(r_z.abs().median()) if r_z.numel() else float("nan"),
              "ray": float(r_ray.abs().median()) if r_ray.numel() else float("nan")}
    inliers = (r_z.abs() < DEPTH_TYPE_OUTLIER) & (r_ray.abs() < DEPTH_TYPE_OUTLIER)
    r, pred = r_z[inliers], g_all[inliers]
    n = int(r.numel())
    beta = se = float("nan")
    if n >= 50:
        dc = pred - pred.mean()
        sxx = float((dc * dc).sum())
        if sxx > 0:
            beta = float((dc * (r - r.mean())).sum()) / sxx
            resid = (r - r.mean()) - beta * dc
            se = math.sqrt(float((resid * resid).sum()) / max(n - 2, 1) / sxx)
    by_fit = None
    if math.isfinite(beta) and math.isfinite(se) and se < 0.1:
        if abs(beta) < 0.3 and abs(beta - 1) > 0.7:
            by_fit = "z"
        elif abs(beta - 1) < 0.3 and abs(beta) > 0.7:
            by_fit = "ray"
    by_median = None
    if n >= 50 and all(math.isfinite(e) for e in errors.values()):
        if errors["z"] * 3 < errors["ray"] and errors["ray"] > 3e-3:
            by_median = "z"
        elif errors["ray"] * 3 < errors["z"] and errors["z"] > 3e-3:
            by_median = "ray"
    # Either test may decide (the medians where the depth is accurate, the fit where noise hides
    # the difference in the medians); when they disagree, nothing is concluded.
    votes = {v for v in (by_fit, by_median) if v is not None}
    likely = votes.pop() if len(votes) == 1 else None
    return DepthTypeCheck(errors=errors, pixels=n, likely=likely, beta=beta, beta_se=se)


def depth_type_problem(check: DepthTypeCheck, given: str, what: str, between: str) -> str | None:
    """The message for a ``given`` depth type that :func:`check_depth_type` finds wrong, else None."""
    if check.likely is None or check.likely == given:
        return None
    other = check.likely
    looks = "z-depth (along the optical axis)" if other == "z" else "distance along the ray"
    return (f"{what} look like {looks}, not --depth-type {given}: reprojected between {between} they "
            f"disagree by a median {100 * check.errors[given]:.2f}% as {given}, {100 * check.errors[other]:.2f}% "
            f"as {other} (fit of the ray-distance signature {check.beta:+.2f} +- {check.beta_se:.2f}: 0 for z, "
            f"1 for ray; {check.pixels} pixels). Likely fix: --depth-type {other} (depth_type={other!r})")


def _depth_type_views(source, frames, found, depth_scale: float, background: str, count: int = DEPTH_TYPE_VIEWS):
    """Pairs for :func:`check_depth_type`: up to ``count`` views, each with its nearest by position."""
    from roguenerf.geometry.cameras import scale_intrinsics
    from roguenerf.imageio import read_depth, read_image_size

    cache: dict[str, tuple[Tensor, Tensor, Tensor]] = {}

    def view(frame):
        if frame.name not in cache:
            rgb_path, depth_path, _ = found[frame.name]
            width, height = read_image_size(rgb_path)
            K = scale_intrinsics(frame.K, width / frame.width, height / frame.height)
            depth = read_depth(depth_path, scale=float(depth_scale)).double()
            if tuple(depth.shape[1:]) != (height, width):
                raise SceneFormatError(depth_path, f"depth is {depth.shape[2]}x{depth.shape[1]}, its render "
                                                   f"{rgb_path.name} is {width}x{height}")
            cache[frame.name] = (background_to_unknown(depth, background), K, frame.world_from_cam)
        return cache[frame.name]

    if len(frames) < 2:
        return []
    positions = torch.stack([f.world_from_cam[:3, 3].to(torch.float64) for f in frames])
    chosen = sorted({round(k * (len(frames) - 1) / max(count - 1, 1)) for k in range(min(count, len(frames)))})
    pairs = []
    for i in chosen:
        dist = (positions - positions[i]).norm(dim=-1)
        dist[i] = float("inf")
        j = int(dist.argmin())
        pairs.append((view(frames[i]), view(frames[j])))
    return pairs


def _is_import(folder: Path) -> bool:
    try:
        doc = json.loads((folder / "transforms.json").read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError):
        return False
    return isinstance(doc, dict) and isinstance(doc.get("source"), dict) and doc["source"].get("tool") in TOOLS


SCENE_FILE_KEYS = ("file_path", "render_path", "depth_path", "acc_path")


def written_files(folder: Path) -> set[str]:
    """The files of the scene folder ``folder`` that an importer wrote (relative POSIX paths): its
    ``transforms.json``, the files its frames name, and the dataparser transforms."""
    try:
        doc = json.loads((Path(folder) / "transforms.json").read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError):
        return set()
    files = {"transforms.json", DATAPARSER_FILE}
    frames = doc.get("frames") if isinstance(doc, dict) else None
    for frame in frames if isinstance(frames, list) else []:
        if isinstance(frame, dict):
            files.update(str(PurePosixPath(frame[key])) for key in SCENE_FILE_KEYS if isinstance(frame.get(key), str))
    return files


def _write_import(source, frames, found, output: Path, *, tool, dataset, renders, depth_type, depth_scale,
                  background, parser, skipped, progress):
    """Write the scene folder ``output`` (the temporary one) view by view, transforms.json last."""
    from roguenerf.data.readers import load_scene
    from roguenerf.geometry.cameras import opencv_to_opengl, ray_to_z_depth, scale_intrinsics
    from roguenerf.imageio import atomic_write, encode_npy, read_depth, read_image_size

    for sub in ("images", "renders", "depths"):
        (output / sub).mkdir(parents=True, exist_ok=True)
    dataset_root = source.root
    out_frames = []
    for n, frame in enumerate(frames):
        rgb_path, depth_path, split = found[frame.name]
        width, height = read_image_size(rgb_path)
        K = scale_intrinsics(frame.K, width / frame.width, height / frame.height)
        photo = _photo_for_size(frame, dataset_root, width, height)
        depth = read_depth(depth_path, scale=float(depth_scale)).double()
        if tuple(depth.shape[1:]) != (height, width):
            raise SceneFormatError(depth_path, f"depth is {depth.shape[2]}x{depth.shape[1]}, its render "
                                               f"{rgb_path.name} is {width}x{height}")
        depth = background_to_unknown(depth, background)
        if depth_type == "ray":
            depth = ray_to_z_depth(depth, K)
        photo_out = output / "images" / f"{frame.name}{photo.suffix.lower()}"
        render_out = output / "renders" / f"{frame.name}{_file_key(rgb_path)[1]}"
        shutil.copyfile(photo, photo_out)
        shutil.copyfile(rgb_path, render_out)
        atomic_write(output / "depths" / f"{frame.name}.npy", encode_npy(depth[0].float().numpy()))
        gl = opencv_to_opengl(frame.world_from_cam)
        out_frames.append({
            "file_path": str(photo_out.relative_to(output)),
            "render_path": str(render_out.relative_to(output)),
            "depth_path": f"depths/{frame.name}.npy",
            "split": split or frame.split,
            **camera_fields(K, width, height),
            "transform_matrix": gl.tolist(),
        })
        if progress is not None:
            progress(n + 1, len(frames))
    if parser is not None:
        atomic_write(output / DATAPARSER_FILE, json.dumps(parser.to_json(), indent=2).encode())
    doc = {
        "camera_model": "OPENCV",
        "source": {"tool": tool, "dataset": str(dataset), "renders": str(renders), "depth_type": depth_type,
                   "background": background, "skipped_views": len(skipped), "skipped": skipped},
        "frames": out_frames,
    }
    atomic_write(output / "transforms.json", json.dumps(doc, indent=1).encode())
    return load_scene(output)  # it loads (every file is there and readable) before it is renamed


def _match_indexed(indexed: dict[str, list[tuple[Path, Path]]], source, renders) -> dict:
    """Numbered renders -> view names: the ``i``-th render of a split is the ``i``-th view of
    that split in name order (how Inria lists its cameras)."""
    order = source.meta.get("colmap_names") or [f.name for f in source.frames]
    by_split: dict[str, list[str]] = {}
    for _, frame in sorted(zip(order, source.frames, strict=True), key=lambda pair: pair[0]):
        by_split.setdefault(frame.split, []).append(frame.name)
    out = {}
    for split, files in indexed.items():
        views = by_split.get(split, [])
        if len(files) != len(views):
            raise InputError(
                f"{renders}: {len(files)} {split} renders, but the dataset has {len(views)} {split} views "
                f"with this split; pass the split the model was trained with (--hold 8 for "
                f"Inria's --eval, --hold 0 without it, or --split-file)")
        for name, (rgb, depth) in zip(views, files, strict=True):
            out[name] = (rgb, depth, split)
    return out


def write_depth_like(path: str | Path, depth: np.ndarray, *, kind: str, scale: float = 1.0) -> Path:
    """Write ``depth`` ``(H, W)`` the way a tool would (for tests and examples): ``kind`` is
    ``"npy.gz"`` (nerfstudio: ``(H, W, 1)`` float32, gzip), ``"npy"``, ``"npz"``, ``"png16"``
    (``round(depth / scale)`` as 16-bit) or ``"tiff"`` (32-bit float)."""
    import gzip
    import io

    from PIL import Image

    path = Path(path)
    depth = np.asarray(depth, dtype=np.float32)
    if kind == "npy.gz":
        buf = io.BytesIO()
        np.save(buf, depth[..., None])
        path.write_bytes(gzip.compress(buf.getvalue()))
    elif kind == "npy":
        np.save(path, depth)
    elif kind == "npz":
        np.savez_compressed(path, depth=depth)
    elif kind == "png16":
        values = np.clip(np.round(depth / scale), 0, 65535).astype(np.uint16)
        Image.fromarray(values).save(path)
    elif kind == "tiff":
        Image.fromarray(depth).save(path)
    else:
        raise InputError(f"kind: expected npy.gz, npy, npz, png16 or tiff, got {kind!r}")
    return path
