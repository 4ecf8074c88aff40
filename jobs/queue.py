"""Huey wiring: SqliteHuey in data_dir by default, RedisHuey when ``redis_url`` is set.

Messages only say "run job <id>"; the job table (:mod:`jobs.store`) holds the truth, so a
lost or duplicated message is harmless: the sweeper requeues lost jobs and a claim refuses
a job that is not queued.
"""

from __future__ import annotations

from collections.abc import Callable

from huey import RedisHuey, SqliteHuey
from huey.api import Huey

TASK_NAME = "roguenerf.finetune"


class QueueUnavailable(RuntimeError):
    """The queue backend (SQLite file or Redis) cannot be reached."""


def _refuse(job_id: str) -> None:
    raise RuntimeError(f"job {job_id} reached a process that only enqueues (no worker handler)")


class JobQueue:
    """The Huey instance plus the one task; ``handler(job_id)`` runs in a worker."""

    def __init__(self, settings, handler: Callable[[str], None] | None = None):
        self.settings = settings
        if settings.redis_url:
            self.huey: Huey = RedisHuey("roguenerf", url=settings.redis_url, results=False)
        else:
            settings.data_dir.mkdir(parents=True, exist_ok=True)
            self.huey = SqliteHuey("roguenerf", filename=str(settings.queue_path), results=False,
                                   timeout=30)
        run = handler or _refuse

        @self.huey.task(name=TASK_NAME)
        def finetune_job(job_id: str) -> None:
            run(job_id)

        self._task = finetune_job

    @property
    def backend(self) -> str:
        return "redis" if self.settings.redis_url else "sqlite"

    def enqueue(self, job_id: str) -> None:
        try:
            self._task(job_id)
        except Exception as exc:
            raise QueueUnavailable(f"{self.backend} queue: {exc}") from exc

    def pending(self) -> int:
        """Messages waiting; raises QueueUnavailable when the backend is unreachable."""
        try:
            return self.huey.pending_count()
        except Exception as exc:
            raise QueueUnavailable(f"{self.backend} queue: {exc}") from exc
