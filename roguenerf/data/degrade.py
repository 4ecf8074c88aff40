"""A NeRF-like degradation simulator: turn exact photos + depths into plausible "renders".

Pre-training needs (render, photo) pairs with the artefacts of radiance fields. Starting from
exact toy photos and z-depths, :class:`Degradation` applies, per view and in this order:

1. **Pose error**: the render is re-rendered from a slightly wrong camera (rotation of about
   ``pose_noise_deg`` degrees RMS, translation of about ``pose_noise_trans`` pose units RMS),
   by forward-reprojecting with the exact depth; the returned depth follows the same camera.
2. **Blur**: a Gaussian of ``sigma ~ U(blur_sigma)`` pixels, then a slight **defocus**: a disk
   blur of radius ``~ U(defocus)`` pixels blended in where the depth is far from a random
   focus plane (in inverse depth, like a thin lens).
3. **Haze**: blend toward the background colour with weight ``~ U(haze)`` times how far a pixel
   is (0 at the 5 % depth quantile, 1 at the 95 % quantile and where depth is missing), like
   the faint floaters of a semi-transparent field. The background colour is ``background``
   or, if None, the mean photo colour weighted toward the farthest pixels.
4. **Colour shift**: per-channel gain ``1 + N(0, color_shift)`` and offset ``N(0, color_shift / 2)``.
5. **Noise**: Gaussian, standard deviation ``~ U(noise)``; the result is clipped to [0, 1].

Depth error: the depth is multiplied by ``1 + depth_noise * n(x)`` with ``n`` a smooth
(4x4 control points, bilinear) standard normal field. Missing depth (unknown per
:mod:`roguenerf.geometry.depth`: non-finite, <= 1e-6 or >= 1e10)
stays missing.

Deterministic for a given ``torch.Generator`` state (all random numbers are drawn on the CPU
from it in a fixed order).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import kornia
import torch
import torch.nn.functional as F
from torch import Tensor

from roguenerf.errors import InputError
from roguenerf.geometry.depth import known_depth_mask
from roguenerf.images import check_float_image


def _check_range(name: str, value) -> tuple[float, float]:
    try:
        lo, hi = (float(v) for v in value)
    except (TypeError, ValueError):
        raise InputError(f"{name}: expected a (low, high) pair of numbers, got {value!r}") from None
    if not (math.isfinite(lo) and math.isfinite(hi) and 0 <= lo <= hi):
        raise InputError(f"{name}: expected finite 0 <= low <= high, got ({lo}, {hi})")
    return lo, hi


@dataclass
class Degradation:
    """NeRF-like degradation of exact views; see the module docstring for each step."""

    blur_sigma: tuple[float, float] = (0.5, 2.0)
    """Gaussian blur standard deviation range, pixels."""
    noise: tuple[float, float] = (0.0, 0.02)
    """Additive Gaussian noise standard deviation range (images in [0, 1])."""
    pose_noise_deg: float = 0.5
    """RMS rotation error of the rendering camera, degrees."""
    pose_noise_trans: float = 0.01
    """RMS translation error of the rendering camera, pose units."""
    depth_noise: float = 0.02
    """Relative amplitude of the smooth multiplicative depth error."""
    haze: tuple[float, float] = (0.0, 0.1)
    """Range of the haze strength toward the background colour at far / missing depth."""
    defocus: tuple[float, float] = (0.0, 1.5)
    """Disk-blur radius range (pixels) away from the focus plane."""
    color_shift: float = 0.02
    """Standard deviation of the per-channel gain (offset: half of it)."""
    background: tuple[float, float, float] | None = None
    """Haze colour; None estimates it per view from the farthest pixels."""

    def __post_init__(self) -> None:
        self.blur_sigma = _check_range("blur_sigma", self.blur_sigma)
        self.noise = _check_range("noise", self.noise)
        self.haze = _check_range("haze", self.haze)
        self.defocus = _check_range("defocus", self.defocus)
        for name in ("pose_noise_deg", "pose_noise_trans", "depth_noise", "color_shift"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value >= 0):
                raise InputError(f"{name}: expected a finite number >= 0, got {value!r}")
        if self.haze[1] > 1:
            raise InputError(f"haze: expected values in [0, 1], got {self.haze}")
        if self.background is not None:
            bg = tuple(float(v) for v in self.background)
            if len(bg) != 3 or not all(0 <= v <= 1 for v in bg):
                raise InputError(f"background: expected an RGB triple in [0, 1], got {self.background!r}")
            self.background = bg

    def __call__(
        self, photos: Tensor, depths: Tensor, generator: torch.Generator, *, K: Tensor | None = None
    ) -> tuple[Tensor, Tensor]:
        """Degrade a batch of views.

        Args:
            photos: ``(M, 3, H, W)`` in [0, 1].
            depths: ``(M, 1, H, W)`` z-depth (unknown per :mod:`roguenerf.geometry.depth`: missing).
            generator: a CPU ``torch.Generator``; same state, same output.
            K: ``(3, 3)`` or ``(M, 3, 3)`` pixel-centre intrinsics for the pose error; None
                assumes a focal length of ``W`` pixels (about 53 degrees) and a centred
                principal point.
        Returns:
            ``(renders (M, 3, H, W) in [0, 1], depths (M, 1, H, W))``.
        """
        if isinstance(photos, Tensor):
            check_float_image(photos, "photos")
        if not isinstance(photos, Tensor) or photos.ndim != 4 or photos.shape[1] != 3 or not photos.is_floating_point():
            got = getattr(photos, "shape", type(photos))
            raise InputError(f"photos: expected a float (M, 3, H, W) tensor, got {got}")
        m, _, h, w = photos.shape
        if not isinstance(depths, Tensor) or tuple(depths.shape) != (m, 1, h, w):
            raise InputError(f"depths: expected shape ({m}, 1, {h}, {w}), got {tuple(getattr(depths, 'shape', ()))}")
        if not isinstance(generator, torch.Generator) or generator.device.type != "cpu":
            raise InputError("generator: expected a CPU torch.Generator")
        dev, dt = photos.device, photos.dtype
        K = self._intrinsics(K, m, h, w).to(dev, dt)
        depths = depths.to(dt)

        def rand(*shape):
            return torch.rand(*shape, generator=generator, dtype=torch.float64).to(dev, dt)

        def randn(*shape):
            return torch.randn(*shape, generator=generator, dtype=torch.float64).to(dev, dt)

        # Every draw happens in this order regardless of which steps are active, so changing
        # one strength leaves the others' random numbers unchanged.
        rot = randn(m, 3) * math.radians(self.pose_noise_deg) / math.sqrt(3)
        trans = randn(m, 3) * self.pose_noise_trans / math.sqrt(3)
        sigma = self._uniform(rand(m), self.blur_sigma)
        radius = self._uniform(rand(m), self.defocus)
        focus_q = rand(m)
        haze = self._uniform(rand(m), self.haze)
        gain = 1 + randn(m, 3) * self.color_shift
        offset = randn(m, 3) * self.color_shift / 2
        noise_std = self._uniform(rand(m), self.noise)
        noise = randn(m, 3, h, w)
        depth_field = randn(m, 1, 4, 4)

        known = known_depth_mask(depths)
        images, depths = _pose_error(photos, depths, known, K, rot, trans)
        known = known_depth_mask(depths)
        inv_depth = torch.where(known, 1.0 / torch.where(known, depths, 1.0), 0.0)
        images = _gaussian(images, sigma)
        images = _defocus(images, inv_depth, known, radius, focus_q)
        images = self._haze(images, photos, depths, known, haze)
        images = images * gain[:, :, None, None] + offset[:, :, None, None]
        images = (images + noise * noise_std[:, None, None, None]).clamp(0.0, 1.0)

        field = F.interpolate(depth_field, size=(h, w), mode="bilinear", align_corners=False)
        depths = torch.where(known, depths * (1 + self.depth_noise * field), depths)
        return images, depths

    @staticmethod
    def _uniform(u: Tensor, bounds: tuple[float, float]) -> Tensor:
        return bounds[0] + (bounds[1] - bounds[0]) * u

    @staticmethod
    def _intrinsics(K: Tensor | None, m: int, h: int, w: int) -> Tensor:
        if K is None:
            K = torch.tensor([[w, 0.0, w / 2], [0.0, w, h / 2], [0.0, 0.0, 1.0]], dtype=torch.float64)
        if not isinstance(K, Tensor) or K.shape not in ((3, 3), (m, 3, 3)):
            raise InputError(f"K: expected shape (3, 3) or ({m}, 3, 3), got {tuple(getattr(K, 'shape', ()))}")
        return K.expand(m, 3, 3)

    def _haze(self, images: Tensor, photos: Tensor, depths: Tensor, known: Tensor, strength: Tensor) -> Tensor:
        flat = torch.where(known, depths, torch.nan).flatten(1)
        q = torch.nanquantile(flat, torch.tensor([0.05, 0.95], dtype=flat.dtype, device=flat.device), dim=1)
        near, far = q[0].view(-1, 1, 1, 1), q[1].view(-1, 1, 1, 1)
        farness = ((depths - near) / (far - near).clamp_min(1e-6)).clamp(0.0, 1.0)
        farness = torch.where(known, torch.nan_to_num(farness, nan=1.0), 1.0)
        if self.background is not None:
            bg = images.new_tensor(self.background).view(1, 3, 1, 1)
        else:
            weight = farness**4 + 1e-6
            bg = (photos * weight).sum(dim=(2, 3), keepdim=True) / weight.sum(dim=(2, 3), keepdim=True)
        alpha = strength.view(-1, 1, 1, 1) * farness
        return images * (1 - alpha) + bg * alpha


def _pose_error(images: Tensor, depths: Tensor, known: Tensor, K: Tensor, rot: Tensor, trans: Tensor):
    """Re-render from cameras moved by (rot (M, 3) axis-angle, trans (M, 3)); returns images, depths."""
    if not (rot.any() or trans.any()):
        return images, depths
    m, _, h, w = images.shape
    R = kornia.geometry.conversions.axis_angle_to_rotation_matrix(rot)
    v, u = torch.meshgrid(
        torch.arange(h, dtype=images.dtype, device=images.device) + 0.5,
        torch.arange(w, dtype=images.dtype, device=images.device) + 0.5,
        indexing="ij",
    )
    pix = torch.stack([u, v, torch.ones_like(u)], dim=0).reshape(1, 3, -1)
    rays = torch.linalg.solve(K, pix.expand(m, 3, -1))
    z = torch.where(known, depths, 0.0).reshape(m, 1, -1)
    # A point the perturbed camera sees at pixel x (its depth taken from the exact view, a
    # first-order approximation for small motions), expressed in the exact camera; missing
    # depth is treated as infinitely far (rotation only).
    points = R @ (rays * torch.where(z > 0, z, 1.0)) + torch.where(z > 0, 1.0, 0.0) * trans[:, :, None]
    proj = K @ points
    zc = proj[:, 2:].clamp_min(1e-6)
    grid = torch.stack([2 * proj[:, 0] / zc[:, 0] / w - 1, 2 * proj[:, 1] / zc[:, 0] / h - 1], dim=-1)
    grid = grid.reshape(m, h, w, 2)
    out = F.grid_sample(images, grid, mode="bilinear", padding_mode="border", align_corners=False)
    # Nearest for depth: bilinear would invent depths between foreground and background.
    src = torch.where(known, depths, torch.nan)
    sampled = F.grid_sample(src, grid, mode="nearest", padding_mode="border", align_corners=False)
    got = known_depth_mask(sampled)
    sampled = torch.where(got, sampled, 0.0).reshape(m, 1, -1)
    # The sampled exact-view point, moved back into the perturbed camera: its z is the new depth.
    source_pts = torch.linalg.solve(K, torch.cat([_grid_to_pix(grid, h, w), torch.ones_like(sampled)], dim=1))
    source_pts = source_pts * sampled
    moved = R.transpose(1, 2) @ (source_pts - trans[:, :, None])
    new_depth = torch.where(got.reshape(m, 1, -1), moved[:, 2:], 0.0).reshape(m, 1, h, w)
    return out, new_depth


def _grid_to_pix(grid: Tensor, h: int, w: int) -> Tensor:
    """``(M, H, W, 2)`` normalised grid (align_corners=False) -> ``(M, 2, H*W)`` pixel-centre coords."""
    x = (grid[..., 0] + 1) * w / 2
    y = (grid[..., 1] + 1) * h / 2
    return torch.stack([x, y], dim=1).flatten(2)


def _gaussian(images: Tensor, sigma: Tensor) -> Tensor:
    top = float(sigma.max()) if sigma.numel() else 0.0
    if top <= 0:
        return images
    size = 2 * math.ceil(3 * top) + 1
    sig = sigma.clamp_min(1e-3)[:, None].expand(-1, 2)
    return kornia.filters.gaussian_blur2d(images, (size, size), sig, border_type="reflect")


def _defocus(images: Tensor, inv_depth: Tensor, known: Tensor, radius: Tensor, focus_q: Tensor) -> Tensor:
    top = float(radius.max()) if radius.numel() else 0.0
    if top <= 0:
        return images
    m = images.shape[0]
    half = math.ceil(top + 0.5)
    ax = torch.arange(-half, half + 1, dtype=images.dtype, device=images.device)
    dist = torch.sqrt(ax[None, :] ** 2 + ax[:, None] ** 2)
    # A soft-edged disk, so the kernel changes continuously with the radius.
    disk = (radius.view(-1, 1, 1) + 0.5 - dist).clamp(0.0, 1.0)
    disk = disk / disk.sum(dim=(1, 2), keepdim=True)
    blurred = kornia.filters.filter2d(images, disk, border_type="reflect")
    flat = torch.where(known, inv_depth, torch.nan).flatten(1)
    focus = torch.stack([
        torch.nanquantile(flat[i], focus_q[i], interpolation="nearest") if known[i].any() else flat.new_tensor(0.0)
        for i in range(m)
    ])
    off = (inv_depth - focus.view(-1, 1, 1, 1)).abs()
    mix = off / off.flatten(1).amax(dim=1).clamp_min(1e-12).view(-1, 1, 1, 1)
    return images * (1 - mix) + blurred * mix
