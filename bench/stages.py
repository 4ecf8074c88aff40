"""Per-stage profile of the whole enhancement: time, FLOPs and FLOP efficiency per stage.

    python -m bench.stages --output bench/results/stages.csv [--variants micro,nano,T,S,B]
                            [--sizes 378x504,512x512] [--repeats 3] [--no-reference]

For each variant and size, one enhancement with 5 neighbours whose sampling sources are cached
(as ``SceneEnhancer`` serves a scene), ``torch.inference_mode``, torch's default threads (one
per core), glibc keeping freed memory (``roguenerf.runtime.configure``). Stages are the ones
the enhancer marks (``roguenerf.profiling``): encoders, reprojection, flow, attention, fusion,
merge, uformer, other.

Columns per stage:
  seconds            median over ``--repeats`` timed runs of the fast path (after one warm-up)
  seconds_torch_fast the present fast path with its fused C kernels off (``native.disabled()``):
                     torch operators only, as on a machine without a C compiler
                     (the two paths' runs alternate, run by run; the fast path before issue
                     12's inference work, once a third column, is at the git tag
                     ``pre-ops-dispatch``)
  gb_moved           GB the stage's operators read and write (every aten operator's tensor
                     arguments and outputs: the code as written, each operator streaming its
                     operands; views free; a fused C kernel of roguenerf.native counts its
                     operands once; its few FLOPs, elementwise, are not counted)
  floor_s            max(gflop_executed / peak, gb_moved / bandwidth): the stage's roofline floor
                     as written, bandwidth = best copy GB/s of a 256 MiB tensor (read + write)
  seconds_reference  the plain implementation (``reference_mode()``: no fused kernels, NCHW,
                     grid_sample, unshared target work, per-call masks), same weights and inputs
  gflop_model        FLOPs of the architecture as written (counted on the reference path:
                     convolutions and matmuls, attention included; 2 per multiply-add)
  gflop_executed     FLOPs the fast path executes (it shares target work across neighbours)
  efficiency         gflop_model / seconds / peak, where peak is the best float32 matmul
                     GFLOP/s (2048^3, best of 5) measured in this run, before and after
Also per configuration: ``max_abs_diff`` between the fast and reference outputs, and one row
``uformer_official``: the official Uformer architecture alone on RGB input (T: 5.23 M
parameters), reference path, the size's input - the issue's yardstick.

Writes the CSV (date, machine, commit on every row), a JSON summary next to it (must-show
figures: T at 512x512) and a PNG plot. Weights are random with the zero-initialised layers
randomised too (speed does not depend on weights; the flow is then non-zero).
"""

from __future__ import annotations

import argparse
import math
import statistics
import time
from pathlib import Path

import torch

from bench.common import beside, save_figure, stamp, write_csv, write_json
from roguenerf import native, runtime
from roguenerf.fastpath import reference_mode
from roguenerf.models import VARIANTS, NeighbourBatch, Uformer, build_enhancer
from roguenerf.profiling import STAGES, StageProfile

NEIGHBOURS = 5


def matmul_peak(n: int = 2048, repeats: int = 5) -> float:
    """Best float32 matmul GFLOP/s of ``repeats`` runs (n x n times n x n)."""
    a, b = torch.randn(n, n), torch.randn(n, n)
    a @ b
    best = math.inf
    for _ in range(repeats):
        t = time.perf_counter()
        a @ b
        best = min(best, time.perf_counter() - t)
    return 2 * n**3 / best / 1e9


def memory_bandwidth(mib: int = 256, repeats: int = 5) -> float:
    """Best GB/s of ``repeats`` copies of a ``mib`` MiB float32 tensor into another (bytes read
    + bytes written), torch's threads: what a memory-bound op can stream, far beyond the caches."""
    src = torch.rand(mib * 2**18)
    dst = torch.empty_like(src)
    dst.copy_(src)
    best = math.inf
    for _ in range(repeats):
        t = time.perf_counter()
        dst.copy_(src)
        best = min(best, time.perf_counter() - t)
    return 2 * src.numel() * 4 / best / 1e9


def _stage_bytes(fn) -> dict:
    """Bytes each stage's operators read and write, per stage: the sum over every aten operator
    run inside the stage of its tensor arguments' and outputs' bytes (each operator as if it
    streamed its operands from memory: what the code as written moves, not what a fused kernel
    would). Views and metadata-only operators count 0."""
    from torch.utils._python_dispatch import TorchDispatchMode
    from torch.utils._pytree import tree_flatten

    from roguenerf import profiling

    free = {"view", "_unsafe_view", "reshape", "permute", "transpose", "t", "expand", "slice", "select",
            "unsqueeze", "squeeze", "as_strided", "alias", "detach", "split", "chunk", "unbind",
            "split_with_sizes", "lift_fresh", "empty", "empty_like", "empty_strided", "unfold",
            "_reshape_alias", "narrow", "view_as", "resize_", "set_", "is_nonzero", "_local_scalar_dense"}
    counts: dict[str, float] = {}

    def add(key: str, nbytes: float) -> None:
        counts[key] = counts.get(key, 0.0) + nbytes

    def native_bytes(_name: str, nbytes: int) -> None:  # a fused C kernel: its operands once
        active = profiling._active
        add((active._current if active is not None else None) or "other", nbytes)

    class Bytes(TorchDispatchMode):
        def __torch_dispatch__(self, func, types, args=(), kwargs=None):
            out = func(*args, **(kwargs or {}))
            name = func.overloadpacket.__name__
            if name not in free:
                seen, total = set(), 0
                for t in tree_flatten((args, kwargs or {}, out))[0]:
                    if isinstance(t, torch.Tensor) and id(t) not in seen:
                        seen.add(id(t))
                        total += t.numel() * t.element_size()
                active = profiling._active
                add((active._current if active is not None else None) or "other", total)
            return out

    native.on_call = native_bytes
    try:
        with StageProfile() as _, Bytes():
            fn()
    finally:
        native.on_call = None
    return {k: v / 1e9 for k, v in counts.items()}


def randomise_zero_layers(model, std: float = 0.02) -> None:
    """The output projection and flow increment head start at 0; give them weights."""
    with torch.no_grad():
        layer = model.uformer.output_proj if model.uformer is not None else model.to_rgb
        layer.weight.normal_(0, std)
        if model.flow is not None:
            model.flow.to_delta[-1].weight.normal_(0, 1e-3)


def make_inputs(model, h: int, w: int, n: int = NEIGHBOURS):
    """A target render of a wall ~4 units away and ``n`` neighbours beside it, their sampling
    sources cached as ``SceneEnhancer`` caches them. Call under inference mode."""
    g = torch.Generator().manual_seed(0)
    f = 0.9 * w
    K = torch.tensor([[f, 0.0, w / 2], [0.0, f, h / 2], [0.0, 0.0, 1.0]])
    render = torch.rand(1, 3, h, w, generator=g)
    depth = 4.0 + 0.2 * torch.rand(1, 1, h, w, generator=g)
    poses = torch.eye(4).repeat(n + 1, 1, 1)
    poses[1:, 0, 3] = torch.linspace(-0.3, 0.3, n)
    photos = torch.rand(n, 3, h, w, generator=g)
    sources = [model.neighbour_source(model.encode_neighbours(photos[j:j + 1]), 4.0 * torch.ones(1, 1, h, w))
               for j in range(n)]
    nb = NeighbourBatch(None, None, K.expand(1, n, 3, 3), poses[None, 1:], sources=sources)
    return render, depth, K[None], poses[:1], nb


def _stage_times(fn, repeats: int, *others) -> tuple[dict, float] | list[tuple[dict, float]]:
    """Median seconds per stage and in total over ``repeats`` runs of ``fn``; with ``others``,
    the same for each of them, all alternating run by run (fair under a varying load)."""
    fns = [fn, *others]
    per_stage: list[dict[str, list[float]]] = [{} for _ in fns]
    totals: list[list[float]] = [[] for _ in fns]
    for _ in range(repeats):
        for i, f in enumerate(fns):
            with StageProfile() as prof:
                f()
            totals[i].append(prof.total_seconds)
            for row in prof.rows():
                per_stage[i].setdefault(row["stage"], []).append(row["seconds"])
    out = [({k: statistics.median(v) for k, v in ps.items()}, statistics.median(t)) for ps, t in zip(per_stage, totals)]
    return out[0] if not others else out


def _stage_flops(fn) -> dict:
    with StageProfile(count_flops=True) as prof:
        fn()
    return {row["stage"]: row["gflop"] for row in prof.rows()}


def profile(variant: str, h: int, w: int, repeats: int, reference: bool) -> tuple[list[dict], dict]:
    torch.manual_seed(0)
    model = build_enhancer(variant).eval()
    randomise_zero_layers(model)
    with torch.inference_mode():
        render, depth, K, pose, nb = make_inputs(model, h, w)
        run = lambda: model(render, depth, K, pose, nb)  # noqa: E731
        fast_out = run()

        def run_torch():
            with native.disabled():
                return run()

        torch_diff = float((run_torch() - fast_out).abs().max())
        (seconds, total), (torch_seconds, torch_total) = _stage_times(run, repeats, run_torch)
        executed = _stage_flops(run)
        moved = _stage_bytes(run)
    ref_seconds, ref_total, diff = {}, float("nan"), float("nan")
    with torch.no_grad(), reference_mode():
        model_flops = _stage_flops(run)
        if reference:
            ref_out = run()
            ref_seconds, ref_total = _stage_times(run, 1)
            diff = float((fast_out - ref_out).abs().max())
    rows = []
    names = [s for s in (*STAGES, "other") if s in seconds]
    for stage in names + ["total"]:
        if stage == "total":
            sec, ref, gm, ge = total, ref_total, sum(model_flops.values()), sum(executed.values())
            tfast = torch_total
        else:
            sec, ref = seconds[stage], ref_seconds.get(stage, float("nan"))
            tfast = torch_seconds.get(stage, float("nan"))
            gm, ge = model_flops.get(stage, 0.0), executed.get(stage, 0.0)
        gb = sum(moved.values()) if stage == "total" else moved.get(stage, 0.0)
        rows.append(dict(variant=variant, height=h, width=w, neighbours=NEIGHBOURS, stage=stage,
                         seconds=round(sec, 4), seconds_torch_fast=round(tfast, 4),
                         seconds_reference=round(ref, 4), gflop_model=round(gm, 3),
                         gflop_executed=round(ge, 3), gb_moved=round(gb, 4), max_abs_diff=diff))
    official = Uformer(model.config.uformer, in_channels=3, out_channels=3).eval()
    rgb = torch.rand(1, 3, h, w)
    with torch.no_grad(), reference_mode():
        official(rgb)
        t = time.perf_counter()
        official(rgb)
        official_s = time.perf_counter() - t
        official_gflop = _stage_flops(lambda: official(rgb))["other"]
    lib = native.library()
    summary = dict(variant=variant, height=h, width=w, seconds=total,
                   native_kernels=lib._name if lib is not None else None,
                   seconds_torch_fast=torch_total, speedup_vs_torch_fast=torch_total / total,
                   max_abs_diff_torch_fast=torch_diff,
                   seconds_reference=ref_total,
                   gflop_model=sum(model_flops.values()), gflop_executed=sum(executed.values()),
                   gb_moved=sum(moved.values()),
                   uformer_official_seconds=official_s, uformer_official_gflop=official_gflop,
                   max_abs_diff=diff)
    return rows, summary


def plot(rows: list[dict], summaries: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    configs = [(s["variant"], s["height"], s["width"]) for s in summaries]
    paths = (("seconds_reference", "plain"), ("seconds_torch_fast", "fast, no C kernels"), ("seconds", "fast"))
    fig, (ax_t, ax_e) = plt.subplots(1, 2, figsize=(13, 0.35 * len(configs) * len(paths) + 2.5))
    colors = dict(zip((*STAGES, "other"), plt.cm.tab10.colors))
    labels = []
    for i, (v, h, w) in enumerate(configs):
        for k, (col, name) in enumerate(paths):
            y = len(paths) * i + k
            left = 0.0
            for r in rows:
                if (r["variant"], r["height"], r["width"]) != (v, h, w) or r["stage"] == "total":
                    continue
                val = r[col] if r[col] == r[col] else 0.0
                ax_t.barh(y, val, left=left, color=colors[r["stage"]],
                          label=r["stage"] if i == 0 and k == len(paths) - 1 else None)
                left += val
            labels.append(f"{v} {w}x{h} {name}")
    ax_t.set_yticks(range(len(labels)), labels, fontsize=7)
    ax_t.set_xlabel("seconds per enhancement (5 neighbours), stacked by stage")
    ax_t.legend(fontsize=7, loc="upper right")
    effs = [s["efficiency_model"] for s in summaries]
    ax_e.barh(range(len(configs)), effs, color="tab:green")
    ax_e.axvline(0.4, color="k", ls="--", lw=1)
    ax_e.set_yticks(range(len(configs)), [f"{v} {w}x{h}" for v, h, w in configs], fontsize=7)
    ax_e.set_xlabel("whole forward: model GFLOP / s / matmul peak")
    s0 = rows[0]
    fig.suptitle(f"RoGUENeRF enhancement profile - peak {summaries[0]['peak_gflops']:.0f} GFLOP/s - "
                 f"{s0['date']} - {s0['commit']}\n{s0['machine']}", fontsize=8)
    save_figure(fig, path)


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--output", required=True, type=Path, help="CSV to write (JSON and PNG go next to it)")
    p.add_argument("--variants", default="micro,nano,T,S,B")
    p.add_argument("--sizes", default="378x504,512x512", help="comma-separated HxW")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--no-reference", action="store_true", help="skip timing the plain implementation")
    args = p.parse_args(argv)
    applied = runtime.configure()
    variants = [v for v in args.variants.split(",") if v]
    unknown = [v for v in variants if v not in VARIANTS]
    if unknown:
        p.error(f"--variants: unknown {unknown}; expected some of {sorted(VARIANTS)}")
    sizes = [tuple(int(x) for x in s.lower().split("x")) for s in args.sizes.split(",") if s]
    meta = stamp()
    print(f"runtime: {applied}", flush=True)
    peaks = [matmul_peak()]
    bandwidths = [memory_bandwidth()]
    print(f"matmul peak: {peaks[0]:.1f} GFLOP/s, memory bandwidth (copy): {bandwidths[0]:.1f} GB/s", flush=True)
    rows, summaries = [], []
    for variant in variants:
        for h, w in sizes:
            r, s = profile(variant, h, w, args.repeats, not args.no_reference)
            rows += [{**meta, **row} for row in r]
            summaries.append(s)
            print(f"{variant} {w}x{h}: {s['seconds']:.3f} s ("
                  f"without the C kernels {s['seconds_torch_fast']:.3f} s: {s['speedup_vs_torch_fast']:.2f}x; "
                  f"plain {s['seconds_reference']:.3f} s), "
                  f"{s['gflop_model']:.1f} GFLOP model / {s['gflop_executed']:.1f} executed, "
                  f"max |fast - plain| {s['max_abs_diff']:.2e}, official Uformer alone "
                  f"{s['uformer_official_seconds']:.3f} s", flush=True)
    peaks.append(matmul_peak())
    bandwidths.append(memory_bandwidth())
    peak, bandwidth = max(peaks), max(bandwidths)
    for row in rows:
        row["peak_gflops"] = round(peak, 1)
        row["gflops_per_s"] = round(row["gflop_executed"] / row["seconds"], 2) if row["seconds"] else 0.0
        row["efficiency"] = round(row["gflop_model"] / row["seconds"] / peak, 4) if row["seconds"] else 0.0
        row["efficiency_executed"] = round(row["gflop_executed"] / row["seconds"] / peak, 4) if row["seconds"] else 0.0
        row["threads"] = applied["threads"]
        # Roofline floor of the stage as written: its FLOPs at the matmul peak, or its operators'
        # bytes at the copy bandwidth, whichever is longer (no overlap, no fusion assumed).
        row["bandwidth_gbs"] = round(bandwidth, 1)
        row["floor_flops_s"] = round(row["gflop_executed"] / peak, 5)
        row["floor_bytes_s"] = round(row["gb_moved"] / bandwidth, 5)
        row["floor_s"] = max(row["floor_flops_s"], row["floor_bytes_s"])
        row["seconds_over_floor"] = round(row["seconds"] / row["floor_s"], 2) if row["floor_s"] else 0.0
    for s in summaries:
        same = (s["variant"], s["height"], s["width"])
        stage_rows = [r for r in rows if (r["variant"], r["height"], r["width"]) == same
                      and r["stage"] not in ("total", "other")]
        # The stage costing the most time beyond what it would take at the matmul peak.
        limiting = max(stage_rows, key=lambda r: r["seconds"] - r["gflop_model"] / peak)
        floor = sum(r["floor_s"] for r in stage_rows) + next(
            (r["floor_s"] for r in rows if (r["variant"], r["height"], r["width"], r["stage"])
             == (s["variant"], s["height"], s["width"], "other")), 0.0)
        s.update(bandwidth_gbs=bandwidth, bandwidths_measured=bandwidths, floor_s=floor,
                 floor_table={r["stage"]: {k: r[k] for k in ("seconds", "gflop_executed", "gb_moved", "floor_flops_s",
                                                             "floor_bytes_s", "floor_s")} for r in rows
                              if (r["variant"], r["height"], r["width"]) == (s["variant"], s["height"], s["width"])})
        s.update(peak_gflops=peak, peaks_measured=peaks, threads=applied["threads"],
                 efficiency_model=s["gflop_model"] / s["seconds"] / peak,
                 efficiency_executed=s["gflop_executed"] / s["seconds"] / peak,
                 speedup_vs_plain=s["seconds_reference"] / s["seconds"],
                 limiting_stage=limiting["stage"],
                 limiting_stage_seconds=limiting["seconds"],
                 limiting_stage_efficiency=limiting["gflop_model"] / limiting["seconds"] / peak)
        print(f"{s['variant']} {s['width']}x{s['height']}: efficiency {s['efficiency_model']:.1%} of peak "
              f"(executed FLOPs: {s['efficiency_executed']:.1%}), {s['speedup_vs_plain']:.2f}x the plain path, "
              f"limited by {s['limiting_stage']}", flush=True)
        print("  stage seconds now / without the C kernels: " + ", ".join(
            f"{r['stage']} {r['seconds']:.4f}/{r['seconds_torch_fast']:.4f}" for r in rows
            if (r["variant"], r["height"], r["width"]) == (s["variant"], s["height"], s["width"])), flush=True)
        print(f"  floor (per stage max(FLOP / {peak:.0f} GFLOP/s, bytes / {bandwidth:.1f} GB/s)): "
              f"{s['floor_s']:.4f} s of {s['seconds']:.4f} s", flush=True)
        for stage, r in s["floor_table"].items():
            print(f"    {stage:>12} {r['seconds']:8.4f} s  {r['gflop_executed']:7.3f} GFLOP"
                  f" -> {r['floor_flops_s']:.4f} s  {r['gb_moved']:7.3f} GB -> {r['floor_bytes_s']:.4f} s", flush=True)
    write_csv(beside(args.output, ".csv"), rows)
    write_json(beside(args.output, ".json"), {**meta, "runtime": applied, "configs": summaries})
    plot(rows, summaries, beside(args.output, ".png"))
    print(f"wrote {beside(args.output, '.csv')}, {beside(args.output, '.json')} and {beside(args.output, '.png')}")


if __name__ == "__main__":
    main()
