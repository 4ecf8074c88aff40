"""What trusting the neighbours by their agreement buys, per setting, side by side in one run.

Every test view of each scene folder is enhanced once as shipped but with trust off (pose
refinement and colour matching on); the share of its pixels where two or more neighbours agree
is measured on the same small copies the enhancer uses. Each ``--settings`` value of
:attr:`~roguenerf.enhance.trust.TrustConfig.full_share` then keeps ``min(1, share / value)`` of
that output's change over the render (:func:`~roguenerf.enhance.trust.trust_factor`), so the
settings differ in nothing else; plain numbers are per view on every view. ``localS`` (e.g.
``local16``) instead keeps, per pixel, the share of agreeing pixels within about S pixels of it
(Gaussian sigma, small copies) over 0.5: a per-pixel trust on every view. ``belowX`` (e.g.
``below0.1``) is the shipped rule with
:attr:`~roguenerf.enhance.trust.TrustConfig.local_below` = X: per view, and per pixel
(``local_sigma``) on views whose agreement is under X
(:func:`~roguenerf.enhance.trust.kept_change`). ``alone`` keeps the shipped rule's share but
takes the rest of the change from the model run without neighbours instead of the render (a
fallback measured, not shipped). A scene folder may name the checkpoint to use
for it (``FOLDER=CHECKPOINT``: a fine-tuned model), else ``--checkpoint``. Per view and setting: PSNR
gain over the render, FLIP change (lower is better), the agreement share and the share kept.
CSV + plot with date, machine and commit.

    python -m bench.trust runs/kinds/pairs/ollie/splat_s2 \\
        runs/kinds/pairs/ollie/splat_s2=runs/kinds/finetune/ollie/splat_s2/E8h/10min/model.safetensors
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from bench.common import RESULTS, save_figure, scene_label, stamp, summary_by_setting, write_outputs

DEFAULT_SETTINGS = "off,0.3,0.4,0.5,0.6,0.7"
PREFIXES = {"local": "S > 0 pixels", "below": "X a share in [0, 1]"}
MAPS = (*PREFIXES, "alone")
"""Settings that keep the change by the view's agreement map (:attr:`EnhanceResult.agreement_map`)."""


def _settings(text: str) -> list[str]:
    out = [c.strip() for c in text.split(",") if c.strip()]
    if not out:
        raise argparse.ArgumentTypeError("--settings: expected at least one setting")
    for c in out:
        if c.startswith(tuple(PREFIXES)):
            prefix = c[:5]
            try:
                value = float(c[5:])
                if not (value > 0 if prefix == "local" else 0 <= value <= 1):
                    raise ValueError
            except ValueError:
                letter = "S" if prefix == "local" else "X"
                raise argparse.ArgumentTypeError(
                    f"--settings: {c!r} is not {prefix}{letter} with {PREFIXES[prefix]}") from None
        elif c not in ("off", "alone"):
            try:
                value = float(c)
            except ValueError:
                raise argparse.ArgumentTypeError(f"--settings: {c!r} is neither off nor a number") from None
            if not 0 < value <= 1:
                raise argparse.ArgumentTypeError(f"--settings: {c!r} is not a share in (0, 1]")
    return out


def _job(text: str) -> tuple[Path, Path | None]:
    folder, _, checkpoint = text.partition("=")
    return Path(folder), (Path(checkpoint) if checkpoint else None)


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("scenes", type=_job, nargs="+",
                   help="scene folders (photos, renders, depths), each optionally =CHECKPOINT")
    p.add_argument("--checkpoint", type=Path, default=None, help="default: the shipped checkpoint")
    p.add_argument("--settings", type=_settings, default=_settings(DEFAULT_SETTINGS),
                   help="comma-separated: off, TrustConfig.full_share values (per view), localS (per-pixel "
                        "agreement within S pixels), belowX (the shipped rule with local_below X), "
                        "alone (the shipped share, the rest from the model without neighbours) "
                        f"(default {DEFAULT_SETTINGS})")
    p.add_argument("--max-views", type=int, default=None)
    p.add_argument("--output", type=Path, default=RESULTS / "trust")
    return p.parse_args(argv)


def measure(args) -> list[dict]:
    import torch

    from roguenerf import metrics
    from roguenerf.checkpoint import default_checkpoint_path, load_checkpoint
    from roguenerf.data.readers import load_scene
    from roguenerf.enhance import EnhanceOptions
    from roguenerf.enhance.trust import TrustConfig, kept_change, local_keep, share_kept, trust_factor
    from roguenerf.geometry import as_world_from_cam
    from roguenerf.inference import SceneEnhancer

    base = stamp()
    rows = []
    for scene_dir, own in args.scenes:
        checkpoint = own or args.checkpoint or default_checkpoint_path()
        model, _ = load_checkpoint(checkpoint)
        scene = load_scene(scene_dir)
        enhancer = SceneEnhancer(scene, model, options=EnhanceOptions(trust=None))
        label = scene_label(scene_dir) + (" (fine-tuned)" if own else "")
        views = scene.indices("test")[: args.max_views] if args.max_views else scene.indices("test")
        for i in views:
            frame = scene.frames[i]
            photo, render, depth = scene.photo(i)[None], scene.render(i)[None], scene.depth(i)
            r_psnr, r_flip = float(metrics.psnr(render, photo)[0]), float(metrics.flip(render, photo)[0])
            t0 = time.perf_counter()
            result = enhancer.enhance_view(i)
            seconds = time.perf_counter() - t0
            share, agree = result.agreement, result.agreement_map  # the enhancer's (colour matching's test)
            for spec in args.settings:
                fallback = render  # what the change not kept leaves
                if spec.startswith("local") and agree is not None:
                    keep = local_keep(agree, render.shape[-2:], float(spec[5:]), 0.5)
                    kept = share_kept(keep)
                elif spec.startswith(("below", "alone")) and agree is not None:
                    config = TrustConfig() if spec == "alone" else TrustConfig(local_below=float(spec[5:]))
                    keep = kept_change(agree, render.shape[-2:], config)
                    kept = share_kept(keep)
                    if spec == "alone":
                        with torch.inference_mode():  # the model alone: no neighbours
                            K = torch.as_tensor(frame.K, dtype=torch.float32)[None]
                            fallback = model(render, depth[None], K, as_world_from_cam(frame.world_from_cam)[None],
                                             None).clamp(0, 1)
                else:
                    kept = (1.0 if spec == "off" or spec.startswith(MAPS) or share is None
                            else trust_factor(share, TrustConfig(float(spec))))
                    keep = kept
                out = fallback + keep * (result.image[None] - fallback)
                rows.append({**base, "scene": label, "view": frame.name, "setting": spec,
                             "gain_db": round(float(metrics.psnr(out, photo)[0]) - r_psnr, 4),
                             "flip_change": round(float(metrics.flip(out, photo)[0]) - r_flip, 5),
                             "agreement": None if share is None else round(share, 4), "kept": round(kept, 4),
                             "enhance_seconds": round(seconds, 2), "checkpoint": str(checkpoint)})
            print(f"{label} {frame.name}: agreement {share if share is None else round(share, 3)}, gains "
                  + " ".join(f"{r['setting']}:{r['gain_db']:+.3f}" for r in rows[-len(args.settings):]), flush=True)
    return rows


def summary(rows: list[dict]) -> list[dict]:
    """Per setting: the mean over scenes of each scene's mean gain, views with a better FLIP, worst view."""
    return summary_by_setting(rows, "setting")


def plot(rows: list[dict], path: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    specs = list(dict.fromkeys(r["setting"] for r in rows))
    scenes = list(dict.fromkeys(r["scene"] for r in rows))
    fig, (gain, worst) = plt.subplots(1, 2, figsize=(max(9, 1.2 * len(scenes) * len(specs) / 3 + 4), 4.4))
    width = 0.8 / max(1, len(specs))
    for k, spec in enumerate(specs):
        mine = [[r["gain_db"] for r in rows if r["setting"] == spec and r["scene"] == s] for s in scenes]
        xs = [i - 0.4 + width * (k + 0.5) for i in range(len(scenes))]
        gain.bar(xs, [sum(g) / max(1, len(g)) for g in mine], width=width, label=spec)
        worst.bar(xs, [min(g) if g else 0 for g in mine], width=width, label=spec)
    for ax, label in ((gain, "mean PSNR gain over the render (dB)"), (worst, "worst view's gain (dB)")):
        ax.axhline(0, color="k", lw=0.8)
        ax.set_ylabel(label)
        ax.set_xticks(range(len(scenes)), [s.replace("/", "\n", 1) for s in scenes], fontsize=6)
    gain.legend(fontsize=7, title="full_share", title_fontsize=7)
    first = rows[0] if rows else {}
    fig.suptitle(f"trusting the neighbours by their agreement — {first.get('date', '')[:10]}, "
                 f"{first.get('commit', '')}\n{first.get('machine', '')}", fontsize=8)
    return save_figure(fig, path)


def main(argv=None) -> int:
    args = parse_args(argv)
    rows = measure(args)
    write_outputs(args.output, rows, plot)
    for s in summary(rows):
        print(f"{s['setting']:>5}: gain {s['gain_db']:+.3f} dB (worst scene {s['worst_scene_gain_db']:+.3f}), "
              f"FLIP better on {s['views_flip_better']}/{s['views']} views, "
              f"worst view {s['worst_view_gain_db']:+.3f} dB")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
