"""Make pre-training pairs for every posed photo set in a folder, resumably, with a manifest.

    python -m roguefit.batch --data ../shared/data/real --cache ~/.cache/roguenerf/pairs \\
        --presets blur,coarse --manifest docs/pairs/manifest.csv --examples docs/pairs

For each scene folder (a ``transforms.json`` inside) and each preset it runs
:func:`roguefit.make_pairs` into ``CACHE/SCENE/PRESET`` (outside the repository: the renders are
too large to commit). A finished fit is skipped, an interrupted one resumes, so the same command
can be run again until everything is done. The manifest lists every finished fit (scene, fit,
minutes, steps, render PSNR/SSIM on training and held-out views), keeping the rows of fits made
in another cache; ``--examples`` writes one render | photo image of a held-out view per scene.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import io
import json
import logging
import sys
import time
from pathlib import Path

from roguefit.pairs import FIT_FILE, make_pairs
from roguefit.registry import PRESETS, describe_presets

log = logging.getLogger("roguefit.batch")

MANIFEST_FIELDS = ["scene", "fit", "resolution", "features", "render_scale", "minutes", "steps", "fit_seconds",
                   "render_seconds", "train_views", "train_psnr", "train_ssim", "test_views", "test_psnr", "test_ssim"]


def scene_folders(data: Path) -> list[Path]:
    return sorted(p for p in data.iterdir() if (p / "transforms.json").is_file())


def manifest_rows(cache: Path) -> list[dict]:
    rows = []
    for fit_json in sorted(cache.glob(f"*/*/{FIT_FILE}")):
        report = json.loads(fit_json.read_text())
        c, tr, te = report["config"], report["train"], report["test"] or {}
        rows.append({
            "scene": fit_json.parent.parent.name, "fit": fit_json.parent.name,
            "resolution": c.get("resolution", ""), "features": c.get("features", ""),
            "render_scale": c.get("render_scale", 1),
            "minutes": c["minutes"], "steps": report["steps"], "fit_seconds": report["fit_seconds"],
            "render_seconds": report["render_seconds"],
            "train_views": tr["views"], "train_psnr": round(tr["psnr"], 3), "train_ssim": round(tr["ssim"], 4),
            "test_views": te.get("views", 0), "test_psnr": round(te["psnr"], 3) if te else "",
            "test_ssim": round(te["ssim"], 4) if te else "",
        })
    return rows


def write_manifest(cache: Path, path: Path) -> list[dict]:
    """(Re)write the manifest at ``path``: every finished fit in ``cache``, plus the rows of an
    existing manifest whose (scene, fit) is not in this cache (fits made in another cache or
    session stay listed; a fit in the cache replaces its old row). Sorted by scene, then fit."""
    from roguenerf.imageio import atomic_write

    rows = manifest_rows(cache)
    if path.is_file():
        fresh = {(r["scene"], r["fit"]) for r in rows}
        with path.open(newline="") as fh:
            kept = [r for r in csv.DictReader(fh)  # rows without a scene and fit are not fits
                    if r.get("scene") and r.get("fit") and (r["scene"], r["fit"]) not in fresh]
        rows = sorted(rows + [{k: r.get(k, "") for k in MANIFEST_FIELDS} for r in kept],
                      key=lambda r: (r["scene"], r["fit"]))
    path.parent.mkdir(parents=True, exist_ok=True)
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=MANIFEST_FIELDS, lineterminator="\n")
    writer.writeheader()
    writer.writerows(rows)
    atomic_write(path, buf.getvalue().encode())
    return rows


def write_example(scene_dir: Path, out: Path, max_width: int = 640) -> Path | None:
    """``render | photo`` of the first held-out view, downscaled to ``max_width``."""
    import torch
    import torch.nn.functional as F

    from roguenerf.data.readers import load_scene
    from roguenerf.imageio import write_png

    scene = load_scene(scene_dir)
    test = list(scene.indices("test"))
    if not test:
        return None
    i = test[0]
    pair = torch.cat([scene.render(i), scene.photo(i)], dim=2)
    if pair.shape[2] > max_width:
        scale = max_width / pair.shape[2]
        pair = F.interpolate(pair[None], scale_factor=scale, mode="area")[0]
    out.parent.mkdir(parents=True, exist_ok=True)
    write_png(out, pair.clamp(0, 1))
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m roguefit.batch", description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, required=True, help="folder of posed photo sets")
    parser.add_argument("--cache", type=Path, required=True, help="output root (outside the repository)")
    parser.add_argument("--presets", default="blur,coarse", help=f"comma-separated, of {describe_presets()}")
    parser.add_argument("--scenes", default="",
                        help="comma-separated scene names, fitted in this order (default: all, sorted)")
    parser.add_argument("--budget-scale", type=float, default=1.0,
                        help="multiply every preset's budget (steps or minutes); a smoke test uses 0.01")
    parser.add_argument("--folds", type=int, default=1,
                        help="cross-fit with K folds (make_pairs' folds) into CACHE/SCENE/PRESET_xK; 1: one field")
    parser.add_argument("--manifest", type=Path,
                        help="CSV manifest to (re)write after every fit (rows of fits not in --cache are kept)")
    parser.add_argument("--examples", type=Path, help="folder for one render|photo example per scene")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, stream=sys.stderr, format="%(asctime)s %(message)s")
    from roguenerf import runtime

    runtime.configure()
    presets = [p for p in args.presets.split(",") if p]
    for p in presets:
        if p not in PRESETS:
            parser.error(f"--presets: unknown preset {p!r} (expected {', '.join(PRESETS)})")
    if args.folds < 1:
        parser.error(f"--folds: expected >= 1, got {args.folds}")
    if not args.budget_scale > 0:
        parser.error(f"--budget-scale: expected > 0, got {args.budget_scale}")
    if not args.data.is_dir():
        parser.error(f"--data: {args.data} is not a directory")
    scenes = scene_folders(args.data)
    if args.scenes:
        wanted = [w for w in args.scenes.split(",") if w]
        by_name = {s.name: s for s in scenes}
        missing = [w for w in wanted if w not in by_name]
        if missing:
            parser.error(f"--scenes: not in {args.data}: {', '.join(missing)}")
        scenes = [by_name[w] for w in wanted]  # in the order given
    from tqdm import tqdm

    for scene in scenes:
        for preset in presets:
            config = PRESETS[preset]
            if args.budget_scale != 1.0:
                if config.steps is not None:
                    config = dataclasses.replace(config, steps=max(1, round(config.steps * args.budget_scale)))
                else:
                    config = dataclasses.replace(config, minutes=config.minutes * args.budget_scale)
            if args.folds > 1:
                config = dataclasses.replace(config, folds=args.folds)
            out = args.cache / scene.name / (preset if args.folds == 1 else f"{preset}_x{args.folds}")
            t0 = time.monotonic()
            bar = tqdm(total=100, desc=f"{scene.name}/{preset}", unit="%", file=sys.stderr, mininterval=5)

            def progress(p: dict, bar=bar) -> None:
                bar.set_postfix(psnr=f"{p['psnr']:.2f}", size=p.get("resolution", p.get("gaussians")), refresh=False)
                bar.update(int(100 * p["fraction"]) - bar.n)

            bars = [bar]

            def render_progress(done: int, total: int, bars=bars, scene=scene, preset=preset) -> None:
                if len(bars) == 1:
                    bars[0].close()
                    bars.append(tqdm(total=total, desc=f"{scene.name}/{preset} rendering", unit="view",
                                     file=sys.stderr, mininterval=5))
                bars[1].update(done - bars[1].n)

            try:
                report = make_pairs(scene, out, config, progress=progress, render_progress=render_progress)
            finally:
                for b in bars:
                    b.close()
            log.info("%s/%s: train %.2f dB, held-out %s dB (%.0f s)", scene.name, preset, report["train"]["psnr"],
                     f"{report['test']['psnr']:.2f}" if report["test"] else "-", time.monotonic() - t0)
            if args.manifest:
                write_manifest(args.cache, args.manifest)
            if args.examples and preset == presets[-1]:
                write_example(out, args.examples / f"{scene.name}_{preset}.png")
    if args.manifest:
        write_manifest(args.cache, args.manifest)
    return 0


if __name__ == "__main__":
    sys.exit(main())
