"""The worker process: a Huey consumer (one thread: training uses every core) plus a sweeper.

SIGINT drains: the running job is asked to stop (the library saves its state), goes back
to the queue, and the process exits; a later worker resumes it. SIGTERM stops at once
(the sweeper of the next worker requeues the job once its heartbeat is stale).
"""

from __future__ import annotations

import logging
import signal
import threading

from huey.consumer import Consumer

from jobs.data import open_data
from jobs.lifecycle import WorkerContext
from jobs.queue import JobQueue
from jobs.store import JobStore
from workers.dispatch import run_job

log = logging.getLogger("roguenerf.worker")


def sweep_once(store: JobStore, queue: JobQueue, settings) -> list:
    """One sweeper pass: requeue / fail jobs of lost workers, re-send stale queued jobs."""
    actions = store.sweep(stale_after=settings.heartbeat_timeout, max_attempts=settings.max_attempts)
    for action in actions:
        log.warning("sweeper: job %s %s (attempt %s)", action.job_id, action.action, action.attempt)
    resend = [a.job_id for a in actions if a.action == "requeued"]
    resend += store.stale_queued(stale_after=settings.heartbeat_timeout)
    for job_id in dict.fromkeys(resend):
        queue.enqueue(job_id)
    return actions


class Sweeper(threading.Thread):
    def __init__(self, store: JobStore, queue: JobQueue, settings):
        super().__init__(name="sweeper", daemon=True)
        self.store, self.queue, self.settings = store, queue, settings
        self.stop = threading.Event()

    def run(self) -> None:
        while True:
            try:
                sweep_once(self.store, self.queue, self.settings)
            except Exception:  # the next pass retries; a dead sweeper would strand jobs
                log.exception("sweeper pass failed")
            if self.stop.wait(self.settings.sweeper_period):
                return


class DrainingConsumer(Consumer):
    """A Huey consumer that tells the running job to checkpoint and stop when it stops."""

    def __init__(self, huey, draining: threading.Event, *, interrupted: threading.Event | None = None,
                 **options):
        super().__init__(huey, **options)
        self._draining = draining
        self._interrupted = interrupted

    def _set_signal_handlers(self) -> None:
        super()._set_signal_handlers()
        # A SIGINT that arrived while the worker was still starting (before these handlers)
        # was caught by main()'s handler: replay it now, so the consumer stops at once.
        if self._interrupted is not None and self._interrupted.is_set():
            self._handle_signal(signal.SIGINT, None)

    def stop(self, graceful: bool = False) -> None:
        self._draining.set()
        super().stop(graceful=graceful)


def build_worker(settings) -> tuple[WorkerContext, JobQueue, JobStore]:
    layout, store = open_data(settings)
    holder: dict = {}
    queue = JobQueue(settings, handler=lambda job_id: run_job(holder["ctx"], job_id))
    ctx = WorkerContext(settings=settings, store=store, layout=layout, enqueue=queue.enqueue)
    holder["ctx"] = ctx
    return ctx, queue, store


def run_worker(settings, *, interrupted: threading.Event | None = None) -> None:
    """Run until SIGINT (drain) or SIGTERM; blocks. ``interrupted``: set by the caller's own
    SIGINT handler during start-up; the consumer then stops as soon as it starts."""
    ctx, queue, store = build_worker(settings)
    from roguenerf import (
        finetune,  # noqa: F401  (pay torch's import before the first job, not during it)
        runtime,
    )

    log.info("runtime: %s", runtime.configure())

    sweeper = Sweeper(store, queue, settings)
    sweeper.start()
    consumer = DrainingConsumer(
        queue.huey, ctx.draining, interrupted=interrupted, workers=1, worker_type="thread", periodic=False,
        initial_delay=0.05, backoff=1.5, max_delay=settings.worker_poll_max_delay,
        shutdown_timeout=settings.drain_timeout,
    )
    log.info("worker ready: queue=%s, data_dir=%s", queue.backend, settings.data_dir)
    try:
        consumer.run()
    finally:
        sweeper.stop.set()
        log.info("worker stopped")
