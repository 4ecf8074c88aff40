"""``run()``: the API plus an embedded worker, nothing else to install or start.

The worker is a sibling process (``python -m workers``), not a thread: training holds the
GIL and the CPU for minutes, and a crash in it must not take the API down. A supervisor
thread restarts the worker if it dies; Ctrl-C stops the API, then drains the worker (its
running job checkpoints and goes back to the queue).
"""

from __future__ import annotations

import logging
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

log = logging.getLogger("roguenerf.service")

WORKER_RESTART_DELAY_S = 2.0


class EmbeddedWorker:
    """A supervised ``python -m workers`` child process."""

    def __init__(self, settings):
        self.settings = settings
        self.proc: subprocess.Popen | None = None
        self._stopping = threading.Event()
        self._thread = threading.Thread(target=self._supervise, name="worker-supervisor", daemon=True)
        self.restarts = 0

    def _env(self) -> dict[str, str]:
        env = {k: v for k, v in os.environ.items() if not k.startswith("ROGUENERF_")}
        env.update({k: v for k, v in self.settings.env().items() if k != "ROGUENERF_API_KEY"})
        root = str(Path(__file__).resolve().parent.parent)
        env["PYTHONPATH"] = os.pathsep.join(p for p in (root, env.get("PYTHONPATH")) if p)
        return env

    def _spawn(self) -> None:
        # Own session: a terminal's Ctrl-C reaches only the API, which then sends the worker
        # exactly one SIGINT (a second one would make Huey abandon the drain).
        # --parent-pid: the worker exits with this process even when it dies before the worker
        # reached its parent check (PR_SET_PDEATHSIG on Linux; workers/__main__.py).
        self.proc = subprocess.Popen([sys.executable, "-m", "workers", "--exit-with-parent",
                                      "--parent-pid", str(os.getpid())],
                                     env=self._env(), start_new_session=True)
        log.info("embedded worker started (pid %s)", self.proc.pid)

    def start(self) -> None:
        self._spawn()
        self._thread.start()

    def _supervise(self) -> None:
        try:
            self._restart_loop()
        finally:
            # The kernel's parent-death signal follows the *thread* that forked the worker: a
            # worker restarted from here must not get it (a second SIGINT: an abandoned drain)
            # while stop() drains it, so this thread outlives the worker it started.
            proc = self.proc
            if proc is not None:
                proc.wait()

    def _restart_loop(self) -> None:
        while not self._stopping.is_set():
            code = self.proc.poll()
            if code is not None and not self._stopping.is_set():
                log.error("embedded worker exited with code %s; restarting in %.0f s", code,
                          WORKER_RESTART_DELAY_S)
                if self._stopping.wait(WORKER_RESTART_DELAY_S):
                    return
                self.restarts += 1
                self._spawn()
            self._stopping.wait(0.5)

    def stop(self) -> int | None:
        """SIGINT (drain), then SIGTERM, then SIGKILL; returns the exit code."""
        self._stopping.set()
        proc = self.proc
        if proc is None or proc.poll() is not None:
            return None if proc is None else proc.returncode
        for sig, wait_s in ((signal.SIGINT, self.settings.drain_timeout + 5), (signal.SIGTERM, 5.0)):
            try:
                proc.send_signal(sig)
            except ProcessLookupError:
                break
            try:
                return proc.wait(wait_s)
            except subprocess.TimeoutExpired:
                log.warning("embedded worker did not stop after %s; escalating", signal.Signals(sig).name)
        proc.kill()
        return proc.wait()


def run(host: str = "127.0.0.1", port: int = 8000, data_dir: Path | str = Path("./data")) -> None:
    """Serve the API on ``host:port`` with an embedded worker; blocks until Ctrl-C.

    Defaults: SQLite job table and SQLite queue in ``data_dir``; other settings from
    ``ROGUENERF_*`` environment variables (see :class:`service.settings.Settings`).
    """
    import uvicorn

    from service.app import create_app
    from service.settings import Settings

    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    settings = Settings(data_dir=Path(data_dir))
    from jobs.layout import Layout

    Layout(settings.data_dir).ensure()  # a folder of the user's is refused here, in one line, before any start
    app = create_app(settings)
    shown_host = f"[{host}]" if ":" in host else host
    url = f"http://{shown_host}:{port}"

    class _Server(uvicorn.Server):
        async def startup(self, sockets=None):
            await super().startup(sockets=sockets)
            if self.started:
                print(f"RoGUENeRF service ready at {url}  (API docs: {url}/docs; Ctrl-C to stop)",
                      flush=True)

    server = _Server(uvicorn.Config(app, host=host, port=port, log_level="info",
                                    timeout_graceful_shutdown=10))
    worker = EmbeddedWorker(settings)
    worker.start()
    started = time.perf_counter()
    try:
        server.run()
    except KeyboardInterrupt:
        pass  # uvicorn re-raises the Ctrl-C it handled once it has shut down; that is our exit
    finally:
        print("stopping: draining the worker ...", flush=True)
        code = worker.stop()
        log.info("worker exited with %s after %.1f s of service", code, time.perf_counter() - started)
        print("stopped", flush=True)
