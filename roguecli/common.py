"""What every command shares: one error format and exit codes, logging, progress bars, the
scene and checkpoint a command reads, and the options several commands take.

Errors are one line on stderr and an exit code: 2 for bad input (missing scene, bad
checkpoint, bad flag values), 130 after Ctrl-C ("interrupted"), 1 for failures (divergence,
cancellation, anything else). Progress and logs go to stderr, so ``evaluate --json`` prints
exactly one JSON object.

Importing this module loads neither torch nor anything above the library: ``--help`` stays
quick, and the library's defaults read here come from torch-free modules.
"""

from __future__ import annotations

import _thread
import atexit
import contextlib
import dataclasses
import functools
import gc
import inspect
import logging
import os
import signal
import sys
import threading
import typing
from pathlib import Path
from typing import Annotated

import typer

from roguenerf.errors import InputError, RoGUENeRFError

CheckpointOpt = Annotated[Path | None, typer.Option(
    "--checkpoint", help="Enhancer .safetensors, or the folder a fine-tune wrote (its model.safetensors); "
                         "default: the shipped default checkpoint.")]
SeedOpt = Annotated[int, typer.Option("--seed", help="Random seed.")]
NeighboursOpt = Annotated[int | None, typer.Option("--neighbours", help="Neighbours per view (default: model's).")]
DepthScaleOpt = Annotated[float, typer.Option(
    "--depth-scale", help="Multiply stored depth by this (0.001 for millimetre PNGs).")]


class Flags:
    """Options several commands take, handed to each command as one object.

    A subclass is a frozen dataclass whose fields are typer parameters (an ``Annotated`` option
    type and its default). A command decorated with :func:`takes_flags` declares the group as one
    keyword-only parameter annotated with the subclass: typer sees the fields' options in its
    place (``--help`` lists them there) and the command gets one object holding their values.
    Building anything from them (and its errors) is left to the command, inside its
    :func:`handle_errors`.
    """


def takes_flags(command=None, *, omit: tuple[str, ...] = ()):
    """Decorate a command whose parameters include :class:`Flags` groups (see there); ``omit``:
    fields the command does not offer (they keep their defaults)."""
    if command is None:
        return functools.partial(takes_flags, omit=omit)
    params, groups, offered = [], {}, set()
    for param in inspect.signature(command, eval_str=True).parameters.values():
        group = param.annotation
        if Flags not in getattr(group, "__mro__", ()):
            params.append(param)
            continue
        hints = typing.get_type_hints(group, include_extras=True)
        fields = [f for f in dataclasses.fields(group) if f.name not in omit]
        groups[param.name] = (group, [f.name for f in fields])
        offered.update(f.name for f in dataclasses.fields(group))
        params += [inspect.Parameter(f.name, inspect.Parameter.KEYWORD_ONLY, annotation=hints[f.name],
                                     default=f.default) for f in fields]
    if not offered.issuperset(omit):
        raise TypeError(f"{command.__name__}: omit names no field of its flags: {sorted(set(omit) - offered)}")
    signature = inspect.Signature(params)  # raises where a field's name is a parameter's too

    @functools.wraps(command)
    def run(*args, **kwargs):
        for name, (group, fields) in groups.items():
            kwargs[name] = group(**{field: kwargs.pop(field) for field in fields if field in kwargs})
        return command(*args, **kwargs)

    run.__signature__ = signature  # what typer reads, with the annotations' values
    run.__annotations__ = {p.name: p.annotation for p in params}
    return run


@dataclasses.dataclass(frozen=True)
class EnhanceFlags(Flags):
    """The enhance options of evaluate and enhance; :meth:`options` builds their
    :class:`~roguenerf.enhance.EnhanceOptions`."""

    neighbours: NeighboursOpt = None
    align: Annotated[bool, typer.Option("--align/--no-align", help=(
        "Refine each neighbour's pose against the render before using its photo (for dataset poses that are a "
        "little off; refused where it does not clearly help). Default on."))] = True
    colour: Annotated[bool, typer.Option("--colour/--no-colour", help=(
        "Match the enhanced view's overall colour to the neighbour photos where two or more agree (the model's "
        "colour prior comes from its pre-training renders). Default on."))] = True
    trust: Annotated[bool, typer.Option("--trust/--no-trust", help=(
        "Keep only part of the enhancer's change on a view where the neighbour photos mostly disagree (the "
        "field's geometry is off there: floaters), in proportion to the share where they agree; where they "
        "agree on under a tenth of it, only where they agree nearby. Default on."))] = True
    tile: Annotated[int | None, typer.Option("--tile", help=(
        "Enhance images taller or wider than this many pixels tile by tile (default on the CPU 1024 up to "
        "1920 x 1080 pixels and 512 above, bounding memory; 2048 on a GPU): larger tiles are faster on large "
        "images and take more memory (docs/results.md, Speed at users' sizes)."))] = None

    def options(self, **more):
        """The :class:`~roguenerf.enhance.EnhanceOptions` (``more``: a subclass's flags); bad
        values raise :class:`InputError`."""
        from roguenerf.enhance import EnhanceOptions

        return EnhanceOptions.from_flags(neighbours=self.neighbours, align=self.align, colour=self.colour,
                                         trust=self.trust, tile=self.tile, **more)


@dataclasses.dataclass(frozen=True)
class PathEnhanceFlags(EnhanceFlags):
    """enhance-path's: those of :class:`EnhanceFlags` and ``--temporal``."""

    temporal: Annotated[bool, typer.Option("--temporal/--no-temporal", help=(
        "Along the path, blend each frame with the last one (reprojected through the depth; less where the two "
        "renders disagree or the parallax is large) and fit each neighbour's pose once (again from a frame at "
        "under half the distance): less flicker, faster; --no-temporal enhances every frame on its own. "
        "Default on."))] = True

    model_every: Annotated[int | None, typer.Option("--model-every", help=(
        "With --temporal, run the model on at least one frame in this many and carry the model frames' "
        "results, reprojected, into the frames between, where they see at least 95 % of them: faster, but a "
        "carried frame keeps only part of the model's detail, most lost on fast orbits and near the photos "
        "(--carry-nearer 1, as --fast: only where no training photo is nearer to it than they are). 1: the "
        "model on every frame (the default; docs/results.md, Speed at users' sizes)."))] = None

    carry_between: Annotated[bool | None, typer.Option("--carry-between/--carry-after", help=(
        "With --model-every K, make the model frames 0, K, 2K, ... first and carry each frame between two of "
        "them from both, mixed by how near each is (the default); --carry-after: from the last model frame "
        "only."), show_default=False)] = None

    between_agreement: Annotated[float | None, typer.Option("--between-agreement", metavar="DB", help=(
        "With --model-every (carrying between), carry a frame only where the two model frames around it, "
        "reprojected into it, also agree with each other to this PSNR (default 0: no such test; it depends on "
        "the scene's quality: docs/results.md)."))] = None

    carry_agreement: Annotated[float | None, typer.Option("--carry-agreement", metavar="DB", help=(
        "With --model-every, carry a frame only where the model frames' renders, reprojected into it, "
        "match its render to this PSNR (e.g. 28; higher: fewer frames carried, more of the model's detail "
        "kept; default 0: carry wherever 95 % is seen)."))] = None

    carry_share: Annotated[float | None, typer.Option("--carry-share", metavar="SHARE", help=(
        "With --model-every, carry a frame only where what the model frames' renders, reprojected into it, "
        "miss of its render is at most this share of the enhancer's change there (mean squares; e.g. 0.05; "
        "default 0: no such test). Unlike --carry-agreement it scales with the scene: docs/results.md."
        ))] = None

    carry_nearer: Annotated[float | None, typer.Option("--carry-nearer", metavar="RATIO", help=(
        "With --model-every, carry a frame only where the model frames it is carried from are at most this "
        "many times as far from it as its nearest training photo (camera centres): where a photo is nearer, "
        "the model brings from it what they do not have (default 0: no such test)."))] = None

    schedule: Annotated[str | None, typer.Option("--schedule", metavar="fixed|gate", help=(
        "With --model-every K (carrying between): where the model frames go: fixed, every K-th frame (the "
        "default); gate, as far apart as --carry-nearer lets every frame between them be carried, at most K "
        "frames: the model runs where the path passes near the photos and at most once in K frames elsewhere "
        "(measured, not chosen for --fast: docs/results.md)."))] = None

    both_ways: Annotated[bool | None, typer.Option("--both-ways/--one-way", help=(
        "With --temporal, blend each frame with the frames after it too: a second pass from the last frame "
        "back over the first pass's frames (kept in OUTPUT/forward/): no lag, so a frame where a nearer photo "
        "comes in keeps more of it (the default; with --fast one way); --one-way: the first pass alone, frames "
        "final as they are made."), show_default=False)] = None

    fast: Annotated[bool, typer.Option("--fast", help=(
        "The fast setting: the model on one frame in 4, the frames between carried from both where they are "
        "no farther from the frame than its nearest training photo, one way (--model-every 4 --carry-nearer 1 "
        "--one-way; those flags, given beside it, win). Faster on smooth paths, as fast as the model where the "
        "path passes near the photos; a carried frame can keep less of the model's gain (up to 0.83 dB less on "
        "the paths measured), and one pass can flicker more than the render on very smooth paths (then add "
        "--both-ways; docs/results.md, Speed at users' sizes)."))] = False

    def options(self):
        temporal = self.temporal
        if self.both_ways is False and not self.temporal:
            raise InputError("--one-way: the frames are blended only with --temporal; drop --no-temporal")
        if self.fast and not self.temporal:
            raise InputError("--fast: frames are carried by the temporal filter; drop --no-temporal")
        carrying = self.model_every is not None or self.fast
        for value, flag in ((self.carry_agreement, "--carry-agreement"), (self.carry_share, "--carry-share"),
                            (self.carry_nearer, "--carry-nearer"), (self.schedule, "--schedule"),
                            (self.carry_between, "--carry-between/--carry-after")):
            if value is not None and not carrying:
                raise InputError(f"{flag}: frames are carried only with --model-every K (K > 1) or --fast")
        if self.schedule is not None and self.carry_between is False:
            raise InputError("--schedule: places the model frames that frames are carried between: drop --carry-after")
        if self.between_agreement is not None and (not carrying or self.carry_between is False):
            raise InputError("--between-agreement: judges frames carried between model frames: needs --model-every "
                             "K (K > 1) or --fast, without --carry-after")
        if self.model_every is not None and not self.temporal:
            raise InputError("--model-every: frames are carried by the temporal filter; drop --no-temporal")
        if carrying or self.both_ways is False:
            from roguenerf.enhance.temporal import TemporalConfig

            chosen = {"model_every": self.model_every, "carry_agreement": self.carry_agreement,
                      "carry_share": self.carry_share, "carry_nearer": self.carry_nearer, "both_ways": self.both_ways,
                      "carry_between": self.carry_between, "between_agreement": self.between_agreement,
                      "schedule": self.schedule}
            chosen = {k: v for k, v in chosen.items() if v is not None}
            temporal = TemporalConfig.fast(**chosen) if self.fast else TemporalConfig(**chosen)
        return super().options(temporal=temporal)


INTERRUPTED = 130
"""Exit status after Ctrl-C (128 + SIGINT), as shells report it."""
_reported = {"interrupted": False}
"""Whether a command's error handling has said "interrupted" already (:func:`run_app`)."""
START_UP_THRESHOLD = 200_000
"""Objects made between two of the collector's youngest passes while :func:`run_app` starts up
(Python's default: 700)."""
_start_up: dict = {"thresholds": None}
"""The collector's thresholds to restore once the imports are done (:func:`_started`)."""


def _started() -> None:
    """The imports are done (:func:`handle_errors`, after torch's): the objects made so far are
    kept out of every later collection and the collector's usual thresholds come back."""
    if _start_up["thresholds"] is not None:
        gc.freeze()
        gc.set_threshold(*_start_up["thresholds"])
        _start_up["thresholds"] = None


def _importing(frame) -> bool:
    """Whether ``frame`` runs inside an import (importlib's frames are on its stack)."""
    while frame is not None:
        if frame.f_code.co_filename.startswith("<frozen importlib"):
            return True
        frame = frame.f_back
    return False


def _on_interrupt(signum, frame) -> None:
    """SIGINT: ``KeyboardInterrupt``, but never inside an import. An interrupted import leaves a
    module half made, and some callers (torch's C++ importing ``torch._dynamo`` or NumPy) swallow
    the exception: the Ctrl-C was lost, or a later import failed (a RecursionError, "cannot load
    module more than once"). There the interrupt is raised again 20 ms later, until it lands
    outside any import."""
    if not _importing(frame):
        raise KeyboardInterrupt
    timer = threading.Timer(0.02, _thread.interrupt_main)
    timer.daemon = True
    timer.start()


_done: dict = {"exit_now": False}
"""Whether the command that ran has closed everything it made (:func:`exit_when_done`)."""


def exit_when_done() -> None:
    """Called by a command once everything it makes is written and closed (a one-view
    ``enhance``): the process may end without tearing the interpreter down (:func:`run_app`)."""
    _done["exit_now"] = True


def _exit_now() -> None:
    """End the process with status 0 now: the atexit handlers run, logging and the standard
    streams are flushed, then ``os._exit`` skips the interpreter's teardown (freeing torch's
    modules and objects one by one: 0.13-0.17 s of a one-view command on 2 cores, issue 51)."""
    atexit._run_exitfuncs()
    logging.shutdown()
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):  # a closed pipe: nothing more can be said
            stream.flush()
    os._exit(0)


def _may_exit_now(code) -> bool:
    """A command said it is done, it succeeded, and no other thread would be cut short."""
    return (_done["exit_now"] and code in (0, None) and threading.current_thread() is threading.main_thread()
            and all(t.daemon or t is threading.main_thread() for t in threading.enumerate()))


def run_app(typer_app, *, fast_exit: bool = False) -> None:
    """Run ``typer_app``; Ctrl-C outside a command's error handling (typer exits 130 silently) gets
    its one line too, and never lands inside an import (:func:`_on_interrupt`). With
    ``fast_exit`` (the console script's process, never a caller that goes on), a command that
    called :func:`exit_when_done` and succeeded ends the process at once (:func:`_exit_now`)."""
    _reported["interrupted"] = False
    _done["exit_now"] = False
    handled = threading.current_thread() is threading.main_thread() and \
        signal.getsignal(signal.SIGINT) is signal.default_int_handler  # not where SIGINT is ignored
    if handled:
        signal.signal(signal.SIGINT, _on_interrupt)
    # Start-up and exit: importing torch makes about a million objects, which the collector
    # walks again and again while they are made and once more at exit (0.2-0.5 s each on
    # 2 cores); none of them is garbage. The collector runs rarely until the imports are done
    # (:func:`_started`; a command that never gets there still collects), and everything is
    # frozen before the interpreter exits.
    if _start_up["thresholds"] is None:
        _start_up["thresholds"] = gc.get_threshold()
        gc.set_threshold(START_UP_THRESHOLD, *_start_up["thresholds"][1:])
    try:
        typer_app()
    except SystemExit as exc:
        if exc.code == INTERRUPTED and not _reported["interrupted"]:
            typer.echo("error: interrupted", err=True)
        if fast_exit and _may_exit_now(exc.code):
            _exit_now()
        raise
    finally:
        _started()
        gc.freeze()
        if handled:
            signal.signal(signal.SIGINT, signal.default_int_handler)


def fail(message: str, code: int) -> None:
    """One ``error: ...`` line on stderr, then exit with ``code``."""
    typer.echo(f"error: {message}", err=True)
    raise typer.Exit(code)


@contextlib.contextmanager
def handle_errors():
    """Apply the process settings (:mod:`roguenerf.runtime`), then turn library exceptions into
    one stderr line and an exit code (no stack trace)."""
    try:
        from roguenerf import runtime

        runtime.configure()  # imports torch
        _started()
        yield
    except typer.Exit:
        raise
    except InputError as exc:
        fail(str(exc), 2)
    except RoGUENeRFError as exc:
        fail(str(exc), 1)
    except KeyboardInterrupt:  # Ctrl-C: the shell's status for SIGINT, one line, no traceback
        _reported["interrupted"] = True
        fail("interrupted", INTERRUPTED)
    except Exception as exc:  # noqa: BLE001 - the CLI promises no stack traces
        fail(f"{type(exc).__name__}: {exc}", 1)


def setup_logging() -> None:
    logging.basicConfig(level=logging.INFO, stream=sys.stderr, format="%(message)s", force=True)


@contextlib.contextmanager
def progress_bar(desc: str, unit: str, *, clock=None):
    """A ``progress(done, total)`` callback drawing a tqdm bar on stderr (created on first call).
    ``clock``: ``(done, total) -> seconds left or None`` (:class:`roguenerf.trajectory.PathClock`),
    shown instead of tqdm's own estimate (which takes every step to cost the same)."""
    bar = None

    def progress(done: int, total: int) -> None:
        nonlocal bar
        if bar is None:
            from tqdm import tqdm

            shape = {"bar_format": "{l_bar}{bar}| {n_fmt}/{total_fmt} [{elapsed}{postfix}]"} if clock else {}
            bar = tqdm(total=total, unit=unit, desc=desc, file=sys.stderr, dynamic_ncols=True, **shape)
        if clock is not None:
            left = clock(done, total)
            bar.set_postfix_str("" if left is None else f"about {bar.format_interval(left)} left", refresh=False)
        bar.update(done - bar.n)

    try:
        yield progress
    finally:
        if bar is not None:
            bar.close()


def open_scene(scene_dir: Path, *, check: bool = True):
    """The scene, and (``check``) a warning naming its unusable views: every view's files are
    read once for that; a one-view command checks just the views it reads instead."""
    from roguenerf.data.readers import load_scene

    if not scene_dir.exists():
        raise InputError(f"scene directory {scene_dir} does not exist")
    if not scene_dir.is_dir():
        raise InputError(f"scene directory {scene_dir} is not a directory")
    scene = load_scene(scene_dir)
    if check:
        warn_unusable(scene)
    return scene


def warn_unusable(scene, reads=None) -> None:
    """One warning line listing the views that cannot serve (e.g. a depth map of zeros): all of
    the scene's, or, with ``reads`` (``{view index: files}``), the files a one-view command reads
    (:func:`~roguenerf.data.scene.unusable_views`: through the scene's read cache)."""
    from roguenerf.data.scene import unusable_views

    bad = unusable_views(scene, reads=reads)
    if bad:
        among = (f"of {len(scene.frames)} views of {scene.root}" if reads is None
                 else f"of the {len(reads)} views of {scene.root} this command reads")
        typer.echo(f"warning: {len(bad)} {among} are unusable and "
                   f"contribute nothing: {'; '.join(str(v) for v in bad)}", err=True)


def checkpoint_file(checkpoint: Path | None) -> Path:
    """The file ``--checkpoint`` names (a folder: :func:`roguenerf.checkpoint.resolve_checkpoint`),
    or without it the shipped default checkpoint."""
    from roguenerf.checkpoint import default_checkpoint_path, resolve_checkpoint

    if checkpoint is not None:
        return resolve_checkpoint(checkpoint)
    path = default_checkpoint_path(must_exist=False)
    if not path.is_file():
        raise InputError(f"no --checkpoint given and the default checkpoint {path} does not exist yet "
                         "(train one with `roguenerf pretrain`, or pass --scratch to fine-tune from scratch)")
    return path


def load_model(checkpoint: Path | None):
    from roguenerf.checkpoint import load_checkpoint

    model, _meta = load_checkpoint(checkpoint_file(checkpoint))
    return model


def check_budget(steps, minutes, *, evaluate_hint: bool = False) -> None:
    """The budget flags, by the library's rules (:meth:`TrainConfig.validate_budget`)."""
    from roguenerf.training import TrainConfig

    try:
        TrainConfig.validate_budget(steps, minutes, names=("--steps", "--minutes"))
    except InputError as exc:
        if not evaluate_hint or (steps is not None and minutes is not None):
            raise  # the hint is for a budget too small to train
        raise InputError(f"{exc} (to measure a checkpoint without training, use `roguenerf evaluate`)") from None
