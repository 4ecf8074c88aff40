"""PSNR gain on lego's test views against fine-tuning time, and against model variant.

Sweep 1 (time): one fine-tuning run, evaluated after each budget in --minutes (1, 3, 10, 30
by default): the run resumes exactly from its saved state, so the 30-minute point costs 30
minutes of training in total, not 44.
Sweep 2 (variant): each variant in --variants fine-tuned for --variant-minutes, with its
inference latency per view.

Writes CSV rows (date, machine, commit, sweep, variant, minutes, steps, steps/s, crop, PSNR/SSIM
of renders and enhanced, gain, latency) and a PNG plot to --output.

    .venv/bin/python -m bench.speed_vs_error             # full (about an hour on 2 CPU cores)
    .venv/bin/python -m bench.speed_vs_error --quick     # seconds-long budgets, 2 test views
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

from bench.common import (
    LEGO,
    RESULTS,
    caption_line,
    configure_runtime,
    save_figure,
    scene_metrics,
    stamp,
    starting_checkpoint,
    write_outputs,
)


def _floats(text: str) -> list[float]:
    return [float(x) for x in text.split(",") if x.strip()]


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scene", type=Path, default=LEGO)
    p.add_argument("--minutes", type=_floats, default=[1, 3, 10, 30], help="comma-separated budgets")
    p.add_argument("--variants", default="micro,nano,T", help="comma-separated variants")
    p.add_argument("--variant-minutes", type=float, default=3.0, help="fine-tuning budget per variant")
    p.add_argument("--checkpoint", type=Path, default=None, help="start here (default: shipped default)")
    p.add_argument("--scratch", action="store_true", help="fine-tune from random weights")
    p.add_argument("--crop", type=int, default=None)
    p.add_argument("--lr", type=float, default=1e-4, help="Adam learning rate")
    p.add_argument("--max-views", type=int, default=None, help="evaluate only the first test views")
    p.add_argument("--skip-variants", action="store_true")
    p.add_argument("--quick", action="store_true", help="tiny budgets and 2 test views (proves it runs)")
    p.add_argument("--output", type=Path, default=RESULTS / "speed_vs_error")
    args = p.parse_args(argv)
    if args.quick:
        args.minutes = [0.05, 0.1]
        args.variants = "micro,nano"
        args.variant_minutes = 0.05
        args.max_views = args.max_views or 2
        args.crop = args.crop or 64
    return args


def run(args) -> list[dict]:
    from roguenerf.checkpoint import load_checkpoint
    from roguenerf.data.readers import load_scene
    from roguenerf.training import TrainConfig, evaluate, finetune

    scene = load_scene(args.scene)
    start = starting_checkpoint(args.checkpoint, args.scratch)
    base = stamp()
    rows = []
    work = Path(tempfile.mkdtemp(prefix="speed_vs_error_"))

    start_variant = load_checkpoint(start)[0].config.variant if start else None

    def record(sweep: str, result, report, started_from) -> dict:
        row = {**base, "sweep": sweep, "scene": scene.root.name, "variant": result.config["variant"],
               "start": "checkpoint" if started_from else "scratch", "minutes": round(result.seconds / 60, 3),
               "steps": result.steps, "steps_per_s": round(result.steps / max(result.seconds, 1e-9), 4),
               "crop": result.config["crop_used"], "neighbours": result.config["num_neighbours"],
               "loss": result.loss_kind, **scene_metrics(report)}
        print(", ".join(f"{k}={v}" for k, v in row.items() if k not in base), flush=True)
        rows.append(row)
        return row

    run_dir = work / "time"
    for minutes in sorted(args.minutes):
        config = TrainConfig(lr=args.lr, minutes=minutes, crop=args.crop, evaluate=False)
        result = finetune(scene, run_dir, checkpoint=start, config=config)
        model, _ = load_checkpoint(result.checkpoint)
        record("minutes", result, evaluate(scene, model, max_views=args.max_views), start)

    if not args.skip_variants:
        for variant in [v for v in args.variants.split(",") if v]:
            config = TrainConfig(lr=args.lr, minutes=args.variant_minutes, crop=args.crop, variant=variant,
                                 evaluate=False)
            # A checkpoint of another variant has other shapes: those variants start from scratch.
            own = start if variant == start_variant else None
            result = finetune(scene, work / f"variant_{variant}", checkpoint=own, config=config)
            model, _ = load_checkpoint(result.checkpoint)
            record("variant", result, evaluate(scene, model, max_views=args.max_views), own)
    return rows


def plot(rows: list[dict], path: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (left, right) = plt.subplots(1, 2, figsize=(10, 4))
    timed = [r for r in rows if r["sweep"] == "minutes"]
    if timed:
        left.plot([r["minutes"] for r in timed], [r["gain_db"] for r in timed], "o-")
        left.set_xscale("log")
    left.axhline(0, color="grey", lw=0.8)
    left.set_xlabel("fine-tuning time (min)")
    left.set_ylabel("PSNR gain over renders (dB)")
    left.set_title("gain vs fine-tuning time")
    for r in (r for r in rows if r["sweep"] == "variant"):
        right.scatter(r["latency_s_per_view"], r["gain_db"])
        right.annotate(f"{r['variant']} ({r['steps']} steps, {r['start']})", (r["latency_s_per_view"], r["gain_db"]))
    right.axhline(0, color="grey", lw=0.8)
    right.set_xlabel("inference latency per view (s)")
    right.set_ylabel("PSNR gain (dB)")
    right.set_title("gain vs variant")
    caption_line(fig, rows, "{scene} test views", fontsize=8)
    return save_figure(fig, path)


def main(argv=None) -> int:
    args = parse_args(argv)
    configure_runtime()
    write_outputs(args.output, run(args), plot, quick=args.quick)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
