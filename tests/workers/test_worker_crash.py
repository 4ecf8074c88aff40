"""kill -9 a worker mid-job: the next worker's sweeper requeues the job and training resumes
from its last checkpoint; with no attempts left the job fails with ``worker_lost``. The
scene's files are untouched either way. Real processes, real HTTP, the job table on a SQLite
file and on a real PostgreSQL server.
"""

from __future__ import annotations

import time

import pytest

from service.settings import Settings
from tests.service_helpers import (
    FAST,
    LiveServer,
    WorkerProcess,
    get_job,
    register,
    tree_digest,
    wait_job,
    wait_until,
)


def test_kill9_requeues_and_resumes_then_fails_when_out_of_attempts(tmp_path, toy, database_url):
    data = tmp_path / "data"
    settings = Settings(data_dir=data, database_url=database_url, max_attempts=2, **FAST)
    workers = [WorkerProcess(settings, tmp_path / "w1.log")]  # starts while the scene uploads
    with LiveServer(settings) as live, live.client() as c:
        try:
            sid = register(c, toy["zip"], toy["checkpoint"]).json()["id"]
            scene_folder = data / "scenes" / sid / "scene"
            before = tree_digest(scene_folder)
            job_id = c.post(f"/scenes/{sid}/finetune", json={"steps": 10_000}).json()["id"]
            workers[0].wait_ready()
            wait_until(lambda: (get_job(c, job_id)["step"] or 0) >= 2, timeout=120, what="two training steps")
            # Fast steps can reach step 2 before the first periodic save (every 0.2 s): give
            # it time, so there is a saved step > 0 for the next worker to resume from.
            time.sleep(3 * settings.checkpoint_every_s + 0.2)
            workers[0].kill9()
            killed = get_job(c, job_id)
            assert killed["state"] == "running" and killed["attempt"] == 1
            stale_at = time.time() + settings.heartbeat_timeout

            second = WorkerProcess(settings, tmp_path / "w2.log")
            workers.append(second)
            second.wait_ready()
            ready_at = time.time()
            requeued_by = wait_until(lambda: get_job(c, job_id)["attempt"] == 2 and time.time(),
                                     timeout=60, interval=0.05, what="the sweeper to requeue the job")
            # Requeued within one sweeper period of the heartbeat going stale (or of the new
            # worker's start, whichever is later), plus polling slack.
            assert requeued_by - max(stale_at, ready_at) <= settings.sweeper_period + 1.0
            # Training resumes from the saved state, not from step 0.
            resumed = wait_until(lambda: (j := get_job(c, job_id))["state"] == "running" and
                                 (j["step"] or 0) > killed["step"] and j, timeout=120, what="resumed steps")
            assert "resuming finetune from step" in second.log()
            first_after = int(second.log().split("resuming finetune from step")[1].split()[0])
            assert 1 <= first_after <= resumed["step"]

            # Killed again with no attempts left: the job fails with the reason.
            second.kill9()
            third = WorkerProcess(settings, tmp_path / "w3.log")
            workers.append(third)
            failed = wait_job(c, job_id, {"failed", "succeeded", "cancelled"}, timeout=90)
            assert failed["state"] == "failed", failed
            assert failed["error"]["code"] == "worker_lost" and failed["attempt"] == 2
            assert "stopped sending heartbeats" in failed["error"]["message"]
            assert tree_digest(scene_folder) == before
            scene = c.get(f"/scenes/{sid}").json()
            assert scene["active_version"] == 1 and scene["checkpoint_versions"] == [1]
            assert scene["active_job"] is None
        finally:
            for w in workers:
                w.close()


@pytest.mark.parametrize("delay", [0.5, 1.5])
def test_ctrl_c_during_worker_startup_stops_it_promptly(tmp_path, delay):
    # `./dev serve` then Ctrl-C at once: the API sends its worker one SIGINT, which may land
    # while the worker is still importing torch. It must still stop (nothing to drain yet),
    # not wait for the API's drain timeout and a SIGTERM.
    worker = WorkerProcess(Settings(data_dir=tmp_path / "data", **FAST), tmp_path / "worker.log")
    try:
        time.sleep(delay)
        assert worker.proc.poll() is None, worker.log()
        t = time.perf_counter()
        code = worker.interrupt(timeout=60)
        assert code == 0, worker.log()
        assert time.perf_counter() - t < 30, worker.log()
    finally:
        worker.close()
