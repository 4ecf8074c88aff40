"""Per-stage wall time and FLOPs of the real forward pass, at no cost when not profiling.

The enhancer marks its stages with ``with stage("reprojection"): ...``. Outside a
:class:`StageProfile` that is a no-op (one global read). Inside one, each stage's wall time
and the convolution / matmul FLOPs counted by ``torch.utils.flop_counter.FlopCounterMode`` are
summed per stage name; time spent outside every stage is reported as ``"other"``.

    with StageProfile() as prof:
        model(render, depth, K, pose, neighbours)
    prof.rows()   # [{"stage": "encoders", "seconds": ..., "gflop": ...}, ...]

Stages do not nest: an inner ``stage`` inside an outer one is ignored (it counts to the outer).
"""

from __future__ import annotations

import math
import time
from collections import defaultdict
from contextlib import contextmanager

STAGES = ("encoders", "reprojection", "flow", "attention", "fusion", "merge", "uformer")
"""The stages the enhancer reports, in forward order."""

_active: StageProfile | None = None


def add_flops(flops: float) -> None:
    """Count ``flops`` (2 per multiply-add, as torch counts) of work done outside torch's
    operators (``roguenerf.native``'s kernels) to the active FLOP-counting profile, if any."""
    prof = _active
    if prof is not None and prof._counter is not None:
        prof._kernel_flops += flops


@contextmanager
def stage(name: str):
    """Attribute the time and FLOPs of the enclosed block to ``name`` (when profiling)."""
    prof = _active
    if prof is None or prof._current is not None:
        yield
        return
    prof._enter(name)
    try:
        yield
    finally:
        prof._exit()


def extra_flop_formulas() -> dict:
    """FLOP formulas for the kernels the fast path calls that ``FlopCounterMode`` does not know:
    oneDNN's fused linear / convolution and the CPU flash attention (2 FLOPs per multiply-add,
    as torch counts convs and matmuls). Activations, sampling and element-wise ops are not
    counted, as elsewhere."""
    import torch
    from torch.utils import flop_counter

    def linear(x, w, *args, out_shape=None, **kwargs):
        # _linear_pointwise(x, w, b, attr, scalars, algorithm) or its .binary overload
        # (x, other, w, b, attr): the sum with ``other`` fused; the weight is then the third.
        if len(args) == 3:
            w = args[0]
        return 2 * math.prod(x[:-1]) * x[-1] * w[0]

    def conv(x, w, *args, out_shape=None, **kwargs):
        return flop_counter.conv_flop_count(x, w, out_shape, transposed=False)

    def sdpa(q, k, v, *args, out_shape=None, **kwargs):
        return flop_counter.sdpa_flop_count(q, k, v)

    formulas = {torch.ops.aten._scaled_dot_product_flash_attention_for_cpu: sdpa}
    mkldnn = getattr(torch.ops, "mkldnn", None)
    for name, fn in (("_linear_pointwise", linear), ("_convolution_pointwise", conv)):
        try:
            formulas[getattr(mkldnn, name)] = fn
        except (AttributeError, RuntimeError):
            pass
    return formulas


class StageProfile:
    """Collects per-stage seconds and GFLOP while active (not thread-safe: one forward at a time).

    Args:
        count_flops: also count FLOPs (adds a dispatch hook that slows small ops slightly;
            time and FLOPs are best measured in separate runs).
    """

    def __init__(self, *, count_flops: bool = False):
        self.count_flops = count_flops
        self.seconds: dict[str, float] = defaultdict(float)
        self.flops: dict[str, float] = defaultdict(float)
        self.total_seconds = 0.0
        self._current: str | None = None
        self._counter = None
        self._kernel_flops = 0.0  # FLOPs that code outside torch reported (add_flops)
        self._t0 = self._f0 = 0.0

    def _total_flops(self) -> float:
        counted = float(self._counter.get_total_flops()) if self._counter is not None else 0.0
        return counted + self._kernel_flops

    def _enter(self, name: str) -> None:
        self._current = name
        self._f0 = self._total_flops()
        self._t0 = time.perf_counter()

    def _exit(self) -> None:
        name, self._current = self._current, None
        self.seconds[name] += time.perf_counter() - self._t0
        self.flops[name] += self._total_flops() - self._f0

    def __enter__(self) -> StageProfile:
        global _active
        if _active is not None:
            raise RuntimeError("StageProfile: another profile is already active")
        if self.count_flops:
            from torch.utils.flop_counter import FlopCounterMode

            self._counter = FlopCounterMode(display=False, custom_mapping=extra_flop_formulas())
            self._counter.__enter__()
        _active = self
        self._start = time.perf_counter()
        return self

    def __exit__(self, *exc) -> None:
        global _active
        self.total_seconds += time.perf_counter() - self._start
        _active = None
        if self._counter is not None:
            all_flops = self._total_flops()
            self._counter.__exit__(*exc)
            self.flops["other"] += all_flops - sum(self.flops.values())
            self._counter = None

    def rows(self) -> list[dict]:
        """One dict per stage (forward order, then ``other``): stage, seconds, gflop."""
        names = [s for s in STAGES if s in self.seconds] + sorted(set(self.seconds) - set(STAGES))
        rows = [{"stage": s, "seconds": self.seconds[s], "gflop": self.flops.get(s, 0.0) / 1e9} for s in names]
        other = self.total_seconds - sum(self.seconds.values())
        rows.append({"stage": "other", "seconds": max(other, 0.0), "gflop": self.flops.get("other", 0.0) / 1e9})
        return rows
