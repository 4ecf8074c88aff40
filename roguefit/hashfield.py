"""An Instant-NGP style radiance field for the CPU: a multi-resolution hash encoding, a small
density MLP and view-dependent colour from spherical harmonics of the direction.

Another kind of field than :class:`~roguefit.field.GridField`'s dense grids, with its own look
(the one nerfacto and Instant-NGP renders have: sharp where the hash tables resolve detail,
hash-collision noise and floaters elsewhere), so that pre-training pairs and the
leave-one-kind-out figure can include it. It keeps :class:`GridField`'s world: the same
contraction, occupancy grid, sample placement, volume rendering, median depth and early
ray termination (it subclasses it and replaces only what a sample's density and colour are).

Encoding (Müller et al. 2022): ``L`` levels with grid resolutions growing geometrically from
``base`` to ``finest`` over the contracted cube; per level a table of ``T`` vectors of ``F``
features. A grid vertex indexes its level's table directly where the level has no more vertices
than ``T`` (a dense grid), and through the spatial hash ``(x * 1 ^ y * 2654435761 ^ z * 805459861)
mod T`` otherwise; a point's feature is the trilinear interpolation of its cell's 8 vertices.
Pure PyTorch (gathers; their backward is a scatter-add).

Its fitter, :class:`HashFitter` (kind "hash", a :class:`~roguefit.fit.FitConfig` with
``kind="hash"``), is :class:`~roguefit.fit.GridFitter` making a :class:`HashField` instead.

Dimension legend: P points, L levels, F features per level, G geometry features, K SH coefficients.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from roguefit.field import DENSITY_SHIFT, GridField
from roguefit.fit import FitConfig, GridFitter

HASH_PRIMES = (1, 2654435761, 805459861)
"""Instant-NGP's primes of the spatial hash (x, y, z)."""
MAX_LOG_DENSITY = 15.0
"""Clamp of the log-density before ``exp``."""
GEO_FEATURES = 15
"""Features the density MLP hands the colour MLP besides the density (Instant-NGP: 15)."""

_CORNERS = torch.tensor([[(c >> 0) & 1, (c >> 1) & 1, (c >> 2) & 1] for c in range(8)], dtype=torch.int64)
"""The 8 vertices of a cell as (dx, dy, dz) offsets."""


def level_resolutions(levels: int, base: int, finest: int) -> list[int]:
    """Grid resolutions of the levels: ``floor(base * b^l)``, ``b = (finest / base)^(1 / (L - 1))``."""
    if levels == 1:
        return [int(base)]
    growth = math.exp((math.log(finest) - math.log(base)) / (levels - 1))
    return [int(math.floor(base * growth**level + 1e-6)) for level in range(levels)]


class HashEncoding(nn.Module):
    """Multi-resolution hash encoding of points in ``[0, 1]^3`` -> ``(P, L * F)`` (level-major).

    Args:
        levels: L. log2_table: ``T = 2^log2_table`` rows per level. features: F per level.
        base, finest: resolutions of the coarsest and finest level.
    """

    def __init__(self, levels: int = 12, log2_table: int = 16, features: int = 2, base: int = 16,
                 finest: int = 512):
        super().__init__()
        if levels < 1 or features < 1 or not 4 <= log2_table <= 24 or not 1 <= base <= finest:
            raise ValueError(f"hash encoding: bad sizes (levels {levels}, log2_table {log2_table}, "
                             f"features {features}, base {base}, finest {finest})")
        self.levels, self.features, self.table_size = int(levels), int(features), 2 ** int(log2_table)
        self.resolutions = level_resolutions(self.levels, int(base), int(finest))
        # Instant-NGP's initialisation: small uniform values.
        self.tables = nn.Parameter(torch.empty(self.levels, self.table_size, self.features).uniform_(-1e-4, 1e-4))

    @property
    def out_features(self) -> int:
        return self.levels * self.features

    def forward(self, x: Tensor) -> Tensor:
        """``x`` ``(P, 3)`` in [0, 1] (clamped) -> ``(P, L * F)``."""
        x = x.clamp(0.0, 1.0)
        p = x.shape[0]
        out = []
        flat = self.tables.reshape(-1, self.features)
        t = self.table_size
        for level, res in enumerate(self.resolutions):
            pos = x * res
            cell = pos.floor().clamp_(max=res - 1)
            frac = pos - cell                                                      # (P, 3)
            lo = cell.long()
            # Per axis the two vertex coordinates' terms, combined over the 8 corners by
            # broadcasting (corner c = (dx, dy, dz) bits 0, 1, 2 as _CORNERS): (P, 2z, 2y, 2x).
            ax = [torch.stack([lo[:, a], lo[:, a] + 1], dim=1) for a in range(3)]  # (P, 2) each
            side = res + 1
            if side**3 <= t:
                rows = (ax[0].view(p, 1, 1, 2) + side * ax[1].view(p, 1, 2, 1)
                        + (side * side) * ax[2].view(p, 2, 1, 1))
            else:
                rows = torch.bitwise_xor(torch.bitwise_xor(ax[0].view(p, 1, 1, 2) * HASH_PRIMES[0],
                                                           ax[1].view(p, 1, 2, 1) * HASH_PRIMES[1]),
                                         ax[2].view(p, 2, 1, 1) * HASH_PRIMES[2]) & (t - 1)
            rows = rows.reshape(p, 8) + level * t
            wa = [torch.stack([1.0 - frac[:, a], frac[:, a]], dim=1) for a in range(3)]
            w = (wa[0].view(p, 1, 1, 2) * wa[1].view(p, 1, 2, 1) * wa[2].view(p, 2, 1, 1)).reshape(p, 8)
            # F.embedding: a gather whose CPU backward sums duplicate rows in a fixed order
            # (indexing's scatter-add is threaded and not), so a resumed fit equals an unbroken one.
            out.append((F.embedding(rows, flat) * w[..., None]).sum(dim=1))          # (P, F)
        return torch.cat(out, dim=-1)


def spherical_harmonics(dirs: Tensor, degree: int = 3) -> Tensor:
    """Real spherical harmonics (orthonormal on the sphere) of unit ``dirs`` ``(P, 3)`` up to
    ``degree`` (0..3) -> ``(P, (degree + 1)^2)``, in the order of Instant-NGP and nerfstudio."""
    if not 0 <= degree <= 3:
        raise ValueError(f"spherical harmonics: degree 0..3, got {degree}")
    x, y, z = dirs.unbind(-1)
    out = [torch.full_like(x, 0.28209479177387814)]
    if degree >= 1:
        out += [-0.48860251190291987 * y, 0.48860251190291987 * z, -0.48860251190291987 * x]
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        out += [1.0925484305920792 * x * y, -1.0925484305920792 * y * z,
                0.94617469575755997 * zz - 0.31539156525251999,
                -1.0925484305920792 * x * z, 0.54627421529603959 * (xx - yy)]
    if degree >= 3:
        out += [0.59004358992664352 * y * (-3.0 * xx + yy), 2.8906114426405538 * x * y * z,
                0.45704579946446572 * y * (1.0 - 5.0 * zz), 0.3731763325901154 * z * (5.0 * zz - 3.0),
                0.45704579946446572 * x * (1.0 - 5.0 * zz), 1.4453057213202769 * z * (xx - yy),
                0.59004358992664352 * x * (-xx + 3.0 * yy)]
    return torch.stack(out, dim=-1)


class HashField(GridField):
    """Hash-encoded density and view-dependent colour over :class:`GridField`'s contracted world.

    Args:
        centre, radius: the contraction (as :class:`GridField`).
        levels, log2_table, features, base, finest: the :class:`HashEncoding` (over the contracted
            cube [-1, 1]^3; the inner, uncontracted cube is its middle half).
        hidden: width of both MLPs. sh_degree: degree of the direction's spherical harmonics.
    """

    def __init__(self, centre: Tensor, radius: float, *, levels: int = 12, log2_table: int = 16,
                 features: int = 2, base: int = 16, finest: int = 512, hidden: int = 64, sh_degree: int = 3,
                 occupancy_size: int = 64):
        nn.Module.__init__(self)
        self.register_buffer("centre", torch.as_tensor(centre, dtype=torch.float32).reshape(3))
        self.radius = float(radius)
        self.features = 0
        self.encoding = HashEncoding(levels, log2_table, features, base, finest)
        self.density_mlp = nn.Sequential(nn.Linear(self.encoding.out_features, hidden), nn.ReLU(inplace=True),
                                         nn.Linear(hidden, 1 + GEO_FEATURES))
        self.sh_degree = int(sh_degree)
        self.colour_mlp = nn.Sequential(
            nn.Linear(GEO_FEATURES + (self.sh_degree + 1) ** 2, hidden), nn.ReLU(inplace=True),
            nn.Linear(hidden, hidden), nn.ReLU(inplace=True), nn.Linear(hidden, 3))
        self.mlp = None
        self.use_mlp = True
        self.register_buffer("occupancy", torch.ones(occupancy_size, occupancy_size, occupancy_size, dtype=torch.bool))

    @property
    def resolution(self) -> int:
        """The finest level's resolution (what the progress bar shows as the grid)."""
        return int(self.encoding.resolutions[-1])

    def param_groups(self, lr_grid: float, lr_mlp: float) -> list[dict]:
        return [{"params": [self.encoding.tables], "lr": lr_grid},
                {"params": list(self.density_mlp.parameters()) + list(self.colour_mlp.parameters()), "lr": lr_mlp}]

    def _density(self, u: Tensor) -> tuple[Tensor, Tensor]:
        h = self.density_mlp(self.encoding((u + 1.0) * 0.5))
        # Instant-NGP's exponential density (clamped against overflow): an opaque surface is a
        # raw value of ~5, which a small MLP reaches in tens of steps (softplus would need ~50).
        return torch.exp((h[:, 0] + DENSITY_SHIFT).clamp(max=MAX_LOG_DENSITY)), h[:, 1:]

    def sigma(self, u: Tensor) -> Tensor:
        return self._density(u)[0]

    def rgb(self, u: Tensor, dirs: Tensor) -> Tensor:
        return self._colour(self._density(u)[1], dirs)

    def _colour(self, geo: Tensor, dirs: Tensor) -> Tensor:
        return torch.sigmoid(self.colour_mlp(torch.cat([geo, spherical_harmonics(dirs, self.sh_degree)], dim=-1)))

    # One pass per sample, as Instant-NGP: the density MLP's geometry features of the samples the
    # renderer kept are reused for the colour of those it shades (a subset), not recomputed.
    def _sigma_of(self, u: Tensor, keep: Tensor) -> Tensor:
        sigma, geo = self._density(u[keep])
        self._geo = (u, keep, geo)
        return sigma

    def _rgb_of(self, u: Tensor, shade: Tensor, unit: Tensor) -> Tensor:
        cached = getattr(self, "_geo", None)
        self._geo = None
        if cached is None or cached[0] is not u:
            return self.rgb(u[shade], unit[shade])
        _, keep, geo = cached
        if bool((shade & ~keep).any()):
            return self.rgb(u[shade], unit[shade])
        # Position of each shaded sample among the kept ones (shade implies keep).
        rank = torch.cumsum(keep.reshape(-1), 0) - 1
        return self._colour(geo[rank[shade.reshape(-1)]], unit[shade])

    @torch.no_grad()
    def upsample(self, resolution: int) -> None:
        """Nothing to resample: the levels are fixed (the fit's grow plan has one level)."""

    @torch.no_grad()
    def prune(self, seen: Tensor, alpha_threshold: float = 1e-4, generator: torch.Generator | None = None,
              chunk: int = 65536) -> float:
        """Occupancy = seen by a training camera and not negligibly transparent at the cell's
        centre or at a random point in it; returns the kept fraction."""
        g = self.occupancy.shape[0]
        c = torch.arange(g, dtype=torch.float32)
        zz, yy, xx = torch.meshgrid(c, c, c, indexing="ij")
        cells = torch.stack([xx, yy, zz], dim=-1).reshape(-1, 3)
        idx = seen.reshape(-1).nonzero()[:, 0]
        if generator is None:  # the same cells' points every call: a resumed fit prunes as an unbroken one
            generator = torch.Generator().manual_seed(0)
        sigma = torch.zeros(g**3)
        for offset in (torch.full((idx.numel(), 3), 0.5), torch.rand(idx.numel(), 3, generator=generator)):
            u = (cells[idx] + offset) / g * 2.0 - 1.0
            for s in range(0, idx.numel(), chunk):
                part = idx[s:s + chunk]
                sigma[part] = torch.maximum(sigma[part], self.sigma(u[s:s + chunk]))
        voxel = 4.0 / g
        dense = ((1.0 - torch.exp(-sigma * voxel)) > alpha_threshold).reshape(g, g, g)
        self.occupancy = seen & dense
        return float(self.occupancy.float().mean())

    def total_variation(self, block: int, generator: torch.Generator) -> Tensor:
        """No grid to smooth: 0 (the hash preset sets ``tv_weight`` 0)."""
        return self.encoding.tables.new_zeros(())


class HashFitter(GridFitter):
    """Fits a :class:`HashField` (kind "hash"): :class:`~roguefit.fit.GridFitter`'s fit, resume
    and renders; only the field differs (its levels are fixed: the grow plan has one)."""

    @staticmethod
    def new_field(config: FitConfig, centre: Tensor, radius: float, resolution: int | None = None) -> HashField:
        """The untrained :class:`HashField` of ``config`` (finest level ``config.resolution``;
        ``resolution`` is ignored)."""
        return HashField(centre, radius, levels=config.hash_levels, log2_table=config.hash_log2_table,
                         features=config.hash_features, base=config.hash_base, finest=config.resolution,
                         sh_degree=config.sh_degree)

    def _first_field(self, centre: Tensor, radius: float) -> HashField:
        with torch.random.fork_rng(devices=[]):  # random initial weights from the config's seed alone
            torch.manual_seed(self.config.seed)
            return self.new_field(self.config, centre, radius)
