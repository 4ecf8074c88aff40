"""The job and scene table: the truth about every fine-tuning job.

Huey only delivers "run job X" messages; a message can be lost with a killed worker, so the
state machine lives here::

    queued -> running -> succeeded | failed | cancelled
    running -> queued            (sweeper: heartbeat stale, attempts left; worker drain)
    running -> failed            (sweeper: heartbeat stale, no attempts left: worker_lost)
    queued  -> cancelled         (cancel before a worker took it)

A worker owns a running job through a random ``lease``; every write of a running job is
fenced by it, so a worker that was presumed dead cannot overwrite a job that moved on.
At most one job per scene is queued or running (a partial unique index, atomic across
API processes).
"""

from __future__ import annotations

import json
import time
import uuid
from dataclasses import dataclass

from workers.db import Database, IntegrityConflict

ACTIVE_STATES = ("queued", "running")
TERMINAL_STATES = ("succeeded", "failed", "cancelled")
LOSS_HISTORY = 20
"""Recent losses kept per job (GET /jobs/{id} shows them)."""

SCHEMA = [
    """CREATE TABLE IF NOT EXISTS scenes (
        id TEXT PRIMARY KEY,
        created_at DOUBLE PRECISION NOT NULL,
        views INTEGER NOT NULL,
        train_views INTEGER NOT NULL,
        test_views INTEGER NOT NULL,
        width INTEGER NOT NULL,
        height INTEGER NOT NULL,
        active_version INTEGER NOT NULL,
        next_version INTEGER NOT NULL
    )""",
    """CREATE TABLE IF NOT EXISTS jobs (
        id TEXT PRIMARY KEY,
        scene_id TEXT NOT NULL,
        state TEXT NOT NULL,
        request TEXT NOT NULL,
        idempotency_key TEXT UNIQUE,
        attempt INTEGER NOT NULL,
        lease TEXT,
        cancel_requested INTEGER NOT NULL,
        progress DOUBLE PRECISION NOT NULL,
        step INTEGER,
        total_steps INTEGER,
        eta_s DOUBLE PRECISION,
        loss DOUBLE PRECISION,
        losses TEXT,
        error_code TEXT,
        error_message TEXT,
        result TEXT,
        base_version INTEGER,
        checkpoint_path TEXT,
        checkpoint_version INTEGER,
        created_at DOUBLE PRECISION NOT NULL,
        updated_at DOUBLE PRECISION NOT NULL,
        started_at DOUBLE PRECISION,
        finished_at DOUBLE PRECISION,
        heartbeat_at DOUBLE PRECISION
    )""",
    "CREATE UNIQUE INDEX IF NOT EXISTS jobs_one_active_per_scene ON jobs (scene_id) "
    "WHERE state IN ('queued', 'running')",
    "CREATE INDEX IF NOT EXISTS jobs_by_state ON jobs (state)",
]


class ActiveJobExists(Exception):
    """The scene already has a queued or running job."""

    def __init__(self, job_id: str | None):
        self.job_id = job_id
        super().__init__(f"scene already has an active fine-tuning job ({job_id})")


class IdempotencyMismatch(Exception):
    """An Idempotency-Key was reused for a different request."""


class SceneBusy(Exception):
    """The scene cannot be deleted while a job is queued or running on it."""


@dataclass
class SweepAction:
    job_id: str
    action: str
    """"requeued", "failed" or "cancelled"."""
    attempt: int


def _loads(text):
    return None if text is None else json.loads(text)


def _job_view(row: dict | None) -> dict | None:
    if row is None:
        return None
    row = dict(row)
    for key in ("request", "losses", "result"):
        row[key] = _loads(row[key])
    row["cancel_requested"] = bool(row["cancel_requested"])
    return row


class JobStore:
    """Scenes and jobs in one database (see the module docstring for the state machine)."""

    def __init__(self, db: Database | str):
        self.db = db if isinstance(db, Database) else Database(db)

    def init_schema(self) -> None:
        with self.db.tx() as tx:
            for statement in SCHEMA:
                tx.execute(statement)

    # ---------------------------------------------------------------- scenes
    def create_scene(self, scene_id: str, *, views: int, train_views: int, test_views: int,
                     width: int, height: int, active_version: int) -> dict:
        now = time.time()
        with self.db.tx() as tx:
            tx.execute(
                "INSERT INTO scenes (id, created_at, views, train_views, test_views, width, height,"
                " active_version, next_version) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?)",
                (scene_id, now, views, train_views, test_views, width, height,
                 active_version, active_version + 1),
            )
        return self.get_scene(scene_id)

    def get_scene(self, scene_id: str) -> dict | None:
        with self.db.tx(write=False) as tx:
            return tx.one("SELECT * FROM scenes WHERE id = ?", (scene_id,))

    def list_scenes(self, *, limit: int, after: tuple[float, str] | None = None) -> list[dict]:
        """Scenes newest first (``created_at``, then id, descending); ``after`` is the
        ``(created_at, id)`` of the last scene of the previous page."""
        with self.db.tx(write=False) as tx:
            if after is None:
                return tx.all("SELECT * FROM scenes ORDER BY created_at DESC, id DESC LIMIT ?", (limit,))
            created, last_id = after
            return tx.all(
                "SELECT * FROM scenes WHERE created_at < ? OR (created_at = ? AND id < ?)"
                " ORDER BY created_at DESC, id DESC LIMIT ?",
                (created, created, last_id, limit),
            )

    def delete_scene(self, scene_id: str) -> bool:
        """Remove the scene's row; False if unknown. Raises SceneBusy while a job is active."""
        with self.db.tx() as tx:
            active = tx.one(
                "SELECT id FROM jobs WHERE scene_id = ? AND state IN ('queued', 'running')",
                (scene_id,),
            )
            if active is not None:
                raise SceneBusy(active["id"])
            return tx.execute("DELETE FROM scenes WHERE id = ?", (scene_id,)) == 1

    def allocate_version(self, scene_id: str) -> int | None:
        """Reserve the next checkpoint version number of a scene (None if the scene is gone)."""
        with self.db.tx() as tx:
            if tx.execute("UPDATE scenes SET next_version = next_version + 1 WHERE id = ?",
                          (scene_id,)) != 1:
                return None
            return tx.one("SELECT next_version FROM scenes WHERE id = ?", (scene_id,))["next_version"] - 1

    # ------------------------------------------------------------------ jobs
    def create_job(self, scene_id: str, request: dict, *, idempotency_key: str | None = None,
                   base_version: int = 0) -> tuple[dict, bool]:
        """Insert a queued job; returns ``(job, created)``.

        With an idempotency key already used for the same scene and request, returns that
        job and ``created=False``; for a different request raises IdempotencyMismatch.
        Raises ActiveJobExists when the scene has a queued or running job.
        """
        if idempotency_key is not None:
            existing = self._by_key(idempotency_key)
            if existing is not None:
                return self._same_request(existing, scene_id, request), False
        job_id = uuid.uuid4().hex
        now = time.time()
        try:
            with self.db.tx() as tx:
                tx.execute(
                    "INSERT INTO jobs (id, scene_id, state, request, idempotency_key, attempt,"
                    " cancel_requested, progress, base_version, created_at, updated_at, heartbeat_at)"
                    " VALUES (?, ?, 'queued', ?, ?, 1, 0, 0, ?, ?, ?, ?)",
                    (job_id, scene_id, json.dumps(request, sort_keys=True), idempotency_key,
                     base_version, now, now, now),
                )
        except IntegrityConflict:
            if idempotency_key is not None:
                existing = self._by_key(idempotency_key)
                if existing is not None:
                    return self._same_request(existing, scene_id, request), False
            active = self.active_job(scene_id)
            raise ActiveJobExists(active["id"] if active else None) from None
        return self.get_job(job_id), True

    def _by_key(self, key: str) -> dict | None:
        with self.db.tx(write=False) as tx:
            return _job_view(tx.one("SELECT * FROM jobs WHERE idempotency_key = ?", (key,)))

    @staticmethod
    def _same_request(job: dict, scene_id: str, request: dict) -> dict:
        if job["scene_id"] != scene_id or job["request"] != json.loads(json.dumps(request)):
            raise IdempotencyMismatch(
                f"Idempotency-Key already used by job {job['id']} for a different request "
                f"(scene {job['scene_id']}, {job['request']})"
            )
        return job

    def delete_job(self, job_id: str) -> None:
        """Forget a job that was never handed to the queue (enqueue failed)."""
        with self.db.tx() as tx:
            tx.execute("DELETE FROM jobs WHERE id = ? AND state = 'queued'", (job_id,))

    def get_job(self, job_id: str) -> dict | None:
        with self.db.tx(write=False) as tx:
            return _job_view(tx.one("SELECT * FROM jobs WHERE id = ?", (job_id,)))

    def active_job(self, scene_id: str) -> dict | None:
        with self.db.tx(write=False) as tx:
            return _job_view(tx.one(
                "SELECT * FROM jobs WHERE scene_id = ? AND state IN ('queued', 'running')",
                (scene_id,),
            ))

    def request_cancel(self, job_id: str) -> dict | None:
        """Queued: cancelled at once. Running: flag for the training loop. Terminal: unchanged."""
        now = time.time()
        with self.db.tx() as tx:
            tx.execute(
                "UPDATE jobs SET state = 'cancelled', finished_at = ?, updated_at = ?,"
                " cancel_requested = 1, error_code = 'cancelled', error_message = ?"
                " WHERE id = ? AND state = 'queued'",
                (now, now, "cancelled before it started", job_id),
            )
            tx.execute(
                "UPDATE jobs SET cancel_requested = 1, updated_at = ? WHERE id = ? AND state = 'running'",
                (now, job_id),
            )
        return self.get_job(job_id)

    # ------------------------------------------------------- worker side
    def claim(self, job_id: str, lease: str) -> dict | None:
        """Take a queued job for this worker; None if it is not queued (already done, taken,
        cancelled or a duplicate message)."""
        now = time.time()
        with self.db.tx() as tx:
            n = tx.execute(
                "UPDATE jobs SET state = 'running', lease = ?, heartbeat_at = ?, updated_at = ?,"
                " started_at = COALESCE(started_at, ?) WHERE id = ? AND state = 'queued'",
                (lease, now, now, now, job_id),
            )
        return self.get_job(job_id) if n == 1 else None

    def heartbeat(self, job_id: str, lease: str) -> bool:
        """Refresh the heartbeat; False when this worker no longer owns the job."""
        now = time.time()
        with self.db.tx() as tx:
            return tx.execute(
                "UPDATE jobs SET heartbeat_at = ? WHERE id = ? AND lease = ? AND state = 'running'",
                (now, job_id, lease),
            ) == 1

    def record_progress(self, job_id: str, lease: str, *, step: int, total_steps: int | None,
                        fraction: float, eta_s: float | None, loss: float) -> bool:
        now = time.time()
        with self.db.tx() as tx:
            row = tx.one("SELECT losses FROM jobs WHERE id = ? AND lease = ? AND state = 'running'",
                         (job_id, lease))
            if row is None:
                return False
            losses = (_loads(row["losses"]) or [])[-(LOSS_HISTORY - 1):] + [[step, loss]]
            tx.execute(
                "UPDATE jobs SET step = ?, total_steps = ?, progress = ?, eta_s = ?, loss = ?,"
                " losses = ?, heartbeat_at = ?, updated_at = ? WHERE id = ? AND lease = ?",
                (step, total_steps, min(max(fraction, 0.0), 1.0), eta_s, loss, json.dumps(losses),
                 now, now, job_id, lease),
            )
            return True

    def should_stop(self, job_id: str, lease: str) -> bool:
        """True when a cancel was asked or this worker lost the job."""
        with self.db.tx(write=False) as tx:
            row = tx.one("SELECT cancel_requested, lease, state FROM jobs WHERE id = ?", (job_id,))
        return row is None or bool(row["cancel_requested"]) or row["lease"] != lease or row["state"] != "running"

    def finish(self, job_id: str, lease: str, state: str, *, error_code: str | None = None,
               error_message: str | None = None, result: dict | None = None,
               checkpoint_path: str | None = None, checkpoint_version: int | None = None) -> bool:
        """End a running job owned by ``lease``; a succeeded job's checkpoint version becomes
        the scene's active one in the same transaction. False if the lease was lost."""
        assert state in TERMINAL_STATES
        now = time.time()
        with self.db.tx() as tx:
            n = tx.execute(
                "UPDATE jobs SET state = ?, lease = NULL, error_code = ?, error_message = ?, result = ?,"
                " checkpoint_path = ?, checkpoint_version = ?, finished_at = ?, updated_at = ?,"
                " progress = CASE WHEN ? = 'succeeded' THEN 1.0 ELSE progress END,"
                " eta_s = CASE WHEN ? = 'succeeded' THEN 0.0 ELSE eta_s END"
                " WHERE id = ? AND lease = ? AND state = 'running'",
                (state, error_code, error_message, None if result is None else json.dumps(result),
                 checkpoint_path, checkpoint_version, now, now, state, state, job_id, lease),
            )
            if n != 1:
                return False
            if state == "succeeded" and checkpoint_version is not None:
                job = tx.one("SELECT scene_id FROM jobs WHERE id = ?", (job_id,))
                tx.execute("UPDATE scenes SET active_version = ? WHERE id = ?",
                           (checkpoint_version, job["scene_id"]))
        return True

    def release(self, job_id: str, lease: str) -> bool:
        """Give a running job back to the queue without using an attempt (worker drain)."""
        now = time.time()
        with self.db.tx() as tx:
            return tx.execute(
                "UPDATE jobs SET state = 'queued', lease = NULL, heartbeat_at = ?, updated_at = ?"
                " WHERE id = ? AND lease = ? AND state = 'running'",
                (now, now, job_id, lease),
            ) == 1

    def stale_queued(self, *, stale_after: float, now: float | None = None) -> list[str]:
        """Queued jobs nobody took for ``stale_after`` seconds; their clock restarts.

        Their message may have been lost (a worker killed between dequeue and claim, an
        enqueue that failed); re-sending is safe because only one claim can succeed.
        """
        now = time.time() if now is None else now
        cutoff = now - stale_after
        with self.db.tx() as tx:
            rows = tx.all("SELECT id FROM jobs WHERE state = 'queued' AND heartbeat_at < ?", (cutoff,))
            for row in rows:
                tx.execute("UPDATE jobs SET heartbeat_at = ? WHERE id = ? AND state = 'queued'",
                           (now, row["id"]))
        return [row["id"] for row in rows]

    def sweep(self, *, stale_after: float, max_attempts: int, now: float | None = None) -> list[SweepAction]:
        """Requeue (attempt + 1) or fail (``worker_lost``) running jobs whose heartbeat is older
        than ``stale_after`` seconds; a lost job whose cancel was asked ends cancelled."""
        now = time.time() if now is None else now
        cutoff = now - stale_after
        actions: list[SweepAction] = []
        with self.db.tx() as tx:
            stale = tx.all(
                "SELECT id, attempt, cancel_requested, lease, heartbeat_at FROM jobs"
                " WHERE state = 'running' AND heartbeat_at < ?",
                (cutoff,),
            )
            for job in stale:
                where = " WHERE id = ? AND state = 'running' AND heartbeat_at < ?"
                if job["cancel_requested"]:
                    tx.execute(
                        "UPDATE jobs SET state = 'cancelled', lease = NULL, finished_at = ?, updated_at = ?,"
                        " error_code = 'cancelled', error_message = 'cancelled; its worker was lost'" + where,
                        (now, now, job["id"], cutoff),
                    )
                    actions.append(SweepAction(job["id"], "cancelled", job["attempt"]))
                elif job["attempt"] >= max_attempts:
                    silent = now - job["heartbeat_at"]
                    tx.execute(
                        "UPDATE jobs SET state = 'failed', lease = NULL, finished_at = ?, updated_at = ?,"
                        " error_code = 'worker_lost', error_message = ?" + where,
                        (now, now, f"the worker running attempt {job['attempt']} of {max_attempts} "
                         f"stopped sending heartbeats {silent:.0f} s ago; no attempts left",
                         job["id"], cutoff),
                    )
                    actions.append(SweepAction(job["id"], "failed", job["attempt"]))
                else:
                    tx.execute(
                        "UPDATE jobs SET state = 'queued', lease = NULL, attempt = attempt + 1,"
                        " heartbeat_at = ?, updated_at = ?" + where,
                        (now, now, job["id"], cutoff),
                    )
                    actions.append(SweepAction(job["id"], "requeued", job["attempt"] + 1))
        return actions
