"""Load: /enhance runs off the event loop with bounded concurrency (over capacity -> 503 +
Retry-After at once, no queue), /healthz stays fast meanwhile; a full fine-tuning queue ->
503 + Retry-After; a repeated POST with the same Idempotency-Key -> the same job, even when
sent concurrently. Loopback only; every wait is bounded.
"""

from __future__ import annotations

import json
import threading
import time
from collections import Counter
from concurrent.futures import ThreadPoolExecutor

import httpx
import numpy as np

from tests.reliability_helpers import assert_error, assert_healthy, db_rows, post_enhance

CLIENTS = 12
PER_CLIENT = 4
MIN_PROBES = 10  # /healthz samples taken while the clients hammer /enhance


# The shared fixtures' scene and settings: a larger render makes each enhancement long enough
# (tens of ms) to overlap on 2 cores.
TOY_SCENE = {"height": 96, "width": 128}
SERVER = {"enhance_concurrency": 1, "max_queued_jobs": 2}


def test_enhance_over_capacity_is_503_at_once_and_healthz_stays_fast(s):
    view = s.view()
    assert post_enhance(s.client, s.scene_id, render=view["render"], depth=view["depth"],
                        camera=view["camera"]).status_code == 200  # warm the scene's cache
    results: list[tuple[int, float, dict]] = []
    health: list[float] = []
    stop = threading.Event()
    lock = threading.Lock()

    def probe():
        with httpx.Client(base_url=s.live.url, timeout=10) as c:
            while not stop.is_set():
                t = time.perf_counter()
                assert c.get("/healthz").status_code == 200
                health.append(time.perf_counter() - t)
                time.sleep(0.01)

    def hammer(_):
        with httpx.Client(base_url=s.live.url, timeout=60) as c:
            sent = 0
            # PER_CLIENT requests each, and on until the prober has its samples under load
            # (fast enhancements can finish within fewer than MIN_PROBES probes).
            while sent < PER_CLIENT or (len(health) < MIN_PROBES and prober.is_alive()):
                sent += 1
                t = time.perf_counter()
                r = post_enhance(c, s.scene_id, render=view["render"], depth=view["depth"], camera=view["camera"])
                with lock:
                    results.append((r.status_code, time.perf_counter() - t, dict(r.headers)))

    prober = threading.Thread(target=probe)
    prober.start()
    start = time.perf_counter()
    try:
        with ThreadPoolExecutor(CLIENTS) as pool:
            list(pool.map(hammer, range(CLIENTS)))
    finally:
        stop.set()
        prober.join(10)
    wall = time.perf_counter() - start

    codes = Counter(code for code, _, _ in results)
    assert sum(codes.values()) >= CLIENTS * PER_CLIENT
    assert set(codes) <= {200, 503}, codes
    assert codes[200] >= 1 and codes[503] >= 1, codes
    refused = [(sec, h) for code, sec, h in results if code == 503]
    assert all(h["retry-after"] == "1" for _, h in refused)
    refused_p95 = float(np.percentile([sec for sec, _ in refused], 95))
    served_median = float(np.median([sec for code, sec, _ in results if code == 200]))
    # Refusals do not wait for a slot: they come back within about one served request. Since
    # enhancements got ~2x faster, the served time no longer covers the scheduling noise of 12
    # clients on 2 busy cores (one CI run: p95 0.49 s against a 0.15 s median), hence 0.6 s:
    # a refusal that waited for a slot would take a served request per request ahead of it.
    assert refused_p95 < max(0.6, served_median), (refused_p95, served_median)
    health_p95 = float(np.percentile(health, 95))
    assert len(health) >= MIN_PROBES and health_p95 < 0.25, health_p95
    figures = {"requests": len(results), "ok_200": codes[200], "busy_503": codes[503],
               "other": sum(v for k, v in codes.items() if k not in (200, 503)), "clients": CLIENTS,
               "enhance_concurrency": 1, "wall_s": round(wall, 2),
               "served_median_s": round(served_median, 4), "refused_p95_s": round(refused_p95, 4),
               "healthz_probes": len(health), "healthz_p95_s": round(health_p95, 4),
               "healthz_max_s": round(max(health), 4), "render": "128x96"}
    print("\nLOAD FIGURES", json.dumps(figures))  # quoted in docs/reliability.md
    assert_healthy(s.client)


def test_full_finetune_queue_is_503_and_replays_still_answer(s):
    scenes = [s.scene_id] + [s.client.post("/scenes", files={"archive": ("a.zip", s.zip)}).json()["id"]
                             for _ in range(2)]
    first = s.client.post(f"/scenes/{scenes[0]}/finetune", json={"steps": 5}, headers={"Idempotency-Key": "q-1"})
    second = s.client.post(f"/scenes/{scenes[1]}/finetune", json={"steps": 5})
    assert first.status_code == second.status_code == 202
    before = db_rows(s.data_dir)
    full = s.client.post(f"/scenes/{scenes[2]}/finetune", json={"steps": 5})
    message = assert_error(full, 503, "queue_full")
    assert "2 fine-tuning jobs" in message and "limit 2" in message
    assert int(full.headers["Retry-After"]) > 0
    assert db_rows(s.data_dir) == before
    # Replaying an accepted request creates nothing, so a full queue does not refuse it.
    replay = s.client.post(f"/scenes/{scenes[0]}/finetune", json={"steps": 5}, headers={"Idempotency-Key": "q-1"})
    assert replay.status_code == 202 and replay.json()["id"] == first.json()["id"]
    assert s.client.post(f"/jobs/{first.json()['id']}/cancel").json()["state"] == "cancelled"
    third = s.client.post(f"/scenes/{scenes[2]}/finetune", json={"steps": 5})
    assert third.status_code == 202, third.text
    for job in (second, third):
        s.client.post(f"/jobs/{job.json()['id']}/cancel")


def test_concurrent_posts_with_one_idempotency_key_make_one_job(s):
    sid = s.client.post("/scenes", files={"archive": ("a.zip", s.zip)}).json()["id"]
    barrier = threading.Barrier(8)

    def submit(_):
        with httpx.Client(base_url=s.live.url, timeout=60) as c:
            barrier.wait(10)
            return c.post(f"/scenes/{sid}/finetune", json={"minutes": 1.5}, headers={"Idempotency-Key": "same-key"})

    with ThreadPoolExecutor(8) as pool:
        answers = list(pool.map(submit, range(8)))
    assert [r.status_code for r in answers] == [202] * 8, [r.text for r in answers]
    assert len({r.json()["id"] for r in answers}) == 1
    jobs = [row for row in db_rows(s.data_dir)["jobs"] if row[1] == sid]
    assert len(jobs) == 1
    s.client.post(f"/jobs/{answers[0].json()['id']}/cancel")
