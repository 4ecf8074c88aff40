"""Training commands: ``finetune`` (one scene) and ``pretrain`` (many scenes and/or toy ones).

Their defaults come from the library's training configuration (:mod:`roguenerf.training.config`,
which loads without torch), not restated here.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

import typer

from roguecli.common import (
    CheckpointOpt,
    Flags,
    NeighboursOpt,
    SeedOpt,
    check_budget,
    checkpoint_file,
    handle_errors,
    open_scene,
    setup_logging,
    takes_flags,
)
from roguenerf.errors import InputError
from roguenerf.training.config import COMPONENTS, CPU_LR, CPU_MINUTES, GPU_LR, GPU_MINUTES, TrainConfig


def _short(x: float) -> str:
    """A default as the help states it: 10.0 -> 10, 5e-4 -> 5e-4."""
    if x >= 1:
        return f"{x:g}"
    mantissa, exponent = f"{x:e}".split("e")
    return f"{mantissa.rstrip('0').rstrip('.')}e{int(exponent)}"


MinutesOpt = Annotated[float | None, typer.Option("--minutes", help=(
    f"Training budget in minutes (> 0). Default without --steps: {_short(CPU_MINUTES)} minutes on a CPU, "
    f"{_short(GPU_MINUTES)} on a GPU."))]
StepsOpt = Annotated[int | None, typer.Option("--steps", help="Training budget in optimiser steps (> 0).")]
WithoutOpt = Annotated[list[str] | None, typer.Option(
    "--without", help=f"Switch a component off (repeatable): {', '.join(COMPONENTS)}.")]
VariantOpt = Annotated[str | None, typer.Option("--variant", help="Model variant: nano, micro, T, S, B.")]
CropOpt = Annotated[int | None, typer.Option("--crop", help="Random crop side in pixels (default per machine).")]
BatchOpt = Annotated[int, typer.Option("--batch", help="Crops per optimiser step.")]
VggOpt = Annotated[Path | None, typer.Option(
    "--vgg-weights", help="Local torchvision VGG-19 weights for the perceptual loss (else L1 alone).")]
LrOpt = Annotated[float | None, typer.Option("--lr", help=(
    f"Adam learning rate (default: {_short(CPU_LR)} on a CPU, chosen by measured gain per minute; "
    f"{_short(GPU_LR)} on a GPU, the paper's)."))]
LrScheduleOpt = Annotated[str | None, typer.Option(
    "--lr-schedule", help="cosine (the lr falls to 0 over the budget; the default) or constant.")]
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

NeighbourRendersOpt = Annotated[float | None, typer.Option(
    "--neighbour-renders", help="Share of the crops (0-1) whose target render and depth are the nearest training "
                                "view's render drawn into the view's camera, so the training views look like novel "
                                "views (default: the plan's).")]


@dataclass(frozen=True)
class TrainFlags(Flags):
    """The training options of finetune and pretrain (finetune has no ``--batch``);
    :meth:`config` builds their :class:`TrainConfig`."""

    minutes: MinutesOpt = None
    steps: StepsOpt = None
    without: WithoutOpt = None
    variant: VariantOpt = None
    crop: CropOpt = None
    batch: BatchOpt = TrainConfig.batch
    vgg_weights: VggOpt = None
    seed: SeedOpt = TrainConfig.seed
    neighbours: NeighboursOpt = None
    lr: LrOpt = None
    lr_schedule: LrScheduleOpt = None

    def config(self, *, evaluate: bool, **extra) -> TrainConfig:
        """The validated config: these options, ``evaluate`` and a command's own (``extra``)."""
        check_budget(self.steps, self.minutes, evaluate_hint=True)
        without = tuple(self.without or ())
        for w in without:
            if w not in COMPONENTS:
                raise InputError(f"--without: expected one of {', '.join(COMPONENTS)}, got {w!r}")
        return TrainConfig(steps=self.steps, minutes=self.minutes, crop=self.crop, batch=self.batch,
                           vgg_weights=self.vgg_weights, seed=self.seed, variant=self.variant, without=without,
                           num_neighbours=self.neighbours, evaluate=evaluate, lr=self.lr,
                           lr_schedule=self.lr_schedule, **extra).validate()


def _report_training(result) -> None:
    typer.echo(f"saved {result.checkpoint} after {result.steps} steps in {result.seconds:.0f} s "
               f"(final loss {result.final_loss:.4f}, loss {result.loss_kind})", err=True)
    transfer = result.config.get("transfer")
    if transfer:
        typer.echo(f"weights from the checkpoint: {transfer['loaded']} tensors loaded; dropped: "
                   f"{', '.join(transfer['dropped']) or 'nothing'}; fresh: {', '.join(transfer['fresh']) or 'nothing'}"
                   f"; widened (new inputs at zero weight): {', '.join(transfer.get('widened', [])) or 'nothing'}",
                   err=True)
    guard = getattr(result, "guard", None)
    if guard and guard.get("views"):
        verdict = "kept" if guard["kept"] else "not kept: the checkpoint holds the starting weights"
        typer.echo(f"fine-tuned weights {verdict}; on {len(guard['views'])} training views drawn like novel views "
                   f"they gain {guard['tuned_mean_db']:+.2f} dB, the starting weights {guard['start_mean_db']:+.2f} dB",
                   err=True)
    if result.before and result.after:
        b, a = result.before, result.after
        typer.echo(f"test PSNR: render {b['render']['psnr']:.2f} dB, enhanced before {b['enhanced']['psnr']:.2f} dB, "
                   f"after {a['enhanced']['psnr']:.2f} dB", err=True)


@takes_flags(omit=("batch",))
def finetune(
    scene_dir: Annotated[Path, typer.Argument(help="Scene folder (transforms.json with renders and depths).")],
    output: Annotated[Path, typer.Option("--output", help="Output directory (model + resumable state).")],
    checkpoint: CheckpointOpt = None,
    scratch: Annotated[bool, typer.Option("--scratch", help="Start from random weights, not a checkpoint.")] = False,
    *,
    train: TrainFlags,
    freeze_neighbour_encoder: FreezeOpt = None,
    render_warp: RenderWarpOpt = None,
    neighbour_renders: NeighbourRendersOpt = None,
    depth_noise: DepthNoiseOpt = None,
    no_eval: Annotated[bool, typer.Option("--no-eval", help="Skip the before/after test evaluation.")] = False,
    guard: Annotated[bool, typer.Option(
        "--guard", help="Keep the fine-tuned weights only where they enhance training views drawn like novel "
                        "views better than the starting weights (off by default: it refused lego's fine-tune, "
                        "which helps there).")] = False,
) -> None:
    """Fine-tune the enhancer on one scene's training views; resumes from OUTPUT when interrupted."""
    from roguenerf.training import finetune as run_finetune

    setup_logging()
    with handle_errors():
        if scratch and checkpoint is not None:
            raise InputError("give either --checkpoint or --scratch, not both")
        config = train.config(evaluate=not no_eval, freeze_neighbour_encoder=freeze_neighbour_encoder,
                              render_warp=render_warp, depth_noise=depth_noise,
                              neighbour_renders=neighbour_renders, guard=guard)
        from roguenerf.training.loop import check_training_output

        check_training_output(output)
        scene = open_scene(scene_dir)
        start = None if scratch else checkpoint_file(checkpoint)
        result = run_finetune(scene, output, checkpoint=start, config=config)
        _report_training(result)
        typer.echo(str(result.checkpoint))


@takes_flags
def pretrain(
    scene_dirs: Annotated[list[Path] | None, typer.Argument(help="Scene folders to pre-train on.")] = None,
    output: Annotated[Path, typer.Option("--output", help="Output directory (model + resumable state).")] = ...,
    toy: Annotated[int, typer.Option("--toy", help="Add N generated toy scenes (degraded renders).")] = 0,
    checkpoint: Annotated[Path | None, typer.Option("--checkpoint", help="Start from these weights.")] = None,
    *,
    train: TrainFlags,
    held_out_from: Annotated[list[Path] | None, typer.Option(
        "--held-out-from", help="Also train on this scene folder's held-out views (repeatable; added to the "
        "scenes if missing): renders of views its radiance field never saw, with training-view neighbours. "
        "Never for a scene you evaluate on.")] = None,
    held_out_share: Annotated[float, typer.Option(
        "--held-out-share", help="Chance that a target of a --held-out-from scene is a held-out view.",
    )] = TrainConfig.held_out_share,
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

    setup_logging()
    with handle_errors():
        if toy < 0:
            raise InputError(f"--toy: expected >= 0, got {toy}")
        noise = None
        if neighbour_pose_noise is not None:
            try:
                noise = tuple(float(x) for x in neighbour_pose_noise.split(","))
            except ValueError:
                raise InputError("--neighbour-pose-noise: expected DEG,SHARE numbers, "
                                 f"got {neighbour_pose_noise!r}") from None
        config = train.config(evaluate=False, held_out_share=held_out_share, pool_spread=pool_spread,
                              neighbour_pose_noise=noise, depth_noise=depth_noise)
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
        scenes = [open_scene(d) for d in dirs]
        scenes += make_toy_scenes(output / TOY_FOLDER, toy, seed=train.seed)
        if not scenes:
            raise InputError("no scenes to pre-train on: give SCENE_DIR arguments and/or --toy N")
        if checkpoint is not None:
            from roguenerf.checkpoint import resolve_checkpoint

            checkpoint = resolve_checkpoint(checkpoint)  # a file, or the folder a run wrote
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
