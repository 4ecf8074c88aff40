"""``python -m workers [--data-dir DIR]``: a fine-tuning worker (settings from ROGUENERF_*)."""

from __future__ import annotations

import argparse
import logging

# Importing roguenerf (first, before torch loads) sets OpenMP's PASSIVE wait policy unless the
# user chose one: a training job's idle threads then sleep instead of spinning against the API's
# enhancements on the same cores (roguenerf.runtime, bench/threads.py).
import roguenerf  # noqa: F401


def main(argv: list[str] | None = None) -> None:
    import signal
    import threading

    # Ctrl-C during start-up (importing torch takes seconds) must neither be lost nor end in
    # a traceback: note it here, and the consumer replays it once its own handlers are in.
    interrupted = threading.Event()
    signal.signal(signal.SIGINT, lambda signum, frame: interrupted.set())

    from workers.settings import WorkerSettings
    from workers.worker import run_worker

    parser = argparse.ArgumentParser(prog="python -m workers", description=__doc__)
    parser.add_argument("--data-dir", help="overrides ROGUENERF_DATA_DIR")
    parser.add_argument("--redis-url", help="overrides ROGUENERF_REDIS_URL")
    parser.add_argument("--database-url", help="overrides ROGUENERF_DATABASE_URL")
    parser.add_argument("--exit-with-parent", action="store_true",
                        help="drain and exit when the parent process dies (embedded worker)")
    args = parser.parse_args(argv)
    exit_with_parent = args.exit_with_parent
    del args.exit_with_parent
    overrides = {k: v for k, v in vars(args).items() if v is not None}
    if exit_with_parent:
        _watch_parent()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    run_worker(WorkerSettings(**overrides), interrupted=interrupted)


def _watch_parent() -> None:
    """An orphaned embedded worker drains itself (SIGINT) instead of running forever."""
    import os
    import signal
    import threading
    import time

    parent = os.getppid()

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(1.0)
        os.kill(os.getpid(), signal.SIGINT)

    threading.Thread(target=watch, name="parent-watch", daemon=True).start()


if __name__ == "__main__":
    main()
