"""CPU latency and FLOP efficiency of the enhancer variants.

    python bench/latency.py --output bench/latency.csv [--variants nano,T] [--repeats 3]
                            [--skip B@512x512] [--threads 2]

For each variant and size: median wall time of one enhancement (``torch.inference_mode``,
5 neighbours whose conv_H features are already cached, as in ``SceneEnhancer``), its FLOPs
(``torch.utils.flop_counter.FlopCounterMode``: convs and matmuls; grid_sample and
element-wise ops are not counted), achieved GFLOP/s, the float32 matmul peak measured in the
same run, their ratio (efficiency), and the time of the Uformer alone on the same merged
features. Writes the CSV (with date, machine and commit) and a PNG plot next to it.
Weights are random (the zero-initialised layers too): speed does not depend on them.
"""

from __future__ import annotations

import argparse
import csv
import datetime
import math
import os
import platform
import statistics
import subprocess
import sys
import time
from pathlib import Path

import torch
from torch.utils.flop_counter import FlopCounterMode

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from roguenerf.models import VARIANTS, NeighbourBatch, build_enhancer  # noqa: E402

SIZES = [(378, 504), (512, 512)]
"""(height, width): a 504 x 378 landscape render (LLFF at 1/8) and a 512 x 512 one."""

COLUMNS = ["date", "machine", "commit", "threads", "variant", "height", "width", "neighbours", "seconds",
           "gflop", "gflops_per_s", "peak_gflops_per_s", "efficiency", "uformer_seconds", "uformer_gflop",
           "enhancer_to_uformer_ratio"]


def commit() -> str:
    root = Path(__file__).resolve().parents[1]
    try:
        head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=root, capture_output=True,
                              text=True, check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain"], cwd=root, capture_output=True,
                               text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"
    return head + ("-dirty" if dirty else "")


def machine() -> str:
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return f"{platform.node()} | {cpu} | {os.cpu_count()} cpus"


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


def inputs(model, h: int, w: int, n: int):
    g = torch.Generator().manual_seed(0)
    f = 0.9 * w
    K = torch.tensor([[f, 0.0, w / 2], [0.0, f, h / 2], [0.0, 0.0, 1.0]])
    render = torch.rand(1, 3, h, w, generator=g)
    depth = 4.0 + 0.2 * torch.rand(1, 1, h, w, generator=g)
    poses = torch.eye(4).repeat(n + 1, 1, 1)
    poses[1:, 0, 3] = torch.linspace(-0.3, 0.3, n)
    feats = model.encode_neighbours(torch.rand(n, 3, h, w, generator=g))
    nb = NeighbourBatch(feats[None], 4.0 * torch.ones(1, n, 1, h, w), K.expand(1, n, 3, 3), poses[None, 1:])
    return render, depth, K[None], poses[:1], nb


def timed(fn, repeats: int) -> float:
    fn()
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return statistics.median(times)


def flops(fn) -> float:
    counter = FlopCounterMode(display=False)
    with counter:
        fn()
    return counter.get_total_flops() / 1e9


def run(variant: str, h: int, w: int, n: int, repeats: int, peak: float) -> dict:
    torch.manual_seed(0)
    model = build_enhancer(variant).eval()
    layer = model.uformer.output_proj if model.uformer is not None else model.to_rgb
    torch.nn.init.normal_(layer.weight, std=0.02)
    with torch.inference_mode():
        render, depth, K, pose, nb = inputs(model, h, w, n)
        enhance = lambda: model(render, depth, K, pose, nb)  # noqa: E731
        seconds = timed(enhance, repeats)
        gflop = flops(enhance)
        merged = torch.randn(1, model.config.features, h, w)
        uformer = lambda: model.uformer(merged)  # noqa: E731
        u_seconds = timed(uformer, repeats) if model.uformer is not None else float("nan")
        u_gflop = flops(uformer) if model.uformer is not None else 0.0
    return dict(variant=variant, height=h, width=w, neighbours=n, seconds=round(seconds, 4),
                gflop=round(gflop, 2), gflops_per_s=round(gflop / seconds, 2), peak_gflops_per_s=round(peak, 1),
                efficiency=round(gflop / seconds / peak, 3), uformer_seconds=round(u_seconds, 4),
                uformer_gflop=round(u_gflop, 2), enhancer_to_uformer_ratio=round(seconds / u_seconds, 2))


def plot(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax_t, ax_e) = plt.subplots(1, 2, figsize=(11, 4))
    sizes = sorted({(r["height"], r["width"]) for r in rows})
    variants = list(dict.fromkeys(r["variant"] for r in rows))
    width = 0.8 / max(1, len(sizes))
    for k, (h, w) in enumerate(sizes):
        sel = {r["variant"]: r for r in rows if (r["height"], r["width"]) == (h, w)}
        xs = [i + k * width for i in range(len(variants))]
        ax_t.bar(xs, [sel[v]["seconds"] if v in sel else 0 for v in variants], width, label=f"{w}x{h}")
        ax_e.bar(xs, [sel[v]["gflops_per_s"] if v in sel else 0 for v in variants], width, label=f"{w}x{h}")
    for ax in (ax_t, ax_e):
        ax.set_xticks([i + width * (len(sizes) - 1) / 2 for i in range(len(variants))], variants)
        ax.legend()
    ax_t.set_ylabel("seconds per enhancement (5 neighbours)")
    ax_t.set_yscale("log")
    ax_e.set_ylabel("achieved GFLOP/s")
    ax_e.axhline(rows[0]["peak_gflops_per_s"], color="k", ls="--", lw=1, label="matmul peak")
    ax_e.legend()
    r0 = rows[0]
    fig.suptitle(f"RoGUENeRF enhancer on CPU ({r0['threads']} threads) - {r0['date']} - {r0['commit']}\n"
                 f"{r0['machine']}", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--output", required=True, type=Path, help="CSV file to write (PNG plot goes next to it)")
    p.add_argument("--variants", default="micro,nano,T,S,B", help=f"comma-separated, from {sorted(VARIANTS)}")
    p.add_argument("--repeats", type=int, default=3, help="timed runs per measurement (median reported)")
    p.add_argument("--neighbours", type=int, default=5)
    p.add_argument("--skip", action="append", default=[], metavar="VARIANT@HxW",
                   help="skip one measurement, e.g. B@512x512 (repeatable)")
    p.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's choice)")
    args = p.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    variants = [v.strip() for v in args.variants.split(",") if v.strip()]
    unknown = [v for v in variants if v not in VARIANTS]
    if unknown:
        p.error(f"--variants: unknown {unknown}; expected some of {sorted(VARIANTS)}")
    meta = dict(date=datetime.datetime.now().isoformat(timespec="seconds"), machine=machine(), commit=commit(),
                threads=torch.get_num_threads())
    peak = matmul_peak()
    print(f"matmul peak: {peak:.1f} GFLOP/s on {meta['threads']} threads", flush=True)
    rows = []
    args.output.parent.mkdir(parents=True, exist_ok=True)
    for variant in variants:
        for h, w in SIZES:
            if f"{variant}@{h}x{w}" in args.skip or f"{variant}@{w}x{h}" in args.skip:
                continue
            row = {**meta, **run(variant, h, w, args.neighbours, args.repeats, peak)}
            rows.append(row)
            print(", ".join(f"{k}={row[k]}" for k in COLUMNS[4:]), flush=True)
            with args.output.open("w", newline="") as fh:
                writer = csv.DictWriter(fh, fieldnames=COLUMNS)
                writer.writeheader()
                writer.writerows(rows)
    if rows:
        plot(rows, args.output.with_suffix(".png"))
        print(f"wrote {args.output} and {args.output.with_suffix('.png')}")


if __name__ == "__main__":
    main()
