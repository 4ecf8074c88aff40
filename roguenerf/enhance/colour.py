"""Colour matching: the enhanced view's low-frequency colour, anchored on the neighbour photos.

The enhancer learns a colour prior from its pre-training renders (our grid fields render a
little darker than the photos, so it brightens), and its small model restores detail better
than smooth shading. A field of another kind (splats, which match the photos' colour) then
comes out a few thousandths too bright, and flat regions drift a little: PSNR barely notices,
but FLIP (:func:`roguenerf.metrics.flip`) does, in every flat region of the image.

The neighbour photos are the camera's own colour. Where two or more of them, reprojected
through the render's depth, agree with each other at low frequency, the geometry is right
there and their colour is what the view's photo shows. :func:`colour_match` measures, on those
pixels, the neighbours' colour minus the enhanced image's (both blurred: colour, not detail):

- its median per channel, the **offset** of the whole view;
- and a smooth **field** of it: the difference averaged over the agreeing pixels within about
  :attr:`ColourConfig.local_sigma` pixels, blended into the offset where few pixels near by agree.

:class:`~roguenerf.inference.SceneEnhancer` adds the field (upsampled) to the enhanced image.
Where fewer than :attr:`ColourConfig.min_share` of the pixels have agreeing neighbours (a field
whose geometry is broken, a single neighbour), nothing is changed.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from roguenerf.errors import InputError
from roguenerf.ops.filters import gaussian_blur


@dataclass(frozen=True)
class ColourConfig:
    sigma: float = 2.0
    """Gaussian blur (pixels of the copies no larger than ``ALIGN_SIDE``) of both the
    neighbours and the enhanced image before they are compared: colour, not detail."""
    max_disagreement: float = 0.03
    """Two neighbours agree at a pixel when their blurred colours differ by less than this
    (mean over RGB, colours in [0, 1]); 0.02 and 0.05 gave the same offsets within 0.01 dB on
    the leave-one-kind-out figure (docs/kinds.md)."""
    min_share: float = 0.3
    """Share of the view's pixels with agreeing neighbours below which nothing is changed: the
    geometry is then too wrong to trust the neighbours' colour. On the leave-one-kind-out
    figure, views of fields with sound geometry have 57-82 %, those of ollie's broken hash
    field (floaters) 0-24 %, where a 10-minute fine-tune's worst view lost another 0.18 dB
    with a 5 % floor (docs/kinds.md)."""
    local_sigma: float = 3.0
    """Reach (Gaussian sigma, pixels of the small copies) of the field: the colour difference is
    averaged over the agreeing pixels this near. 0: the view's offset alone, no field. 2, 3, 4,
    6, 8 (the default before 2026-11-27) and 16 were measured side by side (docs/kinds.md,
    *Matching the neighbours' colour*): the smaller, the higher the zero-shot gain on the
    leave-one-kind-out figure and the lower the flicker along a path; under 3 the gain flattens
    on our own look while its worst view gets worse."""
    local_support: float = 0.5
    """Where the agreeing pixels' weight near a pixel (their blurred share) is under this, the
    field there leans on the view's offset in proportion."""

    def __post_init__(self):
        for name in ("sigma", "max_disagreement", "min_share", "local_support"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and 0 < value < float("inf")):
                raise InputError(f"ColourConfig.{name}: expected a positive number, got {value!r}")
        if not (isinstance(self.local_sigma, (int, float)) and 0 <= self.local_sigma < float("inf")):
            raise InputError(f"ColourConfig.local_sigma: expected a number >= 0, got {self.local_sigma!r}")
        for name in ("min_share", "local_support"):
            if getattr(self, name) > 1:
                raise InputError(f"ColourConfig.{name}: expected a share in (0, 1], got {getattr(self, name)}")


@dataclass
class ColourMatch:
    offset: Tensor
    """``(3,)`` the view's offset: the median over the agreeing pixels."""
    field: Tensor
    """``(1, 3, h, w)`` what to add at each pixel (the image's size): the offset where
    ``local_sigma`` is 0."""
    share: float
    """Share of the pixels where two or more neighbours agree."""


def blur(x: Tensor, sigma: float) -> Tensor:
    """``(B, C, h, w)`` Gaussian blur of ``sigma`` pixels (kernel out to 3 sigma, edges replicated)."""
    k = 2 * int(3 * sigma) + 1
    return gaussian_blur(x, k, sigma)


def neighbour_agreement(neighbours: list[tuple[Tensor, Tensor]], size, sigma: float,
                        max_disagreement: float) -> tuple[Tensor, Tensor]:
    """Where two or more reprojected neighbours agree at low frequency.

    Args:
        neighbours: per neighbour (two or more), its photo reprojected into the view
            ``(1, 3, h, w)`` and where that is valid ``(1, 1, h, w)`` (0/1).
        size: ``(h, w)`` expected of every neighbour.
        sigma: Gaussian blur (pixels) of each neighbour over its valid pixels before comparing.
        max_disagreement: two neighbours agree where their blurred colours differ by less than
            this (mean over RGB); every pair seeing a pixel must agree there.
    Returns:
        ``agree`` ``(1, h, w)`` bool (two or more neighbours see the pixel and agree) and
        ``mean`` ``(1, 3, h, w)``, the blurred neighbours' mean colour where they see.
    """
    if len(neighbours) < 2:
        raise InputError(f"neighbours: expected two or more to compare, got {len(neighbours)}")
    size = tuple(size)
    stack, valid = [], []
    for colour, mask in neighbours:
        if tuple(colour.shape) != (1, 3, *size) or tuple(mask.shape) != (1, 1, *size):
            raise InputError(f"neighbours: expected colours of size (1, 3, *{size}) and masks (1, 1, *{size}), got "
                             f"{tuple(colour.shape)} and {tuple(mask.shape)}")
        m = (mask.float() > 0.5).float()
        # Blur over the valid pixels only (normalised convolution): no colour bleeds in from
        # where the neighbour does not see; what is there is ignored, NaN included (NaN × 0 is NaN).
        stack += [torch.where(m > 0, colour.float(), torch.zeros((), dtype=torch.float32)), m]
        valid.append(m[:, 0] > 0.5)
    # every neighbour's colour and mask in one blur (each channel on its own: the same values)
    smooth = blur(torch.cat(stack, dim=1), sigma)
    blurred = [smooth[:, 4 * j:4 * j + 3] / smooth[:, 4 * j + 3:4 * j + 4].clamp_min(1e-3)
               for j in range(len(neighbours))]
    count = torch.stack(valid).sum(0)
    total = torch.zeros_like(blurred[0])
    for b, v in zip(blurred, valid, strict=True):
        total += b * v[:, None]
    mean = total / count[:, None].clamp_min(1)
    disagreement = torch.zeros(count.shape, dtype=total.dtype)
    for a in range(len(blurred)):
        for b in range(a + 1, len(blurred)):
            both = valid[a] & valid[b]
            d = (blurred[a] - blurred[b]).abs().mean(1)
            disagreement = torch.where(both, torch.maximum(disagreement, d), disagreement)
    return (count >= 2) & (disagreement < max_disagreement), mean


def colour_match(image: Tensor, neighbours: list[tuple[Tensor, Tensor]],
                 config: ColourConfig | None = None, *,
                 agreement: tuple[Tensor, Tensor] | None = None) -> ColourMatch | None:
    """How far ``image``'s colour is from the agreeing neighbours', as an offset and a field.

    Args:
        image: ``(1, 3, h, w)`` the enhanced view (any size; the caller passes a small copy).
        neighbours: per neighbour, its photo reprojected into the view ``(1, 3, h, w)`` and
            where that is valid ``(1, 1, h, w)`` (0/1), as :func:`~roguenerf.reprojection.reproject`
            gives them.
        config: thresholds; default :class:`ColourConfig`.
        agreement: :func:`neighbour_agreement` of ``neighbours`` with ``config``'s ``sigma`` and
            ``max_disagreement``, when the caller has it already (not measured again).
    Returns:
        A :class:`ColourMatch`, or None where fewer than two neighbours agree on at least
        ``config.min_share`` of the pixels.
    """
    config = config or ColourConfig()
    if image.ndim != 4 or image.shape[:2] != (1, 3):
        raise InputError(f"image: expected shape (1, 3, h, w), got {tuple(image.shape)}")
    if len(neighbours) < 2:
        return None
    image = image.float()
    agree, mean = agreement or neighbour_agreement(neighbours, image.shape[-2:], config.sigma,
                                                   config.max_disagreement)
    share = float(agree.float().mean())
    if share < config.min_share:
        return None
    diff = mean - blur(image, config.sigma)  # (1, 3, h, w)
    offset = torch.stack([diff[0, c][agree[0]].median() for c in range(3)])
    if not bool(torch.isfinite(offset).all()):
        return None
    field = offset.view(1, 3, 1, 1).expand_as(image).clone()
    if config.local_sigma > 0:
        a = agree[:, None].float()
        smooth = blur(torch.cat([diff * a, a], dim=1), config.local_sigma)  # one blur, 4 channels
        support = smooth[:, 3:]
        local = smooth[:, :3] / support.clamp_min(1e-3)
        w = (support / config.local_support).clamp(0, 1)
        field = w * local + (1 - w) * field
    return ColourMatch(offset=offset, field=field, share=share)


def apply_match(image: Tensor, match: ColourMatch) -> Tensor:
    """``(3, H, W)`` ``image`` plus ``match``'s field (bilinearly upsampled to its size), clamped to [0, 1]."""
    field = match.field
    if field.shape[-2:] != image.shape[-2:]:
        field = torch.nn.functional.interpolate(field, size=tuple(image.shape[-2:]), mode="bilinear",
                                                align_corners=False)
    return (image + field[0]).clamp(0, 1)


def colour_offset(image: Tensor, neighbours: list[tuple[Tensor, Tensor]],
                  config: ColourConfig | None = None) -> Tensor | None:
    """The view's ``(3,)`` offset of :func:`colour_match` (None where it finds no agreement)."""
    match = colour_match(image, neighbours, config)
    return None if match is None else match.offset
