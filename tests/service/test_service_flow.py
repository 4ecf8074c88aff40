"""End to end through the embedded server: ``service.server.run()`` in its own process
(API + sibling worker, SQLite job table and queue), driven over real HTTP.

register -> enhance -> fine-tune -> the job succeeds -> enhance uses the new checkpoint ->
delete; a second concurrent fine-tune is refused; cancel mid-run; /enhance equals the
library bit for bit; Ctrl-C stops API and worker. Latency and start-up figures are printed.
"""

from __future__ import annotations

import io
import signal
import statistics
import time

import httpx
import pytest

from tests.service_helpers import (
    EmbeddedServer,
    alive,
    children_of,
    enhance,
    make_checkpoint,
    make_scene,
    register,
    view_request,
    wait_job,
    wait_until,
    zip_folder,
)

FIGURES: dict[str, float] = {}


@pytest.fixture(scope="module")
def embedded(tmp_path_factory):
    data = tmp_path_factory.mktemp("data")
    with EmbeddedServer(data, log_path=data.parent / f"{data.name}-server.log", ready="/readyz") as server:
        FIGURES["start_to_readyz_s"] = server.started_s
        yield server
    print("\nservice figures:", {k: round(v, 3) for k, v in FIGURES.items()})


@pytest.fixture(scope="module")
def client(embedded):
    with httpx.Client(base_url=embedded.url, timeout=180) as c:
        yield c


def _register(client, toy) -> str:
    r = register(client, toy["zip"], toy["checkpoint"])
    assert r.status_code == 201, r.text
    assert r.json()["views"] == 8
    return r.json()["id"]


def test_register_enhance_finetune_enhance_delete(client, toy, embedded):
    from roguenerf import SceneEnhancer, load_checkpoint
    from roguenerf.imageio import read_image

    sid = _register(client, toy)
    view = view_request(toy["scene"], 6)
    first = enhance(client, sid, view)
    assert first.status_code == 200, first.text
    assert first.headers["X-Checkpoint-Version"] == "1"

    r = client.post(f"/scenes/{sid}/finetune", json={"steps": 2})
    assert r.status_code == 202, r.text
    job_id = r.json()["id"]
    clash = client.post(f"/scenes/{sid}/finetune", json={"steps": 2})
    assert clash.status_code == 409 and clash.json()["error"]["code"] == "job_active"

    job = wait_job(client, job_id, {"succeeded", "failed", "cancelled"}, timeout=150)
    assert job["state"] == "succeeded", job
    assert job["progress"] == 1.0 and job["eta_s"] == 0.0
    assert job["step"] == 2 and job["total_steps"] == 2
    assert [s for s, _ in job["recent_losses"]] == [1, 2] and job["loss"] == job["recent_losses"][-1][1]
    assert job["result"]["steps"] == 2 and job["result"]["loss_kind"] == "l1"
    assert job["checkpoint_version"] == 2 and job["error"] is None

    scene = client.get(f"/scenes/{sid}").json()
    assert scene["active_version"] == 2 and scene["checkpoint_versions"] == [1, 2]
    assert scene["active_job"] is None
    folder = embedded.data_dir / "scenes" / sid
    assert (folder / "checkpoints" / "v1.safetensors").read_bytes() == toy["checkpoint"]

    second = enhance(client, sid, view)
    assert second.status_code == 200 and second.headers["X-Checkpoint-Version"] == "2"
    a, b = read_image(first.content), read_image(second.content)
    assert (a - b).abs().max() > 1 / 255, "the fine-tuned checkpoint did not change the output"
    # The new output is exactly what the library computes with the promoted checkpoint.
    model, _ = load_checkpoint(folder / "checkpoints" / "v2.safetensors")
    direct = _direct_png(SceneEnhancer(toy["scene"], model), view)
    assert _same_pixels(second.content, direct)

    assert client.delete(f"/scenes/{sid}").status_code == 204
    assert client.get(f"/scenes/{sid}").status_code == 404
    assert not folder.exists()
    assert not (embedded.data_dir / "jobs" / job_id).exists()


def test_cancel_mid_run(client, toy, embedded):
    sid = _register(client, toy)
    job_id = client.post(f"/scenes/{sid}/finetune", json={"steps": 10_000}).json()["id"]
    running = wait_until(lambda: (j := client.get(f"/jobs/{job_id}").json())["step"] and j,
                         timeout=120, interval=0.2, what="the first training step")
    assert running["state"] == "running" and 0 < running["progress"] < 1 and running["eta_s"] > 0
    r = client.post(f"/jobs/{job_id}/cancel")
    assert r.status_code == 202 and r.json()["cancel_requested"] is True
    job = wait_job(client, job_id, {"cancelled", "succeeded", "failed"}, timeout=60)
    assert job["state"] == "cancelled" and job["error"]["code"] == "cancelled"
    assert job["step"] < 10_000
    assert not (embedded.data_dir / "jobs" / job_id).exists()  # a cancelled job leaves no training state
    scene = client.get(f"/scenes/{sid}").json()
    assert scene["active_version"] == 1 and scene["checkpoint_versions"] == [1]
    again = client.post(f"/jobs/{job_id}/cancel")  # a finished job, cancelled ones included: 409
    assert again.status_code == 409 and again.json()["error"]["code"] == "job_finished"
    assert client.delete(f"/scenes/{sid}").status_code == 204


def _same_pixels(a: bytes, b: bytes) -> bool:
    """Two PNGs decode to exactly the same pixels. (The service compresses its answers faster
    than ``write_png``'s default, so the bytes differ; the image must not.)"""
    import torch

    from roguenerf.imageio import read_image

    return torch.equal(read_image(a), read_image(b))


def _direct_png(enhancer, view: dict) -> bytes:
    """The library call a Python user would make with the same files and camera."""
    import numpy as np
    import torch

    from roguenerf.geometry import intrinsics_matrix, opengl_to_opencv
    from roguenerf.imageio import read_image, write_png

    cam = view["camera"]
    render = read_image(view["render"])
    depth = torch.from_numpy(np.load(io.BytesIO(view["depth"])).astype(np.float32))[None]
    K = intrinsics_matrix(cam["fl_x"], cam["fl_y"], cam["cx"], cam["cy"], dtype=torch.float64)
    pose = opengl_to_opencv(torch.tensor(cam["transform_matrix"], dtype=torch.float64))
    return write_png(None, enhancer.enhance(render, depth, K, pose).image)


def test_enhance_bit_for_bit_and_latency_504x378(client, tmp_path):
    from roguenerf import SceneEnhancer, load_checkpoint

    scene = make_scene(tmp_path / "big", seed=3, height=378, width=504, n_train=2, n_test=1)
    ckpt = make_checkpoint(tmp_path / "micro.safetensors", seed=1)
    r = register(client, zip_folder(tmp_path / "big"), ckpt.read_bytes())
    assert r.status_code == 201, r.text
    sid = r.json()["id"]
    view = view_request(scene, 2)

    warm = enhance(client, sid, view)  # builds the SceneEnhancer and caches neighbour features
    assert warm.status_code == 200, warm.text
    model, _ = load_checkpoint(ckpt)
    enhancer = SceneEnhancer(scene, model)
    direct = _direct_png(enhancer, view)
    assert _same_pixels(warm.content, direct)

    # Interleaved pairs, so both paths see the same machine load; medians reported.
    http_s, server_s, direct_s = [], [], []
    for _ in range(2):
        t0 = time.perf_counter()
        timed = enhance(client, sid, view)
        http_s.append(time.perf_counter() - t0)
        server_s.append(float(timed.headers["X-Enhance-Seconds"]))
        assert _same_pixels(timed.content, direct)
        t0 = time.perf_counter()
        assert _direct_png(enhancer, view) == direct
        direct_s.append(time.perf_counter() - t0)
    FIGURES["http_enhance_504x378_s"] = statistics.median(http_s)
    FIGURES["http_enhance_504x378_server_compute_s"] = statistics.median(server_s)
    FIGURES["direct_enhance_504x378_s"] = statistics.median(direct_s)
    assert client.delete(f"/scenes/{sid}").status_code == 204


def test_ctrl_c_stops_api_and_worker(embedded):
    proc = embedded.proc
    workers = children_of(proc.pid)
    assert len(workers) == 1 and alive(workers[0])
    t0 = time.perf_counter()
    proc.send_signal(signal.SIGINT)
    assert proc.wait(60) == 0
    FIGURES["ctrl_c_shutdown_s"] = time.perf_counter() - t0
    wait_until(lambda: not alive(workers[0]), timeout=10, what="the worker to exit")
    log = embedded.log_path.read_text()
    assert "API docs: http://127.0.0.1:" in log and "/docs" in log
    assert "stopped" in log
