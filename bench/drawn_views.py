"""How much a scene's drawn training views look like its novel views (``TrainConfig.neighbour_renders``).

    python -m bench.drawn_views runs/kinds/pairs/SCENE/KIND ... [--output bench/results/drawn_views]

Per scene (a ``bench.kinds`` / ``roguefit`` output with held-out views): the PSNR against their
photos of the training views' own renders, of the training views drawn from their nearest other
training view's render (:meth:`~roguenerf.training.loop.SceneData.draw_from_neighbours`, their
own render where nothing lands) and of the held-out views' renders, what the enhancer meets at
inference; the share of pixels drawn, and the seconds drawing took. A field renders its training
views better than its novel views; fine-tuning pairs teach the enhancer the job on the training
views, so the closer the drawn views come to the held-out renders, the more alike the two jobs.
Writes ``OUTPUT.csv`` (a row per view), ``OUTPUT.json`` (per scene means) and ``OUTPUT.png``.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from bench.common import RESULTS, beside, caption_line, save_figure, scene_label, stamp, write_csv, write_json


def measure(path: Path) -> tuple[list[dict], dict]:
    """Per-view rows and the scene's summary."""
    from roguenerf.data.readers import load_scene
    from roguenerf.metrics import psnr
    from roguenerf.training.loop import SceneData

    scene = load_scene(path)
    data = SceneData(scene, 0, held_out=True)
    if not data.held_out:
        raise SystemExit(f"{path}: expected held-out views (renders of views the field never saw)")
    start = time.perf_counter()
    share = data.draw_from_neighbours()
    seconds = time.perf_counter() - start
    m, label, base = len(data.train), scene_label(path), stamp()

    def score(image, photo) -> float:
        return float(psnr(image[None].clamp(0, 1), photo[None]))

    rows = []
    for k in range(len(data.photos)):
        row = {**base, "scene": label, "view": scene.frames[(data.train + data.held_out)[k]].name}
        if k < m:
            row.update(split="train", render_psnr=score(data.renders[k], data.photos[k]),
                       drawn_psnr=score(data.drawn_renders[k], data.photos[k]))
        else:
            row.update(split="held-out", render_psnr=score(data.renders[k], data.photos[k]), drawn_psnr=None)
        rows.append(row)
    train = [r for r in rows if r["split"] == "train"]
    held = [r for r in rows if r["split"] == "held-out"]
    summary = {"scene": label, "train_views": len(train), "held_out_views": len(held),
               "train_render_psnr": sum(r["render_psnr"] for r in train) / len(train),
               "train_drawn_psnr": sum(r["drawn_psnr"] for r in train) / len(train),
               "held_out_render_psnr": sum(r["render_psnr"] for r in held) / len(held),
               "drawn_share": share, "seconds": seconds, "size": f"{data.width}x{data.height}"}
    print(f"{label}: training views {summary['train_render_psnr']:.2f} dB own, "
          f"{summary['train_drawn_psnr']:.2f} drawn ({share:.0%} of pixels); held-out "
          f"{summary['held_out_render_psnr']:.2f} dB; {seconds:.1f} s", flush=True)
    return rows, summary


def plot(summaries: list[dict], rows: list[dict], path: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(1.6 + 1.3 * len(summaries), 3.6))
    x = range(len(summaries))
    for offset, key, label in ((-0.25, "train_render_psnr", "training views, own render"),
                               (0.0, "train_drawn_psnr", "training views, drawn"),
                               (0.25, "held_out_render_psnr", "held-out views (novel)")):
        ax.bar([i + offset for i in x], [s[key] for s in summaries], width=0.25, label=label)
    ax.set_xticks(list(x), [s["scene"].replace("/", "\n") for s in summaries], fontsize=6)
    ax.set_ylabel("PSNR against the photos (dB)")
    ax.legend(fontsize=7)
    caption_line(fig, rows, "drawn training views against novel views")
    return save_figure(fig, path)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scenes", nargs="+", type=Path, help="scene folders with renders, depths and held-out views")
    ap.add_argument("--output", type=Path, default=RESULTS / "drawn_views")
    args = ap.parse_args(argv)
    rows, summaries = [], []
    for path in args.scenes:
        new, summary = measure(path)
        rows += new
        summaries.append(summary)
    write_csv(beside(args.output, ".csv"), rows)
    write_json(beside(args.output, ".json"), {"command": "python -m bench.drawn_views " + " ".join(
        str(p) for p in args.scenes), "scenes": summaries, **stamp()})
    print(f"wrote {plot(summaries, rows, beside(args.output, '.png'))}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
