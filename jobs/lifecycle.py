"""The one lifecycle of a running job, which every task shares.

:func:`run_job` claims a queued job (one conditional ``UPDATE`` takes a random lease), keeps
its heartbeat going, hands a :class:`JobRun` to the :class:`Task` of the job's kind and ends
the job once, the same way for every kind::

    the body returns run.succeed(result)          succeeded (lost when the lease went meanwhile)
    the body returns run.fail(code, message)      failed; the message fit for clients
    the body raises JobStopped(where)             should_stop said yes, because
        the lease was lost                        lost: another worker owns the job now
        a cancel was asked                        cancelled "cancelled <where>"; its folder removed
        the worker drains (SIGINT)                requeued: released and enqueued again
        none of these                             failed internal_error
    the library raises RoGUENeRFError             failed invalid_input (the input is at fault)
    anything else raises                          failed internal_error; the traceback in the log
    the job table is unreachable (DatabaseError)  raised: the job stays running, and the
                                                  sweeper requeues it once its heartbeat is stale

A task (``workers/tasks.py``, ``paths.py``, ``imports.py``) is then only its body: load, call the
library with ``run.should_stop`` and a progress callback that writes through :meth:`JobRun.record`,
and report.
"""

from __future__ import annotations

import logging
import math
import threading
import time
import traceback
import uuid
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path

from jobs.db import DatabaseError
from jobs.layout import Layout, public_message
from jobs.store import JobStore
from roguenerf import RoGUENeRFError

log = logging.getLogger("roguenerf.worker")

SHOULD_STOP_POLL_S = 0.5
"""The training loop asks should_stop every step; the table is read at most this often."""


@dataclass
class WorkerContext:
    settings: object
    """jobs.settings.JobSettings (or the API's Settings, which extends it)."""
    store: JobStore
    layout: Layout
    enqueue: Callable[[str], None]
    """Hand a job id back to the queue (after a drain)."""
    draining: threading.Event = field(default_factory=threading.Event)
    """Set on SIGINT: the running job checkpoints, stops and is requeued."""


class JobStopped(Exception):
    """A task's work stopped because ``should_stop`` said so; ``where`` says how far it got
    ("at step 40", "after 12 frames"), for the job's message and the log."""

    def __init__(self, where: str):
        self.where = where
        super().__init__(f"stopped {where}")


@dataclass(frozen=True)
class Task:
    """A kind of job: its body and how messages name it."""

    body: Callable[[JobRun], str]
    """Runs a claimed job; returns ``run.succeed(...)`` or ``run.fail(...)`` (or raises)."""
    label: str = "job"
    """The job in the log: "job", "path job", "import job"."""
    work: str = "job"
    """What stops, in "<work> stopped without a reason ...": "training", "path", "import"."""


def jsonable(value):
    """Training summaries may hold tensors, Paths or NaN; the job row holds plain JSON."""
    if isinstance(value, dict):
        return {str(k): jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [jsonable(v) for v in value]
    if hasattr(value, "item") and callable(value.item) and getattr(value, "ndim", 1) == 0:
        value = value.item()
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if value is None or isinstance(value, (bool, int, str)):
        return value
    return str(value)


class Heartbeat(threading.Thread):
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


class JobRun:
    """A claimed job as its task's body sees it: the job, what it may use, and how it ends.

    ``root``, ``root_name``, ``aliases`` and ``clean_on_failure`` shape a failure; a body sets
    them before it can fail: a message's paths inside ``root`` become relative to it (the folder
    itself ``root_name``), each ``aliases`` key becomes its value, and with ``clean_on_failure``
    a failed job's folder is removed.
    """

    def __init__(self, ctx: WorkerContext, job: dict, lease: str, beat: Heartbeat, task: Task):
        self.ctx, self.job, self.lease, self.beat, self.task = ctx, job, lease, beat, task
        self.settings, self.store, self.layout = ctx.settings, ctx.store, ctx.layout
        self.id, self.scene_id = job["id"], job["scene_id"]
        self.request: dict = job["request"] or {}
        self.job_dir: Path = self.layout.job_dir(self.id)
        self.should_stop = cancel_poller(ctx, beat, self.store, self.id, lease)
        self.root: Path | None = self.layout.scene_files(self.scene_id)
        self.root_name = "the scene"
        self.aliases: dict[str, str] = {}
        self.clean_on_failure = False

    def record(self, write: Callable[..., bool], **values) -> None:
        """A progress write of the store (``store.record_progress``, ``record_frames``,
        ``record_phase``) for this job and lease; a refused one means the lease is gone (the
        heartbeat's ``lost`` is set, and ``should_stop`` says yes). A failed write is logged."""
        try:
            owned = write(self.id, self.lease, **values)
        except Exception:
            log.exception("%s %s: could not record progress", self.task.label, self.id)
            return
        if not owned:
            self.beat.lost.set()

    def fail(self, code: str, message: str) -> str:
        """End the job failed with ``code``; clients read ``message`` (GET /jobs), so paths
        become relative to :attr:`root` and none of the server's are left."""
        log.warning("%s %s failed: %s: %s", self.task.label, self.id, code, message)
        for text, alias in self.aliases.items():
            message = message.replace(text, alias)
        public = public_message(message, root=self.root, data_dir=self.layout.root, root_name=self.root_name)
        if self.store.finish(self.id, self.lease, "failed", error_code=code, error_message=public) \
                and self.clean_on_failure:
            self.layout.remove_tree(self.job_dir)
        return "failed"

    def succeed(self, result: dict, *, checkpoint_path: str | None = None, checkpoint_version: int | None = None,
                keep_files: bool = False) -> str:
        """End the job succeeded with ``result`` (made plain JSON); a checkpoint version becomes
        the scene's active one. Its folder is removed unless ``keep_files``. "lost" when the lease
        went meanwhile (nothing written: the result is not the job's)."""
        if not self.store.finish(self.id, self.lease, "succeeded", result=jsonable(result),
                                 checkpoint_path=checkpoint_path, checkpoint_version=checkpoint_version):
            log.warning("%s %s finished after losing its lease; its result was discarded", self.task.label, self.id)
            return "lost"
        if not keep_files:
            self.layout.remove_tree(self.job_dir)
        return "succeeded"

    def stopped(self, where: str) -> str:
        """The body stopped on ``should_stop``: lost, cancelled, requeued (drain), or failed."""
        if self.beat.lost.is_set():
            log.warning("%s %s: lost its lease (presumed dead); stopped %s", self.task.label, self.id, where)
            return "lost"
        current = self.store.get_job(self.id)
        if current is not None and current["cancel_requested"]:
            if self.store.finish(self.id, self.lease, "cancelled", error_code="cancelled",
                                 error_message=f"cancelled {where}"):
                self.layout.remove_tree(self.job_dir)
            return "cancelled"
        if self.ctx.draining.is_set():
            if self.store.release(self.id, self.lease):
                self.ctx.enqueue(self.id)
                log.info("%s %s: worker draining; requeued, stopped %s", self.task.label, self.id, where)
            return "requeued"
        return self.fail("internal_error", f"{self.task.work} stopped without a reason {where}")


def run_job(ctx: WorkerContext, job_id: str, tasks: Mapping[str, Task], *, default: str = "finetune") -> str:
    """Claim job ``job_id`` and run it through the task of its kind (``request["kind"]``; other
    requests are ``default``'s) under a heartbeat; returns what happened: "skipped" (not
    claimable), "succeeded", "failed", "cancelled", "requeued" or "lost"."""
    lease = uuid.uuid4().hex
    job = ctx.store.claim(job_id, lease)
    if job is None:
        log.info("job %s not claimable (not queued any more); message dropped", job_id)
        return "skipped"
    log.info("job %s: attempt %s on scene %s", job_id, job["attempt"], job["scene_id"])
    task = tasks.get((job.get("request") or {}).get("kind"), tasks[default])
    beat = Heartbeat(ctx.store, job_id, lease, ctx.settings.heartbeat_period)
    beat.start()
    try:
        run = JobRun(ctx, job, lease, beat, task)
        try:
            return task.body(run)
        except JobStopped as stop:
            return run.stopped(stop.where)
        except DatabaseError:
            raise
        except RoGUENeRFError as exc:
            return run.fail("invalid_input", str(exc))
        except Exception as exc:
            log.error("%s %s crashed:\n%s", task.label, job_id, traceback.format_exc())
            return run.fail("internal_error", f"{type(exc).__name__}: {exc}")
    finally:
        beat.stop.set()
        beat.join()
