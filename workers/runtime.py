"""The job runtime that every task shares: its context, heartbeat, cancel poller, JSON helper
and base checkpoint.

The fine-tuning task (:mod:`workers.tasks`) and the camera-path task (:mod:`workers.paths`)
both import this module and never each other; :mod:`workers.dispatch` claims a job and hands
it to its task.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from workers.jobs import JobStore
from workers.layout import Layout

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
