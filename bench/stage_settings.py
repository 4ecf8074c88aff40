"""Settings of one enhancement stage side by side in one run, on one model output per view.

``--stage`` picks the stage; every test view of each scene folder is enhanced, and each
``--settings`` value is measured on it, so the settings differ in nothing else. Per view and
setting: PSNR gain over the render and FLIP change (lower is better), plus the stage's own
columns. CSV + plot with date, machine and commit; ``colour`` and ``trust`` also print a summary
per setting. A scene folder may name the checkpoint to use for it (``FOLDER=CHECKPOINT``: a
fine-tuned model; labelled ``(fine-tuned)``), else ``--checkpoint``.

``align`` (neighbour pose refinement; ``--settings off,on[,reuse,noreuse,earlyX]``): for each
``--noise`` level (Gaussian noise on the training views' poses only, as ``bench/kinds.py``)
every test view is enhanced with pose refinement off and on, in alternation (so both see the
same machine load): seconds per view and the share of neighbours whose fit was kept. ``reuse``
and ``noreuse`` are on with :attr:`~roguenerf.enhance.align.AlignConfig.reuse` True and False:
one enhancer per setting and noise level enhances the views in order, so a reused judgement
was made on an earlier view (the untimed call that warms the neighbour cache leaves
``SceneEnhancer.settled`` as it was). ``earlyX`` (e.g.
``early0.03``; ``early0``: every level fitted) is on with
:attr:`~roguenerf.enhance.align.AlignConfig.early_refusal` = X; ``earlyX@L`` also judges level
L (:attr:`~roguenerf.enhance.align.AlignConfig.early_level`; ``early0.05@0``: the first). ``--max-rotation`` and
``--max-translation`` set the fit's trust region.

``colour`` (``--settings`` of :class:`~roguenerf.enhance.colour.ColourConfig`: ``off``,
``default`` or ``FIELD=VALUE[:FIELD=VALUE]``): every view is enhanced once without colour
matching (the model's own output, pose refinement on as shipped); each setting then matches
that same output to the neighbours (:meth:`SceneEnhancer.colour_match`): the share of pixels
where the neighbours agree, whether anything was changed, and the seconds the match took.

``trust``: every view is enhanced once as shipped but with trust off (pose refinement and
colour matching on); the share of its pixels where two or more neighbours agree is measured on
the same small copies the enhancer uses. Each plain number of ``--settings`` is a
:attr:`~roguenerf.enhance.trust.TrustConfig.full_share` that keeps ``min(1, share / value)`` of
that output's change over the render (:func:`~roguenerf.enhance.trust.trust_factor`), per view
on every view. ``localS`` (e.g. ``local16``) instead keeps, per pixel, the share of agreeing
pixels within about S pixels of it (Gaussian sigma, small copies) over 0.5: a per-pixel trust on
every view. ``belowX`` (e.g. ``below0.1``) is the shipped rule with
:attr:`~roguenerf.enhance.trust.TrustConfig.local_below` = X: per view, and per pixel
(``local_sigma``) on views whose agreement is under X
(:func:`~roguenerf.enhance.trust.kept_change`). ``alone`` keeps the shipped rule's share but
takes the rest of the change from the model run without neighbours instead of the render (a
fallback measured, not shipped). Columns: the agreement share and the share kept.

    python -m bench.stage_settings --stage align runs/kinds/pairs/can_clip/splat_s2 --noise 0/0,0.5/0.05
    python -m bench.stage_settings --stage colour runs/kinds/pairs/can_clip/splat_s2 \\
        --settings off,local_sigma=0,local_sigma=8
    python -m bench.stage_settings --stage trust runs/kinds/pairs/ollie/splat_s2 \\
        runs/kinds/pairs/ollie/splat_s2=runs/kinds/finetune/ollie/splat_s2/E8h/10min/model.safetensors
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import NamedTuple

from bench.common import RESULTS, save_figure, scene_label, stamp, summary_by_setting, write_outputs
from bench.kinds import _noise

COLOUR_SETTINGS = "off,local_sigma=0:min_share=0.05,local_sigma=0,local_sigma=4,local_sigma=8,local_sigma=16"
TRUST_SETTINGS = "off,0.3,0.4,0.5,0.6,0.7"
ALIGN_NOISE = "0/0,0.5/0.05"
PREFIXES = {"local": "S > 0 pixels", "below": "X a share in [0, 1]"}
MAPS = (*PREFIXES, "alone")
"""Trust settings that keep the change by the view's agreement map (:attr:`EnhanceResult.agreement_map`)."""


def _specs(text: str) -> list[str]:
    out = [c.strip() for c in text.split(",") if c.strip()]
    if not out:
        raise argparse.ArgumentTypeError("--settings: expected at least one setting")
    return out


def align_settings(text: str) -> list[str]:
    """``off``, ``on`` and / or ``earlyX`` (X a share in [0, 1); ``early0`` fits every level): pose
    refinement per view, in that order."""
    out = []
    for c in _specs(text):
        if c.startswith("early"):
            try:
                _early(c)
            except ValueError:
                raise argparse.ArgumentTypeError(f"--settings: {c!r}: expected earlyX or earlyX@L with X in [0, 1) "
                                                 "and L a level index, e.g. early0.03 or early0.05@0") from None
        elif c not in ("off", "on", "reuse", "noreuse"):
            raise argparse.ArgumentTypeError(f"--settings: {c!r} is none of off, on, reuse, noreuse, earlyX, earlyX@L")
        out.append(c)
    return out


def _align_config(setting: str, **trust):
    """The AlignConfig of an ``align_settings`` entry (None: off). ``on`` is the shipped one."""
    from roguenerf.enhance.align import AlignConfig

    if setting == "off":
        return None
    if setting.startswith("early"):
        share, level = _early(setting)
        return AlignConfig(early_refusal=share, early_level=level, **trust)
    if setting in ("reuse", "noreuse"):
        return AlignConfig(reuse=setting == "reuse", **trust)
    return AlignConfig(**trust)


def _early(setting: str) -> tuple[float, int]:
    """``earlyX[@L]``: the early-refusal share X and the judged level L (default: the one before
    the finest, -2); ValueError when it is not that."""
    share, _, level = setting[len("early"):].partition("@")
    x, index = float(share), int(level) if level else -2
    if not 0 <= x < 1:
        raise ValueError(setting)
    return x, index


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
            raise InputError(f"--settings: {part!r} is not FIELD=VALUE with a field of ColourConfig "
                             f"({', '.join(ColourConfig.__dataclass_fields__)})")
        fields[name] = float(value)
    return ColourConfig(**fields)


def colour_settings(text: str) -> list[tuple[str, object]]:
    """Each setting with its :class:`ColourConfig` (None: off)."""
    from roguenerf.errors import InputError

    try:
        return [(spec, colour_config(spec)) for spec in _specs(text)]
    except (InputError, ValueError) as exc:  # a field ColourConfig has not, a value that is no number
        raise argparse.ArgumentTypeError(str(exc)) from None


def trust_settings(text: str) -> list[str]:
    out = _specs(text)
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
    p.add_argument("--stage", required=True, choices=list(STAGES), help="the stage whose settings are compared")
    p.add_argument("scenes", type=_job, nargs="+",
                   help="scene folders (photos, renders, depths), each optionally =CHECKPOINT")
    p.add_argument("--checkpoint", type=Path, default=None, help="default: the shipped checkpoint")
    p.add_argument("--settings", default=None,
                   help="comma-separated settings of the stage (see above); default: align "
                        f"{STAGES['align'].settings}, colour {COLOUR_SETTINGS}, trust {TRUST_SETTINGS}")
    p.add_argument("--noise", type=_noise, default=None,
                   help=f"align: pose-noise levels deg/share, comma-separated (default {ALIGN_NOISE})")
    p.add_argument("--max-rotation", type=float, default=None,
                   help="align: the fit's trust region, degrees (default: AlignConfig's)")
    p.add_argument("--max-translation", type=float, default=None,
                   help="align: the fit's trust region, share of the median depth (default: AlignConfig's)")
    p.add_argument("--max-views", type=int, default=None)
    p.add_argument("--output", type=Path, default=None,
                   help="default: bench/results/align_cost, colour or trust, by --stage")
    args = p.parse_args(argv)
    stage = STAGES[args.stage]
    if args.stage != "align" and (args.noise, args.max_rotation, args.max_translation) != (None, None, None):
        p.error("--noise, --max-rotation, --max-translation: for --stage align only")
    try:
        args.settings = stage.parse(stage.settings if args.settings is None else args.settings)
    except argparse.ArgumentTypeError as exc:
        p.error(str(exc))
    args.noise = _noise(ALIGN_NOISE) if args.noise is None else args.noise
    args.output = RESULTS / stage.output if args.output is None else args.output
    return args


def _views(scene, max_views: int | None) -> list[int]:
    return scene.indices("test")[:max_views] if max_views else scene.indices("test")


class _View:
    """A test view's photo and render, and the render's PSNR and FLIP against the photo."""

    def __init__(self, scene, i: int):
        from roguenerf import metrics

        self.frame = scene.frames[i]
        self.photo, self.render = scene.photo(i)[None], scene.render(i)[None]
        self.psnr = float(metrics.psnr(self.render, self.photo)[0])
        self.flip = float(metrics.flip(self.render, self.photo)[0])

    def scores(self, out) -> dict:
        """``gain_db`` and ``flip_change`` of ``out`` (1,3,H,W) over the render."""
        from roguenerf import metrics

        return {"gain_db": round(float(metrics.psnr(out, self.photo)[0]) - self.psnr, 4),
                "flip_change": round(float(metrics.flip(out, self.photo)[0]) - self.flip, 5)}


def _align_rows(args, clean, model, checkpoint: Path, head: dict) -> list[dict]:
    from bench.kinds import noisy_scene
    from roguenerf.enhance import EnhanceOptions
    from roguenerf.enhance.align import AlignConfig
    from roguenerf.inference import SceneEnhancer

    trust = {k: v for k, v in (("max_rotation_deg", args.max_rotation), ("max_translation", args.max_translation))
             if v is not None}
    config = AlignConfig(**trust)
    rows = []
    for k, (deg, share) in enumerate(args.noise):
        scene = clean if deg == 0 and share == 0 else noisy_scene(clean, deg, share, seed=1000 + k)
        enhancers = {a: SceneEnhancer(scene, model, options=EnhanceOptions(align=_align_config(a, **trust)))
                     for a in args.settings}
        for i in _views(scene, args.max_views):
            for enhancer in enhancers.values():  # warm each neighbour cache: time the request, not the cache
                settled = set(enhancer.settled)  # but leave what earlier views settled as it was
                enhancer.enhance_view(i)
                enhancer.settled = settled
            view = _View(scene, i)
            for align in args.settings:
                t0 = time.perf_counter()
                result = enhancers[align].enhance_view(i)
                seconds = time.perf_counter() - t0
                rows.append({**head, "noise_deg": deg, "noise_share": share, "view": view.frame.name,
                             "align": align, "seconds": round(seconds, 3), **view.scores(result.image[None]),
                             "aligned_share": (round(sum(result.aligned) / len(result.aligned), 3)
                                               if result.aligned else 0.0),
                             "checkpoint": checkpoint.name, "max_rotation_deg": config.max_rotation_deg,
                             "max_translation": config.max_translation,
                             "early_refusal": (enhancers[align].align.early_refusal
                                               if enhancers[align].align is not None else None),
                             "early_level": (enhancers[align].align.early_level
                                             if enhancers[align].align is not None else None)})
                print(f"{head['scene']} {deg:g}/{share:g} {view.frame.name} align={align}: "
                      f"{seconds:.2f} s, gain {rows[-1]['gain_db']:+.3f} dB", flush=True)
    return rows


def _each_view(args, scene, model, stage: str, per_view) -> list[dict]:
    """``per_view(enhancer, i, view)`` rows of each test view, enhanced with ``stage`` off."""
    from roguenerf.enhance import EnhanceOptions
    from roguenerf.inference import SceneEnhancer

    enhancer = SceneEnhancer(scene, model, options=EnhanceOptions(**{stage: None}))
    return [row for i in _views(scene, args.max_views) for row in per_view(enhancer, i, _View(scene, i))]


def _colour_rows(args, scene, model, checkpoint: Path, head: dict) -> list[dict]:
    from roguenerf.enhance.colour import apply_match

    def per_view(enhancer, i: int, view: _View) -> list[dict]:
        frame, depth = view.frame, scene.depth(i)
        result = enhancer.enhance_view(i)
        positions = [enhancer.train.index(scene.index(n)) for n in result.neighbours]
        poses, rows = None, []
        for spec, config in args.settings:
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
            rows.append({**head, "view": frame.name, "config": spec, **view.scores(image[None]),
                         "agree_share": None if share is None else round(share, 3), "changed": changed,
                         "match_seconds": round(seconds, 3), "checkpoint": checkpoint.name})
            print(f"{head['scene']} {frame.name} {spec}: gain {rows[-1]['gain_db']:+.3f} dB, "
                  f"FLIP {rows[-1]['flip_change']:+.4f}", flush=True)
        return rows

    return _each_view(args, scene, model, "colour", per_view)


def _trust_rows(args, scene, model, checkpoint: Path, head: dict) -> list[dict]:
    import torch

    from roguenerf.enhance.trust import TrustConfig, kept_change, local_keep, share_kept, trust_factor
    from roguenerf.geometry import as_world_from_cam

    def per_view(enhancer, i: int, view: _View) -> list[dict]:
        frame, render, depth = view.frame, view.render, scene.depth(i)
        t0 = time.perf_counter()
        result = enhancer.enhance_view(i)
        seconds = time.perf_counter() - t0
        share, agree = result.agreement, result.agreement_map  # the enhancer's (colour matching's test)
        rows = []
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
            rows.append({**head, "view": frame.name, "setting": spec, **view.scores(out),
                         "agreement": None if share is None else round(share, 4), "kept": round(kept, 4),
                         "enhance_seconds": round(seconds, 2), "checkpoint": str(checkpoint)})
        print(f"{head['scene']} {frame.name}: agreement {share if share is None else round(share, 3)}, gains "
              + " ".join(f"{r['setting']}:{r['gain_db']:+.3f}" for r in rows), flush=True)
        return rows

    return _each_view(args, scene, model, "trust", per_view)


def measure(args) -> list[dict]:
    from roguenerf.checkpoint import default_checkpoint_path, load_checkpoint
    from roguenerf.data.readers import load_scene

    stage = STAGES[args.stage]
    base = stamp()
    rows, models = [], {}
    for scene_dir, own in args.scenes:
        checkpoint = own or args.checkpoint or default_checkpoint_path()
        if checkpoint not in models:
            models[checkpoint], _ = load_checkpoint(checkpoint)
        head = {**base, "scene": scene_label(scene_dir) + (" (fine-tuned)" if own else "")}
        rows += stage.measure(args, load_scene(scene_dir), models[checkpoint], checkpoint, head)
    return rows


def summary(rows: list[dict], stage: str) -> list[dict]:
    """Per setting: the mean over scenes of each scene's mean gain, views with a better FLIP, worst view."""
    return summary_by_setting(rows, STAGES[stage].column)


def _caption(rows: list[dict], what: str, lead: str = "") -> str:
    first = rows[0] if rows else {}
    return f"{what} — {lead}{first.get('date', '')[:10]}, {first.get('commit', '')}\n{first.get('machine', '')}"


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_align(rows: list[dict], path: Path) -> Path:
    plt = _pyplot()
    settings = list(dict.fromkeys(r["align"] for r in rows))
    groups: dict[tuple, dict[str, list[dict]]] = {}
    for r in rows:
        group = groups.setdefault((r["scene"], r["noise_deg"], r["noise_share"]), {a: [] for a in settings})
        group[r["align"]].append(r)
    labels = [f"{s}\n{d:g}°/{sh:.0%}" for s, d, sh in groups]
    fig, (gain, speed) = plt.subplots(1, 2, figsize=(max(8, 1.6 * len(labels) + 2), 4.2))
    x = range(len(labels))
    width = 0.8 / len(settings)
    for j, align in enumerate(settings):
        offset = (j - (len(settings) - 1) / 2) * width
        mean = [sum(r["gain_db"] for r in g[align]) / max(1, len(g[align])) for g in groups.values()]
        secs = [sum(r["seconds"] for r in g[align]) / max(1, len(g[align])) for g in groups.values()]
        name = {"on": "pose refinement on", "off": "off"}.get(align, f"on, {align[len('early'):]} early refusal")
        gain.bar([i + offset for i in x], mean, width=width, label=name)
        speed.bar([i + offset for i in x], secs, width=width, label=name)
    gain.axhline(0, color="k", lw=0.8)
    gain.set_ylabel("mean PSNR gain over the render (dB)")
    speed.set_ylabel("seconds per view")
    for ax in (gain, speed):
        ax.set_xticks(list(x), labels, fontsize=8)
        ax.legend(fontsize=8)
    fig.suptitle(_caption(rows, "neighbour pose refinement"), fontsize=8)
    return save_figure(fig, path)


def _plot_by_scene(rows: list[dict], key: str, right: tuple, path: Path, *, title: str, tick_size: int,
                   legend_title: str | None = None) -> Path:
    """Per scene, one bar per setting (``rows[...][key]``): the mean gain on the left, ``right``'s
    ``(ylabel, value of a scene's rows)`` on the right."""
    plt = _pyplot()
    specs = list(dict.fromkeys(r[key] for r in rows))
    scenes = list(dict.fromkeys(r["scene"] for r in rows))
    fig, axes = plt.subplots(1, 2, figsize=(max(9, 1.2 * len(scenes) * len(specs) / 3 + 4), 4.4))
    panels = (("mean PSNR gain over the render (dB)", lambda mine: sum(r["gain_db"] for r in mine) / max(1, len(mine))),
              right)
    width = 0.8 / max(1, len(specs))
    for k, spec in enumerate(specs):
        xs = [i - 0.4 + width * (k + 0.5) for i in range(len(scenes))]
        for ax, (_, value) in zip(axes, panels):
            ax.bar(xs, [value([r for r in rows if r[key] == spec and r["scene"] == s]) for s in scenes],
                   width=width, label=spec)
    for ax, (label, _) in zip(axes, panels):
        ax.axhline(0, color="k", lw=0.8)
        ax.set_ylabel(label)
        ax.set_xticks(range(len(scenes)), [s.replace("/", "\n", 1) for s in scenes], fontsize=tick_size)
    axes[0].legend(fontsize=7, title=legend_title, title_fontsize=7)
    fig.suptitle(title, fontsize=8)
    return save_figure(fig, path)


def plot_colour(rows: list[dict], path: Path) -> Path:
    lead = f"{rows[0].get('checkpoint', '')}, " if rows else ", "
    return _plot_by_scene(rows, "config", ("views with a better FLIP", lambda mine: sum(r["flip_change"] < 0
                                                                                        for r in mine)),
                          path, title=_caption(rows, "colour matching to the neighbours", lead), tick_size=7)


def plot_trust(rows: list[dict], path: Path) -> Path:
    worst = ("worst view's gain (dB)", lambda mine: min(r["gain_db"] for r in mine) if mine else 0)
    return _plot_by_scene(rows, "setting", worst, path, title=_caption(rows, "trusting the neighbours by their "
                                                                             "agreement"),
                          tick_size=6, legend_title="full_share")


def report_colour(rows: list[dict]) -> None:
    for s in summary(rows, "colour"):
        print(f"{s['config']:>36}: gain {s['gain_db']:+.3f} dB, FLIP better on {s['views_flip_better']}/{s['views']} "
              f"views, worst view {s['worst_view_gain_db']:+.3f} dB")


def report_trust(rows: list[dict]) -> None:
    for s in summary(rows, "trust"):
        print(f"{s['setting']:>5}: gain {s['gain_db']:+.3f} dB (worst scene {s['worst_scene_gain_db']:+.3f}), "
              f"FLIP better on {s['views_flip_better']}/{s['views']} views, "
              f"worst view {s['worst_view_gain_db']:+.3f} dB")


class Stage(NamedTuple):
    settings: str
    """The default ``--settings``."""
    parse: object
    """``--settings`` text -> what the measurement iterates."""
    column: str
    """The rows' column naming the setting."""
    output: str
    """The default ``--output`` under ``bench/results``."""
    measure: object
    """``(args, scene, model, checkpoint, head) -> rows`` of one scene folder."""
    plot: object
    report: object = None
    """Prints a summary of the rows (or nothing)."""


STAGES = {
    "align": Stage("off,on", align_settings, "align", "align_cost", _align_rows, plot_align),
    "colour": Stage(COLOUR_SETTINGS, colour_settings, "config", "colour", _colour_rows, plot_colour, report_colour),
    "trust": Stage(TRUST_SETTINGS, trust_settings, "setting", "trust", _trust_rows, plot_trust, report_trust),
}


def main(argv=None) -> int:
    args = parse_args(argv)
    stage = STAGES[args.stage]
    rows = measure(args)
    write_outputs(args.output, rows, stage.plot)
    if stage.report is not None:
        stage.report(rows)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
