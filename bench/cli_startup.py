"""The one-view ``enhance`` command as a user runs it, at this checkout and at an older commit,
side by side: its wall-clock, the view time it prints, and the difference (imports, loading,
writing, exit).

    python -m bench.cli_startup --scene runs/sizes/dtu_scan37_fine_504x378 --view 000 \\
        --before ee6db0e [--repeats 6] [--output bench/results/cli_startup]

Every run starts without pose judgements of earlier runs (a first command on the scene; each
its own ``ROGUENERF_SETTLED_CACHE``); ``--keep-judgements`` lets a tree's runs share them, as a
user's later commands on the scene do (trees older than ``roguenerf.enhance.settled`` ignore it).

``--before`` is checked out into a temporary git worktree (removed after); both trees run with
this checkout's interpreter and packages, alternated (before, after, before, after ...), so a
busy machine slows both alike. Writes ``OUTPUT.csv`` (a row per run; date, machine, commit),
``OUTPUT.json`` (medians per tree) and ``OUTPUT.png``.
"""

from __future__ import annotations

import argparse
import re
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from bench.common import REPO, RESULTS, beside, older_tree, save_figure, stamp, write_csv, write_json

VIEW_LINE = re.compile(r"enhanced (\S+) in ([0-9.]+) s")


def run_enhance(tree: Path, scene: Path, view: str, output: Path, judgements: Path) -> tuple[float, float]:
    """Wall-clock of ``python -m roguecli enhance`` run from ``tree``, and the view time it prints;
    the command keeps its pose judgements in ``judgements`` (``ROGUENERF_SETTLED_CACHE``)."""
    start = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "roguecli", "enhance", str(scene), "--view", view,
                           "--output", str(output)], cwd=tree, capture_output=True, text=True,
                          env={"PYTHONPATH": str(tree), "PATH": "/usr/bin:/bin",
                               "ROGUENERF_SETTLED_CACHE": str(judgements)})
    wall = time.perf_counter() - start
    found = VIEW_LINE.search(proc.stdout + proc.stderr)
    if proc.returncode != 0 or found is None:
        raise SystemExit(f"enhance failed in {tree} (exit {proc.returncode}):\n{proc.stderr[-2000:]}")
    return wall, float(found.group(2))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scene", type=Path, required=True, help="scene folder with the view's render and depth")
    ap.add_argument("--view", required=True)
    ap.add_argument("--before", required=True, help="the older commit (any git revision)")
    ap.add_argument("--repeats", type=int, default=6)
    ap.add_argument("--output", type=Path, default=RESULTS / "cli_startup")
    ap.add_argument("--keep-judgements", action="store_true",
                    help="let each tree's runs share their pose judgements (roguenerf.enhance.settled), as "
                         "a user's later commands on the scene do; by default every run starts without any, "
                         "as a first command on the scene")
    args = ap.parse_args(argv)
    if args.repeats < 1:
        raise SystemExit(f"--repeats: expected 1 or more, got {args.repeats}")
    scene = args.scene.resolve()
    rows = []
    with older_tree(args.before) as (old, rev), tempfile.TemporaryDirectory() as tmp:
        trees = {"before": old, "after": REPO}
        for repeat in range(args.repeats):
            for name, tree in trees.items():
                judgements = Path(tmp) / (f"{name}-judgements" if args.keep_judgements else f"{name}-{repeat}")
                wall, view = run_enhance(tree, scene, args.view, Path(tmp) / f"{name}.png", judgements)
                rows.append({**stamp(), "tree": name, "revision": rev if name == "before" else "",
                             "repeat": repeat, "wall_s": round(wall, 3), "view_s": view,
                             "overhead_s": round(wall - view, 3)})
                print(f"{name}: wall {wall:.2f} s, view {view:.2f} s", flush=True)
    summary = {**stamp(), "command": " ".join(["python -m bench.cli_startup", *(argv or sys.argv[1:])]),
               "before": rev, "repeats": args.repeats,
               **{f"{name}_{key}": statistics.median(r[key] for r in rows if r["tree"] == name)
                  for name in ("before", "after") for key in ("wall_s", "view_s", "overhead_s")}}
    write_csv(beside(args.output, ".csv"), rows)
    write_json(beside(args.output, ".json"), summary)

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5, 3.5))
    for i, name in enumerate(("before", "after")):
        ax.scatter([i] * args.repeats, [r["overhead_s"] for r in rows if r["tree"] == name])
    ax.set_xticks([0, 1], [f"before ({summary['before']})", "after"])
    ax.set_ylabel("wall-clock minus view time (s)")
    ax.set_title(f"enhance {args.view}: {summary['before_overhead_s']:.2f} -> {summary['after_overhead_s']:.2f} s",
                 fontsize=9)
    fig.suptitle(f"{summary['date']} {summary['machine']} {summary['commit']}", fontsize=6)
    save_figure(fig, beside(args.output, ".png"))
    print(f"overhead (median): before {summary['before_overhead_s']:.2f} s, after {summary['after_overhead_s']:.2f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
