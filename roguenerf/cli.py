"""The library's commands: finetune, evaluate, enhance, enhance-path, import-nerfstudio,
import-gsplat, import-3dgs, pretrain (``python -m roguenerf``). The ``roguenerf`` console script
(:mod:`roguecli`) builds on this app and adds ``serve`` and ``make-pairs``.

Errors are one line on stderr and an exit code: 2 for bad input (missing scene, bad
checkpoint, bad flag values), 130 after Ctrl-C ("interrupted"), 1 for failures (divergence,
cancellation, anything else).
Progress and logs go to stderr, so ``evaluate --json`` prints exactly one JSON object.
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import sys
from pathlib import Path
from typing import Annotated

import typer

from roguenerf.errors import InputError, RoGUENeRFError

# rich_markup_mode=None: typer's rich help shows flags (--json, --help) as taking a "<bool>" value.
app = typer.Typer(add_completion=False, no_args_is_help=True, pretty_exceptions_enable=False,
                  rich_markup_mode=None,
                  help="RoGUENeRF: enhance radiance-field renders with geometry-aligned training photos.")

CheckpointOpt = Annotated[Path | None, typer.Option(
    "--checkpoint", help="Enhancer .safetensors, or the folder a fine-tune wrote (its model.safetensors); "
                         "default: the shipped default checkpoint.")]
DEFAULT_MINUTES_CPU, DEFAULT_MINUTES_GPU = 10, 60
"""The library's default budget (roguenerf.training.config CPU_MINUTES / GPU_MINUTES; a test
checks they agree). Not imported from there: that module loads torch, and --help should not."""
MinutesOpt = Annotated[float | None, typer.Option("--minutes", help=(
    f"Training budget in minutes (> 0). Default without --steps: {DEFAULT_MINUTES_CPU} minutes on a CPU, "
    f"{DEFAULT_MINUTES_GPU} on a GPU."))]
StepsOpt = Annotated[int | None, typer.Option("--steps", help="Training budget in optimiser steps (> 0).")]
WithoutOpt = Annotated[list[str] | None, typer.Option(
    "--without", help="Switch a component off (repeatable): neighbours, alignment, refinement, attention.")]
VariantOpt = Annotated[str | None, typer.Option("--variant", help="Model variant: nano, micro, T, S, B.")]
CropOpt = Annotated[int | None, typer.Option("--crop", help="Random crop side in pixels (default per machine).")]
BatchOpt = Annotated[int, typer.Option("--batch", help="Crops per optimiser step.")]
VggOpt = Annotated[Path | None, typer.Option(
    "--vgg-weights", help="Local torchvision VGG-19 weights for the perceptual loss (else L1 alone).")]
SeedOpt = Annotated[int, typer.Option("--seed", help="Random seed.")]
LrOpt = Annotated[float | None, typer.Option("--lr", help=(
    "Adam learning rate (default: 5e-4 on a CPU, chosen by measured gain per minute; "
    "1e-4 on a GPU, the paper's)."))]
LrScheduleOpt = Annotated[str | None, typer.Option(
    "--lr-schedule", help="cosine (the lr falls to 0 over the budget; the default) or constant.")]
def _enhance_options(neighbours, align: bool, colour: bool, trust: bool):
    """The one :class:`~roguenerf.enhance.EnhanceOptions` of evaluate, enhance and enhance-path."""
    from roguenerf.enhance import EnhanceOptions

    return EnhanceOptions.from_flags(neighbours=neighbours, align=align, colour=colour, trust=trust)


NeighboursOpt = Annotated[int | None, typer.Option("--neighbours", help="Neighbours per view (default: model's).")]
AlignOpt = Annotated[bool, typer.Option("--align/--no-align", help=(
    "Refine each neighbour's pose against the render before using its photo (for dataset poses that are a "
    "little off; refused where it does not clearly help). Default on."))]
ColourOpt = Annotated[bool, typer.Option("--colour/--no-colour", help=(
    "Match the enhanced view's overall colour to the neighbour photos where two or more agree (the model's "
    "colour prior comes from its pre-training renders). Default on."))]
TrustOpt = Annotated[bool, typer.Option("--trust/--no-trust", help=(
    "Keep only part of the enhancer's change on a view where the neighbour photos mostly disagree (the "
    "field's geometry is off there: floaters), in proportion to the share where they agree; where they agree on "
    "under a tenth of it, only where they agree nearby. Default on."))]
FreezeOpt = Annotated[bool | None, typer.Option(
    "--freeze-neighbour-encoder/--train-neighbour-encoder",
    help="Keep conv_H (the neighbour-photo encoder) fixed and encode the training photos once, so each "
         "step skips it; default: the plan's.")]

DepthNoiseOpt = Annotated[float | None, typer.Option(
    "--depth-noise", help="Largest log-depth error put on half the target depths as a smooth random field "
                          "(e.g. 0.3: up to x1.35); render and photo unchanged, so the model learns to fall back "
                          "on the render where the geometry is off. Default: none.")]
RenderWarpOpt = Annotated[float | None, typer.Option(
    "--render-warp", help="Pixels: displace the target render and depth of half the crops along a smooth random "
                          "shift up to this size, so the training views look like novel views (default: the plan's).")]


INTERRUPTED = 130
"""Exit status after Ctrl-C (128 + SIGINT), as shells report it."""
_reported = {"interrupted": False}
"""Whether a command's error handling has said "interrupted" already (:func:`run_app`)."""


def run_app(typer_app) -> None:
    """Run ``typer_app``; Ctrl-C outside a command's error handling (typer exits 130 silently) gets
    its one line too."""
    _reported["interrupted"] = False
    try:
        typer_app()
    except SystemExit as exc:
        if exc.code == INTERRUPTED and not _reported["interrupted"]:
            typer.echo("error: interrupted", err=True)
        raise


def _fail(message: str, code: int) -> None:
    typer.echo(f"error: {message}", err=True)
    raise typer.Exit(code)


@contextlib.contextmanager
def _errors():
    """Apply the process settings (:mod:`roguenerf.runtime`), then turn library exceptions into
    one stderr line and an exit code (no stack trace)."""
    try:
        from roguenerf import runtime

        runtime.configure()
        yield
    except typer.Exit:
        raise
    except InputError as exc:
        _fail(str(exc), 2)
    except RoGUENeRFError as exc:
        _fail(str(exc), 1)
    except KeyboardInterrupt:  # Ctrl-C: the shell's status for SIGINT, one line, no traceback
        _reported["interrupted"] = True
        _fail("interrupted", INTERRUPTED)
    except Exception as exc:  # noqa: BLE001 - the CLI promises no stack traces
        _fail(f"{type(exc).__name__}: {exc}", 1)


def _setup_logging() -> None:
    logging.basicConfig(level=logging.INFO, stream=sys.stderr, format="%(message)s", force=True)


def _load_scene(scene_dir: Path, *, check: bool = True):
    """The scene, and (``check``) a warning naming its unusable views: every view's files are
    read once for that; a one-view command checks just the views it reads instead."""
    from roguenerf.data.readers import load_scene

    if not scene_dir.exists():
        raise InputError(f"scene directory {scene_dir} does not exist")
    if not scene_dir.is_dir():
        raise InputError(f"scene directory {scene_dir} is not a directory")
    scene = load_scene(scene_dir)
    if check:
        _warn_unusable(scene)
    return scene


def _warn_unusable(scene, indices=None) -> None:
    """One warning line listing the views that cannot serve (e.g. a depth map of zeros): all of
    the scene's, or those of ``indices`` (the views a command reads)."""
    from roguenerf.data.scene import unusable_views

    bad = unusable_views(scene, indices=indices)
    if bad:
        among = (f"of {len(scene.frames)} views of {scene.root}" if indices is None
                 else f"of the {len(set(indices))} views of {scene.root} this command reads")
        typer.echo(f"warning: {len(bad)} {among} are unusable and "
                   f"contribute nothing: {'; '.join(str(v) for v in bad)}", err=True)


def _checkpoint_path(checkpoint: Path | None) -> Path:
    from roguenerf.checkpoint import default_checkpoint_path

    if checkpoint is not None:
        if checkpoint.is_dir():
            return _checkpoint_in(checkpoint)
        if not checkpoint.is_file():
            raise InputError(f"checkpoint {checkpoint} does not exist")
        return checkpoint
    path = default_checkpoint_path(must_exist=False)
    if not path.is_file():
        raise InputError(f"no --checkpoint given and the default checkpoint {path} does not exist yet "
                         "(train one with `roguenerf pretrain`, or pass --scratch to fine-tune from scratch)")
    return path


def _checkpoint_in(folder: Path) -> Path:
    """The final checkpoint in a folder `roguenerf finetune` / `pretrain` wrote (its --output)."""
    from roguenerf.training.loop import MODEL_FILE, STATE_FILE

    model = folder / MODEL_FILE
    if model.is_file():
        return model
    if (folder / STATE_FILE).is_file():
        raise InputError(f"checkpoint folder {folder} holds no finished checkpoint ({MODEL_FILE}), only the "
                         f"resume state of an unfinished run ({STATE_FILE}): run the same fine-tune again to "
                         "finish it")
    found = sorted(p.name for p in folder.glob("*.safetensors"))
    if len(found) == 1:
        return folder / found[0]
    raise InputError(f"checkpoint folder {folder} holds no checkpoint: expected {MODEL_FILE} (what "
                     "`roguenerf finetune --output` writes)"
                     + (f"; it holds {', '.join(found)}: pass one of them" if found else ""))


def _load_model(checkpoint: Path | None):
    from roguenerf.checkpoint import load_checkpoint

    model, _meta = load_checkpoint(_checkpoint_path(checkpoint))
    return model


def _check_budget(steps, minutes, *, evaluate_hint: bool = False) -> None:
    """The budget flags, by the library's rules (:meth:`TrainConfig.validate_budget`)."""
    from roguenerf.training import TrainConfig

    try:
        TrainConfig.validate_budget(steps, minutes, names=("--steps", "--minutes"))
    except InputError as exc:
        if not evaluate_hint or (steps is not None and minutes is not None):
            raise  # the hint is for a budget too small to train
        raise InputError(f"{exc} (to measure a checkpoint without training, use `roguenerf evaluate`)") from None


def _train_config(*, minutes, steps, without, variant, crop, vgg_weights, seed, neighbours, lr=None,
                  lr_schedule=None, evaluate=True, **extra):
    from roguenerf.training import COMPONENTS, TrainConfig

    _check_budget(steps, minutes, evaluate_hint=True)
    without = tuple(without or ())
    for w in without:
        if w not in COMPONENTS:
            raise InputError(f"--without: expected one of {', '.join(COMPONENTS)}, got {w!r}")
    return TrainConfig(steps=steps, minutes=minutes, crop=crop, vgg_weights=vgg_weights, seed=seed,
                       variant=variant, without=without, num_neighbours=neighbours, evaluate=evaluate,
                       lr=lr, lr_schedule=lr_schedule, **extra).validate()


def _report_training(result) -> None:
    typer.echo(f"saved {result.checkpoint} after {result.steps} steps in {result.seconds:.0f} s "
               f"(final loss {result.final_loss:.4f}, loss {result.loss_kind})", err=True)
    transfer = result.config.get("transfer")
    if transfer:
        typer.echo(f"weights from the checkpoint: {transfer['loaded']} tensors loaded; dropped: "
                   f"{', '.join(transfer['dropped']) or 'nothing'}; fresh: {', '.join(transfer['fresh']) or 'nothing'}"
                   f"; widened (new inputs at zero weight): {', '.join(transfer.get('widened', [])) or 'nothing'}",
                   err=True)
    if result.before and result.after:
        b, a = result.before, result.after
        typer.echo(f"test PSNR: render {b['render']['psnr']:.2f} dB, enhanced before {b['enhanced']['psnr']:.2f} dB, "
                   f"after {a['enhanced']['psnr']:.2f} dB", err=True)


@app.command()
def finetune(
    scene_dir: Annotated[Path, typer.Argument(help="Scene folder (transforms.json with renders and depths).")],
    output: Annotated[Path, typer.Option("--output", help="Output directory (model + resumable state).")],
    checkpoint: CheckpointOpt = None,
    scratch: Annotated[bool, typer.Option("--scratch", help="Start from random weights, not a checkpoint.")] = False,
    minutes: MinutesOpt = None,
    steps: StepsOpt = None,
    without: WithoutOpt = None,
    variant: VariantOpt = None,
    crop: CropOpt = None,
    vgg_weights: VggOpt = None,
    seed: SeedOpt = 0,
    neighbours: NeighboursOpt = None,
    lr: LrOpt = None,
    lr_schedule: LrScheduleOpt = None,
    freeze_neighbour_encoder: FreezeOpt = None,
    render_warp: RenderWarpOpt = None,
    depth_noise: DepthNoiseOpt = None,
    no_eval: Annotated[bool, typer.Option("--no-eval", help="Skip the before/after test evaluation.")] = False,
) -> None:
    """Fine-tune the enhancer on one scene's training views; resumes from OUTPUT when interrupted."""
    from roguenerf.training import finetune as run_finetune

    _setup_logging()
    with _errors():
        if scratch and checkpoint is not None:
            raise InputError("give either --checkpoint or --scratch, not both")
        config = _train_config(minutes=minutes, steps=steps, without=without, variant=variant, crop=crop,
                               vgg_weights=vgg_weights, seed=seed, neighbours=neighbours, lr=lr,
                               lr_schedule=lr_schedule, evaluate=not no_eval,
                               freeze_neighbour_encoder=freeze_neighbour_encoder, render_warp=render_warp,
                               depth_noise=depth_noise)
        from roguenerf.training.loop import check_training_output

        check_training_output(output)
        scene = _load_scene(scene_dir)
        start = None if scratch else _checkpoint_path(checkpoint)
        result = run_finetune(scene, output, checkpoint=start, config=config)
        _report_training(result)
        typer.echo(str(result.checkpoint))


@app.command()
def pretrain(
    scene_dirs: Annotated[list[Path] | None, typer.Argument(help="Scene folders to pre-train on.")] = None,
    output: Annotated[Path, typer.Option("--output", help="Output directory (model + resumable state).")] = ...,
    toy: Annotated[int, typer.Option("--toy", help="Add N generated toy scenes (degraded renders).")] = 0,
    checkpoint: Annotated[Path | None, typer.Option("--checkpoint", help="Start from these weights.")] = None,
    minutes: MinutesOpt = None,
    steps: StepsOpt = None,
    without: WithoutOpt = None,
    variant: VariantOpt = None,
    crop: CropOpt = None,
    batch: BatchOpt = 4,
    vgg_weights: VggOpt = None,
    seed: SeedOpt = 0,
    neighbours: NeighboursOpt = None,
    lr: LrOpt = None,
    lr_schedule: LrScheduleOpt = None,
    held_out_from: Annotated[list[Path] | None, typer.Option(
        "--held-out-from", help="Also train on this scene folder's held-out views (repeatable; added to the "
        "scenes if missing): renders of views its radiance field never saw, with training-view neighbours. "
        "Never for a scene you evaluate on.")] = None,
    held_out_share: Annotated[float, typer.Option(
        "--held-out-share", help="Chance that a target of a --held-out-from scene is a held-out view.")] = 0.5,
    pool_spread: Annotated[bool | None, typer.Option(
        "--pool-spread/--no-pool-spread", help="Give the merge the neighbours' spread (max - min) next to their "
        "max-pool (not in the paper); from a checkpoint without it, the new inputs start at zero weight. "
        "Default: the checkpoint's.")] = None,
    neighbour_pose_noise: Annotated[str | None, typer.Option(
        "--neighbour-pose-noise", metavar="DEG,SHARE", help="Perturb each neighbour's pose per sample, up to: "
        "rotation RMS in degrees, translation RMS as a share of the cameras' spread (e.g. 0.5,0.05); each "
        "target draws its own level, from exact poses to these.")] = None,
    depth_noise: DepthNoiseOpt = None,
) -> None:
    """Pre-train across scene folders and/or generated toy scenes."""
    from roguenerf.training import pretrain as run_pretrain

    _setup_logging()
    with _errors():
        if toy < 0:
            raise InputError(f"--toy: expected >= 0, got {toy}")
        noise = None
        if neighbour_pose_noise is not None:
            try:
                noise = tuple(float(x) for x in neighbour_pose_noise.split(","))
            except ValueError:
                raise InputError("--neighbour-pose-noise: expected DEG,SHARE numbers, "
                                 f"got {neighbour_pose_noise!r}") from None
        config = _train_config(minutes=minutes, steps=steps, without=without, variant=variant, crop=crop,
                               vgg_weights=vgg_weights, seed=seed, neighbours=neighbours, lr=lr,
                               lr_schedule=lr_schedule, evaluate=False, held_out_share=held_out_share, batch=batch,
                               pool_spread=pool_spread, neighbour_pose_noise=noise, depth_noise=depth_noise)
        dirs = list(scene_dirs or [])
        position = {}  # resolved folder -> its first position in dirs
        for k, d in enumerate(dirs):
            position.setdefault(d.resolve(), k)
        held = []
        for d in held_out_from or []:
            key = d.resolve()
            if key not in position:
                position[key] = len(dirs)
                dirs.append(d)
            held.append(position[key])
        from roguenerf.training.loop import TOY_FOLDER, check_training_output

        check_training_output(output)  # before the toy scenes are written into it
        scenes = [_load_scene(d) for d in dirs]
        scenes += make_toy_scenes(output / TOY_FOLDER, toy, seed=seed)
        if not scenes:
            raise InputError("no scenes to pre-train on: give SCENE_DIR arguments and/or --toy N")
        if checkpoint is not None:
            checkpoint = _checkpoint_path(checkpoint)  # a file, or the folder a run wrote
        result = run_pretrain(scenes, output, checkpoint=checkpoint, config=config, held_out_scenes=held)
        _report_training(result)
        typer.echo(str(result.checkpoint))


def make_toy_scenes(root: Path, count: int, *, seed: int = 0, height: int = 96, width: int = 128) -> list:
    """``count`` toy scenes with NeRF-like degradations under ``root`` (reused when already there)."""
    from roguenerf.data.degrade import Degradation
    from roguenerf.data.readers import load_scene
    from roguenerf.data.toy import make_toy_scene

    scenes = []
    for k in range(count):
        path = root / f"toy_{seed + k:03d}"
        if (path / "transforms.json").is_file():
            scenes.append(load_scene(path))
        else:
            scenes.append(make_toy_scene(path, seed=seed + k, height=height, width=width,
                                         degradation=Degradation()))
    return scenes


@contextlib.contextmanager
def _progress_bar(desc: str, unit: str):
    """A ``progress(done, total)`` callback drawing a tqdm bar on stderr (created on first call)."""
    bar = None

    def progress(done: int, total: int) -> None:
        nonlocal bar
        if bar is None:
            from tqdm import tqdm

            bar = tqdm(total=total, unit=unit, desc=desc, file=sys.stderr, dynamic_ncols=True)
        bar.update(done - bar.n)

    try:
        yield progress
    finally:
        if bar is not None:
            bar.close()


@app.command()
def evaluate(
    scene_dir: Annotated[Path, typer.Argument(help="Scene folder.")],
    checkpoint: CheckpointOpt = None,
    split: Annotated[str, typer.Option("--split", help="Views to evaluate: test, train or all.")] = "test",
    as_json: Annotated[bool, typer.Option("--json", help="Print one JSON object and nothing else.")] = False,
    neighbours: NeighboursOpt = None,
    align: AlignOpt = True,
    colour: ColourOpt = True,
    trust: TrustOpt = True,
) -> None:
    """PSNR/SSIM/FLIP of renders and enhanced renders against the photos, per view and mean (FLIP: lower is better)."""
    from roguenerf.training import evaluate as run_evaluate

    with _errors():
        if split not in ("test", "train", "all"):
            raise InputError(f"--split: expected test, train or all, got {split!r}")
        scene = _load_scene(scene_dir)
        model = _load_model(checkpoint)
        with _progress_bar(f"evaluating {split} views", "view") as progress:
            report = run_evaluate(scene, model, split=split, progress=progress,
                                  options=_enhance_options(neighbours, align, colour, trust))
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


@app.command()
def enhance(
    scene_dir: Annotated[Path, typer.Argument(help="Scene folder holding the view's render and depth.")],
    view: Annotated[str, typer.Option("--view", help="Name of the view to enhance (e.g. test_r_0).")],
    output: Annotated[Path, typer.Option("--output", help="Where to write the enhanced PNG.")],
    checkpoint: CheckpointOpt = None,
    neighbours: NeighboursOpt = None,
    align: AlignOpt = True,
    colour: ColourOpt = True,
    trust: TrustOpt = True,
) -> None:
    """Enhance one view's render (a training view never uses its own photo)."""
    from roguenerf.imageio import write_png
    from roguenerf.inference import SceneEnhancer

    with _errors():
        if output.suffix.lower() != ".png":
            raise InputError(f"--output: expected a .png path, got {output}")
        # Only the file is created (as by any program writing one): checked before the work.
        folder = output.parent
        if not folder.is_dir():
            raise InputError(f"--output: folder {folder} does not exist" if not folder.exists()
                             else f"--output: {folder} is not a folder")
        scene = _load_scene(scene_dir, check=False)  # the views read are checked below, not all
        index = scene.index(view)
        model = _load_model(checkpoint)
        enhancer = SceneEnhancer(scene, model, options=_enhance_options(neighbours, align, colour, trust))
        frame = scene.frames[index]
        chosen = enhancer.select(frame.world_from_cam, exclude=index if frame.split == "train" else None)
        _warn_unusable(scene, [index, *chosen])
        with _progress_bar(f"enhancing {view}", "tile") as progress:
            result = enhancer.enhance_view(index, progress=progress)
        write_png(output, result.image)
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


def _import_command(tool: str, dataset: Path, renders: Path, output: Path, depth_type, depth_scale: float,
                    depth_units: str, dataparser_transforms, background, skip_missing: bool = False,
                    force: bool = False, hold_flag: str = "--hold", **split) -> None:
    from roguenerf.data.exports import import_renders

    with _errors():
        if split.get("test_every") is not None and split["test_every"] < 0:
            raise InputError(f"{hold_flag}: expected >= 0 (0: no test views), got {split['test_every']}")
        if split.get("split_file") is not None and not split["split_file"].is_file():
            raise InputError(f"--split-file: {split['split_file']} does not exist")
        if depth_type not in (None, "z", "ray"):
            raise InputError(f"--depth-type: expected z or ray, got {depth_type!r}")
        if background not in (None, "zero", "max"):
            raise InputError(f"--background: expected zero or max, got {background!r}")
        if not dataset.exists():
            raise InputError(f"dataset {dataset} does not exist")
        if dataparser_transforms is not None and not dataparser_transforms.is_file():
            raise InputError(f"--dataparser-transforms: {dataparser_transforms} does not exist")
        with _progress_bar(f"importing {tool} renders", "view") as progress:
            scene = import_renders(dataset, renders, output, tool=tool, depth_type=depth_type,
                                   depth_scale=depth_scale, depth_units=depth_units,
                                   dataparser_transforms=dataparser_transforms, background=background,
                                   progress=progress, skip_missing=skip_missing, check_depth=not force,
                                   hints={"skip_missing": "--skip-missing", "check_depth": "--force"}, **split)
        skipped = scene.meta.get("skipped_views") or []
        if skipped:
            typer.echo(f"warning: skipped {len(skipped)} views without a render or depth: {', '.join(skipped)}",
                       err=True)
        typer.echo(f"wrote {scene!r}", err=True)
        _warn_unusable(scene)
        typer.echo(str(output))


DepthTypeOpt = Annotated[str | None, typer.Option("--depth-type", help=(
    "ray: distance along the ray (nerfacto, gsplat ED); z: along the optical axis (splatfacto, gsplat RGB+ED). "
    "Default: ray for nerfstudio, z for gsplat."))]
DepthScaleOpt = Annotated[float, typer.Option(
    "--depth-scale", help="Multiply stored depth by this (0.001 for millimetre PNGs).")]
BackgroundOpt = Annotated[str | None, typer.Option("--background", help=(
    "What no-surface pixels hold: zero, or max (the map's maximum; gsplat's default). Made unknown."))]
SkipMissingOpt = Annotated[bool, typer.Option("--skip-missing", help=(
    "Import the views that have both a render and a depth, skipping (with a warning) those missing one; "
    "without it a missing file is an error naming it."))]
ImportForceOpt = Annotated[bool, typer.Option("--force", help=(
    "Import with the --depth-type given even when the depths of neighbouring views disagree under it "
    "and agree under the other type (checked by reprojecting a few hundred pixels)."))]
HOLD_HELP = ("COLMAP dataset: every N-th view in name order is a test view, the split of the 3DGS and gsplat "
             "trainers' --eval (Inria's --eval, gsplat's default --test-every 8); 0: none, every view trains.")
DataparserOpt = Annotated[Path | None, typer.Option("--dataparser-transforms", help=(
    "The trained model's dataparser_transforms.json: kept in the scene for camera paths from nerfstudio's viewer."))]


@app.command("import-nerfstudio")
def import_nerfstudio(
    dataset: Annotated[Path, typer.Argument(help="nerfstudio dataset: folder with transforms.json and the photos.")],
    renders: Annotated[Path, typer.Option(
        "--renders", help="ns-render dataset output (<split>/rgb, <split>/raw-depth).")],
    output: Annotated[Path, typer.Option("--output", help="Scene folder to write.")],
    depth_type: DepthTypeOpt = None,
    depth_scale: DepthScaleOpt = 1.0,
    depth_units: Annotated[str, typer.Option("--depth-units", help=(
        "dataset: depth in the dataset's pose units (ns-render divides by the dataparser scale); "
        "model: in the model's world (divided by the scale here)."))] = "dataset",
    dataparser_transforms: DataparserOpt = None,
    background: BackgroundOpt = None,
    skip_missing: SkipMissingOpt = False,
    force: ImportForceOpt = False,
) -> None:
    """Turn a nerfstudio dataset plus `ns-render dataset` output into a scene folder (z-depth, pose units)."""
    _import_command("nerfstudio", dataset, renders, output, depth_type, depth_scale, depth_units,
                    dataparser_transforms, background, skip_missing, force)


@app.command("import-gsplat")
def import_gsplat(
    dataset: Annotated[Path, typer.Argument(help=(
        "Dataset with the photos and their poses: COLMAP (images/ + sparse/0/, .bin or .txt) or "
        "transforms.json (nerfstudio style)."))],
    renders: Annotated[Path, typer.Option("--renders", help=(
        "Folder with rgb/ and depth/ (.npy, .npy.gz, .npz, 16-bit PNG, float TIFF), files named by view; or an "
        "Inria model folder whose <split>/ours_<iter>/ holds renders/ and a depth/ folder (numbered)."))],
    output: Annotated[Path, typer.Option("--output", help="Scene folder to write.")],
    depth_type: DepthTypeOpt = None,
    depth_scale: DepthScaleOpt = 1.0,
    background: BackgroundOpt = None,
    images: Annotated[str, typer.Option("--images", help=(
        "COLMAP dataset: the image folder (images_2 for gsplat's --data-factor 2)."))] = "images",
    hold: Annotated[int | None, typer.Option("--hold", help=(
        HOLD_HELP + " Default 8; Inria's numbered renders: their own split (test renders: 8, none: 0). A "
        "transforms.json dataset keeps its own split unless --hold is given."))] = None,
    eval_split: Annotated[bool, typer.Option("--eval", help=(
        "Same as --hold 8, now the default (kept for old scripts)."))] = False,
    test_every: Annotated[int | None, typer.Option("--test-every", help=(
        "Same as --hold N (kept for old scripts)."))] = None,
    split_file: Annotated[Path | None, typer.Option("--split-file", help=(
        'Test views by name: JSON {"train": [...], "test": [...]} or one name per line '
        "(Inria's sparse/0/test.txt). Overrides --hold."))] = None,
    skip_missing: SkipMissingOpt = False,
    force: ImportForceOpt = False,
) -> None:
    """Turn gsplat renders + expected depth (and the dataset's poses) into a scene folder."""
    with _errors():
        if hold is not None and test_every is not None and hold != test_every:
            raise InputError(f"--hold {hold} and --test-every {test_every} disagree: give one (--hold)")
    flag = "--hold" if hold is not None else "--test-every"
    test_every = hold if hold is not None else test_every
    if test_every is None and eval_split:
        test_every = 8
    _import_command("gsplat", dataset, renders, output, depth_type, depth_scale, "dataset", None, background,
                    skip_missing, force, images=images, test_every=test_every, split_file=split_file,
                    hold_flag=flag)


@app.command("import-3dgs")
def import_3dgs_command(
    dataset: Annotated[Path, typer.Argument(
        help="The dataset the splats were trained on: COLMAP (images/ + sparse/0) or transforms.json.")],
    ply: Annotated[Path | None, typer.Option("--ply", help=(
        "Inria 3DGS point_cloud.ply (point_cloud/iteration_30000/); default: --model's latest."))] = None,
    output: Annotated[Path, typer.Option(
        "--output", help="Scene folder to write (renders, z-depth, opacity, photos).")] = ...,
    path: Annotated[Path | None, typer.Option("--path", help=(
        "Also render this camera path (any enhance-path --cameras format: camera_path.json, transforms-style, "
        "cameras.json (read in image-name order, at the dataset views' size), COLMAP images.txt) into "
        "OUTPUT/path for enhance-path. OUTPUT already holding this import: only the path is rendered."))] = None,
    backend: Annotated[str, typer.Option(
        "--backend", help="auto (gsplat with CUDA, else CPU), cpu or gsplat.")] = "auto",
    hold: Annotated[int, typer.Option("--hold", help=HOLD_HELP + " A transforms.json dataset keeps its own "
                                      "split.")] = 8,
    images: Annotated[str, typer.Option(
        "--images", help="COLMAP: image folder in the dataset (images_2 for half size).")] = "images",
    dataparser_transforms: Annotated[Path | None, typer.Option("--dataparser-transforms", help=(
        "splatfacto exports: nerfstudio's dataparser_transforms.json (the .ply is in its model's world)."))] = None,
    depth_threshold: Annotated[float, typer.Option(
        "--depth-threshold", help="Depth is known where the splats' opacity reaches this.")] = 0.5,
    model: Annotated[Path | None, typer.Option("--model", help=(
        "Inria's model folder (cameras.json, point_cloud/iteration_*/point_cloud.ply): the latest iteration's "
        ".ply, and without --path a smooth fly-through through the dataset's views into OUTPUT/path."))] = None,
    frames: Annotated[int, typer.Option(
        "--frames", help="--model without --path: frames of the fly-through (24 per second).")] = 120,
    force: Annotated[bool, typer.Option("--force", help=(
        "Render even when the splats do not lie in the dataset's views (another world: gsplat's normalised "
        "one, a splatfacto export without --dataparser-transforms) or the path sees none of them; the "
        "problem is printed as a warning."))] = False,
) -> None:
    """Render a trained 3DGS scene's .ply at every dataset view (RGB, z-depth, opacity) into a scene folder."""
    from roguenerf.splats.importer import PATH_CAMERAS, PATH_FOLDER, import_3dgs

    with _errors():
        if ply is None and model is None:
            raise InputError("give the splats: --ply point_cloud.ply or --model MODEL (Inria's model folder)")
        if ply is not None and not ply.is_file():
            raise InputError(f"--ply: {ply} does not exist")
        if path is not None and not path.is_file():
            raise InputError(f"--path: {path} does not exist")
        if not 0 <= depth_threshold <= 1:
            raise InputError(f"--depth-threshold: expected 0..1, got {depth_threshold}")
        if frames < 2:
            raise InputError(f"--frames: expected at least 2, got {frames}")
        fly = frames if model is not None and path is None else None
        with _progress_bar("rendering splats", "view") as progress:
            scene = import_3dgs(dataset, ply, output, backend=backend, hold=hold, images=images,
                                dataparser_transforms=dataparser_transforms, depth_threshold=depth_threshold,
                                camera_path=path, model=model, fly_through_frames=fly, force=force,
                                messages=lambda line: typer.echo(line, err=True), progress=progress)
        typer.echo(f"wrote {scene!r}", err=True)
        if path is not None or fly is not None:
            frames_dir = output / PATH_FOLDER
            cams = frames_dir / PATH_CAMERAS
            video = output.with_name(output.name + "_video")
            typer.echo(f"next: roguenerf enhance-path {output} --frames {frames_dir} --cameras {cams} "
                       f"--output {video}", err=True)
        typer.echo(str(output))


@app.command("enhance-path")
def enhance_path_command(
    scene_dir: Annotated[Path, typer.Argument(help="Scene folder (the training photos, poses, renders, depths).")],
    frames: Annotated[Path, typer.Option(
        "--frames", help="Folder of the path's renders and depths (rgb/ + depth/, or NAME.png + NAME.npy).")],
    cameras: Annotated[Path, typer.Option("--cameras", help=(
        "nerfstudio camera_path.json, a transforms-style list of cameras, Inria 3DGS cameras.json, or COLMAP "
        "images.txt / images.bin (cameras file beside it)."))],
    output: Annotated[Path, typer.Option(
        "--output", help="Output folder: frames/, enhanced.mp4, side_by_side.mp4, flicker.json.")],
    checkpoint: CheckpointOpt = None,
    neighbours: NeighboursOpt = None,
    align: AlignOpt = True,
    colour: ColourOpt = True,
    trust: TrustOpt = True,
    quality: Annotated[int, typer.Option("--quality", help="x264 CRF, 0 (lossless) .. 51; 18-23 look good.")] = 20,
    fps: Annotated[float | None, typer.Option(
        "--fps", help="Frame rate (default: the camera path's, else 24).")] = None,
    depth_type: Annotated[str, typer.Option("--depth-type", help="z or ray (distance along the ray, nerfacto).")] = "z",
    depth_scale: DepthScaleOpt = 1.0,
    background: Annotated[str, typer.Option(
        "--background", help="No-surface pixels hold zero, or max (gsplat).")] = "zero",
    dataparser_transforms: Annotated[Path | None, typer.Option("--dataparser-transforms", help=(
        "Maps a nerfstudio camera path (model world) to the scene's poses; default: the scene folder's "
        "dataparser_transforms.json when there is one."))] = None,
    no_video: Annotated[bool, typer.Option("--no-video", help="Write the frames and flicker.json only.")] = False,
    force: Annotated[bool, typer.Option("--force", help=(
        "Enhance the path even when its cameras do not fit the scene (far from its cameras, or seeing none "
        "of its training photos: another coordinate space, missing dataparser transforms, OpenGL vs OpenCV); "
        "the problem is printed as a warning."))] = False,
) -> None:
    """Enhance every frame of a camera path; write the frames, an MP4, a side-by-side MP4 and the flicker.

    Resumable: run the same command again after an interruption.
    """
    from roguenerf.data.exports import DATAPARSER_FILE, DataparserTransform
    from roguenerf.inference import SceneEnhancer
    from roguenerf.trajectory import FLICKER_FILE, check_path_output, enhance_path, read_camera_path

    with _errors():
        if depth_type not in ("z", "ray"):
            raise InputError(f"--depth-type: expected z or ray, got {depth_type!r}")
        if background not in ("zero", "max"):
            raise InputError(f"--background: expected zero or max, got {background!r}")
        if not 0 <= quality <= 51:
            raise InputError(f"--quality: expected 0..51 (x264 CRF), got {quality}")
        if fps is not None and not (math.isfinite(fps) and 0 < fps <= 240):
            raise InputError(f"--fps: expected a number in (0, 240], got {fps}")
        if not no_video:
            from roguenerf.video import require_av

            require_av()
        # The output folder and the cameras (every pose checked) first: before the scene and model load.
        check_path_output(output)
        camera_path = read_camera_path(cameras)
        if camera_path.source == "nerfstudio":
            parser_file = dataparser_transforms or (scene_dir / DATAPARSER_FILE)
            if parser_file.is_file():
                camera_path = read_camera_path(cameras, dataparser=DataparserTransform.read(parser_file))
            elif dataparser_transforms is not None:
                raise InputError(f"--dataparser-transforms: {dataparser_transforms} does not exist")
            else:
                typer.echo("note: nerfstudio camera path and no dataparser_transforms.json: its poses are "
                           "taken as the scene's own", err=True)
        scene = _load_scene(scene_dir)
        ckpt = _checkpoint_path(checkpoint)
        from roguenerf.checkpoint import load_checkpoint

        model, _meta = load_checkpoint(ckpt)
        enhancer = SceneEnhancer(scene, model, options=_enhance_options(neighbours, align, colour, trust))
        stat = ckpt.stat()
        with _progress_bar(f"enhancing {len(camera_path)} frames", "frame") as progress:
            result = enhance_path(scene, enhancer, camera_path, frames, output, depth_type=depth_type,
                                  depth_scale=depth_scale, background=background, video=not no_video,
                                  quality=quality, fps=fps,
                                  checkpoint_id=f"{ckpt.resolve()}:{stat.st_size}:{stat.st_mtime_ns}"
                                  + ("" if align else ":no-align") + ("" if colour else ":no-colour"),
                                  progress=progress, force=force, force_hint="--force")
        for warning in result.warnings:
            typer.echo(f"warning: {warning}", err=True)
        f, p = result.flicker["flicker"], result.flicker["psnr"]
        resumed = result.frames - result.enhanced_now
        typer.echo(f"enhanced {result.enhanced_now} frames in {result.seconds:.1f} s"
                   + (f" ({resumed} already done)" if resumed else "")
                   + f"; neighbour features cached for {result.cached_views} training photos", err=True)
        if f["render"] is not None:
            typer.echo(f"flicker (mean |frame t reprojected into t+1 - frame t+1| on valid pixels): render "
                       f"{f['render']:.4f}, enhanced {f['enhanced']:.4f} (x{f['ratio']:.3f})"
                       + (f", photos {f['photo']:.4f}" if f["photo"] is not None else ""), err=True)
        if p["frames_with_photos"]:
            typer.echo(f"{p['frames_with_photos']} frames have photos: PSNR render {p['render']:.2f} dB, enhanced "
                       f"{p['enhanced']:.2f} dB, mean gain {p['mean_gain_db']:+.2f} dB", err=True)
        typer.echo(f"wrote {output / FLICKER_FILE}", err=True)
        typer.echo(str(result.video or output))


# What the top-level CLI (package roguecli, which adds `serve` and `make-pairs` from the
# packages above this one) shares with these commands: one error format, logging, bars, budgets.
handle_errors, fail, setup_logging, progress_bar, check_budget = (
    _errors, _fail, _setup_logging, _progress_bar, _check_budget)

ABOVE_THE_LIBRARY = {"serve": "the service", "make-pairs": "the roguefit data tool"}
"""Commands of the ``roguenerf`` console script that live above the library (package roguecli)."""


def main() -> None:
    """Entry point of ``python -m roguenerf``: the library's commands.

    The ``roguenerf`` console script is :func:`roguecli.main`, which adds ``serve`` and
    ``make-pairs``; asked for one of those here, say where it is (the library imports nothing
    above it)."""
    command = sys.argv[1] if len(sys.argv) > 1 else None
    if command in ABOVE_THE_LIBRARY:
        typer.echo(f"error: `{command}` runs {ABOVE_THE_LIBRARY[command]}, above the library: use the "
                   f"console script (`roguenerf {command}`) or `python -m roguecli {command}`", err=True)
        raise SystemExit(2)
    run_app(app)


if __name__ == "__main__":
    main()
