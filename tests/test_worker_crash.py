"""kill -9 a worker mid-job: the next worker's sweeper requeues the job and training resumes
from its last checkpoint; with no attempts left the job fails with ``worker_lost``. The
scene's files are untouched either way. Real processes, real SQLite, real HTTP.
"""

from __future__ import annotations

import time

import pytest

from service.settings import Settings
from tests.service_helpers import (
    FAST,
    LiveServer,
    WorkerProcess,
    make_checkpoint,
    make_scene,
    register,
    tree_digest,
    wait_job,
    wait_until,
    zip_folder,
)


@pytest.fixture(scope="module")
def toy(tmp_path_factory):
    root = tmp_path_factory.mktemp("toy")
    make_scene(root / "scene")
    return {"zip": zip_folder(root / "scene"),
            "checkpoint": make_checkpoint(root / "micro.safetensors").read_bytes()}


def _job(client, job_id):
    return client.get(f"/jobs/{job_id}").json()


def test_kill9_requeues_and_resumes_then_fails_when_out_of_attempts(tmp_path, toy):
    data = tmp_path / "data"
    settings = Settings(data_dir=data, max_attempts=2, **FAST)
    workers = []
    with LiveServer(settings) as live, live.client() as c:
        sid = register(c, toy["zip"], toy["checkpoint"]).json()["id"]
        scene_folder = data / "scenes" / sid / "scene"
        before = tree_digest(scene_folder)
        job_id = c.post(f"/scenes/{sid}/finetune", json={"steps": 6}).json()["id"]

        first = WorkerProcess(settings, tmp_path / "w1.log")
        workers.append(first)
        try:
            first.wait_ready()
            wait_until(lambda: (_job(c, job_id)["step"] or 0) >= 2, timeout=120, what="two training steps")
            first.kill9()
            killed = _job(c, job_id)
            assert killed["state"] == "running" and killed["attempt"] == 1
            stale_at = time.time() + settings.heartbeat_timeout

            second = WorkerProcess(settings, tmp_path / "w2.log")
            workers.append(second)
            second.wait_ready()
            requeued_by = wait_until(lambda: _job(c, job_id)["attempt"] == 2 and time.time(),
                                     timeout=60, interval=0.05, what="the sweeper to requeue the job")
            # Requeued no later than one sweeper period after the heartbeat went stale (+ slack).
            assert requeued_by - stale_at <= settings.sweeper_period + 1.5
            done = wait_job(c, job_id, {"succeeded", "failed", "cancelled"}, timeout=150)
            assert done["state"] == "succeeded", done
            assert done["result"]["steps"] == 6 and done["checkpoint_version"] == 2
            assert "resuming finetune from step" in second.log()
            assert c.get(f"/scenes/{sid}").json()["active_version"] == 2

            # Out of attempts: a second kill ends the job failed, with the reason.
            job2 = c.post(f"/scenes/{sid}/finetune", json={"steps": 10_000}).json()["id"]
            wait_until(lambda: (_job(c, job2)["step"] or 0) >= 1, timeout=120, what="job 2 to train")
            second.kill9()
            third = WorkerProcess(Settings(data_dir=data, **{**FAST, "max_attempts": 1}), tmp_path / "w3.log")
            workers.append(third)
            third.wait_ready()
            failed = wait_job(c, job2, {"failed", "succeeded", "cancelled", "queued"}, timeout=60)
            assert failed["state"] == "failed", failed
            assert failed["error"]["code"] == "worker_lost"
            assert "stopped sending heartbeats" in failed["error"]["message"]
            assert tree_digest(scene_folder) == before
            assert c.get(f"/scenes/{sid}").json()["checkpoint_versions"] == [1, 2]
        finally:
            for w in workers:
                w.close()
