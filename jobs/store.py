"""The job and scene table: the truth about every fine-tuning job (SQLAlchemy Core).

Huey only delivers "run job X" messages; a message can be lost with a killed worker, so the
state machine lives here::

    queued -> running -> succeeded | failed | cancelled
    running -> queued            (sweeper: heartbeat stale, attempts left; worker drain)
    running -> failed            (sweeper: heartbeat stale, no attempts left: worker_lost)
    queued  -> cancelled         (cancel before a worker took it)

A worker owns a running job through a random ``lease`` taken in one conditional ``UPDATE``
(``queued -> running``), so of two workers racing for a job exactly one gets it. The lease
expires when its heartbeat is older than ``heartbeat_timeout``: the sweeper then requeues
the job; every write of a running job is fenced by the lease, so a worker that was presumed
dead cannot overwrite a job that moved on. At most one job per scene is queued or running
(a partial unique index), and at most ``max_queued`` jobs wait (counted and inserted under
one lock): both hold across API processes and machines.

A running job also has a ``phase`` (:data:`PHASES`): ``training`` while optimiser steps
happen, ``evaluating`` while it measures the held-out views (no ETA then); finished and queued
jobs have none. Scenes and jobs are listed newest first with keyset pagination
(:meth:`JobStore.list_scenes`, :meth:`JobStore.list_jobs`).

The schema is versioned in a ``schema_version`` table; :data:`UPGRADES` are the ordered
steps, run by whichever process starts first (see :meth:`JobStore.init_schema`).
"""

from __future__ import annotations

import json
import time
import uuid
from collections.abc import Callable
from dataclasses import dataclass

import sqlalchemy as sa

from jobs.db import Database, DatabaseError, IntegrityConflict, Tx

ACTIVE_STATES = ("queued", "running")
TERMINAL_STATES = ("succeeded", "failed", "cancelled")
LOSS_HISTORY = 20
"""Recent losses kept per job (GET /jobs/{id} shows them)."""
PHASES = ("training", "evaluating")
"""What a running job is doing: optimiser steps, or measuring the held-out views (before the
first step and after the last), when no step happens and no ETA is known."""
MAX_PAGE = 200
"""Largest page of :meth:`JobStore.list_jobs` / :meth:`JobStore.list_scenes`."""

metadata = sa.MetaData()

scenes = sa.Table(
    "scenes", metadata,
    sa.Column("id", sa.Text, primary_key=True),
    sa.Column("created_at", sa.Double, nullable=False),
    *(sa.Column(count, sa.Integer, nullable=False)  # its views, its images' size, its checkpoint versions
      for count in ("views", "train_views", "test_views", "width", "height", "active_version", "next_version")),
    sa.Column("name", sa.Text),
    # Schema v4 added ``name`` (a person's label for the scene; a table made by v1-v3 gets it
    # from the v4 step, its scenes keep none).
)

jobs = sa.Table(
    "jobs", metadata,
    sa.Column("id", sa.Text, primary_key=True),
    sa.Column("scene_id", sa.Text, nullable=False),
    sa.Column("state", sa.Text, nullable=False),
    sa.Column("request", sa.Text, nullable=False),
    sa.Column("idempotency_key", sa.Text, unique=True),
    sa.Column("attempt", sa.Integer, nullable=False),
    sa.Column("lease", sa.Text),
    sa.Column("cancel_requested", sa.Integer, nullable=False),
    sa.Column("progress", sa.Double, nullable=False),
    sa.Column("step", sa.Integer),
    sa.Column("total_steps", sa.Integer),
    sa.Column("eta_s", sa.Double),
    sa.Column("loss", sa.Double),
    sa.Column("losses", sa.Text),
    sa.Column("error_code", sa.Text),
    sa.Column("error_message", sa.Text),
    sa.Column("result", sa.Text),
    sa.Column("base_version", sa.Integer),
    sa.Column("checkpoint_path", sa.Text),
    sa.Column("checkpoint_version", sa.Integer),
    sa.Column("created_at", sa.Double, nullable=False),
    sa.Column("updated_at", sa.Double, nullable=False),
    *(sa.Column(moment, sa.Double) for moment in ("started_at", "finished_at", "heartbeat_at")),  # None until then
    sa.Column("phase", sa.Text),
    # Schema v3 added ``phase`` (a table made by v1/v2 gets it from the v3 step).
)

_ACTIVE = jobs.c.state.in_(ACTIVE_STATES)
_ACTIVE_SQL = sa.text("state IN ('queued', 'running')")
one_active_per_scene = sa.Index("jobs_one_active_per_scene", jobs.c.scene_id, unique=True,
                                sqlite_where=_ACTIVE_SQL, postgresql_where=_ACTIVE_SQL)
by_state = sa.Index("jobs_by_state", jobs.c.state)
by_scene_newest = sa.Index("jobs_by_scene_created", jobs.c.scene_id, jobs.c.created_at)
"""Schema v2: listing a scene's jobs newest first without a sort of the whole table."""
jobs_newest = sa.Index("jobs_by_created", jobs.c.created_at, jobs.c.id)
scenes_newest = sa.Index("scenes_by_created", scenes.c.created_at, scenes.c.id)
"""Schema v3: GET /jobs and GET /scenes without a filter, newest first, page by page."""

schema_version = sa.Table(
    "schema_version", metadata,
    sa.Column("id", sa.Integer, primary_key=True),
    sa.Column("version", sa.Integer, nullable=False),
    sa.Column("upgraded_at", sa.Double, nullable=False),
)


def _v1(tx: Tx) -> None:
    # The schema the hand-written SQL layer created (CREATE ... IF NOT EXISTS): a database
    # made before versioning already has it, and checkfirst adopts it as version 1. (A new
    # database gets the tables with every index at once; later steps are idempotent.)
    metadata.create_all(tx.conn, tables=[scenes, jobs], checkfirst=True)
    for index in (one_active_per_scene, by_state):
        index.create(tx.conn, checkfirst=True)


def _v2(tx: Tx) -> None:
    by_scene_newest.create(tx.conn, checkfirst=True)


def _v3(tx: Tx) -> None:
    # The job's phase (training / evaluating) and the indexes of the unfiltered listings. A new
    # database already has them (v1 creates the current tables); an older one gets them here.
    have = {c["name"] for c in sa.inspect(tx.conn).get_columns("jobs")}
    if "phase" not in have:
        tx.conn.exec_driver_sql("ALTER TABLE jobs ADD COLUMN phase TEXT")
    for index in (jobs_newest, scenes_newest):
        index.create(tx.conn, checkfirst=True)


def _v4(tx: Tx) -> None:
    # The scene's name (given at upload; the zip's file name by default). Nullable: scenes
    # registered before it have none, and the page shows their id instead.
    have = {c["name"] for c in sa.inspect(tx.conn).get_columns("scenes")}
    if "name" not in have:
        tx.conn.exec_driver_sql("ALTER TABLE scenes ADD COLUMN name TEXT")


UPGRADES: list[tuple[int, Callable[[Tx], None]]] = [(1, _v1), (2, _v2), (3, _v3), (4, _v4)]
"""(version, step): each step takes the schema from version - 1 to version. Append, never edit."""
SCHEMA_VERSION = UPGRADES[-1][0]


class ActiveJobExists(Exception):
    """The scene already has a queued or running job."""

    def __init__(self, job_id: str | None):
        self.job_id = job_id
        super().__init__(f"scene already has an active fine-tuning job ({job_id})")


class QueueFull(Exception):
    """``max_queued`` jobs already wait; nothing was inserted."""

    def __init__(self, waiting: int, limit: int):
        self.waiting, self.limit = waiting, limit
        super().__init__(f"{waiting} fine-tuning jobs are already waiting (limit {limit})")


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


def select_jobs() -> sa.Select:
    """``SELECT * FROM jobs``: every job query (one, by key, active, listings) starts here."""
    return sa.select(jobs)


def _page(limit: int) -> int:
    return max(1, min(int(limit), MAX_PAGE))


def _newest_first(query: sa.Select, table: sa.Table, limit: int,
                  before: tuple[float, str] | None) -> sa.Select:
    """``query`` newest first, at most ``limit`` rows, older than the ``(created_at, id)`` of
    ``before`` (keyset pagination: a page is stable while rows are added or deleted)."""
    if before is not None:
        created_at, row_id = before
        query = query.where(sa.or_(
            table.c.created_at < created_at,
            sa.and_(table.c.created_at == created_at, table.c.id < row_id),
        ))
    return query.order_by(table.c.created_at.desc(), table.c.id.desc()).limit(_page(limit))


class JobStore:
    """Scenes and jobs in one database (see the module docstring for the state machine)."""

    def __init__(self, db: Database | str):
        self.db = db if isinstance(db, Database) else Database(db)

    def init_schema(self) -> int:
        """Create or upgrade the schema to :data:`SCHEMA_VERSION`; returns the version found.

        Runs in one transaction under a lock, so an API and workers starting together
        upgrade once; a database newer than this code is refused rather than misread.
        """
        with self.db.tx() as tx:
            tx.lock("schema")
            schema_version.create(tx.conn, checkfirst=True)
            found = tx.scalar(sa.select(schema_version.c.version).where(schema_version.c.id == 1))
            found = 0 if found is None else int(found)
            if found > SCHEMA_VERSION:
                raise DatabaseError(
                    f"job database schema is version {found}, newer than this roguenerf "
                    f"(version {SCHEMA_VERSION}); upgrade roguenerf on this machine"
                )
            for version, step in UPGRADES:
                if version > found:
                    step(tx)
            if found == 0:
                tx.execute(sa.insert(schema_version).values(id=1, version=SCHEMA_VERSION,
                                                            upgraded_at=time.time()))
            elif found < SCHEMA_VERSION:
                tx.execute(sa.update(schema_version).where(schema_version.c.id == 1)
                           .values(version=SCHEMA_VERSION, upgraded_at=time.time()))
        return found

    def schema_version(self) -> int:
        with self.db.tx(write=False) as tx:
            return int(tx.scalar(sa.select(schema_version.c.version).where(schema_version.c.id == 1)))

    # ---------------------------------------------------------------- scenes
    def create_scene(self, scene_id: str, *, views: int, train_views: int, test_views: int,
                     width: int, height: int, active_version: int, name: str | None = None) -> dict:
        with self.db.tx() as tx:
            tx.execute(sa.insert(scenes).values(
                id=scene_id, created_at=time.time(), views=views, train_views=train_views,
                test_views=test_views, width=width, height=height,
                active_version=active_version, next_version=active_version + 1, name=name,
            ))
        return self.get_scene(scene_id)

    def get_scene(self, scene_id: str) -> dict | None:
        with self.db.tx(write=False) as tx:
            return tx.one(sa.select(scenes).where(scenes.c.id == scene_id))

    def rename_scene(self, scene_id: str, name: str | None) -> bool:
        """Set the scene's name; False if the scene is unknown."""
        with self.db.tx() as tx:
            return tx.execute(sa.update(scenes).where(scenes.c.id == scene_id).values(name=name)).rowcount == 1

    def delete_scene(self, scene_id: str) -> bool:
        """Remove the scene's row; False if unknown. Raises SceneBusy while a job is active."""
        return self.delete_scene_and_jobs(scene_id) is not None

    def delete_scene_and_jobs(self, scene_id: str) -> list[str] | None:
        """Remove the scene's row and its (finished) jobs' rows in one transaction; returns the
        removed jobs' ids (their folders are the caller's), None if the scene is unknown.
        Raises SceneBusy while a job is queued or running on it."""
        with self.db.tx() as tx:
            active = tx.one(sa.select(jobs.c.id).where(jobs.c.scene_id == scene_id, _ACTIVE))
            if active is not None:
                raise SceneBusy(active["id"])
            if tx.execute(sa.delete(scenes).where(scenes.c.id == scene_id)).rowcount != 1:
                return None
            return list(tx.execute(sa.delete(jobs).where(jobs.c.scene_id == scene_id)
                                   .returning(jobs.c.id)).scalars())

    def list_scenes(self, *, limit: int = 50, before: tuple[float, str] | None = None) -> list[dict]:
        """Scenes, newest first: at most ``limit`` rows created before the ``(created_at, id)``
        of ``before`` (the last row of the previous page; keyset pagination, so a page is stable
        while scenes are added or deleted)."""
        with self.db.tx(write=False) as tx:
            return tx.all(_newest_first(sa.select(scenes), scenes, limit, before))

    def active_jobs(self, scene_ids: list[str]) -> dict[str, str]:
        """``{scene id: id of its queued or running job}`` for those of ``scene_ids`` that have one."""
        if not scene_ids:
            return {}
        with self.db.tx(write=False) as tx:
            rows = tx.all(sa.select(jobs.c.id, jobs.c.scene_id)
                          .where(_ACTIVE, jobs.c.scene_id.in_(list(scene_ids))))
        return {row["scene_id"]: row["id"] for row in rows}

    def allocate_version(self, scene_id: str) -> int | None:
        """Reserve the next checkpoint version number of a scene (None if the scene is gone)."""
        with self.db.tx() as tx:
            taken = tx.scalar(
                sa.update(scenes).where(scenes.c.id == scene_id)
                .values(next_version=scenes.c.next_version + 1)
                .returning(scenes.c.next_version - 1)
            )
        return None if taken is None else int(taken)

    def set_active_version(self, scene_id: str, version: int) -> bool:
        with self.db.tx() as tx:
            return tx.execute(sa.update(scenes).where(scenes.c.id == scene_id)
                              .values(active_version=version)).rowcount == 1

    # ------------------------------------------------------------------ jobs
    def create_job(self, scene_id: str, request: dict, *, idempotency_key: str | None = None,
                   base_version: int = 0, max_queued: int | None = None) -> tuple[dict, bool]:
        """Insert a queued job; returns ``(job, created)``.

        With an idempotency key already used for the same scene and request, returns that
        job and ``created=False``; for a different request raises IdempotencyMismatch.
        Raises QueueFull when ``max_queued`` jobs already wait (counted and inserted in one
        locked transaction, so concurrent submissions never overshoot), ActiveJobExists when
        the scene has a queued or running job.
        """
        if idempotency_key is not None:
            existing = self._by_key(idempotency_key)
            if existing is not None:
                return self._same_request(existing, scene_id, request), False
        job_id = uuid.uuid4().hex
        now = time.time()
        try:
            with self.db.tx() as tx:
                if max_queued is not None:
                    tx.lock("queue")
                    waiting = tx.scalar(sa.select(sa.func.count()).select_from(jobs)
                                        .where(jobs.c.state == "queued"))
                    if waiting >= max_queued:
                        raise QueueFull(int(waiting), max_queued)
                tx.execute(sa.insert(jobs).values(
                    id=job_id, scene_id=scene_id, state="queued",
                    request=json.dumps(request, sort_keys=True), idempotency_key=idempotency_key,
                    attempt=1, cancel_requested=0, progress=0.0, base_version=base_version,
                    created_at=now, updated_at=now, heartbeat_at=now,
                ))
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
            return _job_view(tx.one(select_jobs().where(jobs.c.idempotency_key == key)))

    def has_key(self, key: str) -> bool:
        """An Idempotency-Key already names a job (its replay creates nothing)."""
        return self._by_key(key) is not None

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
            tx.execute(sa.delete(jobs).where(jobs.c.id == job_id, jobs.c.state == "queued"))

    def get_job(self, job_id: str) -> dict | None:
        with self.db.tx(write=False) as tx:
            return _job_view(tx.one(select_jobs().where(jobs.c.id == job_id)))

    def list_jobs(self, *, scene_id: str | None = None, states: tuple[str, ...] | list[str] = (),
                  limit: int = 50, before: tuple[float, str] | None = None) -> list[dict]:
        """Jobs, newest first, optionally of one scene and in some states; at most ``limit``
        created before the ``(created_at, id)`` of ``before`` (keyset pagination). One scene's
        jobs come from the ``(scene_id, created_at)`` index (v2), all jobs from ``(created_at,
        id)`` (v3)."""
        query = select_jobs()
        if scene_id is not None:
            query = query.where(jobs.c.scene_id == scene_id)
        if states:
            query = query.where(jobs.c.state.in_(list(states)))
        with self.db.tx(write=False) as tx:
            rows = tx.all(_newest_first(query, jobs, limit, before))
        return [_job_view(row) for row in rows]

    def active_job(self, scene_id: str) -> dict | None:
        with self.db.tx(write=False) as tx:
            return _job_view(tx.one(select_jobs().where(jobs.c.scene_id == scene_id, _ACTIVE)))

    def queued_count(self) -> int:
        with self.db.tx(write=False) as tx:
            return int(tx.scalar(sa.select(sa.func.count()).select_from(jobs).where(jobs.c.state == "queued")))

    def request_cancel(self, job_id: str) -> dict | None:
        """Queued: cancelled at once. Running: flag for the training loop. Terminal: unchanged."""
        now = time.time()
        with self.db.tx() as tx:
            tx.execute(
                sa.update(jobs).where(jobs.c.id == job_id, jobs.c.state == "queued").values(
                    state="cancelled", finished_at=now, updated_at=now, cancel_requested=1,
                    error_code="cancelled", error_message="cancelled before it started")
            )
            tx.execute(
                sa.update(jobs).where(jobs.c.id == job_id, jobs.c.state == "running")
                .values(cancel_requested=1, updated_at=now)
            )
        return self.get_job(job_id)

    # ------------------------------------------------------- worker side
    def claim(self, job_id: str, lease: str) -> dict | None:
        """Take a queued job for this worker in one statement; None if it is not queued
        (already done, taken by another worker, cancelled or a duplicate message)."""
        now = time.time()
        with self.db.tx() as tx:
            row = tx.one(
                sa.update(jobs).where(jobs.c.id == job_id, jobs.c.state == "queued")
                .values(state="running", lease=lease, heartbeat_at=now, updated_at=now,
                        started_at=sa.func.coalesce(jobs.c.started_at, now))
                .returning(*jobs.c)
            )
        return _job_view(row)

    def _owned(self, job_id: str, lease: str):
        return sa.and_(jobs.c.id == job_id, jobs.c.lease == lease, jobs.c.state == "running")

    def heartbeat(self, job_id: str, lease: str) -> bool:
        """Renew the lease; False when this worker no longer owns the job."""
        with self.db.tx() as tx:
            return tx.execute(sa.update(jobs).where(self._owned(job_id, lease))
                              .values(heartbeat_at=time.time())).rowcount == 1

    def record_progress(self, job_id: str, lease: str, *, step: int, total_steps: int | None,
                        fraction: float, eta_s: float | None, loss: float) -> bool:
        now = time.time()
        with self.db.tx() as tx:
            row = tx.one(sa.select(jobs.c.losses).where(self._owned(job_id, lease)))
            if row is None:
                return False
            losses = (_loads(row["losses"]) or [])[-(LOSS_HISTORY - 1):] + [[step, loss]]
            tx.execute(sa.update(jobs).where(self._owned(job_id, lease)).values(
                step=step, total_steps=total_steps, progress=min(max(fraction, 0.0), 1.0), eta_s=eta_s,
                loss=loss, losses=json.dumps(losses), heartbeat_at=now, updated_at=now, phase="training",
            ))
            return True

    def record_frames(self, job_id: str, lease: str, *, done: int, total: int, eta_s: float | None) -> bool:
        """Progress of a camera-path job (frames enhanced of ``total``; no loss, no phase). False
        when this worker no longer owns the job."""
        now = time.time()
        with self.db.tx() as tx:
            return tx.execute(sa.update(jobs).where(self._owned(job_id, lease)).values(
                step=done, total_steps=total, progress=min(max(done / max(total, 1), 0.0), 1.0), eta_s=eta_s,
                heartbeat_at=now, updated_at=now,
            )).rowcount == 1

    def record_phase(self, job_id: str, lease: str, phase: str) -> bool:
        """A running job entered ``phase`` (:data:`PHASES`); evaluating has no ETA. False when
        this worker no longer owns the job."""
        assert phase in PHASES
        now = time.time()
        with self.db.tx() as tx:
            return tx.execute(sa.update(jobs).where(self._owned(job_id, lease)).values(
                phase=phase, eta_s=None if phase == "evaluating" else jobs.c.eta_s,
                heartbeat_at=now, updated_at=now,
            )).rowcount == 1

    def should_stop(self, job_id: str, lease: str) -> bool:
        """True when a cancel was asked or this worker lost the job."""
        with self.db.tx(write=False) as tx:
            row = tx.one(sa.select(jobs.c.cancel_requested, jobs.c.lease, jobs.c.state)
                         .where(jobs.c.id == job_id))
        return row is None or bool(row["cancel_requested"]) or row["lease"] != lease or row["state"] != "running"

    def finish(self, job_id: str, lease: str, state: str, *, error_code: str | None = None,
               error_message: str | None = None, result: dict | None = None,
               checkpoint_path: str | None = None, checkpoint_version: int | None = None) -> bool:
        """End a running job owned by ``lease``; a succeeded job's checkpoint version becomes
        the scene's active one in the same transaction. False if the lease was lost."""
        assert state in TERMINAL_STATES
        now = time.time()
        succeeded = state == "succeeded"
        with self.db.tx() as tx:
            row = tx.one(
                sa.update(jobs).where(self._owned(job_id, lease)).values(
                    state=state, lease=None, phase=None, error_code=error_code, error_message=error_message,
                    result=None if result is None else json.dumps(result),
                    checkpoint_path=checkpoint_path, checkpoint_version=checkpoint_version,
                    finished_at=now, updated_at=now,
                    progress=1.0 if succeeded else jobs.c.progress,
                    eta_s=0.0 if succeeded else jobs.c.eta_s,
                ).returning(jobs.c.scene_id)
            )
            if row is None:
                return False
            if succeeded and checkpoint_version is not None:
                tx.execute(sa.update(scenes).where(scenes.c.id == row["scene_id"])
                           .values(active_version=checkpoint_version))
        return True

    def release(self, job_id: str, lease: str) -> bool:
        """Give a running job back to the queue without using an attempt (worker drain)."""
        now = time.time()
        with self.db.tx() as tx:
            return tx.execute(sa.update(jobs).where(self._owned(job_id, lease)).values(
                state="queued", lease=None, phase=None, heartbeat_at=now, updated_at=now)).rowcount == 1

    def stale_queued(self, *, stale_after: float, now: float | None = None) -> list[str]:
        """Queued jobs nobody took for ``stale_after`` seconds; their clock restarts.

        Their message may have been lost (a worker killed between dequeue and claim, an
        enqueue that failed); re-sending is safe because only one claim can succeed.
        """
        now = time.time() if now is None else now
        with self.db.tx() as tx:
            rows = tx.all(
                sa.update(jobs).where(jobs.c.state == "queued", jobs.c.heartbeat_at < now - stale_after)
                .values(heartbeat_at=now).returning(jobs.c.id)
            )
        return sorted(row["id"] for row in rows)

    def sweep(self, *, stale_after: float, max_attempts: int, now: float | None = None) -> list[SweepAction]:
        """Requeue (attempt + 1) or fail (``worker_lost``) running jobs whose lease expired
        (heartbeat older than ``stale_after`` seconds); a lost job whose cancel was asked ends
        cancelled. Each transition is one conditional UPDATE: a heartbeat that lands first wins."""
        now = time.time() if now is None else now
        cutoff = now - stale_after
        actions: list[SweepAction] = []
        with self.db.tx() as tx:
            stale = tx.all(
                sa.select(jobs.c.id, jobs.c.attempt, jobs.c.cancel_requested, jobs.c.heartbeat_at)
                .where(jobs.c.state == "running", jobs.c.heartbeat_at < cutoff)
            )
            for job in stale:
                expired = sa.update(jobs).where(jobs.c.id == job["id"], jobs.c.state == "running",
                                                jobs.c.heartbeat_at < cutoff)
                if job["cancel_requested"]:
                    n = tx.execute(expired.values(
                        state="cancelled", lease=None, phase=None, finished_at=now, updated_at=now,
                        error_code="cancelled", error_message="cancelled; its worker was lost")).rowcount
                    action = SweepAction(job["id"], "cancelled", job["attempt"])
                elif job["attempt"] >= max_attempts:
                    silent = now - job["heartbeat_at"]
                    n = tx.execute(expired.values(
                        state="failed", lease=None, phase=None, finished_at=now, updated_at=now,
                        error_code="worker_lost",
                        error_message=f"the worker running attempt {job['attempt']} of {max_attempts} "
                                      f"stopped sending heartbeats {silent:.0f} s ago; no attempts left",
                    )).rowcount
                    action = SweepAction(job["id"], "failed", job["attempt"])
                else:
                    n = tx.execute(expired.values(state="queued", lease=None, phase=None, attempt=jobs.c.attempt + 1,
                                                  heartbeat_at=now, updated_at=now)).rowcount
                    action = SweepAction(job["id"], "requeued", job["attempt"] + 1)
                if n == 1:
                    actions.append(action)
        return actions
