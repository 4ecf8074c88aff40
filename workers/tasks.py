"""The fine-tuning task: load the job, call the library's ``finetune``, record, promote.

The task only orchestrates. Training, checkpointing and resuming are the library's
(``finetune(scene, output_dir, resume=True)`` in a per-job output dir); this module turns
its callbacks into heartbeats, progress rows and cancellation, and makes a finished
checkpoint the scene's active version.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import traceback
from pathlib import Path

from workers.layout import copy_atomic, public_message
from workers.runtime import Heartbeat, WorkerContext, base_checkpoint, cancel_poller, jsonable

log = logging.getLogger("roguenerf.worker")


def train_options(train_config_cls, settings, request: dict) -> dict:
    """TrainConfig keyword arguments for a job: its budget plus the worker's settings."""
    wanted = {
        "steps": request.get("steps"),
        "minutes": request.get("minutes"),
        "crop": settings.finetune_crop,
        "batch": settings.finetune_batch,
        "checkpoint_every_s": settings.checkpoint_every_s,
        "variant": settings.finetune_variant,
        "lr": settings.finetune_lr,
        "evaluate": settings.finetune_evaluate,
        "progress_bar": False,
    }
    # evaluate / progress_bar are library extras beyond the written contract; pass them only
    # while TrainConfig has them.
    known = {f.name for f in dataclasses.fields(train_config_cls)}
    return {k: v for k, v in wanted.items() if k in known}


def run_finetune_job(ctx: WorkerContext, job: dict, lease: str, beat: Heartbeat) -> str:
    """Run a claimed fine-tuning job to its end; returns what happened."""
    from roguenerf import (
        RoGUENeRFError,
        TrainConfig,
        TrainingCancelled,
        TrainingDivergedError,
        finetune,
        load_scene,
    )

    settings, store, layout = ctx.settings, ctx.store, ctx.layout
    job_id, scene_id = job["id"], job["scene_id"]

    def fail(code: str, message: str) -> str:
        log.warning("job %s failed: %s: %s", job_id, code, message)
        # Clients read the message (GET /jobs): paths relative to the scene, none of the server's.
        public = public_message(message, root=layout.scene_files(scene_id), data_dir=layout.root)
        store.finish(job_id, lease, "failed", error_code=code, error_message=public)
        return "failed"

    scene_row = store.get_scene(scene_id)
    if scene_row is None:
        return fail("scene_deleted", f"scene {scene_id} no longer exists")

    should_stop = cancel_poller(ctx, beat, store, job_id, lease)

    def progress(p) -> None:
        try:
            if getattr(p, "phase", "training") == "evaluating":
                owned = store.record_phase(job_id, lease, "evaluating")
            else:
                owned = store.record_progress(
                    job_id, lease, step=int(p.step), total_steps=p.total_steps,
                    fraction=float(p.fraction), eta_s=p.eta_s, loss=float(p.loss),
                )
        except Exception:
            log.exception("job %s: could not record progress", job_id)
            return
        if not owned:
            beat.lost.set()

    request = job["request"]
    try:
        scene = load_scene(layout.scene_files(scene_id), confine=True)
        checkpoint = base_checkpoint(settings, layout, scene_id, scene_row["active_version"])
        config = TrainConfig(**train_options(TrainConfig, settings, request))
        output_dir = layout.job_dir(job_id)
        output_dir.mkdir(parents=True, exist_ok=True)
        result = finetune(scene, output_dir, checkpoint=checkpoint, config=config,
                          progress=progress, should_stop=should_stop, resume=True)
    except TrainingCancelled as exc:
        if beat.lost.is_set():
            log.warning("job %s: lost its lease (presumed dead); stopped at step %s", job_id, exc.step)
            return "lost"
        current = store.get_job(job_id)
        if current is not None and current["cancel_requested"]:
            if store.finish(job_id, lease, "cancelled", error_code="cancelled",
                            error_message=f"cancelled at step {exc.step}"):
                layout.remove_tree(layout.job_dir(job_id))
            return "cancelled"
        if ctx.draining.is_set():
            if store.release(job_id, lease):
                ctx.enqueue(job_id)
                log.info("job %s: worker draining; requeued at step %s", job_id, exc.step)
            return "requeued"
        return fail("internal_error", f"training stopped without a reason at step {exc.step}")
    except TrainingDivergedError as exc:
        # The message names the step; the server path of the kept checkpoint stays server-side.
        log.error("job %s diverged: %s", job_id, exc)
        return fail("diverged", f"non-finite training loss at step {exc.step}; the last good checkpoint was kept")
    except RoGUENeRFError as exc:
        return fail("invalid_input", str(exc))
    except Exception as exc:
        log.error("job %s crashed:\n%s", job_id, traceback.format_exc())
        return fail("internal_error", f"{type(exc).__name__}: {exc}")

    version = store.allocate_version(scene_id)
    if version is None:
        return fail("scene_deleted", f"scene {scene_id} was deleted while the job ran")
    destination = layout.checkpoint(scene_id, version)
    copy_atomic(Path(result.checkpoint), destination)
    sidecar = Path(result.checkpoint).with_suffix(".json")
    if sidecar.is_file():
        copy_atomic(sidecar, destination.with_suffix(".json"))
    summary = jsonable({
        "steps": result.steps,
        "seconds": result.seconds,
        "final_loss": result.final_loss,
        "loss_kind": result.loss_kind,
        "before": result.before,
        "after": result.after,
        "config": result.config,
    })
    if not store.finish(job_id, lease, "succeeded", result=summary,
                        checkpoint_path=str(destination), checkpoint_version=version):
        destination.unlink(missing_ok=True)
        destination.with_suffix(".json").unlink(missing_ok=True)
        log.warning("job %s finished after losing its lease; checkpoint discarded", job_id)
        return "lost"
    log.info("job %s succeeded: scene %s now on checkpoint v%s (%s)", job_id, scene_id, version,
             json.dumps({"loss": summary["final_loss"], "steps": summary["steps"]}))
    layout.remove_tree(layout.job_dir(job_id))
    return "succeeded"
