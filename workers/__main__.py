"""``python -m workers [--data-dir DIR]``: a fine-tuning worker (settings from ROGUENERF_*)."""

from __future__ import annotations

import os
import signal
import sys
import threading

PARENT_PID_ENV = "ROGUENERF_WORKER_PARENT_PID"
"""The embedded worker's parent (``roguenerf serve``) sets its own PID here (or ``--parent-pid``)."""

_parent_pid: int | None = None
_interrupted = threading.Event()


def _parent_gone() -> bool:
    return _parent_pid is not None and os.getppid() != _parent_pid


def _on_signal(signum, frame) -> None:
    # Before the consumer's own handlers: nothing runs yet, so an orphan (its server died
    # during start-up) or a SIGTERM exits at once; a SIGINT with the parent alive is noted
    # and replayed by the consumer (Ctrl-C during start-up neither lost nor a traceback).
    if signum == signal.SIGTERM or _parent_gone():
        raise SystemExit(0)
    _interrupted.set()


def _install_early_handlers(parent_pid: int | None) -> None:
    """Signal handling and the parent's death signal, in place before any heavy import.

    With a parent PID (the embedded worker): on Linux the kernel sends SIGINT (drain) when the
    parent dies (``prctl(PR_SET_PDEATHSIG)``), and a worker whose parent is already gone (it died
    between the fork and here: the worker would take init for its parent) exits at once.
    """
    global _parent_pid
    _parent_pid = parent_pid
    signal.signal(signal.SIGINT, _on_signal)
    signal.signal(signal.SIGTERM, _on_signal)
    if parent_pid is None:
        return
    if sys.platform.startswith("linux"):
        import ctypes

        PR_SET_PDEATHSIG = 1
        try:
            libc = ctypes.CDLL(None, use_errno=True)
            libc.prctl(PR_SET_PDEATHSIG, int(signal.SIGINT), 0, 0, 0)
        except (OSError, AttributeError):  # no prctl: the watch thread below still applies
            pass
    if _parent_gone():  # checked after prctl: a parent dying in between is caught either way
        raise SystemExit(0)
    _watch_parent(parent_pid)


def _parent_from(argv: list[str]) -> int | None:
    """``--parent-pid N`` (or the environment), read before argparse and its imports."""
    value = None
    for k, arg in enumerate(argv):
        if arg == "--parent-pid" and k + 1 < len(argv):
            value = argv[k + 1]
        elif arg.startswith("--parent-pid="):
            value = arg.split("=", 1)[1]
    if value is None:
        value = os.environ.get(PARENT_PID_ENV)
    if value is None and "--exit-with-parent" in argv:
        return os.getppid()
    try:
        return int(value) if value is not None else None
    except ValueError:
        return None


def main(argv: list[str] | None = None) -> None:
    args_in = sys.argv[1:] if argv is None else argv
    _install_early_handlers(_parent_from(args_in))

    import argparse
    import logging

    # Importing roguenerf (first, before torch loads) sets OpenMP's PASSIVE wait policy unless the
    # user chose one: a training job's idle threads then sleep instead of spinning against the API's
    # enhancements on the same cores (roguenerf.runtime, bench/threads.py).
    import roguenerf  # noqa: F401
    from jobs.settings import JobSettings
    from workers.worker import run_worker

    parser = argparse.ArgumentParser(prog="python -m workers", description=__doc__)
    parser.add_argument("--data-dir", help="overrides ROGUENERF_DATA_DIR")
    parser.add_argument("--redis-url", help="overrides ROGUENERF_REDIS_URL")
    parser.add_argument("--database-url", help="overrides ROGUENERF_DATABASE_URL")
    parser.add_argument("--exit-with-parent", action="store_true",
                        help="drain and exit when the parent process dies (embedded worker)")
    parser.add_argument("--parent-pid", type=int,
                        help=f"the parent to exit with (default: ${PARENT_PID_ENV}, else the current parent)")
    args = parser.parse_args(args_in)
    del args.exit_with_parent, args.parent_pid
    overrides = {k: v for k, v in vars(args).items() if v is not None}
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    # From here on SIGINT drains (the consumer replays one noted during start-up); SIGTERM stops.
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    run_worker(JobSettings(**overrides), interrupted=_interrupted)


def _watch_parent(parent: int) -> None:
    """An orphaned embedded worker drains itself (SIGINT) instead of running forever (the
    portable twin of the death signal). ``parent`` is the PID the server gave, never our own
    ``getppid()`` read late (that could already be init)."""
    import time

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(1.0)
        os.kill(os.getpid(), signal.SIGINT)

    threading.Thread(target=watch, name="parent-watch", daemon=True).start()


if __name__ == "__main__":
    main()
