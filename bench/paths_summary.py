"""Every camera path of ``bench.paths`` side by side: flicker against gain, per path and setting.

    python -m bench.paths_summary [--results bench/results] [--output bench/results/paths_summary]

Reads the JSON of every ``bench.paths`` run whose name carries the path's shape
(``paths_<scene>_<fit>_<KEYS>x<STEPS>[_notemporal | _temporal_<setting>].json``, the names from
2026-11-29 on) and writes one row per run: the path, the setting (``off``, ``on`` as shipped
when it ran, or the ``--temporal`` setting), the camera's mean turn per frame, the flicker of the
enhanced frames over the render's, the gain on the frames with photos, the checkpoint, date and
commit. ``OUTPUT.csv``, ``OUTPUT.json`` (the rows, and per setting the mean over the paths that
have it) and ``OUTPUT.png`` (gain against flicker, a panel per path; the render's flicker at 1).
"""

from __future__ import annotations

import argparse
import json
import re
import statistics
import sys
from pathlib import Path

from bench.common import RESULTS, beside, save_figure, stamp, write_csv, write_json

NAME = re.compile(r"^paths_(?P<path>.+_\d+x\d+)(?:_(?P<off>notemporal)|_temporal_(?P<setting>.+))?$")


def parse_name(stem: str) -> tuple[str, str] | None:
    """``(path, setting)`` of a ``bench.paths`` result's file stem, or None for other names
    (older results without the path's shape, other benches)."""
    match = NAME.match(stem)
    if match is None:
        return None
    return match["path"], "off" if match["off"] else match["setting"] or "on"


def collect(results: Path) -> list[dict]:
    rows = []
    for path in sorted(results.glob("paths_*.json")):
        parsed = parse_name(path.stem)
        if parsed is None:
            continue
        report = json.loads(path.read_text())
        if "flicker" not in report or "psnr" not in report:
            continue
        rows.append({"path": parsed[0], "setting": parsed[1], "frames": report.get("frames"),
                     "size": report.get("size"), "turn_deg": (report.get("turn_deg") or {}).get("mean"),
                     "flicker_ratio": report["flicker"].get("ratio"),
                     "flicker_ratio_sharpened": report["flicker"].get("ratio_sharpened"),  # from 2026-12-07
                     "gain_db": report["psnr"].get("mean_gain_db"),
                     "checkpoint": Path(str(report.get("checkpoint", ""))).name, "date": report.get("date"),
                     "commit": report.get("commit"), "file": path.name})
    return rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--results", type=Path, default=RESULTS)
    ap.add_argument("--output", type=Path, default=RESULTS / "paths_summary")
    args = ap.parse_args(argv)
    rows = collect(args.results)
    if not rows:
        raise SystemExit(f"no bench.paths results named by the path's shape in {args.results}")
    settings = {}
    for r in rows:
        if r["flicker_ratio"] is not None and r["gain_db"] is not None:
            settings.setdefault(r["setting"], []).append(r)
    means = {s: {"paths": len(rs), "flicker_ratio": statistics.mean(r["flicker_ratio"] for r in rs),
                 "gain_db": statistics.mean(r["gain_db"] for r in rs)} for s, rs in settings.items()}
    write_csv(beside(args.output, ".csv"), rows)
    write_json(beside(args.output, ".json"), {**stamp(), "command": " ".join(["python -m bench.paths_summary",
                                                                              *(argv or sys.argv[1:])]),
                                              "rows": rows, "by_setting": means})

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    paths = sorted({r["path"] for r in rows})
    cols = min(4, len(paths))
    lines = (len(paths) + cols - 1) // cols
    fig, axes = plt.subplots(lines, cols, figsize=(4 * cols, 3.2 * lines), squeeze=False)
    for ax, name in zip(axes.flat, paths):
        for r in (r for r in rows if r["path"] == name and r["flicker_ratio"] is not None):
            ax.scatter(r["flicker_ratio"], r["gain_db"], s=14)
            ax.annotate(r["setting"], (r["flicker_ratio"], r["gain_db"]), xytext=(3, 3), textcoords="offset points",
                        fontsize=5)
        ax.axvline(1.0, color="0.6", lw=0.6)
        ax.set_title(name, fontsize=6)
        ax.set_xlabel("flicker / render's", fontsize=6)
        ax.set_ylabel("gain, frames with photos (dB)", fontsize=6)
        ax.tick_params(labelsize=5)
    for ax in list(axes.flat)[len(paths):]:
        ax.axis("off")
    info = stamp()
    fig.suptitle(f"bench.paths, every path and setting: {info['date']} {info['machine'][:70]} {info['commit']}",
                 fontsize=7)
    save_figure(fig, beside(args.output, ".png"))
    for s, m in sorted(means.items(), key=lambda kv: -kv[1]["paths"]):
        print(f"{s:40s} {m['paths']:3d} paths  flicker x{m['flicker_ratio']:.3f}  gain {m['gain_db']:+.3f} dB")
    print(f"wrote {beside(args.output, '.csv')}, {beside(args.output, '.json')} and {beside(args.output, '.png')}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
