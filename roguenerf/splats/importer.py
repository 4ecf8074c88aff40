"""A trained 3DGS scene in: render every dataset view (RGB, z-depth, opacity) from its ``.ply``
and write our scene folder with the photos; render a camera path's frames for ``enhance-path``.

Datasets: a COLMAP dataset (``images/`` + ``sparse/0``, :mod:`roguenerf.data.colmap`; every
``hold``-th view in name order is a test view, the trainers' ``--eval`` split) or anything
:func:`~roguenerf.data.readers.load_scene` reads with photos (nerfstudio ``transforms.json``,
LLFF, a scene folder). The ``.ply`` must be in the dataset's world, as Inria's and gsplat's
trainers write it; nerfstudio's splatfacto exports live in its model's world: give its
``dataparser_transforms.json`` and the cameras are mapped there and the depth back.

Rendering uses ``gsplat`` when CUDA and gsplat are there (``backend="auto"``), else the CPU
rasterizer of :mod:`roguenerf.splats.raster`: one image formation either way (3DGS's).
Outputs are written into a temporary folder beside ``output`` and renamed into place at the end.
"""

from __future__ import annotations

import importlib.util
import json
import shutil
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import Tensor

from roguenerf.data.writers import CONVENTIONS, camera_fields
from roguenerf.errors import InputError
from roguenerf.imageio import atomic_folder, check_output_folder
from roguenerf.splats.gaussians import Gaussians
from roguenerf.splats.raster import DEFAULT_DEPTH_THRESHOLD, render

BACKENDS = ("auto", "cpu", "gsplat")
TOOL = "3dgs"
"""``source.tool`` of what ``import-3dgs`` writes (the scene's and the path's transforms.json): its marker."""
PATH_FOLDER = "path"
PATH_CAMERAS = "transforms.json"
"""The path's cameras as rendered (transforms style, the dataset's world), beside ``rgb/`` and ``depth/``."""
"""Where ``import_3dgs(..., camera_path=...)`` writes the path's frames inside the scene folder."""


@dataclass
class DatasetView:
    name: str
    photo: Path
    K: Tensor
    world_from_cam: Tensor
    width: int
    height: int
    split: str


def read_dataset_views(dataset: str | Path, *, hold: int = 8, images: str = "images") -> tuple[list[DatasetView], str]:
    """The posed photos of a dataset and its format (``"colmap"`` or :func:`load_scene`'s)."""
    from roguenerf.data.colmap import is_colmap_dataset, read_colmap
    from roguenerf.data.readers import load_scene

    dataset = Path(dataset)
    if not dataset.exists():
        raise InputError(f"dataset {dataset} does not exist")
    if hold < 0:
        raise InputError(f"hold: expected >= 0 (0: every view is a training view), got {hold}")
    if is_colmap_dataset(dataset) and not (dataset / "transforms.json").is_file():
        ds = read_colmap(dataset, images=images)
        return [DatasetView(name, path, ds.K[i], ds.world_from_cam[i], ds.widths[i], ds.heights[i],
                            "test" if hold and i % hold == 0 else "train")
                for i, (name, path) in enumerate(zip(ds.stems, ds.image_paths, strict=True))], "colmap"
    scene = load_scene(dataset)
    views = []
    for f in scene.frames:
        if f.image_path is None:
            raise InputError(f"{dataset}: view {f.name} has no photo")
        views.append(DatasetView(f.name, f.image_path, f.K, f.world_from_cam, f.width, f.height, f.split))
    return views, str(scene.meta.get("format", "scene"))


def pick_backend(backend: str) -> str:
    if backend not in BACKENDS:
        raise InputError(f"backend: expected one of {', '.join(BACKENDS)}, got {backend!r}")
    has_gsplat = importlib.util.find_spec("gsplat") is not None and torch.cuda.is_available()
    if backend == "gsplat" and not has_gsplat:
        raise InputError("backend gsplat: needs the gsplat package and a CUDA GPU (use --backend cpu)")
    if backend == "auto":
        return "gsplat" if has_gsplat else "cpu"
    return backend


def render_view(gaussians: Gaussians, world_from_cam: Tensor, K: Tensor, height: int, width: int, *,
                backend: str = "cpu", depth_threshold: float = DEFAULT_DEPTH_THRESHOLD,
                background=None) -> tuple[Tensor, Tensor, Tensor]:
    """RGB ``(3, H, W)``, z-depth ``(1, H, W)`` (0: unknown) and opacity ``(1, H, W)`` on the CPU."""
    with torch.no_grad():
        if backend == "gsplat":
            return _render_gsplat(gaussians, world_from_cam, K, height, width, depth_threshold, background)
        rgb, depth, acc = render(gaussians, world_from_cam, K, height, width, background=background,
                                 depth_threshold=depth_threshold)
    return rgb.clamp(0, 1), depth, acc.clamp(0, 1)


def _render_gsplat(g: Gaussians, world_from_cam, K, height, width, depth_threshold, background):
    import gsplat  # optional: CUDA only

    dev = torch.device("cuda")
    cache = getattr(g, "_cuda", None)
    if cache is None:
        cache = (g.means.to(dev), g.quats.to(dev), torch.exp(g.log_scales).to(dev),
                 torch.sigmoid(g.opacity).to(dev), g.sh.to(dev))
        g._cuda = cache
    means, quats, scales, opac, sh = cache
    viewmat = torch.linalg.inv(torch.as_tensor(world_from_cam, dtype=torch.float64)).float().to(dev)
    bg = torch.zeros(3) if background is None else torch.as_tensor(background, dtype=torch.float32)
    colours, alphas, _ = gsplat.rasterization(
        means, quats, scales, opac, sh, viewmat[None], torch.as_tensor(K, dtype=torch.float32).to(dev)[None],
        int(width), int(height), sh_degree=g.sh_degree, render_mode="RGB+ED", backgrounds=bg.to(dev)[None])
    rgb = colours[0, ..., :3].permute(2, 0, 1).float().cpu().clamp(0, 1)
    depth = colours[0, ..., 3:4].permute(2, 0, 1).float().cpu()
    acc = alphas[0].permute(2, 0, 1).float().cpu().clamp(0, 1)
    depth = torch.where(acc >= depth_threshold, depth, torch.zeros_like(depth))
    return rgb, depth, acc


def _model_camera(world_from_cam: Tensor, parser) -> Tensor:
    return world_from_cam if parser is None else parser.to_model(world_from_cam)


def _source(doc_file: Path) -> dict:
    try:
        doc = json.loads(doc_file.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError):
        return {}
    source = doc.get("source") if isinstance(doc, dict) else None
    return source if isinstance(source, dict) else {}


def _is_ours(folder: Path) -> bool:
    """An earlier scene folder of ``import-3dgs`` (its own marker: ``source.tool``): replaced whole."""
    source = _source(folder / "transforms.json")
    return source.get("tool") == TOOL and "camera_path" not in source  # not a rendered path


def _is_our_path(folder: Path) -> bool:
    """An earlier rendered path (``render_camera_path``, ``import-3dgs --path``): replaced whole."""
    source = _source(folder / PATH_CAMERAS)
    # Without "tool": written before the marker was (its only keys were these two).
    return (source.get("tool") == TOOL and "camera_path" in source) or set(source) == {"camera_path", "format"}


def _our_path_files(folder: Path) -> set[str]:
    """The files a rendered path holds: the cameras, then a frame and a depth per camera."""
    try:
        count = len(json.loads((folder / PATH_CAMERAS).read_text(encoding="utf-8"))["frames"])
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, KeyError, TypeError):
        return {PATH_CAMERAS}
    digits = max(5, len(str(count)))
    return {PATH_CAMERAS, *(f"rgb/{t:0{digits}d}.png" for t in range(count)),
            *(f"depth/{t:0{digits}d}.npy" for t in range(count))}


def _our_files(folder: Path) -> set[str]:
    """What an earlier ``import-3dgs`` wrote: the scene folder's files and those of its rendered path."""
    from roguenerf.data.exports import written_files

    path = folder / PATH_FOLDER
    inner = {f"{PATH_FOLDER}/{name}" for name in _our_path_files(path)} if _is_our_path(path) else set()
    return written_files(folder) | inner


def import_3dgs(dataset: str | Path, ply: str | Path, output: str | Path, *, backend: str = "auto",
                hold: int = 8, images: str = "images", dataparser_transforms: str | Path | None = None,
                depth_threshold: float = DEFAULT_DEPTH_THRESHOLD, camera_path: str | Path | None = None,
                progress: Callable[[int, int], None] | None = None):
    """Render every view of ``dataset`` from the 3DGS ``ply`` and write the scene folder ``output``.

    Args:
        dataset: COLMAP dataset or a folder :func:`load_scene` reads (with photos).
        ply: Inria ``point_cloud.ply``.
        backend: ``"auto"`` (gsplat with CUDA, else the CPU rasterizer), ``"cpu"`` or ``"gsplat"``.
        hold: COLMAP datasets: every ``hold``-th view is a test view (0: none).
        images: COLMAP datasets: the image folder (``images_2`` for a half-size training).
        dataparser_transforms: nerfstudio's file when the ``.ply`` is in its model's world.
        depth_threshold: depth is known where the opacity reaches this share.
        camera_path: also render this camera path into ``output/path`` (see :func:`render_camera_path`).
        progress: ``callback(done, total)`` per view (dataset views, then path frames).
    Returns:
        The written scene, loaded.
    """
    from roguenerf.data.exports import DATAPARSER_FILE, DataparserTransform
    from roguenerf.data.readers import load_scene
    from roguenerf.geometry.cameras import opencv_to_opengl
    from roguenerf.imageio import atomic_write, encode_npy, encode_png, read_image_size
    from roguenerf.splats.ply import read_ply

    backend = pick_backend(backend)
    check_output_folder(Path(output), _is_ours, "output", owned=_our_files)
    views, fmt = read_dataset_views(dataset, hold=hold, images=images)
    parser = DataparserTransform.read(dataparser_transforms) if dataparser_transforms is not None else None
    gaussians = read_ply(ply)
    output = Path(output)
    path_cams = None
    if camera_path is not None:
        from roguenerf.paths import read_camera_path

        path_cams = read_camera_path(camera_path, dataparser=parser)
    with atomic_folder(output, replaceable=_is_ours, owned=_our_files) as tmp:
        total = len(views) + (len(path_cams) if path_cams is not None else 0)
        frames = []
        for n, view in enumerate(views):
            width, height = read_image_size(view.photo)
            if (width, height) != (view.width, view.height):
                raise InputError(f"{view.photo}: photo is {width}x{height}, its camera says {view.width}x{view.height}")
            rgb, depth, acc = render_view(gaussians, _model_camera(view.world_from_cam, parser), view.K, height,
                                          width, backend=backend, depth_threshold=depth_threshold)
            if parser is not None:
                depth = depth / parser.scale
            suffix = view.photo.suffix.lower()
            photo_rel = f"images/{view.name}{'.jpg' if suffix == '.jpeg' else suffix}"
            (tmp / "images").mkdir(exist_ok=True)
            shutil.copyfile(view.photo, tmp / photo_rel)
            atomic_write(tmp / "renders" / f"{view.name}.png", encode_png(rgb), make_parents=True)
            atomic_write(tmp / "depths" / f"{view.name}.npy", encode_npy(depth[0].numpy()), make_parents=True)
            atomic_write(tmp / "acc" / f"{view.name}.png", encode_png(acc), make_parents=True)
            frames.append({
                "file_path": photo_rel, "render_path": f"renders/{view.name}.png",
                "depth_path": f"depths/{view.name}.npy", "acc_path": f"acc/{view.name}.png", "split": view.split,
                **camera_fields(view.K, width, height),
                "transform_matrix": opencv_to_opengl(view.world_from_cam).tolist(),
            })
            if progress is not None:
                progress(n + 1, total)
        if parser is not None:
            atomic_write(tmp / DATAPARSER_FILE, json.dumps(parser.to_json(), indent=2).encode())
        if path_cams is not None:
            _render_path_into(gaussians, path_cams, Path(camera_path), tmp / PATH_FOLDER, backend, parser,
                              depth_threshold, lambda k, _t: progress(len(views) + k, total) if progress else None)
        doc = {
            "camera_model": "OPENCV",
            **CONVENTIONS,
            "source": {"tool": TOOL, "dataset": str(dataset), "dataset_format": fmt, "ply": str(ply),
                       "gaussians": len(gaussians), "sh_degree": gaussians.sh_degree, "backend": backend,
                       "depth_threshold": depth_threshold},
            "frames": frames,
        }
        atomic_write(tmp / "transforms.json", json.dumps(doc, indent=1).encode())
    return load_scene(output)


def _render_path_into(gaussians, cams, camera_file: Path, folder: Path, backend, parser, depth_threshold,
                      progress) -> None:
    from roguenerf.imageio import atomic_write, encode_npy, encode_png

    digits = max(5, len(str(len(cams))))
    for t in range(len(cams)):
        rgb, depth, _ = render_view(gaussians, _model_camera(cams.world_from_cam[t], parser), cams.K[t],
                                    cams.height, cams.width, backend=backend, depth_threshold=depth_threshold)
        if parser is not None:
            depth = depth / parser.scale
        atomic_write(folder / "rgb" / f"{t:0{digits}d}.png", encode_png(rgb), make_parents=True)
        atomic_write(folder / "depth" / f"{t:0{digits}d}.npy", encode_npy(depth[0].numpy()), make_parents=True)
        if progress is not None:
            progress(t + 1, len(cams))
    # The cameras as rendered (the dataset's world, whatever file they came from): what
    # ``enhance-path --cameras`` reads beside the frames.
    from roguenerf.geometry.cameras import opencv_to_opengl

    doc = {"fps": cams.fps, "source": {"tool": TOOL, "camera_path": str(camera_file), "format": cams.source},
           "frames": [{"transform_matrix": opencv_to_opengl(cams.world_from_cam[t]).tolist(),
                       **camera_fields(cams.K[t], cams.width, cams.height)} for t in range(len(cams))]}
    atomic_write(folder / PATH_CAMERAS, json.dumps(doc, indent=1).encode())


def render_camera_path(ply: str | Path, camera_path: str | Path, output: str | Path, *, backend: str = "auto",
                       dataparser_transforms: str | Path | None = None,
                       depth_threshold: float = DEFAULT_DEPTH_THRESHOLD,
                       progress: Callable[[int, int], None] | None = None) -> Path:
    """Render a camera path (nerfstudio ``camera_path.json`` or a transforms-style list, poses in
    the dataset's world) from ``ply`` into ``output/rgb/NNNNN.png`` + ``output/depth/NNNNN.npy``,
    with the camera file copied beside them: what ``enhance-path --frames`` reads."""
    from roguenerf.data.exports import DataparserTransform
    from roguenerf.paths import read_camera_path
    from roguenerf.splats.ply import read_ply

    backend = pick_backend(backend)
    check_output_folder(Path(output), _is_our_path, "path output", owned=_our_path_files)
    parser = DataparserTransform.read(dataparser_transforms) if dataparser_transforms is not None else None
    cams = read_camera_path(camera_path, dataparser=parser)
    gaussians = read_ply(ply)
    output = Path(output)
    with atomic_folder(output, replaceable=_is_our_path, what="path output", owned=_our_path_files) as tmp:
        _render_path_into(gaussians, cams, Path(camera_path), tmp, backend, parser, depth_threshold, progress)
    return output
