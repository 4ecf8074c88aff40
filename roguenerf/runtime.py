"""Process-level settings for fast CPU inference and training.

Two settings measured to matter more than any kernel on this project's CPUs
(``python -m bench.threads``; figures in docs/results.md):

* **Keep freed memory.** glibc returns large freed blocks (>= 128 KiB by default) to the
  OS with ``munmap`` and trims the heap top eagerly; the next forward pass then page-faults
  every activation again (T at 512x512: ~0.5 M faults, ~1 s of system time per forward).
  :func:`configure` raises glibc's mmap and trim thresholds (``mallopt``) so freed blocks are
  reused. Cost: the process keeps its peak heap (bounded by tiling) instead of shrinking.
* **Threads and OpenMP's wait policy.** torch uses one thread per core it may run on
  (``sched_getaffinity``). OpenMP reads its wait policy once, when torch is loaded. Its default
  (spin about 3 ms, then sleep) collapses beside any other busy process: measured
  (``python -m bench.threads``, docs/results.md *Process settings*) the CLI's ``evaluate`` on lego took minutes
  instead of seconds in some processes, and enhancements ran 3-14x slower. ``PASSIVE`` never
  collapsed, at a small price on an idle machine. So every entry point starts with it:
  ``import roguenerf`` calls :func:`prefer_passive_wait` before anything loads torch (the CLI,
  the service, the worker, the benches and library users who import roguenerf before torch),
  unless the user chose a policy (``OMP_WAIT_POLICY`` or ``GOMP_SPINCOUNT`` set;
  ``GOMP_SPINCOUNT=300000`` is libgomp's default). :func:`configure` reports what is in effect.

Nothing here changes results. ``ROGUENERF_KEEP_FREED_MEMORY=0`` turns the allocator change off.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools
import os
import sys
from pathlib import Path

M_TRIM_THRESHOLD = -1
M_MMAP_THRESHOLD = -3
KEEP_BYTES = 1 << 30
"""Freed blocks below this size stay with the process (glibc mallopt thresholds)."""

_applied: dict | None = None


_wait_policy: str | None = None
"""The OpenMP wait policy this process's torch runs with, as decided by the first
:func:`prefer_passive_wait` call (None: not called)."""


def prefer_passive_wait() -> bool:
    """Set ``OMP_WAIT_POLICY=PASSIVE`` for this process and its children, unless the user chose a
    wait policy (``OMP_WAIT_POLICY`` or ``GOMP_SPINCOUNT`` in the environment) or torch is already
    loaded (OpenMP read the environment then; changing it now would only mislead).

    Returns whether PASSIVE is what this process's torch uses. ``import roguenerf`` calls it.
    """
    global _wait_policy
    if _wait_policy is None:
        _wait_policy = wait_policy_in_effect()
        if (_wait_policy == "default" and "torch" not in sys.modules
                and "OMP_WAIT_POLICY" not in os.environ and "GOMP_SPINCOUNT" not in os.environ):
            os.environ["OMP_WAIT_POLICY"] = "PASSIVE"
            _wait_policy = "PASSIVE"
    return _wait_policy == "PASSIVE"


def wait_policy_in_effect() -> str:
    """``OMP_WAIT_POLICY`` (upper case), ``GOMP_SPINCOUNT=N``, or ``default`` (libgomp's spin, then sleep)."""
    policy = os.environ.get("OMP_WAIT_POLICY", "").strip().upper()
    if policy:
        return policy
    if "GOMP_SPINCOUNT" in os.environ:
        return f"GOMP_SPINCOUNT={os.environ['GOMP_SPINCOUNT']}"
    return "default"


@functools.cache
def _glibc_function(name: str):
    """``libc.<name>`` when the C library is glibc-like and has it, else None. Looked up once:
    ``find_library`` runs ``ldconfig`` (~1.4 ms), and the trim is called once per tile."""
    lib = ctypes.util.find_library("c")
    if not lib:
        return None
    try:
        return getattr(ctypes.CDLL(lib), name)
    except (OSError, AttributeError):  # not glibc (musl, macOS): nothing to do
        return None


def keep_freed_memory() -> bool:
    """Make glibc keep freed blocks below :data:`KEEP_BYTES` for reuse; False where unavailable."""
    if os.environ.get("ROGUENERF_KEEP_FREED_MEMORY", "1") == "0":
        return False
    mallopt = _glibc_function("mallopt")
    if mallopt is None:
        return False
    mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    return bool(mallopt(M_MMAP_THRESHOLD, KEEP_BYTES)) and bool(mallopt(M_TRIM_THRESHOLD, KEEP_BYTES))


def release_freed_memory() -> bool:
    """Give the heap's free pages back to the OS now (glibc ``malloc_trim``); False where unavailable.

    Kept freed memory fragments when block sizes vary from one call to the next (each tile of
    a very large image encodes neighbour crops of a different size): without this, the RSS of
    a 4096x3072 enhancement with variant T grew by about 55 MiB a tile, to 9.5 GiB over 88 tiles.
    Called between such tiles, the RSS stays at one tile's working set (bench/memory.py).
    """
    trim = _glibc_function("malloc_trim")
    if trim is None:
        return False
    trim.argtypes = [ctypes.c_size_t]
    return bool(trim(0))


def user_cache_dir(name: str, override: str) -> Path:
    """The folder where the library keeps its ``name`` files for this user: ``$<override>`` when
    set, else ``$XDG_CACHE_HOME/roguenerf/<name>`` (``~/.cache`` by default)."""
    env = os.environ.get(override)
    if env:
        return Path(env)
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "roguenerf" / name


def resident_bytes() -> int | None:
    """The process's resident memory now (Linux ``/proc/self/statm``), None where unknown."""
    try:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError, IndexError, AttributeError):
        return None


TRIM_MARGIN = 384 << 20
"""How much a process may grow by kept freed blocks before :class:`FreedMemoryGuard` trims."""


class FreedMemoryGuard:
    """:func:`release_freed_memory` only once the process has grown by ``margin`` bytes since
    the last trim (the first call always trims): the RSS stays within ``margin`` of a trimmed
    working set, and the pages a trim hands back are not faulted in again tile after tile.

    Trimming between every tile of a 2016 x 1512 view (20 tiles whose neighbour crops differ
    in size) cost 4.2 s of system time against 2.0 with this guard at 384 MiB (5 trims), and
    10.4-11.2 s per view against 9.1-9.9, for a peak of 1.26-1.31 GB instead of 1.20-1.23
    (one process per view, alternated three times; docs/results.md, *Speed at users' sizes*).
    Where the RSS cannot be read, every call trims.
    """

    def __init__(self, margin: int = TRIM_MARGIN, *, rss=resident_bytes, trim=None):
        self.margin = int(margin)
        self._rss = rss
        self._trim = trim or release_freed_memory
        self._base: int | None = None
        self.trims = 0

    def __call__(self) -> bool:
        """Trim if due; whether it trimmed."""
        now = self._rss()
        if now is not None and self._base is not None and now <= self._base + self.margin:
            return False
        self._trim()
        self.trims += 1
        self._base = self._rss()
        return True


def available_cpus() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return os.cpu_count() or 1


def configure(threads: int | None = None) -> dict:
    """Apply the settings once per process (later calls only change ``threads`` when given).

    Returns what is in effect: threads, keep_freed_memory, omp_wait_policy.
    """
    global _applied
    import torch

    if _applied is None:
        _applied = {"keep_freed_memory": keep_freed_memory()}
        if threads is None:
            threads = int(os.environ.get("ROGUENERF_THREADS", "0")) or available_cpus()
    if threads is not None:
        torch.set_num_threads(max(1, int(threads)))
    _applied.update(threads=torch.get_num_threads(), omp_wait_policy=_wait_policy or wait_policy_in_effect())
    return dict(_applied)
