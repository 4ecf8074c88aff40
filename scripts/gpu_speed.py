"""GPU speed of the shipped enhancer end to end (issue 51, item 4), beside the CPU of the same
machine: seconds per view at 512 x 512 and 1920 x 1080, in float32 and with the model in float16,
and frames per second along a 48-frame path, each with its gain so that speed is shown against
error.

Here (the machine with the scene), once; what travels is capped at 64 MiB, so the scene is
packed (its training views, JPEG, float16 depths; scripts/pack_pairs.py prints the cost), with
the kornia wheels of scripts/gpu_pretrain.sh in .whl/:
    python scripts/pack_pairs.py runs/speed/dtu_scan37_fine --out .gpu/speed --every 1 --quality 95
There (device tool: carry .gpu and .whl), from the repository root:
    python3 -m pip install -q --no-index --no-deps --target /tmp/site .whl/*.whl
    PYTHONPATH=/tmp/site:$PWD ROGUENERF_THREADS=8 python3 scripts/gpu_speed.py .gpu/speed/dtu_scan37 --out $OUT
    ... --devices cuda --tiles 1024,2048 --no-path      # tile sizes (with and without pose fits) beside the default
(Run on an H200 on 2026-11-29 with ``runs/kinds/pairs/mary_rose/fine_s1_600steps`` packed:
``bench/results/gpu/``, docs/results.md, *fifth session*.)
Here, on the CPU alone (proves it runs; what the test does):
    python scripts/gpu_speed.py SCENE --devices cpu --sizes 64x48 --views 2 --frames 4 --out /tmp/g

The packed scene holds training views only: each view enhanced is a training view, which never
uses its own photo as a neighbour (as a held-out view would not), and the path runs through the
first ``--frames`` training cameras in order (dtu_scan37 has 42), each frame its render: far
apart, so its flicker and gain say little; its frames per second are the point. Per size the scene is resampled once
(``bench.sizes.sized_scene``). Per size and device, the first view warms up (kernels, the
neighbours' encodings), the others are timed (CUDA synchronised) and their gain over the render
measured; the float16 rows run the model under ``torch.autocast`` (pose fits, colour and trust as
they are) and report their largest difference from the float32 image on the same device.
Writes ``OUT/gpu_speed.json`` (with the card, torch and the commit) and prints one line per row.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.common import stamp  # noqa: E402
from bench.sizes import sized_scene  # noqa: E402
from roguenerf.checkpoint import default_checkpoint_path, load_checkpoint  # noqa: E402
from roguenerf.data.readers import load_scene  # noqa: E402
from roguenerf.enhance import EnhanceOptions  # noqa: E402
from roguenerf.inference import SceneEnhancer  # noqa: E402
from roguenerf.metrics import psnr  # noqa: E402


def _sync(device: str) -> None:
    if device.startswith("cuda"):
        torch.cuda.synchronize()


def _half_model(enhancer: SceneEnhancer, device: str) -> None:
    """Run ``enhancer``'s model under float16 autocast (its output back in float32)."""
    forward = enhancer.model.forward

    def half(*args, **kwargs):
        with torch.autocast(device_type=device.split(":")[0], dtype=torch.float16):
            return forward(*args, **kwargs).float()

    enhancer.model.forward = half


def views_row(scene, views: list[int], device: str, half: bool, reference: dict | None,
              options: EnhanceOptions | None = None) -> tuple[dict, dict]:
    model, _ = load_checkpoint(default_checkpoint_path())
    enhancer = SceneEnhancer(scene, model, device=device, options=options)
    if half:
        _half_model(enhancer, device)
    enhancer.enhance_view(views[0])  # warm-up
    seconds, gains, images, stages = [], [], {}, {}
    for i in views[1:]:
        _sync(device)
        start = time.perf_counter()
        result = enhancer.enhance_view(i)
        _sync(device)
        seconds.append(time.perf_counter() - start)
        for name, value in result.timings.items():
            stages.setdefault(name, []).append(value)
        photo, render = scene.photo(i), scene.render(i)
        gains.append(float(psnr(result.image[None], photo[None])[0] - psnr(render[None], photo[None])[0]))
        images[i] = result.image
    row = {"device": device, "precision": "float16 model" if half else "float32", "views": len(seconds),
           "seconds_per_view": statistics.median(seconds), "gain_db": statistics.mean(gains),
           "stage_seconds": {k: round(statistics.median(v), 4) for k, v in stages.items()}}
    if reference is not None:
        row["max_abs_diff_vs_float32"] = max(float((images[i] - reference[i]).abs().max()) for i in images)
    return row, images


def path_rows(scene, views: list[int], device: str, work: Path) -> list[dict]:
    """``views`` as a camera path (their poses in order, their renders and depths as the frames),
    enhanced with the temporal filter off and on."""
    from roguenerf.imageio import write_png
    from roguenerf.trajectory import CameraPath, enhance_path

    frames = work / "frames"
    frames.mkdir(parents=True, exist_ok=True)
    for t, i in enumerate(views):
        write_png(frames / f"{t:05d}.png", scene.render(i))
        np.save(frames / f"{t:05d}.npy", scene.depth(i)[0].numpy())
    f0 = scene.frames[views[0]]
    path = CameraPath(world_from_cam=torch.stack([torch.as_tensor(scene.frames[i].world_from_cam, dtype=torch.float64)
                                                  for i in views]),
                      K=torch.stack([torch.as_tensor(scene.frames[i].K, dtype=torch.float64) for i in views]),
                      width=f0.width, height=f0.height)
    model, _ = load_checkpoint(default_checkpoint_path())
    rows = []
    for temporal in (False, True):
        enhancer = SceneEnhancer(scene, model, device=device, options=EnhanceOptions.from_flags(temporal=temporal))
        out = work / f"path_{device.replace(':', '')}_{temporal}"
        result = enhance_path(scene, enhancer, path, frames, out, video=False, force=True)
        report = result.flicker
        rows.append({"device": device, "path_frames": result.enhanced_now, "size": f"{f0.width}x{f0.height}",
                     "temporal": temporal, "frames_per_second": result.frames_per_second,
                     "flicker_ratio": report["flicker"]["ratio"], "gain_db": report["psnr"]["mean_gain_db"]})
    return rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scene", type=Path, help="scene folder with renders and depths (a packed one travels)")
    ap.add_argument("--devices", default="cpu,cuda", help="comma-separated (default cpu,cuda)")
    ap.add_argument("--sizes", default="512x512,1920x1080")
    ap.add_argument("--views", type=int, default=4, help="views per size and device, the first a warm-up")
    ap.add_argument("--frames", type=int, default=48, help="cameras of the path (the first views in order)")
    ap.add_argument("--tiles", default="", help=(
        "comma-separated tile sizes (EnhanceOptions.tile) to time on the non-CPU devices beside the shipped one, "
        "e.g. 1024,2048; each also without pose refinement"))
    ap.add_argument("--no-path", action="store_true", help="skip the path rows")
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args(argv)
    devices = [d for d in args.devices.split(",") if d]
    if any(d.startswith("cuda") for d in devices) and not torch.cuda.is_available():
        raise SystemExit("--devices: no CUDA device here (use --devices cpu)")
    card = torch.cuda.get_device_name() if torch.cuda.is_available() else None
    print(f"torch {torch.__version__}, card {card}, {torch.get_num_threads()} CPU threads", flush=True)
    scene_dir = args.scene.resolve()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for text in args.sizes.split(","):
            w, h = (int(x) for x in text.split("x"))
            scene = load_scene(sized_scene(scene_dir, (w, h), Path(tmp) / text))
            views = scene.indices("train")[:args.views]
            for device in devices:
                row, reference = views_row(scene, views, device, False, None)
                rows.append({"size": text, **row})
                print(json.dumps(rows[-1]), flush=True)
                if device != "cpu":
                    try:
                        row, _ = views_row(scene, views, device, True, reference)
                    except Exception as exc:  # noqa: BLE001 - a model that will not run in float16 is a result
                        row = {"device": device, "precision": "float16 model", "error": f"{type(exc).__name__}: {exc}"}
                    rows.append({"size": text, **row})
                    print(json.dumps(rows[-1]), flush=True)
                    for tile in [int(t) for t in args.tiles.split(",") if t]:
                        for align in (True, False):
                            options = EnhanceOptions.from_flags(tile=tile, align=align)
                            row, _ = views_row(scene, views, device, False, reference, options)
                            rows.append({"size": text, "tile": tile, "align": align, **row})
                            print(json.dumps(rows[-1]), flush=True)
        scene = load_scene(scene_dir)
        views = scene.indices("train")[:args.frames]
        for device in [] if args.no_path else devices:
            for row in path_rows(scene, views, device, Path(tmp)):
                rows.append(row)
                print(json.dumps(row), flush=True)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "gpu_speed.json").write_text(json.dumps({**stamp(), "card": card, "torch": torch.__version__,
                                                         "command": " ".join(sys.argv), "rows": rows}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
