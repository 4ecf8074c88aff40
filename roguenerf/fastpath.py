"""The switch between the fast inference paths and the plain reference implementation.

Fast paths (fused oneDNN kernels, channels-last layouts, gather-based bilinear sampling,
target work shared across neighbours) are taken only when no gradient is being recorded and
the tensors are float32 on the CPU; they compute the same function as the plain code to
float32 rounding. Where it is built, :mod:`roguenerf.native` replaces chains of them with fused
C kernels (same function; off in reference mode and in :func:`roguenerf.native.disabled`).
:func:`reference_mode` turns all of them off in the current thread, giving the plain
implementation for tests and benchmarks to compare against. These are the switches;
:func:`roguenerf.ops.backend.pick` reads them and chooses each operation's body.
"""

from __future__ import annotations

import threading
from contextlib import contextmanager

import torch
from torch import Tensor

_state = threading.local()


@contextmanager
def thread_switch(name: str, enabled: bool = True):
    """Inside: the thread-local switch ``name`` is ``enabled`` (read with :func:`switched`);
    nestable, restored on exit."""
    previous = getattr(_state, name, False)
    setattr(_state, name, enabled)
    try:
        yield
    finally:
        setattr(_state, name, previous)


def switched(name: str) -> bool:
    """The thread-local switch ``name`` (False unless a :func:`thread_switch` set it)."""
    return getattr(_state, name, False)


def reference_mode(enabled: bool = True):
    """Inside: the plain (slow) implementation everywhere in this thread. Nestable."""
    return thread_switch("reference", enabled)


def in_reference_mode() -> bool:
    return switched("reference")


def layout_enabled(x: Tensor) -> bool:
    """Channels-last layouts apply, with or without gradient: not in reference mode, float32 on
    the CPU. oneDNN's convolutions with 3-32 channels run forward + backward 15-40 % faster on
    channels-last inputs than on NCHW ones (docs/results.md, *Channels-last convolutions in training*);
    the values are the same to float32 rounding."""
    return not in_reference_mode() and x.device.type == "cpu" and x.dtype == torch.float32


def fast_enabled(x: Tensor) -> bool:
    """Fast paths apply: not in reference mode, no gradient recorded, float32 on the CPU."""
    return (not in_reference_mode() and not torch.is_grad_enabled() and x.device.type == "cpu"
            and x.dtype == torch.float32)
