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
from pathlib import Path

from jobs.data import base_checkpoint
from jobs.layout import copy_atomic
from jobs.lifecycle import JobRun, JobStopped, Task, jsonable

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


def run_finetune_job(run: JobRun) -> str:
    """Fine-tune the scene's enhancer from its active checkpoint; the new checkpoint becomes the
    scene's next version and its active one."""
    from roguenerf import TrainConfig, TrainingCancelled, TrainingDivergedError, finetune, load_scene

    store, layout, scene_id = run.store, run.layout, run.scene_id
    scene_row = store.get_scene(scene_id)
    if scene_row is None:
        return run.fail("scene_deleted", f"scene {scene_id} no longer exists")

    def progress(p) -> None:
        if getattr(p, "phase", "training") == "evaluating":
            run.record(store.record_phase, phase="evaluating")
        else:
            run.record(store.record_progress, step=int(p.step), total_steps=p.total_steps,
                       fraction=float(p.fraction), eta_s=p.eta_s, loss=float(p.loss))

    scene = load_scene(layout.scene_files(scene_id), confine=True)
    checkpoint = base_checkpoint(run.settings, layout, scene_id, scene_row["active_version"])
    config = TrainConfig(**train_options(TrainConfig, run.settings, run.request))
    run.job_dir.mkdir(parents=True, exist_ok=True)
    try:
        result = finetune(scene, run.job_dir, checkpoint=checkpoint, config=config,
                          progress=progress, should_stop=run.should_stop, resume=True)
    except TrainingCancelled as exc:
        raise JobStopped(f"at step {exc.step}") from exc
    except TrainingDivergedError as exc:
        # The message names the step; the server path of the kept checkpoint stays server-side.
        log.error("job %s diverged: %s", run.id, exc)
        return run.fail("diverged", f"non-finite training loss at step {exc.step}; the last good checkpoint was kept")

    version = store.allocate_version(scene_id)
    if version is None:
        return run.fail("scene_deleted", f"scene {scene_id} was deleted while the job ran")
    destination = layout.checkpoint(scene_id, version)
    copy_atomic(Path(result.checkpoint), destination)
    sidecar = Path(result.checkpoint).with_suffix(".json")
    if sidecar.is_file():
        copy_atomic(sidecar, destination.with_suffix(".json"))
    summary = {
        "steps": result.steps,
        "seconds": result.seconds,
        "final_loss": result.final_loss,
        "loss_kind": result.loss_kind,
        "before": result.before,
        "after": result.after,
        "config": result.config,
        "guard": result.guard,
    }
    outcome = run.succeed(summary, checkpoint_path=str(destination), checkpoint_version=version)
    if outcome == "succeeded":
        log.info("job %s succeeded: scene %s now on checkpoint v%s (%s)", run.id, scene_id, version,
                 json.dumps(jsonable({"loss": result.final_loss, "steps": result.steps})))
    else:  # the lease went: the checkpoint never became the scene's
        destination.unlink(missing_ok=True)
        destination.with_suffix(".json").unlink(missing_ok=True)
    return outcome


FINETUNE = Task(run_finetune_job, label="job", work="training")
