"""The one place that chooses which body of an operation runs.

Every operation of :mod:`roguenerf.ops` has up to four bodies that compute the same function
(to float32 rounding; ``tests/unit/roguenerf/native/test_fastpath.py``, ``tests/unit/roguenerf/native/test_native.py``):

* ``NATIVE``: a fused C kernel of :mod:`roguenerf.native`: no gradient recorded, float32 CPU
  tensors, the kernels built and not :func:`roguenerf.native.disabled`;
* ``FAST``: torch's fast path (oneDNN fused kernels, channels-last, gather sampling): no
  gradient recorded, float32 CPU tensors;
* ``TORCH``: the torch operators that also serve training and other dtypes / devices (fused
  scaled-dot-product attention, channels-last convolutions), outside reference mode;
* ``REFERENCE``: the plain implementation, the ground truth of the equality tests, inside
  :func:`roguenerf.fastpath.reference_mode`.

:func:`pick` applies these rules to an operation's tensors; an op that has no body of some
kind takes the next one down (NATIVE -> FAST -> TORCH -> REFERENCE).
"""

from __future__ import annotations

import enum

import torch
from torch import Tensor

from roguenerf import native
from roguenerf.fastpath import in_reference_mode


class Body(enum.Enum):
    NATIVE = "native"
    FAST = "fast"
    TORCH = "torch"
    REFERENCE = "reference"

    @property
    def fast(self) -> bool:
        """No gradient, float32 CPU, not reference mode: the native or the torch fast body."""
        return self in (Body.NATIVE, Body.FAST)


def pick(*tensors: Tensor, allow_native: bool = True) -> Body:
    """The body an operation on ``tensors`` runs: NATIVE where every tensor takes the kernels
    (:func:`roguenerf.native.enabled`) and ``allow_native``, else FAST where every tensor
    takes the fast path (:func:`roguenerf.fastpath.fast_enabled`), else TORCH outside
    reference mode, else REFERENCE."""
    # fast_enabled(t) and native.enabled(t) for every t, with the switches read once (this runs
    # some 70 times per forward)
    if in_reference_mode():
        return Body.REFERENCE
    if torch.is_grad_enabled():
        return Body.TORCH
    for t in tensors:
        if t.dtype != torch.float32 or not t.is_cpu:
            return Body.TORCH
    if allow_native and not native.is_disabled() and native.library() is not None:
        return Body.NATIVE
    return Body.FAST


def as_channels_last(x: Tensor) -> Tensor:
    """``x`` in the channels-last layout the C kernels read (no copy when it is already)."""
    return x.contiguous(memory_format=torch.channels_last)


def as_contiguous(x: Tensor | None) -> Tensor | None:
    """``x`` row-major contiguous, as the C kernels read it (None stays None)."""
    return x.contiguous() if x is not None else None
