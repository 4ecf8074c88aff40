"""A trained 3DGS scene in: render every dataset view (RGB, z-depth, opacity) from its ``.ply``
and write our scene folder with the photos; render a camera path's frames for ``enhance-path``.

Datasets: a COLMAP dataset (``images/`` + ``sparse/0``, :mod:`roguenerf.data.colmap`; every
``hold``-th view in name order is a test view, the trainers' ``--eval`` split) or anything
:func:`~roguenerf.data.readers.load_scene` reads with photos (nerfstudio ``transforms.json``,
LLFF, a scene folder). The ``.ply`` must be in the dataset's world, as Inria's and gsplat's
trainers write it; nerfstudio's splatfacto exports live in its model's world: give its
``dataparser_transforms.json`` and the cameras are mapped there and the depth back.

Before rendering, cheap checks: the splats lie in the dataset's world (:func:`check_world`: a
``.ply`` in gsplat's normalised world or a splatfacto export without its transform renders blank
views) and a camera path sees them (:func:`~roguenerf.trajectory.check_camera_path`); ``force`` goes on.
An Inria model folder gives the ``.ply`` (latest iteration) and, without a path, a smooth
:func:`fly_through` of the dataset's views.

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

import numpy as np
import torch
from torch import Tensor

from roguenerf.data.scene import Frame, Scene
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


WORLD_VIEWS = 8
"""How many dataset views (evenly spread) :func:`check_world` projects the splats into."""
WORLD_GRID = 16
""":func:`check_world` counts the cells of a ``WORLD_GRID x WORLD_GRID`` grid over each view that
hold the projected centre of a Gaussian."""
MIN_COVERAGE = 0.05
"""A view "sees" the splats when at least this share of its grid cells holds a Gaussian's centre
(the right .ply of the tests: a third and more; one recentred and scaled by 1/20, as gsplat's
trainer saves it by default: 0 to 2 %)."""
WORLD_SAMPLE = 200_000
"""At most this many Gaussians (evenly strided) are projected: the check stays cheap."""
FLY_KEYS = 24
"""A fly-through passes through at most this many dataset views (evenly spread in name order)."""
FLY_FRAMES = 120
"""Frames of the fly-through :func:`import_3dgs` renders when a model folder comes without a path."""


@dataclass
class WorldCheck:
    """What :func:`check_world` found; ``problem`` is None when the splats lie in the views."""

    checked: list[str]
    coverage: list[float]
    """Per checked view: share of the grid cells holding a Gaussian's projected centre."""
    extent_ratio: float
    """The Gaussians' extent (90th percentile distance from their median) over the cameras' spread."""
    offset: float
    """Distance from the cameras' centre to the Gaussians' median, in cameras' spreads."""
    problem: str | None = None


def check_world(gaussians: Gaussians, views: list[DatasetView], parser=None, *,
                views_checked: int = WORLD_VIEWS) -> WorldCheck:
    """Do the splats lie in the dataset's world? Project the Gaussians' centres (opacity >= 5 %,
    at most :data:`WORLD_SAMPLE`) into up to ``views_checked`` dataset cameras (evenly spread;
    with ``parser`` mapped to the model's world) and measure which share of each view they cover
    (:data:`WORLD_GRID` cells). Cheap: no rendering. ``problem`` is set when fewer than half the
    checked views see the splats (:data:`MIN_COVERAGE`); it names the likely causes and their fixes."""
    from roguenerf.splats.gaussians import logit

    keep = gaussians.opacity >= logit(0.05)
    means = gaussians.means[keep].to(torch.float64)
    if means.shape[0] > WORLD_SAMPLE:
        means = means[:: -(-means.shape[0] // WORLD_SAMPLE)]
    n = max(1, min(views_checked, len(views)))
    picked = sorted({round(k * (len(views) - 1) / max(n - 1, 1)) for k in range(n)})
    poses = torch.stack([_model_camera(v.world_from_cam, parser).to(torch.float64) for v in views])
    coverage = []
    for i in picked:
        view, pose = views[i], poses[i]
        cam = (means - pose[:3, 3]) @ pose[:3, :3]
        z = cam[:, 2]
        front = z > 1e-9
        x, y, z = cam[front, 0], cam[front, 1], z[front]
        K = view.K.to(torch.float64)
        u = K[0, 0] * x / z + K[0, 1] * y / z + K[0, 2]
        v = K[1, 1] * y / z + K[1, 2]
        inside = (u >= 0) & (u < view.width) & (v >= 0) & (v < view.height)
        cells = ((u[inside] * WORLD_GRID / view.width).long() * WORLD_GRID
                 + (v[inside] * WORLD_GRID / view.height).long())
        coverage.append(float(cells.unique().numel()) / WORLD_GRID ** 2)
    centres = poses[:, :3, 3]
    cam_centre = centres.mean(0)
    spread = float((centres - cam_centre).norm(dim=-1).max()) or 1.0
    if means.shape[0]:
        median = means.median(dim=0).values
        extent = float(torch.quantile((means - median).norm(dim=-1)[:100_000], 0.9))
        offset = float((median - cam_centre).norm()) / spread
    else:
        extent, offset = 0.0, float("nan")
    check = WorldCheck(checked=[views[i].name for i in picked], coverage=coverage, extent_ratio=extent / spread,
                       offset=offset)
    seeing = sum(c >= MIN_COVERAGE for c in coverage)
    if 2 * seeing < len(picked):
        median_cover = sorted(coverage)[len(coverage) // 2]
        check.problem = (
            f"--ply: the splats do not lie in the dataset's world: {seeing} of {len(picked)} checked views see "
            f"them (the Gaussians' centres cover a median {100 * median_cover:.1f}% of a view); the Gaussians "
            f"span {check.extent_ratio:.2g} times the cameras' spread, their centre {offset:.2g} spreads from "
            "the cameras' centre. Likely causes: gsplat's simple_trainer normalises the world by default "
            "(recentred on the cameras and scaled): retrain with --no-normalize-world-space, or map the .ply "
            "back with the inverse of its parser's transform; a splatfacto export lives in nerfstudio's model "
            "world: pass --dataparser-transforms dataparser_transforms.json (beside the model's config.yml)"
            + (" that belongs to this model" if parser is not None else "")
            + "; a .ply of another dataset. To import it anyway: --force")
    return check


def find_model_ply(model: str | Path) -> Path:
    """The latest ``point_cloud/iteration_N/point_cloud.ply`` of an Inria model folder (largest N)."""
    import re

    model = Path(model)
    if not model.is_dir():
        raise InputError(f"--model: {model} is not a folder (expected Inria's model folder: cameras.json, "
                         "point_cloud/iteration_*/point_cloud.ply)")
    found = []
    for ply in (model / "point_cloud").glob("iteration_*/point_cloud.ply"):
        m = re.fullmatch(r"iteration_(\d+)", ply.parent.name)
        if m and ply.is_file():
            found.append((int(m.group(1)), ply))
    if not found:
        raise InputError(f"--model: {model} has no point_cloud/iteration_*/point_cloud.ply (what Inria's train.py "
                         "writes); give the .ply with --ply")
    return max(found)[1]


def _check_model_cameras(model: Path, views: list[DatasetView]) -> None:
    """The model's ``cameras.json`` (when there) must name views of the dataset."""
    from roguenerf.trajectory import read_camera_path

    cameras = model / "cameras.json"
    if not cameras.is_file():
        return
    names = read_camera_path(cameras).names
    ours = {v.name for v in views}
    if names and not ours & set(names):
        raise InputError(f"--model: {cameras} names none of the dataset's views (it has {', '.join(names[:3])}, "
                         f"the dataset {', '.join(v.name for v in views[:3])}): the model was trained on another "
                         "dataset; give the dataset it was trained on")


def _fit_path_to_views(cams, views: list[DatasetView]):
    """An Inria ``cameras.json`` or COLMAP path names the dataset's views: use their intrinsics and
    size (the chosen image folder's, e.g. ``images_2``), so that each frame is its view (and gets
    a PSNR in ``enhance-path``). Else, when the file's size is an integer multiple of the views'
    one size, scale its intrinsics down to it. Other paths are rendered as given."""
    from dataclasses import replace

    if cams.source not in ("inria", "colmap"):
        return cams
    by_name = {v.name: v for v in views}
    sizes = {(v.width, v.height) for v in views}
    if cams.names and all(n in by_name for n in cams.names):
        matched = [by_name[n] for n in cams.names]
        size = {(v.width, v.height) for v in matched}
        if len(size) == 1:
            (width, height), = size
            return replace(cams, K=torch.stack([v.K.to(torch.float64) for v in matched]), width=width,
                           height=height)
    if len(sizes) == 1:
        (width, height), = sizes
        factor = cams.width // width
        if factor > 1 and (cams.width, cams.height) == (factor * width, factor * height):
            K = cams.K.clone()
            K[:, :2] /= factor
            return replace(cams, K=K, width=width, height=height)
    return cams


def fly_through(views: list[DatasetView], frames: int = FLY_FRAMES):
    """A smooth camera path (:func:`~roguenerf.trajectory.smooth_path`) through up to :data:`FLY_KEYS`
    dataset views evenly spread in name order (the capture order), about ``frames`` frames; the
    frames at the key views are those views exactly (pose, intrinsics, size: ``enhance-path``
    measures their PSNR), the others use their segment's first key's intrinsics."""
    from roguenerf.trajectory import CameraPath, natural_key, smooth_path

    if isinstance(frames, bool) or not isinstance(frames, int) or frames < 2:
        raise InputError(f"frames: expected an integer >= 2, got {frames!r}")
    ordered = sorted(views, key=lambda v: natural_key(v.name))
    same = [v for v in ordered if (v.width, v.height) == (ordered[0].width, ordered[0].height)]
    m = min(len(same), FLY_KEYS, frames)
    if m < 2:
        raise InputError("fly-through: needs at least 2 dataset views of one size; give a camera path (--path)")
    keys = [same[round(k * (len(same) - 1) / (m - 1))] for k in range(m)]
    steps = max(1, round((frames - 1) / (m - 1)))
    poses = smooth_path(torch.stack([v.world_from_cam.to(torch.float64) for v in keys]), steps)
    K = torch.stack([keys[min(t // steps, m - 1)].K.to(torch.float64) for t in range(len(poses))])
    return CameraPath(world_from_cam=poses, K=K, width=keys[0].width, height=keys[0].height, fps=24.0,
                      source="fly-through", labels=[f"fly-through frame {t}" for t in range(len(poses))])


@dataclass(eq=False)
class _RenderingScene(Scene):
    """The dataset views as a :class:`Scene` whose depth is rendered (and written) on demand: what
    :func:`~roguenerf.trajectory.check_camera_path` reads before everything is rendered."""

    depth_of: Callable[[int], Tensor] | None = None

    def depth(self, i: int | str) -> Tensor:
        return self.depth_of(self._resolve(i))


def _path_problem(scene, cams, depth_of, depth_threshold: float) -> str | None:
    """:func:`~roguenerf.trajectory.check_camera_path`, plus: a path none of whose checked cameras sees
    a splat (no pixel reaches the depth threshold) does not fit either."""
    from roguenerf.trajectory import check_camera_path

    if not scene.indices("train"):
        return None
    check = check_camera_path(scene, cams, depth_of)
    if check.problem is not None:
        return check.problem
    if all(check.seen[t] is None for t in check.checked):
        return (f"the camera path does not fit the scene: none of the {len(check.checked)} checked cameras sees a "
                f"splat (no pixel reaches opacity {depth_threshold}); it looks away from the scene or lies in "
                "another world. Likely causes: OpenGL vs OpenCV axes (camera paths and transforms-style lists are "
                "read as OpenGL, as nerfstudio and Blender write them: convert OpenCV poses, columns 1 and 2 "
                "negated); a nerfstudio camera_path.json is in the model's world: it needs --dataparser-transforms; "
                "another coordinate space or unit than the dataset's poses")
    return None


def _ply_stamp(ply: Path) -> dict:
    st = Path(ply).stat()
    return {"ply_bytes": st.st_size, "ply_mtime_ns": st.st_mtime_ns}


def import_3dgs(dataset: str | Path, ply: str | Path | None, output: str | Path, *, backend: str = "auto",
                hold: int = 8, images: str = "images", dataparser_transforms: str | Path | None = None,
                depth_threshold: float = DEFAULT_DEPTH_THRESHOLD, camera_path: str | Path | None = None,
                model: str | Path | None = None, fly_through_frames: int | None = None, force: bool = False,
                messages: Callable[[str], None] | None = None,
                progress: Callable[[int, int], None] | None = None):
    """Render every view of ``dataset`` from the 3DGS ``ply`` and write the scene folder ``output``.

    Before rendering, :func:`check_world` checks that the splats lie in the dataset's world and,
    with a camera path, :func:`~roguenerf.trajectory.check_camera_path` that the path sees them (from a
    few rendered frames, kept): an :class:`InputError` naming the causes and fixes, or with
    ``force`` a warning. When ``output`` is an earlier import of the same dataset, ``.ply`` and
    options (its ``transforms.json`` ``source``) and a path is asked for, only the path is rendered.

    Args:
        dataset: COLMAP dataset or a folder :func:`load_scene` reads (with photos).
        ply: Inria ``point_cloud.ply``; None: the latest one of ``model``.
        backend: ``"auto"`` (gsplat with CUDA, else the CPU rasterizer), ``"cpu"`` or ``"gsplat"``.
        hold: COLMAP datasets: every ``hold``-th view is a test view (0: none).
        images: COLMAP datasets: the image folder (``images_2`` for a half-size training).
        dataparser_transforms: nerfstudio's file when the ``.ply`` is in its model's world.
        depth_threshold: depth is known where the opacity reaches this share.
        camera_path: also render this camera path into ``output/path`` (see :func:`render_camera_path`);
            an Inria ``cameras.json`` or COLMAP path of the dataset's views gets their intrinsics and
            size (:func:`_fit_path_to_views`).
        model: Inria's model folder: the ``.ply`` (latest iteration) when ``ply`` is None; its
            ``cameras.json`` must name the dataset's views.
        fly_through_frames: without ``camera_path``, render a :func:`fly_through` of this many frames.
        force: go on when a check fails (its message goes to ``messages`` as a warning).
        messages: ``callback(line)`` for what the user should hear (default: logged).
        progress: ``callback(done, total)`` per view (dataset views, then path frames).
    Returns:
        The written scene, loaded.
    """
    import logging

    from roguenerf.data.exports import DATAPARSER_FILE, DataparserTransform
    from roguenerf.data.readers import load_scene
    from roguenerf.geometry.cameras import opencv_to_opengl
    from roguenerf.imageio import atomic_write, encode_npy, encode_png, read_image_size
    from roguenerf.splats.ply import read_ply

    say = messages or logging.getLogger("roguenerf.splats").warning
    backend = pick_backend(backend)
    if ply is None:
        if model is None:
            raise InputError("give the splats: --ply point_cloud.ply or --model MODEL (Inria's model folder)")
        ply = find_model_ply(model)
    check_output_folder(Path(output), _is_ours, "output", owned=_our_files)
    views, fmt = read_dataset_views(dataset, hold=hold, images=images)
    if model is not None:
        _check_model_cameras(Path(model), views)
    parser = DataparserTransform.read(dataparser_transforms) if dataparser_transforms is not None else None
    gaussians = read_ply(ply)
    world = check_world(gaussians, views, parser)
    if world.problem is not None:
        if not force:
            raise InputError(world.problem)
        say(f"warning: {world.problem}")
    output = Path(output)
    path_cams, path_label = None, None
    if camera_path is not None:
        from roguenerf.trajectory import read_camera_path

        path_cams = _fit_path_to_views(read_camera_path(camera_path, dataparser=parser), views)
        path_label = str(camera_path)
    elif fly_through_frames is not None:
        path_cams, path_label = fly_through(views, fly_through_frames), "fly-through"
    source = {"tool": TOOL, "dataset": str(dataset), "dataset_format": fmt, "ply": str(ply), **_ply_stamp(ply),
              "gaussians": len(gaussians), "sh_degree": gaussians.sh_degree, "backend": backend,
              "depth_threshold": depth_threshold, "hold": hold, "images": images,
              "dataparser_transforms": None if dataparser_transforms is None else str(dataparser_transforms)}

    def path_problem(scene, path_writer) -> None:
        problem = _path_problem(scene, path_cams, path_writer.depth, depth_threshold)
        if problem is not None:
            if not force:
                raise InputError(f"--path: {problem}. To render it anyway: --force")
            say(f"warning: --path: {problem}")

    if path_cams is not None and _same_import(output, source):
        # Only the path is new: the dataset views are there already.
        scene = load_scene(output)
        with atomic_folder(output / PATH_FOLDER, replaceable=_is_our_path, owned=_our_path_files,
                           what="path output") as tmp:
            writer = _PathWriter(gaussians, path_cams, path_label, tmp, backend, parser, depth_threshold)
            path_problem(scene, writer)
            writer.finish(progress)
        say(f"{output} holds this dataset and .ply already: rendered only the path ({len(path_cams)} frames)")
        return scene

    with atomic_folder(output, replaceable=_is_ours, owned=_our_files) as tmp:
        total = len(views) + (len(path_cams) if path_cams is not None else 0)
        frames: dict[int, dict] = {}

        def write_view(n: int) -> Tensor:
            view = views[n]
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
            frames[n] = {
                "file_path": photo_rel, "render_path": f"renders/{view.name}.png",
                "depth_path": f"depths/{view.name}.npy", "acc_path": f"acc/{view.name}.png", "split": view.split,
                **camera_fields(view.K, width, height),
                "transform_matrix": opencv_to_opengl(view.world_from_cam).tolist(),
            }
            return depth

        def view_depth(n: int) -> Tensor:
            if n in frames:
                return torch.from_numpy(np.load(tmp / frames[n]["depth_path"]))[None]
            return write_view(n)

        writer = None
        if path_cams is not None:
            # The path check renders a few path frames and the training views it compares them
            # with (kept: they are part of the output); a failure leaves nothing behind.
            writer = _PathWriter(gaussians, path_cams, path_label, tmp / PATH_FOLDER, backend, parser,
                                 depth_threshold)
            lazy = _RenderingScene(root=Path(dataset), frames=[
                Frame(v.name, v.world_from_cam, v.K, v.width, v.height, v.split, image_path=v.photo) for v in views],
                depth_of=view_depth)
            path_problem(lazy, writer)
        for n in range(len(views)):
            if n not in frames:
                write_view(n)
            if progress is not None:
                progress(n + 1, total)
        if parser is not None:
            atomic_write(tmp / DATAPARSER_FILE, json.dumps(parser.to_json(), indent=2).encode())
        if writer is not None:
            writer.finish(lambda k, _t: progress(len(views) + k, total) if progress else None)
        doc = {
            "camera_model": "OPENCV",
            **CONVENTIONS,
            "source": source,
            "frames": [frames[n] for n in range(len(views))],
        }
        atomic_write(tmp / "transforms.json", json.dumps(doc, indent=1).encode())
    return load_scene(output)


def _same_import(output: Path, source: dict) -> bool:
    """``output`` is an earlier import of the same dataset, ``.ply`` (size, time) and options."""
    try:
        doc = json.loads((output / "transforms.json").read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError):
        return False
    return isinstance(doc, dict) and doc.get("source") == source


class _PathWriter:
    """Renders a path's frames into ``folder`` (``rgb/``, ``depth/``, then the cameras as
    :data:`PATH_CAMERAS`); a frame rendered early (for the path check) is not rendered again."""

    def __init__(self, gaussians, cams, label: str, folder: Path, backend, parser, depth_threshold):
        self.gaussians, self.cams, self.label, self.folder = gaussians, cams, label, folder
        self.backend, self.parser, self.depth_threshold = backend, parser, depth_threshold
        self.digits = max(5, len(str(len(cams))))
        self.done: dict[int, Tensor] = {}

    def depth(self, t: int) -> Tensor:
        if t not in self.done:
            self.done[t] = self._render(t)
        return self.done[t]

    def _render(self, t: int) -> Tensor:
        from roguenerf.imageio import atomic_write, encode_npy, encode_png

        cams = self.cams
        rgb, depth, _ = render_view(self.gaussians, _model_camera(cams.world_from_cam[t], self.parser), cams.K[t],
                                    cams.height, cams.width, backend=self.backend,
                                    depth_threshold=self.depth_threshold)
        if self.parser is not None:
            depth = depth / self.parser.scale
        atomic_write(self.folder / "rgb" / f"{t:0{self.digits}d}.png", encode_png(rgb), make_parents=True)
        atomic_write(self.folder / "depth" / f"{t:0{self.digits}d}.npy", encode_npy(depth[0].numpy()),
                     make_parents=True)
        return depth

    def finish(self, progress) -> None:
        from roguenerf.geometry.cameras import opencv_to_opengl
        from roguenerf.imageio import atomic_write

        cams = self.cams
        for t in range(len(cams)):
            if t not in self.done:
                self._render(t)
            if progress is not None:
                progress(t + 1, len(cams))
        self.done.clear()
        # The cameras as rendered (the dataset's world, whatever file they came from): what
        # ``enhance-path --cameras`` reads beside the frames.
        doc = {"fps": cams.fps, "source": {"tool": TOOL, "camera_path": self.label, "format": cams.source},
               "frames": [{"transform_matrix": opencv_to_opengl(cams.world_from_cam[t]).tolist(),
                           **camera_fields(cams.K[t], cams.width, cams.height)} for t in range(len(cams))]}
        atomic_write(self.folder / PATH_CAMERAS, json.dumps(doc, indent=1).encode())


def render_camera_path(ply: str | Path, camera_path: str | Path, output: str | Path, *, backend: str = "auto",
                       dataparser_transforms: str | Path | None = None,
                       depth_threshold: float = DEFAULT_DEPTH_THRESHOLD,
                       progress: Callable[[int, int], None] | None = None) -> Path:
    """Render a camera path (nerfstudio ``camera_path.json`` or a transforms-style list, poses in
    the dataset's world) from ``ply`` into ``output/rgb/NNNNN.png`` + ``output/depth/NNNNN.npy``,
    with the camera file copied beside them: what ``enhance-path --frames`` reads."""
    from roguenerf.data.exports import DataparserTransform
    from roguenerf.splats.ply import read_ply
    from roguenerf.trajectory import read_camera_path

    backend = pick_backend(backend)
    check_output_folder(Path(output), _is_our_path, "path output", owned=_our_path_files)
    parser = DataparserTransform.read(dataparser_transforms) if dataparser_transforms is not None else None
    cams = read_camera_path(camera_path, dataparser=parser)
    gaussians = read_ply(ply)
    output = Path(output)
    with atomic_folder(output, replaceable=_is_our_path, what="path output", owned=_our_path_files) as tmp:
        _PathWriter(gaussians, cams, str(camera_path), tmp, backend, parser, depth_threshold).finish(progress)
    return output
