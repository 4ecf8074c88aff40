"""Pack render/photo pair folders small enough to travel to a lent GPU machine (64 MiB in all).

    python scripts/pack_pairs.py CACHE/cup/coarse_x3 CACHE/beer/coarse_x3 ... ../shared/data/lego \
        --out .gpu/pairs --every 2 --quality 95

Each folder becomes ``OUT/<scene>`` (``OUT/<scene>_<preset>`` when two share a scene name), a
scene folder ``roguenerf.data.load_scene`` reads: its training views only (pre-training's
targets and neighbours; held-out views are never used there), every ``--every``-th of them in
file order (the captures are orbits and sweeps in order, so this thins them evenly), photos and
renders as JPEG (``--quality``, 4:4:4), depths as float16 ``.npz``. What the compression costs
is printed per folder: PSNR of the packed photo and render against the originals, and the
depths' largest relative error. Runs again from scratch (the output folder of a scene is
replaced when this script packed it and it holds nothing else; any other folder is refused).
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
from pathlib import Path

import numpy as np
from PIL import Image

from roguenerf.imageio import foreign_files, holds_files


def _psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2)) / 255.0**2
    return 10 * np.log10(1 / max(mse, 1e-12))


def _save_jpeg(src: Path, dst: Path, quality: int) -> float:
    image = np.asarray(Image.open(src).convert("RGB"))
    Image.fromarray(image).save(dst, "JPEG", quality=quality, subsampling=0)
    return _psnr(image, np.asarray(Image.open(dst).convert("RGB")))


def check_out(out: Path) -> None:
    """``out`` may be new, empty, or a folder this script packed holding nothing else (it is then
    replaced); anything else (a dataset, a folder of the user's) is refused before any work."""
    if not holds_files(out, lambda: SystemExit(f"{out}: exists and is not a folder; choose a new --out")):
        return
    try:
        meta = json.loads((out / "transforms.json").read_text())
        ours = {"transforms.json", *(f[k] for f in meta["frames"] for k in ("file_path", "render_path", "depth_path"))}
        packed = "packed_from" in meta
    except (OSError, ValueError, KeyError, TypeError):
        packed, ours = False, set()
    if not packed:
        raise SystemExit(f"{out}: exists and is not empty: it holds other files, not a folder this script packed "
                         "(which would be replaced); choose a new --out")
    foreign = foreign_files(out, ours)
    if foreign:
        raise SystemExit(f"{out}: a packed folder that also holds files this script did not write "
                         f"({', '.join(foreign[:3])}), which replacing it would delete; move them out or choose "
                         "a new --out")


def pack(folder: Path, out: Path, every: int, quality: int) -> tuple[int, int]:
    """Pack one pair folder into ``out``; returns (views kept, bytes written)."""
    meta = json.loads((folder / "transforms.json").read_text())
    train = [f for f in meta["frames"] if f.get("split", "train") == "train"]
    if not train:
        raise SystemExit(f"{folder}: no training views")
    for f in train:
        if not f.get("render_path") or not f.get("depth_path"):
            raise SystemExit(f"{folder}: view {f['file_path']} has no render or depth: not a pair folder")
    keep = sorted(train, key=lambda f: f["file_path"])[::every]
    check_out(out)
    if out.exists():
        shutil.rmtree(out)
    for sub in ("images", "renders", "depths"):
        (out / sub).mkdir(parents=True)
    frames, photo_db, render_db, depth_err = [], [], [], 0.0
    for f in keep:
        stem = Path(f["file_path"]).stem
        frame = {k: v for k, v in f.items() if k not in ("acc_path",)}
        photo_db.append(_save_jpeg(folder / f["file_path"], out / "images" / f"{stem}.jpg", quality))
        render_db.append(_save_jpeg(folder / f["render_path"], out / "renders" / f"{stem}.jpg", quality))
        depth = np.load(folder / f["depth_path"]).astype(np.float32)
        half = depth.astype(np.float16)
        if not np.isfinite(half).all():
            raise SystemExit(f"{folder / f['depth_path']}: depth does not fit float16")
        np.savez_compressed(out / "depths" / f"{stem}.npz", depth=half)
        valid = depth > 0
        if valid.any():
            depth_err = max(depth_err, float(np.max(np.abs(half[valid] - depth[valid]) / depth[valid])))
        frame.update(file_path=f"images/{stem}.jpg", render_path=f"renders/{stem}.jpg",
                     depth_path=f"depths/{stem}.npz", split="train")
        frames.append(frame)
    meta = {k: v for k, v in meta.items() if k not in ("frames", "train_filenames", "test_filenames",
                                                       "val_filenames")}
    meta["frames"] = frames
    meta["packed_from"] = {"folder": str(folder), "every": every, "jpeg_quality": quality,
                           "depth": "float16 npz"}
    (out / "transforms.json").write_text(json.dumps(meta, indent=1))
    size = sum(p.stat().st_size for p in out.rglob("*") if p.is_file())
    print(f"{folder} -> {out}: {len(keep)} of {len(train)} training views, {size / 2**20:.1f} MiB; "
          f"photos {min(photo_db):.1f} dB, renders {min(render_db):.1f} dB (worst view), "
          f"depth {depth_err:.2e} relative (largest)", file=sys.stderr)
    return len(keep), size


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("folders", nargs="+", type=Path, help="pair folders (transforms.json with render_path)")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--every", type=int, default=1, help="keep every N-th training view")
    parser.add_argument("--quality", type=int, default=95, help="JPEG quality of photos and renders")
    args = parser.parse_args(argv)
    if args.every < 1 or not 1 <= args.quality <= 100:
        parser.error("--every >= 1 and --quality in 1..100")
    names = [f.resolve().parent.name if (f / "fit.json").is_file() else f.resolve().name for f in args.folders]
    outs = [args.out / (f"{name}_{folder.resolve().name}" if names.count(name) > 1 else name)
            for folder, name in zip(args.folders, names)]
    for out in outs:  # every output checked before any is written
        check_out(out)
    total = 0
    for folder, out in zip(args.folders, outs):
        total += pack(folder, out, args.every, args.quality)[1]
    print(f"{len(args.folders)} folders, {total / 2**20:.1f} MiB in {args.out}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
