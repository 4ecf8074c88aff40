"""Which neighbours help a held-out view? Zero-shot diagnostics of the neighbour choice (issue 11).

For every scene folder and every held-out (test) view, with one checkpoint and no fine-tuning:

- ``single``: the gain with each of the ``--candidates`` nearest training views (the paper's
  rule's ranking) used alone;
- ``pair``: the shipped choice, the first two of that ranking;
- ``pair_agreement``: the two candidates whose photo, reprojected with the rendered depth,
  agrees best with the render (mean |difference| of 8x8 block means over the valid pixels): a
  rule that needs no photo of the target, tried as a replacement for the pose ranking;
- ``best_single`` / ``oracle``: the best single candidate, and the better of it and the pair
  (these need the target's photo: upper bounds, not rules);

and per scene, for ``n`` = 1, 2, 3 neighbours, the mean and worst gain on the held-out views and
on up to 12 training views, each enhanced with neighbours other than itself (leave-one-out:
what a user could measure on their own scene before choosing ``n``).

Writes ``OUTPUT.csv`` (one row per view and rule, then per scene and ``n``; date, machine and
commit on every row) and ``OUTPUT.png`` (per scene: mean gain of each rule).

    .venv/bin/python -m bench.neighbour_choice ~/.cache/roguenerf/pairs/mary_rose/coarse \\
        ~/.cache/roguenerf/pairs/dtu_scan37/coarse --output bench/results/neighbour_choice
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch
import torch.nn.functional as F

from bench.common import RESULTS, scene_label, stamp, write_outputs
from roguenerf.metrics import psnr

RULES = ("pair", "pair_agreement", "best_single", "oracle")


class _Target:
    """One view's render, depth, photo, camera and render PSNR, read once."""

    def __init__(self, scene, k: int):
        frame = scene.frames[k]
        self.render, self.depth, self.photo = scene.render(k), scene.depth(k), scene.photo(k)
        self.K, self.pose = frame.K.to(torch.float32), frame.world_from_cam.to(torch.float64)
        self.render_psnr = float(psnr(self.render, self.photo))

    def gain(self, image: torch.Tensor) -> float:
        return float(psnr(image, self.photo)) - self.render_psnr


def _agreement(scene, enhancer, target: _Target, position: int) -> float:
    """Mean |block mean of the reprojected neighbour photo - block mean of the render| (8x8
    blocks, valid pixels only): low where the neighbour's photo, warped by the rendered depth,
    looks like the render. Needs no photo of the target."""
    from roguenerf.reprojection import reproject

    i = enhancer.train[position]
    render = target.render
    with torch.inference_mode():
        rp = reproject(scene.photo(i)[None], scene.depth(i)[None], target.depth[None], enhancer.train_K[position],
                       target.K, enhancer.train_poses[position], target.pose)
        valid = rp.valid[0]
        diff = (F.avg_pool2d((rp.features[0] * valid)[None], 8) - F.avg_pool2d((render * valid)[None], 8)).abs().mean(1)
        covered = F.avg_pool2d(valid[None], 8) > 0
    return float(diff.sum() / covered.sum().clamp_min(1))


def measure(scene_dir: Path, checkpoint: Path | None, candidates: int) -> list[dict]:
    from roguenerf.checkpoint import default_checkpoint_path, load_checkpoint
    from roguenerf.data.readers import load_scene
    from roguenerf.enhance import EnhanceOptions
    from roguenerf.geometry import select_neighbours
    from roguenerf.inference import SceneEnhancer
    from roguenerf.models import NeighbourBatch

    scene = load_scene(scene_dir)
    model, _ = load_checkpoint(checkpoint or default_checkpoint_path(must_exist=True))
    enhancer = SceneEnhancer(scene, model, options=EnhanceOptions.from_flags(neighbours=2))
    label = scene_label(scene_dir)
    rows = []
    run_stamp = stamp()  # once per scene: machine() and commit() (two git calls) per row would repeat
    train = scene.indices("train")
    loo = train[:: max(1, len(train) // 12)][:12]
    targets = {i: _Target(scene, i) for i in scene.indices("test") + loo}  # each view read once

    def gain(target: _Target, positions: list[int]) -> float:
        batch = NeighbourBatch(None, None, enhancer.train_K[positions][None], enhancer.train_poses[positions][None],
                               sources=enhancer._cached_sources(positions))
        with torch.inference_mode():
            out = model(target.render[None], target.depth[None], target.K[None], target.pose[None], batch)[0]
        return target.gain(out.clamp(0, 1))

    for k in scene.indices("test"):
        frame, target = scene.frames[k], targets[k]
        ranked = select_neighbours(target.pose, enhancer.train_poses, candidates).tolist()
        singles = [gain(target, [p]) for p in ranked]
        agree = [_agreement(scene, enhancer, target, p) for p in ranked]
        by_agreement = sorted(range(len(ranked)), key=lambda j: agree[j])[:2]
        pair = gain(target, ranked[:2])
        pair_agreement = pair if sorted(by_agreement) == [0, 1] else gain(target, [ranked[j] for j in by_agreement])
        names = [scene.frames[enhancer.train[p]].name for p in ranked]
        base = dict(**run_stamp, scene=label, view=frame.name, candidates=" ".join(names),
                    single_gains=" ".join(f"{g:+.3f}" for g in singles),
                    agreement=" ".join(f"{a:.4f}" for a in agree))
        chosen = {"pair": (pair, names[:2]), "pair_agreement": (pair_agreement, [names[j] for j in by_agreement]),
                  "best_single": (max(singles), [names[max(range(len(singles)), key=singles.__getitem__)]])}
        chosen["oracle"] = max(chosen["pair"], chosen["best_single"], key=lambda c: c[0])
        for rule in RULES:
            g, used = chosen[rule]
            rows.append(dict(base, kind="view", rule=rule, neighbours=" ".join(used), gain_db=round(g, 4)))
        print(label, frame.name, {r: round(chosen[r][0], 3) for r in RULES}, flush=True)

    for n in (1, 2, 3):
        per_n = SceneEnhancer(scene, model, options=EnhanceOptions.from_flags(neighbours=n))
        for split, views in (("test", scene.indices("test")), ("train_leave_one_out", loo)):
            gains = [targets[i].gain(per_n.enhance_view(i).image) for i in views]
            rows.append(dict(**run_stamp, scene=label, kind="count", rule=f"n={n}", split=split, views=len(views),
                             gain_db=round(sum(gains) / len(gains), 4), worst_gain_db=round(min(gains), 4)))
            print(label, f"n={n}", split, round(sum(gains) / len(gains), 3), round(min(gains), 3), flush=True)
    return rows


def plot(rows: list[dict], path: Path) -> Path:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    scenes = list(dict.fromkeys(r["scene"] for r in rows))
    fig, axes = plt.subplots(1, len(scenes), figsize=(4.5 * len(scenes), 3.6), squeeze=False)
    for ax, label in zip(axes[0], scenes):
        names = list(RULES) + [f"n={n} {s}" for n in (1, 2, 3) for s in ("test", "loo")]
        values = []
        for rule in RULES:
            g = [r["gain_db"] for r in rows if r["scene"] == label and r["kind"] == "view" and r["rule"] == rule]
            values.append(sum(g) / len(g))
        for n in (1, 2, 3):
            for split in ("test", "train_leave_one_out"):
                values += [r["gain_db"] for r in rows if r["scene"] == label and r["kind"] == "count"
                           and r["rule"] == f"n={n}" and r["split"] == split]
        ax.barh(names, values)
        ax.invert_yaxis()
        ax.set_title(label, fontsize=9)
        ax.set_xlabel("mean PSNR gain, dB (zero-shot)")
    r0 = rows[0]
    fig.suptitle(f"neighbour choice | {r0['machine']} | {r0['commit']} | {r0['date'][:10]}", fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("scenes", nargs="+", type=Path, help="scene folders with held-out views")
    p.add_argument("--checkpoint", type=Path, default=None, help="default: the shipped checkpoint")
    p.add_argument("--candidates", type=int, default=5)
    p.add_argument("--output", type=Path, default=RESULTS / "neighbour_choice")
    args = p.parse_args(argv)
    rows = []
    for scene_dir in args.scenes:
        rows += measure(scene_dir, args.checkpoint, args.candidates)
    write_outputs(args.output, rows, plot)


if __name__ == "__main__":
    main()
