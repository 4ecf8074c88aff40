"""Camera-path bench: a smooth path through a real scene, rendered by its fitted radiance field,
enhanced frame by frame; flicker (render vs enhanced vs photos) and per-frame PSNR gain.

Data: the finished coarse fit of ``data/real/cup`` made by ``roguenerf make-pairs`` (its scene
folder and ``.fit/`` state, default ``~/.cache/roguenerf/pairs/cup/coarse``). The scene is
downscaled by ``--factor`` (photos, renders, depths: 2x2 means; intrinsics scaled) so the
bench stays cheap on a CPU. The path goes through ``--keys`` held-out views of the scene, sorted
by azimuth around the object, with ``--steps`` frames per segment: the frames at the key views
have photos (their PSNR gain is a novel-view figure), the frames between them were taken from no
photo. The field (``roguefit.GridField``) renders each frame's RGB and z-depth at the scene's
downscaled size. Everything is cached in ``--work``: a second run resumes.

    nice -n 15 .venv/bin/python -m bench.paths            # 5 keys x 15 steps = 61 frames
    nice -n 15 .venv/bin/python -m bench.paths --quick    # 3 keys x 4 steps = 9 frames

``--fit`` takes any grid (``coarse``, ``fine``), hash (``--preset hash``) or splat (``--preset
splat``) make-pairs output; a field's frames are rendered within the fitter's own ray bounds (those
of the photo set's view nearest the camera), splats as the fitter renders its views. A field
whose novel views are floaters fails enhance_path's path check whatever the path; ``--force``
goes on and keeps the warning in the JSON:

    python -m bench.paths --fit runs/kinds/pairs/ollie/hash_s2_400steps_1024rays_48samples --factor 1 --force

Writes ``bench/results/paths[_quick].csv`` (one row per frame: flicker of the pair ending there,
PSNR where a photo exists), ``.json`` (means, the stamp) and ``.png`` (per-frame flicker, render vs
enhanced, and the per-frame gain), plus the MP4s in the work folder.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import torch
import torch.nn.functional as F

from bench.common import RESULTS, stamp, write_json, write_outputs

DEFAULT_FIT = Path.home() / ".cache" / "roguenerf" / "pairs" / "cup" / "coarse"


def downscale_scene(scene, out: Path, factor: int):
    """The scene at 1/factor size (2x2 means; depth: mean of the known values), written once."""
    from roguenerf.data.readers import load_scene
    from roguenerf.data.writers import write_scene_folder
    from roguenerf.geometry import known_depth_mask, scale_intrinsics

    if (out / "transforms.json").is_file():
        return load_scene(out)
    photos, renders, depths, Ks = [], [], [], []
    for i, f in enumerate(scene.frames):
        photos.append(F.avg_pool2d(scene.photo(i)[None], factor)[0])
        renders.append(F.avg_pool2d(scene.render(i)[None], factor)[0])
        d = scene.depth(i)[None]
        known = known_depth_mask(d).float()
        total = F.avg_pool2d(torch.where(known > 0, d, 0.0), factor)
        weight = F.avg_pool2d(known, factor)
        depths.append(torch.where(weight > 0, total / weight.clamp_min(1e-6), 0.0)[0])
        Ks.append(scale_intrinsics(f.K, 1 / factor, 1 / factor))
    write_scene_folder(out, names=[f.name for f in scene.frames], photos=torch.stack(photos).clamp(0, 1),
                       renders=torch.stack(renders).clamp(0, 1), depths=torch.stack(depths),
                       world_from_cam=scene.poses(), K=torch.stack(Ks), splits=[f.split for f in scene.frames])
    return load_scene(out)


def load_field(fit_dir: Path):
    """The fitted field of a make-pairs output (``.fit/state.safetensors`` + ``fit.json``): a
    GridField (``coarse``, ``fine``) or a HashField (``--preset hash``)."""
    from safetensors.torch import load_file

    from roguefit.fit import FitConfig
    from roguefit.registry import FITTERS

    meta = json.loads((fit_dir / ".fit" / "state.json").read_text())
    report = json.loads((fit_dir / "fit.json").read_text())
    tensors = load_file(str(fit_dir / ".fit" / "state.safetensors"))
    model = {k[6:]: v for k, v in tensors.items() if k.startswith("model.")}
    kind = meta["config"].get("kind", "grid")
    if kind not in ("grid", "hash"):
        raise SystemExit(f"--fit {fit_dir}: a {kind!r} fit has no field to render a path with here")
    config = FitConfig(**meta["config"])
    field = FITTERS[config.kind].new_field(config, torch.tensor(report["centre"]), float(report["radius"]),
                                           int(meta["resolution"]))
    if config.kind == "grid":
        field.use_mlp = int(meta["level"]) > 0
    field.occupancy = model["occupancy"].to(torch.bool)
    field.load_state_dict(model)
    return field.eval(), config.samples


def ray_bounds(fit_dir: Path, scene):
    """``bounds(pose) -> (near, far)`` for a path camera. As the fitter's where its photo set
    has them: the near x 0.9 and far x 1.2 of the photo set's view nearest the camera (a field
    whose floaters reach the cameras, as ollie's hash fit, piles them up at its near bound, so
    rendered from nearer its frames would not be the field's renders). Else one pair for every
    camera from the scene's rendered depth, generously widened."""
    from roguenerf.geometry import known_depth_mask

    report = json.loads((fit_dir / "fit.json").read_text())
    photos = Path(report.get("photos") or "")
    if report.get("photos") and (photos / "transforms.json").is_file():
        frames = [f for f in json.loads((photos / "transforms.json").read_text())["frames"]
                  if f.get("near") is not None and f.get("far") is not None]
        if frames:
            centres = torch.tensor([[row[3] for row in f["transform_matrix"][:3]] for f in frames], dtype=torch.float64)
            near = [0.9 * float(f["near"]) for f in frames]
            far = [1.2 * float(f["far"]) for f in frames]

            def nearest(pose):
                k = int((centres - torch.as_tensor(pose, dtype=torch.float64)[:3, 3]).norm(dim=1).argmin())
                return near[k], far[k]

            return nearest
    known = [scene.depth(i)[known_depth_mask(scene.depth(i))] for i in scene.indices("train")]
    fixed = float(min(k.min() for k in known)) * 0.5, float(max(k.max() for k in known)) * 1.5
    return lambda pose: fixed


@torch.no_grad()
def render_frame(field, samples, K, pose, width, height, near, far, chunk=16384):
    from roguefit.fit import camera_rays

    vv, uu = torch.meshgrid(torch.arange(height), torch.arange(width), indexing="ij")
    vv, uu = vv.reshape(-1), uu.reshape(-1)
    rgb, depth = [], []
    for s in range(0, height * width, chunk):
        v, u = vv[s:s + chunk], uu[s:s + chunk]
        n = v.shape[0]
        origins, dirs = camera_rays(K.expand(n, 3, 3), pose.expand(n, 4, 4), v, u)
        out = field.render_fast(origins, dirs, torch.full((n,), near), torch.full((n,), far), samples)
        rgb.append(out["rgb"]), depth.append(out["depth"])
    rgb = torch.cat(rgb).reshape(height, width, 3).permute(2, 0, 1).clamp(0, 1)
    return rgb, torch.cat(depth).reshape(1, height, width).float()


def frame_renderer(fit_dir: Path, scene):
    """``render(K, pose, width, height) -> (rgb (3, H, W), z-depth (1, H, W))`` of a make-pairs
    output's fitted field, whatever its kind: a grid or hash field within the fitter's own ray
    bounds (:func:`ray_bounds`), splats (``--preset splat``: the ``point_cloud.ply`` the fit
    wrote) as the fitter renders its views (black background; depth unknown, 0, where the
    splats are not opaque enough)."""
    from roguefit.splats import PLY_FILE

    if (fit_dir / PLY_FILE).is_file():  # what a splat fit writes (SplatFitter.write_extras)
        from roguenerf.splats import read_ply
        from roguenerf.splats import render as render_splats

        gaussians = read_ply(fit_dir / PLY_FILE)

        def splats(K, pose, width, height):
            rgb, depth, _ = render_splats(gaussians, pose, K, height, width)
            return rgb.clamp(0, 1), depth.float()

        return splats
    field, samples = load_field(fit_dir)
    bounds = ray_bounds(fit_dir, scene)
    return lambda K, pose, width, height: render_frame(field, samples, K, pose, width, height, *bounds(pose))


def key_views(scene, count: int, split: str = "test") -> list[int]:
    """``count`` views of ``split`` ("test" or "all"), in order of azimuth around the cameras'
    centre: the contiguous run with the smallest largest gap."""
    test = scene.indices(split)
    centre = scene.poses()[:, :3, 3].mean(0)
    az = {i: math.atan2(float(scene.frames[i].world_from_cam[1, 3] - centre[1]),
                        float(scene.frames[i].world_from_cam[0, 3] - centre[0])) for i in test}
    ordered = sorted(test, key=az.get)
    best, best_gap = ordered[:count], float("inf")
    for s in range(len(ordered) - count + 1):
        run = ordered[s:s + count]
        gap = max(abs(az[b] - az[a]) for a, b in zip(run, run[1:]))
        if gap < best_gap:
            best, best_gap = run, gap
    return best


def field_frames(args):
    """Scene (downscaled make-pairs output) and the path frames rendered by its fitted field."""
    from roguenerf import load_scene
    from roguenerf.imageio import atomic_write, encode_npy, write_png
    from roguenerf.trajectory import smooth_path

    # Per scene and fit (the coarse fit's cache keeps its first name).
    work = args.work / args.fit.parent.name / (f"x{args.factor}" if args.fit.name == "coarse"
                                               else f"{args.fit.name}_x{args.factor}")
    scene = downscale_scene(load_scene(args.fit), work / "scene", args.factor)
    keys = key_views(scene, args.keys, "all" if args.photo_path else "test")
    poses = smooth_path(scene.poses(keys), args.steps)
    K = scene.frames[keys[0]].K
    width, height = scene.frames[keys[0]].width, scene.frames[keys[0]].height
    frames = work / (f"photo_frames_{args.keys}" if args.photo_path else f"frames_{args.keys}x{args.steps}")
    (frames / "rgb").mkdir(parents=True, exist_ok=True)
    (frames / "depth").mkdir(parents=True, exist_ok=True)
    render = frame_renderer(args.fit, scene)
    started = time.perf_counter()
    rendered = 0
    for t, pose in enumerate(poses):
        rgb_path, depth_path = frames / "rgb" / f"{t:05d}.png", frames / "depth" / f"{t:05d}.npy"
        if rgb_path.is_file() and depth_path.is_file():
            continue
        rgb, depth = render(K, pose, width, height)
        atomic_write(depth_path, encode_npy(depth[0].numpy()))
        write_png(rgb_path, rgb)
        rendered += 1
        print(f"rendered frame {t + 1}/{len(poses)}", flush=True)
    return (scene, frames, poses, K, width, height, time.perf_counter() - started, rendered,
            args.fit.parent.name)


def toy_frames(args):
    """An exact-geometry toy orbit: photos and depth exact, renders degraded per frame."""
    from roguenerf.data.degrade import Degradation
    from roguenerf.data.readers import load_scene
    from roguenerf.data.toy import make_toy_scene, make_toy_world, render_toy_view
    from roguenerf.imageio import atomic_write, encode_npy, write_png
    from roguenerf.trajectory import smooth_path

    work = args.work / "toy"
    height, width = 96, 128
    if (work / "scene" / "transforms.json").is_file():
        scene = load_scene(work / "scene")
    else:
        scene = make_toy_scene(work / "scene", seed=0, n_train=16, n_test=6, height=height, width=width,
                               degradation=Degradation(), kind="orbit")
    world = make_toy_world(0)
    keys = key_views(scene, args.keys, "all" if args.photo_path else "test")
    poses = smooth_path(scene.poses(keys), args.steps)
    K = scene.frames[keys[0]].K
    frames = work / f"frames_{args.keys}x{args.steps}"
    (frames / "rgb").mkdir(parents=True, exist_ok=True)
    (frames / "depth").mkdir(parents=True, exist_ok=True)
    started, rendered = time.perf_counter(), 0
    for t, pose in enumerate(poses):
        rgb_path, depth_path = frames / "rgb" / f"{t:05d}.png", frames / "depth" / f"{t:05d}.npy"
        if rgb_path.is_file() and depth_path.is_file():
            continue
        photo, z = render_toy_view(world, pose, K, height, width)
        render, depth = Degradation()(photo[None], z[None], torch.Generator().manual_seed(1000 + t), K=K)
        atomic_write(depth_path, encode_npy(depth[0, 0].numpy()))
        write_png(rgb_path, render[0].clamp(0, 1))
        rendered += 1
    return scene, frames, poses, K, width, height, time.perf_counter() - started, rendered, "toy"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--fit", type=Path, default=DEFAULT_FIT, help="make-pairs output with .fit/ state")
    parser.add_argument("--work", type=Path, default=Path.home() / ".cache" / "roguenerf" / "bench_paths")
    parser.add_argument("--factor", type=int, default=2, help="downscale of the scene and the path renders")
    parser.add_argument("--keys", type=int, default=5, help="held-out views the path goes through")
    parser.add_argument("--steps", type=int, default=15, help="frames per segment between key views")
    parser.add_argument("--checkpoint", type=Path, default=None, help="enhancer (default: the shipped one)")
    parser.add_argument("--quality", type=int, default=20, help="x264 CRF of the MP4s")
    parser.add_argument("--quick", action="store_true", help="3 keys x 4 steps (9 frames)")
    parser.add_argument("--align", choices=["on", "off"], default="on",
                        help="neighbour pose refinement (default on, as shipped)")
    parser.add_argument("--colour", default="on",
                        help="colour matching to the neighbour photos: on (default, as shipped), off, or a "
                             "setting FIELD=VALUE[:FIELD=VALUE] of ColourConfig (as bench.stage_settings "
                             "--stage colour --settings)")
    parser.add_argument("--trust", choices=["on", "off"], default="on",
                        help="keep only part of the enhancer's change where the neighbours mostly disagree "
                             "(roguenerf.enhance.trust; default on, as shipped)")
    parser.add_argument("--temporal", default="on",
                        help="keep neighbours from frame to frame and blend each frame's change with the last "
                             "frame's (roguenerf.enhance.temporal): on (default, as shipped), off, or a setting "
                             "FIELD=VALUE[:FIELD=VALUE] of TemporalConfig (e.g. weight=0:keep_within=4)")
    parser.add_argument("--force", action="store_true", help=(
        "enhance a path that enhance_path's check refuses (a field whose novel views are floaters fails it "
        "whatever the path): the problem is kept as a warning in the JSON"))
    parser.add_argument("--photo-path", action="store_true", help=(
        "a path made only of the scene's views (train and test, in azimuth order, --steps 1): every "
        "frame has a photo, so the photos' own flicker is measured too"))
    parser.add_argument("--toy", action="store_true", help=(
        "an exact-geometry toy orbit instead of the fitted field (renders: the photos through "
        "roguenerf's NeRF-like Degradation, drawn anew per frame)"))
    args = parser.parse_args()
    from bench.stage_settings import colour_config
    from roguenerf.errors import InputError

    colour = {"on": True, "off": False}.get(args.colour)
    if colour is None:
        try:
            colour = colour_config(args.colour)
        except (InputError, ValueError) as exc:  # a field ColourConfig has not, a value that is no number
            parser.error(f"--colour: expected on, off or FIELD=VALUE[:FIELD=VALUE], got {args.colour!r} ({exc})")
    temporal = {"on": True, "off": False}.get(args.temporal)
    if temporal is None:
        from roguenerf.enhance.temporal import TemporalConfig

        try:
            fields = dict(part.split("=", 1) for part in args.temporal.split(":"))
            kinds = {"keep_within": int, "model_every": int, "change_frames": int,
                     "reuse_poses": lambda v: {"1": True, "0": False}[v],
                     "both_ways": lambda v: {"1": True, "0": False}[v], "blend": str, "resample": str}
            temporal = TemporalConfig(**{k: kinds.get(k, float)(v) for k, v in fields.items()})
        except (InputError, ValueError, TypeError, KeyError) as exc:
            parser.error(f"--temporal: expected on, off or FIELD=VALUE[:FIELD=VALUE], got {args.temporal!r} ({exc})")
    colour_tag = {"on": "", "off": "_nocolour"}.get(
        args.colour, "_colour_" + args.colour.replace("=", "").replace(":", "_")) + (
        "_notrust" if args.trust == "off" else "") + {"on": "", "off": "_notemporal"}.get(
        args.temporal, "_temporal_" + args.temporal.replace("=", "").replace(":", "_"))
    if args.quick:
        args.keys, args.steps = 3, 4
    if args.photo_path:
        args.steps = 1

    import roguenerf.runtime
    from roguenerf import SceneEnhancer, load_checkpoint
    from roguenerf.checkpoint import default_checkpoint_path
    from roguenerf.enhance import EnhanceOptions
    from roguenerf.trajectory import CameraPath, enhance_path

    roguenerf.runtime.configure()
    tag = ("toy_" if args.toy else "") + ("quick" if args.quick else "full")
    if args.toy:
        scene, frames, poses, K, width, height, render_s, rendered, name = toy_frames(args)
    else:
        scene, frames, poses, K, width, height, render_s, rendered, name = field_frames(args)
    keys = key_views(scene, args.keys, "all" if args.photo_path else "test")
    checkpoint = args.checkpoint or default_checkpoint_path()
    model, _ = load_checkpoint(checkpoint)
    enhancer = SceneEnhancer(scene, model, options=EnhanceOptions.from_flags(
        align=args.align == "on", colour=colour, trust=args.trust == "on", temporal=temporal))
    camera_path = CameraPath(world_from_cam=poses, K=K.expand(len(poses), 3, 3).clone(), width=width,
                             height=height, fps=24.0)
    out = frames.parent / ("enhanced_" + frames.name + ("" if args.align == "on" else "_noalign") + colour_tag)
    result = enhance_path(scene, enhancer, camera_path, frames, out, quality=args.quality,
                          checkpoint_id=f"{checkpoint}:align={args.align}:colour={args.colour}:trust={args.trust}"
                                        f":temporal={args.temporal}",
                          progress=lambda d, n: print(f"enhanced {d}/{n}", flush=True), force=args.force)
    from roguenerf.geometry.euler import rotation_angle
    from roguenerf.video import read_video_info

    info = read_video_info(result.video)
    side = read_video_info(result.side_by_side)
    assert (info["frames"], info["width"], info["height"]) == (len(poses), width + width % 2, height + height % 2), info
    report = result.flicker
    base = stamp()
    rows = []
    # how far the camera turns from one frame to the next
    turns = [None] + [round(float(rotation_angle(a[:3, :3].double(), b[:3, :3].double())), 3)
                      for a, b in zip(poses, poses[1:])]
    pairs = {p["to"]: p for p in report["per_pair"]}
    for f in report["per_frame"]:
        pair = pairs.get(f["frame"], {})
        rows.append({**base, "scene": name, "size": f"{width}x{height}", "frame": f["frame"],
                     "view": f["view"] or "", "turn_deg": turns[f["frame"]], "render_flicker": pair.get("render"),
                     "enhanced_flicker": pair.get("enhanced"), "photo_flicker": pair.get("photo"),
                     "sharpened_flicker": pair.get("sharpened"), "detail_ratio": f.get("detail_ratio"),
                     "valid_fraction": pair.get("valid_fraction"), "render_psnr": f.get("render_psnr"),
                     "enhanced_psnr": f.get("enhanced_psnr"), "gain_db": f.get("gain_db")})
    fl, ps_ = report["flicker"], report["psnr"]
    summary = {**base, "command": " ".join(["python -m bench.paths", *sys.argv[1:]]),
               "scene": "toy (exact geometry, Degradation per frame)" if args.toy else str(args.fit),
               "size": f"{width}x{height}", "frames": len(poses), "key_views": [scene.frames[i].name for i in keys],
               "turn_deg": {"mean": round(sum(turns[1:]) / max(len(turns) - 1, 1), 3),
                            "max": max(turns[1:], default=0.0)},
               "checkpoint": str(checkpoint), "align": args.align, "colour": args.colour,
               "trust": args.trust, "temporal": args.temporal, "flicker": fl, "psnr": ps_,
               "flicker_ratio_ok": fl["ratio"] is not None and fl["ratio"] <= 1.05,
               "render_s": round(render_s, 1), "frames_rendered_now": rendered,
               "enhance_s": round(result.seconds, 1), "frames_enhanced_now": result.enhanced_now,
               "enhance_s_per_frame": (round(result.seconds / max(result.enhanced_now, 1), 3)
                                       if result.enhanced_now else None),
               "cached_views": result.cached_views, "warnings": list(result.warnings),
               "video": {"enhanced": info, "side_by_side": side},
               "video_path": str(result.video)}
    # The path's shape in the name from 2026-11-29 on (results before it: paths of 4 x 8 unless their
    # docs say otherwise), so a path with other --keys / --steps does not overwrite another's.
    variant = (("_toy" if args.toy else "")
               + (f"_{args.fit.parent.name}_{args.fit.name}" if not args.toy and args.fit != DEFAULT_FIT else "")
               + (f"_{args.keys}x{args.steps}" if not args.toy and args.fit != DEFAULT_FIT and not args.photo_path
                  else "")
               + ("_photos" if args.photo_path else "")
               + ("_noalign" if args.align == "off" else "") + colour_tag)
    stem = "paths" + variant + ("_quick" if args.quick else "")
    write_json(RESULTS / f"{stem}.json", summary)

    def plot(rows, path):
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, (ax, bx) = plt.subplots(2, 1, figsize=(9, 6), sharex=True)
        xs = [r["frame"] for r in rows if r["render_flicker"] is not None]
        ax.plot(xs, [r["render_flicker"] for r in rows if r["render_flicker"] is not None], label="render")
        ax.plot(xs, [r["enhanced_flicker"] for r in rows if r["render_flicker"] is not None], label="enhanced")
        photo = [(r["frame"], r["photo_flicker"]) for r in rows if r["photo_flicker"] is not None]
        if photo:
            ax.plot(*zip(*photo), label="photos", color="0.5", ls="--")
        ax.set_ylabel("flicker: MAE of frame t-1\nreprojected into t")
        ax.legend()
        ax.set_title(f"{name} path, {len(rows)} frames {width}x{height}: flicker "
                     f"render {fl['render']:.4f}, enhanced {fl['enhanced']:.4f} (x{fl['ratio']:.3f})", fontsize=9)
        gx = [r["frame"] for r in rows if r["gain_db"] is not None]
        bx.bar(gx, [r["gain_db"] for r in rows if r["gain_db"] is not None], width=0.8 if len(gx) > 10 else 1.5,
               color="tab:green")
        bx.axhline(0, color="k", lw=0.5)
        bx.set_ylabel("PSNR gain (dB)\nframes with photos")
        bx.set_xlabel("frame")
        fig.text(0.01, 0.005, f"{base['date']}  {base['machine'][:90]}  commit {base['commit']}", fontsize=6)
        fig.tight_layout(rect=(0, 0.02, 1, 1))
        fig.savefig(path, dpi=110)
        plt.close(fig)
        return path

    write_outputs(RESULTS / ("paths" + variant), rows, plot, quick=args.quick)
    print(json.dumps({k: summary[k] for k in ("frames", "flicker", "psnr", "enhance_s", "render_s")}, indent=1))
    print(f"{tag}: videos in {out}")


if __name__ == "__main__":
    main()
