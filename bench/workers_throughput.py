"""Small fine-tuning jobs per hour with 1 and 2 workers on one Redis queue and one PostgreSQL job
table, and the failover time after a SIGKILL.

    python -m bench.workers_throughput [--jobs 6] [--steps 40] [--workers 1 2]
                                       [--output bench/results/workers_throughput.json]

Everything real, as in a team's set-up on one machine: Debian's redis-server and PostgreSQL on
loopback (temp dirs), the API (uvicorn, in this process), ``python -m workers`` processes. Per
worker count: a fresh data dir, Redis and database; ``--jobs`` toy scenes (64 x 48, 6 training
views, a micro checkpoint) registered over HTTP; every worker started and ready; then the clock
runs from submitting the ``--jobs`` jobs (``--steps`` steps each, crop 32, batch 1, no
evaluation) until all have succeeded. jobs/hour = jobs / wall * 3600.

Failover: two workers, one long job; after it has saved a checkpoint its worker gets SIGKILL;
measured until the other worker trains past the killed step (heartbeat timeout 2.5 s, sweeper
every 0.5 s, as in the tests; the production defaults are 60 s and 15 s, so expect about
heartbeat_timeout + sweeper_period/2 + a few seconds there).

Writes the JSON (date, machine, commit, settings, per-run figures) to ``--output``.
"""

from __future__ import annotations

import argparse
import shutil
import tempfile
import time
from pathlib import Path

from bench.common import stamp, write_json
from service.settings import Settings
from tests import service_helpers as helpers

REPO = Path(__file__).resolve().parents[1]


def _settings(root: Path, redis_url: str, db_url: str) -> Settings:
    return Settings(data_dir=root / "data", redis_url=redis_url, database_url=db_url, max_attempts=3, **helpers.FAST)


def throughput(pg: helpers.PostgresServer, toy: dict, root: Path, *, n_workers: int, jobs: int, steps: int) -> dict:
    (root / "redis").mkdir(parents=True)
    with helpers.redis_server(root / "redis") as redis_url:
        settings = _settings(root, redis_url, pg.new_database())
        workers = [helpers.WorkerProcess(settings, root / f"w{i}.log") for i in range(n_workers)]
        try:
            with helpers.LiveServer(settings) as live, live.client() as c:
                scenes = [helpers.register(c, toy["zip"], toy["checkpoint"]).json()["id"] for _ in range(jobs)]
                for w in workers:
                    w.wait_ready(timeout=180)
                t0 = time.perf_counter()
                ids = [c.post(f"/scenes/{sid}/finetune", json={"steps": steps}).json()["id"] for sid in scenes]
                done = [helpers.wait_job(c, j, {"succeeded", "failed", "cancelled"}, timeout=1800) for j in ids]
                wall = time.perf_counter() - t0
            assert all(j["state"] == "succeeded" for j in done), [j["state"] for j in done]
            per_worker = [w.log().count(": attempt ") for w in workers]
        finally:
            for w in workers:
                w.close()
    return {"workers": n_workers, "jobs": jobs, "steps_per_job": steps, "wall_s": round(wall, 2),
            "jobs_per_hour": round(jobs / wall * 3600, 1), "jobs_taken_per_worker": per_worker}


def failover(pg: helpers.PostgresServer, toy: dict, root: Path) -> dict:
    (root / "redis").mkdir(parents=True)
    with helpers.redis_server(root / "redis") as redis_url:
        settings = _settings(root, redis_url, pg.new_database())
        workers = [helpers.WorkerProcess(settings, root / f"w{i}.log") for i in range(2)]
        try:
            with helpers.LiveServer(settings) as live, live.client() as c:
                sid = helpers.register(c, toy["zip"], toy["checkpoint"]).json()["id"]
                for w in workers:
                    w.wait_ready(timeout=180)
                job = c.post(f"/scenes/{sid}/finetune", json={"steps": 100_000}).json()["id"]
                helpers.wait_until(lambda: (c.get(f"/jobs/{job}").json()["step"] or 0) >= 2, timeout=120,
                                   what="training")
                time.sleep(3 * settings.checkpoint_every_s + 0.2)
                victim = next(w for w in workers if job in w.log())
                killed_at = time.perf_counter()
                victim.kill9()
                step = c.get(f"/jobs/{job}").json()["step"]
                helpers.wait_until(lambda: (j := c.get(f"/jobs/{job}").json())["attempt"] == 2
                                   and (j["step"] or 0) > step,
                                   timeout=120, interval=0.05, what="resumed on the other worker")
                seconds = time.perf_counter() - killed_at
                c.post(f"/jobs/{job}/cancel")
        finally:
            for w in workers:
                w.close()
    return {"failover_s": round(seconds, 2), "heartbeat_timeout_s": settings.heartbeat_timeout,
            "sweeper_period_s": settings.sweeper_period, "checkpoint_every_s": settings.checkpoint_every_s}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--jobs", type=int, default=6)
    parser.add_argument("--steps", type=int, default=40)
    parser.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--output", type=Path, default=REPO / "bench" / "results" / "workers_throughput.json")
    args = parser.parse_args()
    root = Path(tempfile.mkdtemp(prefix="roguenerf-bench-workers-"))
    try:
        toy = helpers.toy_upload(root / "toy")
        with helpers.PostgresServer() as pg:
            runs = []
            for n in args.workers:
                runs.append(throughput(pg, toy, root / f"run{n}", n_workers=n, jobs=args.jobs, steps=args.steps))
                print(runs[-1], flush=True)
            fail = failover(pg, toy, root / "failover")
            print(fail, flush=True)
    finally:
        shutil.rmtree(root, ignore_errors=True)
    out = {**stamp(), "queue": "redis", "database": "postgresql",
           "job": {"scene": "toy 64x48, 6 train + 2 test views", "model": "micro",
                   "crop": helpers.FAST["finetune_crop"], "batch": helpers.FAST["finetune_batch"], "evaluate": False},
           "throughput": runs, "failover": fail}
    write_json(args.output, out)
    print(f"wrote {args.output}")


if __name__ == "__main__":
    main()
