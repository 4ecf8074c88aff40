"""The dense-grid and hash-grid fields' fitter: :class:`FitConfig` (kinds "grid" and "hash") and
:class:`GridFitter` (a :class:`~roguefit.fitter.Fitter`).

It fits a :class:`GridField` (or, through :class:`~roguefit.hashfield.HashFitter`, a
:class:`~roguefit.hashfield.HashField`) to a photo set's training views with random rays, grows
the grid coarse to fine, prunes the occupancy grid, and resumes from ``state_dir``
(``state.safetensors`` + ``state.json``, saved every ``checkpoint_every_s`` seconds and on Ctrl-C).
:func:`roguefit.pairs.make_pairs` drives it.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import time
from collections.abc import Callable
from pathlib import Path

import torch
import torch.nn.functional as F
from safetensors.torch import load_file, save_file
from torch import Tensor

from roguefit.field import GridField, scene_frame, seen_by_cameras
from roguefit.fitter import ConfigCheck, fit_steps
from roguefit.photos import PhotoSet
from roguenerf.errors import InputError
from roguenerf.imageio import atomic_write

log = logging.getLogger("roguefit")

FIELD_KINDS = ("grid", "hash")
"""The kinds of field a :class:`FitConfig` describes (both registered in :data:`roguefit.registry.FITTERS`)."""
HASH_KEYS = ("hash_levels", "hash_log2_table", "hash_features", "hash_base", "sh_degree")
FORMAT_VERSION = 1
"""Of the resume state (``state.json``)."""


@dataclasses.dataclass(frozen=True)
class FitConfig:
    """How to fit one field."""

    resolution: int = 160
    """Final grid side; the fit starts at half of it and grows (coarse to fine) at ``grow_at``
    fractions of the budget."""
    features: int = 6
    """Colour-feature channels read by the view-dependent MLP (0: an RGB grid, view-independent)."""
    rays: int = 2048
    """Rays per step."""
    samples: int = 64
    """Samples per ray (spaced in inverse depth)."""
    lr_grid: float = 0.1
    lr_mlp: float = 2e-3
    tv_weight: float = 1e-4
    """Weight of the density's total variation (mean squared neighbour difference over a random
    32³ block of the grid)."""
    distortion_weight: float = 0.01
    grow_at: tuple[float, ...] = (0.15, 0.35)
    prune_every: int = 200
    """Steps between prunings of the occupancy grid (cells no training camera sees, or all but
    transparent)."""
    minutes: float | None = 10.0
    steps: int | None = None
    """The budget: ``steps`` wins over ``minutes`` when both are given."""
    seed: int = 0
    hold: int = 8
    """Every ``hold``-th view (0, hold, 2 hold, ...) is held out: a test view."""
    folds: int = 1
    """Cross-fitting (:func:`make_pairs`): K > 1 fields, each rendering the training views it
    never saw; 1: one field, its own training views rendered."""
    checkpoint_every_s: float = 60.0
    render_scale: int = 1
    """Render every view at 1/render_scale of the photo size and upsample (bilinear) to it: a
    cheap render for a field whose voxels already span several pixels, where it changes almost
    nothing but costs render_scale² fewer rays."""
    kind: str = "grid"
    """"grid": :class:`GridField` (dense grids); "hash": :class:`~roguefit.hashfield.HashField`
    (Instant-NGP's multi-resolution hash encoding, ``resolution`` its finest level, with the
    ``hash_*`` sizes and spherical harmonics of ``sh_degree``; ``features`` and ``grow_at``
    unused)."""
    hash_levels: int = 12
    """Levels of the hash encoding, from ``hash_base`` cells a side to ``resolution``."""
    hash_log2_table: int = 16
    """Entries of each level's table, as a power of two."""
    hash_features: int = 2
    """Features per level."""
    hash_base: int = 16
    sh_degree: int = 3
    """Degree of the spherical harmonics of the hash field's colour."""

    def __post_init__(self) -> None:
        """The one validation of a fit's configuration (:class:`~roguefit.fitter.ConfigCheck`)."""
        check = ConfigCheck(self)
        for name, low in (("resolution", 4), ("features", 0), ("rays", 1), ("samples", 2), ("prune_every", 1),
                          ("hold", 2), ("render_scale", 1), ("folds", 1)):
            check.integer(name, low)
        check.integer("seed")
        check.budget()
        for name in ("lr_grid", "lr_mlp", "checkpoint_every_s"):
            check.number(name, positive=True)
        for name in ("tv_weight", "distortion_weight"):
            check.number(name, positive=False)
        try:
            grow = [float(g) for g in self.grow_at]
        except (TypeError, ValueError):
            check.fail("grow_at", "fractions of the budget")
        if any(not (0 < g < 1) for g in grow) or grow != sorted(grow):
            check.fail("grow_at", "increasing fractions in (0, 1)")
        if self.kind not in FIELD_KINDS:
            check.fail("kind", f"one of {', '.join(FIELD_KINDS)}")
        if self.kind == "hash":
            bounds = {"hash_levels": (1, 32), "hash_log2_table": (4, 24), "hash_features": (1, 64),
                      "hash_base": (1, self.resolution), "sh_degree": (0, 3)}
            for name, (low, high) in bounds.items():
                value = getattr(self, name)
                if isinstance(value, bool) or not isinstance(value, int) or not low <= value <= high:
                    check.fail(name, f"an integer in [{low}, {high}] (the hash field)")

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d["grow_at"] = list(self.grow_at)
        return d

    def identity(self) -> dict:
        """The keys that define the result (not the checkpoint cadence)."""
        d = self.to_dict()
        d.pop("checkpoint_every_s")
        if d["render_scale"] == 1:  # fits made before the option existed stay complete
            d.pop("render_scale")
        if d["folds"] == 1:
            d.pop("folds")
        if d["kind"] == "grid":  # likewise: grid fits carry no hash keys
            for key in ("kind", *HASH_KEYS):
                d.pop(key)
        return d


def camera_rays(K: Tensor, world_from_cam: Tensor, v: Tensor, u: Tensor) -> tuple[Tensor, Tensor]:
    """Rays through pixel centres ``(v, u)`` (row, col) of cameras ``K (B,3,3)``, ``world_from_cam (B,4,4)``.

    Returns origins and directions ``(B, 3)`` float32 with the direction's camera-z equal to 1, so
    the ray parameter is z-depth.
    """
    x = (u.to(torch.float64) + 0.5 - K[:, 0, 2]) / K[:, 0, 0]
    y = (v.to(torch.float64) + 0.5 - K[:, 1, 2]) / K[:, 1, 1]
    d_cam = torch.stack([x, y, torch.ones_like(x)], dim=-1)
    dirs = (world_from_cam[:, :3, :3] @ d_cam[..., None])[..., 0]
    return world_from_cam[:, :3, 3].to(torch.float32), dirs.to(torch.float32)


def _grow_plan(config: FitConfig) -> list[int]:
    final = config.resolution
    levels = len(config.grow_at) + 1
    return [max(16, round(final * (0.5 + 0.5 * i / (levels - 1)))) for i in range(levels)] if levels > 1 else [final]


class GridFitter:
    """Fits a :class:`GridField` (kind "grid"): the :class:`~roguefit.fitter.Fitter` of a
    :class:`FitConfig`; :class:`~roguefit.hashfield.HashFitter` changes only the field it makes."""

    @staticmethod
    def new_field(config: FitConfig, centre: Tensor, radius: float, resolution: int | None = None) -> GridField:
        """The untrained field a fit with ``config`` trains over the contraction ``centre``,
        ``radius``: a :class:`GridField` at ``resolution`` (default ``config.resolution``)."""
        return GridField(centre, radius, config.resolution if resolution is None else resolution,
                         features=config.features)

    def _first_field(self, centre: Tensor, radius: float) -> GridField:
        """The field the fit starts from: at the grow plan's first resolution."""
        return self.new_field(self.config, centre, radius, self.levels[0])

    def __init__(self, ps: PhotoSet, config: FitConfig, state_dir: Path):
        self.ps, self.config, self.state_dir = ps, config, state_dir
        self.train = ps.indices("train")
        self.train_index = torch.as_tensor(self.train)
        if len(self.train) < 2:
            raise InputError(f"photo set: expected at least 2 training views, got {len(self.train)}")
        pose = ps.world_from_cam[self.train]
        self.near = (ps.near * 0.9).to(torch.float32)
        self.far = (ps.far * 1.2).to(torch.float32)
        centre, radius = scene_frame(pose, ps.near[self.train])
        self.levels = _grow_plan(config)
        self.field = self._first_field(centre, radius)
        self.seen = seen_by_cameras(self.field, pose, ps.K[self.train], self.near[self.train],
                                    self.far[self.train], ps.height, ps.width)
        self.field.occupancy = self.seen.clone()
        self.pixels = (ps.photos[self.train] * 255).round().to(torch.uint8).permute(0, 2, 3, 1).contiguous()
        self.generator = torch.Generator().manual_seed(config.seed)
        self.step = 0
        self.elapsed = 0.0
        self.level = 0
        self._make_optimizer()

    def _make_optimizer(self) -> None:
        groups = self.field.param_groups(self.config.lr_grid, self.config.lr_mlp)
        self.optimizer = torch.optim.Adam(groups, betas=(0.9, 0.99), eps=1e-15)

    # -- resume ------------------------------------------------------------------------------
    def save(self) -> None:
        self.state_dir.mkdir(parents=True, exist_ok=True)
        tensors = {f"model.{k}": v.detach().contiguous() for k, v in self.field.state_dict().items()}
        for gi, group in enumerate(self.optimizer.param_groups):
            for pi, p in enumerate(group["params"]):
                st = self.optimizer.state.get(p, {})
                for key in ("exp_avg", "exp_avg_sq"):
                    if key in st:
                        tensors[f"opt.{gi}.{pi}.{key}"] = st[key].contiguous()
                if "step" in st:
                    tensors[f"opt.{gi}.{pi}.step"] = torch.as_tensor(st["step"], dtype=torch.float32).reshape(1)
        tensors["rng"] = self.generator.get_state()
        tmp = self.state_dir / "state.safetensors.tmp"
        save_file(tensors, str(tmp))
        tmp.replace(self.state_dir / "state.safetensors")
        meta = {"format_version": FORMAT_VERSION, "config": self.config.identity(), "step": self.step,
                "elapsed": self.elapsed, "level": self.level, "resolution": self.field.resolution}
        atomic_write(self.state_dir / "state.json", json.dumps(meta).encode())

    def load(self) -> bool:
        meta_path, tensor_path = self.state_dir / "state.json", self.state_dir / "state.safetensors"
        if not (meta_path.is_file() and tensor_path.is_file()):
            return False
        try:
            meta = json.loads(meta_path.read_text())
            tensors = load_file(str(tensor_path))
        except (OSError, ValueError, json.JSONDecodeError) as exc:
            log.warning("ignoring unreadable fit state in %s (%s): starting over", self.state_dir, exc)
            return False
        if meta.get("format_version") != FORMAT_VERSION or meta.get("config") != self.config.identity():
            log.warning("fit state in %s was made with another configuration: starting over", self.state_dir)
            return False
        self.field.use_mlp = int(meta["level"]) > 0
        if meta["resolution"] != self.field.resolution:
            self.field.upsample(meta["resolution"])
        self.field.occupancy = tensors["model.occupancy"].to(torch.bool)
        self.field.load_state_dict({k[6:]: v for k, v in tensors.items() if k.startswith("model.")})
        self._make_optimizer()
        for gi, group in enumerate(self.optimizer.param_groups):
            for pi, p in enumerate(group["params"]):
                if f"opt.{gi}.{pi}.exp_avg" in tensors:
                    self.optimizer.state[p] = {
                        "step": tensors[f"opt.{gi}.{pi}.step"][0].clone(),
                        "exp_avg": tensors[f"opt.{gi}.{pi}.exp_avg"],
                        "exp_avg_sq": tensors[f"opt.{gi}.{pi}.exp_avg_sq"],
                    }
        self.generator.set_state(tensors["rng"])
        self.step, self.elapsed, self.level = int(meta["step"]), float(meta["elapsed"]), int(meta["level"])
        return True

    # -- training --------------------------------------------------------------------------
    def fraction(self) -> float:
        c = self.config
        if c.steps is not None:
            return self.step / max(c.steps, 1)
        return self.elapsed / max(c.minutes * 60.0, 1e-9)

    def train_step(self) -> float:
        c, ps = self.config, self.ps
        m = torch.randint(0, len(self.train), (c.rays,), generator=self.generator)
        v = torch.randint(0, ps.height, (c.rays,), generator=self.generator)
        u = torch.randint(0, ps.width, (c.rays,), generator=self.generator)
        views = self.train_index[m]
        origins, dirs = camera_rays(ps.K[views], ps.world_from_cam[views], v, u)
        target = self.pixels[m, v, u].to(torch.float32) / 255.0
        background = torch.rand(c.rays, 3, generator=self.generator)
        out = self.field.render(origins, dirs, self.near[views], self.far[views], c.samples, self.generator,
                                background=background)
        mse = F.mse_loss(out["rgb"], target)
        loss = mse
        if c.distortion_weight > 0:
            loss = loss + c.distortion_weight * out["distortion"].mean()
        if c.tv_weight > 0:
            loss = loss + c.tv_weight * self.field.total_variation(32, self.generator)
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        self.optimizer.step()
        return float(mse.detach())

    def run(self, progress: Callable[[dict], None] | None, should_stop: Callable[[], bool] | None) -> None:
        c = self.config
        last_save = time.monotonic()

        def grow() -> None:
            while self.level + 1 < len(self.levels) and self.fraction() >= c.grow_at[self.level]:
                self.level += 1
                self.field.upsample(self.levels[self.level])
                self.field.use_mlp = True
                self._make_optimizer()
                self.field.prune(self.seen)

        def prune() -> None:
            if self.step % c.prune_every == 0 and self.fraction() > 0.05:
                self.field.prune(self.seen)

        def checkpoint() -> None:
            nonlocal last_save
            if time.monotonic() - last_save > c.checkpoint_every_s:
                self.save()
                last_save = time.monotonic()

        fit_steps(self, progress, should_stop, before_step=grow, after_step=prune, checkpoint=checkpoint,
                  report=lambda: {"resolution": self.field.resolution,
                                  "occupied": float(self.field.occupancy.float().mean())})

    def summary(self) -> dict:
        """This field's own entries of the fit report."""
        return {"centre": [float(x) for x in self.field.centre], "radius": self.field.radius,
                "occupied_fraction": float(self.field.occupancy.float().mean())}

    def write_extras(self, output: Path) -> None:
        """Files beside the scene folder that only this kind of field writes: none."""

    # -- rendering -------------------------------------------------------------------------
    @torch.no_grad()
    def render_view(self, i: int, chunk: int = 16384) -> tuple[Tensor, Tensor, Tensor]:
        ps, c = self.ps, self.config
        full_h, full_w = ps.height, ps.width
        K = ps.K[i]
        h, w = full_h, full_w
        if c.render_scale > 1:
            # The low-resolution image covers the same extent (pixel centres at u + 0.5 in both),
            # which is what bilinear upsampling with align_corners=False assumes.
            h, w = max(1, round(full_h / c.render_scale)), max(1, round(full_w / c.render_scale))
            K = K.clone()
            K[0] *= w / full_w
            K[1] *= h / full_h
        vv, uu = torch.meshgrid(torch.arange(h), torch.arange(w), indexing="ij")
        vv, uu = vv.reshape(-1), uu.reshape(-1)
        rgb, depth, acc = [], [], []
        for s in range(0, h * w, chunk):
            v, u = vv[s:s + chunk], uu[s:s + chunk]
            n = v.shape[0]
            origins, dirs = camera_rays(K.expand(n, 3, 3), ps.world_from_cam[i].expand(n, 4, 4), v, u)
            out = self.field.render_fast(origins, dirs, self.near[i].expand(n), self.far[i].expand(n), c.samples)
            rgb.append(out["rgb"]), depth.append(out["depth"]), acc.append(out["acc"])
        rgb = torch.cat(rgb).reshape(h, w, 3).permute(2, 0, 1).clamp(0, 1)
        acc = torch.cat(acc).reshape(1, h, w).clamp(0, 1)
        depth = torch.cat(depth).reshape(1, h, w).to(torch.float32)
        if (h, w) != (full_h, full_w):
            up = torch.nn.functional.interpolate(torch.cat([rgb, depth, acc])[None], size=(full_h, full_w),
                                                 mode="bilinear", align_corners=False)[0]
            rgb, depth, acc = up[:3].clamp(0, 1), up[3:4], up[4:5].clamp(0, 1)
        return rgb, depth, acc
