"""The same job flow with RedisHuey: Debian's redis-server on a loopback port (no
persistence), the API in this process, the worker as a separate process. Also: SIGINT
drains a running job back to the queue (its attempt not counted) and the next worker
resumes it; /readyz reports the queue down when Redis goes away. The job table on a SQLite
file and on a real PostgreSQL server.
"""

from __future__ import annotations

from roguenerf.imageio import read_image
from service.settings import Settings
from tests.service_helpers import (
    FAST,
    LiveServer,
    WorkerProcess,
    enhance,
    redis_server,
    register,
    view_request,
    wait_job,
    wait_until,
)


def test_redis_job_flow_drain_and_readiness(tmp_path, toy, database_url):
    (tmp_path / "redis").mkdir()
    redis = redis_server(tmp_path / "redis")
    url = redis.__enter__()
    data = tmp_path / "data"
    settings = Settings(data_dir=data, redis_url=url, database_url=database_url, **FAST)
    workers = []
    try:
        with LiveServer(settings) as live, live.client() as c:
            ready = c.get("/readyz")
            assert ready.status_code == 200 and ready.json()["queue"] == "redis"
            sid = register(c, toy["zip"], toy["checkpoint"]).json()["id"]
            view = view_request(toy["scene"], 6)
            before = enhance(c, sid, view)
            assert before.status_code == 200

            first = WorkerProcess(settings, tmp_path / "w1.log")
            workers.append(first)
            job_id = c.post(f"/scenes/{sid}/finetune", json={"steps": 2}).json()["id"]
            assert c.post(f"/scenes/{sid}/finetune", json={"steps": 2}).status_code == 409
            job = wait_job(c, job_id, {"succeeded", "failed", "cancelled"}, timeout=150)
            assert job["state"] == "succeeded", job
            after = enhance(c, sid, view)
            assert after.headers["X-Checkpoint-Version"] == "2"
            assert (read_image(after.content) - read_image(before.content)).abs().max() > 1 / 255
            assert not (data / "queue.db").exists()  # the queue really is Redis

            # SIGINT drains: the running job checkpoints and goes back to the queue.
            job2 = c.post(f"/scenes/{sid}/finetune", json={"steps": 10_000}).json()["id"]
            wait_until(lambda: (c.get(f"/jobs/{job2}").json()["step"] or 0) >= 1, timeout=120,
                       what="job 2 to train")
            assert first.interrupt(timeout=60) == 0
            drained = c.get(f"/jobs/{job2}").json()
            assert drained["state"] == "queued" and drained["attempt"] == 1, drained
            assert "worker draining; requeued" in first.log()

            second = WorkerProcess(settings, tmp_path / "w2.log")
            workers.append(second)
            step_at_drain = drained["step"]
            wait_until(lambda: (c.get(f"/jobs/{job2}").json()["step"] or 0) > step_at_drain, timeout=120,
                       what="job 2 to resume")
            assert "resuming finetune from step" in second.log()
            c.post(f"/jobs/{job2}/cancel")
            assert wait_job(c, job2, {"cancelled", "failed", "succeeded"}, timeout=60)["state"] == "cancelled"
            assert second.interrupt(timeout=60) == 0

            redis.__exit__(None, None, None)
            redis = None
            down = c.get("/readyz")
            assert down.status_code == 503
            assert down.json()["error"]["code"] == "not_ready" and "queue" in down.json()["error"]["message"]
            refused = c.post(f"/scenes/{sid}/finetune", json={"steps": 2})
            assert refused.status_code == 503 and refused.json()["error"]["code"] == "queue_unavailable"
            assert c.get(f"/scenes/{sid}").json()["active_job"] is None  # the refused job left no row
    finally:
        for w in workers:
            w.close()
        if redis is not None:
            redis.__exit__(None, None, None)
