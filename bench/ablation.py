"""The paper's ablation (Table 4) on lego with equal fine-tuning budgets.

Rows (each fine-tuned for the same --minutes on lego's training views, evaluated on its test views):

    UF          Uformer alone              --without neighbours alignment refinement attention
    +NN         + nearest neighbours       --without alignment refinement attention (unwarped)
    +3D-A       + 3D alignment             --without refinement attention
    +NRF        + non-rigid refinement     --without attention
    +GA         + geometric attention      everything, from scratch
    +PT         + pre-training             everything, from the default checkpoint (or --checkpoint)

Writes CSV + JSON + a markdown table (date, machine, commit; PSNR/SSIM, gain, steps, steps/s
and inference latency per view side by side).

    .venv/bin/python -m bench.ablation --minutes 10     # about an hour on 2 CPU cores
    .venv/bin/python -m bench.ablation --quick          # 2 steps per row, 2 test views
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

from bench.common import LEGO, RESULTS, scene_metrics, stamp, starting_checkpoint, write_csv, write_json

ROWS = [
    ("UF", ("neighbours", "alignment", "refinement", "attention"), False),
    ("+NN", ("alignment", "refinement", "attention"), False),
    ("+3D-A", ("refinement", "attention"), False),
    ("+NRF", ("attention",), False),
    ("+GA", (), False),
    ("+PT", (), True),
]


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scene", type=Path, default=LEGO)
    p.add_argument("--minutes", type=float, default=10.0, help="fine-tuning budget of every row")
    p.add_argument("--steps", type=int, default=None, help="step budget instead of minutes")
    p.add_argument("--variant", default="micro")
    p.add_argument("--lr", type=float, default=1e-4, help="Adam learning rate of every row")
    p.add_argument("--crop", type=int, default=None)
    p.add_argument("--checkpoint", type=Path, default=None, help="pre-trained weights for the +PT row")
    p.add_argument("--max-views", type=int, default=None)
    p.add_argument("--rows", default=",".join(r[0] for r in ROWS), help="comma-separated subset of rows")
    p.add_argument("--quick", action="store_true", help="2 steps per row, crop 64, 2 test views")
    p.add_argument("--output", type=Path, default=RESULTS / "ablation")
    args = p.parse_args(argv)
    if args.quick:
        args.steps, args.crop, args.max_views = 2, args.crop or 64, args.max_views or 2
    return args


def run(args) -> list[dict]:
    from roguenerf.checkpoint import load_checkpoint
    from roguenerf.data.readers import load_scene
    from roguenerf.training import TrainConfig, evaluate, finetune

    scene = load_scene(args.scene)
    pretrained = starting_checkpoint(args.checkpoint, scratch=False)
    wanted = set(args.rows.split(","))
    base = stamp()
    work = Path(tempfile.mkdtemp(prefix="ablation_"))
    rows = []
    for name, without, from_checkpoint in ROWS:
        if name not in wanted:
            continue
        if from_checkpoint and pretrained is None:
            print(f"skipping {name}: no pre-trained checkpoint (give --checkpoint)", flush=True)
            continue
        config = TrainConfig(lr=args.lr, steps=args.steps, minutes=None if args.steps else args.minutes, crop=args.crop,
                             variant=None if from_checkpoint else args.variant, without=without, evaluate=False)
        result = finetune(scene, work / name.strip("+"), checkpoint=pretrained if from_checkpoint else None,
                          config=config)
        model, _ = load_checkpoint(result.checkpoint)
        report = evaluate(scene, model, max_views=args.max_views)
        row = {**base, "row": name, "without": " ".join(without) or "-",
               "start": "pretrained" if from_checkpoint else "scratch", "variant": result.config["variant"],
               "steps": result.steps, "minutes": round(result.seconds / 60, 3),
               "steps_per_s": round(result.steps / max(result.seconds, 1e-9), 4),
               "crop": result.config["crop_used"], "loss": result.loss_kind, **scene_metrics(report)}
        print(", ".join(f"{k}={v}" for k, v in row.items() if k not in base), flush=True)
        rows.append(row)
    return rows


def markdown(rows: list[dict]) -> str:
    if not rows:
        return "(no rows)\n"
    head = (f"Ablation on {rows[0]['views']} lego test views, equal budgets; {rows[0]['date']}, "
            f"{rows[0]['machine']}, commit {rows[0]['commit']}\n\n")
    lines = ["| row | switched off | start | steps | PSNR (dB) | gain (dB) | SSIM | steps/s | s/view |",
             "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['row']} | {r['without']} | {r['start']} | {r['steps']} | {r['enhanced_psnr']:.2f} | "
                     f"{r['gain_db']:+.2f} | {r['enhanced_ssim']:.4f} | {r['steps_per_s']:.3f} | "
                     f"{r['latency_s_per_view']:.3f} |")
    lines.append(f"| renders | | | | {rows[0]['render_psnr']:.2f} | | {rows[0]['render_ssim']:.4f} | | |")
    return head + "\n".join(lines) + "\n"


def main(argv=None) -> int:
    args = parse_args(argv)
    from roguenerf import runtime

    print(f"runtime: {runtime.configure()}", flush=True)
    rows = run(args)
    stem = args.output.name + ("_quick" if args.quick else "")
    csv_path = write_csv(args.output.with_name(stem + ".csv"), rows)
    write_json(args.output.with_name(stem + ".json"), rows)
    md_path = args.output.with_name(stem + ".md")
    md_path.write_text(markdown(rows))
    print(markdown(rows))
    print(f"wrote {csv_path}, {md_path} and the .json")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
