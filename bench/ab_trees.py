"""Time the enhancement of two checkouts of the code alternately, run by run, in one session.

    git worktree add /tmp/base <commit>
    python -m bench.ab_trees /tmp/base . --variant micro --size 378x504 --repeats 15 \
        --output bench/results/ab.json

On a shared machine the load drifts between two separate ``bench/stages.py`` runs; here each
checkout runs in its own worker process (same interpreter and packages, ``sys.path`` pointing
at its tree) on ``bench/stages.py``'s inputs (5 neighbours with cached sampling sources, random
weights, ``torch.inference_mode``), and the driver alternates the two forwards A, B, A, B ...,
(B, A in every second pair), so both see the same load. Reports per tree the median and
minimum wall seconds of the fast path (C kernels on), the median CPU seconds of the process
(all threads: less sensitive to other processes' load than wall time, as OpenMP waits
passively), and whether the two trees' outputs are bitwise equal.
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

WORKER = r"""
import sys, time
sys.path.insert(0, sys.argv[1])
import roguenerf  # first: OpenMP's wait policy is set before torch loads
import torch
from bench.stages import make_inputs, randomise_zero_layers
from roguenerf import runtime
from roguenerf.models import build_enhancer

runtime.configure()
torch.manual_seed(0)
model = build_enhancer(sys.argv[2]).eval()
randomise_zero_layers(model)
h, w = int(sys.argv[3]), int(sys.argv[4])
with torch.inference_mode():
    inputs = make_inputs(model, h, w)
    out = model(*inputs)
    torch.save(out.clone(), sys.argv[5])
    print("ready", flush=True)
    for line in sys.stdin:
        t, c = time.perf_counter(), time.process_time()
        model(*inputs)
        print(time.perf_counter() - t, time.process_time() - c, flush=True)
"""


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("base", type=Path, help="checkout A (e.g. a git worktree of the old commit)")
    p.add_argument("new", type=Path, help="checkout B")
    p.add_argument("--variant", default="micro")
    p.add_argument("--size", default="378x504", help="HxW")
    p.add_argument("--repeats", type=int, default=15)
    p.add_argument("--output", type=Path, help="JSON to write (optional)")
    args = p.parse_args(argv)
    h, w = (int(x) for x in args.size.lower().split("x"))
    tmp = Path(tempfile.mkdtemp())
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    workers = {}
    for name, tree in (("base", args.base), ("new", args.new)):
        workers[name] = subprocess.Popen(
            [sys.executable, "-c", WORKER, str(tree.resolve()), args.variant, str(h), str(w), str(tmp / f"{name}.pt")],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, cwd=tree, env=env)
    try:
        for name, proc in workers.items():
            if proc.stdout.readline().strip() != "ready":
                raise SystemExit(f"{name}: the worker did not start (exit {proc.wait()})")
        times = {name: [] for name in workers}
        cpu = {name: [] for name in workers}
        for i in range(args.repeats):
            for name in (("base", "new") if i % 2 == 0 else ("new", "base")):
                proc = workers[name]
                proc.stdin.write("run\n")
                proc.stdin.flush()
                wall, used = proc.stdout.readline().split()
                times[name].append(float(wall))
                cpu[name].append(float(used))
    finally:
        for proc in workers.values():
            proc.stdin.close()
            proc.wait()
    import torch

    equal = torch.equal(torch.load(tmp / "base.pt"), torch.load(tmp / "new.pt"))
    result = {name: {"tree": str(getattr(args, name).resolve()), "median_s": statistics.median(t), "min_s": min(t),
                     "median_cpu_s": statistics.median(cpu[name]), "seconds": t, "cpu_seconds": cpu[name]}
              for name, t in times.items()}
    result.update(variant=args.variant, height=h, width=w, repeats=args.repeats, outputs_bitwise_equal=equal,
                  ratio_new_over_base=result["new"]["median_s"] / result["base"]["median_s"],
                  cpu_ratio_new_over_base=result["new"]["median_cpu_s"] / result["base"]["median_cpu_s"])
    for name in workers:
        print(f"{name}: median {result[name]['median_s']:.4f} s, min {result[name]['min_s']:.4f} s, "
              f"CPU median {result[name]['median_cpu_s']:.4f} s ({result[name]['tree']})")
    print(f"new / base: wall medians {result['ratio_new_over_base']:.3f}, CPU medians "
          f"{result['cpu_ratio_new_over_base']:.3f}; outputs bitwise equal: {equal}")
    if args.output:
        from bench.common import write_json

        write_json(args.output, result)
        print(f"wrote {args.output}")


if __name__ == "__main__":
    main()
