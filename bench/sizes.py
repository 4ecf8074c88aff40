"""Seconds and peak memory per view at the sizes users have, per step, next to the gain.

    python -m bench.sizes --scene runs/speed/dtu_scan37_fine \\
        [--sizes 504x378,1008x756,1920x1080,2016x1512] [--settings defaults,no-align,no-colour,no-trust]
        [--views 3] [--cli/--no-cli] [--before REV] [--rounds 1] [--output bench/results/sizes/sizes]

The scene (a scene folder with renders and depths, e.g. a ``make-pairs`` output) is brought to
each size once (``runs/sizes/``): centre-cropped to the size's aspect ratio, photos and renders
resampled with antialiased bicubic, depths with nearest (no depth between a surface and its
background), intrinsics cropped and scaled. Then, per size and setting, a fresh child process
loads the scene and the shipped checkpoint as the CLI does and enhances the first ``--views``
test views one after another. Per view it records the wall-clock seconds of each step the
enhancer reports (``EnhanceResult.timings``: checks, select, probe, align, encode, model,
agreement, colour, trust) and the gain (PSNR of the enhanced view minus the render's, against the photo). Per child:
the peak RSS (``VmHWM``, imports and model included) and the seconds spent loading (imports,
scene, checkpoint). With ``--cli`` the one-view command as a user runs it (``roguenerf enhance``,
defaults) is timed too: its wall-clock beside the view time it prints.

Settings: ``defaults``, ``no-align``, ``no-colour``, ``no-trust``, ``neighbours=N``, ``measured`` (the
neighbour rule that measures its candidates, ``NeighbourRule(measured=True)``), ``tile=PX`` (the
tile size, ``EnhanceOptions.tile``), ``early=SHARE`` (the pose fits'
``AlignConfig.early_refusal``; ``early=0`` fits every level), ``cache=MiB``
(the neighbour cache's budget, ``SceneEnhancer(cache_bytes=)``), ``judged`` (an untimed child
first enhances the views keeping its pose judgements in a file, as an earlier command would; the
timed child's enhancer reads that file: what a later one-view command on the scene runs; needs a
tree with ``SceneEnhancer(settled_file=)``); several switches joined by ``+``
(``no-align+no-trust``). The one-view command (``--cli``) starts without earlier judgements.

With ``--before REV`` every setting also runs with the code of an older revision (a temporary
git worktree, this checkout's interpreter), labelled ``SETTING@REV``; the two trees' children
alternate, ``--rounds`` times each, so a busy machine slows both alike (speeds compared side by
side, never against an old file). Per setting, the first view of each child is its own column.

Writes ``OUTPUT.csv`` (one row per view; date, machine, commit), ``OUTPUT.json`` (per size and
setting: median seconds per view without the first, the first view, peak memory, mean gain) and
``OUTPUT.png``. Run it on a quiet machine: every figure is a wall-clock time.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import statistics
import subprocess
import sys
import time
from pathlib import Path

from bench.common import RESULTS, beside, older_tree, save_figure, stamp, write_csv, write_json

ROOT = Path(__file__).resolve().parent.parent
SIZES = "504x378,1008x756,1920x1080,2016x1512"
SETTINGS = "defaults,no-align,no-colour,no-trust"
STEPS = ("checks", "select", "probe", "align", "encode", "model", "agreement", "colour", "trust")

CHILD = r"""
import json, sys, time
t0 = time.perf_counter()
sys.path.insert(0, {repo!r})
from roguenerf import runtime
runtime.configure()
import torch
from roguenerf.checkpoint import default_checkpoint_path, load_checkpoint
from roguenerf.data.readers import load_scene
from roguenerf.enhance import EnhanceOptions
from roguenerf.enhance.align import AlignConfig
from roguenerf.inference import SceneEnhancer
from roguenerf.metrics import psnr

scene = load_scene({scene!r})
model, _ = load_checkpoint(default_checkpoint_path())
options = EnhanceOptions.from_flags(**{flags!r})
if {measured!r}:
    from roguenerf.enhance import NeighbourRule
    options = options.with_(neighbours=NeighbourRule(measured=True))
enhancer = SceneEnhancer(scene, model, options=options, **{extra!r})
loaded = time.perf_counter() - t0
rows = []
for view in scene.indices("test")[:{views}]:
    frame = scene.frames[view]
    t = time.perf_counter()
    render, depth, photo = scene.render(view), scene.depth(view), scene.photo(view)
    io = time.perf_counter() - t
    result = enhancer.enhance(render, depth, frame.K, frame.world_from_cam)
    rows.append({{"view": frame.name, "seconds": result.seconds, "io": io, **result.timings,
                  "neighbours": len(result.neighbours), "candidates": len(result.candidates or []),
                  "render_psnr": float(psnr(render, photo)),
                  "enhanced_psnr": float(psnr(result.image, photo))}})
peak = [int(line.split()[1]) for line in open("/proc/self/status") if line.startswith("VmHWM:")][0]
print(json.dumps({{"rows": rows, "peak_mb": peak / 1024, "load_s": loaded, "wall_s": time.perf_counter() - t0}}))
"""


def parse_size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(x) for x in text.lower().split("x"))
    except ValueError:
        raise SystemExit(f"--sizes: expected WIDTHxHEIGHT, got {text!r}") from None
    if w < 32 or h < 32:
        raise SystemExit(f"--sizes: {text} is too small (32 px at least)")
    return w, h


def parse_setting(text: str) -> tuple[dict, dict]:
    """A setting's ``EnhanceOptions.from_flags`` arguments, and the ``SceneEnhancer``'s others."""
    flags: dict = {}
    extra: dict = {}
    for part in text.split("+"):
        if part == "defaults":
            continue
        if part in ("no-align", "no-colour", "no-trust"):
            flags[part[3:]] = False
        elif part.startswith("neighbours="):
            flags["neighbours"] = int(part.split("=", 1)[1])
        elif part.startswith("tile="):
            flags["tile"] = int(part.split("=", 1)[1])
        elif part.startswith("early="):
            from roguenerf.enhance.align import AlignConfig

            flags["align"] = AlignConfig(early_refusal=float(part.split("=", 1)[1]))
        elif part.startswith("cache="):
            extra["cache_bytes"] = int(float(part.split("=", 1)[1]) * 2**20)
        elif part == "judged":
            extra["judged"] = True
        elif part == "measured":
            extra["measured"] = True
        else:
            raise SystemExit(f"--settings: unknown switch {part!r} (defaults, no-align, no-colour, no-trust, "
                             "neighbours=N, measured, tile=PX, cache=MiB, early=SHARE, judged, joined by +)")
    return flags, extra


def sized_scene(scene_dir: Path, size: tuple[int, int], out: Path) -> Path:
    """``scene_dir`` centre-cropped to ``size``'s aspect ratio and resampled to it, written once."""
    import torch
    import torch.nn.functional as F

    from roguenerf.data.readers import load_scene
    from roguenerf.data.writers import write_scene_folder
    from roguenerf.geometry import scale_intrinsics

    if (out / "transforms.json").is_file():
        return out
    scene = load_scene(scene_dir)
    w, h = size
    f0 = scene.frames[0]
    src_w, src_h = f0.width, f0.height
    if src_w * h > w * src_h:  # wider than wanted: crop the width
        cw, ch = round(src_h * w / h), src_h
    else:
        cw, ch = src_w, round(src_w * h / w)
    x0, y0 = (src_w - cw) // 2, (src_h - ch) // 2

    def resample(x, mode):
        x = x[None, :, y0:y0 + ch, x0:x0 + cw]
        if mode == "nearest":
            return F.interpolate(x, size=(h, w), mode="nearest")[0]
        return F.interpolate(x, size=(h, w), mode="bicubic", antialias=True, align_corners=False)[0].clamp(0, 1)

    Ks = []
    for f in scene.frames:
        K = f.K.clone().to(torch.float64)
        K[0, 2] -= x0  # the crop moves the principal point; edges stay at 0 and W
        K[1, 2] -= y0
        Ks.append(scale_intrinsics(K, w / cw, h / ch).float())
    write_scene_folder(out, names=[f.name for f in scene.frames],
                       photos=torch.stack([resample(scene.photo(i), "bicubic") for i in range(len(scene))]),
                       renders=torch.stack([resample(scene.render(i), "bicubic") for i in range(len(scene))]),
                       depths=torch.stack([resample(scene.depth(i), "nearest") for i in range(len(scene))]),
                       world_from_cam=scene.poses(), K=torch.stack(Ks), splits=[f.split for f in scene.frames])
    return out


def run_child(scene: Path, setting: tuple[dict, dict], views: int, repo: Path = ROOT) -> dict:
    """One fresh process enhancing ``views`` test views of ``scene`` with the code of ``repo``;
    with ``judged``, after an untimed one that judged their neighbours' poses into a file."""
    flags, extra = setting
    if extra.get("judged"):
        import tempfile

        with tempfile.TemporaryDirectory() as tmp:
            extra = {k: v for k, v in extra.items() if k != "judged"} | {"settled_file": f"{tmp}/settled.json"}
            run_child(scene, (flags, extra), views, repo)  # the earlier process
            return run_child(scene, (flags, extra), views, repo)
    measured = bool(extra.get("measured"))
    extra = {k: v for k, v in extra.items() if k != "measured"}
    code = CHILD.format(repo=str(repo), scene=str(scene), flags=flags, extra=extra, views=views, measured=measured)
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    if proc.returncode != 0:
        raise SystemExit(f"the child failed on {scene}:\n{proc.stderr[-3000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def run_cli(scene: Path, view: str, tmp: Path) -> dict:
    """The one-view command as a user runs it: its wall-clock and the view time it prints."""
    import os
    import tempfile

    out = tmp / "cli.png"
    with tempfile.TemporaryDirectory() as judgements:  # a first command on the scene: no earlier judgements
        t = time.perf_counter()
        proc = subprocess.run([sys.executable, "-m", "roguecli", "enhance", str(scene), "--view", view,
                               "--output", str(out)], capture_output=True, text=True, cwd=ROOT,
                              env={**os.environ, "ROGUENERF_SETTLED_CACHE": judgements})
        wall = time.perf_counter() - t
    if proc.returncode != 0:
        raise SystemExit(f"roguenerf enhance failed on {scene}:\n{proc.stderr[-3000:]}")
    said = [line for line in proc.stderr.splitlines() if line.startswith("enhanced ")]
    view_s = float(said[-1].split(" in ")[1].split(" s")[0]) if said else float("nan")
    return {"cli_wall_s": round(wall, 3), "cli_view_s": round(view_s, 3)}


def summarise(rows: list[dict]) -> list[dict]:
    out = []
    for key in dict.fromkeys((r["size"], r["setting"]) for r in rows):
        mine = [r for r in rows if (r["size"], r["setting"]) == key]
        firsts = [r for r in mine if r["first"]]  # each child's first view
        later = [r for r in mine if not r["first"]] or mine
        item = {"size": key[0], "setting": key[1], "views": len(mine), "children": len(firsts),
                "seconds_per_view": round(statistics.median(r["seconds"] for r in later), 3),
                "first_view_s": round(statistics.median(r["seconds"] for r in firsts), 3),
                "peak_mb": round(statistics.median(r["peak_mb"] for r in firsts), 1),
                "load_s": round(statistics.median(r["load_s"] for r in firsts), 3),
                "gain_db": round(statistics.fmean(r["enhanced_psnr"] - r["render_psnr"] for r in mine), 3),
                "worst_view_gain_db": round(min(r["enhanced_psnr"] - r["render_psnr"] for r in mine), 3)}
        for step in STEPS:
            item[f"{step}_s"] = round(statistics.median(r.get(step, 0.0) for r in later), 3)
        for k in ("cli_wall_s", "cli_view_s"):
            if k in mine[0]:
                item[k] = mine[0][k]
        out.append(item)
    return out


def plot(summary: list[dict], path: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    sizes = list(dict.fromkeys(s["size"] for s in summary))
    settings = list(dict.fromkeys(s["setting"] for s in summary))
    fig, (ax, bx) = plt.subplots(1, 2, figsize=(12, 4.5))
    for setting in settings:
        mine = {s["size"]: s for s in summary if s["setting"] == setting}
        xs = [i for i, size in enumerate(sizes) if size in mine]
        ax.plot(xs, [mine[sizes[i]]["seconds_per_view"] for i in xs], "o-",
                label=f"{setting} (gain {statistics.fmean(mine[sizes[i]]['gain_db'] for i in xs):+.2f} dB)")
    ax.set_xticks(range(len(sizes)), sizes)
    ax.set_ylabel("seconds per view (median, after the first)")
    ax.set_title("per view, by setting")
    ax.legend(fontsize=8)
    defaults = [next((s for s in summary if s["size"] == size and s["setting"] == settings[0]), None) for size in sizes]
    bottom = [0.0] * len(sizes)
    for step in STEPS:
        heights = [d[f"{step}_s"] if d else 0.0 for d in defaults]
        bx.bar(range(len(sizes)), heights, bottom=bottom, label=step)
        bottom = [b + h for b, h in zip(bottom, heights, strict=True)]
    for i, d in enumerate(defaults):
        if d:
            bx.text(i, bottom[i], f"{d['peak_mb'] / 1024:.2f} GB", ha="center", va="bottom", fontsize=8)
    bx.set_xticks(range(len(sizes)), sizes)
    bx.set_ylabel("seconds (median per view); peak memory on top")
    bx.set_title(f"{settings[0]}: per step")
    bx.legend(fontsize=8)
    first = summary[0]
    fig.suptitle(f"bench.sizes  {first.get('date', '')}  {first.get('machine', '')}  {first.get('commit', '')}",
                 fontsize=8)
    return save_figure(fig, path)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scene", type=Path, required=True, help="Scene folder with renders and depths.")
    ap.add_argument("--sizes", default=SIZES, help=f"WIDTHxHEIGHT, comma-separated (default {SIZES}).")
    ap.add_argument("--settings", default=SETTINGS, help=f"Comma-separated (default {SETTINGS}).")
    ap.add_argument("--views", type=int, default=3, help="Test views per size and setting (default 3).")
    ap.add_argument("--cli", action=argparse.BooleanOptionalAction, default=True,
                    help="Also time the one-view command (roguenerf enhance) per size.")
    ap.add_argument("--work", type=Path, default=ROOT / "runs" / "sizes", help="Where the resized scenes go.")
    ap.add_argument("--before", default=None,
                    help="An older revision to run beside this checkout (a temporary git worktree): every "
                         "setting runs in both trees, alternated, the older's labelled SETTING@REV.")
    ap.add_argument("--rounds", type=int, default=1,
                    help="Children per size, setting and tree, alternated between the trees (default 1).")
    ap.add_argument("--output", type=Path, default=RESULTS / "sizes" / "sizes")
    args = ap.parse_args(argv)
    if not (args.scene / "transforms.json").is_file():
        raise SystemExit(f"--scene: {args.scene} is not a scene folder (no transforms.json)")
    if args.views < 1:
        raise SystemExit(f"--views: expected 1 or more, got {args.views}")
    if args.rounds < 1:
        raise SystemExit(f"--rounds: expected 1 or more, got {args.rounds}")
    sizes = [parse_size(s) for s in args.sizes.split(",")]
    settings = {s: parse_setting(s) for s in args.settings.split(",")}
    with contextlib.ExitStack() as stack:
        trees = [("", ROOT)]
        if args.before:
            old, rev = stack.enter_context(older_tree(args.before))
            trees.insert(0, (f"@{rev}", old))
        rows = measure(args, sizes, settings, trees)
    summary = summarise(rows)
    for s in summary:
        s.update({k: rows[0][k] for k in ("date", "machine", "commit")})
    csv_path = write_csv(beside(args.output, ".csv"), rows)
    command = " ".join(["python -m bench.sizes", *(argv or sys.argv[1:])])
    json_path = write_json(beside(args.output, ".json"),
                           {"scene": str(args.scene), "command": command, "summary": summary})
    png_path = plot(summary, beside(args.output, ".png"))
    print(f"wrote {csv_path}, {json_path} and {png_path}")
    return 0


def measure(args, sizes: list[tuple[int, int]], settings: dict, trees: list[tuple[str, Path]]) -> list[dict]:
    """Every size, setting, round and tree (alternated): a row per view."""
    rows = []
    for w, h in sizes:
        folder = sized_scene(args.scene, (w, h), args.work / f"{args.scene.resolve().name}_{w}x{h}")
        cli = {}
        if args.cli:
            from roguenerf.data.readers import load_scene

            sized = load_scene(folder)
            view = sized.frames[sized.indices("test")[0]].name
            cli = run_cli(folder, view, args.work)
        for setting, parsed in settings.items():
            for round_ in range(args.rounds):
                for tag, tree in trees:
                    label = setting + tag
                    child = run_child(folder, parsed, args.views, tree)
                    for k, r in enumerate(child["rows"]):
                        row = {**stamp(), "scene": args.scene.resolve().name, "size": f"{w}x{h}", "setting": label,
                               "round": round_, "first": k == 0, **r, "peak_mb": child["peak_mb"],
                               "load_s": child["load_s"], "child_wall_s": child["wall_s"]}
                        if k == 0 and round_ == 0 and setting == next(iter(settings)) and not tag:
                            row.update(cli)
                        rows.append(row)
                    last = summarise([r for r in rows if r["size"] == f"{w}x{h}" and r["setting"] == label])[0]
                    print(f"{w}x{h} {label}: {last['seconds_per_view']:.2f} s/view (first {last['first_view_s']:.2f}), "
                          f"peak {last['peak_mb']:.0f} MB, gain {last['gain_db']:+.2f} dB", flush=True)
    return rows


if __name__ == "__main__":
    sys.exit(main())
