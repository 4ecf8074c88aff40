"""The ``roguenerf`` console script: the library's commands, plus ``serve`` and ``make-pairs``.

This package sits above all the others: it builds its typer app from the library's
(:mod:`roguenerf.cli`: finetune, evaluate, enhance, enhance-path, import-*, pretrain) and adds
``serve`` (package ``service``) and ``make-pairs`` (package ``roguefit``), each imported only
when its command runs, so ``--help`` and the library's commands load neither. Nothing imports
this package; the library imports nothing above it (docs/architecture.md, Layers).
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Annotated

import typer

from roguenerf import cli as library
from roguenerf.cli import SeedOpt, check_budget, fail, handle_errors, progress_bar, setup_logging
from roguenerf.errors import InputError

app = typer.Typer(add_completion=False, no_args_is_help=True, pretty_exceptions_enable=False,
                  rich_markup_mode=None, help=library.app.info.help)
app.registered_commands.extend(library.app.registered_commands)


@app.command("make-pairs")
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



@app.command()
def serve(
    host: Annotated[str, typer.Option("--host", help="Address to listen on.")] = "127.0.0.1",
    port: Annotated[int, typer.Option("--port", help="Port to listen on.")] = 8000,
    data_dir: Annotated[Path, typer.Option(
        "--data-dir", help="Where scenes, jobs and checkpoints live.")] = Path("./data"),
) -> None:
    """Start the HTTP API with its embedded job worker."""
    # OpenMP's wait policy was chosen when this package imported roguenerf (roguenerf.runtime:
    # PASSIVE unless the user set one), before torch loads; the worker inherits it.
    with handle_errors():
        try:
            from service.server import run
        except ImportError as exc:
            missing = exc.name or str(exc)
            fail(f"the service cannot start: {missing} is not installed "
                  "(install the extras: pip install 'roguenerf[service]')", 1)
        run(host=host, port=port, data_dir=data_dir)


def _help_order() -> None:
    """`make-pairs` where it always stood in the help: after `pretrain`, whose data it makes."""
    commands = app.registered_commands
    make_pairs = next(c for c in commands if c.name == "make-pairs")
    commands.remove(make_pairs)
    after = next(k for k, c in enumerate(commands) if c.callback is library.pretrain)
    commands.insert(after + 1, make_pairs)


_help_order()


def main() -> None:
    """Console-script entry point (``roguenerf``; ``python -m roguecli``)."""
    library.run_app(app)
