"""A DVGO-style dense-grid radiance field for the CPU.

Geometry: a density grid and a colour-feature grid, sampled trilinearly
(``torch.nn.functional.grid_sample`` in 3D), over a *contracted* world: around the point every
camera looks at (``centre``) and inside ``radius`` the space is kept as it is; outside it the
L-infinity contraction of mip-NeRF 360 maps everything up to infinity into the shell
``1 < |x|_inf < 2``. That serves forward-facing captures (far content lands in the shell at the
lower resolution perspective gives it anyway) and object orbits (the object fills the inner cube)
with one representation. Samples are placed uniformly in inverse depth between each view's
near and far bound.

Colour: a feature grid read by a small MLP with the viewing direction (view-dependent), or, with
``features == 0``, an RGB grid (a view-independent, blurrier field). Empty space is skipped with
an occupancy grid (voxels no training camera sees, and voxels whose density became negligible);
colour is evaluated only where a sample's rendering weight is not negligible (early ray
termination, as DVGO does).

Dimension legend: B rays, S samples per ray, P kept samples, C feature channels, N grid side.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor, nn

DENSITY_SHIFT = -4.0
"""``sigma = softplus(raw + DENSITY_SHIFT)``: a zero grid starts almost transparent."""
BACKGROUND = 0.5
"""Colour of the light that reaches the far bound when rendering."""
WEIGHT_EPS = 1e-4
"""Samples whose rendering weight is below this get no colour evaluation."""


def _distortion(weights: Tensor, s: Tensor, samples: int) -> Tensor:
    """mip-NeRF 360's distortion loss per ray in O(S): ``sum_ij w_i w_j |s_i - s_j| + sum_i w_i^2 ds / 3``
    over samples at positions ``s`` (inverse-depth fraction, bins of width ``1 / samples``). It pulls a
    ray's weight together (surfaces, not fog) — the fog a short CPU fit otherwise leaves is also what
    makes rendering slow, since no ray then terminates early."""
    w_before = torch.cumsum(weights, dim=1) - weights
    ws_before = torch.cumsum(weights * s, dim=1) - weights * s
    cross = 2.0 * (weights * (s * w_before - ws_before)).sum(dim=1)
    return cross + (weights.pow(2)).sum(dim=1) / (3.0 * samples)


def _dir_encoding(dirs: Tensor, degrees: int = 2) -> Tensor:
    """Unit directions ``(P, 3)`` -> ``[d, sin(2^k d), cos(2^k d)]`` ``(P, 3 + 6 * degrees)``."""
    out = [dirs]
    for k in range(degrees):
        out += [torch.sin(dirs * (2.0**k)), torch.cos(dirs * (2.0**k))]
    return torch.cat(out, dim=-1)


class GridField(nn.Module):
    """Density + colour grids over the contracted world; see the module docstring.

    Args:
        centre: ``(3,)`` world point the contraction is centred on.
        radius: world radius of the uncontracted inner cube.
        resolution: grid side N.
        features: colour-feature channels C (0: an RGB grid, no MLP).
        hidden: MLP width.
    """

    def __init__(self, centre: Tensor, radius: float, resolution: int, features: int = 6, hidden: int = 64,
                 occupancy_size: int = 64):
        super().__init__()
        self.register_buffer("centre", torch.as_tensor(centre, dtype=torch.float32).reshape(3))
        self.radius = float(radius)
        self.features = int(features)
        n = int(resolution)
        self.density = nn.Parameter(torch.zeros(1, 1, n, n, n))
        self.colour = nn.Parameter(torch.zeros(1, 3 + self.features, n, n, n))
        if self.features > 0:
            self.mlp = nn.Sequential(
                nn.Linear(3 + self.features + 3 + 6 * 2, hidden), nn.ReLU(inplace=True),
                nn.Linear(hidden, 3),
            )
            nn.init.zeros_(self.mlp[-1].weight)
            nn.init.zeros_(self.mlp[-1].bias)
        else:
            self.mlp = None
        self.use_mlp = False
        """The MLP's view-dependent correction is switched on after the coarse stage (DVGO's
        coarse stage has none): until then colour is the RGB grid alone, which is far cheaper."""
        self.register_buffer("occupancy", torch.ones(occupancy_size, occupancy_size, occupancy_size, dtype=torch.bool))

    @property
    def resolution(self) -> int:
        return int(self.density.shape[-1])

    # -- coordinates -----------------------------------------------------------------------
    def contract(self, pts: Tensor) -> Tensor:
        """World points ``(..., 3)`` -> grid coordinates in [-1, 1] (grid_sample's, align_corners=True)."""
        x = (pts - self.centre) / self.radius
        n = x.abs().amax(dim=-1, keepdim=True).clamp_min(1e-9)
        outer = (2.0 - 1.0 / n) * (x / n)
        x = torch.where(n <= 1.0, x, outer)
        return x * 0.5

    def uncontract(self, u: Tensor) -> Tensor:
        """Inverse of :meth:`contract` for ``|2u|_inf < 2``."""
        x = u * 2.0
        n = x.abs().amax(dim=-1, keepdim=True).clamp_min(1e-9)
        m = 1.0 / (2.0 - n).clamp_min(1e-6)
        x = torch.where(n <= 1.0, x, x * (m / n))
        return x * self.radius + self.centre.to(u.dtype)

    def occupied(self, u: Tensor) -> Tensor:
        """Occupancy of grid coordinates ``(..., 3)`` -> bool ``(...)``."""
        g = self.occupancy.shape[0]
        idx = ((u + 1.0) * 0.5 * g).long().clamp_(0, g - 1)
        flat = (idx[..., 2] * g + idx[..., 1]) * g + idx[..., 0]
        return self.occupancy.reshape(-1)[flat]

    # -- queries ---------------------------------------------------------------------------
    @staticmethod
    def _sample(grid: Tensor, u: Tensor) -> Tensor:
        """Trilinear samples of ``grid`` ``(1, C, N, N, N)`` at ``u`` ``(P, 3)`` -> ``(P, C)``."""
        out = F.grid_sample(grid, u.reshape(1, -1, 1, 1, 3), mode="bilinear", padding_mode="border",
                            align_corners=True)
        return out.reshape(grid.shape[1], -1).t()

    def sigma(self, u: Tensor) -> Tensor:
        """Volume density (per ``radius`` of distance) at ``u`` ``(P, 3)`` -> ``(P,)``."""
        return F.softplus(self._sample(self.density, u)[:, 0] + DENSITY_SHIFT)

    def rgb(self, u: Tensor, dirs: Tensor) -> Tensor:
        """Colour at ``u`` ``(P, 3)`` seen along unit ``dirs`` ``(P, 3)`` -> ``(P, 3)`` in [0, 1]."""
        feat = self._sample(self.colour, u)
        logit = feat[:, :3]
        if self.mlp is not None and self.use_mlp:
            logit = logit + self.mlp(torch.cat([feat, _dir_encoding(dirs)], dim=-1))
        return torch.sigmoid(logit)

    def _sigma_of(self, u: Tensor, keep: Tensor) -> Tensor:
        """:meth:`sigma` of the samples ``u[keep]`` (``u`` ``(..., 3)``, ``keep`` bool ``(...)``);
        a field may keep what it computed there for :meth:`_rgb_of` of the same ``u``."""
        return self.sigma(u[keep])

    def _rgb_of(self, u: Tensor, shade: Tensor, unit: Tensor) -> Tensor:
        """:meth:`rgb` of the samples ``u[shade]`` seen along ``unit[shade]`` (``shade`` is a
        subset of the last :meth:`_sigma_of`'s ``keep`` on this ``u``)."""
        return self.rgb(u[shade], unit[shade])

    # -- rendering -------------------------------------------------------------------------
    def render(self, origins: Tensor, dirs: Tensor, near: Tensor, far: Tensor, samples: int,
               generator: torch.Generator | None = None, background: Tensor | None = None) -> dict[str, Tensor]:
        """Volume-render rays.

        Args:
            origins, dirs: ``(B, 3)``; ``dirs`` scaled so that a step of 1 along it moves 1 in the
                camera's z (then the ray parameter is the z-depth).
            near, far: ``(B,)`` z bounds; samples are uniform in 1/z between them.
            samples: S per ray.
            generator: stratified jitter of the samples (training); None: bin centres.
            background: ``(B, 3)`` colour of the light that reaches the far bound (training draws it
                at random per ray, so the field must become opaque rather than let a background
                explain the photo); None: ``BACKGROUND`` grey.
        Returns:
            ``rgb (B, 3)``, ``depth (B,)`` median z of the ray's weights (the far bound where nothing
            stopped half the light before it),
            ``acc (B,)`` opacity accumulated before the far bound.
        """
        s, t, delta = self._samples(dirs, near, far, samples, generator)
        b = origins.shape[0]
        u = self.contract(origins[:, None, :] + t[..., None] * dirs[:, None, :])   # (B, S, 3)
        keep = self.occupied(u)
        sigma = torch.zeros(b, samples, dtype=origins.dtype)
        if keep.any():
            sigma = sigma.masked_scatter(keep, self._sigma_of(u, keep))
        alpha = 1.0 - torch.exp(-sigma * delta)
        # The last sample (at the far bound) takes whatever light is left, as NeRF's open last
        # interval does, with a background colour (random in training): a colour per ray from the
        # grid there would be a sky box that memorises the training photos.
        alpha = torch.cat([alpha[:, :-1], torch.ones(b, 1, dtype=alpha.dtype)], dim=1)
        trans = torch.cumprod(torch.cat([torch.ones(b, 1), 1.0 - alpha + 1e-10], dim=1), dim=1)[:, :-1]
        weights = alpha * trans
        acc = 1.0 - trans[:, -1]
        shade = weights.detach() > WEIGHT_EPS
        shade[:, -1] = False
        colour = torch.zeros(b, samples, 3, dtype=origins.dtype)
        if shade.any():
            unit = F.normalize(dirs, dim=-1)[:, None, :].expand(b, samples, 3)
            colour = colour.masked_scatter(shade[..., None], self._rgb_of(u, shade, unit))
        rgb = (weights[:, :-1, None] * colour[:, :-1]).sum(dim=1) + weights[:, -1:] * (
            background if background is not None else torch.full((b, 3), BACKGROUND))
        # Median depth (where the accumulated weight passes 1/2): a surface's depth, never a mix
        # of a surface and the far bound or of a floater and what is behind it, as the mean is.
        cum = torch.cumsum(weights.detach(), dim=1)
        k = torch.searchsorted(cum, torch.full((b, 1), 0.5, dtype=cum.dtype)).clamp_(max=samples - 1)
        depth = torch.gather(t, 1, k)[:, 0]
        return {"rgb": rgb, "depth": depth, "acc": acc, "distortion": _distortion(weights[:, :-1], s[:, :-1], samples)}

    def _samples(self, dirs: Tensor, near: Tensor, far: Tensor, samples: int,
                 generator: torch.Generator | None) -> tuple[Tensor, Tensor, Tensor]:
        """Sample positions: ``s`` in [0, 1] (uniform in inverse depth), z ``t`` and interval lengths
        ``delta`` (in units of ``radius``), each ``(B, S)``."""
        b = dirs.shape[0]
        base = torch.arange(samples, dtype=dirs.dtype)
        if generator is None:
            s = (base + 0.5).expand(b, samples) / samples
        else:
            s = (base + torch.rand(b, samples, generator=generator)) / samples
        inv_near, inv_far = 1.0 / near[:, None], 1.0 / far[:, None]
        t = 1.0 / (inv_near + s * (inv_far - inv_near))
        edges = torch.cat([t[:, :1], 0.5 * (t[:, 1:] + t[:, :-1]), t[:, -1:]], dim=1)
        delta = (edges[:, 1:] - edges[:, :-1]) * dirs.norm(dim=-1, keepdim=True) / self.radius
        return s, t, delta

    @torch.no_grad()
    def render_fast(self, origins: Tensor, dirs: Tensor, near: Tensor, far: Tensor, samples: int, *,
                    segment: int = 16, termination: float = 1e-4) -> dict[str, Tensor]:
        """:meth:`render` without gradients (bin-centre samples), ``segment`` samples at a time,
        dropping rays whose transmittance fell below ``termination`` (early ray termination: the
        light they have left changes a pixel by less than that). ``termination=0`` gives
        :meth:`render`'s result to float rounding."""
        b = origins.shape[0]
        _, t, delta = self._samples(dirs, near, far, samples, None)
        unit = F.normalize(dirs, dim=-1)
        rgb = torch.zeros(b, 3)
        trans = torch.ones(b)
        cum = torch.zeros(b)
        depth = t[:, -1].clone()
        found = torch.zeros(b, dtype=torch.bool)
        acc = torch.zeros(b)
        active = torch.arange(b)
        for start in range(0, samples, segment):
            if active.numel() == 0:
                break
            stop = min(start + segment, samples)
            ts, ds = t[active, start:stop], delta[active, start:stop]
            a, k = ts.shape
            u = self.contract(origins[active, None, :] + ts[..., None] * dirs[active, None, :])
            keep = self.occupied(u)
            sigma = torch.zeros(a, k)
            if keep.any():
                sigma[keep] = self._sigma_of(u, keep)
            alpha = 1.0 - torch.exp(-sigma * ds)
            last = stop == samples
            if last:
                acc[active] = 1.0 - trans[active] * torch.prod(1.0 - alpha[:, :-1] + 1e-10, dim=1)
                alpha[:, -1] = 1.0
            local = torch.cumprod(torch.cat([torch.ones(a, 1), 1.0 - alpha + 1e-10], dim=1), dim=1)
            weights = alpha * local[:, :-1] * trans[active, None]
            shade = weights > WEIGHT_EPS
            if last:
                shade[:, -1] = False
                rgb[active] += weights[:, -1:] * BACKGROUND
            if shade.any():
                colour = torch.zeros(a, k, 3)
                colour[shade] = self._rgb_of(u, shade, unit[active, None, :].expand(a, k, 3))
                rgb[active] += (weights[..., None] * colour).sum(dim=1)
            run = cum[active, None] + torch.cumsum(weights, dim=1)
            crossed = (run >= 0.5) & ~found[active, None]
            hit = crossed.any(dim=1)
            if hit.any():
                first = crossed.float().argmax(dim=1)
                rows = active[hit]
                depth[rows] = ts[hit, first[hit]]
                found[rows] = True
            cum[active] = run[:, -1]
            trans[active] = trans[active] * local[:, -1]
            if not last:
                done = trans[active] < termination if termination > 0 else torch.zeros(a, dtype=torch.bool)
                acc[active[done]] = 1.0 - trans[active[done]]
                active = active[~done]
        return {"rgb": rgb, "depth": depth, "acc": acc}

    # -- schedule helpers ------------------------------------------------------------------
    def param_groups(self, lr_grid: float, lr_mlp: float) -> list[dict]:
        """The optimizer's parameter groups: the grids at ``lr_grid``, the MLP (if any) at ``lr_mlp``."""
        groups = [{"params": [self.density, self.colour], "lr": lr_grid}]
        if self.mlp is not None:
            groups.append({"params": list(self.mlp.parameters()), "lr": lr_mlp})
        return groups

    @torch.no_grad()
    def upsample(self, resolution: int) -> None:
        """Resample both grids to side ``resolution`` (trilinear, corners aligned)."""
        size = (resolution,) * 3
        self.density = nn.Parameter(F.interpolate(self.density.data, size=size, mode="trilinear", align_corners=True))
        self.colour = nn.Parameter(F.interpolate(self.colour.data, size=size, mode="trilinear", align_corners=True))

    @torch.no_grad()
    def prune(self, seen: Tensor, alpha_threshold: float = 1e-4) -> float:
        """Occupancy = seen by a training camera and not negligibly transparent; returns the kept fraction."""
        g = self.occupancy.shape[0]
        sigma = F.softplus(self.density.data + DENSITY_SHIFT)
        sigma = F.adaptive_max_pool3d(sigma, g)[0, 0]
        voxel = 4.0 / self.resolution
        dense = (1.0 - torch.exp(-sigma * voxel)) > alpha_threshold
        self.occupancy = seen & dense
        return float(self.occupancy.float().mean())

    def total_variation(self, block: int, generator: torch.Generator) -> Tensor:
        """Mean squared neighbour difference of the density over one random ``block``^3 sub-grid."""
        n = self.resolution
        k = min(block, n)
        z, y, x = (int(torch.randint(0, n - k + 1, (1,), generator=generator)) for _ in range(3))
        sub = self.density[0, 0, z:z + k, y:y + k, x:x + k]
        return ((sub[1:] - sub[:-1]).pow(2).mean() + (sub[:, 1:] - sub[:, :-1]).pow(2).mean()
                + (sub[:, :, 1:] - sub[:, :, :-1]).pow(2).mean())


@torch.no_grad()
def seen_by_cameras(field: GridField, world_from_cam: Tensor, K: Tensor, near: Tensor, far: Tensor,
                    height: int, width: int) -> Tensor:
    """Occupancy-grid voxels whose centre some camera sees inside its near/far range -> bool ``(G, G, G)``."""
    g = field.occupancy.shape[0]
    c = (torch.arange(g, dtype=torch.float64) + 0.5) / g * 2.0 - 1.0
    zz, yy, xx = torch.meshgrid(c, c, c, indexing="ij")
    u = torch.stack([xx, yy, zz], dim=-1).reshape(-1, 3) * 0.999
    pts = field.uncontract(u)
    cam_from_world = torch.linalg.inv(world_from_cam.double())
    margin = 0.05 * max(height, width)
    seen = torch.zeros(pts.shape[0], dtype=torch.bool)
    for i in range(world_from_cam.shape[0]):
        p = torch.addmm(cam_from_world[i, :3, 3], pts, cam_from_world[i, :3, :3].T).to(torch.float32)
        z = p[:, 2]
        px = p[:, 0] / z.clamp_min(1e-9) * float(K[i, 0, 0]) + float(K[i, 0, 2])
        py = p[:, 1] / z.clamp_min(1e-9) * float(K[i, 1, 1]) + float(K[i, 1, 2])
        seen |= ((z > 0.8 * float(near[i])) & (z < 1.5 * float(far[i])) & (px > -margin) & (px < width + margin)
                 & (py > -margin) & (py < height + margin))
    return seen.reshape(g, g, g)


def scene_frame(world_from_cam: Tensor, near: Tensor) -> tuple[Tensor, float]:
    """Contraction centre and radius for a camera set: the common look-at point, and the median
    distance from a camera to it minus its near bound (the content's extent around that point)."""
    from roguefit.photos import look_at_point

    centre = look_at_point(world_from_cam)
    dist = (world_from_cam[:, :3, 3] - centre).norm(dim=-1)
    radius = float((dist - near).median())
    radius = max(radius, 0.25 * float(dist.median()), 1e-6)
    if not math.isfinite(radius):
        radius = 1.0
    return centre, radius
