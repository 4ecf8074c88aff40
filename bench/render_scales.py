"""At which scales are a field's renders wrong? Training views (the fine-tune's targets) against
held-out views (what a user enhances).

For every scene folder given, the mean PSNR of render against photo over the training and over
the held-out views, with both images average-pooled by 1, 2, 4, 8 and 16 first: an error that
survives pooling by 16 is a large-scale one (misplaced structure, floaters, colour), which
sharper detail from the neighbours cannot mend pixel by pixel. Also each split's PSNR after the
render is blurred by a Gaussian of sigma 1 and 2 px (what the removed ``render_blur`` fine-tuning
option did to the targets) and after a per-channel affine colour fit (how much of the error is
colour). No model runs; seconds per scene.

    .venv/bin/python -m bench.render_scales ~/.cache/roguenerf/pairs/{dtu_scan37,mary_rose}/{coarse,fine} \\
        ../shared/data/lego --output bench/results/render_scales
"""

from __future__ import annotations

import argparse
from pathlib import Path

from bench.common import RESULTS, save_figure, scene_label, stamp, write_outputs

POOLS = (1, 2, 4, 8, 16)
SIGMAS = (1.0, 2.0)


def measure(scene) -> list[dict]:
    """One row per split: mean PSNR at each pooling, after each blur and after an affine colour fit."""
    import torch
    import torch.nn.functional as F
    from kornia.filters import gaussian_blur2d

    from roguenerf.metrics import psnr

    def _psnr(a, b) -> float:
        return float(psnr(a, b))

    rows = []
    for split in ("train", "test"):
        views = list(scene.indices(split))
        if not views:
            continue
        sums: dict[str, float] = {}
        for i in views:
            render, photo = scene.render(i)[None], scene.photo(i)[None]
            values = {f"psnr_pool{k}": _psnr(F.avg_pool2d(render, k), F.avg_pool2d(photo, k)) if k > 1
                      else _psnr(render, photo) for k in POOLS}
            for s in SIGMAS:
                radius = int(3 * s + 1)
                values[f"psnr_blur{s:g}"] = _psnr(gaussian_blur2d(render, 2 * radius + 1, (s, s)), photo)
            r, p = render[0].flatten(1), photo[0].flatten(1)  # (3, P)
            design = torch.stack([r, torch.ones_like(r)], dim=-1)  # per channel: a r + b
            fitted = (design @ torch.linalg.lstsq(design, p[..., None]).solution)[..., 0]
            values["psnr_affine_colour"] = _psnr(fitted.view_as(render), photo)
            for key, value in values.items():
                sums[key] = sums.get(key, 0.0) + value
        rows.append({"split": split, "views": len(views),
                     **{k: round(v / len(views), 3) for k, v in sums.items()}})
    return rows


def plot(rows: list[dict], path: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7.5, 4.5))
    scenes = list(dict.fromkeys(r["scene"] for r in rows))
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for k, scene in enumerate(scenes):
        for r in rows:
            if r["scene"] != scene:
                continue
            ax.plot(POOLS, [r[f"psnr_pool{p}"] for p in POOLS], marker="o", color=colours[k % len(colours)],
                    linestyle="-" if r["split"] == "train" else "--",
                    label=f"{scene} {'training' if r['split'] == 'train' else 'held-out'}")
    ax.set_xscale("log", base=2)
    ax.set_xticks(POOLS, [f"1/{p}" for p in POOLS])
    ax.set_xlabel("render and photo average-pooled to")
    ax.set_ylabel("PSNR of render against photo, dB")
    first = rows[0]
    ax.set_title(f"Render error by scale: training (solid) vs held-out views (dashed)\n"
                 f"{first['date'][:10]}, {first['machine']}, {first['commit']}", fontsize=7)
    ax.legend(fontsize=6, ncol=2)
    ax.grid(alpha=0.3)
    return save_figure(fig, path)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("scenes", type=Path, nargs="+", help="scene folders with renders")
    p.add_argument("--output", type=Path, default=RESULTS / "render_scales")
    args = p.parse_args(argv)
    from roguenerf.data.readers import load_scene

    rows = []
    for scene_dir in args.scenes:
        label = scene_label(scene_dir)
        for row in measure(load_scene(scene_dir)):
            rows.append({**stamp(), "scene": label, **row})
            print(", ".join(f"{k}={v}" for k, v in rows[-1].items() if k not in ("date", "machine", "commit")),
                  flush=True)
    write_outputs(args.output, rows, plot)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
