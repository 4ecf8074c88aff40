"""The camera-path task: load the job's upload, call the library's ``enhance_path``, record.

Files live in the job's folder: ``input/`` (the validated upload), ``output/`` (frames, MP4s,
flicker.json, frames.zip). ``enhance_path`` keeps every finished frame, so a requeued job (a
drained or lost worker) resumes after the last one; a cancelled job's folder is removed.
"""

from __future__ import annotations

import logging
import os
import time
import traceback
import zipfile
from pathlib import Path

from workers.layout import public_message
from workers.runtime import base_checkpoint, cancel_poller, jsonable

log = logging.getLogger("roguenerf.worker")


def zip_frames(frame_dir: Path, destination: Path) -> None:
    """``frames.zip`` of the enhanced PNGs (stored: PNGs are compressed already), atomically."""
    tmp = destination.with_name(f".{destination.name}.partial")
    with zipfile.ZipFile(tmp, "w", zipfile.ZIP_STORED) as archive:
        for path in sorted(frame_dir.glob("*.png")):
            archive.write(path, f"frames/{path.name}")
    os.replace(tmp, destination)


def run_path_job(ctx, job: dict, lease: str, beat) -> str:
    from roguenerf import (
        CameraMismatchError,
        EnhanceOptions,
        PathCancelled,
        RoGUENeRFError,
        SceneEnhancer,
        load_checkpoint,
        load_scene,
    )
    from roguenerf.data.exports import DATAPARSER_FILE, DataparserTransform
    from roguenerf.trajectory import enhance_path, find_camera_file, read_camera_path

    settings, store, layout = ctx.settings, ctx.store, ctx.layout
    job_id, scene_id, request = job["id"], job["scene_id"], job["request"]
    job_dir = layout.job_dir(job_id)

    def fail(code: str, message: str) -> str:
        log.warning("path job %s failed: %s: %s", job_id, code, message)
        public = public_message(message, root=job_dir / "input", data_dir=layout.root, root_name="the path archive")
        store.finish(job_id, lease, "failed", error_code=code, error_message=public)
        return "failed"

    scene_row = store.get_scene(scene_id)
    if scene_row is None:
        return fail("scene_deleted", f"scene {scene_id} no longer exists")
    should_stop = cancel_poller(ctx, beat, store, job_id, lease)

    started = time.monotonic()
    first_done: list = []

    def progress(done: int, total: int) -> None:
        first_done.append(done) if not first_done else None
        rate = (done - first_done[0] + 1) / max(time.monotonic() - started, 1e-6)
        eta = (total - done) / rate if rate > 0 else None
        try:
            if not store.record_frames(job_id, lease, done=done, total=total, eta_s=eta):
                beat.lost.set()
        except Exception:
            log.exception("path job %s: could not record progress", job_id)

    try:
        scene = load_scene(layout.scene_files(scene_id), confine=True)
        checkpoint = base_checkpoint(settings, layout, scene_id, scene_row["active_version"])
        if checkpoint is None:
            return fail("no_checkpoint", "the scene has no enhancer checkpoint")
        model, _ = load_checkpoint(checkpoint)
        parser_file = layout.scene_files(scene_id) / DATAPARSER_FILE
        parser = DataparserTransform.read(parser_file) if parser_file.is_file() else None
        inputs = job_dir / "input"
        camera_path = read_camera_path(find_camera_file(inputs), dataparser=parser)
        enhancer = SceneEnhancer(scene, model, options=EnhanceOptions())  # the shipped defaults
        stat = Path(checkpoint).stat()
        result = enhance_path(
            scene, enhancer, camera_path, inputs, job_dir / "output",
            depth_type=request.get("depth_type", "z"), depth_scale=float(request.get("depth_scale", 1.0)),
            background=request.get("background", "zero"), quality=int(request.get("quality", 20)),
            checkpoint_id=f"{checkpoint}:{stat.st_size}:{stat.st_mtime_ns}", progress=progress,
            should_stop=should_stop, force=bool(request.get("force", False)),
            force_hint="force=true (a form field of the path upload)")
        zip_frames(job_dir / "output" / "frames", job_dir / "output" / "frames.zip")
    except PathCancelled as exc:
        if beat.lost.is_set():
            log.warning("path job %s: lost its lease; stopped after %s frames", job_id, exc.frame)
            return "lost"
        current = store.get_job(job_id)
        if current is not None and current["cancel_requested"]:
            if store.finish(job_id, lease, "cancelled", error_code="cancelled",
                            error_message=f"cancelled after {exc.frame} frames"):
                layout.remove_tree(job_dir)
            return "cancelled"
        if ctx.draining.is_set():
            if store.release(job_id, lease):
                ctx.enqueue(job_id)
            return "requeued"
        return fail("internal_error", f"path stopped without a reason after {exc.frame} frames")
    except CameraMismatchError as exc:  # the API checked it at upload; the scene changed since
        return fail("invalid_input", f"{exc.problem}. To enhance it anyway: upload the path again with force=true")
    except RoGUENeRFError as exc:
        return fail("invalid_input", str(exc))
    except Exception as exc:
        log.error("path job %s crashed:\n%s", job_id, traceback.format_exc())
        return fail("internal_error", f"{type(exc).__name__}: {exc}")

    summary = {
        "kind": "path", "frames": result.frames, "seconds": result.seconds, "cached_views": result.cached_views,
        "flicker": {k: v for k, v in result.flicker["flicker"].items()},
        "psnr": result.flicker["psnr"],
        "files": {"video": "GET /jobs/{id}/result", "side_by_side": "?what=side_by_side",
                  "frames": "?what=frames", "flicker": "?what=flicker"},
    }
    if not store.finish(job_id, lease, "succeeded", result=jsonable(summary)):
        log.warning("path job %s finished after losing its lease", job_id)
        return "lost"
    log.info("path job %s succeeded: %d frames, flicker %s", job_id, result.frames, summary["flicker"])
    return "succeeded"
