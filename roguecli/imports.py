"""Import commands: other tools' renders (``import-nerfstudio``, ``import-gsplat``) and trained
3DGS splats (``import-3dgs``) into a scene folder."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from roguecli.common import DepthScaleOpt, handle_errors, progress_bar, warn_unusable
from roguenerf.errors import InputError

DepthTypeOpt = Annotated[str | None, typer.Option("--depth-type", help=(
    "ray: distance along the ray (nerfacto, gsplat ED); z: along the optical axis (splatfacto, gsplat RGB+ED). "
    "Default: ray for nerfstudio, z for gsplat."))]
BackgroundOpt = Annotated[str | None, typer.Option("--background", help=(
    "What no-surface pixels hold: zero, or max (the map's maximum; gsplat's default). Made unknown."))]
SkipMissingOpt = Annotated[bool, typer.Option("--skip-missing", help=(
    "Import the views that have both a render and a depth, skipping (with a warning) those missing one; "
    "without it a missing file is an error naming it."))]
ImportForceOpt = Annotated[bool, typer.Option("--force", help=(
    "Import with the --depth-type given even when the depths of neighbouring views disagree under it "
    "and agree under the other type (checked by reprojecting a few hundred pixels)."))]
HOLD_HELP = ("COLMAP dataset: every N-th view in name order is a test view, the split of the 3DGS and gsplat "
             "trainers' --eval (Inria's --eval, gsplat's default --test-every 8); 0: none, every view trains.")
DataparserOpt = Annotated[Path | None, typer.Option("--dataparser-transforms", help=(
    "The trained model's dataparser_transforms.json: kept in the scene for camera paths from nerfstudio's viewer."))]


def _import_command(tool: str, dataset: Path, renders: Path, output: Path, depth_type, depth_scale: float,
                    depth_units: str, dataparser_transforms, background, skip_missing: bool = False,
                    force: bool = False, hold_flag: str = "--hold", **split) -> None:
    from roguenerf.data.exports import import_renders

    with handle_errors():
        if split.get("test_every") is not None and split["test_every"] < 0:
            raise InputError(f"{hold_flag}: expected >= 0 (0: no test views), got {split['test_every']}")
        if split.get("split_file") is not None and not split["split_file"].is_file():
            raise InputError(f"--split-file: {split['split_file']} does not exist")
        if depth_type not in (None, "z", "ray"):
            raise InputError(f"--depth-type: expected z or ray, got {depth_type!r}")
        if background not in (None, "zero", "max"):
            raise InputError(f"--background: expected zero or max, got {background!r}")
        if not dataset.exists():
            raise InputError(f"dataset {dataset} does not exist")
        if dataparser_transforms is not None and not dataparser_transforms.is_file():
            raise InputError(f"--dataparser-transforms: {dataparser_transforms} does not exist")
        with progress_bar(f"importing {tool} renders", "view") as progress:
            scene = import_renders(dataset, renders, output, tool=tool, depth_type=depth_type,
                                   depth_scale=depth_scale, depth_units=depth_units,
                                   dataparser_transforms=dataparser_transforms, background=background,
                                   progress=progress, skip_missing=skip_missing, check_depth=not force,
                                   hints={"skip_missing": "--skip-missing", "check_depth": "--force"}, **split)
        skipped = scene.meta.get("skipped_views") or []
        if skipped:
            typer.echo(f"warning: skipped {len(skipped)} views without a render or depth: {', '.join(skipped)}",
                       err=True)
        typer.echo(f"wrote {scene!r}", err=True)
        warn_unusable(scene)
        typer.echo(str(output))


def import_nerfstudio(
    dataset: Annotated[Path, typer.Argument(help="nerfstudio dataset: folder with transforms.json and the photos.")],
    renders: Annotated[Path, typer.Option(
        "--renders", help="ns-render dataset output (<split>/rgb, <split>/raw-depth).")],
    output: Annotated[Path, typer.Option("--output", help="Scene folder to write.")],
    depth_type: DepthTypeOpt = None,
    depth_scale: DepthScaleOpt = 1.0,
    depth_units: Annotated[str, typer.Option("--depth-units", help=(
        "dataset: depth in the dataset's pose units (ns-render divides by the dataparser scale); "
        "model: in the model's world (divided by the scale here)."))] = "dataset",
    dataparser_transforms: DataparserOpt = None,
    background: BackgroundOpt = None,
    skip_missing: SkipMissingOpt = False,
    force: ImportForceOpt = False,
) -> None:
    """Turn a nerfstudio dataset plus `ns-render dataset` output into a scene folder (z-depth, pose units)."""
    _import_command("nerfstudio", dataset, renders, output, depth_type, depth_scale, depth_units,
                    dataparser_transforms, background, skip_missing, force)


def import_gsplat(
    dataset: Annotated[Path, typer.Argument(help=(
        "Dataset with the photos and their poses: COLMAP (images/ + sparse/0/, .bin or .txt) or "
        "transforms.json (nerfstudio style)."))],
    renders: Annotated[Path, typer.Option("--renders", help=(
        "Folder with rgb/ and depth/ (.npy, .npy.gz, .npz, 16-bit PNG, float TIFF), files named by view; or an "
        "Inria model folder whose <split>/ours_<iter>/ holds renders/ and a depth/ folder (numbered)."))],
    output: Annotated[Path, typer.Option("--output", help="Scene folder to write.")],
    depth_type: DepthTypeOpt = None,
    depth_scale: DepthScaleOpt = 1.0,
    background: BackgroundOpt = None,
    images: Annotated[str, typer.Option("--images", help=(
        "COLMAP dataset: the image folder (images_2 for gsplat's --data-factor 2)."))] = "images",
    hold: Annotated[int | None, typer.Option("--hold", help=(
        HOLD_HELP + " Default 8; Inria's numbered renders: their own split (test renders: 8, none: 0). A "
        "transforms.json dataset keeps its own split unless --hold is given."))] = None,
    eval_split: Annotated[bool, typer.Option("--eval", help=(
        "Same as --hold 8, now the default (kept for old scripts)."))] = False,
    test_every: Annotated[int | None, typer.Option("--test-every", help=(
        "Same as --hold N (kept for old scripts)."))] = None,
    split_file: Annotated[Path | None, typer.Option("--split-file", help=(
        'Test views by name: JSON {"train": [...], "test": [...]} or one name per line '
        "(Inria's sparse/0/test.txt). Overrides --hold."))] = None,
    skip_missing: SkipMissingOpt = False,
    force: ImportForceOpt = False,
) -> None:
    """Turn gsplat renders + expected depth (and the dataset's poses) into a scene folder."""
    with handle_errors():
        if hold is not None and test_every is not None and hold != test_every:
            raise InputError(f"--hold {hold} and --test-every {test_every} disagree: give one (--hold)")
    flag = "--hold" if hold is not None else "--test-every"
    test_every = hold if hold is not None else test_every
    if test_every is None and eval_split:
        test_every = 8
    _import_command("gsplat", dataset, renders, output, depth_type, depth_scale, "dataset", None, background,
                    skip_missing, force, images=images, test_every=test_every, split_file=split_file,
                    hold_flag=flag)


def import_3dgs_command(
    dataset: Annotated[Path, typer.Argument(
        help="The dataset the splats were trained on: COLMAP (images/ + sparse/0) or transforms.json.")],
    ply: Annotated[Path | None, typer.Option("--ply", help=(
        "Inria 3DGS point_cloud.ply (point_cloud/iteration_30000/); default: --model's latest."))] = None,
    output: Annotated[Path, typer.Option(
        "--output", help="Scene folder to write (renders, z-depth, opacity, photos).")] = ...,
    path: Annotated[Path | None, typer.Option("--path", help=(
        "Also render this camera path (any enhance-path --cameras format: camera_path.json, transforms-style, "
        "cameras.json (read in image-name order, at the dataset views' size), COLMAP images.txt) into "
        "OUTPUT/path for enhance-path. OUTPUT already holding this import: only the path is rendered."))] = None,
    backend: Annotated[str, typer.Option(
        "--backend", help="auto (gsplat with CUDA, else CPU), cpu or gsplat.")] = "auto",
    hold: Annotated[int, typer.Option("--hold", help=HOLD_HELP + " A transforms.json dataset keeps its own "
                                      "split.")] = 8,
    images: Annotated[str, typer.Option(
        "--images", help="COLMAP: image folder in the dataset (images_2 for half size).")] = "images",
    dataparser_transforms: Annotated[Path | None, typer.Option("--dataparser-transforms", help=(
        "splatfacto exports: nerfstudio's dataparser_transforms.json (the .ply is in its model's world)."))] = None,
    depth_threshold: Annotated[float, typer.Option(
        "--depth-threshold", help="Depth is known where the splats' opacity reaches this.")] = 0.5,
    model: Annotated[Path | None, typer.Option("--model", help=(
        "Inria's model folder (cameras.json, point_cloud/iteration_*/point_cloud.ply): the latest iteration's "
        ".ply, and without --path a smooth fly-through through the dataset's views into OUTPUT/path."))] = None,
    frames: Annotated[int, typer.Option(
        "--frames", help="--model without --path: frames of the fly-through (24 per second).")] = 120,
    force: Annotated[bool, typer.Option("--force", help=(
        "Render even when the splats do not lie in the dataset's views (another world: gsplat's normalised "
        "one, a splatfacto export without --dataparser-transforms) or the path sees none of them; the "
        "problem is printed as a warning."))] = False,
) -> None:
    """Render a trained 3DGS scene's .ply at every dataset view (RGB, z-depth, opacity) into a scene folder."""
    from roguenerf.splats.importer import PATH_CAMERAS, PATH_FOLDER, import_3dgs

    with handle_errors():
        if ply is None and model is None:
            raise InputError("give the splats: --ply point_cloud.ply or --model MODEL (Inria's model folder)")
        if ply is not None and not ply.is_file():
            raise InputError(f"--ply: {ply} does not exist")
        if path is not None and not path.is_file():
            raise InputError(f"--path: {path} does not exist")
        if not 0 <= depth_threshold <= 1:
            raise InputError(f"--depth-threshold: expected 0..1, got {depth_threshold}")
        if frames < 2:
            raise InputError(f"--frames: expected at least 2, got {frames}")
        fly = frames if model is not None and path is None else None
        with progress_bar("rendering splats", "view") as progress:
            scene = import_3dgs(dataset, ply, output, backend=backend, hold=hold, images=images,
                                dataparser_transforms=dataparser_transforms, depth_threshold=depth_threshold,
                                camera_path=path, model=model, fly_through_frames=fly, force=force,
                                messages=lambda line: typer.echo(line, err=True), progress=progress)
        typer.echo(f"wrote {scene!r}", err=True)
        if path is not None or fly is not None:
            frames_dir = output / PATH_FOLDER
            cams = frames_dir / PATH_CAMERAS
            video = output.with_name(output.name + "_video")
            typer.echo(f"next: roguenerf enhance-path {output} --frames {frames_dir} --cameras {cams} "
                       f"--output {video}", err=True)
        typer.echo(str(output))
