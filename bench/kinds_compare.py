"""Checkpoints side by side on the leave-one-kind-out figure (issue 35): the means of several
``python -m bench.kinds`` runs (their ``.json``), one row per checkpoint, field kind, scene and
condition, and a plot of the zero-shot gain without and with pose noise.

    python -m bench.kinds_compare bench/results/kinds/*.json --output bench/results/kinds_compare

Writes ``OUTPUT.csv`` and ``OUTPUT.png`` (date, machine and commit of this run, and each input's
own commit in the CSV).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from bench.common import beside, caption_line, save_figure, stamp, write_csv

PANELS = ((0.0, 0.0), (0.25, 0.02), (0.5, 0.05))
"""Zero-shot pose-noise levels plotted (degrees, share): none, the issue's 0.25° / 2 % and 0.5° / 5 %."""


def compare_rows(paths: list[Path]) -> list[dict]:
    """One row per checkpoint, kind, scene and condition, from each run's per-condition means."""
    rows = []
    for path in paths:
        run = json.loads(path.read_text())
        commit = run["rows"][0]["commit"] if run["rows"] else ""
        for m in run["means"]:
            checkpoint = next(r["checkpoint"] for r in run["rows"] if r["scene"] == m["scene"])
            rows.append({"checkpoint": Path(checkpoint).stem, "kind": m["kind"], "scene": m["scene"],
                         "stage": m["stage"], "minutes": m["minutes"], "noise_deg": m["noise_deg"],
                         "noise_share": m["noise_share"], "neighbours": m.get("neighbours"),
                         "model_neighbours": m.get("model_neighbours"), "views": m["views"],
                         "render_psnr": m["render_psnr"], "gain_db": m["gain_db"],
                         "worst_view_gain_db": m["worst_view_gain_db"], "flip_change": m["flip_change"],
                         "views_flip_better": m["views_flip_better"], "source": path.name, "source_commit": commit})
    return rows


def zero_shot(rows: list[dict], deg: float, share: float) -> dict[tuple[str, str], dict[str, float]]:
    """``{(kind, scene): {checkpoint: gain}}`` at one noise level, the model's own neighbour count."""
    out: dict[tuple[str, str], dict[str, float]] = {}
    for r in rows:
        own = r["neighbours"] is None or r["neighbours"] == r["model_neighbours"]
        if r["stage"] == "zero-shot" and own and (r["noise_deg"], r["noise_share"]) == (deg, share):
            out.setdefault((r["kind"], r["scene"]), {})[r["checkpoint"]] = r["gain_db"]
    return out


def plot(rows: list[dict], path: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    checkpoints = list(dict.fromkeys(r["checkpoint"] for r in rows))
    fig, axes = plt.subplots(1, len(PANELS), figsize=(5 * len(PANELS), 4), sharey=True)
    width = 0.8 / max(1, len(checkpoints))
    for ax, (deg, share) in zip(axes, PANELS, strict=True):
        table = zero_shot(rows, deg, share)
        pairs = sorted(table)
        for k, name in enumerate(checkpoints):
            xs = [i + k * width for i, p in enumerate(pairs) if name in table[p]]
            ys = [table[p][name] for p in pairs if name in table[p]]
            ax.bar(xs, ys, width, label=name)
        ax.set_xticks([i + 0.4 - width / 2 for i in range(len(pairs))], [f"{k}\n{s}" for k, s in pairs], fontsize=7)
        ax.axhline(0, color="grey", lw=0.8)
        ax.set_title(f"zero-shot, pose noise {deg:g}° / {share:.0%}", fontsize=8)
    axes[0].set_ylabel("PSNR gain over renders, held-out views (dB)", fontsize=8)
    axes[0].legend(fontsize=7)
    caption_line(fig, [stamp()], "leave-one-kind-out")
    return save_figure(fig, path)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("runs", type=Path, nargs="+", help="bench.kinds JSON outputs")
    p.add_argument("--output", type=Path, required=True, help="OUTPUT.csv and OUTPUT.png")
    args = p.parse_args(argv)
    missing = [str(r) for r in args.runs if not r.is_file()]
    if missing:
        p.error(f"not a file: {', '.join(missing)}")
    rows = compare_rows(args.runs)
    base = stamp()
    csv_path = write_csv(beside(args.output, ".csv"), [{**base, **r} for r in rows])
    png = plot(rows, beside(args.output, ".png"))
    print(f"wrote {csv_path} and {png}")
    for deg, share in PANELS:
        for (kind, scene), gains in sorted(zero_shot(rows, deg, share).items()):
            cells = "  ".join(f"{c} {g:+.2f}" for c, g in gains.items())
            print(f"noise {deg:g}/{share:g} {kind:<6} {scene:<10} {cells}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
