"""How the flicker figure moves with sharpness alone: the render of a path under one fixed
unsharp mask (or blur), the same operation on every frame, measured as ``enhance_path`` measures.

    python -m bench.flicker_sharpness --fit runs/kinds/pairs/can_clip/fine_s1_600steps --factor 1 \\
        --keys 4 --steps 51 --work runs/paths [--amounts 0.5,1,2] [--output bench/results/...]

The path and its frames are ``bench.paths``'s (same ``--fit``, ``--factor``, ``--keys``,
``--steps`` and ``--work``: rendered once, cached). Every frame's render is sharpened by
``render + a * (render - blur(render))`` (Gaussian, sigma 1 px, clamped to [0, 1]) for each
amount ``a``, and blurred once (sigma 1 px); each pair of frames is measured by
:func:`~roguenerf.trajectory.pair_flicker` (frame t reprojected into t+1, mean absolute error on
the valid pixels), the figure as written (``plain``) and on the same difference low-passed by a
Gaussian of sigma 1 px (``lowpass``: the resampling's loss of fine detail mostly removed). Nothing
changes between frames but the camera, so any ratio above 1 is what the metric makes of
sharpness. Writes ``OUTPUT.csv`` (a row per variant and measure), ``OUTPUT.json`` and
``OUTPUT.png`` (date, machine, commit); prints the ratios to the render's flicker.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from bench.common import RESULTS, beside, save_figure, stamp, write_csv, write_json


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--fit", type=Path, required=True, help="a make-pairs fit folder (as bench.paths)")
    ap.add_argument("--factor", type=int, default=1)
    ap.add_argument("--keys", type=int, default=4)
    ap.add_argument("--steps", type=int, default=16)
    ap.add_argument("--work", type=Path, default=Path("runs/paths"))
    ap.add_argument("--amounts", default="0.5,1,2", help="comma-separated unsharp-mask amounts")
    ap.add_argument("--output", type=Path, default=None)
    args = ap.parse_args(argv)
    amounts = [float(a) for a in args.amounts.split(",")]
    if any(a <= 0 for a in amounts):
        raise SystemExit(f"--amounts: expected positive amounts, got {args.amounts}")
    args.photo_path, args.toy, args.quick, args.force = False, False, False, False

    import torch
    import torch.nn.functional as F

    import roguenerf.runtime
    from bench.paths import field_frames
    from roguenerf.imageio import read_depth, read_image
    from roguenerf.ops import gaussian_blur
    from roguenerf.reprojection import reproject
    from roguenerf.trajectory import find_path_frames

    roguenerf.runtime.configure()
    scene, frames, poses, K, width, height, *_rest, name = field_frames(args)
    pairs = find_path_frames(frames, len(poses))
    variants = ["render", *[f"unsharp {a:g}" for a in amounts], "blur"]

    def blur(x: torch.Tensor) -> torch.Tensor:
        return gaussian_blur(x[None], 7, 1.0)[0]

    def images(t: int) -> tuple[list[torch.Tensor], torch.Tensor]:
        render, depth = read_image(pairs[t][0]), read_depth(pairs[t][1])
        soft = blur(render)
        return [render, *[(render + a * (render - soft)).clamp(0, 1) for a in amounts], soft], depth

    errors = {(v, m): [] for v in variants for m in ("plain", "lowpass")}
    started = time.perf_counter()
    prev = images(0)
    for t in range(1, len(poses)):
        cur = images(t)
        moved = reproject(torch.cat(prev[0])[None], prev[1][None], cur[1][None], K.float(), K.float(),
                          poses[t - 1].double(), poses[t].double())
        valid = (moved.valid[0] > 0.5).float()
        diff = (moved.features[0] - torch.cat(cur[0])) * valid
        seen = valid[0] > 0.5
        low = gaussian_blur(diff[None], 7, 1.0)[0]
        seen_low = -F.max_pool2d(-valid[None], 7, 1, 3)[0, 0] > 0.5  # the whole 7 x 7 window seen
        for k, v in enumerate(variants):
            errors[(v, "plain")].append(float(diff[3 * k:3 * k + 3].abs().mean(0)[seen].mean()))
            errors[(v, "lowpass")].append(float(low[3 * k:3 * k + 3].abs().mean(0)[seen_low].mean()))
        prev = cur
    seconds = time.perf_counter() - started
    base = stamp()
    rows = []
    for (v, m), values in errors.items():
        mean = sum(values) / len(values)
        render = sum(errors[("render", m)]) / len(errors[("render", m)])
        rows.append({**base, "scene": name, "size": f"{width}x{height}", "frames": len(poses), "variant": v,
                     "measure": m, "flicker": round(mean, 6), "ratio": round(mean / render, 4)})
    summary = {**base, "command": " ".join(["python -m bench.flicker_sharpness", *(argv or sys.argv[1:])]),
               "scene": name, "size": f"{width}x{height}", "frames": len(poses), "seconds": round(seconds, 1),
               "ratio": {m: {r["variant"]: r["ratio"] for r in rows if r["measure"] == m}
                         for m in ("plain", "lowpass")}}
    output = args.output or RESULTS / f"flicker_sharpness_{name}_{args.keys}x{args.steps}"
    write_csv(beside(output, ".csv"), rows)
    write_json(beside(output, ".json"), summary)
    for m, ratios in summary["ratio"].items():
        print(f"{m}: " + ", ".join(f"{v} x{r:.3f}" for v, r in ratios.items()))

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5.5, 3.5))
    for i, m in enumerate(("plain", "lowpass")):
        ax.bar([k + 0.4 * i for k in range(len(variants))], [summary["ratio"][m][v] for v in variants], width=0.4,
               label=m)
    ax.axhline(1.0, color="k", lw=0.8)
    ax.set_xticks([k + 0.2 for k in range(len(variants))], variants)
    ax.set_ylabel("flicker / render's")
    ax.set_title(f"{name}, {len(poses)}-frame path: one operation on every frame", fontsize=9)
    ax.legend()
    fig.suptitle(f"{base['date']} {base['machine']} {base['commit']}", fontsize=6)
    save_figure(fig, beside(output, ".png"))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
