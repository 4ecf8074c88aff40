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
import math
import threading
import time
import traceback
import uuid
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from workers.jobs import JobStore
from workers.layout import Layout, copy_atomic, public_message

log = logging.getLogger("roguenerf.worker")

SHOULD_STOP_POLL_S = 0.5
"""The training loop asks should_stop every step; the table is read at most this often."""


@dataclass
class WorkerContext:
    settings: object
    """workers.settings.WorkerSettings (or the API's Settings, which extends it)."""
    store: JobStore
    layout: Layout
    enqueue: Callable[[str], None]
    """Hand a job id back to the queue (after a drain)."""
    draining: threading.Event = field(default_factory=threading.Event)
    """Set on SIGINT: the running job checkpoints, stops and is requeued."""


def base_checkpoint(settings, layout: Layout, scene_id: str, version: int) -> Path | None:
    """The checkpoint a scene's active ``version`` means: vN.safetensors, or for version 0
    the configured / bundled default (None when neither exists)."""
    if version > 0:
        return layout.checkpoint(scene_id, version)
    if settings.default_checkpoint is not None:
        return Path(settings.default_checkpoint)
    return bundled_checkpoint()


def bundled_checkpoint() -> Path | None:
    """The library's default checkpoint, or None when the package ships none."""
    from roguenerf import CheckpointError, default_checkpoint_path

    try:
        path = Path(default_checkpoint_path())
    except CheckpointError:
        return None
    return path if path.is_file() else None


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


def _jsonable(value):
    """Training summaries may hold tensors, Paths or NaN; the job row holds plain JSON."""
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if hasattr(value, "item") and callable(value.item) and getattr(value, "ndim", 1) == 0:
        value = value.item()
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if value is None or isinstance(value, (bool, int, str)):
        return value
    return str(value)


class _Heartbeat(threading.Thread):
    """Proves the worker is alive even while one training step takes long."""

    def __init__(self, store: JobStore, job_id: str, lease: str, period: float):
        super().__init__(name=f"heartbeat-{job_id[:8]}", daemon=True)
        self.store, self.job_id, self.lease, self.period = store, job_id, lease, period
        self.stop = threading.Event()
        self.lost = threading.Event()

    def run(self) -> None:
        while not self.stop.wait(self.period):
            try:
                if not self.store.heartbeat(self.job_id, self.lease):
                    self.lost.set()
                    return
            except Exception:  # a busy database must not kill the heartbeat; retry next period
                log.exception("heartbeat of job %s failed", self.job_id)


def cancel_poller(ctx, beat, store: JobStore, job_id: str, lease: str) -> Callable[[], bool]:
    """``should_stop`` for a running job: True when the worker drains, the lease is lost, or the
    job's cancel flag is set (read from the store at most every SHOULD_STOP_POLL_S)."""
    last_poll, stop_cached = [0.0], [False]

    def should_stop() -> bool:
        if ctx.draining.is_set() or beat.lost.is_set():
            return True
        now = time.monotonic()
        if now - last_poll[0] >= SHOULD_STOP_POLL_S:
            last_poll[0] = now
            try:
                stop_cached[0] = store.should_stop(job_id, lease)
            except Exception:
                log.exception("job %s: could not read its cancel flag", job_id)
        return stop_cached[0]

    return should_stop


def run_job(ctx: WorkerContext, job_id: str) -> str:
    """Claim and run one job; returns what happened (for logs and tests)."""
    lease = uuid.uuid4().hex
    job = ctx.store.claim(job_id, lease)
    if job is None:
        log.info("job %s not claimable (not queued any more); message dropped", job_id)
        return "skipped"
    log.info("job %s: attempt %s on scene %s", job_id, job["attempt"], job["scene_id"])
    beat = _Heartbeat(ctx.store, job_id, lease, ctx.settings.heartbeat_period)
    beat.start()
    try:
        if (job.get("request") or {}).get("kind") == "path":
            from workers.paths import run_path_job

            return run_path_job(ctx, job, lease, beat)
        return _train(ctx, job, lease, beat)
    finally:
        beat.stop.set()
        beat.join()


def _train(ctx: WorkerContext, job: dict, lease: str, beat: _Heartbeat) -> str:
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
    summary = _jsonable({
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
