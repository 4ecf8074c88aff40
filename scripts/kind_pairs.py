"""Cross-fitted pairs of other kinds of field for pre-training scenes (issue 35, items 2-3).

    python scripts/kind_pairs.py --scenes cup,coke_can,dtu_scan24,doraemon --kinds hash,splat \
        --scale 2 --folds 2 --out ~/.cache/roguenerf/pairs

For each scene of ``../shared/data/real`` (never one of the held-out scenes) and each kind: the
photo set at 1/``--scale`` size, then ``make-pairs --preset KIND`` with ``--folds`` cross-fitting
(every view rendered by a field that never saw it) into ``OUT/SCENE/KIND_sS_xF``, with the same
reduced budgets as the leave-one-kind-out figure (``bench.kinds``: hash 400 steps x 1024 rays x
48 samples; splat its preset). Resumable: a finished fit is left as it is.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.kinds import downscaled_photo_set, fit_pairs  # noqa: E402

HELD_OUT = {"dtu_scan37", "mary_rose", "can_clip", "ollie"}
"""Never pre-trained on (scripts/pretrain_real.sh HOLDOUT): the evaluation scenes."""
BUDGETS = {"hash": {"steps": 400, "rays": 1024, "samples": 48}, "splat": {"steps": None}}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenes", required=True)
    parser.add_argument("--kinds", default="hash,splat")
    parser.add_argument("--data", type=Path, default=Path("../shared/data/real"))
    parser.add_argument("--scale", type=int, default=2)
    parser.add_argument("--folds", type=int, default=2)
    parser.add_argument("--out", type=Path, default=Path.home() / ".cache/roguenerf/pairs")
    args = parser.parse_args(argv)
    scenes = [s for s in args.scenes.split(",") if s]
    if HELD_OUT & set(scenes):
        parser.error(f"--scenes: {', '.join(sorted(HELD_OUT & set(scenes)))} are held out: never pre-train on them")
    kinds = [k for k in args.kinds.split(",") if k]
    for k in kinds:
        if k not in BUDGETS:
            parser.error(f"--kinds: expected some of {', '.join(BUDGETS)}, got {k!r}")
    if args.folds < 2:
        parser.error("--folds: expected >= 2 (cross-fitted pairs)")
    for name in scenes:
        src = args.data / name
        if not (src / "transforms.json").is_file():
            parser.error(f"--scenes: {src} is not a photo set")
        photos = downscaled_photo_set(src, args.out / name / f"photos_s{args.scale}", args.scale)
        for kind in kinds:
            budget = dict(BUDGETS[kind])
            out = args.out / name / f"{kind}_s{args.scale}_x{args.folds}"
            t0 = time.monotonic()
            report = fit_pairs(photos, out, kind, budget.pop("steps"), folds=args.folds, **budget)
            test = report.get("test") or {}
            print(f"{name}/{out.name}: train {report['train']['psnr']:.2f} dB, cross-fitted "
                  f"{test.get('psnr', float('nan')):.2f} dB, {time.monotonic() - t0:.0f} s", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
