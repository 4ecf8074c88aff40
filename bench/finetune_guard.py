"""The fine-tune guard on fine-tunes already made: what it measures, what it decides, and what
that decision gives on the held-out views it never sees.

    python -m bench.finetune_guard PAIR=TUNED ... [--checkpoint START] [--output bench/results/guard/guard]

Each argument names a scene folder with held-out views (a ``bench.kinds`` pair) and a fine-tuned
checkpoint of it (e.g. ``runs/kinds/finetune/SCENE/KIND/default/10min/model.safetensors``), both
fine-tuned from ``--checkpoint`` (default: the shipped one). Per pair: the guard's measure
(:func:`roguenerf.training.guard.judge`: the PSNR gain of the starting and the fine-tuned weights
on up to 8 training views drawn from their nearest other training view; here the fine-tune has
already seen those views' photos as targets, as it has inside ``finetune``) next to the same
gains on the training views' own renders and on the held-out views (what a user gets: each
view enhanced as ``evaluate`` does), and the held-out gain of the weights the guard keeps.
Writes ``OUTPUT.csv`` (a row per pair; date, machine, commit), ``OUTPUT.json`` and ``OUTPUT.png``.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from bench.common import RESULTS, beside, caption_line, save_figure, scene_label, stamp, write_csv, write_json


def measure(pair: Path, tuned_path: Path, start_path: Path) -> dict:
    """One pair's row."""
    from roguenerf import load_checkpoint, load_scene
    from roguenerf.training import evaluate
    from roguenerf.training.guard import drawn_view_gains, guard_positions, judge
    from roguenerf.training.loop import SceneData

    scene = load_scene(pair)
    if not scene.indices("test"):
        raise SystemExit(f"{pair}: expected held-out views to report on")
    start, _ = load_checkpoint(start_path)
    tuned, _ = load_checkpoint(tuned_path)
    data = SceneData(scene, 0)
    began = time.perf_counter()
    report = judge(data, start, tuned)
    positions = guard_positions(data)
    own = [(data.renders[k], data.depths[k]) for k in positions]
    own_start = drawn_view_gains(data, start, positions, own)
    own_tuned = drawn_view_gains(data, tuned, positions, own)
    def held_out_gain(model) -> tuple[float, int]:  # what `roguenerf evaluate` reports
        report = evaluate(scene, model)
        return report["enhanced"]["psnr"] - report["render"]["psnr"], len(report["views"])

    (test_start, views), (test_tuned, _) = held_out_gain(start), held_out_gain(tuned)
    mean = lambda xs: sum(xs) / len(xs)  # noqa: E731
    row = {**stamp(), "pair": scene_label(pair), "tuned": str(tuned_path), "start": str(start_path),
           "guard_views": len(report.views), "drawn_share": round(report.drawn_share, 3),
           "drawn_start_db": round(report.start_mean, 4), "drawn_tuned_db": round(report.tuned_mean, 4),
           "kept": report.kept, "guard_seconds": round(report.seconds, 1),
           "own_start_db": round(mean(own_start), 4), "own_tuned_db": round(mean(own_tuned), 4),
           "held_out_views": views, "held_out_start_db": round(test_start, 4),
           "held_out_tuned_db": round(test_tuned, 4),
           "held_out_guarded_db": round(test_tuned if report.kept else test_start, 4),
           "seconds": round(time.perf_counter() - began, 1)}
    print(f"{row['pair']}: drawn {row['drawn_start_db']:+.3f} -> {row['drawn_tuned_db']:+.3f} dB "
          f"({'kept' if report.kept else 'refused'}); own renders {row['own_start_db']:+.3f} -> "
          f"{row['own_tuned_db']:+.3f}; held-out {test_start:+.3f} -> {test_tuned:+.3f}, guarded "
          f"{row['held_out_guarded_db']:+.3f}", flush=True)
    return row


def plot(rows: list[dict], path: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.5))
    for r in rows:
        x = r["drawn_tuned_db"] - r["drawn_start_db"]
        y = r["held_out_tuned_db"] - r["held_out_start_db"]
        ax.scatter([x], [y], color="tab:green" if r["kept"] else "tab:red")
        ax.annotate(r["pair"], (x, y), fontsize=7)
    ax.axhline(0, color="grey", lw=0.5)
    ax.axvline(0, color="grey", lw=0.5)
    ax.set_xlabel("fine-tuned minus starting weights, drawn training views (dB): the guard's measure")
    ax.set_ylabel("the same on the held-out views (dB)")
    caption_line(fig, rows, "fine-tune guard (green: kept, red: refused)")
    return save_figure(fig, path)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("pairs", nargs="+", help="SCENE_DIR=TUNED_CHECKPOINT")
    p.add_argument("--checkpoint", type=Path, default=None, help="the weights the fine-tunes started from "
                                                                 "(default: the shipped checkpoint)")
    p.add_argument("--output", type=Path, default=RESULTS / "guard" / "guard")
    args = p.parse_args(argv)
    import roguenerf.runtime
    from roguenerf.checkpoint import default_checkpoint_path

    roguenerf.runtime.configure()
    start = args.checkpoint or default_checkpoint_path()
    rows = []
    for item in args.pairs:
        pair, sep, tuned = item.partition("=")
        if not sep:
            p.error(f"expected SCENE_DIR=TUNED_CHECKPOINT, got {item!r}")
        rows.append(measure(Path(pair), Path(tuned), Path(start)))
    csv_path = write_csv(beside(args.output, ".csv"), rows)
    json_path = write_json(beside(args.output, ".json"), {**stamp(), "rows": rows})
    png = plot(rows, beside(args.output, ".png"))
    print(f"wrote {csv_path}, {json_path} and {png}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
