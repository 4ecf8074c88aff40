"""The one job lifecycle (``jobs/lifecycle.py``) with stand-in task bodies, no training: how a
claimed job ends for every kind (succeeded, failed, cancelled, requeued, lost, invalid_input,
internal_error), on a real SQLite job table and data directory.

The real tasks run through it in ``test_service_paths.py``, ``test_service_import.py``,
``test_worker_crash.py`` and the other worker tests; here each ending is checked on its own.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from jobs.db import DatabaseError
from jobs.layout import SERVER_PATH, Layout, new_id
from jobs.lifecycle import JobRun, JobStopped, Task, WorkerContext, run_job
from jobs.settings import JobSettings
from jobs.store import JobStore
from roguenerf import InputError


@pytest.fixture
def ctx(tmp_path):
    settings = JobSettings(data_dir=tmp_path / "data", heartbeat_period=0.05, heartbeat_timeout=5)
    layout = Layout(settings.data_dir)
    layout.ensure()
    store = JobStore(settings.db_url)
    store.init_schema()
    enqueued: list[str] = []
    context = WorkerContext(settings=settings, store=store, layout=layout, enqueue=enqueued.append)
    context.enqueued = enqueued
    yield context
    store.db.close()


def _job(ctx, request=None) -> dict:
    scene = new_id()
    ctx.store.create_scene(scene, views=2, train_views=1, test_views=1, width=4, height=4, active_version=0)
    job, _ = ctx.store.create_job(scene, request if request is not None else {"kind": "x"})
    (ctx.layout.job_dir(job["id"]) / "input").mkdir(parents=True)
    return job


def _run(ctx, body, job=None) -> tuple[str, dict]:
    job = job or _job(ctx)
    outcome = run_job(ctx, job["id"], {"x": Task(body, label="test job", work="test")}, default="x")
    return outcome, ctx.store.get_job(job["id"])


def test_succeed_writes_plain_json_and_removes_the_folder_unless_kept(ctx):
    outcome, job = _run(ctx, lambda run: run.succeed({"loss": float("nan"), "file": Path("/x/y"), "n": 3}))
    assert outcome == "succeeded" and job["state"] == "succeeded" and job["progress"] == 1.0
    assert job["result"] == {"loss": None, "file": "/x/y", "n": 3}
    assert not ctx.layout.job_dir(job["id"]).exists()
    outcome, job = _run(ctx, lambda run: run.succeed({}, keep_files=True))
    assert outcome == "succeeded" and (ctx.layout.job_dir(job["id"]) / "input").is_dir()


def test_a_failure_message_names_no_server_path(ctx):
    def body(run: JobRun) -> str:
        run.root, run.root_name = run.job_dir / "input", "the path archive"
        return run.fail("bad_input", f"{run.root / 'camera.json'}: broken; {run.root} is bad; "
                                     f"see {run.layout.root / 'roguenerf.db'}")

    outcome, job = _run(ctx, body)
    assert outcome == "failed" and job["state"] == "failed" and job["error_code"] == "bad_input"
    assert job["error_message"] == f"camera.json: broken; the path archive is bad; see {SERVER_PATH}"
    assert ctx.layout.job_dir(job["id"]).is_dir()  # kept unless the task cleans on failure


def test_clean_on_failure_and_aliases(ctx):
    def body(run: JobRun) -> str:
        run.aliases["/tmp/somewhere/scene"], run.clean_on_failure = "the imported scene", True
        return run.fail("invalid_input", "/tmp/somewhere/scene has no train views")

    outcome, job = _run(ctx, body)
    assert outcome == "failed" and job["error_message"] == "the imported scene has no train views"
    assert not ctx.layout.job_dir(job["id"]).exists()


def test_a_stop_after_a_cancel_ends_cancelled_and_removes_the_folder(ctx):
    def body(run: JobRun) -> str:
        ctx.store.request_cancel(run.id)
        assert run.should_stop()
        raise JobStopped("after 3 frames")

    outcome, job = _run(ctx, body)
    assert outcome == "cancelled" and job["state"] == "cancelled"
    assert (job["error_code"], job["error_message"]) == ("cancelled", "cancelled after 3 frames")
    assert not ctx.layout.job_dir(job["id"]).exists()


def test_a_stop_while_the_worker_drains_requeues_without_an_attempt(ctx):
    def body(run: JobRun) -> str:
        ctx.draining.set()
        assert run.should_stop()
        raise JobStopped("at step 7")

    outcome, job = _run(ctx, body)
    assert outcome == "requeued" and job["state"] == "queued" and job["attempt"] == 1 and job["lease"] is None
    assert ctx.enqueued == [job["id"]] and ctx.layout.job_dir(job["id"]).is_dir()  # resume state kept


def test_a_refused_progress_write_means_the_lease_is_lost(ctx):
    def body(run: JobRun) -> str:
        run.record(lambda job_id, lease, **values: False, done=1)
        assert run.beat.lost.is_set() and run.should_stop()
        raise JobStopped("at step 1")

    outcome, job = _run(ctx, body)
    assert outcome == "lost" and job["state"] == "running"  # the job is another worker's now: untouched


def test_a_failed_progress_write_is_logged_not_fatal(ctx):
    def write(job_id, lease, **values):
        raise OSError("disk busy")

    def body(run: JobRun) -> str:
        run.record(write, done=1)
        assert not run.beat.lost.is_set()
        run.record(ctx.store.record_frames, done=2, total=4, eta_s=1.0)
        return run.succeed({})

    outcome, job = _run(ctx, body)
    assert outcome == "succeeded" and (job["step"], job["total_steps"]) == (2, 4)


def test_a_stop_without_a_reason_is_an_internal_error(ctx):
    def body(run: JobRun) -> str:
        raise JobStopped("at step 2")

    outcome, job = _run(ctx, body)
    assert outcome == "failed" and job["error_code"] == "internal_error"
    assert job["error_message"] == "test stopped without a reason at step 2"


def test_library_refusals_are_invalid_input_and_crashes_internal_errors(ctx):
    def refused(run: JobRun) -> str:
        raise InputError(f"{run.root / 'depths' / 'a.npy'}: missing file")

    outcome, job = _run(ctx, refused)
    assert outcome == "failed" and job["error_code"] == "invalid_input"
    assert job["error_message"] == "depths/a.npy: missing file"

    def crashed(run: JobRun) -> str:
        raise ValueError("boom")

    outcome, job = _run(ctx, crashed)
    assert outcome == "failed" and (job["error_code"], job["error_message"]) == ("internal_error", "ValueError: boom")


def test_an_unreachable_job_table_leaves_the_job_to_the_sweeper(ctx):
    def body(run: JobRun) -> str:
        raise DatabaseError("job database: connection refused")

    job = _job(ctx)
    with pytest.raises(DatabaseError):
        _run(ctx, body, job)
    assert ctx.store.get_job(job["id"])["state"] == "running"


def test_claim_once_and_the_default_kind(ctx):
    seen = []

    def body(run: JobRun) -> str:
        seen.append(run.request)
        return run.succeed({})

    job = _job(ctx, {"steps": 3})  # no kind: the default task's
    assert _run(ctx, body, job)[0] == "succeeded" and seen == [{"steps": 3}]
    assert _run(ctx, body, job)[0] == "skipped" and len(seen) == 1  # not queued any more
