"""Enhancement commands: ``evaluate`` (metrics over a split) and ``enhance`` (one view to a PNG)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import typer

from roguecli.common import (
    CheckpointOpt,
    EnhanceFlags,
    exit_when_done,
    handle_errors,
    load_model,
    open_scene,
    progress_bar,
    takes_flags,
    warn_unusable,
)
from roguenerf.errors import InputError


@takes_flags
def evaluate(
    scene_dir: Annotated[Path, typer.Argument(help="Scene folder.")],
    checkpoint: CheckpointOpt = None,
    split: Annotated[str, typer.Option("--split", help="Views to evaluate: test, train or all.")] = "test",
    as_json: Annotated[bool, typer.Option("--json", help="Print one JSON object and nothing else.")] = False,
    *,
    flags: EnhanceFlags,
) -> None:
    """PSNR/SSIM/FLIP of renders and enhanced renders against the photos, per view and mean (FLIP: lower is better)."""
    from roguenerf.training import evaluate as run_evaluate

    with handle_errors():
        if split not in ("test", "train", "all"):
            raise InputError(f"--split: expected test, train or all, got {split!r}")
        scene = open_scene(scene_dir)
        model = load_model(checkpoint)
        with progress_bar(f"evaluating {split} views", "view") as progress:
            report = run_evaluate(scene, model, split=split, progress=progress,
                                  options=flags.options())
    if as_json:
        from roguenerf.imageio import finite_for_json

        typer.echo(json.dumps(finite_for_json(report)))
        return
    typer.echo(f"{'view':<24} {'render PSNR':>12} {'SSIM':>7} {'FLIP':>7} "
               f"{'enhanced PSNR':>14} {'SSIM':>7} {'FLIP':>7} {'kept':>5}")

    def row(name: str, r: dict, e: dict, kept: float | None = None) -> str:
        # kept: the share of the enhancer's change kept (trust; "-" where none was measured)
        return (f"{name:<24} {r['psnr']:>12.2f} {r['ssim']:>7.4f} {r['flip']:>7.4f} "
                f"{e['psnr']:>14.2f} {e['ssim']:>7.4f} {e['flip']:>7.4f} "
                f"{'-' if kept is None else format(kept, '.0%'):>5}")

    for v in report["views"]:
        typer.echo(row(v["name"], v["render"], v["enhanced"], v.get("trust")))
    kept = [v["trust"] for v in report["views"] if v.get("trust") is not None]
    typer.echo(row("mean", report["render"], report["enhanced"], sum(kept) / len(kept) if kept else None))


@takes_flags
def enhance(
    scene_dir: Annotated[Path, typer.Argument(help="Scene folder holding the view's render and depth.")],
    view: Annotated[str, typer.Option("--view", help="Name of the view to enhance (e.g. test_r_0).")],
    output: Annotated[Path, typer.Option("--output", help="Where to write the enhanced PNG.")],
    checkpoint: CheckpointOpt = None,
    *,
    flags: EnhanceFlags,
) -> None:
    """Enhance one view's render (a training view never uses its own photo)."""
    from roguenerf.enhance import settled
    from roguenerf.imageio import write_png
    from roguenerf.inference import SceneEnhancer

    with handle_errors():
        if output.suffix.lower() != ".png":
            raise InputError(f"--output: expected a .png path, got {output}")
        # Only the file is created (as by any program writing one): checked before the work.
        folder = output.parent
        if not folder.is_dir():
            raise InputError(f"--output: folder {folder} does not exist" if not folder.exists()
                             else f"--output: {folder} is not a folder")
        scene = open_scene(scene_dir, check=False)  # the views read are checked below, not all
        index = scene.index(view)
        model = load_model(checkpoint)
        # a neighbour's pose judged by an earlier run on this scene is not fitted again
        enhancer = SceneEnhancer(scene, model, options=flags.options(), settled_file=settled.default_path(scene.root))
        with progress_bar(f"enhancing {view}", "tile") as progress:
            result = enhancer.enhance_view(index, progress=progress)
        # What the command read (the view's render and depth, its neighbours' photos and depths),
        # checked after the work: the files are in the scene's read cache by now, decoded once.
        reads = {scene.index(n): ("photo", "depth") for n in result.neighbours}
        warn_unusable(scene, {index: ("render", "depth"), **reads})
        write_png(output, result.image, strategy="rle")  # the same pixels in a quarter of zlib's time
        used = ", ".join(f"{n} (pose refined)" if done else n
                         for n, done in zip(result.neighbours, result.aligned or [False] * len(result.neighbours)))
        used = used or "none"
        typer.echo(f"enhanced {view} in {result.seconds:.2f} s with neighbours: {used}", err=True)
        if result.colour_offset is not None:
            typer.echo("colour matched to the neighbours: RGB offset "
                       + ", ".join(f"{x:+.4f}" for x in result.colour_offset), err=True)
        if result.note:
            typer.echo(f"note: {result.note}", err=True)
        typer.echo(str(output))
        exit_when_done()  # the PNG is written and closed: no interpreter teardown (issue 51)
