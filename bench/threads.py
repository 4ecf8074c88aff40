"""Process-level settings against enhancement time: threads, OpenMP wait policy, allocator.

    python -m bench.threads --output bench/results/threads.csv [--variant micro] [--size 378x504]
                            [--repeats 5] [--trials 1]
    python -m bench.threads --cli-evaluate ../shared/data/lego --output bench/results/threads_cli.csv
                            [--trials 2]

``--cli-evaluate SCENE`` times the whole ``roguenerf evaluate SCENE --json`` command instead (a
fresh CLI process per run; wall time from start to exit, and the CLI's own seconds per view),
idle and beside the competing process, with the CLI's own choice (no variable set: PASSIVE
since issue 17), libgomp's default (``GOMP_SPINCOUNT=300000``, what an unset policy means) and
a shorter spin (``GOMP_SPINCOUNT=10000``).

Each configuration runs in a fresh child process (OpenMP reads its wait policy when torch is
imported), on an idle machine and again beside a competing process that keeps both cores
busy with float32 matmuls on 2 threads (as a fine-tuning job beside the service would), once
with OpenMP's default wait policy in the competitor and once with ``PASSIVE`` (what the
project's fine-tuning worker sets). The
child builds the variant with random weights, caches 5 neighbours' sampling sources as
``SceneEnhancer`` does, warms up twice and reports the median of ``--repeats`` forwards
(``torch.inference_mode``). Writes CSV (date, machine, commit) and a PNG bar chart.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import subprocess
import sys
import time
from pathlib import Path

from bench.common import beside, save_figure, stamp, write_csv

CHILD = r"""
import json, statistics, sys, time
sys.path.insert(0, {repo!r})
import torch
from roguenerf import runtime
applied = runtime.configure({threads})
from bench.stages import make_inputs
from roguenerf.models import build_enhancer
torch.manual_seed(0)
model = build_enhancer({variant!r}).eval()
with torch.inference_mode():
    render, depth, K, pose, nb = make_inputs(model, {h}, {w}, 5)
    run = lambda: model(render, depth, K, pose, nb)
    run(); run()
    times = []
    for _ in range({repeats}):
        t = time.perf_counter(); run(); times.append(time.perf_counter() - t)
print(json.dumps(dict(applied, seconds=statistics.median(times))))
"""

COMPETITOR = "import torch\ntorch.set_num_threads(2)\na = torch.randn(1024, 1024)\nwhile True:\n    a @ a\n"

LOADS = [  # (label, the competitor's OMP_WAIT_POLICY): none; a default process; a process like
    # the fine-tuning worker, which sets PASSIVE (workers/__main__.py)
    ("idle", None), ("competing process", None), ("competing PASSIVE process", "PASSIVE"),
]

CONFIGS = [  # (threads, OMP_WAIT_POLICY or None for the default, keep freed memory)
    (2, None, True), (2, "PASSIVE", True), (2, "ACTIVE", True), (1, None, True), (2, None, False),
]


CLI_CONFIGS = [  # (label, extra environment of the CLI process)
    ("CLI as shipped (PASSIVE)", {}),
    ("libgomp default (GOMP_SPINCOUNT=300000)", {"GOMP_SPINCOUNT": "300000"}),
    ("GOMP_SPINCOUNT=10000", {"GOMP_SPINCOUNT": "10000"}),
]


def _clean_env() -> dict:
    return {k: v for k, v in os.environ.items()
            if k not in ("OMP_WAIT_POLICY", "OMP_NUM_THREADS", "GOMP_SPINCOUNT")}


@contextlib.contextmanager
def competing(env: dict | None):
    """A process keeping both cores busy (``COMPETITOR``, in ``env``) while the block runs, started
    2 s before it; none for ``env`` None (idle)."""
    if env is None:
        yield
        return
    competitor = subprocess.Popen([sys.executable, "-c", COMPETITOR], env=env)
    time.sleep(2.0)
    try:
        yield
    finally:
        competitor.kill()
        competitor.wait()


def run_cli_evaluate(scene: Path, extra_env: dict) -> dict:
    """One ``roguenerf evaluate SCENE --json`` process: wall seconds, the CLI's seconds per view."""
    env = {**_clean_env(), **extra_env}
    load = os.getloadavg()[0]
    t0 = time.perf_counter()
    out = subprocess.run([sys.executable, "-m", "roguecli", "evaluate", str(scene), "--json"], env=env,
                         capture_output=True, text=True, check=True)
    wall = time.perf_counter() - t0
    report = json.loads(out.stdout)
    return {"wall_s": round(wall, 2), "seconds_per_view": round(report["seconds_per_view"], 4),
            "views": len(report["views"]), "enhanced_psnr": round(report["enhanced"]["psnr"], 4),
            "loadavg_1min_before": round(load, 2)}


def cli_main(args, meta: dict) -> None:
    rows = []
    for load in ("idle", "competing process"):
        with competing(None if load == "idle" else _clean_env()):
            for trial in range(1 if load == "idle" else max(1, args.trials)):
                for label, extra in CLI_CONFIGS:
                    r = run_cli_evaluate(args.cli_evaluate, extra)
                    rows.append({**meta, "command": f"roguenerf evaluate {args.cli_evaluate} --json",
                                 "load": load, "setting": label, "trial": trial, **r})
                    print(f"{load:18s} {label:40s} trial {trial}: {r['wall_s']:.1f} s "
                          f"({r['seconds_per_view']:.3f} s/view, load {r['loadavg_1min_before']})", flush=True)
    write_csv(beside(args.output, ".csv"), rows)
    print(f"wrote {beside(args.output, '.csv')}")


def run_child(repo: Path, variant: str, h: int, w: int, repeats: int, threads: int, policy: str | None,
              keep: bool) -> dict:
    env = {k: v for k, v in os.environ.items() if k not in ("OMP_WAIT_POLICY", "OMP_NUM_THREADS")}
    if policy:
        env["OMP_WAIT_POLICY"] = policy
    env["ROGUENERF_KEEP_FREED_MEMORY"] = "1" if keep else "0"
    code = CHILD.format(repo=str(repo), threads=threads, variant=variant, h=h, w=w, repeats=repeats)
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--output", required=True, type=Path)
    p.add_argument("--variant", default="micro")
    p.add_argument("--size", default="378x504", help="HxW")
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--trials", type=int, default=1,
                   help="child processes per configuration beside a competitor (the default wait "
                        "policy's slowdowns come and go with the process, so one child can miss them)")
    p.add_argument("--cli-evaluate", type=Path, metavar="SCENE",
                   help="time `roguenerf evaluate SCENE --json` processes instead of bare forwards")
    args = p.parse_args(argv)
    if args.cli_evaluate is not None:
        cli_main(args, stamp())
        return
    h, w = (int(v) for v in args.size.lower().split("x"))
    repo = Path(__file__).resolve().parents[1]
    meta = stamp()
    rows = []
    for load, competitor_policy in LOADS:
        env = None
        if load != "idle":
            env = {k: v for k, v in os.environ.items() if k not in ("OMP_WAIT_POLICY", "OMP_NUM_THREADS")}
            if competitor_policy:
                env["OMP_WAIT_POLICY"] = competitor_policy
        with competing(env):
            for threads, policy, keep in CONFIGS:
                if load != "idle" and not keep:
                    continue
                for trial in range(1 if load == "idle" else max(1, args.trials)):
                    r = run_child(repo, args.variant, h, w, args.repeats, threads, policy, keep)
                    row = {**meta, "variant": args.variant, "height": h, "width": w, "load": load,
                           "threads": threads, "omp_wait_policy": policy or "default",
                           "keep_freed_memory": keep, "trial": trial, "seconds": round(r["seconds"], 4)}
                    rows.append(row)
                    print(f"{load:18s} threads={threads} policy={policy or 'default':8s} keep_freed={keep!s:5s} "
                          f"trial {trial}: {r['seconds']:.3f} s", flush=True)
    write_csv(beside(args.output, ".csv"), rows)
    plot(rows, beside(args.output, ".png"))
    print(f"wrote {beside(args.output, '.csv')} and {beside(args.output, '.png')}")


def plot(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(12, 4.5))
    no_keep = "\nfreed memory returned"
    short = {"idle": "idle", "competing process": "busy", "competing PASSIVE process": "busy PASSIVE"}
    palette = {"idle": "tab:blue", "competing process": "tab:red"}
    groups: dict[tuple, list[float]] = {}
    for r in rows:  # one bar (median) per configuration, one dot per child process (trial)
        key = (r["load"], r["threads"], r["omp_wait_policy"], r["keep_freed_memory"])
        groups.setdefault(key, []).append(r["seconds"])
    for i, (key, secs) in enumerate(groups.items()):
        ax.bar(i, sorted(secs)[len(secs) // 2], color=palette.get(key[0], "tab:orange"), alpha=0.6)
        ax.plot([i] * len(secs), secs, "k.", ms=4)
    labels = [f"{short.get(k[0], k[0])}\n{k[1]}t {k[2]}" + ("" if k[3] else no_keep) for k in groups]
    ax.set_xticks(range(len(groups)), labels, fontsize=7)
    ax.set_yscale("log")
    ax.set_ylabel("seconds per enhancement (bar: median child, dots: each child)")
    r0 = rows[0]
    ax.set_title(f"{r0['variant']} {r0['width']}x{r0['height']}, 5 neighbours - {r0['date']} - {r0['commit']}\n"
                 f"{r0['machine']}", fontsize=8)
    save_figure(fig, path)


if __name__ == "__main__":
    main()
