"""The camera-path task: load the job's upload, call the library's ``enhance_path``, record.

Files live in the job's folder: ``input/`` (the validated upload), ``output/`` (frames, MP4s,
flicker.json, frames.zip). ``enhance_path`` keeps every finished frame, so a requeued job (a
drained or lost worker) resumes after the last one; a cancelled job's folder is removed.
"""

from __future__ import annotations

import logging
import os
import zipfile
from pathlib import Path

from jobs.data import base_checkpoint
from jobs.lifecycle import JobRun, JobStopped, Task

log = logging.getLogger("roguenerf.worker")


def zip_frames(frame_dir: Path, destination: Path) -> None:
    """``frames.zip`` of the enhanced PNGs (stored: PNGs are compressed already), atomically."""
    tmp = destination.with_name(f".{destination.name}.partial")
    with zipfile.ZipFile(tmp, "w", zipfile.ZIP_STORED) as archive:
        for path in sorted(frame_dir.glob("*.png")):
            archive.write(path, f"frames/{path.name}")
    os.replace(tmp, destination)


def run_path_job(run: JobRun) -> str:
    """Enhance the uploaded camera path with the scene's active checkpoint; the files stay in the
    job's folder (``GET /jobs/{id}/result``)."""
    from roguenerf import (
        DATAPARSER_FILE,
        CameraMismatchError,
        DataparserTransform,
        EnhanceOptions,
        PathCancelled,
        PathClock,
        SceneEnhancer,
        TemporalConfig,
        enhance_path,
        find_camera_file,
        load_checkpoint,
        load_scene,
        read_camera_path,
    )

    store, layout, scene_id, request, job_dir = run.store, run.layout, run.scene_id, run.request, run.job_dir
    run.root, run.root_name = job_dir / "input", "the path archive"
    scene_row = store.get_scene(scene_id)
    if scene_row is None:
        return run.fail("scene_deleted", f"scene {scene_id} no longer exists")

    scene = load_scene(layout.scene_files(scene_id), confine=True)
    checkpoint = base_checkpoint(run.settings, layout, scene_id, scene_row["active_version"])
    if checkpoint is None:
        return run.fail("no_checkpoint", "the scene has no enhancer checkpoint")
    model, _ = load_checkpoint(checkpoint)
    parser_file = layout.scene_files(scene_id) / DATAPARSER_FILE
    parser = DataparserTransform.read(parser_file) if parser_file.is_file() else None
    inputs = job_dir / "input"
    camera_path = read_camera_path(find_camera_file(inputs), dataparser=parser)
    # the shipped defaults, but for the request's carried frames
    chosen = {"carry_agreement": float(request["carry_agreement"])} if "carry_agreement" in request else {}
    # older jobs: the library's defaults
    for name in ("carry_between", "between_agreement", "carry_share", "carry_nearer", "schedule", "both_ways"):
        if name in request:
            chosen[name] = request[name]
    options = EnhanceOptions(temporal=TemporalConfig(model_every=int(request.get("model_every", 1)), **chosen))
    enhancer = SceneEnhancer(scene, model, options=options)
    stat = Path(checkpoint).stat()
    clock = PathClock(options.temporal)  # each pass timed on its own (the second's steps are cheaper)

    def progress(done: int, total: int) -> None:
        run.record(store.record_frames, done=done, total=total, eta_s=clock(done, total))

    try:
        result = enhance_path(
            scene, enhancer, camera_path, inputs, job_dir / "output",
            depth_type=request.get("depth_type", "z"), depth_scale=float(request.get("depth_scale", 1.0)),
            background=request.get("background", "zero"), quality=int(request.get("quality", 20)),
            checkpoint_id=f"{checkpoint}:{stat.st_size}:{stat.st_mtime_ns}", progress=progress,
            should_stop=run.should_stop, force=bool(request.get("force", False)),
            force_hint="force=true (a form field of the path upload)")
    except PathCancelled as exc:
        raise JobStopped(f"after {exc.frame} frames") from exc
    except CameraMismatchError as exc:  # the API checked it at upload; the scene changed since
        return run.fail("invalid_input", f"{exc.problem}. To enhance it anyway: upload the path again with force=true")
    zip_frames(job_dir / "output" / "frames", job_dir / "output" / "frames.zip")

    summary = {
        "kind": "path", "frames": result.frames, "seconds": result.seconds, "cached_views": result.cached_views,
        "flicker": {k: v for k, v in result.flicker["flicker"].items()},
        "psnr": result.flicker["psnr"],
        "carried": sum(bool(f.get("carried")) for f in result.flicker["per_frame"]),
        "files": {"video": "GET /jobs/{id}/result", "side_by_side": "?what=side_by_side",
                  "frames": "?what=frames", "flicker": "?what=flicker"},
    }
    outcome = run.succeed(summary, keep_files=True)  # the job's folder holds the result
    if outcome == "succeeded":
        log.info("path job %s succeeded: %d frames, flicker %s", run.id, result.frames, summary["flicker"])
    return outcome


PATH = Task(run_path_job, label="path job", work="path")
