"""``make-pairs``: the pair-making data tool (package ``roguefit``, beside the library), imported
only when the command runs."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Annotated

import typer

from roguecli.common import SeedOpt, check_budget, fail, handle_errors, progress_bar, setup_logging
from roguenerf.errors import InputError


def make_pairs_command(
    photos_dir: Annotated[Path, typer.Argument(
        help="Posed photo set: transforms.json + photos (every 8th view is held out).")],
    output: Annotated[Path, typer.Option(
        "--output", help="Scene folder to write (renders, depths, acc for every view).")] = ...,
    preset: Annotated[str, typer.Option("--preset", help=(
        "Field preset: blur (64³ RGB grid, half-size render), coarse (96³ RGB grid), fine "
        "(160³, view-dependent), hash (Instant-NGP hash grid, SH colour) or splat (3D Gaussian splats)."))] = "fine",
    minutes: Annotated[float | None, typer.Option(
        "--minutes", help="Fitting budget in minutes (default: the preset's).")] = None,
    steps: Annotated[int | None, typer.Option(
        "--steps", help="Fitting budget in steps (instead of minutes).")] = None,
    resolution: Annotated[int | None, typer.Option(
        "--resolution", help="Final grid side (default: the preset's).")] = None,
    folds: Annotated[int, typer.Option(
        "--folds", min=1, help=(
            "Cross-fit: K fields, each rendering the training views it never saw (novel-view renders "
            "with the field's real geometry error, K times the fitting time); 1: one field.")),
    ] = 1,
    seed: SeedOpt = 0,
) -> None:
    """Fit a radiance field to a posed photo set's training views and render render/photo pairs.

    A data tool (package ``roguefit``) for pre-training: resumable (run the same command again),
    a finished output folder is left as it is.
    """
    import dataclasses

    setup_logging()
    with handle_errors():
        try:
            from roguefit import PRESETS, make_pairs
        except ImportError:
            fail("make-pairs needs the roguefit data tool, which ships in this repository beside roguenerf", 1)
        if preset not in PRESETS:
            raise InputError(f"--preset: expected one of {', '.join(PRESETS)}, got {preset!r}")
        check_budget(steps, minutes)  # the fitter's budget takes the training budget's rules
        if resolution is not None and not 16 <= resolution <= 512:
            raise InputError(f"--resolution: expected 16..512, got {resolution}")
        if not photos_dir.is_dir():
            raise InputError(f"photo set {photos_dir} is not a directory")
        config = PRESETS[preset]
        changes = {"seed": seed, "folds": folds}
        if steps is not None:
            changes.update(steps=steps, minutes=None)
        elif minutes is not None:
            changes.update(minutes=minutes, steps=None)
        if resolution is not None:
            if not hasattr(config, "resolution"):
                raise InputError(f"--resolution: the {preset} preset has no grid")
            changes["resolution"] = resolution
        config = dataclasses.replace(config, **changes)
        from tqdm import tqdm

        total = config.steps * config.folds if config.steps is not None else 100
        bar = tqdm(total=total, desc=f"fitting {photos_dir.name}", unit="step" if config.steps else "%",
                   file=sys.stderr)

        def progress(p: dict) -> None:
            done = p["step"] if config.steps is not None else int(100 * p["fraction"])
            size = {"grid": p["resolution"]} if "resolution" in p else {"splats": p.get("gaussians")}
            bar.set_postfix(psnr=f"{p['psnr']:.2f}", **size, refresh=False)
            bar.update(done - bar.n)

        try:
            with progress_bar("rendering", "view") as view_progress:
                def render_progress(done: int, total_views: int) -> None:
                    bar.close()
                    view_progress(done, total_views)

                report = make_pairs(photos_dir, output, config, progress=progress, render_progress=render_progress)
        finally:
            bar.close()
        test = report["test"]
        typer.echo(f"fitted {report['steps']} steps in {report['fit_seconds']:.0f} s: training views "
                   f"{report['train']['psnr']:.2f} dB" + (f", held-out views {test['psnr']:.2f} dB" if test else ""),
                   err=True)
        typer.echo(str(output))
