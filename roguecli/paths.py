"""Camera-path command: ``enhance-path`` (every frame of a path, MP4s, flicker)."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Annotated

import typer

from roguecli.common import (
    CheckpointOpt,
    DepthScaleOpt,
    PathEnhanceFlags,
    checkpoint_file,
    handle_errors,
    open_scene,
    progress_bar,
    takes_flags,
)
from roguenerf.errors import InputError


@takes_flags
def enhance_path_command(
    scene_dir: Annotated[Path, typer.Argument(help="Scene folder (the training photos, poses, renders, depths).")],
    frames: Annotated[Path, typer.Option(
        "--frames", help="Folder of the path's renders and depths (rgb/ + depth/, or NAME.png + NAME.npy).")],
    cameras: Annotated[Path, typer.Option("--cameras", help=(
        "nerfstudio camera_path.json, a transforms-style list of cameras, Inria 3DGS cameras.json, or COLMAP "
        "images.txt / images.bin (cameras file beside it)."))],
    output: Annotated[Path, typer.Option(
        "--output", help="Output folder: frames/, enhanced.mp4, side_by_side.mp4, flicker.json.")],
    checkpoint: CheckpointOpt = None,
    *,
    flags: PathEnhanceFlags,
    quality: Annotated[int, typer.Option("--quality", help="x264 CRF, 0 (lossless) .. 51; 18-23 look good.")] = 20,
    fps: Annotated[float | None, typer.Option(
        "--fps", help="Frame rate (default: the camera path's, else 24).")] = None,
    depth_type: Annotated[str, typer.Option("--depth-type", help="z or ray (distance along the ray, nerfacto).")] = "z",
    depth_scale: DepthScaleOpt = 1.0,
    background: Annotated[str, typer.Option(
        "--background", help="No-surface pixels hold zero, or max (gsplat).")] = "zero",
    dataparser_transforms: Annotated[Path | None, typer.Option("--dataparser-transforms", help=(
        "Maps a nerfstudio camera path (model world) to the scene's poses; default: the scene folder's "
        "dataparser_transforms.json when there is one."))] = None,
    no_video: Annotated[bool, typer.Option("--no-video", help="Write the frames and flicker.json only.")] = False,
    force: Annotated[bool, typer.Option("--force", help=(
        "Enhance the path even when its cameras do not fit the scene (far from its cameras, or seeing none "
        "of its training photos: another coordinate space, missing dataparser transforms, OpenGL vs OpenCV); "
        "the problem is printed as a warning."))] = False,
) -> None:
    """Enhance every frame of a camera path; write the frames, an MP4, a side-by-side MP4 and the flicker.

    Resumable: run the same command again after an interruption.
    """
    from roguenerf.data.exports import DATAPARSER_FILE, DataparserTransform
    from roguenerf.inference import SceneEnhancer
    from roguenerf.trajectory import FLICKER_FILE, PathClock, check_path_output, enhance_path, read_camera_path

    with handle_errors():
        if depth_type not in ("z", "ray"):
            raise InputError(f"--depth-type: expected z or ray, got {depth_type!r}")
        if background not in ("zero", "max"):
            raise InputError(f"--background: expected zero or max, got {background!r}")
        if not 0 <= quality <= 51:
            raise InputError(f"--quality: expected 0..51 (x264 CRF), got {quality}")
        if fps is not None and not (math.isfinite(fps) and 0 < fps <= 240):
            raise InputError(f"--fps: expected a number in (0, 240], got {fps}")
        if not no_video:
            from roguenerf.video import require_av

            require_av()
        # The output folder and the cameras (every pose checked) first: before the scene and model load.
        check_path_output(output)
        camera_path = read_camera_path(cameras)
        if camera_path.source == "nerfstudio":
            parser_file = dataparser_transforms or (scene_dir / DATAPARSER_FILE)
            if parser_file.is_file():
                camera_path = read_camera_path(cameras, dataparser=DataparserTransform.read(parser_file))
            elif dataparser_transforms is not None:
                raise InputError(f"--dataparser-transforms: {dataparser_transforms} does not exist")
            else:
                typer.echo("note: nerfstudio camera path and no dataparser_transforms.json: its poses are "
                           "taken as the scene's own", err=True)
        scene = open_scene(scene_dir)
        ckpt = checkpoint_file(checkpoint)
        from roguenerf.checkpoint import load_checkpoint

        model, _meta = load_checkpoint(ckpt)
        enhancer = SceneEnhancer(scene, model, options=flags.options())
        stat = ckpt.stat()
        temporal = enhancer.options.temporal
        passes = " in two passes (blended both ways)" if temporal is not None and temporal.both_ways else ""
        clock = PathClock(temporal)  # each pass timed on its own: the second pass's steps are cheaper
        with progress_bar(f"enhancing {len(camera_path)} frames{passes}", "step", clock=clock) as progress:
            result = enhance_path(scene, enhancer, camera_path, frames, output, depth_type=depth_type,
                                  depth_scale=depth_scale, background=background, video=not no_video,
                                  quality=quality, fps=fps,
                                  checkpoint_id=f"{ckpt.resolve()}:{stat.st_size}:{stat.st_mtime_ns}"
                                  + ("" if flags.align else ":no-align") + ("" if flags.colour else ":no-colour")
                                  + ("" if flags.temporal else ":no-temporal"),
                                  progress=progress, force=force, force_hint="--force")
        for warning in result.warnings:
            typer.echo(f"warning: {warning}", err=True)
        f, p = result.flicker["flicker"], result.flicker["psnr"]
        resumed = result.frames - result.enhanced_now
        typer.echo(f"enhanced {result.enhanced_now} frames in {result.seconds:.1f} s"
                   + (f" ({result.frames_per_second:.2f} frames/s)" if result.frames_per_second else "")
                   + (f" ({resumed} already done)" if resumed else "")
                   + f"; neighbour features cached for {result.cached_views} training photos", err=True)
        if f["render"] is not None:
            typer.echo(f"flicker (mean |frame t reprojected into t+1 - frame t+1| on valid pixels): render "
                       f"{f['render']:.4f}, enhanced {f['enhanced']:.4f} (x{f['ratio']:.3f})"
                       + (f", photos {f['photo']:.4f}" if f["photo"] is not None else ""), err=True)
        if f.get("ratio_sharpened") is not None:
            typer.echo(f"  against the render sharpened alike to the enhanced frames' detail "
                       f"(x{f['detail_ratio']:.2f}; sharper frames read as more flicker): "
                       f"x{f['ratio_sharpened']:.3f}", err=True)
        if f.get("neighbour_changes") and f.get("ratio_changed") is not None and f.get("ratio_steady") is not None:
            typer.echo(f"  the neighbour set changed across {f['neighbour_changes']} of {f['pairs']} frame pairs "
                       f"(flicker.json names each frame's): x{f['ratio_changed']:.3f} there, "
                       f"x{f['ratio_steady']:.3f} elsewhere", err=True)
        if p["frames_with_photos"]:
            typer.echo(f"{p['frames_with_photos']} frames have photos: PSNR render {p['render']:.2f} dB, enhanced "
                       f"{p['enhanced']:.2f} dB, mean gain {p['mean_gain_db']:+.2f} dB", err=True)
        typer.echo(f"wrote {output / FLICKER_FILE}", err=True)
        typer.echo(str(result.video or output))
