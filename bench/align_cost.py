"""What neighbour pose refinement costs and buys, side by side in one run.

For each scene folder and pose-noise level (Gaussian noise on the training views' poses only,
as ``bench/kinds.py``), every test view is enhanced with pose refinement off and on, in
alternation (so both see the same machine load): seconds per view, PSNR gain over the render,
FLIP change, and the share of neighbours whose fit was kept. CSV + plot with date, machine and
commit.

    python -m bench.align_cost runs/kinds/pairs/can_clip/splat_s2 --noise 0/0,0.5/0.05
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from bench.common import RESULTS, save_figure, scene_label, stamp, write_outputs
from bench.kinds import _noise


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("scenes", type=Path, nargs="+", help="scene folders (photos, renders, depths)")
    p.add_argument("--checkpoint", type=Path, default=None, help="default: the shipped checkpoint")
    p.add_argument("--noise", type=_noise, default=_noise("0/0,0.5/0.05"),
                   help="pose-noise levels deg/share, comma-separated (default 0/0,0.5/0.05)")
    p.add_argument("--max-rotation", type=float, default=None,
                   help="the fit's trust region, degrees (default: AlignConfig's)")
    p.add_argument("--max-translation", type=float, default=None,
                   help="the fit's trust region, share of the median depth (default: AlignConfig's)")
    p.add_argument("--max-views", type=int, default=None)
    p.add_argument("--output", type=Path, default=RESULTS / "align_cost")
    return p.parse_args(argv)


def measure(args) -> list[dict]:
    from bench.kinds import noisy_scene
    from roguenerf import metrics
    from roguenerf.checkpoint import default_checkpoint_path, load_checkpoint
    from roguenerf.data.readers import load_scene
    from roguenerf.enhance import EnhanceOptions
    from roguenerf.enhance.align import AlignConfig
    from roguenerf.inference import SceneEnhancer

    checkpoint = args.checkpoint or default_checkpoint_path()
    model, _ = load_checkpoint(checkpoint)
    trust = {k: v for k, v in (("max_rotation_deg", args.max_rotation), ("max_translation", args.max_translation))
             if v is not None}
    config = AlignConfig(**trust)
    base = stamp()
    rows = []
    for scene_dir in args.scenes:
        clean = load_scene(scene_dir)
        for k, (deg, share) in enumerate(args.noise):
            scene = clean if deg == 0 and share == 0 else noisy_scene(clean, deg, share, seed=1000 + k)
            enhancers = {False: SceneEnhancer(scene, model, options=EnhanceOptions(align=None)),
                         True: SceneEnhancer(scene, model, options=EnhanceOptions(align=config))}
            views = scene.indices("test")[: args.max_views] if args.max_views else scene.indices("test")
            for i in views:
                enhancers[False].enhance_view(i)  # warm both neighbour caches: time the request, not the cache
                photo, render = scene.photo(i)[None], scene.render(i)[None]
                r_psnr, r_flip = float(metrics.psnr(render, photo)[0]), float(metrics.flip(render, photo)[0])
                for align in (False, True):
                    t0 = time.perf_counter()
                    result = enhancers[align].enhance_view(i)
                    seconds = time.perf_counter() - t0
                    out = result.image[None]
                    rows.append({**base, "scene": scene_label(scene_dir), "noise_deg": deg, "noise_share": share,
                                 "view": scene.frames[i].name, "align": align, "seconds": round(seconds, 3),
                                 "gain_db": round(float(metrics.psnr(out, photo)[0]) - r_psnr, 4),
                                 "flip_change": round(float(metrics.flip(out, photo)[0]) - r_flip, 5),
                                 "aligned_share": (round(sum(result.aligned) / len(result.aligned), 3)
                                                   if result.aligned else 0.0),
                                 "checkpoint": checkpoint.name, "max_rotation_deg": config.max_rotation_deg,
                                 "max_translation": config.max_translation})
                    print(f"{rows[-1]['scene']} {deg:g}/{share:g} {rows[-1]['view']} align={align}: "
                          f"{seconds:.2f} s, gain {rows[-1]['gain_db']:+.3f} dB", flush=True)
    return rows


def plot(rows: list[dict], path: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    groups: dict[tuple, dict[bool, list[dict]]] = {}
    for r in rows:
        groups.setdefault((r["scene"], r["noise_deg"], r["noise_share"]), {False: [], True: []})[r["align"]].append(r)
    labels = [f"{s}\n{d:g}°/{sh:.0%}" for s, d, sh in groups]
    fig, (gain, speed) = plt.subplots(1, 2, figsize=(max(8, 1.6 * len(labels) + 2), 4.2))
    x = range(len(labels))
    for offset, align in ((-0.2, False), (0.2, True)):
        mean = [sum(r["gain_db"] for r in g[align]) / max(1, len(g[align])) for g in groups.values()]
        secs = [sum(r["seconds"] for r in g[align]) / max(1, len(g[align])) for g in groups.values()]
        name = "pose refinement on" if align else "off"
        gain.bar([i + offset for i in x], mean, width=0.4, label=name)
        speed.bar([i + offset for i in x], secs, width=0.4, label=name)
    gain.axhline(0, color="k", lw=0.8)
    gain.set_ylabel("mean PSNR gain over the render (dB)")
    speed.set_ylabel("seconds per view")
    for ax in (gain, speed):
        ax.set_xticks(list(x), labels, fontsize=8)
        ax.legend(fontsize=8)
    first = rows[0] if rows else {}
    fig.suptitle(f"neighbour pose refinement — {first.get('date', '')[:10]}, {first.get('commit', '')}\n"
                 f"{first.get('machine', '')}", fontsize=8)
    return save_figure(fig, path)


def main(argv=None) -> int:
    args = parse_args(argv)
    rows = measure(args)
    write_outputs(args.output, rows, plot)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
