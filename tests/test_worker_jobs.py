"""The job table's state machine on a real SQLite file (WAL), without training.

Claims happen once, leases fence stale workers, the sweeper requeues or fails lost jobs by
the clock it is given, at most one active job per scene, idempotency keys, and the worker's
settings-to-TrainConfig mapping.
"""

from __future__ import annotations

import sqlite3
import threading
import time

import pytest

from service.settings import Settings
from workers.db import Database, DatabaseError
from workers.jobs import ActiveJobExists, IdempotencyMismatch, JobStore, SceneBusy
from workers.layout import Layout, copy_atomic, new_id
from workers.tasks import train_options

SCENE = "a" * 32


@pytest.fixture
def store(tmp_path):
    s = JobStore(f"sqlite:///{tmp_path / 'jobs.db'}")
    s.init_schema()
    s.create_scene(SCENE, views=8, train_views=6, test_views=2, width=64, height=48, active_version=1)
    return s


def test_sqlite_is_wal_and_urls_are_checked(store, tmp_path):
    conn = sqlite3.connect(tmp_path / "jobs.db")
    assert conn.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
    with pytest.raises(DatabaseError, match="scheme 'mysql'"):
        Database("mysql://x")
    with pytest.raises(DatabaseError, match="names no file"):
        Database("sqlite:///")
    assert Settings(data_dir=tmp_path).db_url == f"sqlite:///{tmp_path / 'roguenerf.db'}"


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
    results, errors = [], []

    def create():
        try:
            results.append(store.create_job(SCENE, {"steps": 1})[0]["id"])
        except ActiveJobExists:
            errors.append(1)

    threads = [threading.Thread(target=create) for _ in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert len(results) == 1 and len(errors) == 7


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
