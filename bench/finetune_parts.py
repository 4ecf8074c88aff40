"""Where a windowed fine-tuning step's time goes: forward + backward of the enhancer with each
neighbour component switched off in turn, on the same prepared batches, alternating, in one run.

    .venv/bin/python -m bench.finetune_parts --output bench/results/finetune_parts.json [--toy 378x504]

A toy scene (``make_toy_scene``, forward-facing, 12 training views) at ``--toy`` size; micro,
64 px crops, batch 4, 5 neighbours, ``neighbour_encoding="window"`` batches (three, reused).
Timed per configuration (fresh seeded models; no optimiser step): conv_H on the windows plus
enhancer forward, loss, backward. ``full``; ``no_attention``; ``no_refinement``; ``align_only``
(neither); ``no_neighbours`` (the full model given no neighbours: conv_I, merge, Uformer; its
conv_H forward still runs); ``convH_only`` (conv_H forward + backward on the windows alone).
Differences between rows are what each component costs. Median over ``--reps`` alternating
rounds. Writes a JSON with date, machine and commit.
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

import torch

from bench.common import stamp, write_json


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--output", required=True, type=Path)
    p.add_argument("--toy", default="378x504", help="HEIGHTxWIDTH of the toy scene")
    p.add_argument("--reps", type=int, default=6)
    args = p.parse_args(argv)
    from roguenerf import runtime

    print(f"runtime: {runtime.configure()}", flush=True)
    from roguenerf.data.toy import make_toy_scene
    from roguenerf.models import build_enhancer
    from roguenerf.training.batches import model_inputs, prepare_batch, sample_crops
    from roguenerf.training.loop import SceneData

    h, w = (int(v) for v in args.toy.lower().split("x"))
    with tempfile.TemporaryDirectory() as tmp:
        scene = make_toy_scene(tmp, seed=0, n_train=12, n_test=0, height=h, width=w, kind="forward")
        data = SceneData(scene, 5)
    g = torch.Generator().manual_seed(0)
    batches = []
    for _ in range(3):
        t = torch.randint(0, len(data), (4,), generator=g)
        batches.append(prepare_batch(data, t, sample_crops(data, 4, 64, g), 64, encoding="window", margin=2))
    variants = {"full": {}, "no_refinement": dict(use_refinement=False), "no_attention": dict(use_attention=False),
                "align_only": dict(use_refinement=False, use_attention=False)}
    models = {}
    for name, kw in variants.items():
        torch.manual_seed(0)
        models[name] = build_enhancer("micro", num_neighbours=5, **kw).train()
    base = stamp()
    times: dict[str, list[float]] = {k: [] for k in [*models, "no_neighbours", "convH_only"]}
    dev = torch.device("cpu")

    def timed(key, fn):
        t0 = time.perf_counter()
        fn()
        times[key].append(time.perf_counter() - t0)

    def step(m, b, neighbours=True):
        args_, photo = model_inputs(m, b, dev)
        if not neighbours:
            args_ = (*args_[:4], None)
        (m(*args_) - photo).abs().mean().backward()
        m.zero_grad(set_to_none=True)

    for r in range(args.reps):
        b = batches[r % len(batches)]
        for name, m in models.items():
            timed(name, lambda m=m, b=b: step(m, b))
        full = models["full"]
        timed("no_neighbours", lambda full=full, b=b: step(full, b, neighbours=False))

        def convh(full=full, b=b):
            sum(full.encode_neighbours(x).sum() for x in b.neighbour_photos).backward()
            full.zero_grad(set_to_none=True)

        timed("convH_only", convh)
    ms = {k: round(statistics.median(v) * 1e3, 1) for k, v in times.items()}
    print(ms, "ms forward + backward, median", flush=True)
    write_json(args.output, {**base, "scene": f"toy-{h}x{w}", "variant": "micro", "crop": 64, "batch": 4,
                             "neighbours": 5, "reps": args.reps, "median_ms": ms,
                             "all_s": {k: [round(x, 4) for x in v] for k, v in times.items()}})
    print(f"wrote {args.output}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
