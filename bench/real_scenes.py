"""Honest evaluation on real scenes kept out of pre-training (issue 11).

For every scene folder given (made by ``python -m roguefit.batch`` from ``../shared/data/real``;
the held-out scenes are never pre-trained on, and only their training views are fine-tuned on):

- the renders' PSNR/SSIM/FLIP on the held-out (test) views;
- zero-shot: the old and the new default checkpoint, no fine-tuning;
- after ``finetune --minutes M`` for each M in ``--minutes`` (1, 3, 10), from the new checkpoint,
  evaluated after each budget: a fresh run per budget when the plan's learning rate follows a
  schedule over its budget (the default, cosine: a 1-minute run decays within its minute);
  with a constant lr, one run that resumes exactly from its saved state (the same steps);

each with its mean gain, SSIM, the worst view's gain, steps and seconds. Writes CSV + a plot of
gain against fine-tuning minutes (date, machine, commit on every row and in the plot's title).

``--plans default,whole`` fine-tunes each scene once per plan, in this one sitting (issue 12's
gain per minute: ``default`` is the shipped CPU plan, ``whole`` the same plan with every
neighbour photo encoded whole each step, the training step before crop windows; ``n5``,
``crop96``, ``lr5e-4``, ``lr1e-4``, ``constant`` and ``cosine`` (the lr schedule), ``frozen``
and ``trained`` (conv_H fixed with its features encoded once, or trained) are the
alternatives weighed for the CPU defaults; ``seed1`` and ``seed2`` are the default plan with
another seed (crops, order), for the run-to-run spread of one plan; ``warp4``/``warp8`` warp
the target render and depth of half the crops by up to 4/8 px (``render_warp``; blurring the
target render instead, ``blur1``/``blur2``, was measured to hurt and removed: docs/results.md);
``drawn50``/``drawn100`` take half or all of the crops' target renders from the nearest training
view's render drawn into the view (``neighbour_renders``); ``guard`` judges the finished
fine-tune (``TrainConfig.guard``; where it keeps the starting weights, the fine-tuned ones are
evaluated too, as ``guard (refused weights)``);
``bench/results/real_scenes.csv`` compared ``default`` when its lr was 1e-4 with ``lr5e-4``,
after which 5e-4 became the default). Same data, seed and start.

``--blends 0.5,0.85`` also evaluates each fine-tune's weights blended with the starting
checkpoint's (weight-space ensembling, start + a (tuned - start)), with no extra training.

    .venv/bin/python -m bench.real_scenes ~/.cache/roguenerf/pairs/dtu_scan37/fine \\
        ~/.cache/roguenerf/pairs/mary_rose/fine --old-checkpoint old.safetensors
    .venv/bin/python -m bench.real_scenes SCENE --quick      # seconds-long budgets (proves it runs)
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

from bench.common import RESULTS, add_stage_switches, configure_runtime, save_figure, scene_label, stamp, write_outputs

PLANS = {
    "default": {},
    "whole": {"neighbour_encoding": "whole"},
    "n5": {"num_neighbours": 5},
    "crop96": {"crop": 96},
    "lr5e-4": {"lr": 5e-4},
    "lr1e-4": {"lr": 1e-4},
    "constant": {"lr_schedule": "constant"},
    "cosine": {"lr_schedule": "cosine"},
    "frozen": {"freeze_neighbour_encoder": True},
    "trained": {"freeze_neighbour_encoder": False},
    "seed1": {"seed": 1},
    "seed2": {"seed": 2},
    "warp4": {"render_warp": 4.0},
    "warp8": {"render_warp": 8.0},
    "drawn50": {"neighbour_renders": 0.5},
    "drawn100": {"neighbour_renders": 1.0},
    "guard": {"guard": True},
}
"""Fine-tuning plans as TrainConfig overrides of the shipped CPU plan (``--plans``)."""


def _floats(text: str) -> list[float]:
    return [float(x) for x in text.split(",") if x.strip()]


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("scenes", type=Path, nargs="*", help="scene folders (renders from roguefit)")
    p.add_argument("--checkpoint", type=Path, default=None, help="new checkpoint (default: the shipped default)")
    p.add_argument("--old-checkpoint", type=Path, default=None, help="the checkpoint to compare zero-shot against")
    p.add_argument("--minutes", type=_floats, default=[1, 3, 10], help="comma-separated fine-tuning budgets")
    p.add_argument("--max-views", type=int, default=None)
    add_stage_switches(p)
    p.add_argument("--plans", type=lambda t: [x for x in t.split(",") if x], default=["default"],
                   help=f"comma-separated fine-tuning plans: {', '.join(PLANS)}")
    p.add_argument("--replot", type=Path, nargs="+", default=None, metavar="CSV",
                   help="measure nothing: merge these CSVs (one sitting, e.g. plans run in turn) into "
                        "OUTPUT.csv and OUTPUT.png; a scene's repeated zero-shot rows are kept once")
    p.add_argument("--blends", type=_floats, default=[],
                   help="after each fine-tune, also evaluate its weights blended with the starting "
                        "checkpoint's: start + a (tuned - start) for each comma-separated a in [0, 1] "
                        "(weight-space ensembling; rows with plan_name PLAN+blendA, no extra training)")
    p.add_argument("--quick", action="store_true", help="tiny budgets, 2 views")
    p.add_argument("--output", type=Path, default=RESULTS / "real_scenes")
    args = p.parse_args(argv)
    unknown = [x for x in args.plans if x not in PLANS]
    if unknown:
        p.error(f"--plans: unknown {', '.join(unknown)} (known: {', '.join(PLANS)})")
    if any(not 0.0 <= a <= 1.0 for a in args.blends):
        p.error(f"--blends: expected fractions in [0, 1], got {args.blends}")
    if not args.scenes and not args.replot:
        p.error("give scene folders to measure, or --replot CSV...")
    if args.quick:
        args.minutes = [0.02, 0.05]
        args.max_views = args.max_views or 2
    return args


def summarise(report: dict) -> dict:
    """Mean render/enhanced PSNR, SSIM and FLIP (lower is better; ``views_flip_better`` counts the
    views whose FLIP fell), gain, the worst view's gain, and every view's gain
    (``view_gains_db``: ``name:gain`` pairs joined by spaces, in the report's order)."""
    gains = [v["enhanced"]["psnr"] - v["render"]["psnr"] for v in report["views"]]
    worst = min(range(len(gains)), key=gains.__getitem__)
    r, e = report["render"], report["enhanced"]
    return {"views": len(gains), "render_psnr": round(r["psnr"], 4), "enhanced_psnr": round(e["psnr"], 4),
            "gain_db": round(e["psnr"] - r["psnr"], 4), "render_ssim": round(r["ssim"], 5),
            "enhanced_ssim": round(e["ssim"], 5), "ssim_gain": round(e["ssim"] - r["ssim"], 5),
            "render_flip": round(r["flip"], 5), "enhanced_flip": round(e["flip"], 5),
            "flip_change": round(e["flip"] - r["flip"], 5),
            "views_flip_better": sum(v["enhanced"]["flip"] < v["render"]["flip"] for v in report["views"]),
            "worst_view": report["views"][worst]["name"], "worst_view_gain_db": round(gains[worst], 4),
            "view_gains_db": " ".join(f"{v['name']}:{g:+.3f}" for v, g in zip(report["views"], gains))}


def run(args, save=None) -> list[dict]:
    """The rows; ``save(rows)`` is called after each one (a long run loses nothing on a crash)."""
    from roguenerf.checkpoint import blend_state, default_checkpoint_path, load_checkpoint
    from roguenerf.data.readers import load_scene
    from roguenerf.enhance import EnhanceOptions
    from roguenerf.training import TrainConfig, evaluate, finetune, plan_training

    new = args.checkpoint or default_checkpoint_path()
    base = stamp()
    rows = []
    work = Path(tempfile.mkdtemp(prefix="real_scenes_"))
    start = load_checkpoint(new)[0].state_dict() if args.blends else None  # what --blends mixes with

    def measure(scene, model) -> dict:
        return evaluate(scene, model, max_views=args.max_views, options=EnhanceOptions.from_flags(
            align=args.align == "on", colour=args.colour == "on", trust=args.trust == "on"))

    for scene_dir in args.scenes:
        scene = load_scene(scene_dir)
        label = scene_label(scene_dir)

        def record(kind: str, minutes: float, steps: int, seconds: float, report: dict, *, label: str = label,
                   **extra) -> None:
            row = {**base, "scene": label, "kind": kind, "minutes": minutes, "steps": steps, "align": args.align,
                   "colour": args.colour, "trust": args.trust,
                   "train_seconds": round(seconds, 1), **summarise(report), **extra}
            print(", ".join(f"{k}={v}" for k, v in row.items() if k not in base), flush=True)
            rows.append(row)
            if save is not None:
                save(rows)

        for kind, ckpt in (("zero-shot old", args.old_checkpoint), ("zero-shot new", new)):
            if ckpt is None:
                continue
            model, _ = load_checkpoint(ckpt)
            record(kind, 0.0, 0, 0.0, measure(scene, model), checkpoint=str(ckpt))
        for plan_name in args.plans:
            scheduled = plan_training(scene, TrainConfig(**PLANS[plan_name])).lr_schedule != "constant"
            for minutes in sorted(args.minutes):
                run_dir = work / f"{label.replace('/', '_')}_{plan_name}" / (f"{minutes:g}min" if scheduled else "")
                config = TrainConfig(minutes=minutes, evaluate=False, **PLANS[plan_name])
                result = finetune(scene, run_dir, checkpoint=new, config=config)
                model, _ = load_checkpoint(result.checkpoint)
                c = result.config
                plan = (f"{c['variant']} crop {c['crop_used']} batch {c['batch']} n{c['num_neighbours']} "
                        f"{c['neighbour_encoding']}{'+frozen' if c.get('freeze_neighbour_encoder') else ''} "
                        f"lr {c['lr']:g} {c['lr_schedule']}")
                record("finetune", minutes, result.steps, result.seconds,
                       measure(scene, model), checkpoint=str(new), plan_name=plan_name,
                       plan=plan, **guard_columns(result.guard))
                if result.guard and not result.guard["kept"]:  # what the guard refused, measured
                    record("finetune", minutes, result.steps, result.seconds,
                           measure(scene, refused_weights(run_dir)), checkpoint=str(new),
                           plan_name=f"{plan_name} (refused weights)", plan=plan, **guard_columns(result.guard))
                if args.blends:
                    tuned = {k: v.clone() for k, v in model.state_dict().items()}
                    for a in args.blends:
                        model.load_state_dict(blend_state(start, tuned, a))
                        record("finetune", minutes, result.steps, result.seconds,
                               measure(scene, model), checkpoint=str(new),
                               plan_name=f"{plan_name}+blend{a:g}", plan=f"{plan}, blend {a:g}")
    return rows


def refused_weights(run_dir: Path):
    """The fine-tuned weights of a run whose guard kept the starting ones: its resumable state's."""
    from roguenerf.models import EnhancerConfig, build_enhancer
    from roguenerf.training.loop import STATE_FILE
    from roguenerf.training.state import load_state

    saved = load_state(run_dir / STATE_FILE)
    model = build_enhancer(EnhancerConfig.from_dict(saved["info"]["model_config"]))
    model.load_state_dict(saved["model"])
    return model.eval()


def guard_columns(guard: dict | None) -> dict:
    """A fine-tune's guard report (``TrainResult.guard``) as row columns: kept or not, and the
    mean gains of the fine-tuned and starting weights on the drawn training views."""
    if not guard or not guard.get("views"):
        return {"guard_kept": None if guard is None else True}
    return {"guard_kept": guard["kept"], "guard_tuned_db": round(guard["tuned_mean_db"], 4),
            "guard_start_db": round(guard["start_mean_db"], 4), "guard_seconds": round(guard["seconds"], 1)}


def _save(fig, ax, rows: list[dict], path: Path) -> Path:
    """Stamp the plot with the rows' machine, commit and date; write it as PNG; close it."""
    if rows:
        ax.set_title(f"{rows[0]['machine'][:60]} | {rows[0]['commit']} | {rows[0]['date'][:10]}", fontsize=7)
    return save_figure(fig, path)


def zero_shot_summary(rows: list[dict]) -> list[dict]:
    """Per scene, in order of first appearance: the zero-shot gain and worst view's gain of the new
    checkpoint and (None when not measured) of the old one, dB."""
    out: dict[str, dict] = {}
    for r in rows:
        if r["kind"] in ("zero-shot new", "zero-shot old"):
            side = r["kind"].split()[-1]
            entry = out.setdefault(r["scene"], {"scene": r["scene"], "new": None, "new_worst": None,
                                                "old": None, "old_worst": None})
            entry[side], entry[f"{side}_worst"] = float(r["gain_db"]), float(r["worst_view_gain_db"])
    return [e for e in out.values() if e["new"] is not None]


def plot_zero_shot(rows: list[dict], path: Path) -> Path:
    """Zero-shot rows only (``--minutes ""``): one row of bars per scene, the old checkpoint's and
    the new one's mean gain, each bar's worst view as a black tick."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    summary = zero_shot_summary(rows)
    fig, ax = plt.subplots(figsize=(6.5, 1.3 + 0.34 * max(1, len(summary))))
    y = list(range(len(summary)))[::-1]
    half = 0.38
    for label, key, offset, colour in (("old checkpoint", "old", half / 2, "0.65"),
                                       ("new checkpoint", "new", -half / 2, "tab:blue")):
        pts = [(yy, e[key], e[f"{key}_worst"]) for yy, e in zip(y, summary) if e[key] is not None]
        if not pts:
            continue
        ys = [yy + offset for yy, _, _ in pts]
        ax.barh(ys, [g for _, g, _ in pts], height=half, color=colour, label=label)
        ax.scatter([w for _, _, w in pts], ys, marker="|", color="black", s=60, zorder=3)
    ax.scatter([], [], marker="|", color="black", label="worst view")
    ax.set_yticks(y, [e["scene"] for e in summary], fontsize=7)
    ax.axvline(0, color="grey", lw=0.8)
    ax.set_xlabel("zero-shot PSNR gain over renders, held-out views (dB)")
    ax.legend(fontsize=7, loc="lower right")
    return _save(fig, ax, rows, path)


def plot(rows: list[dict], path: Path) -> Path:
    """Gain against fine-tuning minutes per scene; zero-shot-only rows as bars (``plot_zero_shot``)."""
    if rows and not any(r["kind"] == "finetune" for r in rows):
        return plot_zero_shot(rows, path)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.5, 4))
    styles = ["o-", "s--", "^:", "d-."]
    for scene in dict.fromkeys(r["scene"] for r in rows):
        zero = [r for r in rows if r["scene"] == scene and r["kind"] == "zero-shot new"]
        plans = list(dict.fromkeys(r.get("plan_name", "default") for r in rows
                                   if r["scene"] == scene and r["kind"] == "finetune")) or ["default"]
        color = None
        for k, name in enumerate(plans):
            mine = zero + [r for r in rows if r["scene"] == scene and r["kind"] == "finetune"
                           and r.get("plan_name", "default") == name]
            label = scene if len(plans) == 1 else f"{scene}, plan {name}"
            line, = ax.plot([r["minutes"] for r in mine], [r["gain_db"] for r in mine], styles[k % len(styles)],
                            label=label, color=color)
            color = line.get_color()
        old = [r for r in rows if r["scene"] == scene and r["kind"] == "zero-shot old"]
        if old:
            ax.scatter([0], [old[0]["gain_db"]], marker="x", color=line.get_color(), label=f"{scene}: old checkpoint")
    ax.axhline(0, color="grey", lw=0.8)
    ax.set_xlabel("fine-tuning minutes (0 = zero-shot)")
    ax.set_ylabel("PSNR gain over renders, held-out views (dB)")
    ax.legend(fontsize=7)
    return _save(fig, ax, rows, path)


def merge(paths: list[Path]) -> list[dict]:
    """Rows of several real_scenes CSVs, numbers as numbers; a scene's zero-shot rows once."""
    import csv

    rows, seen = [], set()
    for path in paths:
        with Path(path).open(newline="") as fh:
            for row in csv.DictReader(fh):
                for key in ("minutes", "gain_db", "worst_view_gain_db", "ssim_gain"):
                    if row.get(key):
                        row[key] = float(row[key])
                if row["kind"].startswith("zero-shot"):
                    if (row["scene"], row["kind"]) in seen:
                        continue
                    seen.add((row["scene"], row["kind"]))
                rows.append(row)
    return rows


def main(argv=None) -> int:
    args = parse_args(argv)
    if args.replot:
        write_outputs(args.output, merge(args.replot), plot)
        return 0
    configure_runtime()
    run(args, save=lambda rows: write_outputs(args.output, rows, plot, quick=args.quick))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
