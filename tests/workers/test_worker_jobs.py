"""The job table's state machine, without training, on a real SQLite file (WAL) and on a real
PostgreSQL server (Debian's, on loopback): every store test runs on both.

Claims happen once (also when two workers race), leases fence stale workers, the sweeper
requeues or fails lost jobs by the clock it is given, at most one active job per scene, the
queue limit holds under concurrent submissions, idempotency keys, schema versions and
upgrades (v3: the job's phase), the newest-first keyset listings of scenes and jobs, and the
worker's settings-to-TrainConfig mapping.
"""

from __future__ import annotations

import sqlite3
import threading
import time

import pytest
import sqlalchemy as sa

from jobs.db import Database, DatabaseError
from jobs.layout import Layout, copy_atomic, new_id
from jobs.store import (
    SCHEMA_VERSION,
    ActiveJobExists,
    IdempotencyMismatch,
    JobStore,
    QueueFull,
    SceneBusy,
)
from service.settings import Settings
from workers.tasks import train_options

SCENE = "a" * 32


def _scene(store, scene_id=SCENE):
    store.create_scene(scene_id, views=8, train_views=6, test_views=2, width=64, height=48, active_version=1)


@pytest.fixture
def store(database_url):
    s = JobStore(database_url)
    s.init_schema()
    _scene(s)
    yield s
    s.db.close()


def _race(n: int, fn, *, timeout: float = 60) -> list:
    """Run ``fn(i)`` in ``n`` threads released together; returns their results (exceptions
    included, as values). Bounded: a thread still running after ``timeout`` fails the test."""
    barrier = threading.Barrier(n)
    results: list = [None] * n

    def run(i):
        barrier.wait(timeout)
        try:
            results[i] = fn(i)
        except Exception as exc:  # noqa: BLE001 - collected for the assertions
            results[i] = exc

    threads = [threading.Thread(target=run, args=(i,), daemon=True) for i in range(n)]
    for t in threads:
        t.start()
    deadline = time.monotonic() + timeout
    for t in threads:
        t.join(max(0.0, deadline - time.monotonic()))
    assert not any(t.is_alive() for t in threads), "racing threads did not finish in time"
    return results


def test_sqlite_is_wal_and_urls_are_checked(tmp_path):
    JobStore(f"sqlite:///{tmp_path / 'jobs.db'}").init_schema()
    conn = sqlite3.connect(tmp_path / "jobs.db")
    assert conn.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
    with pytest.raises(DatabaseError, match="scheme 'mysql'"):
        Database("mysql://x")
    with pytest.raises(DatabaseError, match="names no file"):
        Database("sqlite:///")
    with pytest.raises(DatabaseError, match="psycopg"):
        Database("postgresql+asyncpg://u@h/db")
    # Plain postgresql:// (what users write) goes through psycopg 3, not psycopg2.
    assert Database("postgresql://u:secret@127.0.0.1:1/db").engine.url.drivername == "postgresql+psycopg"
    assert Database("postgres://u@127.0.0.1:1/db").kind == "postgresql"
    assert Settings(data_dir=tmp_path).db_url == f"sqlite:///{tmp_path / 'roguenerf.db'}"


def test_unreachable_postgres_is_a_database_error_without_password(tmp_path):
    from tests.service_helpers import free_port

    db = Database(f"postgresql://u:secret@127.0.0.1:{free_port()}/db")
    with pytest.raises(DatabaseError, match="job database") as info:
        db.ping()
    assert "secret" not in str(info.value)


def test_backend_is_the_one_asked_for(store, database_url):
    assert store.db.kind == database_url.split(":")[0]
    with store.db.tx(write=False) as tx:
        assert tx.conn.dialect.name == store.db.kind


def test_one_active_job_per_scene_and_idempotency(store):
    job, created = store.create_job(SCENE, {"steps": 5}, idempotency_key="key")
    assert created and job["state"] == "queued" and job["attempt"] == 1
    same, created = store.create_job(SCENE, {"steps": 5}, idempotency_key="key")
    assert not created and same["id"] == job["id"]
    with pytest.raises(IdempotencyMismatch, match="different request"):
        store.create_job(SCENE, {"steps": 6}, idempotency_key="key")
    with pytest.raises(ActiveJobExists) as info:
        store.create_job(SCENE, {"steps": 5})
    assert info.value.job_id == job["id"]
    with pytest.raises(SceneBusy):
        store.delete_scene(SCENE)
    assert store.request_cancel(job["id"])["state"] == "cancelled"
    second, created = store.create_job(SCENE, {"minutes": 1.0})
    assert created and second["id"] != job["id"]


def test_concurrent_creates_make_exactly_one_job(store):
    results = _race(8, lambda i: store.create_job(SCENE, {"steps": 1})[0]["id"])
    created = [r for r in results if isinstance(r, str)]
    refused = [r for r in results if isinstance(r, ActiveJobExists)]
    assert len(created) == 1 and len(refused) == 7, results
    assert {r.job_id for r in refused} == set(created)


def test_queue_limit_holds_under_concurrent_submissions(store, database_url):
    # 20 submissions for 20 scenes at once through 20 stores (as 20 API processes would):
    # exactly 5 wait, 15 are refused with the count they saw; nothing else is inserted.
    scene_ids = [f"{i:032x}" for i in range(1, 21)]
    for sid in scene_ids:
        _scene(store, sid)
    stores = [JobStore(database_url) for _ in scene_ids]
    try:
        results = _race(20, lambda i: stores[i].create_job(scene_ids[i], {"steps": 1}, max_queued=5))
    finally:
        for s in stores:
            s.db.close()
    created = [r for r in results if isinstance(r, tuple)]
    full = [r for r in results if isinstance(r, QueueFull)]
    assert len(created) == 5 and len(full) == 15, results
    assert all((r.waiting, r.limit) == (5, 5) for r in full)
    assert store.queued_count() == 5
    # A slot frees when a job is taken; the limit counts waiting jobs only.
    assert store.claim(created[0][0]["id"], "lease") is not None
    refused_scene = next(scene_ids[i] for i, r in enumerate(results) if isinstance(r, QueueFull))
    assert store.create_job(refused_scene, {"steps": 1}, max_queued=5)[1] is True
    with pytest.raises(QueueFull):
        store.create_job(SCENE, {"steps": 1}, max_queued=5)


def test_two_workers_racing_for_one_job_exactly_one_wins(store, database_url):
    # Two workers (two stores, two connection pools) claim the same queued job at the same
    # instant, 15 times over: every time exactly one gets the lease.
    other = JobStore(database_url)
    try:
        for round_ in range(15):
            job, _ = store.create_job(SCENE, {"steps": round_ + 1})
            workers = (store, other)
            results = _race(2, lambda i, workers=workers, job=job: workers[i].claim(job["id"], f"lease-{i}"))
            won = [r for r in results if r is not None]
            assert len(won) == 1, results
            assert not any(isinstance(r, Exception) for r in results), results
            row = store.get_job(job["id"])
            assert row["state"] == "running" and row["lease"] == won[0]["lease"] and row["attempt"] == 1
            store.request_cancel(job["id"])
            assert store.finish(job["id"], row["lease"], "cancelled")
    finally:
        other.db.close()


def test_two_sweepers_requeue_a_lost_job_once(store, database_url):
    other = JobStore(database_url)
    try:
        job, _ = store.create_job(SCENE, {"steps": 5})
        store.claim(job["id"], "dead")
        t0 = store.get_job(job["id"])["heartbeat_at"]
        sweepers = (store, other)
        results = _race(2, lambda i: sweepers[i].sweep(stale_after=10, max_attempts=3, now=t0 + 11))
        assert sorted(len(r) for r in results) == [0, 1], results
        assert store.get_job(job["id"])["attempt"] == 2
    finally:
        other.db.close()


LEGACY_SCHEMA = [
    # What the hand-written SQL layer (before schema versions) created.
    """CREATE TABLE scenes (id TEXT PRIMARY KEY, created_at DOUBLE PRECISION NOT NULL,
        views INTEGER NOT NULL, train_views INTEGER NOT NULL, test_views INTEGER NOT NULL,
        width INTEGER NOT NULL, height INTEGER NOT NULL, active_version INTEGER NOT NULL,
        next_version INTEGER NOT NULL)""",
    """CREATE TABLE jobs (id TEXT PRIMARY KEY, scene_id TEXT NOT NULL, state TEXT NOT NULL,
        request TEXT NOT NULL, idempotency_key TEXT UNIQUE, attempt INTEGER NOT NULL, lease TEXT,
        cancel_requested INTEGER NOT NULL, progress DOUBLE PRECISION NOT NULL, step INTEGER,
        total_steps INTEGER, eta_s DOUBLE PRECISION, loss DOUBLE PRECISION, losses TEXT,
        error_code TEXT, error_message TEXT, result TEXT, base_version INTEGER, checkpoint_path TEXT,
        checkpoint_version INTEGER, created_at DOUBLE PRECISION NOT NULL,
        updated_at DOUBLE PRECISION NOT NULL, started_at DOUBLE PRECISION,
        finished_at DOUBLE PRECISION, heartbeat_at DOUBLE PRECISION)""",
    "CREATE UNIQUE INDEX jobs_one_active_per_scene ON jobs (scene_id) WHERE state IN ('queued', 'running')",
    "CREATE INDEX jobs_by_state ON jobs (state)",
    "INSERT INTO scenes VALUES ('" + SCENE + "', 1.0, 8, 6, 2, 64, 48, 1, 2)",
    "INSERT INTO jobs (id, scene_id, state, request, attempt, cancel_requested, progress, created_at,"
    " updated_at, heartbeat_at) VALUES ('" + "b" * 32 + "', '" + SCENE + "', 'queued', '{\"steps\": 3}',"
    " 1, 0, 0, 1.0, 1.0, 1.0)",
]


def _indexes(db: Database) -> set[str]:
    with db.tx(write=False) as tx:
        return {i["name"] for i in sa.inspect(tx.conn).get_indexes("jobs")}


def _columns(db: Database, table: str = "jobs") -> set[str]:
    with db.tx(write=False) as tx:
        return {c["name"] for c in sa.inspect(tx.conn).get_columns(table)}


def _legacy_database(database_url: str, *statements: str, version: int | None = None) -> Database:
    """A database made by an older release: the v1 schema (LEGACY_SCHEMA), then ``statements``;
    with ``version``, the schema_version table saying so."""
    db = Database(database_url)
    with db.tx() as tx:
        for statement in LEGACY_SCHEMA + list(statements):
            tx.conn.exec_driver_sql(statement)
        if version is not None:
            tx.conn.exec_driver_sql("CREATE TABLE schema_version (id INTEGER PRIMARY KEY, version INTEGER NOT NULL,"
                                    " upgraded_at DOUBLE PRECISION NOT NULL)")
            tx.conn.exec_driver_sql(f"INSERT INTO schema_version VALUES (1, {version}, 1.0)")
    return db


def test_schema_is_versioned_and_a_legacy_database_is_upgraded(database_url):
    legacy = _legacy_database(database_url)
    assert "jobs_by_scene_created" not in _indexes(legacy)
    store = JobStore(database_url)
    assert store.init_schema() == 0  # no version table: the legacy schema, adopted as v1
    assert store.schema_version() == SCHEMA_VERSION == 4
    assert "jobs_by_scene_created" in _indexes(store.db)  # the v2 step ran
    assert {"jobs_by_created", "phase"} <= _indexes(store.db) | _columns(store.db)  # and v3
    assert "name" in _columns(store.db, "scenes")  # and v4
    job = store.get_job("b" * 32)
    assert job["request"] == {"steps": 3} and job["state"] == "queued"  # rows kept
    with pytest.raises(ActiveJobExists):  # and the v1 constraints still hold
        store.create_job(SCENE, {"steps": 1})
    assert store.init_schema() == SCHEMA_VERSION  # idempotent
    # A database upgraded by a newer roguenerf is refused, not misread.
    with store.db.tx() as tx:
        tx.conn.exec_driver_sql("UPDATE schema_version SET version = 99")
    with pytest.raises(DatabaseError, match="version 99, newer"):
        JobStore(database_url).init_schema()
    for db in (legacy, store.db):
        db.close()


def test_processes_starting_together_create_the_schema_once(database_url):
    stores = [JobStore(database_url) for _ in range(4)]
    try:
        found = _race(4, lambda i: stores[i].init_schema())
        assert sorted(found) == [0, 4, 4, 4], found
        assert stores[0].schema_version() == SCHEMA_VERSION
    finally:
        for s in stores:
            s.db.close()


def test_a_v2_database_gets_the_phase_column(database_url):
    """Schema v3 adds jobs.phase (training / evaluating) to a table made by v1/v2, rows kept."""
    old = _legacy_database(database_url, "CREATE INDEX jobs_by_scene_created ON jobs (scene_id, created_at)",
                           version=2)
    assert "phase" not in _columns(old)
    store = JobStore(database_url)
    assert store.init_schema() == 2
    assert store.init_schema() == 4  # idempotent
    assert "phase" in _columns(store.db) and "jobs_by_created" in _indexes(store.db)
    job = store.get_job("b" * 32)
    assert job["phase"] is None and job["request"] == {"steps": 3}
    assert store.claim(job["id"], "lease")
    assert store.record_phase(job["id"], "lease", "evaluating")
    assert store.get_job(job["id"])["phase"] == "evaluating"
    for db in (old, store.db):
        db.close()


def test_a_v3_database_gets_scene_names(database_url):
    """Schema v4 adds scenes.name to a v3 table: old scenes keep their rows and have no name;
    new ones store theirs; deleting a scene removes its finished jobs' rows too."""
    old = _legacy_database(database_url, "ALTER TABLE jobs ADD COLUMN phase TEXT", version=3)
    with old.tx() as tx:
        tx.conn.exec_driver_sql("INSERT INTO scenes (id, created_at, views, train_views, test_views, width,"
                                f" height, active_version, next_version) VALUES ('{'c' * 32}', 1.0, 3, 2, 1,"
                                " 8, 6, 0, 1)")
    assert "name" not in _columns(old, "scenes")
    store = JobStore(database_url)
    assert store.init_schema() == 3
    assert store.init_schema() == 4 == store.schema_version()
    assert "name" in _columns(store.db, "scenes")
    assert store.get_scene("c" * 32)["name"] is None and store.get_scene("c" * 32)["views"] == 3
    named = store.create_scene("d" * 32, views=2, train_views=1, test_views=1, width=8, height=6,
                               active_version=0, name="Caf\u00e9 kitchen")
    assert named["name"] == "Caf\u00e9 kitchen"
    names = [s["name"] for s in store.list_scenes()]
    assert names[0] == "Caf\u00e9 kitchen" and names[1:] == [None, None]  # the legacy scenes
    job, _ = store.create_job("d" * 32, {"steps": 1})
    with pytest.raises(SceneBusy):
        store.delete_scene_and_jobs("d" * 32)
    store.request_cancel(job["id"])
    assert store.delete_scene_and_jobs("d" * 32) == [job["id"]]
    assert store.get_job(job["id"]) is None and store.get_scene("d" * 32) is None
    assert store.delete_scene_and_jobs("d" * 32) is None
    assert store.get_job("b" * 32) is not None  # another scene's job is kept
    for db in (old, store.db):
        db.close()


def test_phase_follows_the_running_job(store):
    job, _ = store.create_job(SCENE, {"steps": 3})
    assert store.get_job(job["id"])["phase"] is None
    assert store.claim(job["id"], "L1")
    assert store.record_phase(job["id"], "L1", "evaluating")
    assert store.get_job(job["id"])["phase"] == "evaluating" and store.get_job(job["id"])["eta_s"] is None
    assert store.record_progress(job["id"], "L1", step=1, total_steps=3, fraction=1 / 3, eta_s=2.0, loss=0.5)
    row = store.get_job(job["id"])
    assert row["phase"] == "training" and row["eta_s"] == 2.0
    assert store.record_phase(job["id"], "L1", "evaluating")
    assert store.get_job(job["id"])["eta_s"] is None  # evaluating: no ETA
    assert not store.record_phase(job["id"], "other", "training")  # fenced by the lease
    assert store.release(job["id"], "L1")
    assert store.get_job(job["id"])["phase"] is None  # queued again: no phase
    assert store.claim(job["id"], "L2") and store.record_phase(job["id"], "L2", "training")
    assert store.finish(job["id"], "L2", "succeeded")
    assert store.get_job(job["id"])["phase"] is None


def test_listings_newest_first_keyset_paginated_and_filtered(store):
    scene_ids = [SCENE] + [new_id() for _ in range(4)]
    for scene_id in scene_ids[1:]:
        _scene(store, scene_id)
    # Scenes: newest first; equal timestamps are ordered by id (the keyset's tie-break).
    listed = store.list_scenes(limit=50)
    assert [s["id"] for s in listed] == [s["id"] for s in sorted(
        listed, key=lambda s: (s["created_at"], s["id"]), reverse=True)]
    assert {s["id"] for s in listed} == set(scene_ids)
    seen, before = [], None
    while True:
        page = store.list_scenes(limit=2, before=before)
        if not page:
            break
        seen += [s["id"] for s in page]
        before = (page[-1]["created_at"], page[-1]["id"])
    assert seen == [s["id"] for s in listed]
    assert len(store.list_scenes(limit=10_000)) == 5 and len(store.list_scenes(limit=0)) == 1  # clamped

    # Jobs: a cancelled and a queued one on scene 0, a running one on scene 1.
    j0, _ = store.create_job(scene_ids[0], {"steps": 1})
    store.request_cancel(j0["id"])
    j1, _ = store.create_job(scene_ids[1], {"steps": 1})
    assert store.claim(j1["id"], "L")
    j2, _ = store.create_job(scene_ids[0], {"steps": 2})
    order = [j["id"] for j in sorted((store.get_job(j["id"]) for j in (j0, j1, j2)),
                                     key=lambda j: (j["created_at"], j["id"]), reverse=True)]

    def ids(**kw):
        return [j["id"] for j in store.list_jobs(**kw)]

    assert ids() == order
    assert ids(scene_id=scene_ids[0]) == [i for i in order if i != j1["id"]]
    assert ids(states=("queued", "running")) == [i for i in order if i != j0["id"]]
    assert ids(scene_id=scene_ids[0], states=["queued"]) == [j2["id"]]
    assert ids(scene_id="f" * 32) == [] and ids(states=("failed",)) == []
    first = store.list_jobs(limit=2)
    assert [j["id"] for j in first] == order[:2] and first[0]["request"] is not None  # rows decoded
    assert ids(limit=2, before=(first[-1]["created_at"], first[-1]["id"])) == order[2:]
    assert store.active_jobs(scene_ids[:3]) == {scene_ids[0]: j2["id"], scene_ids[1]: j1["id"]}
    assert store.active_jobs([]) == {}


def test_claim_once_and_lease_fencing(store):
    job, _ = store.create_job(SCENE, {"steps": 5})
    assert store.claim(job["id"], "lease-a")["state"] == "running"
    assert store.claim(job["id"], "lease-b") is None
    assert store.record_progress(job["id"], "lease-a", step=1, total_steps=5, fraction=0.2, eta_s=4.0, loss=0.5)
    assert not store.record_progress(job["id"], "lease-b", step=9, total_steps=5, fraction=1, eta_s=0, loss=0)
    assert not store.should_stop(job["id"], "lease-a")
    assert store.should_stop(job["id"], "lease-b")
    assert not store.finish(job["id"], "lease-b", "succeeded", checkpoint_version=2)
    row = store.get_job(job["id"])
    assert row["state"] == "running" and row["step"] == 1 and row["losses"] == [[1, 0.5]]
    store.request_cancel(job["id"])
    assert store.get_job(job["id"])["state"] == "running"
    assert store.should_stop(job["id"], "lease-a")


def test_recent_losses_are_bounded(store):
    job, _ = store.create_job(SCENE, {"steps": 50})
    store.claim(job["id"], "l")
    for step in range(1, 31):
        store.record_progress(job["id"], "l", step=step, total_steps=50, fraction=step / 50, eta_s=1.0,
                              loss=1.0 / step)
    losses = store.get_job(job["id"])["losses"]
    assert [s for s, _ in losses] == list(range(11, 31))


def test_success_promotes_version_atomically(store):
    job, _ = store.create_job(SCENE, {"steps": 5})
    store.claim(job["id"], "l")
    version = store.allocate_version(SCENE)
    assert version == 2 and store.allocate_version(SCENE) == 3
    assert store.finish(job["id"], "l", "succeeded", result={"steps": 5}, checkpoint_version=version)
    assert store.get_scene(SCENE)["active_version"] == 2
    row = store.get_job(job["id"])
    assert row["state"] == "succeeded" and row["progress"] == 1.0 and row["lease"] is None
    assert store.allocate_version("b" * 32) is None


def test_sweeper_requeues_then_fails(store):
    job, _ = store.create_job(SCENE, {"steps": 5})
    store.claim(job["id"], "l1")
    t0 = store.get_job(job["id"])["heartbeat_at"]
    assert store.sweep(stale_after=10, max_attempts=2, now=t0 + 5) == []
    (action,) = store.sweep(stale_after=10, max_attempts=2, now=t0 + 11)
    assert (action.action, action.attempt) == ("requeued", 2)
    row = store.get_job(job["id"])
    assert row["state"] == "queued" and row["attempt"] == 2 and row["lease"] is None
    assert store.should_stop(job["id"], "l1")  # the presumed-dead worker is fenced out
    store.claim(job["id"], "l2")
    t1 = store.get_job(job["id"])["heartbeat_at"]
    (action,) = store.sweep(stale_after=10, max_attempts=2, now=t1 + 11)
    assert action.action == "failed"
    row = store.get_job(job["id"])
    assert row["state"] == "failed" and row["error_code"] == "worker_lost"
    assert "attempt 2 of 2" in row["error_message"]


def test_sweeper_ends_lost_cancelled_job_as_cancelled(store):
    job, _ = store.create_job(SCENE, {"steps": 5})
    store.claim(job["id"], "l")
    store.request_cancel(job["id"])
    t0 = store.get_job(job["id"])["heartbeat_at"]
    (action,) = store.sweep(stale_after=1, max_attempts=3, now=t0 + 2)
    assert action.action == "cancelled" and store.get_job(job["id"])["state"] == "cancelled"


def test_drain_release_keeps_attempt_and_stale_queued_resend(store):
    job, _ = store.create_job(SCENE, {"steps": 5})
    store.claim(job["id"], "l")
    assert store.release(job["id"], "l")
    row = store.get_job(job["id"])
    assert row["state"] == "queued" and row["attempt"] == 1
    now = time.time()
    assert store.stale_queued(stale_after=60, now=now) == []
    assert store.stale_queued(stale_after=60, now=now + 61) == [job["id"]]
    assert store.stale_queued(stale_after=60, now=now + 62) == []  # its clock restarted


def test_layout_ids_and_atomic_copy(tmp_path):
    layout = Layout(tmp_path)
    layout.ensure()
    with pytest.raises(ValueError, match="32-hex-digit"):
        layout.scene_dir("../etc")
    sid = new_id()
    src = tmp_path / "src.bin"
    src.write_bytes(b"weights")
    copy_atomic(src, layout.checkpoint(sid, 3))
    copy_atomic(src, layout.checkpoint(sid, 1))
    assert layout.versions(sid) == [1, 3]
    assert [p.name for p in layout.checkpoint(sid, 1).parent.iterdir() if p.name.startswith(".")] == []


def test_train_options_follow_settings(tmp_path):
    from roguenerf import TrainConfig

    settings = Settings(data_dir=tmp_path, finetune_crop=32, finetune_batch=2, checkpoint_every_s=5,
                        finetune_lr=1e-3)
    config = TrainConfig(**train_options(TrainConfig, settings, {"minutes": 2.5}))
    assert (config.minutes, config.steps, config.crop, config.batch) == (2.5, None, 32, 2)
    assert (config.checkpoint_every_s, config.lr) == (5, 1e-3)
    default_lr = TrainConfig(**train_options(TrainConfig, Settings(data_dir=tmp_path), {"steps": 3})).lr
    assert default_lr == TrainConfig().lr


def test_settings_refuse_inconsistent_heartbeats(tmp_path):
    with pytest.raises(ValueError, match="heartbeat_timeout"):
        Settings(data_dir=tmp_path, heartbeat_period=5, heartbeat_timeout=5)


def test_workers_package_never_imports_service():
    # Statically: no module of workers/ names the service package ...
    import ast
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[2]
    offenders = []
    for path in sorted((root / "workers").glob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            names = ([a.name for a in node.names] if isinstance(node, ast.Import)
                     else [node.module or ""] if isinstance(node, ast.ImportFrom) else [])
            offenders += [f"{path.name}: {n}" for n in names if n == "service" or n.startswith("service.")]
    assert offenders == []
    # ... and at run time, importing all of it (the worker's entry point included) loads none of it.
    code = ("import sys, workers.__main__, workers.worker, workers.tasks, jobs.store, jobs.settings; "
            "print(sorted(m for m in sys.modules if m == 'service' or m.startswith('service.') "
            "or m.startswith('fastapi')))")
    out = subprocess.run([sys.executable, "-c", code], cwd=root, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]"


def test_stale_temp_files_of_a_killed_writer_are_swept_at_start(tmp_path):
    import os

    from workers.worker import build_worker

    layout = Layout(tmp_path / "data")
    layout.ensure()
    sid = new_id()
    ckpts = layout.checkpoint(sid, 1).parent
    ckpts.mkdir(parents=True)
    old_upload = layout.tmp / new_id()
    (old_upload / "scene").mkdir(parents=True)
    (old_upload / "scene" / "a.png").write_bytes(b"x")
    old_copy = ckpts / f".v2.safetensors.{new_id()}.tmp"   # copy_atomic's temp name
    old_copy.write_bytes(b"partial")
    live_upload = layout.tmp / new_id()                     # another machine's upload in progress
    live_upload.mkdir()
    (live_upload / "archive.zip").write_bytes(b"y")
    kept = [ckpts / "v1.safetensors", ckpts / ".hidden-but-not-ours.tmp"]
    for path in kept:
        path.write_bytes(b"keep")
    hours_ago = time.time() - 7 * 3600
    for path in [old_upload, old_upload / "scene", old_upload / "scene" / "a.png", old_copy, *kept]:
        os.utime(path, (hours_ago, hours_ago))
    # A live upload whose folder is old but whose file is still being written is kept too.
    os.utime(live_upload, (hours_ago, hours_ago))

    settings = Settings(data_dir=tmp_path / "data")
    assert settings.stale_temp_after_s == 6 * 3600
    build_worker(settings)[2].db.close()
    assert not old_upload.exists() and not old_copy.exists()
    assert live_upload.is_dir() and all(p.exists() for p in kept)
    # The API sweeps at start the same way.
    from service.app import _open

    old_copy.write_bytes(b"again")
    os.utime(old_copy, (hours_ago, hours_ago))
    _open(settings).store.db.close()
    assert not old_copy.exists() and live_upload.is_dir()
