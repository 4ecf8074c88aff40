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
``--carry-agreement``, ``--carry-share``, ``--carry-nearer``, ``--carry-between``, ``--between-agreement``,
``--weight``, ``--change-weight``, ``--change-frames`` and ``--both-ways`` run the filter once per combination of
values of
:attr:`~roguenerf.enhance.temporal.TemporalConfig.model_every`,
:attr:`~roguenerf.enhance.temporal.TemporalConfig.resample`,
:attr:`~roguenerf.enhance.temporal.TemporalConfig.reject`,
:attr:`~roguenerf.enhance.temporal.TemporalConfig.carry_from`,
:attr:`~roguenerf.enhance.temporal.TemporalConfig.blend`,
:attr:`~roguenerf.enhance.temporal.TemporalConfig.carry_agreement`,
:attr:`~roguenerf.enhance.temporal.TemporalConfig.carry_share`,
:attr:`~roguenerf.enhance.temporal.TemporalConfig.carry_nearer`,
:attr:`~roguenerf.enhance.temporal.TemporalConfig.carry_between`,
:attr:`~roguenerf.enhance.temporal.TemporalConfig.between_agreement`,
:attr:`~roguenerf.enhance.temporal.TemporalConfig.weight`,
:attr:`~roguenerf.enhance.temporal.TemporalConfig.change_weight`,
:attr:`~roguenerf.enhance.temporal.TemporalConfig.change_frames` and
:attr:`~roguenerf.enhance.temporal.TemporalConfig.both_ways` (labelled ``on`` for the
shipped values, ``on/kK``, ``on/RESAMPLE``, ``on/rejectX``, ``on/from-C``, ``on/BLEND``,
``on/agreeDB``, ``on/shareS``, ``on/nearerR``, ``on/sched-fixed|gate``, ``on/between-on|off``, ``on/mutualDB``,
``on/wW``, ``on/cwW``,
``on/cfN`` and ``on/both-ways-on|off`` for
others; at ``model_every`` 1, where nothing is carried, only the shipped carry gates and ``carry_between`` run),
with the share of frames carried; the CSV also keeps each frame with a photo's gain (``gains``:
frame, gain, carried) and each frame a carry gate judged (``carry_tests``: frame, the renders'
agreement in dB, with ``carry_share`` the change's after ``/``, with ``between_agreement`` the two
model frames' agreement with each other after ``~``, with ``carry_nearer`` their distance over
the nearest photo's after ``@``, carried), and each filter run's carried frames with photos judged
against frame by frame's gain on the same frames (``carried_with_photo``, ``worst_carried_db``:
:func:`judge_carried`; a path whose frames with photos are model frames judges none: choose
``--steps`` so that they fall between, e.g. 15 at ``model_every`` 4). ``--photo-path``: the path of
``--keys`` scene views, train and test, in azimuth order (``bench.paths --photo-path``): every
frame has a photo, so every frame carried is judged. Writes ``OUTPUT.csv`` (a row per
run; date, machine, commit), ``OUTPUT.json`` (the medians, the ratios) and ``OUTPUT.png``.

``--filter-before REV`` also runs every filter setting with the ``TemporalFilter`` of an older
revision's ``roguenerf/enhance/temporal.py`` (loaded from a temporary worktree into this process:
the rest of the code is this checkout's), labelled ``MODE@REV``, alternated with this checkout's
run by run (the order swapped every repeat), so that both see the same load; every row also
keeps the process's CPU seconds (``cpu_seconds``: all threads, less sensitive than the wall
clock to other processes' load). A filter older than ``TemporalConfig.fade_along`` gets the same
setting as this checkout's but fades by the last step's parallax alone, at its ``fade_deg`` (16 by
default now): to time the defaults of then, pass ``--fade-along off --fade-deg 4``.
"""

from __future__ import annotations

import argparse
import contextlib
import itertools
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

from bench.common import RESULTS, beside, older_tree, save_figure, stamp, write_csv, write_json

ONOFF = {"on": True, "off": False}
SWEPT = (
    ("model_every", int, lambda v: f"k{v}"),
    ("resample", str, str),
    ("reject", float, lambda v: f"reject{v:g}"),
    ("carry_from", str, lambda v: f"from-{v}"),
    ("blend", str, str),
    ("carry_agreement", float, lambda v: f"agree{v:g}"),
    ("carry_share", float, lambda v: f"share{v:g}"),
    ("carry_nearer", float, lambda v: f"nearer{v:g}"),
    ("schedule", str, lambda v: f"sched-{v}"),
    ("carry_between", ONOFF, lambda v: f"between-{'on' if v else 'off'}"),
    ("between_agreement", float, lambda v: f"mutual{v:g}"),
    ("weight", float, lambda v: f"w{v:g}"),
    ("change_weight", float, lambda v: f"cw{v:g}"),
    ("change_frames", int, lambda v: f"cf{v}"),
    ("both_ways", ONOFF, lambda v: f"both-ways-{'on' if v else 'off'}"),
    ("fade_deg", float, lambda v: f"fade{v:g}"),
    ("fade_along", ONOFF, lambda v: f"fade-along-{'on' if v else 'off'}"),
    ("reuse_poses", ONOFF, lambda v: f"reuse-poses-{'on' if v else 'off'}"),
    ("refit_nearer", float, lambda v: f"refit{v:g}"),
)
"""The TemporalConfig fields this bench sweeps, in the order of the runs and of their labels: each
with how its comma-separated values are read (on/off for the switches) and its label where it is
not the shipped value."""
CARRY_ONLY = ("between_agreement", "carry_agreement", "carry_between", "carry_nearer", "carry_share", "schedule")
"""The swept fields that only judge or shape carried frames: at ``model_every`` 1, where nothing is
carried, a run with any of them off its shipped value is the shipped values' run again (not made)."""


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--fit", type=Path, required=True, help="make-pairs output (as bench.paths --fit)")
    ap.add_argument("--work", type=Path, default=Path("runs/paths"))
    ap.add_argument("--factor", type=int, default=1)
    ap.add_argument("--keys", type=int, default=4)
    ap.add_argument("--steps", type=int, default=16)
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--output", type=Path, default=None)
    for field, kind, _label in SWEPT:
        ap.add_argument("--" + field.replace("_", "-"), default=None,
                        help=f"comma-separated TemporalConfig.{field} values{', on/off' if kind is ONOFF else ''} "
                             "(default: the shipped one)")
    ap.add_argument("--force", action="store_true", help="enhance a path enhance_path's check refuses (as bench.paths)")
    ap.add_argument("--photo-path", action="store_true",
                    help="the path of --keys scene views, train and test (as bench.paths --photo-path): every "
                         "frame has a photo, so every frame carried is judged against frame by frame")
    ap.add_argument("--filter-before", default=None, metavar="REV",
                    help="also run each filter setting with REV's TemporalFilter, alternated (labelled MODE@REV)")
    args = ap.parse_args(argv)
    if args.repeats < 1:
        raise SystemExit(f"--repeats: expected 1 or more, got {args.repeats}")
    args.toy, args.quick = False, False
    if args.photo_path:
        args.steps = 1
    chosen = {}  # field -> the values asked for (the shipped one where none was)
    for field, kind, _label in SWEPT:
        text = getattr(args, field)
        if text is None:
            continue
        if kind is ONOFF and not set(text.split(",")) <= set(ONOFF):
            raise SystemExit(f"--{field.replace('_', '-')}: expected on, off or on,off, got {text}")
        chosen[field] = [(ONOFF.get if kind is ONOFF else kind)(x) for x in text.split(",")]

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
    modes = {"off": None}
    for values in itertools.product(*(chosen.get(field, [getattr(shipped, field)]) for field, _, _ in SWEPT)):
        config = dict(zip((field for field, _, _ in SWEPT), values))
        if config["model_every"] == 1 and any(config[f] != getattr(shipped, f) for f in CARRY_ONLY):
            continue  # nothing is carried at K = 1: the same run as the shipped values'
        label = "/".join(["on", *(tag(v) for (field, _, tag), v in zip(SWEPT, values)
                                  if v != getattr(shipped, field))])
        modes[label] = TemporalConfig(**config)
    filters = {mode: None for mode in modes}  # None: this checkout's TemporalFilter
    rows = []
    with contextlib.ExitStack() as stack, tempfile.TemporaryDirectory() as tmp:
        pairs = [[mode] for mode in modes]  # each setting, then its older filter's run
        if args.filter_before:
            older = older_filter(*stack.enter_context(older_tree(args.filter_before)))
            for pair in pairs[1:]:
                pair.append(f"{pair[0]}@{older.revision}")
                modes[pair[1]] = modes[pair[0]]
                filters[pair[1]] = older.TemporalFilter
        import roguenerf.trajectory.enhancing as enhancing

        shipped_filter = enhancing.TemporalFilter
        for repeat in range(args.repeats):
            # the older filter's run before this checkout's every second repeat: both see the same load
            for mode in [m for pair in pairs for m in (pair if repeat % 2 == 0 else reversed(pair))]:
                config = modes[mode]
                enhancer = SceneEnhancer(scene, model, options=EnhanceOptions(temporal=config))
                out = Path(tmp) / mode.replace("/", "_").replace("@", "_")
                shutil.rmtree(out, ignore_errors=True)
                enhancing.TemporalFilter = filters[mode] or shipped_filter
                cpu = time.process_time()
                try:
                    result = enhance_path(scene, enhancer, camera_path, frames, out, video=False, force=args.force)
                finally:
                    enhancing.TemporalFilter = shipped_filter
                cpu = time.process_time() - cpu
                report = result.flicker
                rows.append({**stamp(), "scene": name, "size": f"{width}x{height}", "frames": result.enhanced_now,
                             "repeat": repeat, "temporal": mode, "enhance_seconds": round(result.enhance_seconds, 3),
                             "cpu_seconds": round(cpu, 3),
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
                                               for f in report["per_frame"] if "gain_db" in f),
                             "carry_tests": " ".join(carry_test(f) for f in report["per_frame"]
                                                     if "carry_agreement_db" in f or "carry_nearer" in f)})
                print(f"temporal {mode}: {rows[-1]['frames_per_second']:.2f} frames/s, flicker x"
                      f"{rows[-1]['flicker_ratio']:.3f}, gain {rows[-1]['gain_db']:+.3f} dB", flush=True)
    judge_carried(rows)
    fps = {m: statistics.median(r["frames_per_second"] for r in rows if r["temporal"] == m) for m in modes}
    summary = {**stamp(), "command": " ".join(["python -m bench.path_speed", *(argv or sys.argv[1:])]),
               "scene": name, "size": f"{width}x{height}", "frames": len(poses), "repeats": args.repeats,
               "frames_per_second": fps,
               "cpu_seconds": {m: statistics.median(r["cpu_seconds"] for r in rows if r["temporal"] == m)
                               for m in modes},
               "speed_ratio": {m: fps[m] / fps["off"] for m in modes if m != "off"},
               "flicker_ratio": {m: next(r["flicker_ratio"] for r in rows if r["temporal"] == m) for m in fps},
               "flicker_ratio_sharpened": {m: next(r["flicker_ratio_sharpened"] for r in rows if r["temporal"] == m)
                                           for m in fps},
               "gain_db": {m: next(r["gain_db"] for r in rows if r["temporal"] == m) for m in fps},
               "worst_carried_db": {m: next(r["worst_carried_db"] for r in rows if r["temporal"] == m)
                                    for m in fps if m != "off"}}
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
                                      for m in modes], fontsize=7)
    ax.set_ylabel("frames per second")
    ratios = ", ".join(f"{m}: x{r:.2f}" for m, r in summary["speed_ratio"].items())
    ax.set_title(f"{name} {width}x{height}, {len(poses)} frames: {ratios}", fontsize=9)
    fig.suptitle(f"{summary['date']} {summary['machine']} {summary['commit']}", fontsize=6)
    save_figure(fig, beside(output, ".png"))
    print(f"wrote {beside(output, '.csv')}, {beside(output, '.json')} and {beside(output, '.png')}")
    return 0


def frame_gains(row: dict) -> dict[int, tuple[float, bool]]:
    """A run's ``gains`` (``frame:GAIN`` with ``c`` where carried) as ``{frame: (gain, carried)}``."""
    out = {}
    for item in row["gains"].split():
        frame, gain = item.split(":")
        out[int(frame)] = (float(gain.rstrip("c")), gain.endswith("c"))
    return out


def judge_carried(rows: list[dict]) -> None:
    """Each filter run's carried frames with photos against frame by frame of the same repeat (the
    same frames' gains): ``carried_with_photo`` (how many) and ``worst_carried_db`` (the lowest
    gain difference, dB; None where none was carried), written into its row and printed; the
    frame-by-frame rows get neither. What the fast setting's rule judges (docs/results.md)."""
    baseline = {r["repeat"]: frame_gains(r) for r in rows if r["temporal"] == "off"}
    for row in rows:
        if row["temporal"] == "off":
            continue
        off = baseline[row["repeat"]]
        diffs = {t: gain - off[t][0] for t, (gain, carried) in frame_gains(row).items() if carried and t in off}
        row["carried_with_photo"] = len(diffs)
        row["worst_carried_db"] = round(min(diffs.values()), 3) if diffs else None
        if diffs:
            worst = min(diffs, key=diffs.get)
            print(f"temporal {row['temporal']}: {len(diffs)} carried frames with photos, the worst {worst}: "
                  f"{diffs[worst]:+.3f} dB against frame by frame", flush=True)


def carry_test(row: dict) -> str:
    """A frame a carry gate judged, for the CSV's ``carry_tests``: ``frame:AGREEMENT`` (dB; ``-``
    where a gate before it refused), then ``/CHANGE`` (dB), ``~MUTUAL`` (dB) and ``@NEARER`` (the
    model frames' distance over the nearest photo's) where measured, ``c`` where carried."""
    def number(key, digits):
        value = row.get(key)
        return "inf" if key in row and value is None else f"{value:.{digits}f}"

    return (f"{row['frame']}:" + (number("carry_agreement_db", 1) if "carry_agreement_db" in row else "-")
            + (f"/{number('carry_change_db', 1)}" if "carry_change_db" in row else "")
            + (f"~{number('between_agreement_db', 1)}" if "between_agreement_db" in row else "")
            + (f"@{number('carry_nearer', 2)}" if "carry_nearer" in row else "")
            + ("c" if row.get("carried") else ""))


def older_filter(tree: Path, revision: str):
    """``tree``'s ``roguenerf/enhance/temporal.py`` loaded as a module of its own (its imports are
    this checkout's), with ``revision`` (a short hash) as its ``revision``."""
    import importlib.util
    import inspect

    name = f"_temporal_{revision}"
    spec = importlib.util.spec_from_file_location(name, tree / "roguenerf" / "enhance" / "temporal.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module  # dataclasses look their module up while the class is made
    spec.loader.exec_module(module)
    module.revision = revision
    if "parallax" not in inspect.signature(module.TemporalFilter.remember).parameters:
        module.TemporalFilter = _before_fade_along(module)
    if not hasattr(module.TemporalConfig, "carry_share"):  # older: no share gate, nothing to report of it
        module.TemporalFilter = type("Filter", (module.TemporalFilter,), {"last_change": None})
    if "photo_distance" not in inspect.signature(module.TemporalFilter.carry).parameters:
        module.TemporalFilter = _before_carry_nearer(module.TemporalFilter)
    return module


def _before_carry_nearer(older):
    """An older ``TemporalFilter`` (before ``TemporalConfig.carry_nearer``) as this checkout's
    ``enhance_path`` calls it: the photo's distance is never judged, never reported."""

    class Filter(older):
        last_nearer = None

        def carry(self, *args, photo_distance=None, **kwargs):
            return super().carry(*args, **kwargs)

    return Filter


def _before_fade_along(module):
    """An older ``TemporalFilter`` (before ``TemporalConfig.fade_along``) as this checkout's
    ``enhance_path`` calls it: the map of what a frame carries is never made, never asked for."""

    class Filter(module.TemporalFilter):
        last_parallax = None

        def remember(self, *args, parallax=None, blended=None, **kwargs):
            return super().remember(*args, **kwargs)

    return Filter


if __name__ == "__main__":
    sys.exit(main())
