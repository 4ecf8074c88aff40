"""Fine-tuning throughput on the CPU: training steps/s and target pixels/s against crop and batch,
for the two ways of encoding the neighbour photos, on one or more scenes, in one run.

    .venv/bin/python -m bench.finetune_throughput --output bench/results/finetune_throughput.csv \
        --skip 'T@256x8'

    # issue 12: old (whole photos, per-neighbour fusion) vs new (crop windows, batched fusion)
    # at 504x378 and 200x200, one run
    .venv/bin/python -m bench.finetune_throughput --output bench/results/finetune_batched.csv \
        --toy 378x504 --toy 200x200 --variants micro --crops 64 --batches 4 --neighbours 5 \
        --encodings whole-loop,whole,window --steps 6 --warmup 1 --rounds 2 --max-seconds 60 \
        --reference toy-200x200

    # issue 12, first step (crop windows only): the run of bench/results/finetune_windows.csv
    .venv/bin/python -m bench.finetune_throughput --output bench/results/finetune_windows.csv \
        --toy 378x504 --toy 200x200 --scene ../shared/data/lego --variants micro --crops 64 \
        --batches 4 --neighbours 5 --steps 8 --reference toy-200x200

    options: [--scene DIR ...] [--toy HxW ...] [--toy-views 24] [--encodings whole-loop,whole,window]
             [--variants micro,T] [--crops 64,128,256] [--batches 1,2,4,8] [--neighbours 2]
             [--steps 5] [--max-seconds 20] [--warmup 2] [--threads N] [--skip VARIANT@CROPxBATCH ...]
             [--reference SCENE]

About 5-8 minutes on 2 idle cores with the defaults (one scene, both encodings: twice that).
Memory grows with batch x crop: on lego, T at 200 px crops peaked at ~3 GB (batch 1) and
~5.6 GB (batch 2), micro at ~4.9 GB (batch 8), so T@256x8 (~20 GB) is skipped above.

Scenes: ``--scene`` (default lego when no ``--toy`` is given) and ``--toy HxW``: an
exact-geometry toy scene (``roguenerf.data.toy.make_toy_scene``, forward-facing like LLFF,
seed 0, ``--toy-views`` training views, renders = photos blurred) rendered at that size into a
temporary folder. LLFF scenes at 1/8 resolution are 504x378: ``--toy 378x504`` stands for them
while no real scene of that size has renders.

For every scene x variant x neighbours x crop x batch x encoding point, a fresh (seeded,
scratch) model and Adam optimiser make training steps on the scene's training views as
``finetune`` makes them: batches (B random c x c crops of renders, depths and photos, and the
neighbours they need) are drawn and cut in a background thread
(``roguenerf.training.batches.Prefetcher``), and each step is
``roguenerf.training.loop.optimise``: conv_H on the neighbour photos (with grad), enhancer
forward, loss (L1, or L1 + 1e-3 VGG-19 with ``--vgg-weights``), backward, finiteness checks,
Adam step (fused, as ``finetune`` makes it). Encodings (``TrainConfig.neighbour_encoding``):
``whole`` encodes the U distinct
neighbour photos the batch uses, whole; ``window`` only the window
of each neighbour photo that each crop can see (same loss and gradients); ``whole-loop`` is the
step before issue 12: whole photos, and each neighbour refined, weighed and pooled one at a time
(``reference_mode()``; ``whole`` and ``window`` run the neighbours as one batch, sharing the
target's work: same loss and gradients, tests/unit/roguenerf/training/test_training_batched.py). The timed step is
waiting for the next batch plus ``optimise``. Per point: up to ``--warmup`` untimed steps (no
more once they have taken ``--max-seconds``/4), then timed steps until ``--steps`` of them or
``--max-seconds`` (at least one is always timed). Reported: median seconds/step, steps/s =
1 / that, pixels/s = batch * crop_used^2 * steps/s (target pixels only), neighbour pixels
conv_H encoded per step (mean), and the process's peak RSS so far (ru_maxrss: process-wide and
monotone, so the maximum over this point and every point before it, not the point's own).

Crops larger than the scene's images are clamped to them, as in training (lego is 200 x 200:
a requested 256 trains on 200 x 200 crops; the ``crop_used`` column says so, pixels use it).
Neighbours default to what ``plan_training`` picks on a CPU (printed at start). Once a point
takes longer than ``--max-seconds`` for a single step, the points of that scene, variant,
encoding and neighbour count with both a larger-or-equal crop and batch are skipped (printed);
``--skip VARIANT@CROPxBATCH`` (shell-style wildcards, e.g. ``T@256x*``) skips points by hand.

Writes the CSV (every row: date, machine, commit, then scene, size, variant, crop, batch,
neighbours, encoding, threads, seconds_per_step, steps_per_s, pixels_per_s, then details)
after every point; at the end a JSON next to it (the rows, and per point the window/whole
speed-up and each scene's steps/s relative to ``--reference``), a PNG (steps/s per scene and
encoding, one panel per variant/crop/batch) and a table.

Not measured: scene loading and the neighbour lists (``SceneData``, once per run), the
periodic checkpoint saves (every 60 s in ``finetune``), evaluation before/after, the progress
bar and callbacks, pre-training's per-step scene draw, GPUs, resumed optimiser state, and
training quality (loss values are not compared; weights are a fresh scratch init: speed does not depend on them).
"""

from __future__ import annotations

import argparse
import fnmatch
import gc
import itertools
import resource
import statistics
import sys
import time
from pathlib import Path

import torch

from bench.common import LEGO, beside, save_figure, scene_label, stamp, write_csv

ENCODINGS = ("whole-loop", "whole", "window", "frozen")
"""Bench labels: ``whole`` and ``window`` are ``TrainConfig.neighbour_encoding``; ``whole-loop``
is the training step before issue 12: whole photos, and the enhancer's plain per-neighbour
fusion (``reference_mode()``, which in training switches off only the batched neighbour fusion);
``frozen`` is ``window`` with ``TrainConfig.freeze_neighbour_encoder``: conv_H fixed, the training
photos encoded once before timing (not counted), windows cut from those features."""


def _ints(text: str) -> list[int]:
    return [int(x) for x in text.split(",") if x.strip()]


def _names(text: str) -> list[str]:
    return [x.strip() for x in text.split(",") if x.strip()]


def parse_args(argv=None):
    from roguenerf.models import VARIANTS

    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--output", required=True, type=Path, help="CSV file to write (PNG plot goes next to it)")
    p.add_argument("--scene", type=Path, action="append", default=None,
                   help="scene with renders and depths (repeatable; default: lego unless --toy is given)")
    p.add_argument("--toy", action="append", default=[], metavar="HxW",
                   help="also a toy scene rendered at H x W (repeatable), e.g. 378x504")
    p.add_argument("--toy-views", type=int, default=24, help="training views of each toy scene")
    p.add_argument("--encodings", type=_names, default=["whole", "window"],
                   help="neighbour encodings to compare: whole, window, and the step before issue 12: "
                        "whole-loop (whole photos, neighbours fused one at a time)")
    p.add_argument("--rounds", type=int, default=1,
                   help="repeat the whole sweep this many times (interleaves scenes and encodings over time "
                        "on a busy machine); the JSON, plot and table use each point's median over rounds")
    p.add_argument("--reference", default=None,
                   help="scene label the others' steps/s are divided by in the JSON (default: the smallest)")
    p.add_argument("--variants", type=_names, default=["micro", "T"], help=f"comma-separated, from {sorted(VARIANTS)}")
    p.add_argument("--crops", type=_ints, default=[64, 128, 256], help="comma-separated crop sides")
    p.add_argument("--batches", type=_ints, default=[1, 2, 4, 8], help="comma-separated batch sizes")
    p.add_argument("--neighbours", type=_ints, default=None,
                   help="comma-separated neighbours per target (default: plan_training's on a CPU)")
    p.add_argument("--steps", type=int, default=5, help="timed steps per point (fewer if --max-seconds runs out)")
    p.add_argument("--max-seconds", type=float, default=20.0, help="time cap of the timed steps of one point")
    p.add_argument("--warmup", type=int, default=2, help="untimed steps per point before timing")
    p.add_argument("--skip", action="append", default=[], metavar="VARIANT@CROPxBATCH",
                   help="skip points, e.g. T@256x8 or T@256x* (repeatable)")
    p.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's choice)")
    p.add_argument("--lr", type=float, default=1e-4, help="Adam learning rate (as TrainConfig)")
    p.add_argument("--vgg-weights", type=Path, default=None, help="torchvision VGG-19 state dict: L1 + VGG loss")
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    bad = [e for e in args.encodings if e not in ENCODINGS]
    if bad or not args.encodings:
        p.error(f"--encodings: expected some of {', '.join(ENCODINGS)}, got {args.encodings}")
    try:
        args.toy = [tuple(int(v) for v in t.lower().split("x")) for t in args.toy]
    except ValueError:
        p.error(f"--toy: expected HEIGHTxWIDTH, got {args.toy}")
    if any(len(t) != 2 or min(t) < 16 for t in args.toy):
        p.error(f"--toy: expected HEIGHTxWIDTH of at least 16x16, got {args.toy}")
    if args.scene is None:
        args.scene = [] if args.toy else [LEGO]
    unknown = [v for v in args.variants if v not in VARIANTS]
    if unknown:
        p.error(f"--variants: unknown {unknown}; expected some of {sorted(VARIANTS)}")
    if args.steps < 1 or args.warmup < 0 or not args.max_seconds > 0:
        p.error("--steps must be >= 1, --warmup >= 0 and --max-seconds > 0")
    if any(c < 8 for c in args.crops) or any(b < 1 for b in args.batches):
        p.error("--crops must be >= 8 and --batches >= 1")
    return args


def peak_rss_mb() -> float:
    """Peak resident set size of this process so far (Linux reports ru_maxrss in KiB)."""
    kib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return kib / 1024 if sys.platform != "darwin" else kib / 2**20


def measure(variant: str, data, crop: int, batch: int, neighbours: int, encoding: str, args, loss_fn) -> dict:
    """Warm up, then time the training step on one point; returns its columns (after stamp's)."""
    import dataclasses

    from roguenerf.models import build_enhancer
    from roguenerf.training.batches import Prefetcher, prepare_batch, sample_crops
    from roguenerf.training.loop import batch_encoding, make_optimizer, neighbour_margin, optimise

    device = torch.device("cpu")
    torch.manual_seed(args.seed)
    model = build_enhancer(variant)  # scratch, as finetune(checkpoint=None, variant=...) starts
    if model.config.num_neighbours != neighbours and neighbours > 0:
        model.config = dataclasses.replace(model.config, num_neighbours=neighbours)
    model.to(device).train()
    optimizer = make_optimizer(model, args.lr)
    generator = torch.Generator().manual_seed(args.seed)
    from roguenerf.fastpath import reference_mode

    loop = encoding == "whole-loop"
    frozen = encoding == "frozen"
    margin = neighbour_margin(model)
    enc = batch_encoding(model, "whole" if loop else "window" if frozen else encoding)
    data.features = None
    if frozen and model.conv_H is not None:  # as finetune does with freeze_neighbour_encoder
        model.conv_H.requires_grad_(False)
        data.cache_features(model, device)

    def make():  # as finetune's batch thread draws them
        targets = torch.randint(0, len(data), (batch,), generator=generator)
        origins = sample_crops(data, batch, crop, generator)
        return prepare_batch(data, targets, origins, crop, encoding=enc, margin=margin,
                             use_neighbours=model.config.use_neighbours)

    encoded: list[int] = []
    windowed: list[bool] = []

    def step(pre, i: int) -> float:
        t0 = time.perf_counter()
        b = next(pre)
        with reference_mode(loop):
            optimise(model, b, device, loss_fn, optimizer, step=i)
        dt = time.perf_counter() - t0
        photos = b.neighbour_photos if isinstance(b.neighbour_photos, list) else [b.neighbour_photos]
        encoded.append(sum(p.shape[0] * p.shape[-2] * p.shape[-1] for p in photos if p is not None))  # 0 if cached
        windowed.append(b.encoding == "window")
        return dt

    with Prefetcher(make) as pre:
        warm, warm_s = 0, 0.0
        while warm < args.warmup and (warm == 0 or warm_s < args.max_seconds / 4):
            warm_s += step(pre, warm)
            warm += 1
        encoded.clear()
        windowed.clear()
        times: list[float] = []
        while len(times) < args.steps and (not times or sum(times) < args.max_seconds):
            times.append(step(pre, warm + len(times)))
    data.features = None
    crop_used = min(crop, data.height, data.width)
    sec = statistics.median(times)
    return {"variant": variant, "crop": crop, "batch": batch, "neighbours": neighbours, "encoding": encoding,
            "threads": torch.get_num_threads(), "seconds_per_step": round(sec, 5),
            "steps_per_s": round(1.0 / sec, 4), "pixels_per_s": round(batch * crop_used**2 / sec, 1),
            "crop_used": crop_used, "encoded_pixels_per_step": round(statistics.mean(encoded)),
            "window_batches": round(sum(windowed) / len(windowed), 3),
            "timed_steps": len(times), "warmup_steps": warm,
            "warmup_seconds": round(warm_s, 3), "min_seconds_per_step": round(min(times), 5),
            "max_seconds_per_step": round(max(times), 5), "loss": loss_fn.kind,
            "peak_rss_mb_so_far": round(peak_rss_mb(), 1)}


def plot(rows: list[dict], path: Path) -> Path:
    """Steps/s per scene, one bar per encoding; one panel per (variant, neighbours, crop, batch)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    points = list(dict.fromkeys((r["variant"], r["neighbours"], r["crop"], r["batch"]) for r in rows))
    scenes = list(dict.fromkeys(r["scene"] for r in rows))
    encodings = list(dict.fromkeys(r["encoding"] for r in rows))
    cols = min(len(points), 3)
    nrows = -(-len(points) // cols)
    fig, axes = plt.subplots(nrows, cols, figsize=(max(4.5, 1.6 * len(scenes) * len(encodings)) * cols, 4 * nrows),
                             squeeze=False)
    width = 0.8 / len(encodings)
    for ax, point in zip(axes.flat, points):
        mine = {(r["scene"], r["encoding"]): r for r in rows
                if (r["variant"], r["neighbours"], r["crop"], r["batch"]) == point}
        for k, enc in enumerate(encodings):
            xs = [i + (k - (len(encodings) - 1) / 2) * width for i in range(len(scenes))]
            ys = [mine[(sc, enc)]["steps_per_s"] if (sc, enc) in mine else 0.0 for sc in scenes]
            bars = ax.bar(xs, ys, width, label=enc, color=f"C{k}")
            ax.bar_label(bars, labels=[f"{y:.2f}" if y else "" for y in ys], fontsize=7)
        ax.set_xticks(range(len(scenes)), scenes, fontsize=8)
        ax.set_ylabel("training steps per second")
        variant, n, crop, batch = point
        ax.set_title(f"{variant}, crop {crop}, batch {batch}, {n} neighbours, loss {rows[0]['loss']}", fontsize=9)
        ax.grid(True, axis="y", alpha=0.3)
        ax.legend(fontsize=8, title="neighbour encoding", title_fontsize=8)
    for ax in list(axes.flat)[len(points):]:
        ax.axis("off")
    r0 = rows[0]
    fig.suptitle(f"fine-tuning throughput on CPU ({r0['threads']} threads) | {r0['date']} | {r0['commit']}\n"
                 f"{r0['machine']}", fontsize=8)
    return save_figure(fig, path)


def median_rows(rows: list[dict]) -> list[dict]:
    """One row per (scene, variant, neighbours, crop, batch, encoding): the median steps/s over rounds."""
    groups: dict[tuple, list[dict]] = {}
    for r in rows:
        key = (r["scene"], r["variant"], r["neighbours"], r["crop"], r["batch"], r["encoding"])
        groups.setdefault(key, []).append(r)
    out = []
    for group in groups.values():
        sps = statistics.median(r["steps_per_s"] for r in group)
        out.append({**group[0], "round": "median", "rounds": len(group), "steps_per_s": round(sps, 4),
                    "seconds_per_step": round(1.0 / sps, 5),
                    "pixels_per_s": round(group[0]["batch"] * group[0]["crop_used"] ** 2 * sps, 1),
                    "steps_per_s_per_round": [r["steps_per_s"] for r in group]})
    return out


def summary(rows: list[dict], reference: str | None) -> dict:
    """Per point: window/whole speed-up per scene, and each scene's steps/s over the reference's."""
    sizes = {r["scene"]: r["width"] * r["height"] for r in rows}
    reference = reference or min(sizes, key=sizes.get)
    out = []
    for point in dict.fromkeys((r["variant"], r["neighbours"], r["crop"], r["batch"]) for r in rows):
        mine = {(r["scene"], r["encoding"]): r["steps_per_s"] for r in rows
                if (r["variant"], r["neighbours"], r["crop"], r["batch"]) == point}
        entry = {"variant": point[0], "neighbours": point[1], "crop": point[2], "batch": point[3],
                 "steps_per_s": {f"{sc}/{enc}": v for (sc, enc), v in mine.items()}, "window_over_whole": {},
                 "window_over_whole_loop": {}, "frozen_over_window": {}, "frozen_over_whole_loop": {},
                 f"over_{reference}": {}}
        for sc in sizes:
            if (sc, "window") in mine and (sc, "whole") in mine:
                entry["window_over_whole"][sc] = round(mine[(sc, "window")] / mine[(sc, "whole")], 3)
            if (sc, "window") in mine and (sc, "whole-loop") in mine:
                entry["window_over_whole_loop"][sc] = round(mine[(sc, "window")] / mine[(sc, "whole-loop")], 3)
            for base in ("window", "whole-loop"):
                if (sc, "frozen") in mine and (sc, base) in mine:
                    ratio = mine[(sc, "frozen")] / mine[(sc, base)]
                    entry[f"frozen_over_{base.replace('-', '_')}"][sc] = round(ratio, 3)
            for enc in ENCODINGS:
                if (sc, enc) in mine and (reference, enc) in mine:
                    entry[f"over_{reference}"][f"{sc}/{enc}"] = round(mine[(sc, enc)] / mine[(reference, enc)], 3)
        out.append(entry)
    return {"reference": reference, "points": out}


def table(rows: list[dict]) -> str:
    head = (f"{'scene':>14} {'variant':>7} {'crop':>9} {'batch':>5} {'nbrs':>4} {'encoding':>8} {'s/step':>9} "
            f"{'steps/s':>8} {'kpx/s':>9} {'enc Mpx':>8} {'steps':>5} {'rss MB':>8}")
    lines = [head, "-" * len(head)]
    for r in rows:
        crop = f"{r['crop']}" if r["crop"] == r["crop_used"] else f"{r['crop']}->{r['crop_used']}"
        lines.append(f"{r['scene']:>14} {r['variant']:>7} {crop:>9} {r['batch']:>5} {r['neighbours']:>4} "
                     f"{r['encoding']:>8} {r['seconds_per_step']:>9.4f} {r['steps_per_s']:>8.3f} "
                     f"{r['pixels_per_s'] / 1e3:>9.1f} {r['encoded_pixels_per_step'] / 1e6:>8.3f} "
                     f"{r['timed_steps']:>5} {r['peak_rss_mb_so_far']:>8.0f}")
    return "\n".join(lines)


def load_scenes(args, tmp: Path) -> dict:
    """``{label: Scene}``: the ``--scene`` folders, then the ``--toy`` scenes rendered into ``tmp``."""
    from roguenerf.data.readers import load_scene
    from roguenerf.data.toy import make_toy_scene

    scenes = {}
    for path in args.scene:
        scenes[scene_label(path)] = load_scene(path)
    for h, w in args.toy:
        t0 = time.perf_counter()
        label = f"toy-{h}x{w}"
        scenes[label] = make_toy_scene(tmp / label, seed=args.seed, n_train=args.toy_views, n_test=0,
                                       height=h, width=w, kind="forward")
        print(f"{label}: rendered {args.toy_views} views in {time.perf_counter() - t0:.1f} s", flush=True)
    return scenes


def main(argv=None) -> int:
    args = parse_args(argv)
    from roguenerf import runtime

    print(f"runtime: {runtime.configure(args.threads or None)}", flush=True)

    import tempfile

    from bench.common import write_json
    from roguenerf.training import TrainConfig, plan_training
    from roguenerf.training.config import describe_plan
    from roguenerf.training.loop import SceneData
    from roguenerf.training.losses import build_loss

    tmp = tempfile.TemporaryDirectory(prefix="finetune-throughput-")
    scenes = load_scenes(args, Path(tmp.name))
    first = next(iter(scenes.values()))
    plan = plan_training(first, TrainConfig(), device="cpu")
    print(f"fine-tuning from scratch here would use: {describe_plan(plan)}", flush=True)
    neighbours = args.neighbours if args.neighbours is not None else [plan.num_neighbours]
    if args.neighbours is None:
        print(f"neighbours per target: {neighbours[0]} (plan_training's CPU choice)", flush=True)
    loss_fn = build_loss(args.vgg_weights, "cpu")

    base = stamp()
    rows: list[dict] = []
    datasets = {}
    for label, scene in scenes.items():
        for n in neighbours:
            t0 = time.perf_counter()
            datasets[label, n] = d = SceneData(scene, n)
            print(f"{label}: {len(d)} training views of {d.width}x{d.height}, {d.neighbours.shape[1]} neighbours "
                  f"each ({time.perf_counter() - t0:.1f} s)", flush=True)
            big = [c for c in args.crops if c > min(d.height, d.width)]
            if big:
                print(f"note: crops {big} exceed the {d.width}x{d.height} images: they train on "
                      f"{min(d.height, d.width)} px crops (column crop_used)", flush=True)

    json_path = beside(args.output, ".json")
    too_slow: dict[tuple, list] = {}  # (round, scene, variant, n, encoding) -> (crop_used, batch) over the cap
    for rnd, label, variant, n, crop, batch in itertools.product(
            range(args.rounds), scenes, args.variants, neighbours, sorted(args.crops), sorted(args.batches)):
        data = datasets[label, n]
        key = f"{variant}@{crop}x{batch}"
        crop_used = min(crop, data.height, data.width)
        if any(fnmatch.fnmatchcase(key, pattern) for pattern in args.skip):
            print(f"skip {key} (--skip)", flush=True)
            continue
        for encoding in args.encodings:  # old and new side by side, same process
            slow = too_slow.setdefault((rnd, label, variant, n, encoding), [])
            if any(crop_used >= c and batch >= b for c, b in slow):
                print(f"skip {label} {key} {encoding}: a smaller point already took more than --max-seconds "
                      f"per step", flush=True)
                continue
            point = measure(variant, data, crop, batch, n, encoding, args, loss_fn)
            row = {**base, "scene": label, "width": data.width, "height": data.height, "round": rnd, **point}
            gc.collect()  # the point's model, optimiser state and activations
            rows.append(row)
            print(", ".join(f"{k}={row[k]}" for k in list(row)[3:]), flush=True)
            write_csv(beside(args.output, ".csv"), rows)
            if row["seconds_per_step"] > args.max_seconds:
                slow.append((crop_used, batch))

    tmp.cleanup()
    if not rows:
        print("nothing measured")
        return 1
    medians = median_rows(rows)
    result = summary(medians, args.reference)
    write_json(json_path, {**base, "argv": sys.argv[1:] if argv is None else list(argv), **result,
                           "medians": medians, "rows": rows})
    png = plot(medians, beside(args.output, ".png"))
    print()
    print(table(rows))
    print()
    for entry in result["points"]:
        print(f"{entry['variant']} crop {entry['crop']} batch {entry['batch']} {entry['neighbours']} neighbours: "
              f"window/whole {entry['window_over_whole']}; window/whole-loop (the step before issue 12) "
              f"{entry['window_over_whole_loop']}; frozen/window {entry['frozen_over_window']}; "
              f"frozen/whole-loop {entry['frozen_over_whole_loop']}; over {result['reference']} "
              f"{entry['over_' + result['reference']]}")
    print(f"\nwrote {beside(args.output, '.csv')}, {json_path} and {png}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
