"""Training hyper-parameters, progress reports, results, and the per-machine plan."""

from __future__ import annotations

import dataclasses
import math
import numbers
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

from roguenerf.errors import InputError

if TYPE_CHECKING:  # torch loads when a plan is made, not on import: the CLI's --help reads these defaults
    import torch

NEIGHBOUR_ENCODINGS = ("window", "whole")
"""How conv_H sees the neighbour photos during training (TrainConfig.neighbour_encoding)."""
COMPONENTS = ("neighbours", "alignment", "refinement", "attention")
"""Switchable parts of the enhancer (``--without``); pre-training is switched by the checkpoint."""

CPU_CROP = 64
GPU_CROP = 512
CPU_NEIGHBOURS = 2
"""Kept after the re-plan (issue 12): with crop windows more neighbours are cheap, but on the
unseen real scenes the views made worse get worse with each added neighbour (mary_rose 048:
-0.01, -0.42, -0.66 dB with 1, 2, 4) while the mean gains little (docs/results.md)."""
CPU_VARIANT = "micro"
"""On a CPU, micro at 64 px crops trains at ~1.8 steps/s on 2 busy cores (nano: ~0.3 at 96 px)."""
CPU_MINUTES = 10.0
CPU_LR = 5e-4
"""Re-planned (issue 12) from 1e-4: in one sitting from the shipped checkpoint, the gain after
10 minutes was higher on both unseen real scenes (+0.04, +0.02 dB) and on lego (+0.10 dB); after
1 and 3 minutes it was higher on lego and mixed on the real scenes (docs/results.md)."""
GPU_LR = 1e-4
LR_SCHEDULES = ("cosine", "constant")
"""How the learning rate moves over a run's budget (TrainConfig.lr_schedule, :func:`lr_factor`)."""
LR_SCHEDULE = "cosine"
"""The plan's schedule on any device. In one sitting, 1600 steps from the shipped checkpoint,
cosine against constant (lr 5e-4): dtu_scan37 +0.77 against +0.64 dB, mary_rose +1.48
against +1.04, lego +1.45 against +1.51 (docs/results.md). Single runs on scenes where a run's
gain varies by ~0.3 dB from run to run; a constant lr also ends wherever its last steps left it."""
FREEZE_NEIGHBOUR_ENCODER = False
"""Fine-tuning's default for :attr:`TrainConfig.freeze_neighbour_encoder`. Frozen, a step is 1.3x
faster (5 neighbours), but 10-minute fine-tunes from the shipped checkpoint gained no more: mary_rose
+1.43 against +1.43 dB, dtu_scan37 +0.73 against +0.73, lego +1.44 against +1.48
(bench/results/frozen_encoder_paired.json, docs/results.md)."""
FEATURE_CACHE_BYTES = 2 * 1024**3
"""Largest cache of frozen neighbour features (float32, training views x F x H x W) kept in memory."""
RENDER_WARP = 0.0
"""Fine-tuning's default for :attr:`TrainConfig.render_warp` (0: the renders as they are). Off by
default: in one sitting, 3-minute fine-tunes with 4 px gained more on the four unseen real-scene
fits (dtu_scan37 coarse +0.12 dB, fine +0.10; mary_rose +0.01, +0.02) but 0.17 dB less on lego,
whose field renders its novel views about as well as its training views (docs/results.md)."""
NEIGHBOUR_RENDERS = 0.0
"""Fine-tuning's default for :attr:`TrainConfig.neighbour_renders` (0: every crop its own render).
Off by default: half the crops drawn gained 0.06-0.15 dB on five fields that render their
training views better than their novel views (3 min on the choice half, 10 min on the report
half) but cost lego 0.28 dB after 10 minutes side by side (+1.34 against +1.62) and ollie's grid
field 0.06 (docs/broad.md, *Fine-tuning pairs drawn from the nearest view*)."""
MAX_RENDER_WARP = 32.0
MAX_DEPTH_NOISE = 2.0
"""Bound of :attr:`TrainConfig.depth_noise` (exp(2): depths off by a factor up to 7.4)."""
MAX_POSE_NOISE_DEG = 10.0
MAX_POSE_NOISE_SHARE = 1.0
"""Bounds of :attr:`TrainConfig.neighbour_pose_noise` (a pose error past these is no longer
"a little wrong")."""
GPU_MINUTES = 60.0
"""The paper fine-tunes for one hour per scene on GPUs."""
CPU_PLAN_WHY = ("CPU defaults chosen by measured gain after 1, 3 and 10 min on unseen real scenes and lego, "
                "bench/results/real_scenes.csv; the lr decays to 0 by the end of the budget")
GPU_PLAN_WHY = "GPU defaults: the paper's 512 px crops, the checkpoint's neighbours, 60 min"


def validate_budget(steps, minutes, *, required: bool = False, lenient: bool = False,
                    names: tuple[str, str] = ("steps", "minutes")) -> None:
    """Check a training budget; raise :class:`InputError` naming the field.

    The rules, for every entry point (``TrainConfig``, the CLI's ``--steps``/``--minutes``, the
    API's ``POST /scenes/{id}/finetune`` body): ``steps`` an integer > 0, ``minutes`` a finite
    number > 0, and not both at once. Neither means the plan's default (CPU_MINUTES or
    GPU_MINUTES) unless ``required`` (the API: a queued job states its own length).
    ``lenient``: what the library's :class:`TrainConfig` takes beyond a request: 0 (save the
    starting weights and stop) and both at once (whichever runs out first).
    ``names``: how the caller spells the two fields (the CLI: ``("--steps", "--minutes")``).
    """
    steps_name, minutes_name = names
    floor = ">= 0" if lenient else "> 0"
    if steps is not None and minutes is not None and not lenient:
        raise InputError(f"give either {minutes_name} or {steps_name}, not both")
    if steps is None and minutes is None and required:
        raise InputError(f"give exactly one of {steps_name} or {minutes_name}")
    if steps is not None:
        if isinstance(steps, bool) or not isinstance(steps, numbers.Integral):
            raise InputError(f"{steps_name}: expected an integer {floor}, got {steps!r}")
        if steps < 0 or (steps == 0 and not lenient):
            raise InputError(f"{steps_name}: expected {floor}, got {steps}")
    if minutes is not None:
        if isinstance(minutes, bool) or not isinstance(minutes, numbers.Real):
            raise InputError(f"{minutes_name}: expected a number {floor}, got {minutes!r}")
        if not math.isfinite(minutes):
            raise InputError(f"{minutes_name} must be a finite number {floor}, got {minutes}")
        if minutes < 0 or (minutes == 0 and not lenient):
            raise InputError(f"{minutes_name}: expected a number {floor}, got {minutes:g}")


@dataclass
class TrainConfig:
    """What to train and for how long. ``None`` fields are chosen by :func:`plan_training`."""

    steps: int | None = None
    """Stop after this many optimiser steps in total (a resumed run counts the saved ones)."""
    minutes: float | None = None
    """Stop after this much training wall-clock time in total (resumed runs included)."""
    crop: int | None = None
    """Side of the square random crops (paper: 512; CPU: 128)."""
    batch: int = 4
    lr: float | None = None
    """Adam learning rate; None: the plan's (CPU_LR or GPU_LR)."""
    vgg_weights: Path | str | None = None
    """Local torchvision VGG-19 state dict (.safetensors or .pth); without it the loss is L1 alone."""
    checkpoint_every_s: float = 60.0
    """Seconds between periodic checkpoints (0: after every step)."""
    num_neighbours: int | None = None
    """Neighbours per target; default: the model's, capped at 2 on a CPU."""
    seed: int = 0
    variant: str | None = None
    """Model variant when training from scratch (or to override the checkpoint's)."""
    without: tuple[str, ...] = ()
    """Components switched off for ablations: neighbours, alignment, refinement, attention."""
    device: str | None = None
    """"cpu", "cuda", ...; default: CUDA when available."""
    evaluate: bool = True
    """Fine-tuning only: evaluate the scene's test views before and after (TrainResult.before/after)."""
    guard: bool = False
    """Fine-tuning only: keep the fine-tuned weights only where they enhance training views drawn
    like novel views better than the starting weights (:mod:`roguenerf.training.guard`); where
    they do not, the output checkpoint holds the starting weights (the resumable state keeps the
    fine-tuned ones). ``TrainResult.guard`` says what was measured. Off by default: it refused
    lego's 10-minute fine-tune, which gains 0.57 dB on lego's held-out views (docs/broad.md,
    *A fine-tune kept only where it helps*)."""
    progress_bar: bool = True
    """Show a tqdm bar on stderr (loss, steps/s, ETA)."""
    held_out_share: float = 0.5
    """Pre-training only: the chance that a target of a scene given in ``held_out_scenes`` is one
    of its held-out views (:func:`~roguenerf.training.loop.pretrain`); no effect otherwise."""
    lr_schedule: str | None = None
    """"cosine": the lr falls from ``lr`` to 0 along a half cosine over the budget (steps, or
    minutes of training time; the one that runs out first); "constant": ``lr`` throughout.
    None: the plan's (LR_SCHEDULE). A resumed run keeps its schedule and position in it."""
    freeze_neighbour_encoder: bool | None = None
    """True: conv_H (the neighbour-photo encoder) keeps its starting weights, so every training
    view's features are encoded once before the first step (when they fit in
    ``FEATURE_CACHE_BYTES``; otherwise each step encodes its windows without gradient) and steps
    skip conv_H's forward and backward. False: conv_H is trained with the rest. None: the plan's
    (FREEZE_NEIGHBOUR_ENCODER for fine-tuning; pre-training always trains it)."""
    pool_spread: bool | None = None
    """Build the model with (True) or without (False) :attr:`EnhancerConfig.pool_spread`; from a
    checkpoint without it, conv_merge's new inputs start at zero weight (the same function).
    None: the checkpoint's, or the variant's."""
    render_warp: float | None = None
    """Fine-tuning: the largest shift (pixels) of a smooth random displacement put on the
    target render and depth of half of the crops (:func:`~roguenerf.training.batches.warp_renders`):
    the large-scale errors a field's novel views have and its training views lack. 0: none.
    None: the plan's (RENDER_WARP); pre-training: 0."""
    neighbour_renders: float | None = None
    """The share of training-view crops whose render and depth are the nearest other training
    view's render and depth drawn into their camera
    (:meth:`~roguenerf.training.loop.SceneData.draw_from_neighbours`, a forward warp), their own
    where nothing lands. A field renders its training views better than any novel view; drawn
    from another view, a training view carries what a novel view does (geometry errors and
    floaters seen from a new camera, resampling blur, edges) while its photo stays the target.
    0: none. None: the plan's (NEIGHBOUR_RENDERS for fine-tuning; pre-training 0)."""
    depth_noise: float | None = None
    """The largest log-depth error (e.g. 0.3: depths up to x1.35 or /1.35) put on the target depth
    of half of the crops as a smooth random field
    (:func:`~roguenerf.training.batches.corrupt_depths`); the render and the photo target are
    unchanged, so the neighbours' reprojections land wrong where the target stays the photo: the
    model learns to fall back on the render where the geometry is off. 0 or None: none."""
    neighbour_pose_noise: tuple[float, float] | None = None
    """``(degrees, share)``: every neighbour of every training target gets its own random pose
    error (:func:`~roguenerf.geometry.noise.perturb_poses`: a rotation about its centre and a
    displacement), so the model learns that a reprojection can be off, as a user's poses are.
    Each target draws its own level ``u`` uniformly in [0, 1]: its neighbours' errors have RMS
    ``u * degrees`` and ``u * share`` of the scene's camera spread, so one run sees every size
    from exact poses up to these (a model trained at one size only learns to distrust all).
    None (or zeros): the poses as they are, and the batches are those of a run without the
    option."""
    neighbour_encoding: str = "window"
    """"window": conv_H encodes only the window of each neighbour photo that a target crop can
    see; "whole": every neighbour photo whole (the former path, kept for comparison). Same
    loss and gradients (:mod:`roguenerf.training.batches`)."""

    validate_budget = staticmethod(validate_budget)
    """The training budget's rules (:func:`validate_budget`): the CLI and the API call it too."""

    def validate(self) -> TrainConfig:
        validate_budget(self.steps, self.minutes, lenient=True)
        if self.crop is not None and int(self.crop) < 8:
            raise InputError(f"crop: expected >= 8 pixels, got {self.crop}")
        if int(self.batch) < 1:
            raise InputError(f"batch: expected >= 1, got {self.batch}")
        if self.lr is not None and not float(self.lr) > 0:
            raise InputError(f"lr: expected > 0, got {self.lr}")
        if not 0.0 <= float(self.held_out_share) <= 1.0:
            raise InputError(f"held_out_share: expected a probability in [0, 1], got {self.held_out_share}")
        if self.render_warp is not None and not 0.0 <= float(self.render_warp) <= MAX_RENDER_WARP:
            raise InputError(f"render_warp: expected a shift in [0, {MAX_RENDER_WARP:g}] pixels, "
                             f"got {self.render_warp}")
        if self.neighbour_renders is not None and not 0.0 <= float(self.neighbour_renders) <= 1.0:
            raise InputError(f"neighbour_renders: expected a share in [0, 1], got {self.neighbour_renders}")
        if self.num_neighbours is not None and int(self.num_neighbours) < 0:
            raise InputError(f"num_neighbours: expected >= 0, got {self.num_neighbours}")
        if self.lr_schedule is not None and self.lr_schedule not in LR_SCHEDULES:
            raise InputError(f"lr_schedule: expected one of {', '.join(LR_SCHEDULES)}, got {self.lr_schedule!r}")
        if self.depth_noise is not None and not 0.0 <= float(self.depth_noise) <= MAX_DEPTH_NOISE:
            raise InputError(f"depth_noise: expected a log-depth error in [0, {MAX_DEPTH_NOISE:g}], "
                             f"got {self.depth_noise}")
        if self.neighbour_pose_noise is not None:
            noise = tuple(self.neighbour_pose_noise)
            if (len(noise) != 2 or any(isinstance(x, bool) or not isinstance(x, (int, float)) for x in noise)
                    or not 0.0 <= noise[0] <= MAX_POSE_NOISE_DEG or not 0.0 <= noise[1] <= MAX_POSE_NOISE_SHARE):
                raise InputError(f"neighbour_pose_noise: expected (degrees in [0, {MAX_POSE_NOISE_DEG:g}], share "
                                 f"of the camera spread in [0, {MAX_POSE_NOISE_SHARE:g}]), "
                                 f"got {self.neighbour_pose_noise!r}")
        if self.neighbour_encoding not in NEIGHBOUR_ENCODINGS:
            raise InputError(f"neighbour_encoding: expected one of {', '.join(NEIGHBOUR_ENCODINGS)}, "
                             f"got {self.neighbour_encoding!r}")
        unknown = sorted(set(self.without) - set(COMPONENTS))
        if unknown:
            raise InputError(f"without: expected some of {', '.join(COMPONENTS)}, got {', '.join(unknown)}")
        return self


@dataclass
class TrainProgress:
    step: int
    total_steps: int | None
    """Known for step budgets; estimated from the step rate for time budgets."""
    fraction: float
    loss: float
    steps_per_s: float
    eta_s: float | None
    elapsed_s: float
    lr: float | None = None
    """The learning rate of the step just taken (None while evaluating)."""
    phase: str = "training"
    """"training" (after each step) or "evaluating" (measuring the held-out views before the
    first step or after the last; no steps meanwhile, ``eta_s`` None)."""


@dataclass
class TrainResult:
    checkpoint: Path
    steps: int
    seconds: float
    final_loss: float
    loss_kind: str
    """"l1+vgg19" or "l1" (no VGG-19 weights given)."""
    before: dict | None
    after: dict | None
    config: dict = field(default_factory=dict)
    """The plan (device, variant, crop, batch, neighbours, budget), model config and transfer report."""
    guard: dict | None = None
    """Fine-tuning with ``TrainConfig.guard``: :meth:`GuardReport.to_dict
    <roguenerf.training.guard.GuardReport.to_dict>` (``kept`` False: the checkpoint holds the
    starting weights); None otherwise."""


@dataclass(frozen=True)
class TrainPlan:
    """What a run trains, on what, for how long: :func:`plan_training`'s choices for the scenes and
    the machine, every field set. Saved with the run (:meth:`to_dict`); a resumed run keeps it."""

    device: str
    variant: str
    crop: int
    """The crop side asked for."""
    crop_used: int
    """The crop side cut: ``crop``, at most the smallest frame's sides."""
    batch: int
    lr: float
    num_neighbours: int
    steps: int | None
    minutes: float | None
    seed: int
    without: tuple[str, ...] = ()
    lr_schedule: str = "constant"
    """Defaults below: what a run saved before the field existed had (see :meth:`from_dict`)."""
    neighbour_encoding: str = "window"
    freeze_neighbour_encoder: bool = False
    render_warp: float = 0.0
    why: str = ""
    threads: int = 0
    held_out_share: float = 0.0
    """Pre-training: the share of held-out views among the targets of ``held_out_scenes``."""
    neighbour_pose_noise: tuple[float, float] | None = None
    """:attr:`TrainConfig.neighbour_pose_noise` (None: off)."""
    depth_noise: float = 0.0
    """:attr:`TrainConfig.depth_noise` (0: off)."""
    neighbour_renders: float = 0.0
    """:attr:`TrainConfig.neighbour_renders` (0: off)."""

    # The saved plan's key order (JSON in the state and the checkpoint's meta).
    _ORDER = ("device", "variant", "crop", "crop_used", "batch", "lr", "lr_schedule", "num_neighbours",
              "steps", "minutes", "without", "seed", "neighbour_encoding", "freeze_neighbour_encoder",
              "render_warp", "why", "threads", "held_out_share", "neighbour_pose_noise",
              "depth_noise", "neighbour_renders")

    def to_dict(self) -> dict:
        """JSON-able, as saved (``without`` a list)."""
        out = {key: getattr(self, key) for key in self._ORDER}
        out["without"] = list(self.without)
        if self.neighbour_pose_noise is not None:
            out["neighbour_pose_noise"] = list(self.neighbour_pose_noise)
        return out

    @classmethod
    def from_dict(cls, data: Mapping) -> TrainPlan:
        """A saved plan (extra keys, such as a result's ``loss_kind``, are ignored; keys a run saved
        before they existed take their defaults)."""
        known = {f.name for f in dataclasses.fields(cls)}
        values = {key: value for key, value in data.items() if key in known}
        values["without"] = tuple(values.get("without", ()))
        if values.get("neighbour_pose_noise") is not None:
            values["neighbour_pose_noise"] = tuple(values["neighbour_pose_noise"])
        return cls(**values)

    def replace(self, **changes) -> TrainPlan:
        if "without" in changes:
            changes["without"] = tuple(changes["without"])
        return dataclasses.replace(self, **changes)

    def budget_fraction(self, step: int, elapsed_s: float) -> float:
        """See :func:`budget_fraction`."""
        return budget_fraction(self, step, elapsed_s)

    def budget_done(self, step: int, elapsed_s: float) -> bool:
        """True once ``step`` steps or ``elapsed_s`` seconds of training reach the budget."""
        if self.steps is not None and step >= self.steps:
            return True
        return self.minutes is not None and elapsed_s >= self.minutes * 60.0


def _as_plan(plan: TrainPlan | Mapping) -> TrainPlan:
    return plan if isinstance(plan, TrainPlan) else TrainPlan.from_dict(plan)


def default_device() -> str:
    import torch

    return "cuda" if torch.cuda.is_available() else "cpu"


def _frame_sizes(scenes) -> tuple[int, int]:
    heights = [f.height for s in scenes for f in s.frames]
    widths = [f.width for s in scenes for f in s.frames]
    return min(heights), min(widths)


def plan_training(scene, config: TrainConfig, device: str | torch.device | None = None, *,
                  model_config=None, kind: str = "finetune") -> TrainPlan:
    """Choose variant, crop, batch, neighbours and budget for the scene(s) and the machine.

    Args:
        scene: one Scene or a list of them (pre-training).
        config: the caller's wishes; its non-None fields always win.
        device: where training runs (default: CUDA when available).
        model_config: the starting model's EnhancerConfig when fine-tuning a checkpoint.
        kind: "finetune" or "pretrain" (pre-training never freezes conv_H unless asked to).
    Returns:
        A :class:`TrainPlan` (``to_dict()``: JSON-able).
    """
    import torch

    from roguenerf.models import VARIANTS

    config.validate()
    scenes = scene if isinstance(scene, (list, tuple)) else [scene]
    if not scenes:
        raise InputError("scenes: expected at least one scene, got none")
    dev = torch.device(device or config.device or default_device())
    on_gpu = dev.type != "cpu"
    height, width = _frame_sizes(scenes)
    largest = max(f.height * f.width for s in scenes for f in s.frames)

    if config.variant is not None:
        if VARIANTS and config.variant not in VARIANTS:
            raise InputError(f"variant: expected one of {', '.join(VARIANTS)}, got {config.variant!r}")
        variant = config.variant
    elif model_config is not None:
        variant = model_config.variant
    elif on_gpu:
        wanted = "T" if largest <= 1024 * 1024 else "S"
        variant = wanted if wanted in VARIANTS else "nano"
    else:
        variant = CPU_VARIANT

    crop = int(config.crop) if config.crop is not None else (GPU_CROP if on_gpu else CPU_CROP)
    model_n = model_config.num_neighbours if model_config is not None else 5
    if config.num_neighbours is not None:
        n = int(config.num_neighbours)
    else:
        n = model_n if on_gpu else min(model_n, CPU_NEIGHBOURS)
    if "neighbours" in config.without:
        n = 0
    freeze = config.freeze_neighbour_encoder
    if freeze is None:
        freeze = FREEZE_NEIGHBOUR_ENCODER if kind == "finetune" else False
    # Target augmentation: the caller's, else the fine-tuning default; pre-training none.
    warp = config.render_warp if config.render_warp is not None else (RENDER_WARP if kind == "finetune" else 0.0)
    drawn = (config.neighbour_renders if config.neighbour_renders is not None
             else (NEIGHBOUR_RENDERS if kind == "finetune" else 0.0))
    steps, minutes = config.steps, config.minutes
    if steps is None and minutes is None:
        minutes = GPU_MINUTES if on_gpu else CPU_MINUTES
    return TrainPlan(
        device=str(dev),
        variant=variant,
        crop=crop,
        crop_used=min(crop, height, width),
        batch=int(config.batch),
        lr=float(config.lr) if config.lr is not None else (GPU_LR if on_gpu else CPU_LR),
        lr_schedule=config.lr_schedule or LR_SCHEDULE,
        num_neighbours=n,
        steps=None if steps is None else int(steps),
        minutes=None if minutes is None else float(minutes),
        without=tuple(config.without),
        seed=int(config.seed),
        neighbour_encoding=config.neighbour_encoding,
        neighbour_pose_noise=(tuple(float(x) for x in config.neighbour_pose_noise)
                              if config.neighbour_pose_noise is not None and any(config.neighbour_pose_noise)
                              else None),
        freeze_neighbour_encoder=bool(freeze),
        depth_noise=float(config.depth_noise or 0.0),
        render_warp=float(warp),
        neighbour_renders=float(drawn),
        why=GPU_PLAN_WHY if on_gpu else CPU_PLAN_WHY,
        threads=torch.get_num_threads(),
    )


def describe_plan(plan: TrainPlan | Mapping) -> str:
    """The plan in one line (``plan``: a :class:`TrainPlan`, or one as saved, a dict)."""
    plan = _as_plan(plan)
    budget = f"{plan.steps} steps" if plan.steps is not None else f"{plan.minutes:g} min"
    if plan.steps is not None and plan.minutes is not None:
        budget = f"{plan.steps} steps or {plan.minutes:g} min"
    without = f", without {'+'.join(plan.without)}" if plan.without else ""
    if plan.render_warp:
        without += f", half the target renders warped (up to {plan.render_warp:g} px)"
    if plan.neighbour_renders:
        without += f", {plan.neighbour_renders:.0%} of the target renders drawn from the nearest training view's"
    if plan.neighbour_pose_noise:
        deg, share = plan.neighbour_pose_noise
        without += f", neighbour poses perturbed ({deg:g} deg, {share:.0%} of the camera spread RMS)"
    if plan.depth_noise:
        without += f", half the target depths off by a smooth error up to x{math.exp(plan.depth_noise):.2f}"
    if plan.held_out_share:
        without += f", held-out views {plan.held_out_share:.0%} of their scenes' targets"
    return (f"plan: {plan.device} ({plan.threads} threads), variant {plan.variant}, "
            f"crop {plan.crop_used}, batch {plan.batch}, {plan.num_neighbours} neighbours, "
            f"lr {plan.lr:g}{' cosine to 0' if plan.lr_schedule == 'cosine' else ''}, "
            f"budget {budget}{without}"
            + (", conv_H frozen (neighbour features encoded once)" if plan.freeze_neighbour_encoder
               else f", neighbour photos encoded "
                    f"{'per crop window' if plan.neighbour_encoding == 'window' else 'whole'}")
            + (f" ({plan.why})" if plan.why else ""))


def budget_fraction(plan: TrainPlan | Mapping, step: int, elapsed_s: float) -> float:
    """How much of the plan's budget ``step`` steps and ``elapsed_s`` seconds of training have
    used, in [0, 1]: of a step budget, a time budget, or both (the larger share: the one that
    runs out first). ``plan``: a :class:`TrainPlan` or a mapping with its ``steps`` and
    ``minutes``."""
    steps, minutes = (plan.steps, plan.minutes) if isinstance(plan, TrainPlan) else (plan.get("steps"),
                                                                                     plan.get("minutes"))
    shares = []
    if steps:
        shares.append(step / steps)
    if minutes:
        shares.append(elapsed_s / (minutes * 60.0))
    return min(max(shares, default=0.0), 1.0)


def lr_factor(schedule: str, fraction: float) -> float:
    """The multiplier of the plan's lr at ``fraction`` (0..1) of the budget: "cosine"
    ``0.5 (1 + cos(pi f))``, 1 at the start and 0 at the end; "constant" 1."""
    if schedule == "constant":
        return 1.0
    if schedule == "cosine":
        return 0.5 * (1.0 + math.cos(math.pi * min(max(fraction, 0.0), 1.0)))
    raise InputError(f"lr_schedule: expected one of {', '.join(LR_SCHEDULES)}, got {schedule!r}")
