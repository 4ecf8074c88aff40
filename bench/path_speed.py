"""Frames per second along a camera path: frame by frame against the temporal filter, alternated.

    python -m bench.path_speed --fit runs/speed/dtu_scan37_fine --factor 1 --keys 4 --steps 16 \\
        --work runs/paths [--repeats 2] [--model-every 1,2] [--resample bicubic,bilinear] [--reject 0,0.04] \\
        [--output bench/results/path_speed_dtu_scan37_fine]

The path and its frames are ``bench.paths``'s (same ``--fit``, ``--factor``, ``--keys``,
``--steps`` and ``--work``: rendered once, cached). In one process, ``enhance_path`` runs on them
``--repeats`` times with the temporal filter off and on, alternated (off, on, off, on ...), each
into a fresh folder without videos: the frames per second of ``PathResult.frames_per_second``
(each made frame's whole turn: reading, enhancing, smoothing, writing, its flicker and PSNR; before
2026-11-30 without the flicker and PSNR), the flicker against the render's and against the
render sharpened alike (``flicker_ratio_sharpened``, from 2026-12-07:
:func:`~roguenerf.trajectory.flicker.sharpening`), the pairs across which the model's neighbour
set changed and the flicker ratio there and elsewhere (``neighbour_changes``,
``flicker_ratio_changed``, ``flicker_ratio_steady``; pairs with a carried frame in neither), and the
gain on the frames with photos.
``--model-every``, ``--resample``, ``--reject``, ``--carry-from``, ``--blend``,
``--carry-agreement``, ``--carry-between``, ``--between-agreement``, ``--weight``,
``--change-weight``, ``--change-frames`` and ``--both-ways`` run the filter once per combination of values of
:attr:`~roguenerf.enhance.temporal.TemporalConfig.model_every`,
:attr:`~roguenerf.enhance.temporal.TemporalConfig.resample`,
:attr:`~roguenerf.enhance.temporal.TemporalConfig.reject`,
:attr:`~roguenerf.enhance.temporal.TemporalConfig.carry_from`,
:attr:`~roguenerf.enhance.temporal.TemporalConfig.blend`,
:attr:`~roguenerf.enhance.temporal.TemporalConfig.carry_agreement`,
:attr:`~roguenerf.enhance.temporal.TemporalConfig.carry_between`,
:attr:`~roguenerf.enhance.temporal.TemporalConfig.between_agreement`,
:attr:`~roguenerf.enhance.temporal.TemporalConfig.weight`,
:attr:`~roguenerf.enhance.temporal.TemporalConfig.change_weight`,
:attr:`~roguenerf.enhance.temporal.TemporalConfig.change_frames` and
:attr:`~roguenerf.enhance.temporal.TemporalConfig.both_ways` (labelled ``on`` for the
shipped values, ``on/kK``, ``on/RESAMPLE``, ``on/rejectX``, ``on/from-C``, ``on/BLEND``,
``on/agreeDB``, ``on/between-on|off``, ``on/mutualDB``, ``on/wW``, ``on/cwW``, ``on/cfN`` and
``on/both-ways-on|off`` for
others; at ``model_every`` 1, where nothing is
carried, only the shipped ``carry_between`` runs), with the share of frames carried; the CSV also keeps each frame
with a photo's gain (``gains``: frame, gain, carried). Writes ``OUTPUT.csv`` (a row per run;
date, machine, commit), ``OUTPUT.json`` (the medians, the ratios) and ``OUTPUT.png``.
"""

from __future__ import annotations

import argparse
import itertools
import shutil
import statistics
import sys
import tempfile
from pathlib import Path

from bench.common import RESULTS, beside, save_figure, stamp, write_csv, write_json


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--fit", type=Path, required=True, help="make-pairs output (as bench.paths --fit)")
    ap.add_argument("--work", type=Path, default=Path("runs/paths"))
    ap.add_argument("--factor", type=int, default=1)
    ap.add_argument("--keys", type=int, default=4)
    ap.add_argument("--steps", type=int, default=16)
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--output", type=Path, default=None)
    ap.add_argument("--model-every", default=None,
                    help="comma-separated TemporalConfig.model_every values for the filter (default: the shipped one)")
    ap.add_argument("--resample", default=None,
                    help="comma-separated TemporalConfig.resample values for the filter (default: the shipped one)")
    ap.add_argument("--reject", default=None,
                    help="comma-separated TemporalConfig.reject values for the filter (default: the shipped one)")
    ap.add_argument("--carry-agreement", default=None,
                    help="comma-separated TemporalConfig.carry_agreement values (dB) for the filter "
                         "(default: the shipped one)")
    ap.add_argument("--blend", default=None,
                    help="comma-separated TemporalConfig.blend values for the filter (default: the shipped one)")
    ap.add_argument("--carry-from", default=None,
                    help="comma-separated TemporalConfig.carry_from values for the filter (default: the shipped one)")
    ap.add_argument("--carry-between", default=None,
                    help="comma-separated TemporalConfig.carry_between values, on/off (default: the shipped one)")
    ap.add_argument("--between-agreement", default=None,
                    help="comma-separated TemporalConfig.between_agreement values (default: the shipped one)")
    ap.add_argument("--weight", default=None,
                    help="comma-separated TemporalConfig.weight values (default: the shipped one)")
    ap.add_argument("--both-ways", default=None,
                    help="comma-separated TemporalConfig.both_ways values, on/off (default: the shipped one)")
    ap.add_argument("--change-weight", default=None,
                    help="comma-separated TemporalConfig.change_weight values (default: the shipped one)")
    ap.add_argument("--change-frames", default=None,
                    help="comma-separated TemporalConfig.change_frames values (default: the shipped one)")
    ap.add_argument("--force", action="store_true", help="enhance a path enhance_path's check refuses (as bench.paths)")
    args = ap.parse_args(argv)
    if args.repeats < 1:
        raise SystemExit(f"--repeats: expected 1 or more, got {args.repeats}")
    args.photo_path, args.toy, args.quick = False, False, False

    import roguenerf.runtime
    from bench.paths import field_frames
    from roguenerf import SceneEnhancer, load_checkpoint
    from roguenerf.checkpoint import default_checkpoint_path
    from roguenerf.enhance import EnhanceOptions
    from roguenerf.enhance.temporal import TemporalConfig
    from roguenerf.trajectory import CameraPath, enhance_path

    roguenerf.runtime.configure()
    scene, frames, poses, K, width, height, *_rest, name = field_frames(args)
    camera_path = CameraPath(world_from_cam=poses, K=K.expand(len(poses), 3, 3).clone(), width=width,
                             height=height, fps=24.0)
    model, _ = load_checkpoint(default_checkpoint_path())
    shipped = TemporalConfig()
    every = [shipped.model_every] if args.model_every is None else [int(k) for k in args.model_every.split(",")]
    resample = [shipped.resample] if args.resample is None else args.resample.split(",")
    reject = [shipped.reject] if args.reject is None else [float(x) for x in args.reject.split(",")]
    carry = [shipped.carry_from] if args.carry_from is None else args.carry_from.split(",")
    blend = [shipped.blend] if args.blend is None else args.blend.split(",")
    gates = ([shipped.carry_agreement] if args.carry_agreement is None
             else [float(x) for x in args.carry_agreement.split(",")])
    onoff = {"on": True, "off": False}
    if args.carry_between is not None and not set(args.carry_between.split(",")) <= set(onoff):
        raise SystemExit(f"--carry-between: expected on, off or on,off, got {args.carry_between}")
    betweens = ([shipped.carry_between] if args.carry_between is None
                else [onoff[x] for x in args.carry_between.split(",")])
    mutual = ([shipped.between_agreement] if args.between_agreement is None
              else [float(x) for x in args.between_agreement.split(",")])
    weights = [shipped.weight] if args.weight is None else [float(x) for x in args.weight.split(",")]
    change = ([shipped.change_weight] if args.change_weight is None
              else [float(x) for x in args.change_weight.split(",")])
    if args.both_ways is not None and not set(args.both_ways.split(",")) <= set(onoff):
        raise SystemExit(f"--both-ways: expected on, off or on,off, got {args.both_ways}")
    ways = [shipped.both_ways] if args.both_ways is None else [onoff[x] for x in args.both_ways.split(",")]
    settle = ([shipped.change_frames] if args.change_frames is None
              else [int(x) for x in args.change_frames.split(",")])
    modes = {"off": None}
    for k, r, j, c, b, g, bw, m, w, cw, cf, two in itertools.product(every, resample, reject, carry, blend, gates,
                                                                      betweens, mutual, weights, change, settle, ways):
        if k == 1 and m != shipped.between_agreement:
            continue  # nothing is carried at K = 1
        if k == 1 and bw != shipped.carry_between:
            continue  # nothing is carried at K = 1: the same run as the shipped value's
        label = "/".join(["on", *([f"k{k}"] if k != shipped.model_every else []),
                          *([r] if r != shipped.resample else []),
                          *([f"reject{j:g}"] if j != shipped.reject else []),
                          *([f"from-{c}"] if c != shipped.carry_from else []),
                          *([b] if b != shipped.blend else []),
                          *([f"agree{g:g}"] if g != shipped.carry_agreement else []),
                          *([f"between-{'on' if bw else 'off'}"] if bw != shipped.carry_between else []),
                          *([f"mutual{m:g}"] if m != shipped.between_agreement else []),
                          *([f"w{w:g}"] if w != shipped.weight else []),
                          *([f"cw{cw:g}"] if cw != shipped.change_weight else []),
                          *([f"cf{cf}"] if cf != shipped.change_frames else []),
                          *([f"both-ways-{'on' if two else 'off'}"] if two != shipped.both_ways else [])])
        modes[label] = TemporalConfig(model_every=k, resample=r, reject=j, carry_from=c, blend=b,
                                      carry_agreement=g, carry_between=bw, between_agreement=m, weight=w,
                                      change_weight=cw, change_frames=cf, both_ways=two)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for repeat in range(args.repeats):
            for mode, config in modes.items():
                enhancer = SceneEnhancer(scene, model, options=EnhanceOptions(temporal=config))
                out = Path(tmp) / mode.replace("/", "_")
                shutil.rmtree(out, ignore_errors=True)
                result = enhance_path(scene, enhancer, camera_path, frames, out, video=False, force=args.force)
                report = result.flicker
                rows.append({**stamp(), "scene": name, "size": f"{width}x{height}", "frames": result.enhanced_now,
                             "repeat": repeat, "temporal": mode, "enhance_seconds": round(result.enhance_seconds, 3),
                             "frames_per_second": round(result.frames_per_second, 4),
                             "flicker_ratio": round(report["flicker"]["ratio"], 4),
                             "flicker_ratio_sharpened": round(report["flicker"]["ratio_sharpened"], 4),
                             "detail_ratio": round(report["flicker"]["detail_ratio"], 4),
                             "neighbour_changes": report["flicker"]["neighbour_changes"],
                             **{f"flicker_ratio_{k}": (None if report["flicker"][f"ratio_{k}"] is None
                                                       else round(report["flicker"][f"ratio_{k}"], 4))
                                for k in ("changed", "steady")},
                             "gain_db": round(report["psnr"]["mean_gain_db"], 4),
                             "carried_share": round(sum(bool(f.get("carried")) for f in report["per_frame"])
                                                    / len(report["per_frame"]), 4),
                             "gains": " ".join(f"{f['frame']}:{f['gain_db']:+.3f}" + ("c" if f.get("carried") else "")
                                               for f in report["per_frame"] if "gain_db" in f)})
                print(f"temporal {mode}: {rows[-1]['frames_per_second']:.2f} frames/s, flicker x"
                      f"{rows[-1]['flicker_ratio']:.3f}, gain {rows[-1]['gain_db']:+.3f} dB", flush=True)
    fps = {m: statistics.median(r["frames_per_second"] for r in rows if r["temporal"] == m) for m in modes}
    summary = {**stamp(), "command": " ".join(["python -m bench.path_speed", *(argv or sys.argv[1:])]),
               "scene": name, "size": f"{width}x{height}", "frames": len(poses), "repeats": args.repeats,
               "frames_per_second": fps,
               "speed_ratio": {m: fps[m] / fps["off"] for m in modes if m != "off"},
               "flicker_ratio": {m: next(r["flicker_ratio"] for r in rows if r["temporal"] == m) for m in fps},
               "flicker_ratio_sharpened": {m: next(r["flicker_ratio_sharpened"] for r in rows if r["temporal"] == m)
                                           for m in fps},
               "gain_db": {m: next(r["gain_db"] for r in rows if r["temporal"] == m) for m in fps}}
    output = args.output or RESULTS / f"path_speed_{name}_{args.fit.name}"
    write_csv(beside(output, ".csv"), rows)
    write_json(beside(output, ".json"), summary)

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5, 3.5))
    for i, mode in enumerate(modes):
        ax.scatter([i] * args.repeats, [r["frames_per_second"] for r in rows if r["temporal"] == mode])
    ax.set_xticks(range(len(modes)), ["frame by frame" if m == "off" else f"filter {m[3:] or 'shipped'}"
                                      for m in modes])
    ax.set_ylabel("frames per second")
    ratios = ", ".join(f"{m}: x{r:.2f}" for m, r in summary["speed_ratio"].items())
    ax.set_title(f"{name} {width}x{height}, {len(poses)} frames: {ratios}", fontsize=9)
    fig.suptitle(f"{summary['date']} {summary['machine']} {summary['commit']}", fontsize=6)
    save_figure(fig, beside(output, ".png"))
    print(f"wrote {beside(output, '.csv')}, {beside(output, '.json')} and {beside(output, '.png')}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
