"""Pre-training over scenes and per-scene fine-tuning (paper section 3.7).

Dimension legend: B batch, N neighbours per target, U distinct neighbour photos in a batch,
F feature channels, c crop side, H x W full image size.

Each training view is a target: its render (random c x c crop; K's principal point shifted by
the crop offset) is enhanced with its precomputed nearest training views as neighbours (never
itself), and the result is compared with the same crop of its photo. conv_H is trained, so neighbour
features are recomputed every step, by default only on the window of each neighbour photo
that the target crop can see (``TrainConfig.neighbour_encoding``; see
:mod:`roguenerf.training.batches`, which also proves the equality with whole photos). With
``TrainConfig.freeze_neighbour_encoder`` conv_H keeps its weights and the training photos are
encoded once before the first step. Batches are drawn and cut in a background thread while the
model trains.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import torch
from torch import Tensor

from roguenerf.checkpoint import MODEL_FILE, TRAIN_STATE_FILE
from roguenerf.errors import InputError, TrainingCancelled, TrainingDivergedError
from roguenerf.geometry.noise import camera_spread, perturb_poses
from roguenerf.models.layers import receptive_radius
from roguenerf.training.batches import (
    Prefetcher,
    StepBatch,
    corrupt_depths,
    crop_targets,
    model_inputs,
    prepare_batch,
    sample_crops,
    warp_renders,
)
from roguenerf.training.config import (
    FEATURE_CACHE_BYTES,
    TrainConfig,
    TrainPlan,
    TrainProgress,
    TrainResult,
    describe_plan,
    lr_factor,
    plan_training,
)
from roguenerf.training.evaluate import evaluate
from roguenerf.training.losses import build_loss
from roguenerf.training.state import load_state, save_state

log = logging.getLogger("roguenerf.training")

STATE_FILE = TRAIN_STATE_FILE
START_FILE = "start.safetensors"
"""A fine-tune's starting weights, in its output folder: what :mod:`roguenerf.training.guard`
compares the fine-tuned ones with (a resumed run reads them back)."""
TOY_FOLDER = "toy"
"""Where ``roguenerf pretrain --toy N`` writes its generated scenes, inside the output folder."""
PREFETCH = 2
"""Batches the background thread prepares ahead of the training step."""
SWITCHES = {"neighbours": "use_neighbours", "alignment": "use_alignment",
            "refinement": "use_refinement", "attention": "use_attention"}


class SceneData:
    """One scene's target views in memory, with each view's neighbour list computed once.

    The targets are the training views, then (``held_out=True``, pre-training only) the held-out
    views: renders of views the radiance field never saw, the artefacts a user's novel views
    have. Neighbours are always training views, as they are for a novel view at inference.

    photos, renders: ``(M, 3, H, W)``; depths ``(M, 1, H, W)``; K ``(M, 3, 3)``;
    poses ``(M, 4, 4)`` float64; neighbours ``(M, N)`` int64 positions into these tensors
    (always below ``len(train)``). M = ``len(train) + len(held_out)``.
    """

    def __init__(self, scene, num_neighbours: int, *, held_out: bool = False):
        from roguenerf.geometry import select_neighbours

        self.scene = scene
        self.train = list(scene.indices("train"))
        if not self.train:
            raise InputError(f"scene {scene.root}: expected training views, found none")
        self.held_out = list(scene.indices("test")) if held_out else []
        views = self.train + self.held_out
        sizes = {(scene.frames[i].height, scene.frames[i].width) for i in views}
        if len(sizes) != 1:
            raise InputError(f"scene {scene.root}: training needs one image size for all "
                             f"{'views' if self.held_out else 'training views'}, got {sorted(sizes)}")
        self.height, self.width = next(iter(sizes))
        self.photos = torch.stack([scene.photo(i) for i in views])
        self.renders = torch.stack([scene.render(i) for i in views])
        self.depths = torch.stack([scene.depth(i) for i in views])
        self.K = scene.intrinsics(views).to(torch.float32)
        # float64, as the scene holds them: relative poses are formed from these in float64
        # (reprojection, camera attention, neighbour ranking) and only then cast to float32.
        self.poses = scene.poses(views).to(torch.float64)
        m = len(self.train)
        n = min(num_neighbours, m - 1)
        train_poses = self.poses[:m]
        lists = [select_neighbours(self.poses[k], train_poses, n, exclude=k if k < m else None)
                 for k in range(len(views))]
        self.neighbours = torch.stack(lists) if n > 0 else torch.zeros(len(views), 0, dtype=torch.int64)
        self.spread = camera_spread(train_poses)
        """The training cameras' spread (:func:`~roguenerf.geometry.noise.camera_spread`), the unit
        of ``TrainConfig.neighbour_pose_noise``'s translation."""
        self.features: Tensor | None = None
        """``(len(train), F, H, W)`` conv_H features of the training photos when conv_H is frozen
        (:meth:`cache_features`); batches then cut windows of these instead of photos."""
        self.drawn_renders: Tensor | None = None
        self.drawn_depths: Tensor | None = None
        """``(len(train), 3 | 1, H, W)``: each training view as its nearest other training view's
        render draws it (:meth:`draw_from_neighbours`), for ``TrainConfig.neighbour_renders``."""

    def feature_bytes(self, model) -> int:
        """Memory :meth:`cache_features` would take for ``model`` (float32)."""
        return len(self.train) * model.config.features * self.height * self.width * 4

    def cache_features(self, model, device: torch.device) -> None:
        """Encode every training photo once with ``model``'s (frozen) conv_H, whole, on ``device``;
        kept on the CPU, where batches are cut."""
        with torch.no_grad():
            self.features = torch.cat([
                model.encode_neighbours(self.photos[k:k + 1].to(device)).to("cpu").contiguous()
                for k in range(len(self.train))])

    def draw_from_neighbours(self) -> float:
        """Fill :attr:`drawn_renders` and :attr:`drawn_depths`: each training view's render and depth
        as its nearest other training view's render and depth look from its camera
        (:meth:`drawn_view`, :func:`~roguenerf.reprojection.splat_view`: a forward warp, so what is
        wrong in that view's geometry lands where a new camera would see it, as in a novel view),
        its own render and depth where nothing lands. Returns the mean share of pixels drawn."""
        m = len(self.train)
        renders, depths, drawn = self.renders[:m].clone(), self.depths[:m].clone(), []
        if m < 2:
            self.drawn_renders, self.drawn_depths = renders, depths
            return 0.0
        for k in range(m):
            renders[k], depths[k], share = self.drawn_view(k)
            drawn.append(share)
        self.drawn_renders, self.drawn_depths = renders, depths
        return sum(drawn) / len(drawn)

    def drawn_view(self, k: int) -> tuple[Tensor, Tensor, float]:
        """Training view ``k``'s render ``(3, H, W)`` and depth ``(1, H, W)`` as its nearest other
        training view's render and depth draw them into its camera
        (:func:`~roguenerf.reprojection.splat_view`), its own where nothing lands, and the share
        of its pixels drawn (0 with a single training view)."""
        from roguenerf.geometry import select_neighbours
        from roguenerf.reprojection import splat_view

        m = len(self.train)
        if m < 2:
            return self.renders[k].clone(), self.depths[k].clone(), 0.0
        s = int(select_neighbours(self.poses[k], self.poses[:m], 1, exclude=k)[0])
        image, depth, hit = splat_view(self.renders[s], self.depths[s], self.K[s], self.K[k], self.poses[s],
                                       self.poses[k], (self.height, self.width))
        return (torch.where(hit, image, self.renders[k]), torch.where(hit, depth, self.depths[k]),
                float(hit.float().mean()))

    def __len__(self) -> int:
        return len(self.train)

    def draw_targets(self, count: int, generator: torch.Generator, held_out_share: float = 0.0) -> Tensor:
        """``(count,)`` target positions: training views uniformly, or with probability
        ``held_out_share`` each, a held-out view (when this scene has them)."""
        m = len(self.train)
        train = torch.randint(0, m, (count,), generator=generator)
        if not self.held_out or held_out_share <= 0:
            return train
        pick = torch.rand(count, generator=generator) < held_out_share
        held = m + torch.randint(0, len(self.held_out), (count,), generator=generator)
        return torch.where(pick, held, train)


def _crop_batch(data: SceneData, targets: Tensor, crop: int, generator: torch.Generator):
    """Same random crop of render, depth and photo per target; K shifted by the crop offset.

    Returns render ``(B, 3, c, c)``, depth ``(B, 1, c, c)``, photo ``(B, 3, c, c)``, K ``(B, 3, 3)``.
    """
    return crop_targets(data, targets, sample_crops(data, len(targets), crop, generator), crop)


def neighbour_margin(model) -> int:
    """conv_H's receptive radius (0 without neighbours): how far beyond its taps a window must reach."""
    return receptive_radius(model.conv_H) if model.conv_H is not None else 0


def batch_encoding(model, encoding: str) -> str:
    """``encoding``, or "whole" when windows cannot stand for the photos: without 3D alignment
    the enhancer resizes each neighbour photo whole to the target's size."""
    return encoding if model.config.use_alignment else "whole"


def draw_batch(model, data: SceneData, targets: Tensor, crop: int, generator: torch.Generator, *,
               encoding: str = "window") -> StepBatch:
    """Random crops of ``targets`` and the neighbour windows (or photos) they need (no model call)."""
    origins = sample_crops(data, len(targets), crop, generator)
    return prepare_batch(data, targets, origins, crop, encoding=batch_encoding(model, encoding),
                         margin=neighbour_margin(model),
                         use_neighbours=model.config.use_neighbours)


def training_step_inputs(model, data: SceneData, targets: Tensor, crop: int, generator: torch.Generator,
                         device: torch.device, *, encoding: str = "window"):
    """Inputs and ground truth of one step; neighbour features are computed here (with grad).

    ``encoding``: ``"window"`` encodes only the windows of the neighbour photos the crops can
    see, ``"whole"`` the whole photos (same values; :mod:`roguenerf.training.batches`).
    Returns ``(args, photo)`` where ``model(*args)`` is the enhanced crop ``(B, 3, c, c)``.
    """
    return model_inputs(model, draw_batch(model, data, targets, crop, generator, encoding=encoding), device)


def make_optimizer(model, lr: float) -> torch.optim.Optimizer:
    """Adam over ``model``'s parameters, fused (one kernel for all of them) where the device has
    it: the per-parameter loop of the default CPU Adam costs more than conv_H's crop windows
    (micro has 189 parameter tensors). Same update rule and state (resumable either way)."""
    params = list(model.parameters())
    try:
        return torch.optim.Adam(params, lr=lr, fused=True)
    except (RuntimeError, ValueError):  # a device or dtype without the fused kernel
        return torch.optim.Adam(params, lr=lr)


def set_lr(optimizer: torch.optim.Optimizer, plan: TrainPlan, step: int, elapsed_s: float) -> float:
    """Set the learning rate of the step about to be taken, the plan's ``lr`` times
    :func:`~roguenerf.training.config.lr_factor` of its schedule at the share of the budget used
    so far; returns it."""
    lr = plan.lr * lr_factor(plan.lr_schedule, plan.budget_fraction(step, elapsed_s))
    for group in optimizer.param_groups:
        group["lr"] = lr
    return lr


def optimise(model, batch: StepBatch, device: torch.device, loss_fn, optimizer: torch.optim.Optimizer, *,
             step: int = 0, checkpoint: str | None = None) -> float:
    """One optimisation step on a prepared batch: conv_H on its neighbour photos or windows ->
    ``model`` forward -> ``loss_fn(output, photo)`` -> backward -> ``optimizer.step()``.
    Returns the loss value.

    Raises:
        TrainingDivergedError: non-finite loss or gradients, reported as step ``step + 1`` with
            ``checkpoint`` as the last good one; the weights are left unchanged.
    """
    args, photo = model_inputs(model, batch, device)
    output = model(*args)
    loss = loss_fn(output, photo)
    loss_value = float(loss.detach())
    if not math.isfinite(loss_value):
        raise TrainingDivergedError(step + 1, loss_value, checkpoint)
    optimizer.zero_grad(set_to_none=True)
    loss.backward()
    grads = [p.grad for p in model.parameters() if p.grad is not None]
    if grads and not torch.isfinite(torch.stack([g.abs().max() for g in grads])).all():
        raise TrainingDivergedError(step + 1, float("nan"), checkpoint)
    optimizer.step()
    return loss_value


def train_step(model, data: SceneData, targets: Tensor, crop: int, generator: torch.Generator,
               device: torch.device, loss_fn, optimizer: torch.optim.Optimizer, *, step: int = 0,
               checkpoint: str | None = None, encoding: str = "window") -> float:
    """One optimisation step on ``targets`` ``(B,)`` of ``data``, as fine-tuning and pre-training make it.

    Random c x c crops and the neighbours they need (:func:`draw_batch`, ``encoding`` as in
    :func:`training_step_inputs`), then :func:`optimise`. Returns the loss value.
    Raises:
        TrainingDivergedError: non-finite loss or gradients, reported as step ``step + 1`` with
            ``checkpoint`` as the last good one; the weights are left unchanged.
    """
    batch = draw_batch(model, data, targets, crop, generator, encoding=encoding)
    return optimise(model, batch, device, loss_fn, optimizer, step=step, checkpoint=checkpoint)


WIDENABLE = ("conv_merge.0.weight",)
"""Weights whose extra inputs are appended features (:func:`transfer_weights`)."""


def transfer_weights(source: torch.nn.Module, target: torch.nn.Module) -> dict:
    """Copy every parameter/buffer of ``source`` whose name and shape match into ``target``.

    conv_merge, whose inputs are only ever appended (``[I^f]``, ``[I^f, H_pool]``, ``[I^f,
    H_pool, H_spread]``: :attr:`~roguenerf.models.enhancer.Enhancer.pooled_maps`), is widened
    when the target takes more of them: the source's weights for the leading inputs, zeros for
    the new ones, so the model computes what the source did until training moves them. No
    other weight is widened (another layer's extra inputs are not appended features: a larger
    variant's channels mean something else).

    Returns ``{"loaded": count, "dropped": [...], "fresh": [...], "widened": [...]}``: top-level
    sub-modules of the source that the target lacks (or whose shapes differ), target sub-modules
    that keep their initial weights, and those whose inputs were widened.
    """
    src = source.state_dict()
    dst = target.state_dict()
    matched = {k: v for k, v in src.items() if k in dst and dst[k].shape == v.shape}
    widened = []
    for k in WIDENABLE:
        v, d = src.get(k), dst.get(k)
        if (k not in matched and v is not None and d is not None and v.ndim == d.ndim
                and v.shape[0] == d.shape[0] and v.shape[2:] == d.shape[2:] and v.shape[1] < d.shape[1]):
            w = torch.zeros_like(d)
            w[:, : v.shape[1]] = v
            matched[k] = w
            widened.append(k)
    target.load_state_dict({**dst, **matched})

    def groups(keys):
        return sorted({".".join(k.split(".")[:1]) for k in keys})

    return {"loaded": len(matched),
            "dropped": groups(k for k in src if k not in matched),
            "fresh": groups(k for k in dst if k not in matched),
            "widened": groups(widened)}


def _initial_model(checkpoint, config: TrainConfig, plan_variant: str | None):
    """Starting model and a transfer report: a checkpoint (path or Enhancer) or a fresh one."""
    from roguenerf.models import build_enhancer, make_config

    # What the run asks of the model, over the variant's or the checkpoint's config.
    overrides = {SWITCHES[w]: False for w in config.without}
    if config.pool_spread is not None:
        overrides["pool_spread"] = bool(config.pool_spread)
    if checkpoint is None:
        return build_enhancer(make_config(plan_variant or "nano", **overrides)), None
    if isinstance(checkpoint, (str, Path)):
        from roguenerf.checkpoint import load_checkpoint

        source, _meta = load_checkpoint(checkpoint)
    else:
        source = checkpoint
    wanted = source.config
    if config.variant is not None and config.variant != wanted.variant:
        wanted = make_config(config.variant, **overrides)
    else:
        wanted = dataclasses.replace(wanted, **overrides)
    if wanted == source.config:
        model = build_enhancer(wanted)
        model.load_state_dict(source.state_dict())
        return model, None
    model = build_enhancer(wanted)
    report = transfer_weights(source, model)
    log.info("started from a checkpoint with a different config: loaded %d tensors; dropped %s; fresh %s; "
             "widened %s", report["loaded"], report["dropped"] or "nothing", report["fresh"] or "nothing",
             report["widened"] or "nothing")
    return model, report


RESUMED_KEYS = ("variant", "crop", "crop_used", "batch", "lr", "num_neighbours", "without", "seed",
                "lr_schedule", "freeze_neighbour_encoder", "held_out_share", "render_warp",
                "neighbour_pose_noise", "depth_noise", "neighbour_renders")
"""What a resumed run keeps of its saved plan whatever the new wishes (a run saved before a field
existed keeps TrainPlan's default: no schedule, no freezing, no held-out views, no augmentation)."""


def _resume(saved: dict, scenes: list, config: TrainConfig, kind: str, output_dir: Path):
    """A saved run's model, its plan (the saved choices over today's plan for the rest), its
    transfer report and its evaluation before training."""
    from roguenerf.models import EnhancerConfig, build_enhancer

    info = saved["info"]
    model = build_enhancer(EnhancerConfig.from_dict(info["model_config"]))
    model.load_state_dict(saved["model"])
    stored = info["plan"]
    plan = plan_training(scenes, config, stored["device"] if config.device is None else None,
                         model_config=model.config, kind=kind)
    kept = TrainPlan.from_dict(stored)  # fields saved before they existed: TrainPlan's defaults
    plan = plan.replace(**{key: getattr(kept, key) for key in RESUMED_KEYS})
    log.info("resuming %s from step %d in %s", kind, saved["step"], output_dir)
    return model, plan, info.get("transfer"), info.get("before")


def _plan(scenes: list, config: TrainConfig, kind: str, checkpoint, held_out_scenes: Sequence[int]):
    """A fresh run's plan, its starting model (``checkpoint``'s weights, moved over to the
    planned model where it differs, or the seed's) and the transfer report."""
    start_config = None
    if checkpoint is not None and not isinstance(checkpoint, (str, Path)):
        start_config = checkpoint.config
    elif checkpoint is not None:
        from roguenerf.checkpoint import load_checkpoint

        checkpoint, _ = load_checkpoint(checkpoint)
        start_config = checkpoint.config
    plan = plan_training(scenes, config, model_config=start_config, kind=kind)
    torch.manual_seed(plan.seed)  # fresh weights depend on the seed alone
    model, transfer = _initial_model(checkpoint, config, plan.variant)
    plan = plan.replace(variant=model.config.variant,
                        held_out_share=float(config.held_out_share) if held_out_scenes else 0.0)
    return model, plan, transfer


@dataclasses.dataclass
class _Run:
    """What the training loop works on, set up by :func:`_set_up`; ``save`` writes the model and
    the resumable state of the batches consumed so far."""

    kind: str
    plan: TrainPlan
    config: TrainConfig
    model: torch.nn.Module
    device: torch.device
    loss_fn: Callable
    datasets: list
    optimizer: torch.optim.Optimizer
    generator: torch.Generator
    model_path: Path
    state_path: Path
    transfer: dict | None
    before: dict | None
    frozen: bool
    weights: Tensor | None = None
    """Each dataset's chance of giving a batch: its training-view count."""
    step: int = 0
    elapsed_before: float = 0.0
    encoding: str = "window"
    margin: int = 0
    sampler_state: Tensor | None = None
    """The sampler state of the batches consumed so far: what a checkpoint stores (the prefetch
    thread is ahead), so a resumed run draws the very batches this one would have drawn next."""

    def augment(self, render: Tensor, depth: Tensor) -> tuple[Tensor, Tensor]:
        # Fine-tuning targets made to look like novel views (TrainConfig.render_warp).
        if self.plan.render_warp > 0:
            render, depth = warp_renders(render, depth, self.plan.render_warp, self.generator)
        if self.plan.depth_noise > 0:  # TrainConfig.depth_noise: the reprojections read a wrong depth
            depth = corrupt_depths(depth, self.plan.depth_noise, self.generator)
        return render, depth

    def make_batch(self) -> StepBatch:
        # Runs in the prefetch thread, which owns ``generator`` from the first batch on.
        plan, generator = self.plan, self.generator
        index = int(torch.multinomial(self.weights, 1, generator=generator))
        d = self.datasets[index]
        targets = d.draw_targets(plan.batch, generator, plan.held_out_share)
        origins = sample_crops(d, plan.batch, plan.crop, generator)
        drawn = None
        if plan.neighbour_renders > 0:  # TrainConfig.neighbour_renders: training targets only
            drawn = (torch.rand(plan.batch, generator=generator) < plan.neighbour_renders) & (targets < len(d))
        noise = plan.neighbour_pose_noise

        def noisy(poses: Tensor) -> Tensor:  # TrainConfig.neighbour_pose_noise: each (target, neighbour) its own
            level = torch.rand(poses.shape[0], generator=generator, dtype=torch.float64).tolist()  # per target
            return torch.stack([perturb_poses(p, noise[0] * u, noise[1] * d.spread * u, generator)
                                for p, u in zip(poses, level, strict=True)])

        batch = prepare_batch(d, targets, origins, plan.crop, encoding=self.encoding, margin=self.margin,
                              use_neighbours=self.model.config.use_neighbours,
                              augment=(self.augment if plan.render_warp or plan.depth_noise
                                       else None),
                              pose_noise=noisy if noise else None, drawn=drawn)
        batch.dataset, batch.sampler_state = index, generator.get_state()
        return batch

    @property
    def meta(self) -> dict:
        return {"kind": self.kind, "plan": self.plan.to_dict(), "loss_kind": self.loss_fn.kind,
                "transfer": self.transfer, "scenes": [str(d.scene.root) for d in self.datasets]}

    def save(self, step: int, elapsed: float, loss_value: float | None, *, result=None,
             guard: dict | None = None) -> None:
        """Write the resumable state (this model's weights) and the output checkpoint: ``result``'s
        weights where given (the starting ones the guard kept), else this model's; ``guard``
        (its report) in the checkpoint's meta."""
        from roguenerf.checkpoint import save_checkpoint

        if loss_value is not None and not math.isfinite(loss_value):
            loss_value = None
        meta = self.meta
        info = {**meta, "model_config": self.model.config.to_dict(), "before": self.before}
        consumed = torch.Generator()
        consumed.set_state(self.sampler_state)
        save_state(self.state_path, model=self.model, optimizer=self.optimizer, generator=consumed, step=step,
                   elapsed_s=elapsed, info=info)
        training = {**meta, "steps": step, "seconds": round(elapsed, 3), "final_loss": loss_value}
        if guard is not None:
            training["guard"] = guard
        save_checkpoint(self.model_path, self.model if result is None else result, meta={"training": training})


def _set_up(scenes: list, output_dir: Path, *, kind: str, config: TrainConfig, model, plan: TrainPlan,
            transfer, before, saved: dict | None, progress, held_out_scenes: Sequence[int]) -> _Run:
    """Device, loss, data, the evaluation before training, a frozen conv_H's feature cache,
    optimiser and sampler (a saved run's state restored); a fresh run saves its step 0."""
    device = torch.device(plan.device)
    if model.config.num_neighbours != plan.num_neighbours and plan.num_neighbours > 0:
        model.config = dataclasses.replace(model.config, num_neighbours=plan.num_neighbours)
    model.to(device)

    loss_fn = build_loss(config.vgg_weights, device)
    if loss_fn.kind == "l1":
        log.info("no VGG-19 weights given: training with the L1 loss alone (the paper adds 1e-3 VGG-19)")
    log.info("%s", describe_plan(plan))
    from roguenerf.runtime import available_cpus

    if device.type == "cpu" and torch.get_num_threads() != available_cpus():
        log.info("torch uses %d threads on %d available cores (roguenerf.runtime.configure() sets one per core)",
                 torch.get_num_threads(), available_cpus())

    held = set(held_out_scenes)
    datasets = [SceneData(s, plan.num_neighbours if model.config.use_neighbours else 0, held_out=k in held)
                for k, s in enumerate(scenes)]
    if plan.neighbour_renders > 0:
        for d in datasets:
            share = d.draw_from_neighbours()
            log.info("%s: each training view drawn from its nearest training view's render (%.0f%% of its "
                     "pixels on average); %.0f%% of the crops use them", d.scene.root, 100 * share,
                     100 * plan.neighbour_renders)
    if kind == "finetune" and config.evaluate and saved is None and datasets[0].scene.indices("test"):
        _evaluating(progress, 0, plan)
        before = _summary(evaluate(datasets[0].scene, model))
    frozen = bool(plan.freeze_neighbour_encoder) and model.conv_H is not None
    if frozen:
        # Fixed weights: every step would encode the same photos to the same features.
        model.conv_H.requires_grad_(False)
        need = sum(d.feature_bytes(model) for d in datasets)
        if need <= FEATURE_CACHE_BYTES:
            model.eval()
            for d in datasets:
                d.cache_features(model, device)
        else:
            log.info("conv_H frozen; its features would take %.1f GB (> %.1f GB): each step encodes "
                     "its windows without gradient instead", need / 1e9, FEATURE_CACHE_BYTES / 1e9)

    run = _Run(kind=kind, plan=plan, config=config, model=model, device=device, loss_fn=loss_fn,
               datasets=datasets, optimizer=make_optimizer(model, plan.lr),
               generator=torch.Generator().manual_seed(plan.seed), model_path=output_dir / MODEL_FILE,
               state_path=output_dir / STATE_FILE, transfer=transfer, before=before, frozen=frozen)
    if saved is not None:
        run.optimizer.load_state_dict(saved["optim"])
        torch.set_rng_state(saved["rng_torch"])
        run.generator.set_state(saved["rng_sampler"])
        run.step, run.elapsed_before = saved["step"], saved["elapsed_s"]
    else:
        torch.manual_seed(plan.seed)
    run.weights = torch.tensor([float(len(d)) for d in datasets])
    run.margin = neighbour_margin(model)  # prepare_batch needs none for cached features
    run.encoding = batch_encoding(model, plan.neighbour_encoding)
    run.sampler_state = run.generator.get_state()
    if saved is None:
        run.save(0, 0.0, None)
    return run


def _progress_bar(run: _Run):
    """A tqdm bar on stderr, or None. A step budget counts steps; a time budget counts seconds
    (its step total is only an estimate that moves with the step rate, so a bar of steps would
    keep changing its total)."""
    if not run.config.progress_bar:
        return None
    from tqdm import tqdm

    plan = run.plan
    if plan.steps is None:
        budget_s = round(plan.minutes * 60.0)
        return tqdm(total=budget_s, initial=min(round(run.elapsed_before), budget_s),
                    desc=f"{run.kind} ({plan.minutes:g} min)", unit="s", file=sys.stderr, dynamic_ncols=True,
                    bar_format="{l_bar}{bar}| {n:.0f}/{total:.0f} s [{elapsed}<{remaining}{postfix}]")
    return tqdm(total=plan.steps, initial=run.step, desc=run.kind, unit="step", file=sys.stderr,
                dynamic_ncols=True)


def _loop(run: _Run, progress: Callable[[TrainProgress], None] | None,
          should_stop: Callable[[], bool] | None) -> tuple[int, float, float]:
    """Train until the budget is spent; returns (step, elapsed seconds, last loss).

    Raises:
        TrainingCancelled: ``should_stop()`` returned True (state saved first).
        TrainingDivergedError: from :func:`optimise`.
    """
    plan, model = run.plan, run.model
    by_time = plan.steps is None
    bar = _progress_bar(run)
    model.train()
    step, elapsed_before = run.step, run.elapsed_before
    start = time.perf_counter()
    last_save = start
    first_step = step
    loss_value = float("nan")
    batches = None
    try:
        while not plan.budget_done(step, elapsed_before + time.perf_counter() - start):
            if should_stop is not None and should_stop():
                elapsed = elapsed_before + time.perf_counter() - start
                run.save(step, elapsed, loss_value)
                raise TrainingCancelled(step, str(run.model_path))
            if batches is None:
                batches = Prefetcher(run.make_batch, depth=PREFETCH)
            batch = next(batches)
            lr = set_lr(run.optimizer, plan, step, elapsed_before + time.perf_counter() - start)
            loss_value = optimise(model, batch, run.device, run.loss_fn, run.optimizer, step=step,
                                  checkpoint=str(run.model_path))
            run.sampler_state = batch.sampler_state
            step += 1

            now = time.perf_counter()
            elapsed = elapsed_before + now - start
            rate = (step - first_step) / max(now - start, 1e-9)
            if plan.steps is not None:
                total_est = plan.steps
            else:
                total_est = step + int(max(plan.minutes * 60.0 - elapsed, 0.0) * rate)
            remaining = [] if plan.steps is None else [(plan.steps - step) / max(rate, 1e-9)]
            if plan.minutes is not None:
                remaining.append(max(plan.minutes * 60.0 - elapsed, 0.0))
            eta = min(remaining) if remaining else None
            fraction = step / total_est if total_est else 1.0
            if bar is not None:
                if by_time:
                    bar.update(min(elapsed, bar.total) - bar.n)
                    bar.set_postfix(step=step, loss=f"{loss_value:.4f}", lr=f"{lr:.2g}", steps_per_s=f"{rate:.2f}")
                else:
                    bar.update(1)
                    bar.set_postfix(loss=f"{loss_value:.4f}", lr=f"{lr:.2g}",
                                    eta=f"{eta:.0f}s" if eta is not None else "?")
            if progress is not None:
                progress(TrainProgress(step=step, total_steps=total_est, fraction=min(fraction, 1.0),
                                       loss=loss_value, steps_per_s=rate, eta_s=eta, elapsed_s=elapsed, lr=lr))
            if now - last_save >= run.config.checkpoint_every_s:
                run.save(step, elapsed, loss_value)
                last_save = time.perf_counter()
    finally:
        if batches is not None:
            batches.close()
        if bar is not None:
            bar.close()
        model.eval()
        if run.frozen:
            model.conv_H.requires_grad_(True)
    return step, elapsed_before + time.perf_counter() - start, loss_value


def check_training_output(output_dir: str | Path) -> None:
    """A training output folder may be new, empty, or an earlier run's (resumed): one with the resume
    state, a checkpoint of ours (its sidecar says so) or the toy scenes. Any other folder is refused,
    since its ``model.safetensors`` and ``model.json`` would be overwritten."""
    import json

    from roguenerf.checkpoint import FORMAT

    output_dir = Path(output_dir)
    if not output_dir.exists():
        return
    if not output_dir.is_dir():
        raise InputError(f"output: {output_dir} exists and is not a folder; choose a new folder")

    def ours(name: str) -> bool:
        try:
            return json.loads(output_dir.joinpath(name).with_suffix(".json").read_text()).get("format") == FORMAT
        except (OSError, UnicodeDecodeError, json.JSONDecodeError, AttributeError):
            return False

    # a fine-tune stopped before its first save holds only its starting weights (START_FILE)
    if any(output_dir.iterdir()) and not (ours(MODEL_FILE) or ours(START_FILE) or (output_dir / STATE_FILE).is_file()
                                         or (output_dir / TOY_FOLDER).is_dir()):
        raise InputError(f"output: {output_dir} exists and is not empty: it holds other files, not an earlier "
                         "training run (which would be resumed); choose a new folder")


def _fit(scenes: list, output_dir: Path, *, kind: str, checkpoint, config: TrainConfig,
         progress: Callable[[TrainProgress], None] | None, should_stop: Callable[[], bool] | None,
         resume: bool, held_out_scenes: Sequence[int] = ()) -> TrainResult:
    """Resume or plan, set up, train, save, evaluate (fine-tuning), report."""
    config = config.validate()
    output_dir = Path(output_dir)
    check_training_output(output_dir)
    output_dir.mkdir(parents=True, exist_ok=True)
    state_path = output_dir / STATE_FILE
    saved = load_state(state_path) if resume and state_path.is_file() else None
    start_path = output_dir / START_FILE
    if saved is not None:
        model, plan, transfer, before = _resume(saved, scenes, config, kind, output_dir)
    else:
        model, plan, transfer = _plan(scenes, config, kind, checkpoint, held_out_scenes)
        before = None
        if kind == "finetune":  # what the guard compares the fine-tune with, kept for a resumed run
            from roguenerf.checkpoint import save_checkpoint

            save_checkpoint(start_path, model, meta={"training": {"kind": kind, "start": True}})
    run = _set_up(scenes, output_dir, kind=kind, config=config, model=model, plan=plan, transfer=transfer,
                  before=before, saved=saved, progress=progress, held_out_scenes=held_out_scenes)

    step, elapsed, loss_value = _loop(run, progress, should_stop)
    run.save(step, elapsed, loss_value)
    result_model, guard = model, None
    if kind == "finetune" and config.guard:
        if start_path.is_file():
            from roguenerf.checkpoint import load_checkpoint
            from roguenerf.training.guard import judge

            _evaluating(progress, step, plan, loss=loss_value, elapsed=elapsed)
            start, _ = load_checkpoint(start_path, device=run.device)
            report = judge(run.datasets[0], start, model, device=run.device)
            guard = report.to_dict()
            if not report.kept:
                result_model = start
                log.info("the fine-tuned weights enhance training views drawn like novel views by %+.3f dB, the "
                         "starting weights by %+.3f dB: %s holds the starting weights", report.tuned_mean,
                         report.start_mean, run.model_path)
            run.save(step, elapsed, loss_value, result=result_model, guard=guard)
        else:
            log.info("%s has no starting weights (%s; a run begun before the guard): the fine-tune is not judged",
                     output_dir, START_FILE)
    after = None
    if kind == "finetune" and config.evaluate and run.datasets[0].scene.indices("test"):
        _evaluating(progress, step, plan, loss=loss_value, elapsed=elapsed)
        after = _summary(evaluate(run.datasets[0].scene, result_model))
    plan_out = {**plan.to_dict(), "loss_kind": run.loss_fn.kind, "model": model.config.to_dict(),
                "transfer": transfer}
    return TrainResult(checkpoint=run.model_path, steps=step, seconds=elapsed, final_loss=loss_value,
                       loss_kind=run.loss_fn.kind, before=run.before, after=after, config=plan_out, guard=guard)


def _evaluating(progress, step: int, plan: TrainPlan, *, loss: float = float("nan"), elapsed: float = 0.0) -> None:
    """Tell ``progress`` that the held-out views are being evaluated (before or after training):
    no training step happens meanwhile, and how long it takes is not a step rate."""
    if progress is None:
        return
    total = plan.steps if plan.steps is not None else (step or None)
    fraction = 0.0 if step == 0 else 1.0
    progress(TrainProgress(step=step, total_steps=total, fraction=fraction, loss=loss, steps_per_s=0.0,
                           eta_s=None, elapsed_s=elapsed, phase="evaluating"))


def _summary(report: dict) -> dict:
    return {"render": report["render"], "enhanced": report["enhanced"]}


def finetune(scene, output_dir, *, checkpoint=None, config: TrainConfig = TrainConfig(),
             progress: Callable[[TrainProgress], None] | None = None,
             should_stop: Callable[[], bool] | None = None, resume: bool = True) -> TrainResult:
    """Fine-tune on one scene's training views (render -> photo pairs).

    Args:
        scene: the :class:`~roguenerf.data.scene.Scene` (needs renders and depths).
        output_dir: holds ``model.safetensors`` (the result, checkpointed periodically) and
            ``train_state.safetensors`` (for resume).
        checkpoint: starting weights (path or Enhancer); None trains from scratch.
            With ``config.without`` / ``config.variant`` the matching weights are transferred.
        config: budget and hyper-parameters; unset ones are chosen by :func:`plan_training`.
        progress: called after every step with a :class:`TrainProgress`.
        should_stop: polled before every step; True saves and raises TrainingCancelled.
        resume: continue from ``output_dir``'s saved state when there is one.
    Raises:
        TrainingDivergedError: non-finite loss or gradients (the last good checkpoint stays).
        TrainingCancelled: ``should_stop()`` returned True (state saved first).
    """
    return _fit([scene], output_dir, kind="finetune", checkpoint=checkpoint, config=config,
                progress=progress, should_stop=should_stop, resume=resume)


def pretrain(scenes, output_dir, *, checkpoint=None, config: TrainConfig = TrainConfig(),
             progress: Callable[[TrainProgress], None] | None = None,
             should_stop: Callable[[], bool] | None = None, resume: bool = True,
             held_out_scenes: Sequence[int] = ()) -> TrainResult:
    """Pre-train across scenes (each batch comes from one scene, scenes weighted by training-view count).

    ``held_out_scenes``: positions in ``scenes`` whose held-out views also serve as targets, each
    target with probability ``config.held_out_share`` (their neighbours stay training views).
    Their renders come from a radiance field that never saw them, so they carry the artefacts of
    a novel view, which training views (fitted, hence milder) do not. Only for scenes that are
    never evaluated on. Other arguments and errors as :func:`finetune`; ``before``/``after`` are None.
    """
    scenes = list(scenes)
    if not scenes:
        raise InputError("scenes: expected at least one scene to pre-train on, got none")
    held = sorted({int(k) for k in held_out_scenes})
    if held and not 0 <= held[0] <= held[-1] < len(scenes):
        raise InputError(f"held_out_scenes: expected positions in 0..{len(scenes) - 1}, got {held}")
    for k in held:
        if not scenes[k].indices("test"):
            raise InputError(f"held_out_scenes: scene {scenes[k].root} has no held-out views")
    return _fit(scenes, output_dir, kind="pretrain", checkpoint=checkpoint, config=config,
                progress=progress, should_stop=should_stop, resume=resume, held_out_scenes=held)
