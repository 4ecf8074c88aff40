"""Flicker along a camera path: how much consecutive frames disagree where they see the same surface.

**Flicker** (:func:`pair_flicker`): for consecutive frames t, t+1, frame t is reprojected into
t+1 with t+1's depth, t's depth (visibility) and both poses (:func:`~roguenerf.reprojection.reproject`,
with its validity mask); the figure is the mean absolute RGB difference over the valid pixels.
The same mask is used for the renders, the enhanced frames and, where both frames coincide with
views that have photos, the photos. Memory is bounded: two frames are held at a time. With
``TemporalConfig.both_ways`` the path's second pass, which blends each frame with the frame after
it, measures each pair the way it blends, t+1 into t, on the very move it blended by (from
2026-12-08; before, t into t+1, reprojected again: about 2 ms more a pair at 504 px on 2 cores,
8 against 10 ms).

**Sharper frames read as more flicker.** Frame t is resampled where its points land in t+1,
and resampling between pixels averages them: the finer a frame's detail, the more of it the
move loses, so a sharper video scores a larger error even where nothing in it changes from
frame to frame. Along ``can_clip``'s smooth 154-frame path (docs/broad.md) the render sharpened
by a fixed unsharp mask (amount 1, sigma 1 px), the same operation on every frame, scores 1.58
times the render's flicker; blurred (sigma 1 px), 0.67 times. On smooth paths, where the
render's own flicker is small, this is most of what separates an enhanced video from its
render. So the report also measures, as a reference, the render sharpened consistently to the
enhanced frames' detail (:func:`sharpening`: one unsharp-mask amount for both frames of a
pair): ``ratio_sharpened`` (enhanced / that reference) > 1 is flicker the enhancer adds beyond
what its sharpness alone explains.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
from torch import Tensor

DETAIL_SIGMA = 1.0
"""Gaussian sigma (pixels) that splits an image into its blur and its detail (:func:`sharpening`)."""
_DETAIL_SIZE = 7


class Sharpening(NamedTuple):
    """How much sharper an enhanced frame is than its render (:func:`sharpening`)."""

    detail: Tensor
    """``(3, H, W)``: the render minus its Gaussian blur (:data:`DETAIL_SIGMA`)."""
    amount: float
    """The unsharp-mask amount ``a`` (>= 0) that gives ``render + a * detail`` about the enhanced
    frame's detail."""
    ratio: float
    """The enhanced frame's detail over the render's (mean absolute detail): 1 as sharp, 2 twice."""

    def image(self, render: Tensor, amount: float | None = None) -> Tensor:
        """The render sharpened by ``amount`` (this frame's by default), clamped to [0, 1]."""
        return (render.float() + (self.amount if amount is None else amount) * self.detail).clamp(0, 1)


def sharpening(render: Tensor, enhanced: Tensor) -> Sharpening:
    """The unsharp mask of ``render`` (``(3, H, W)``) as sharp as ``enhanced``: sharpness is the
    mean absolute detail (an image minus its Gaussian blur of :data:`DETAIL_SIGMA`); the render's
    detail ``d`` at amount ``a`` is ``d + a * (d - blur(d))``, whose sharpness is measured at
    ``a`` = 0 and 1 and taken as linear between (the mask's own clamping to [0, 1] aside)."""
    from roguenerf.ops import gaussian_blur

    render, enhanced = render.float(), enhanced.float()
    blurred = gaussian_blur(torch.cat([render, enhanced])[None], _DETAIL_SIZE, DETAIL_SIGMA)[0]
    detail = render - blurred[:3]
    target = float((enhanced - blurred[3:]).abs().mean())
    at0 = float(detail.abs().mean())
    at1 = float((2 * detail - gaussian_blur(detail[None], _DETAIL_SIZE, DETAIL_SIGMA)[0]).abs().mean())
    amount = max((target - at0) / (at1 - at0), 0.0) if at1 > at0 else 0.0
    return Sharpening(detail, amount, target / at0 if at0 > 0 else 1.0)


def pair_flicker(images_t: list[Tensor | None], images_t1: list[Tensor | None], depth_t: Tensor, depth_t1: Tensor,
                 K_t: Tensor, K_t1: Tensor, pose_t: Tensor, pose_t1: Tensor, *,
                 warp: tuple[Tensor, Tensor] | None = None) -> tuple[list[float | None], float]:
    """Mean absolute error of each image of frame t reprojected into frame t+1, on valid pixels.

    Args:
        images_t, images_t1: lists of ``(3, H, W)`` images (or None, skipped) of the two frames,
            paired by position (e.g. [render, enhanced, photo]).
        depth_t, depth_t1: ``(1, H, W)`` z-depth of the two frames.
        K_t, K_t1: ``(3, 3)``; pose_t, pose_t1: ``(4, 4)`` OpenCV camera-to-world.
        warp: ``(coords, valid)`` of :func:`~roguenerf.reprojection.reproject` from frame t into
            t+1 with these depths, intrinsics and poses (``(1, H, W, 2)``, ``(1, 1, H, W)``),
            when the caller has made it already (the temporal filter along a path): the images
            are then sampled there (:func:`~roguenerf.reprojection.sample_at`, bilinearly as ``reproject``
            samples) instead of reprojected again.
    Returns:
        ``(errors, valid_fraction)``; an error is None when its images are missing or no pixel is valid.
    """
    from roguenerf.reprojection import reproject, sample_at

    present = [i for i, (a, b) in enumerate(zip(images_t, images_t1)) if a is not None and b is not None]
    out: list[float | None] = [None] * len(images_t)
    if not present:
        return out, 0.0
    src = torch.cat([images_t[i] for i in present])[None].float()
    with torch.inference_mode():
        if warp is None:
            rp = reproject(src, depth_t[None].float(), depth_t1[None].float(), K_t.float(), K_t1.float(),
                           pose_t.double(), pose_t1.double())
            features, valid = rp.features[0], rp.valid[0, 0] > 0
        else:
            features, valid = sample_at(src, warp[0])[0], warp[1][0, 0] > 0
    seen = valid.float()
    count = float(seen.sum())
    fraction = count / valid.numel()
    if count == 0:
        return out, fraction
    # every image's mean over the valid pixels in one pass: (sum of |difference| where valid) / count
    targets = torch.cat([images_t1[i] for i in present]).float()
    sums = ((features - targets).abs() * seen).sum(dim=(1, 2)).view(len(present), 3).sum(1) / 3
    for k, i in enumerate(present):
        out[i] = float(sums[k]) / count
    return out, fraction


def summarise_flicker(per_pair: list[dict], per_frame: list[dict]) -> dict:
    """Means over the pairs (and the frames with photos) of :func:`~roguenerf.trajectory.enhance_path`'s rows;
    ``flicker.ratio_changed`` / ``ratio_steady``: enhanced over render flicker on the
    ``neighbour_changes`` pairs across which the frames' neighbour sets differ / on the pairs
    where they are the same (None where no pair is such: frames carried name no neighbours)."""
    def mean(values):
        values = [v for v in values if v is not None and math.isfinite(v)]
        return sum(values) / len(values) if values else None

    render = mean(p["render"] for p in per_pair)
    enhanced = mean(p["enhanced"] for p in per_pair)
    sharpened = mean(p.get("sharpened") for p in per_pair)
    with_photo = [f for f in per_frame if "gain_db" in f]
    # The pairs across which the model's neighbour set changed, where both frames name theirs
    # (frames carried along a path name none): a path flickers most across them.
    named = {f["frame"]: set(f["neighbours"]) for f in per_frame if f.get("neighbours") is not None}
    both = [p for p in per_pair if p["from"] in named and p["to"] in named]
    change = [p for p in both if named[p["from"]] != named[p["to"]]]
    steady = [p for p in both if named[p["from"]] == named[p["to"]]]

    def ratio(pairs):
        render, enhanced = mean(p["render"] for p in pairs), mean(p["enhanced"] for p in pairs)
        return enhanced / render if render and enhanced is not None else None

    return {
        "flicker": {"render": render, "enhanced": enhanced, "photo": mean(p["photo"] for p in per_pair),
                    "ratio": (enhanced / render) if render and enhanced is not None else None,
                    "sharpened": sharpened,
                    "ratio_sharpened": (enhanced / sharpened) if sharpened and enhanced is not None else None,
                    "detail_ratio": mean(f.get("detail_ratio") for f in per_frame),
                    "pairs": len(per_pair), "pairs_with_photos": sum(p["photo"] is not None for p in per_pair),
                    "neighbour_changes": len(change), "ratio_changed": ratio(change), "ratio_steady": ratio(steady)},
        "psnr": {"frames_with_photos": len(with_photo),
                 "render": mean(f["render_psnr"] for f in with_photo),
                 "enhanced": mean(f["enhanced_psnr"] for f in with_photo),
                 "mean_gain_db": mean(f["gain_db"] for f in with_photo)},
        "per_pair": per_pair,
        "per_frame": per_frame,
    }
