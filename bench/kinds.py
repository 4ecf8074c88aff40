"""Leave one kind out (issue 35): the checkpoint on real scenes rendered by a kind of field it was
never pre-trained on.

For each held-out real scene of ``../shared/data/real`` (``--scenes``; never pre-train on them)
and the field kind ``--kind`` (a ``roguefit`` preset: ``hash``, ...):

1. the photo set, downscaled by ``--scale`` (Lanczos; intrinsics scaled) into the runs folder;
2. ``make-pairs --preset KIND`` on it (``--steps`` overrides the preset's budget): fitted once,
   cached and resumable in ``--runs`` (run the same command again after a stop);
3. the checkpoint evaluated on the held-out views, per view: zero-shot, and after
   ``finetune --minutes M`` for each M of ``--finetune`` (cached per budget in ``--runs``);
4. a pose-noise sweep, zero-shot: Gaussian noise on the training views' poses only (the
   neighbours'; renders, depths and photos untouched), ``deg/share`` pairs of ``--noise``
   (rotation RMS in degrees, translation RMS as a share of the cameras' spread,
   :func:`roguenerf.geometry.noise.perturb_poses`), one fixed draw per scene and level.

Writes ``OUTPUT.csv`` (one row per view and condition: PSNR, SSIM, FLIP of render and enhanced),
``OUTPUT.json`` (rows plus per-condition means) and ``OUTPUT.png`` (gain against fine-tuning
minutes and against pose noise, per scene), stamped with date, machine and commit.

    nice .venv/bin/python -m bench.kinds --kind hash --scenes can_clip,ollie --scale 2 --steps 400 \\
        --rays 1024 --samples 48 --finetune 1,3,10
    nice .venv/bin/python -m bench.kinds ... --quick    # tiny budgets (proves it runs)
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import json
import sys
from pathlib import Path

from bench.common import (
    REPO,
    RESULTS,
    SHARED_DATA,
    add_stage_switches,
    beside,
    caption_line,
    configure_runtime,
    save_figure,
    stamp,
    write_json,
    write_outputs,
)

NOISE_LEVELS = "0/0,0.1/0.01,0.25/0.02,0.5/0.05,1/0.1"
"""The issue's sweep: none, 0.1 deg / 1 %, 0.25 deg / 2 %, 0.5 deg / 5 %, 1 deg / 10 %."""


def _noise(text: str) -> list[tuple[float, float]]:
    out = []
    for part in text.split(","):
        if part.strip():
            deg, share = part.split("/")
            out.append((float(deg), float(share)))
    return out


def parse_args(argv=None):
    from roguefit.registry import PRESETS

    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--kind", required=True,
                   help=f"roguefit preset of the field that renders the scenes: {', '.join(PRESETS)}")
    p.add_argument("--scenes", type=lambda t: [x for x in t.split(",") if x], required=True,
                   help="comma-separated held-out scene names under --data")
    p.add_argument("--data", type=Path, default=SHARED_DATA / "real")
    p.add_argument("--scale", type=int, default=1, help="downscale the photos by this factor first")
    p.add_argument("--steps", type=int, default=None, help="fitting budget in steps (default: the preset's)")
    p.add_argument("--rays", type=int, default=None, help="rays per fitting step (default: the preset's)")
    p.add_argument("--samples", type=int, default=None, help="samples per ray (default: the preset's)")
    p.add_argument("--checkpoint", type=Path, default=None, help="default: the shipped checkpoint")
    p.add_argument("--finetune", type=lambda t: [float(x) for x in t.split(",") if x], default=[],
                   help="comma-separated fine-tuning budgets in minutes (e.g. 1,3,10; default none)")
    p.add_argument("--noise", type=_noise, default=_noise(NOISE_LEVELS),
                   help=f"pose-noise levels deg/share, comma-separated (default {NOISE_LEVELS}; '' for none)")
    p.add_argument("--neighbours", type=lambda t: [int(x) for x in t.split(",") if x], default=[],
                   help="zero-shot neighbour sweep: comma-separated counts (e.g. 2,3,4,5; default: the model's only)")
    add_stage_switches(p)
    p.add_argument("--finetune-depth-noise", type=float, default=0.0,
                   help="fine-tune with TrainConfig.depth_noise (log-depth error on half the target depths; "
                        "default 0, as shipped); cached apart")
    p.add_argument("--finetune-neighbour-renders", type=float, default=0.0,
                   help="fine-tune with TrainConfig.neighbour_renders (this share of the crops' target renders "
                        "drawn from the nearest training view's render; default 0, as shipped); cached apart")
    p.add_argument("--finetune-render-warp", type=float, default=0.0,
                   help="fine-tune with TrainConfig.render_warp (half the target renders and depths displaced by "
                        "up to this many pixels, so they look like novel views; default 0, as shipped); cached apart")
    p.add_argument("--max-views", type=int, default=None)
    p.add_argument("--runs", type=Path, default=REPO / "runs" / "kinds", help="cache of photo sets, fits, fine-tunes")
    p.add_argument("--output", type=Path, default=None, help="default: bench/results/kinds_KIND")
    p.add_argument("--quick", action="store_true", help="tiny budgets, 2 views")
    args = p.parse_args(argv)
    if args.kind not in PRESETS:
        p.error(f"--kind: expected one of {', '.join(PRESETS)}, got {args.kind!r}")
    if args.scale < 1:
        p.error(f"--scale: expected >= 1, got {args.scale}")
    for name in args.scenes:
        if not (args.data / name / "transforms.json").is_file():
            p.error(f"--scenes: {args.data / name} is not a photo set (no transforms.json)")
    if args.output is None:
        args.output = RESULTS / f"kinds_{args.kind}"
    if args.quick:
        args.steps = args.steps or 20
        args.finetune = [0.05] if args.finetune else []
        args.max_views = args.max_views or 2
    return args


# -- data ----------------------------------------------------------------------------------------


def downscaled_photo_set(src: Path, dst: Path, scale: int) -> Path:
    """``src`` (transforms.json + images) at 1/scale size in ``dst`` (made once; intrinsics scaled,
    pixel centres kept: the image covers the same extent)."""
    from PIL import Image

    from roguenerf.imageio import atomic_write

    if scale == 1:
        return src
    meta_path = dst / "transforms.json"
    if meta_path.is_file():
        return dst
    meta = json.loads((src / "transforms.json").read_text())
    w, h = int(meta["w"]), int(meta["h"])
    nw, nh = max(1, round(w / scale)), max(1, round(h / scale))
    sx, sy = nw / w, nh / h
    (dst / "images").mkdir(parents=True, exist_ok=True)
    for frame in meta["frames"]:
        name = Path(frame["file_path"]).name
        with Image.open(src / frame["file_path"]) as im:
            im.convert("RGB").resize((nw, nh), Image.LANCZOS).save(dst / "images" / (Path(name).stem + ".png"))
        frame["file_path"] = f"images/{Path(name).stem}.png"
        for key, s in (("fl_x", sx), ("cx", sx), ("fl_y", sy), ("cy", sy)):
            if key in frame:
                frame[key] = frame[key] * s
    meta.update(w=nw, h=nh, fl_x=meta["fl_x"] * sx, cx=meta["cx"] * sx, fl_y=meta["fl_y"] * sy, cy=meta["cy"] * sy)
    meta["downscaled"] = {"from": str(src), "scale": scale}
    atomic_write(meta_path, json.dumps(meta, indent=1).encode())  # last: marks the set complete
    return dst


def fit_pairs(photos: Path, out: Path, kind: str, steps: int | None, **overrides) -> dict:
    """``make-pairs --preset kind`` (resumable; a finished folder is left as it is), with bars."""
    from tqdm import tqdm

    from roguefit import PRESETS, make_pairs

    config = PRESETS[kind]
    if steps is not None:
        config = dataclasses.replace(config, steps=steps, minutes=None)
    config = dataclasses.replace(config, **{k: v for k, v in overrides.items() if v is not None})
    bar = tqdm(total=config.steps, desc=f"fitting {photos.name} ({kind})", unit="step", file=sys.stderr)

    def progress(p: dict) -> None:
        bar.set_postfix(psnr=f"{p['psnr']:.2f}", refresh=False)
        bar.update(p["step"] - bar.n)

    views = tqdm(desc=f"rendering {photos.name}", unit="view", file=sys.stderr)

    def render_progress(done: int, total: int) -> None:
        bar.close()
        views.total = total
        views.update(done - views.n)

    try:
        return make_pairs(photos, out, config, progress=progress, render_progress=render_progress)
    finally:
        bar.close()
        views.close()


def noisy_scene(scene, deg: float, share: float, seed: int):
    """``scene`` with the training views' poses perturbed (test views, pixels untouched)."""
    import torch

    from roguenerf.data.scene import Scene
    from roguenerf.geometry.noise import camera_spread, perturb_poses

    train = scene.indices("train")
    spread = camera_spread(scene.poses(train))
    poses = perturb_poses(scene.poses(train), deg, share * spread, torch.Generator().manual_seed(seed))
    frames = list(scene.frames)
    for k, i in enumerate(train):
        frames[i] = dataclasses.replace(frames[i], world_from_cam=poses[k])
    return Scene(scene.root, frames, meta=dict(scene.meta))


# -- measuring -------------------------------------------------------------------------------------


def view_rows(report: dict, **condition) -> list[dict]:
    rows = []
    for v in report["views"]:
        r, e = v["render"], v["enhanced"]
        rows.append({**condition, "view": v["name"],
                     "render_psnr": round(r["psnr"], 4), "enhanced_psnr": round(e["psnr"], 4),
                     "gain_db": round(e["psnr"] - r["psnr"], 4),
                     "render_ssim": round(r["ssim"], 5), "enhanced_ssim": round(e["ssim"], 5),
                     "render_flip": round(r["flip"], 5), "enhanced_flip": round(e["flip"], 5),
                     "flip_change": round(e["flip"] - r["flip"], 5), "seconds": round(v["seconds"], 2),
                     "aligned": (None if v.get("aligned") is None
                                 else round(sum(v["aligned"]) / max(1, len(v["aligned"])), 3)),
                     "colour_matched": v.get("colour_offset") is not None,
                     "agreement": v.get("agreement"), "trust_kept": v.get("trust"),
                     "neighbours_used": len(v.get("neighbours") or [])})
    return rows


def cached_rows(path: Path, measure) -> list[dict]:
    """Rows from ``path`` when a previous run measured them, else ``measure()`` saved there."""
    from roguenerf.imageio import atomic_write

    if path.is_file():
        return json.loads(path.read_text())
    rows = measure()
    atomic_write(path, json.dumps(rows).encode(), make_parents=True)
    return rows


def run(args) -> tuple[list[dict], list[dict]]:
    """Every scene's rows (per view and condition) and fit reports."""
    from roguenerf.checkpoint import default_checkpoint_path

    checkpoint = args.checkpoint or default_checkpoint_path()
    base = stamp()
    rows: list[dict] = []
    fits: list[dict] = []
    tag = (f"{args.kind}_s{args.scale}" + (f"_{args.steps}steps" if args.steps else "")
           + (f"_{args.rays}rays" if args.rays else "") + (f"_{args.samples}samples" if args.samples else "")
           + ("_quick" if args.quick else ""))
    for name in args.scenes:
        scene_rows, fit = measure_scene(args, name, checkpoint, base, tag)
        rows += scene_rows
        fits.append(fit)
    return rows, fits


FIELD_CONFIG = {"local_sigma": 8.0}
"""The colour matching of results cached as ``_colourfield`` (ColourConfig's defaults then)."""


def colour_cache_tag(config) -> str:
    """``_colourfield``, plus ``_FIELDVALUE`` for each field where ``config`` differs from the
    setting cached results without it were measured with (:data:`FIELD_CONFIG`)."""
    from roguenerf.enhance.colour import ColourConfig

    then = ColourConfig(**FIELD_CONFIG)
    return "_colourfield" + "".join(f"_{f}{getattr(config, f):g}" for f in ColourConfig.__dataclass_fields__
                                    if getattr(config, f) != getattr(then, f))


def near_cache_tag() -> str:
    """``_nearEXTRAxDEGREES`` while SceneEnhancer adds near neighbours beyond the model's count
    (roguenerf.inference.NEAR_EXTRA, NEAR_DEGREES): results before that are cached apart."""
    from roguenerf.enhance import NEAR_DEGREES, NEAR_EXTRA

    return f"_near{NEAR_EXTRA}x{NEAR_DEGREES:g}" if NEAR_EXTRA else ""


def trust_cache_tag(config) -> str:
    """``_trust`` plus each of ``config``'s fields as ``_FIELDVALUE``: results measured with trust
    on (roguenerf.enhance.trust) are cached apart from those before it, and per setting."""
    from roguenerf.enhance.trust import TrustConfig

    return "_trust" + "".join(f"_{f}{getattr(config, f):g}" for f in TrustConfig.__dataclass_fields__)


def measure_scene(args, name: str, checkpoint: Path, base: dict, tag: str) -> tuple[list[dict], dict]:
    """One held-out scene: fit (cached), zero-shot with each pose-noise level, fine-tunes (cached)."""
    from roguenerf.checkpoint import load_checkpoint
    from roguenerf.data.readers import load_scene
    from roguenerf.enhance import EnhanceOptions
    from roguenerf.enhance.colour import ColourConfig
    from roguenerf.enhance.trust import TrustConfig
    from roguenerf.training import TrainConfig, evaluate, finetune

    photos = downscaled_photo_set(args.data / name, args.runs / "photos" / f"{name}_s{args.scale}", args.scale)
    pairs = args.runs / "pairs" / name / tag
    report = fit_pairs(photos, pairs, args.kind, args.steps, rays=args.rays, samples=args.samples)
    fit = {"scene": name, "kind": args.kind, "steps": report["steps"], "fit_seconds": report["fit_seconds"],
           "render_seconds": report["render_seconds"], "train_psnr": report["train"]["psnr"],
           "test_psnr": (report["test"] or {}).get("psnr")}
    scene = load_scene(pairs)
    cache = args.runs / "results" / name / tag / checkpoint.stem
    model, _ = load_checkpoint(checkpoint)
    default_n = model.config.num_neighbours
    common = {**base, "scene": name, "kind": args.kind, "scale": args.scale, "checkpoint": checkpoint.name,
              "model_neighbours": default_n}
    rows: list[dict] = []
    align = args.align == "on"
    colour = args.colour == "on"
    trust = args.trust == "on"
    # Results cached before pose refinement existed had it off, before colour matching that off
    # ("_colour": the first, view-wide offset only, before its local field).
    suffix = (("_align" if align else "") + (colour_cache_tag(ColourConfig()) if colour else "")
              + (trust_cache_tag(TrustConfig()) if trust else "") + near_cache_tag())
    # the fine-tune's options, in the cache's names and the rows' stage
    tuning = [(args.finetune_depth_noise, "depth", "depth noise"), (args.finetune_render_warp, "warp", "render warp"),
              (args.finetune_neighbour_renders, "drawn", "neighbour renders")]
    plan = "".join(f"_{tag}{value:g}" for value, tag, _ in tuning if value)
    plan_label = "".join(f", {label} {value:g}" for value, _, label in tuning if value)

    def note(new: list[dict]) -> None:
        for x in new:  # rows cached before the neighbour sweep existed used the model's count
            x.setdefault("neighbours", default_n)
            x.setdefault("explicit_count", x["neighbours"] != default_n)  # rows cached before the near rule
            x.setdefault("model_neighbours", default_n)
            x.setdefault("aligned", None)
            x["align"] = align
            x["colour"] = colour
            x["trust"] = trust
        rows.extend(new)
        gain = sum(x["gain_db"] for x in new) / len(new)
        flip = sum(x["flip_change"] for x in new) / len(new)
        c = new[0]
        print(f"{name} {args.kind} {c['stage']} noise {c['noise_deg']:g}/{c['noise_share']:g} "
              f"{c.get('neighbours')} neighbours: "
              f"gain {gain:+.3f} dB, FLIP {flip:+.4f}, worst view {min(x['gain_db'] for x in new):+.3f} dB",
              flush=True)

    def zero_shot(k: int, deg: float, share: float, n: int | None = None) -> list[dict]:
        target = scene if deg == 0 and share == 0 else noisy_scene(scene, deg, share, seed=1000 + k)
        options = EnhanceOptions.from_flags(neighbours=n, align=align, colour=colour, trust=trust)
        return view_rows(evaluate(target, model, max_views=args.max_views, options=options), **common,
                         stage="zero-shot", minutes=0.0, noise_deg=deg, noise_share=share,
                         neighbours=default_n if n is None else n, explicit_count=n is not None)

    def tune(m: float) -> list[dict]:
        result = finetune(scene, args.runs / "finetune" / name / tag / checkpoint.stem / f"{m:g}min{plan}",
                          checkpoint=checkpoint,
                          config=TrainConfig(minutes=m, evaluate=False, depth_noise=args.finetune_depth_noise,
                                             render_warp=args.finetune_render_warp,
                                             neighbour_renders=args.finetune_neighbour_renders))
        tuned, _ = load_checkpoint(result.checkpoint)
        options = EnhanceOptions.from_flags(align=align, colour=colour, trust=trust)
        return view_rows(evaluate(scene, tuned, max_views=args.max_views, options=options), **common,
                         stage=f"finetune {m:g} min{plan_label}",
                         minutes=m, noise_deg=0.0, noise_share=0.0, neighbours=default_n, steps=result.steps)

    for k, (deg, share) in enumerate(args.noise or [(0.0, 0.0)]):
        note(cached_rows(cache / f"zero_shot_noise{deg:g}_{share:g}{suffix}.json",
                         functools.partial(zero_shot, k, deg, share)))
    near = EnhanceOptions().neighbours.counts(default_n)[1]  # a near extra: then n = default_n differs
    for n in args.neighbours:
        if n != default_n or near:
            note(cached_rows(cache / f"zero_shot_{n}neighbours{suffix}.json",
                             functools.partial(zero_shot, 0, 0.0, 0.0, n)))
    for minutes in sorted(args.finetune):
        note(cached_rows(cache / f"finetune_{minutes:g}min{plan}{suffix}.json", functools.partial(tune, minutes)))
    return rows, fit


def summary(rows: list[dict]) -> list[dict]:
    """Per scene and condition: mean gain, FLIP change, worst view, views with better FLIP."""
    groups: dict[tuple, list[dict]] = {}
    for r in rows:
        groups.setdefault((r["scene"], r["kind"], r["stage"], r["noise_deg"], r["noise_share"],
                           r.get("neighbours"), bool(r.get("explicit_count"))), []).append(r)
    out = []
    for (scene, kind, stage, deg, share, neighbours, explicit), rs in groups.items():
        n = len(rs)
        out.append({"scene": scene, "kind": kind, "stage": stage, "minutes": rs[0]["minutes"], "noise_deg": deg,
                    "noise_share": share, "neighbours": neighbours, "explicit_count": explicit,
                    "neighbours_used": round(sum(r.get("neighbours_used") or 0 for r in rs) / n, 2),
                    "model_neighbours": rs[0].get("model_neighbours"), "align": rs[0].get("align", False),
                    "views": n,
                    "render_psnr": round(sum(r["render_psnr"] for r in rs) / n, 4),
                    "gain_db": round(sum(r["gain_db"] for r in rs) / n, 4),
                    "worst_view_gain_db": min(r["gain_db"] for r in rs),
                    "render_flip": round(sum(r["render_flip"] for r in rs) / n, 5),
                    "flip_change": round(sum(r["flip_change"] for r in rs) / n, 5),
                    "views_flip_better": sum(r["flip_change"] < 0 for r in rs),
                    "aligned_share": (None if any(r.get("aligned") is None for r in rs)
                                      else round(sum(r["aligned"] for r in rs) / n, 3))})
    return out


def plot(rows: list[dict], path: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    means = summary(rows)
    fig, (left, middle, right) = plt.subplots(1, 3, figsize=(14, 4))
    for scene in dict.fromkeys(m["scene"] for m in means):
        mine = [m for m in means if m["scene"] == scene]
        # Fine-tunes and noise use the enhancer's default count (the model's, plus near views).
        own = [m for m in mine if m["neighbours"] == m["model_neighbours"] and not m["explicit_count"]]
        tune = sorted((m for m in own if m["noise_deg"] == 0 and m["noise_share"] == 0), key=lambda m: m["minutes"])
        line, = left.plot([m["minutes"] for m in tune], [m["gain_db"] for m in tune], "o-", label=scene)
        left.scatter([m["minutes"] for m in tune], [m["worst_view_gain_db"] for m in tune], marker="_",
                     color=line.get_color())
        sweep = sorted((m for m in own if m["stage"] == "zero-shot"), key=lambda m: (m["noise_deg"], m["noise_share"]))
        labels = [f"{m['noise_deg']:g}°/{m['noise_share']:.0%}" for m in sweep]
        middle.plot(range(len(sweep)), [m["gain_db"] for m in sweep], "o-", color=line.get_color(), label=scene)
        middle.set_xticks(range(len(sweep)), labels, fontsize=7)
        # Explicit counts; the default (which may add near views) at its mean count used.
        counted = sorted((m for m in mine if m["stage"] == "zero-shot" and m["noise_deg"] == 0
                          and m["noise_share"] == 0 and m["explicit_count"]), key=lambda m: m["neighbours"] or 0)
        right.plot([m["neighbours"] for m in counted], [m["gain_db"] for m in counted], "o-",
                   color=line.get_color(), label=scene)
        right.scatter([m["neighbours"] for m in counted], [m["worst_view_gain_db"] for m in counted], marker="_",
                      color=line.get_color())
        default = [m for m in own if m["stage"] == "zero-shot" and m["noise_deg"] == 0 and m["noise_share"] == 0]
        right.scatter([m["neighbours_used"] or m["neighbours"] for m in default], [m["gain_db"] for m in default],
                      marker="*", s=80, color=line.get_color())
    for ax in (left, middle, right):
        ax.axhline(0, color="grey", lw=0.8)
        ax.legend(fontsize=7)
        ax.set_ylabel("PSNR gain over renders, held-out views (dB)", fontsize=8)
    left.set_xlabel("fine-tuning minutes (0 = zero-shot); dashes: worst view", fontsize=8)
    middle.set_xlabel("zero-shot, pose noise on the training views\n"
                      "(rotation RMS / translation RMS, share of the spread)", fontsize=8)
    right.set_xlabel("zero-shot, neighbours per view (star: the default, at its mean count);\n"
                     "dashes: worst view", fontsize=8)
    caption_line(fig, rows, "{kind} fields, checkpoint {checkpoint}")
    return save_figure(fig, path)


def main(argv=None) -> int:
    args = parse_args(argv)
    configure_runtime()
    rows, fits = run(args)
    # --output is a stem: a dot in it (hash_ft0.6) is part of the name, not a suffix to replace.
    name = args.output.name
    for ext in (".csv", ".json", ".png"):
        name = name.removesuffix(ext)
    csv_path, _ = write_outputs(args.output.with_name(name), rows, plot, quick=args.quick)
    json_path = write_json(beside(csv_path, ".json"), {"command": " ".join(sys.argv), "fits": fits,
                                                           "means": summary(rows), "rows": rows})
    print(f"wrote {json_path}")
    for m in summary(rows):
        print(f"{m['scene']:<12} {m['stage']:<18} noise {m['noise_deg']:g}/{m['noise_share']:g} "
              f"n={m['neighbours']}: render "
              f"{m['render_psnr']:.2f} dB, gain {m['gain_db']:+.3f} dB (worst view {m['worst_view_gain_db']:+.3f}), "
              f"FLIP {m['render_flip']:.4f} {m['flip_change']:+.4f} "
              f"({m['views_flip_better']}/{m['views']} views better)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
