"""Neighbour pose refinement: direct image alignment of a training photo onto the render.

Real poses are a little wrong (COLMAP's error; nerfacto's camera optimiser moves them on
purpose), so a neighbour photo reprojected with its dataset pose lands beside the render's
content, and its detail is put in the wrong place. Before a request reprojects a neighbour,
:func:`align_neighbour` turns and moves that neighbour's camera by the small rigid motion that
best maps its photo onto the render through the render's depth (the target pose, render and
depth are the user's and are not touched): a photometric least-squares fit of 6 numbers,
coarse to fine on small copies of the images (long side 64, 128, 256 pixels), sampled with
:func:`~roguenerf.reprojection.reproject` (so the visibility test is the enhancer's).

The motion is a rotation ``w`` (radians) and a move ``v`` of the neighbour camera in its own
frame, ``v`` measured in units of the target's median depth so that the fit does not depend
on the scene's units.
It is kept only where it lowers the photometric error by :attr:`AlignConfig.min_gain` (a
share) and stays within :attr:`AlignConfig.max_rotation_deg` and
:attr:`AlignConfig.max_translation`; otherwise the dataset pose is kept (a featureless
view, a neighbour that barely overlaps, a fit that wandered). The error is a Charbonnier
mean over the target pixels the neighbour sees; a moved camera must still see
:data:`MIN_OVERLAP` of the pixels it saw (the fit cannot win by looking away), and the two poses
are compared on the pixels both see. Each level takes damped Gauss-Newton steps (the photo's
gradients sampled with its colour, IRLS weights of the Charbonnier penalty); a step that does
not lower the error is refused and the damping raised.

Legend: (H, W) target size, (Hs, Ws) neighbour size.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

from roguenerf.errors import InputError
from roguenerf.geometry.cameras import check_intrinsics, check_pose, pixel_rays, relative_pose, scale_intrinsics
from roguenerf.geometry.depth import known_depth_mask, median_known_depth
from roguenerf.geometry.euler import rotation_angle
from roguenerf.geometry.noise import axis_angle_to_matrix
from roguenerf.ops.filters import gaussian_blur, spatial_gradient
from roguenerf.ops.gauss_newton import normal_equations
from roguenerf.reprojection import reproject, sampling_source


@dataclass(frozen=True)
class AlignConfig:
    levels: tuple[int, ...] = (64, 128, 256)
    """Long side (pixels) of the target at each level of the coarse-to-fine fit; levels larger
    than the target itself are skipped."""
    iterations: int = 12
    """Gauss-Newton steps per level (at most; refused steps count)."""
    blur_sigma: float = 1.0
    """Gaussian blur (pixels of the level) of both images: the render is blurry, the photo is not."""
    max_rotation_deg: float = 6.0
    """The fit never turns the camera further than this (a step that would is refused). At 3°
    (and 0.15) the fits of 0.5° / 5 % noise on an orbit (mary_rose, where 5 % of the cameras'
    spread is a large share of the depth) ran to the edge and were refused."""
    max_translation: float = 0.3
    """The fit never moves the camera further than this share of the target's median depth."""
    min_gain: float = 0.10
    """The fit is kept only when it lowers the photometric error by at least this share. With
    the dataset's poses, a fit slides a little along the rotation/translation valley of a
    shallow scene, or fits the geometry errors of a blurry render, and gains 2-7 % (and such
    fits cost up to 0.7 dB on our own `coarse` look); a wrong pose's fit gains 10-75 %."""
    charbonnier: float = 0.01
    """Scale of the Charbonnier penalty ``sqrt(r^2 + c^2) - c`` on colour differences in [0, 1]."""
    early_refusal: float = 0.05
    """Pay for the finest level only where the fit may be kept: once the level before it has
    lowered its own error by less than this share (judged like the final decision, on the
    pixels both poses see), the fit stops there and is refused. 0 fits every level. The finest
    level's gain follows the coarser one's to about 0.03 (dataset poses: 0.01-0.11 before,
    0.01-0.09 after), and a fit is kept only from :attr:`min_gain` = 0.10, so 0.05 was chosen on
    lego (6 views, no noise, 0.25° / 2 % and 0.5° / 5 %: every kept fit kept, 0.05 and 0.08
    alike) and reported on ``ollie`` / fine (docs/results.md, *Speed at users' sizes*)."""
    early_level: int = -2
    """The first level whose gain :attr:`early_refusal` reads, as an index into the levels
    fitted: every level from it to the one before the finest is judged once fitted, and the fit
    stops at the first that gains too little. -2: only the level before the finest; 0: every
    level, so that a fit with nothing to find stops after the first."""

    reuse: bool = True
    """Judge each neighbour's dataset pose once per scene: a
    :class:`~roguenerf.inference.SceneEnhancer` remembers each neighbour whose fit was refused
    for having nothing to gain (:attr:`Alignment.refusal` ``early`` or ``gain``: the dataset
    pose is as good as any near it), and that neighbour keeps its dataset pose on the later
    views without a fit. Every other neighbour is fitted on every view, as without reuse: a fit
    kept on one view and read on another lost up to 0.19 dB on lego at 0.5° / 5 % pose noise,
    and a fit that ran to the trust region's edge on one view was kept on the next. The same
    images as without reuse on lego and the report half at three noise levels (docs/results.md,
    *Speed at users' sizes*); it saves time where views share neighbours (lego's orbit, paths,
    a service's nearby requests), not on held-out views that each have their own."""

    def __post_init__(self):
        if not isinstance(self.reuse, bool):
            raise InputError(f"AlignConfig.reuse: expected True or False, got {self.reuse!r}")
        if isinstance(self.early_level, bool) or not isinstance(self.early_level, int):
            raise InputError(f"AlignConfig.early_level: expected an integer index, got {self.early_level!r}")


@dataclass
class Alignment:
    world_from_cam: Tensor
    """``(4, 4)`` float64: the refined neighbour pose (the given one where not ``accepted``)."""
    accepted: bool
    rotation_deg: float
    """Angle of the fitted rotation (degrees), whether or not it was accepted."""
    translation: float
    """Length of the fitted move, as a share of the target's median depth."""
    error_before: float
    """Photometric error at the finest level with the given pose (nan where nothing overlaps)."""
    error_after: float
    coarse_gain: float = float("nan")
    """Share by which the last level judged (:attr:`AlignConfig.early_level`: the one before
    the finest, unless the fit stopped earlier) lowered its error (on the pixels both poses see
    there); nan with a single level."""
    refusal: str = ""
    """Why the fit was refused ("" where it was kept): ``overlap`` (the neighbour sees too
    little of the view to be fitted), ``early`` (:attr:`stopped_early`), ``gain`` (it ended
    inside the trust region but gained less than :attr:`AlignConfig.min_gain`: nothing to gain)
    or ``edge`` (it ran to the trust region's edge, or its error is not finite: no minimum near
    the dataset pose)."""

    @property
    def stopped_early(self) -> bool:
        """Refused by :attr:`AlignConfig.early_refusal` before the finest level was fitted."""
        return self.refusal == "early"

    @property
    def nothing_to_gain(self) -> bool:
        """Refused ``early`` or for its ``gain``: the given (dataset) pose is as good as a fit."""
        return self.refusal in ("early", "gain")


def _area(x: Tensor, size: tuple[int, int]) -> Tensor:
    return F.interpolate(x, size=size, mode="area") if tuple(x.shape[-2:]) != size else x


def _scaled_K(K: Tensor, size: tuple[int, int], to: tuple[int, int]) -> Tensor:
    """float64 intrinsics of an image of ``size`` (H, W) resized to ``to``
    (:func:`~roguenerf.geometry.cameras.scale_intrinsics`)."""
    return scale_intrinsics(K.to(torch.float64), to[1] / size[1], to[0] / size[0])


def _known_filled(depth: Tensor) -> tuple[Tensor, Tensor]:
    """``(known, z)`` of a ``(1, 1, H, W)`` depth: 1 where known, and the depth there (0 elsewhere)."""
    known = known_depth_mask(depth)
    return known.to(depth.dtype), torch.where(known, depth, 0.0)  # known depth is finite


def _level_depth(depth: Tensor, to: tuple[int, int], filled: tuple[Tensor, Tensor] | None = None) -> Tensor:
    """``(1, 1, h, w)`` mean of the known depth over each cell; 0 (unknown) where less than
    half the cell is known. ``filled``: :func:`_known_filled` of ``depth`` when the caller has it
    (one image's levels share it)."""
    known, z = _known_filled(depth) if filled is None else filled
    weight = _area(known, to)
    mean = _area(z, to) / weight.clamp_min(1e-6)
    return torch.where(weight >= 0.5, mean, 0.0)


def _blurred(image: Tensor, to: tuple[int, int], sigma: float) -> Tensor:
    small = _area(image, to)
    if sigma <= 0:
        return small
    radius = max(1, int(math.ceil(2.5 * sigma)))
    return gaussian_blur(small, 2 * radius + 1, sigma)


def shrink(image: Tensor, depth: Tensor, K: Tensor, side: int) -> tuple[Tensor, Tensor, Tensor]:
    """An image ``(3, H, W)``, its z-depth ``(1, H, W)`` and K, area-resized so that the long
    side is at most ``side`` (unchanged, on the CPU, when it already is); depth is averaged
    over its known pixels (unknown where less than half a cell is known)."""
    image, depth = image.detach().cpu().float(), depth.detach().cpu().float()
    K = torch.as_tensor(K).detach().cpu().to(torch.float64)
    h, w = image.shape[-2:]
    if max(h, w) <= side:
        return image, depth, K
    to = (max(1, round(h * side / max(h, w))), max(1, round(w * side / max(h, w))))
    return _area(image[None], to)[0], _level_depth(depth[None], to)[0], _scaled_K(K, (h, w), to)


def _se3(delta: Tensor) -> Tensor:
    """``(4, 4)`` float64 rigid motion of 6 numbers: a rotation vector (radians), then a move."""
    out = torch.eye(4, dtype=torch.float64)
    out[:3, :3] = axis_angle_to_matrix(delta[:3])
    out[:3, 3] = delta[3:].to(torch.float64)
    return out


MIN_OVERLAP = 0.9
"""A moved neighbour camera must still see this share of the target pixels it saw before."""


STEP_PIXELS = 0.02
"""A level's fit stops once a step would move the pixels by less than this (pixels of the level)."""

CONVERGED = 1e-3
"""A level's fit also stops once a step lowers the error by less than this share."""

INTERIOR = 0.8
"""A fit is kept only when it ends inside this share of the trust region (both limits)."""


def _filled(cache: dict | None, depth: Tensor) -> tuple[Tensor, Tensor] | None:
    """:func:`_known_filled` of a ``(1, H, W)`` depth, computed once per cache (an image's
    levels); None without a cache (each level computes it)."""
    if cache is None:
        return None
    if "filled" not in cache:
        cache["filled"] = _known_filled(depth.float()[None])
    return cache["filled"]


class _Level:
    """One level of the coarse-to-fine fit: blurred small images, depths in units of the
    target's median depth, intrinsics scaled to the level."""

    def __init__(self, n: int, photo, photo_depth, photo_K, render, render_depth, K, scale: float, sigma: float,
                 cache: dict | None = None, target_cache: dict | None = None):
        H, W = render.shape[-2:]
        Hs, Ws = photo.shape[-2:]
        f = n / max(H, W)
        to = (max(4, round(H * f)), max(4, round(W * f)))
        to_s = (max(4, round(Hs * f)), max(4, round(Ws * f)))
        target_key = ("level", to, sigma)
        if target_cache is None or target_key not in target_cache:  # the target's part: the same for every neighbour
            depth = _level_depth(render_depth.float()[None], to, _filled(target_cache, render_depth)) / scale
            level_K = _scaled_K(K, (H, W), to)
            # (h, w, 3) float32 target points (target frame, depth units): float64 rays first
            points = (pixel_rays(level_K, to) * depth[0, 0, ..., None].to(torch.float64)).float()
            target = (_blurred(render.float()[None], to, sigma), depth, level_K, points)
            if target_cache is not None:
                target_cache[target_key] = target
        else:
            target = target_cache[target_key]
        self.render, self.depth, self.K, self.points = target
        key = (to_s, sigma)
        if cache is None or key not in cache:  # the neighbour's part depends on it alone
            small = _blurred(photo.float()[None], to_s, sigma)
            # central differences, edges repeated; sampled together with the colour
            grad = spatial_gradient(small)
            entry = (torch.cat([small, grad[:, :, 0], grad[:, :, 1]], dim=1),
                     _level_depth(photo_depth.float()[None], to_s, _filled(cache, photo_depth)))
            if cache is not None:
                cache[key] = entry
        else:
            entry = cache[key]
        self.stack = entry[0]
        self.photo_depth = entry[1] / scale
        self.photo_K = _scaled_K(photo_K, (Hs, Ws), to_s)
        # what every sample of this level reads from the neighbour (built once, not per sample)
        self.source = sampling_source(self.stack, self.photo_depth)

    def sample(self, photo_from_cam: Tensor) -> tuple[Tensor, Tensor]:
        """``(9, h, w)`` photo colour and gradients reprojected with ``photo_from_cam`` (0 where not
        seen) and ``(h, w)`` bool: seen (target depth known, in front, inside, visible)."""
        rp = reproject(self.stack, self.photo_depth, self.depth, self.photo_K.float(), self.K.float(),
                       torch.eye(4, dtype=torch.float64)[None], photo_from_cam[None], source=self.source,
                       validated=True)
        return rp.features[0], rp.valid[0, 0] > 0

    def error(self, sampled: Tensor, seen: Tensor, counted: Tensor, c: float) -> float:
        """Charbonnier mean over the ``counted`` pixels that are ``seen``; infinite when fewer than
        :data:`MIN_OVERLAP` of them are (the fit must not win by looking away)."""
        use = seen & counted
        n = int(use.sum())
        if n == 0 or n < MIN_OVERLAP * int(counted.sum()):
            return float("inf")
        # over every pixel, the ones not used zeroed (no gather of the used ones: faster)
        r = (sampled[:3] - self.render[0]).square().sum(dim=0)
        return float(torch.where(use, (r + c * c).sqrt() - c, 0.0).sum() / n)

    def step(self, photo_from_cam: Tensor, sampled: Tensor, seen: Tensor, counted: Tensor, c: float,
             damping: float) -> Tensor:
        """One damped Gauss-Newton step (IRLS weights of the Charbonnier penalty): the 6 numbers
        of the motion, in the neighbour's frame, that best reduce the error to first order
        (the normal equations: :func:`roguenerf.ops.gauss_newton.normal_equations`)."""
        use = (seen & counted).reshape(-1)
        A, b = normal_equations(self.points.reshape(-1, 3), sampled.reshape(9, -1), self.render[0].reshape(3, -1),
                                use, photo_from_cam, self.photo_K, c)
        A = A + damping * torch.diag(torch.diagonal(A).clamp_min(1e-12))
        return -torch.linalg.solve(A, b)


def align_neighbour(photo: Tensor, photo_depth: Tensor, photo_K: Tensor, world_from_photo: Tensor,
                    render: Tensor, render_depth: Tensor, K: Tensor, world_from_cam: Tensor, *,
                    config: AlignConfig | None = None, cache: dict | None = None,
                    target_cache: dict | None = None) -> Alignment:
    """Refine the pose of one neighbour photo so that it reprojects onto the render.

    Args:
        photo: ``(3, Hs, Ws)`` the neighbour's photo, float in [0, 1].
        photo_depth: ``(1, Hs, Ws)`` its rendered z-depth (for the visibility test).
        photo_K, K: ``(3, 3)`` intrinsics of the neighbour and the target (pixel-centre convention).
        world_from_photo, world_from_cam: ``(4, 4)`` OpenCV camera-to-world of the neighbour
            (the pose refined) and the target (kept).
        render: ``(3, H, W)``; render_depth: ``(1, H, W)``: the target's render and z-depth.
        config: the fit's settings (:class:`AlignConfig`).
        cache: a dict kept by the caller for this one neighbour photo (and its depth): the
            photo's blurred levels and gradients are stored there and reused by later fits.
        target_cache: a dict kept by the caller for this one target (render, depth, K) and
            ``config``: the target's median depth, blurred levels and points are stored there
            and reused by the fits of its other neighbours.
    Returns:
        :class:`Alignment`. Never raises on image content: where the neighbour sees (almost)
        nothing of the target, or no fit lowers the error, the given pose comes back with
        ``accepted`` False.
    """
    config = config or AlignConfig()
    for name, x, ch in (("photo", photo, 3), ("photo_depth", photo_depth, 1), ("render", render, 3),
                        ("render_depth", render_depth, 1)):
        if not isinstance(x, Tensor) or not x.is_floating_point() or x.ndim != 3 or x.shape[0] != ch:
            raise InputError(f"{name}: expected a float tensor ({ch}, H, W), got "
                             f"{tuple(x.shape) if isinstance(x, Tensor) else type(x).__name__}")
    if photo_depth.shape[1:] != photo.shape[1:] or render_depth.shape[1:] != render.shape[1:]:
        raise InputError("photo_depth / render_depth: expected the size of their image")
    photo_K, K = check_intrinsics(photo_K, "photo_K"), check_intrinsics(K, "K")
    world_from_photo = check_pose(torch.as_tensor(world_from_photo), "world_from_photo").to(torch.float64)
    world_from_cam = check_pose(torch.as_tensor(world_from_cam), "world_from_cam").to(torch.float64)
    photo, photo_depth = photo.detach().cpu(), photo_depth.detach().cpu()
    render, render_depth = render.detach().cpu(), render_depth.detach().cpu()

    def unchanged(before: float = float("nan")) -> Alignment:
        return Alignment(world_from_cam=world_from_photo, accepted=False, rotation_deg=0.0, translation=0.0,
                         error_before=before, error_after=before)

    if target_cache is not None and "scale" in target_cache:
        scale = target_cache["scale"]
    else:
        scale = float(median_known_depth(render_depth.float()[None])[0])
        if target_cache is not None:
            target_cache["scale"] = scale
    H, W = render.shape[-2:]
    sizes = sorted({min(int(n), max(H, W)) for n in config.levels if int(n) >= 8}) or [max(H, W)]
    # Relative pose in float64, in units of the target's median depth.
    start = relative_pose(world_from_photo, world_from_cam).cpu()
    start[:3, 3] /= scale
    c = config.charbonnier
    start_inverse = torch.linalg.inv(start)

    def within(pose: Tensor) -> bool:
        motion = pose @ start_inverse
        return (float(rotation_angle(motion[:3, :3])) <= config.max_rotation_deg
                and float(motion[:3, 3].norm()) <= config.max_translation)

    cache = {} if cache is None else cache  # without the caller's: this fit's levels share it
    target_cache = {} if target_cache is None else target_cache
    with torch.no_grad():
        levels = [_Level(n, photo, photo_depth, photo_K.cpu(), render, render_depth, K.cpu(), scale,
                         config.blur_sigma, cache, target_cache) for n in sizes]
        cache.pop("filled", None)  # every level is built (and kept): not needed again
        target_cache.pop("filled", None)
        finest = levels[-1]
        start_sampled, counted_finest = finest.sample(start)
        if int(counted_finest.sum()) < 64:
            out = unchanged()
            out.refusal = "overlap"
            return out
        pose = start
        coarse_gain = float("nan")
        # the first level whose gain decides whether the finer ones are fitted (none with one level)
        judged = min(config.early_level % len(levels), len(levels) - 2) if len(levels) > 1 else len(levels)
        at_pose = None  # the last level's sample at ``pose`` and what it sees
        for k, level in enumerate(levels):
            if k > judged:
                # Each judged level (from ``early_level`` to the one before the finest), judged as
                # the final decision is: its error with the dataset pose and with the fitted one,
                # on the pixels both see.
                coarse = levels[k - 1]
                c_start, c_seen = coarse.sample(start)
                c_now, c_seen_now = at_pose
                both = c_seen & c_seen_now
                c_before, c_after = coarse.error(c_start, both, both, c), coarse.error(c_now, both, both, c)
                coarse_gain = float("nan")
                if math.isfinite(c_before) and c_before > 0 and math.isfinite(c_after):
                    coarse_gain = 1.0 - c_after / c_before
                if config.early_refusal > 0 and not coarse_gain >= config.early_refusal:
                    before = finest.error(start_sampled, counted_finest, counted_finest, c)
                    return Alignment(world_from_cam=world_from_photo, accepted=False, rotation_deg=0.0,
                                     translation=0.0, error_before=before, error_after=before,
                                     coarse_gain=coarse_gain, refusal="early")
            sampled, counted = level.sample(pose)
            at_pose = (sampled, counted)
            if int(counted.sum()) < 16:
                continue
            seen = counted
            err = level.error(sampled, seen, counted, c)
            damping = 1e-3
            focal = float(level.K[0, 0])
            for _ in range(config.iterations):
                delta = level.step(pose, sampled, seen, counted, c, damping)
                if not bool(torch.isfinite(delta).all()):
                    break
                # About how far the step moves the pixels (a rotation of w radians moves them by
                # focal * w, a move of v depths by up to focal * v): below STEP_PIXELS it is done.
                small = float(delta.norm()) * focal < STEP_PIXELS
                trial = _se3(delta) @ pose
                if not within(trial):  # a trust region: the fit never leaves the plausible motions
                    damping *= 10.0
                    if damping > 1e4:
                        break
                    continue
                t_sampled, t_seen = level.sample(trial)
                t_err = level.error(t_sampled, t_seen, counted, c)
                if t_err < err:
                    converged = small or err - t_err < CONVERGED * err
                    pose, sampled, seen, err = trial, t_sampled, t_seen, t_err
                    at_pose = (sampled, seen)
                    damping = max(damping / 10.0, 1e-6)
                    if converged:
                        break
                else:
                    damping *= 10.0
                    if small or damping > 1e4:
                        break
        # Both poses judged on the pixels both see.
        sampled, seen = finest.sample(pose)
        both = seen & counted_finest
        before = finest.error(start_sampled, both, both, c)
        after = finest.error(sampled, both, both, c)
    motion = pose @ start_inverse  # the fitted motion, in the neighbour's frame
    rotation_deg = float(rotation_angle(motion[:3, :3]))
    translation = float(motion[:3, 3].norm())
    # A fit that ends against the trust region's edge has no minimum near the dataset pose
    # (wrong geometry, a render unlike the photo): refused.
    inside = (math.isfinite(after) and rotation_deg <= INTERIOR * config.max_rotation_deg
              and translation <= INTERIOR * config.max_translation)
    if not (inside and after < before * (1.0 - config.min_gain)):
        out = unchanged(before)
        out.refusal = "gain" if inside else "edge"
        out.rotation_deg, out.translation, out.error_after = rotation_deg, translation, after
        out.coarse_gain = coarse_gain
        return out
    photo_from_cam = pose.clone()
    photo_from_cam[:3, 3] *= scale
    refined = world_from_cam.cpu() @ torch.linalg.inv(photo_from_cam)
    return Alignment(world_from_cam=refined.to(world_from_photo.device), accepted=True, rotation_deg=rotation_deg,
                     translation=translation, error_before=before, error_after=after, coarse_gain=coarse_gain)
