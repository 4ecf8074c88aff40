"""What colour matching to the neighbour photos buys, per setting, side by side in one run.

Every test view of each scene folder is enhanced once without colour matching (the model's own
output, pose refinement on as shipped); each ``--configs`` setting of
:class:`~roguenerf.enhance.colour.ColourConfig` then matches that same output to the
neighbours (:meth:`SceneEnhancer.colour_match`), so the settings differ in nothing else. Per view
and setting: PSNR gain over the render, FLIP change (lower is better), the share of pixels where
the neighbours agree, whether anything was changed, and the seconds the match took. CSV + plot
with date, machine and commit.

    python -m bench.colour runs/kinds/pairs/can_clip/splat_s2 --configs off,local_sigma=0,local_sigma=8
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from bench.common import RESULTS, save_figure, scene_label, stamp, summary_by_setting, write_outputs

DEFAULT_CONFIGS = "off,local_sigma=0:min_share=0.05,local_sigma=0,local_sigma=4,local_sigma=8,local_sigma=16"


def _configs(text: str) -> list[str]:
    out = [c.strip() for c in text.split(",") if c.strip()]
    if not out:
        raise argparse.ArgumentTypeError("--configs: expected at least one setting")
    return out


def colour_config(spec: str):
    """``off``, ``default``, or ``field=value[:field=value...]`` over ColourConfig's defaults."""
    from roguenerf.enhance.colour import ColourConfig
    from roguenerf.errors import InputError

    if spec == "off":
        return None
    if spec == "default":
        return ColourConfig()
    fields = {}
    for part in spec.split(":"):
        name, _, value = part.partition("=")
        if name not in ColourConfig.__dataclass_fields__ or not value:
            raise InputError(f"--configs: {part!r} is not FIELD=VALUE with a field of ColourConfig "
                             f"({', '.join(ColourConfig.__dataclass_fields__)})")
        fields[name] = float(value)
    return ColourConfig(**fields)


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("scenes", type=Path, nargs="+", help="scene folders (photos, renders, depths)")
    p.add_argument("--checkpoint", type=Path, default=None, help="default: the shipped checkpoint")
    p.add_argument("--configs", type=_configs, default=_configs(DEFAULT_CONFIGS),
                   help="comma-separated settings: off, default or FIELD=VALUE[:FIELD=VALUE] "
                        f"(default {DEFAULT_CONFIGS})")
    p.add_argument("--max-views", type=int, default=None)
    p.add_argument("--output", type=Path, default=RESULTS / "colour")
    args = p.parse_args(argv)
    args.parsed = [(spec, colour_config(spec)) for spec in args.configs]
    return args


def measure(args) -> list[dict]:
    from roguenerf import metrics
    from roguenerf.checkpoint import default_checkpoint_path, load_checkpoint
    from roguenerf.data.readers import load_scene
    from roguenerf.enhance import EnhanceOptions
    from roguenerf.enhance.colour import apply_match
    from roguenerf.inference import SceneEnhancer

    checkpoint = args.checkpoint or default_checkpoint_path()
    model, _ = load_checkpoint(checkpoint)
    base = stamp()
    rows = []
    for scene_dir in args.scenes:
        scene = load_scene(scene_dir)
        enhancer = SceneEnhancer(scene, model, options=EnhanceOptions(colour=None))
        views = scene.indices("test")[: args.max_views] if args.max_views else scene.indices("test")
        for i in views:
            frame = scene.frames[i]
            photo, render, depth = scene.photo(i)[None], scene.render(i)[None], scene.depth(i)
            r_psnr, r_flip = float(metrics.psnr(render, photo)[0]), float(metrics.flip(render, photo)[0])
            result = enhancer.enhance_view(i)
            positions = [enhancer.train.index(scene.index(n)) for n in result.neighbours]
            poses = None
            for spec, config in args.parsed:
                image, share, changed, seconds = result.image, None, False, 0.0
                if config is not None and len(positions) >= 2:
                    if poses is None:  # the refined poses the model saw (the fit is deterministic)
                        poses, _ = enhancer.neighbour_poses(positions, scene.render(i), depth, frame.K,
                                                            frame.world_from_cam)
                    enhancer.colour = config
                    t0 = time.perf_counter()
                    match = enhancer.colour_match(positions, result.image, depth, frame.K, frame.world_from_cam, poses)
                    if match is not None:
                        image, share, changed = apply_match(image, match), match.share, True
                    seconds = time.perf_counter() - t0
                    enhancer.colour = None
                out = image[None]
                rows.append({**base, "scene": scene_label(scene_dir), "view": frame.name, "config": spec,
                             "gain_db": round(float(metrics.psnr(out, photo)[0]) - r_psnr, 4),
                             "flip_change": round(float(metrics.flip(out, photo)[0]) - r_flip, 5),
                             "agree_share": None if share is None else round(share, 3), "changed": changed,
                             "match_seconds": round(seconds, 3), "checkpoint": checkpoint.name})
                print(f"{rows[-1]['scene']} {frame.name} {spec}: gain {rows[-1]['gain_db']:+.3f} dB, "
                      f"FLIP {rows[-1]['flip_change']:+.4f}", flush=True)
    return rows


def summary(rows: list[dict]) -> list[dict]:
    """Per setting: the mean over scenes of each scene's mean gain, views with a better FLIP, worst view."""
    return summary_by_setting(rows, "config")


def plot(rows: list[dict], path: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    specs = list(dict.fromkeys(r["config"] for r in rows))
    scenes = list(dict.fromkeys(r["scene"] for r in rows))
    fig, (gain, flip) = plt.subplots(1, 2, figsize=(max(9, 1.2 * len(scenes) * len(specs) / 3 + 4), 4.4))
    width = 0.8 / max(1, len(specs))
    for k, spec in enumerate(specs):
        g = [sum(r["gain_db"] for r in rows if r["config"] == spec and r["scene"] == s)
             / max(1, sum(r["config"] == spec and r["scene"] == s for r in rows)) for s in scenes]
        f = [sum(r["flip_change"] < 0 for r in rows if r["config"] == spec and r["scene"] == s) for s in scenes]
        xs = [i - 0.4 + width * (k + 0.5) for i in range(len(scenes))]
        gain.bar(xs, g, width=width, label=spec)
        flip.bar(xs, f, width=width, label=spec)
    gain.axhline(0, color="k", lw=0.8)
    gain.set_ylabel("mean PSNR gain over the render (dB)")
    flip.set_ylabel("views with a better FLIP")
    for ax in (gain, flip):
        ax.set_xticks(range(len(scenes)), [s.replace("/", "\n", 1) for s in scenes], fontsize=7)
    gain.legend(fontsize=7)
    first = rows[0] if rows else {}
    fig.suptitle(f"colour matching to the neighbours — {first.get('checkpoint', '')}, {first.get('date', '')[:10]}, "
                 f"{first.get('commit', '')}\n{first.get('machine', '')}", fontsize=8)
    return save_figure(fig, path)


def main(argv=None) -> int:
    args = parse_args(argv)
    rows = measure(args)
    write_outputs(args.output, rows, plot)
    for s in summary(rows):
        print(f"{s['config']:>36}: gain {s['gain_db']:+.3f} dB, FLIP better on {s['views_flip_better']}/{s['views']} "
              f"views, worst view {s['worst_view_gain_db']:+.3f} dB")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
