"""Several workers, one queue, one job table: what a team runs on several machines.

Two ``python -m workers`` processes on one Redis each take a job; a duplicate message for a
running job is refused by the lease; a worker killed with SIGKILL mid-job is resumed by the
*other* worker from its last checkpoint; and the queue limit holds when 20 clients submit at
once. Real processes, real Redis, real HTTP; the job table on SQLite and on PostgreSQL.
"""

from __future__ import annotations

import re
import shutil
import time
from concurrent.futures import ThreadPoolExecutor

from service.settings import Settings
from tests.service_helpers import (
    FAST,
    LiveServer,
    WorkerProcess,
    get_job,
    redis_server,
    register,
    wait_job,
    wait_until,
)


def _claimed(worker: WorkerProcess) -> set[str]:
    return set(re.findall(r"job ([0-9a-f]{32}): attempt \d+ on scene", worker.log()))


def test_two_workers_share_the_queue_and_the_survivor_resumes_a_killed_job(tmp_path, toy, database_url):
    (tmp_path / "redis").mkdir()
    with redis_server(tmp_path / "redis") as redis_url:
        settings = Settings(data_dir=tmp_path / "data", redis_url=redis_url, database_url=database_url,
                            max_attempts=3, **FAST)
        workers = [WorkerProcess(settings, tmp_path / f"w{i}.log") for i in (1, 2)]
        try:
            with LiveServer(settings) as live, live.client() as c:
                scenes = [register(c, toy["zip"], toy["checkpoint"]).json()["id"] for _ in range(2)]
                for w in workers:
                    w.wait_ready()
                a = c.post(f"/scenes/{scenes[0]}/finetune", json={"steps": 10_000}).json()["id"]
                wait_until(lambda: get_job(c, a)["state"] == "running", timeout=60, what="job A to start")
                # A duplicate message for a running job (a redelivery): the lease refuses it.
                live.app.state.services.queue.enqueue(a)
                b = c.post(f"/scenes/{scenes[1]}/finetune", json={"steps": 10_000}).json()["id"]
                both = wait_until(lambda: all(get_job(c, j)["state"] == "running" and (get_job(c, j)["step"] or 0) >= 1
                                              for j in (a, b)), timeout=120, what="both jobs training at once")
                assert both
                # Each worker took one of them: two processes, one queue.
                owner = {j: [i for i, w in enumerate(workers) if j in _claimed(w)] for j in (a, b)}
                assert sorted(owner[a] + owner[b]) == [0, 1], owner
                wait_until(lambda: "not claimable" in workers[0].log() + workers[1].log(), timeout=30,
                           what="the duplicate message to be refused")
                assert get_job(c, a)["attempt"] == 1  # the duplicate started nothing

                # Stop B, so the survivor is free; let A checkpoint, then SIGKILL A's worker.
                c.post(f"/jobs/{b}/cancel")
                assert wait_job(c, b, {"cancelled", "failed", "succeeded"}, timeout=60)["state"] == "cancelled"
                wait_until(lambda: (get_job(c, a)["step"] or 0) >= 2, timeout=120, what="job A to train")
                time.sleep(3 * settings.checkpoint_every_s + 0.2)
                victim, survivor = workers[owner[a][0]], workers[1 - owner[a][0]]
                killed_at = time.time()
                victim.kill9()
                killed = get_job(c, a)
                assert killed["state"] == "running" and killed["attempt"] == 1
                resumed = wait_until(lambda: (j := get_job(c, a))["attempt"] == 2 and j["state"] == "running"
                                     and (j["step"] or 0) > killed["step"] and j,
                                     timeout=60, interval=0.05, what="the survivor to resume job A")
                failover_s = time.time() - killed_at
                assert "resuming finetune from step" in survivor.log()
                first_after = int(survivor.log().split("resuming finetune from step")[1].split()[0])
                assert 1 <= first_after <= resumed["step"]  # from its checkpoint, not from step 0
                # Lease expiry + one sweeper period + loading the job, with slack for 2 busy cores.
                assert failover_s <= settings.heartbeat_timeout + settings.sweeper_period + 30, failover_s
                print(f"\nFAILOVER {database_url.split(':')[0]}: {failover_s:.2f} s from SIGKILL to "
                      f"resumed steps (heartbeat_timeout {settings.heartbeat_timeout} s)")
                c.post(f"/jobs/{a}/cancel")
                assert wait_job(c, a, {"cancelled", "failed", "succeeded"}, timeout=60)["state"] == "cancelled"
                assert survivor.interrupt(timeout=60) == 0
        finally:
            for w in workers:
                w.close()


def test_twenty_concurrent_submissions_against_a_limit_of_five(tmp_path, toy, database_url):
    # No worker: jobs stay queued. 20 scenes (one registered over HTTP, 19 copies of its
    # row and folder to save 19 uploads), 20 clients POST /finetune at once.
    settings = Settings(data_dir=tmp_path / "data", database_url=database_url, max_queued_jobs=5, **FAST)
    with LiveServer(settings) as live, live.client() as c:
        first = register(c, toy["zip"], toy["checkpoint"]).json()["id"]
        services = live.app.state.services
        row = services.store.get_scene(first)
        scenes = [first]
        for i in range(19):
            sid = f"{i + 1:032x}"
            shutil.copytree(services.layout.scene_dir(first), services.layout.scene_dir(sid))
            services.store.create_scene(sid, views=row["views"], train_views=row["train_views"],
                                        test_views=row["test_views"], width=row["width"],
                                        height=row["height"], active_version=row["active_version"])
            scenes.append(sid)
        clients = [live.client() for _ in scenes]
        try:
            with ThreadPoolExecutor(len(scenes)) as pool:
                answers = list(pool.map(lambda i: clients[i].post(f"/scenes/{scenes[i]}/finetune",
                                                                  json={"steps": 5}), range(len(scenes))))
        finally:
            for client in clients:
                client.close()
        codes = sorted(r.status_code for r in answers)
        assert codes == [202] * 5 + [503] * 15, codes
        assert {r.json()["error"]["code"] for r in answers if r.status_code == 503} == {"queue_full"}
        assert services.store.queued_count() == 5
        assert live.app.state.services.queue.pending() == 5  # one message per accepted job
