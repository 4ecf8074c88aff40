"""3D Gaussian splatting on the CPU: fit splats to a photo set, render every view, write a scene folder.

Another kind of field for pre-training pairs (``make-pairs --preset splat``), with splats' own
artefacts (needles, popping, holes where no splat lands). The image formation is the library's
rasterizer (:func:`roguenerf.splats.render`, differentiable), so fitted splats render the same
in ``import-3dgs``. The fit follows Kerbl et al. 2023 at a CPU's scale:

* **init**: random points in the training cameras' frustums between their near and far bounds
  (uniform in inverse depth), coloured by the photo pixel they were drawn through, scaled by the
  distance to their three nearest neighbours, opacity 0.1;
* **optimise** means, log-scales, quaternions, opacity logits and SH (to ``sh_degree``) with
  Adam on ``(1 - λ) L1 + λ (1 - SSIM)`` of one training view per step, at ``1/scale`` of the
  photo size, against a random background colour (so empty space must stay empty);
* **densify** every ``densify_every`` steps in ``[densify_from, densify_until)`` of the budget:
  Gaussians whose mean view-space gradient (NDC units, as 3DGS) exceeds ``grad_threshold`` are
  cloned (small) or split in two (large, scale / 1.6), and **prune** those with opacity below
  ``prune_opacity`` or wider than ``prune_size`` × the scene extent;
* **resume**: the whole state (splats, Adam moments, gradient statistics, random generator, step)
  is one ``safetensors`` file in ``output/.fit/``, written atomically every
  ``checkpoint_every`` steps and on a stop; a finished ``fit.json`` with the same configuration
  is left as it is.

Renders are made at the photos' full size with a black background: RGB, expected z-depth (0
where the splats cover less than half the pixel) and opacity, plus the splats as
``point_cloud.ply``.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import os
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import ClassVar

import torch
import torch.nn.functional as F
from safetensors import safe_open
from safetensors.torch import save_file
from torch import Tensor

from roguefit.fitter import ConfigCheck, fit_steps
from roguefit.photos import PhotoSet
from roguenerf.errors import InputError
from roguenerf.splats import Gaussians, logit, render, write_ply
from roguenerf.splats.sh import C0

log = logging.getLogger("roguefit")

STATE_FILE = "splats.safetensors"
PLY_FILE = "point_cloud.ply"
FORMAT_VERSION = 1
_PARAMS = ("means", "sh", "opacity", "log_scales", "quats")


@dataclasses.dataclass(frozen=True)
class SplatConfig:
    """How to fit one splat scene (see the module's docstring). Budgets: ``steps`` wins over
    ``minutes`` when both are given."""

    kind: ClassVar[str] = "splat"
    """Its key in :data:`roguefit.registry.FITTERS` (not a field: ``identity`` names it ``field``)."""
    steps: int | None = 1000
    minutes: float | None = None
    scale: int = 2
    """The fit sees the photos at 1/scale of their size (the renders are made at full size)."""
    init_points: int = 6000
    """Random points the splats start from, in the training cameras' frustums."""
    sh_degree: int = 1
    lr_means: float = 1.6e-3
    """Times the scene extent."""
    lr_sh: float = 2.5e-3
    lr_opacity: float = 0.05
    lr_scales: float = 5e-3
    lr_quats: float = 1e-3
    ssim_weight: float = 0.2
    """λ of the loss ``(1 - λ) L1 + λ (1 - SSIM)``."""
    densify_from: float = 0.1
    densify_until: float = 0.7
    """Densification runs in ``[densify_from, densify_until)`` of the budget ..."""
    densify_every: int = 50
    """... every this many steps."""
    grad_threshold: float = 2e-4
    """Mean view-space gradient (NDC units) above which a Gaussian is cloned or split."""
    dense_share: float = 0.01
    """A Gaussian wider than this share of the scene extent is split, a smaller one cloned."""
    prune_opacity: float = 0.005
    prune_size: float = 0.5
    """Gaussians below ``prune_opacity`` or wider than ``prune_size`` × the extent are pruned."""
    max_gaussians: int = 20000
    """Densification stops growing the splats at this count (the largest gradients first)."""
    seed: int = 0
    hold: int = 8
    folds: int = 1
    """Cross-fitting, as :attr:`roguefit.fit.FitConfig.folds`."""
    checkpoint_every: int = 50
    """Steps between two saves of the whole state (a stopped fit resumes from the last)."""

    def __post_init__(self) -> None:
        """The one validation of a splat fit's configuration (:class:`~roguefit.fitter.ConfigCheck`)."""
        check = ConfigCheck(self)
        check.budget()
        for name, low in (("scale", 1), ("init_points", 1), ("densify_every", 1), ("max_gaussians", 1),
                          ("hold", 2), ("folds", 1), ("checkpoint_every", 1)):
            check.integer(name, low)
        check.integer("sh_degree", 0, 3)
        check.integer("seed")
        for name in ("lr_means", "lr_sh", "lr_opacity", "lr_scales", "lr_quats", "grad_threshold", "dense_share",
                     "prune_size"):
            check.number(name, positive=True)
        for name in ("ssim_weight", "densify_from", "densify_until", "prune_opacity"):
            check.number(name, positive=False, high=1.0)
        if self.densify_from > self.densify_until:
            check.fail("densify_until", f"at least densify_from ({self.densify_from:g})")

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    def identity(self) -> dict:
        """The keys that define the result (not the checkpoint cadence), with the field's kind."""
        d = {"field": "splat", **self.to_dict()}
        d.pop("checkpoint_every")
        if d["folds"] == 1:
            d.pop("folds")
        return d


def _scaled(ps: PhotoSet, scale: int) -> tuple[Tensor, Tensor, int, int]:
    """Photos and K at ``1/scale`` of the photo size (area average; same image extent)."""
    if scale == 1:
        return ps.photos, ps.K.clone(), ps.height, ps.width
    h, w = max(1, ps.height // scale), max(1, ps.width // scale)
    photos = F.interpolate(ps.photos, size=(h, w), mode="area")
    K = ps.K.clone()
    K[:, 0] *= w / ps.width
    K[:, 1] *= h / ps.height
    return photos, K, h, w


def config_scale(config: SplatConfig) -> float:
    """Photo pixels per fitting pixel."""
    return float(config.scale)


def _knn_scale(points: Tensor, k: int = 3, chunk: int = 2048) -> Tensor:
    """Mean distance of each point to its ``k`` nearest neighbours ``(N,)``."""
    out = []
    for s in range(0, points.shape[0], chunk):
        d = torch.cdist(points[s:s + chunk], points)
        d[torch.arange(d.shape[0]), torch.arange(s, s + d.shape[0])] = float("inf")
        out.append(d.topk(min(k, points.shape[0] - 1), largest=False).values.mean(-1))
    return torch.cat(out)


@contextmanager
def one_thread() -> Iterator[None]:
    """Run torch on one thread inside (restored after). The rasterizer is many small tensor
    operations on the CPU: a second thread gains nothing on them and, when the other core is busy,
    makes a step several times slower (measured 8x on 2 loaded cores, docs/splats.md); one thread
    also makes the sums' order, so the fit, repeatable."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(threads)


class SplatFitter:
    """Fits Gaussian splats (kind "splat"): the :class:`~roguefit.fitter.Fitter` of a :class:`SplatConfig`."""

    def __init__(self, ps: PhotoSet, config: SplatConfig, state_dir: Path):
        self.ps, self.config, self.state_dir = ps, config, state_dir
        self.train = ps.indices("train")
        if len(self.train) < 2:
            raise InputError(f"photo set: expected at least 2 training views, got {len(self.train)}")
        self.photos, self.K, self.height, self.width = _scaled(ps, config.scale)
        centres = ps.world_from_cam[self.train, :3, 3]
        self.extent = float(1.1 * (centres - centres.mean(0)).norm(dim=-1).max().clamp_min(1e-6))
        self.generator = torch.Generator().manual_seed(config.seed)
        self.step, self.elapsed = 0, 0.0
        self._init_gaussians()

    # -- state -------------------------------------------------------------------------------
    def _init_gaussians(self) -> None:
        c, ps, g = self.config, self.ps, self.generator
        n = c.init_points
        view = torch.tensor(self.train)[torch.randint(0, len(self.train), (n,), generator=g)]
        u = torch.rand(n, generator=g, dtype=torch.float64) * ps.width
        v = torch.rand(n, generator=g, dtype=torch.float64) * ps.height
        near, far = ps.near[view], ps.far[view]
        t = torch.rand(n, generator=g, dtype=torch.float64)
        z = 1.0 / (1.0 / near * (1 - t) + 1.0 / far * t)
        K, pose = ps.K[view], ps.world_from_cam[view]
        cam = torch.stack([(u - K[:, 0, 2]) / K[:, 0, 0] * z, (v - K[:, 1, 2]) / K[:, 1, 1] * z, z], -1)
        points = (pose[:, :3, :3] @ cam[..., None])[..., 0] + pose[:, :3, 3]
        colour = ps.photos[view, :, v.long().clamp(max=ps.height - 1), u.long().clamp(max=ps.width - 1)]
        k = (c.sh_degree + 1) ** 2
        sh = torch.zeros(n, k, 3)
        sh[:, 0] = (colour - 0.5) / C0
        # The distance to the nearest points, kept between half a pixel and two pixels of the view
        # the point was drawn through: random points fill a large volume sparsely, and splats
        # much wider than that start as a blur over the whole image (and cost every pixel).
        pixel = (z / K[:, 0, 0]).float() * config_scale(c)
        scales = torch.minimum(torch.maximum(_knn_scale(points.float()), 0.5 * pixel), 2.0 * pixel).clamp_min(1e-7)
        self.params = {
            "means": points.float(), "sh": sh, "opacity": torch.full((n,), logit(0.1)),
            "log_scales": torch.log(scales)[:, None].repeat(1, 3), "quats": torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1),
        }
        self._make_optimizer()
        self._reset_stats()

    def _reset_stats(self) -> None:
        n = self.params["means"].shape[0]
        self.grad_sum = torch.zeros(n)
        self.grad_count = torch.zeros(n)

    def _make_optimizer(self, states: dict | None = None) -> None:
        c = self.config
        lrs = {"means": c.lr_means * self.extent, "sh": c.lr_sh, "opacity": c.lr_opacity,
               "log_scales": c.lr_scales, "quats": c.lr_quats}
        for name in _PARAMS:
            self.params[name] = self.params[name].detach().requires_grad_(True)
        groups = [{"params": [self.params[name]], "lr": lrs[name], "name": name} for name in _PARAMS]
        self.optimizer = torch.optim.Adam(groups, betas=(0.9, 0.999), eps=1e-15)
        if states:
            for name in _PARAMS:
                if name in states:
                    self.optimizer.state[self.params[name]] = states[name]

    def gaussians(self) -> Gaussians:
        p = self.params
        return Gaussians(means=p["means"], sh=p["sh"], opacity=p["opacity"], log_scales=p["log_scales"],
                         quats=p["quats"])

    def save(self) -> None:
        self.state_dir.mkdir(parents=True, exist_ok=True)
        tensors = {f"p.{k}": v.detach().contiguous() for k, v in self.params.items()}
        for name in _PARAMS:
            st = self.optimizer.state.get(self.params[name], {})
            for key in ("exp_avg", "exp_avg_sq"):
                if key in st:
                    tensors[f"adam.{name}.{key}"] = st[key].contiguous()
            if "step" in st:
                tensors[f"adam.{name}.step"] = torch.as_tensor(st["step"], dtype=torch.float32).reshape(1)
        tensors["grad_sum"], tensors["grad_count"] = self.grad_sum, self.grad_count
        tensors["rng"] = self.generator.get_state()
        meta = {"format_version": str(FORMAT_VERSION), "config": json.dumps(self.config.identity()),
                "step": str(self.step), "elapsed": repr(self.elapsed)}
        tmp = self.state_dir / (STATE_FILE + ".tmp")
        save_file(tensors, str(tmp), metadata=meta)
        with open(tmp, "rb") as f:
            os.fsync(f.fileno())
        tmp.replace(self.state_dir / STATE_FILE)

    def load(self) -> bool:
        path = self.state_dir / STATE_FILE
        if not path.is_file():
            return False
        try:
            with safe_open(str(path), framework="pt") as f:
                meta = f.metadata() or {}
                tensors = {k: f.get_tensor(k) for k in f.keys()}  # noqa: SIM118 - safe_open has no iterator
        except (OSError, ValueError, RuntimeError) as exc:
            log.warning("ignoring unreadable splat state %s (%s): starting over", path, exc)
            return False
        if meta.get("format_version") != str(FORMAT_VERSION) or \
                meta.get("config") != json.dumps(self.config.identity()):
            log.warning("splat state in %s was made with another configuration: starting over", self.state_dir)
            return False
        self.params = {name: tensors[f"p.{name}"] for name in _PARAMS}
        states = {}
        for name in _PARAMS:
            if f"adam.{name}.exp_avg" in tensors:
                states[name] = {"step": tensors[f"adam.{name}.step"][0].clone(),
                                "exp_avg": tensors[f"adam.{name}.exp_avg"],
                                "exp_avg_sq": tensors[f"adam.{name}.exp_avg_sq"]}
        self._make_optimizer(states)
        self.grad_sum, self.grad_count = tensors["grad_sum"], tensors["grad_count"]
        self.generator.set_state(tensors["rng"])
        self.step, self.elapsed = int(meta["step"]), float(meta["elapsed"])
        return True

    # -- training ----------------------------------------------------------------------------
    def fraction(self) -> float:
        c = self.config
        if c.steps is not None:
            return self.step / c.steps
        return self.elapsed / (c.minutes * 60.0)

    def train_step(self) -> float:
        from roguenerf.metrics import ssim

        c = self.config
        view = self.train[int(torch.randint(0, len(self.train), (1,), generator=self.generator))]
        background = torch.rand(3, generator=self.generator)
        if not all(bool(torch.isfinite(p).all()) for p in self.params.values()):
            return math.nan  # the last step diverged: render refuses non-finite splats, the run calls it divergence
        rgb, _, _, info = render(self.gaussians(), self.ps.world_from_cam[view], self.K[view], self.height,
                                 self.width, background=background, depth_threshold=1.0, return_info=True)
        target = self.photos[view]
        l1 = (rgb - target).abs().mean()
        loss = (1 - c.ssim_weight) * l1
        if c.ssim_weight > 0:
            loss = loss + c.ssim_weight * (1 - ssim(rgb[None].clamp(0, 1), target[None])[0])
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        grad = info["means2d"].grad
        if grad is not None:
            ndc = grad * torch.tensor([self.width / 2.0, self.height / 2.0])
            seen = info["visible"]
            self.grad_sum[seen] += ndc[seen].norm(dim=-1)
            self.grad_count[seen] += 1
        self.optimizer.step()
        with torch.no_grad():
            mse = float(((rgb.detach().clamp(0, 1) - target) ** 2).mean())
        return mse

    def _edit(self, keep: Tensor, extra: dict[str, Tensor]) -> None:
        """Keep the rows ``keep`` (bool) and append ``extra``; Adam moments follow (zeros for new rows)."""
        states = {}
        for name in _PARAMS:
            old = self.params[name]
            st = self.optimizer.state.get(old, {})
            new = torch.cat([old.detach()[keep], extra[name]])
            if st:
                pad = torch.zeros((extra[name].shape[0],) + old.shape[1:])
                states[name] = {"step": st["step"],
                                "exp_avg": torch.cat([st["exp_avg"][keep], pad]),
                                "exp_avg_sq": torch.cat([st["exp_avg_sq"][keep], pad])}
            self.params[name] = new
        self._make_optimizer(states)
        self._reset_stats()

    @torch.no_grad()
    def densify_and_prune(self) -> None:
        c, p = self.config, self.params
        n = p["means"].shape[0]
        avg = self.grad_sum / self.grad_count.clamp_min(1)
        scales = torch.exp(p["log_scales"].detach())
        big = scales.max(-1).values > c.dense_share * self.extent
        grow = (avg >= c.grad_threshold) & (self.grad_count > 0)
        room = max(c.max_gaussians - n, 0)
        if int(grow.sum()) > room:  # keep the largest gradients
            idx = torch.nonzero(grow).squeeze(1)
            grow = torch.zeros_like(grow)
            grow[idx[avg[idx].topk(room).indices]] = True
        clone, split = grow & ~big, grow & big
        extra = {name: p[name].detach()[clone] for name in _PARAMS}
        if split.any():
            s_idx = torch.nonzero(split).squeeze(1).repeat(2)
            from roguenerf.splats import quat_to_rotmat

            R = quat_to_rotmat(p["quats"].detach()[s_idx])
            offset = torch.randn(s_idx.numel(), 3, generator=self.generator) * scales[s_idx]
            halves = {name: p[name].detach()[s_idx] for name in _PARAMS}
            halves["means"] = halves["means"] + (R @ offset[..., None])[..., 0]
            halves["log_scales"] = halves["log_scales"] - math.log(1.6)
            extra = {name: torch.cat([extra[name], halves[name]]) for name in _PARAMS}
        opac = torch.sigmoid(p["opacity"].detach())
        keep = ~split & (opac >= c.prune_opacity) & (scales.max(-1).values <= c.prune_size * self.extent)
        self._edit(keep, extra)

    def run(self, progress: Callable[[dict], None] | None, should_stop: Callable[[], bool] | None) -> None:
        with one_thread():
            self._run(progress, should_stop)

    def _run(self, progress: Callable[[dict], None] | None, should_stop: Callable[[], bool] | None) -> None:
        c = self.config

        def densify() -> None:
            if c.densify_from <= self.fraction() < c.densify_until and self.step % c.densify_every == 0:
                self.densify_and_prune()

        def checkpoint() -> None:
            if self.step % c.checkpoint_every == 0:
                self.save()

        fit_steps(self, progress, should_stop, after_step=densify, checkpoint=checkpoint,
                  report=lambda: {"gaussians": len(self.params["means"])})

    def summary(self) -> dict:
        """The splats' own entries of the fit report."""
        return {"gaussians": len(self.params["means"]), "extent": self.extent}

    def write_extras(self, output: Path) -> None:
        """The fitted splats as Inria's ``point_cloud.ply`` (``import-3dgs`` reads it)."""
        output.mkdir(parents=True, exist_ok=True)
        write_ply(output / PLY_FILE, self.gaussians())

    @torch.no_grad()
    def render_view(self, i: int) -> tuple[Tensor, Tensor, Tensor]:
        with one_thread():
            rgb, depth, acc = render(self.gaussians().detach(), self.ps.world_from_cam[i], self.ps.K[i],
                                     self.ps.height, self.ps.width)
        return rgb.clamp(0, 1), depth, acc.clamp(0, 1)


