"""No orphaned embedded worker (issue 38, finding 6): `roguenerf serve` stopped by SIGTERM at any
moment of its start-up leaves no worker behind, and a worker whose server is already gone exits
at once instead of taking init for its parent. Real processes, a temp data dir, free ports.
"""

from __future__ import annotations

import os
import random
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.service_helpers import free_port, wait_until

ROOT = Path(__file__).resolve().parents[2]


def _workers_of(parents: set[int], data_root: Path | None = None) -> list[int]:
    """PIDs of live `python -m workers` processes started with --parent-pid in ``parents``, or
    whose data dir (ROGUENERF_DATA_DIR in their environment) lies under ``data_root`` (a /proc
    scan: the worker runs in its own session, so process groups do not find it)."""
    found = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            args = (entry / "cmdline").read_bytes().split(b"\0")
            state = (entry / "stat").read_text().rsplit(")", 1)[1].split()[0]
            environ = (entry / "environ").read_bytes().split(b"\0") if data_root is not None else []
        except OSError:
            continue
        if state == "Z" or b"workers" not in args:
            continue
        ours = False
        if b"--parent-pid" in args:
            k = args.index(b"--parent-pid")
            ours = k + 1 < len(args) and args[k + 1].isdigit() and int(args[k + 1]) in parents
        prefix = f"ROGUENERF_DATA_DIR={data_root}".encode() if data_root is not None else None
        if ours or (prefix is not None and any(v.startswith(prefix) for v in environ)):
            found.append(int(entry.name))
    return found


def _env(data_dir: Path) -> dict:
    env = {k: v for k, v in os.environ.items() if not k.startswith("ROGUENERF_")}
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(ROOT), env.get("PYTHONPATH")) if p)
    env["ROGUENERF_DATA_DIR"] = str(data_dir)
    return env


def _serve(tmp_path: Path, k: int) -> subprocess.Popen:
    data = tmp_path / f"data{k}"
    log = open(tmp_path / f"serve{k}.log", "wb")  # noqa: SIM115 - closed with the process
    return subprocess.Popen([sys.executable, "-m", "roguecli", "serve", "--port", str(free_port()),
                             "--data-dir", str(data)], env=_env(data), cwd=ROOT, stdout=log,
                            stderr=subprocess.STDOUT)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="scans /proc")
def test_a_worker_whose_server_is_already_gone_exits_at_once(tmp_path):
    gone = subprocess.Popen([sys.executable, "-c", "pass"])
    gone.wait()  # a PID that is no longer our parent (nor anyone's, for a while)
    t = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "workers", "--exit-with-parent", "--parent-pid", str(gone.pid)],
                          env=_env(tmp_path / "data"), cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    assert "Traceback" not in proc.stderr and "worker ready" not in proc.stderr
    assert time.perf_counter() - t < 15  # before torch and the queue: nothing was started
    assert not (tmp_path / "data").exists()  # it exited before touching the data dir


@pytest.mark.slow
@pytest.mark.timeout(240)
@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="scans /proc")
def test_serve_stopped_at_random_moments_of_its_start_leaves_no_worker(tmp_path):
    rng = random.Random(38)
    parents: set[int] = set()
    # How long this machine (loaded or not) takes to spawn the worker: the stops are drawn around
    # that moment, where the race was (the server gone before the worker's parent check).
    calibration = _serve(tmp_path, 99)
    parents.add(calibration.pid)
    t0 = time.monotonic()
    try:
        wait_until(lambda: _workers_of({calibration.pid}, tmp_path / "data99"), timeout=60, interval=0.02,
                   what="the worker to start")
        spawn_s = time.monotonic() - t0
    finally:
        calibration.send_signal(signal.SIGTERM)
        calibration.wait(30)
    spawned = 0
    for k in range(20):
        serve = _serve(tmp_path, k)
        parents.add(serve.pid)
        # Random moments of the start-up: before the worker is spawned, just after (while it
        # imports, before uvicorn has its handlers), after the server is ready.
        time.sleep(rng.uniform(0.5 * spawn_s, spawn_s + 1.5))
        spawned += bool(_workers_of({serve.pid}, tmp_path / f"data{k}"))
        serve.send_signal(signal.SIGTERM)
        try:
            serve.wait(30)
        except subprocess.TimeoutExpired:
            serve.kill()
            serve.wait()
    assert spawned >= 5, f"only {spawned} stops came after the worker started: the test tested too little"
    try:
        wait_until(lambda: not _workers_of(parents, tmp_path), timeout=45, what="every embedded worker to exit")
    finally:
        for pid in _workers_of(parents, tmp_path):  # never leave one behind, even when the test fails
            os.kill(pid, signal.SIGKILL)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="scans /proc")
def test_serve_killed_outright_takes_its_worker_with_it(tmp_path):
    serve = _serve(tmp_path, 0)
    try:
        wait_until(lambda: _workers_of({serve.pid}), timeout=60, what="the embedded worker to start")
        time.sleep(0.5)
        serve.kill()  # SIGKILL: no handler runs in the server; the kernel tells the worker
        serve.wait()
        wait_until(lambda: not _workers_of({serve.pid}), timeout=30, what="the worker to exit")
    finally:
        if serve.poll() is None:
            serve.kill()
        for pid in _workers_of({serve.pid}):
            os.kill(pid, signal.SIGKILL)


def test_the_worker_entry_point_is_light_until_its_handlers_are_in():
    """Signal handling and the parent check come before torch, huey and the job table load."""
    code = ("import sys, workers.__main__; "
            "print(sorted(m for m in ('torch', 'huey', 'sqlalchemy', 'roguenerf', 'pydantic') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]"
