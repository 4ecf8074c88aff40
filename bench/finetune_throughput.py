"""Fine-tuning throughput on the CPU: training steps/s and target pixels/s against crop and batch.

    .venv/bin/python bench/finetune_throughput.py --output bench/results/finetune_throughput.csv \
        --skip 'T@256x8'

    options: [--variants micro,T] [--crops 64,128,256] [--batches 1,2,4,8] [--neighbours 2]
             [--steps 5] [--max-seconds 20] [--warmup 2] [--threads N] [--skip VARIANT@CROPxBATCH ...]

About 5-8 minutes on 2 idle cores with the defaults. Memory grows with batch x crop: on lego,
T at 200 px crops peaked at ~3 GB (batch 1) and ~5.6 GB (batch 2), micro at ~4.9 GB (batch 8),
so T@256x8 (~20 GB) is skipped above.

For every variant x neighbours x crop x batch point, a fresh (seeded, scratch) model and Adam
optimiser make training steps on lego's training views with the library's own step,
``roguenerf.training.loop.train_step`` (the one ``finetune``/``pretrain`` run): B random c x c
crops of renders, depths and photos; conv_H features of the U distinct *whole* neighbour photos
those targets use (with grad); enhancer forward; loss (L1, or L1 + 1e-3 VGG-19 with
``--vgg-weights``, as ``build_loss`` makes it); backward; finiteness checks; Adam step.
Per point: up to ``--warmup`` untimed steps (no more once they have taken ``--max-seconds``/4),
then timed steps until ``--steps`` of them or ``--max-seconds`` (at least one is always timed).
Reported: median seconds/step, steps/s = 1 / that, pixels/s = batch * crop_used^2 * steps/s
(target pixels only), and the process's peak RSS so far (ru_maxrss: process-wide and monotone,
so it is the maximum over this point and every point before it, not the point's own).

Crops larger than the scene's images are clamped to them, as in training (lego is 200 x 200:
a requested 256 trains on 200 x 200 crops; the ``crop_used`` column says so, pixels use it).
Neighbours default to what ``plan_training`` picks on a CPU (printed at start). Once a point
takes longer than ``--max-seconds`` for a single step, the points of that variant and
neighbour count with both a larger-or-equal crop and batch are skipped (printed);
``--skip VARIANT@CROPxBATCH`` (shell-style wildcards, e.g. ``T@256x*``) skips points by hand.

Writes the CSV (every row: date, machine, commit, then variant, crop, batch, neighbours,
threads, seconds_per_step, steps_per_s, pixels_per_s, then details) after every point, a PNG
next to it (pixels/s against crop, one line per batch, one panel per variant) and a table.

Not measured: scene loading and the neighbour lists (``SceneData``, once per run), the
periodic checkpoint saves (every 60 s in ``finetune``), evaluation before/after, the progress
bar and callbacks, pre-training's per-step scene draw, GPUs, resumed optimiser state, and
training quality (loss values are not compared; weights are a fresh scratch init: speed does not depend on them).
"""

from __future__ import annotations

import argparse
import fnmatch
import gc
import resource
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
import roguenerf  # noqa: E402,F401  (first: OpenMP's wait policy is set before torch loads)
import torch  # noqa: E402

from bench.common import LEGO, stamp, write_csv  # noqa: E402


def _ints(text: str) -> list[int]:
    return [int(x) for x in text.split(",") if x.strip()]


def _names(text: str) -> list[str]:
    return [x.strip() for x in text.split(",") if x.strip()]


def parse_args(argv=None):
    from roguenerf.models import VARIANTS

    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--output", required=True, type=Path, help="CSV file to write (PNG plot goes next to it)")
    p.add_argument("--scene", type=Path, default=LEGO, help="scene with renders and depths (default: lego)")
    p.add_argument("--variants", type=_names, default=["micro", "T"], help=f"comma-separated, from {sorted(VARIANTS)}")
    p.add_argument("--crops", type=_ints, default=[64, 128, 256], help="comma-separated crop sides")
    p.add_argument("--batches", type=_ints, default=[1, 2, 4, 8], help="comma-separated batch sizes")
    p.add_argument("--neighbours", type=_ints, default=None,
                   help="comma-separated neighbours per target (default: plan_training's on a CPU)")
    p.add_argument("--steps", type=int, default=5, help="timed steps per point (fewer if --max-seconds runs out)")
    p.add_argument("--max-seconds", type=float, default=20.0, help="time cap of the timed steps of one point")
    p.add_argument("--warmup", type=int, default=2, help="untimed steps per point before timing")
    p.add_argument("--skip", action="append", default=[], metavar="VARIANT@CROPxBATCH",
                   help="skip points, e.g. T@256x8 or T@256x* (repeatable)")
    p.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's choice)")
    p.add_argument("--lr", type=float, default=1e-4, help="Adam learning rate (as TrainConfig)")
    p.add_argument("--vgg-weights", type=Path, default=None, help="torchvision VGG-19 state dict: L1 + VGG loss")
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    unknown = [v for v in args.variants if v not in VARIANTS]
    if unknown:
        p.error(f"--variants: unknown {unknown}; expected some of {sorted(VARIANTS)}")
    if args.steps < 1 or args.warmup < 0 or not args.max_seconds > 0:
        p.error("--steps must be >= 1, --warmup >= 0 and --max-seconds > 0")
    if any(c < 8 for c in args.crops) or any(b < 1 for b in args.batches):
        p.error("--crops must be >= 8 and --batches >= 1")
    return args


def peak_rss_mb() -> float:
    """Peak resident set size of this process so far (Linux reports ru_maxrss in KiB)."""
    kib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return kib / 1024 if sys.platform != "darwin" else kib / 2**20


def measure(variant: str, data, crop: int, batch: int, neighbours: int, args, loss_fn) -> dict:
    """Warm up, then time ``train_step`` on one point; returns its columns (after stamp's)."""
    import dataclasses

    from roguenerf.models import build_enhancer
    from roguenerf.training.loop import train_step

    device = torch.device("cpu")
    torch.manual_seed(args.seed)
    model = build_enhancer(variant)  # scratch, as finetune(checkpoint=None, variant=...) starts
    if model.config.num_neighbours != neighbours and neighbours > 0:
        model.config = dataclasses.replace(model.config, num_neighbours=neighbours)
    model.to(device).train()
    optimizer = torch.optim.Adam(model.parameters(), lr=args.lr)
    generator = torch.Generator().manual_seed(args.seed)

    def step(i: int) -> float:
        t0 = time.perf_counter()
        targets = torch.randint(0, len(data), (batch,), generator=generator)
        train_step(model, data, targets, crop, generator, device, loss_fn, optimizer, step=i)
        return time.perf_counter() - t0

    warm, warm_s = 0, 0.0
    while warm < args.warmup and (warm == 0 or warm_s < args.max_seconds / 4):
        warm_s += step(warm)
        warm += 1
    times: list[float] = []
    while len(times) < args.steps and (not times or sum(times) < args.max_seconds):
        times.append(step(warm + len(times)))
    crop_used = min(crop, data.height, data.width)
    sec = statistics.median(times)
    return {"variant": variant, "crop": crop, "batch": batch, "neighbours": neighbours,
            "threads": torch.get_num_threads(), "seconds_per_step": round(sec, 5),
            "steps_per_s": round(1.0 / sec, 4), "pixels_per_s": round(batch * crop_used**2 / sec, 1),
            "crop_used": crop_used, "timed_steps": len(times), "warmup_steps": warm,
            "warmup_seconds": round(warm_s, 3), "min_seconds_per_step": round(min(times), 5),
            "max_seconds_per_step": round(max(times), 5), "loss": loss_fn.kind,
            "peak_rss_mb_so_far": round(peak_rss_mb(), 1)}


def plot(rows: list[dict], path: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    variants = list(dict.fromkeys(r["variant"] for r in rows))
    series = sorted({(r["neighbours"], r["batch"]) for r in rows})
    colour = {key: f"C{i % 10}" for i, key in enumerate(series)}  # same colour for a batch in every panel
    fig, axes = plt.subplots(1, len(variants), figsize=(5 * len(variants), 4), squeeze=False)
    for ax, variant in zip(axes[0], variants):
        mine = [r for r in rows if r["variant"] == variant]
        several_n = len({r["neighbours"] for r in mine}) > 1
        for n, batch in sorted({(r["neighbours"], r["batch"]) for r in mine}):
            line = sorted((r["crop_used"], r["pixels_per_s"] / 1e3) for r in mine
                          if r["batch"] == batch and r["neighbours"] == n)
            label = f"batch {batch}" + (f", {n} neighbours" if several_n else "")
            ax.plot([c for c, _ in line], [p for _, p in line], "o-", color=colour[(n, batch)], label=label)
        crops = sorted({r["crop_used"] for r in mine})
        ax.set_xscale("log", base=2)
        ax.set_xticks(crops, [str(c) for c in crops])
        ax.minorticks_off()
        ax.set_ylim(bottom=0)
        ax.set_xlabel("crop side used (px)")
        ax.set_ylabel("target pixels per second (thousands)")
        n_text = "" if several_n else f", {mine[0]['neighbours']} neighbours"
        ax.set_title(f"{variant}{n_text}, loss {mine[0]['loss']}", fontsize=9)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
    r0 = rows[0]
    fig.suptitle(f"fine-tuning throughput on CPU ({r0['threads']} threads) | {r0['date']} | {r0['commit']}\n"
                 f"{r0['machine']}", fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def table(rows: list[dict]) -> str:
    head = (f"{'variant':>7} {'crop':>9} {'batch':>5} {'nbrs':>4} {'s/step':>9} {'steps/s':>8} "
            f"{'kpx/s':>9} {'steps':>5} {'rss MB':>8}")
    lines = [head, "-" * len(head)]
    for r in rows:
        crop = f"{r['crop']}" if r["crop"] == r["crop_used"] else f"{r['crop']}->{r['crop_used']}"
        lines.append(f"{r['variant']:>7} {crop:>9} {r['batch']:>5} {r['neighbours']:>4} "
                     f"{r['seconds_per_step']:>9.4f} {r['steps_per_s']:>8.3f} {r['pixels_per_s'] / 1e3:>9.1f} "
                     f"{r['timed_steps']:>5} {r['peak_rss_mb_so_far']:>8.0f}")
    return "\n".join(lines)


def main(argv=None) -> int:
    args = parse_args(argv)
    from roguenerf import runtime

    print(f"runtime: {runtime.configure(args.threads or None)}", flush=True)

    from roguenerf.data.readers import load_scene
    from roguenerf.training import TrainConfig, plan_training
    from roguenerf.training.config import describe_plan
    from roguenerf.training.loop import SceneData
    from roguenerf.training.losses import build_loss

    scene = load_scene(args.scene)
    plan = plan_training(scene, TrainConfig(), device="cpu")
    print(f"fine-tuning from scratch here would use: {describe_plan(plan)}", flush=True)
    neighbours = args.neighbours if args.neighbours is not None else [plan["num_neighbours"]]
    if args.neighbours is None:
        print(f"neighbours per target: {neighbours[0]} (plan_training's CPU choice)", flush=True)
    loss_fn = build_loss(args.vgg_weights, "cpu")

    base = stamp()
    rows: list[dict] = []
    datasets = {}
    for n in neighbours:
        t0 = time.perf_counter()
        datasets[n] = SceneData(scene, n)
        d = datasets[n]
        print(f"SceneData: {len(d)} training views of {d.width}x{d.height}, {d.neighbours.shape[1]} neighbours "
              f"each ({time.perf_counter() - t0:.1f} s)", flush=True)
        big = [c for c in args.crops if c > min(d.height, d.width)]
        if big:
            print(f"note: crops {big} exceed the {d.width}x{d.height} images: they train on "
                  f"{min(d.height, d.width)} px crops (column crop_used)", flush=True)

    for variant in args.variants:
        for n in neighbours:
            data = datasets[n]
            too_slow: list[tuple[int, int]] = []  # (crop_used, batch) whose single step beat --max-seconds
            for crop in sorted(args.crops):
                for batch in sorted(args.batches):
                    key = f"{variant}@{crop}x{batch}"
                    crop_used = min(crop, data.height, data.width)
                    if any(fnmatch.fnmatchcase(key, pattern) for pattern in args.skip):
                        print(f"skip {key} (--skip)", flush=True)
                        continue
                    if any(crop_used >= c and batch >= b for c, b in too_slow):
                        print(f"skip {key}: a smaller point already took more than --max-seconds per step",
                              flush=True)
                        continue
                    row = {**base, **measure(variant, data, crop, batch, n, args, loss_fn)}
                    gc.collect()  # the point's model, optimiser state and activations
                    rows.append(row)
                    print(", ".join(f"{k}={row[k]}" for k in list(row)[3:]), flush=True)
                    write_csv(args.output, rows)
                    if row["seconds_per_step"] > args.max_seconds:
                        too_slow.append((crop_used, batch))

    if not rows:
        print("nothing measured")
        return 1
    png = plot(rows, args.output.with_suffix(".png"))
    print()
    print(table(rows))
    print(f"\nwrote {args.output} and {png}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
