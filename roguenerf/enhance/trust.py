"""Trust: how much of the enhancer's change to keep, from how well the neighbours agree.

The enhancer moves detail from the neighbour photos into the render through the render's
depth. Where the field's geometry is right, two neighbours reprojected through that depth show
the same colour; where it is wrong (floaters, a field that overfits its training views), they
disagree, and the detail they bring lands in the wrong place: PSNR then falls below the
render's, and a fine-tune on the field's own training views (whose geometry looks right to it)
makes that worse, not better.

The share of the view's pixels where two or more neighbours agree
(:func:`~roguenerf.enhance.colour.neighbour_agreement`, the test colour matching uses) is
measured on the small copies pose refinement already made. Below :attr:`TrustConfig.full_share`
the enhancer's change is scaled down in proportion::

    out = render + min(1, share / full_share) * (enhanced - render)

On the leave-one-kind-out figure, views of fields with sound geometry have 57-82 % agreement
(lego's test views 58-89 %), those of a hash field whose novel views are floaters 0-24 %; our
own fitter's held-out views of dtu_scan37 and mary_rose 14-93 %. The setting was chosen side by
side on the leave-one-kind-out figure (``python -m bench.stage_settings --stage trust``;
docs/kinds.md, *Trusting the neighbours by their agreement*). With fewer than two neighbours
there is nothing to compare, and the change is kept whole.

Below :attr:`TrustConfig.local_below` (10 %) the view's geometry is broken almost everywhere,
and the little change kept, spread evenly, still lands mostly where it is wrong. There the
share kept is set per pixel instead, by the share of agreeing pixels around it (a Gaussian of
:attr:`TrustConfig.local_sigma` pixels of the small copy) over ``full_share``: the change is
kept where the neighbours agree nearby, and the render elsewhere (:func:`kept_change`;
docs/kinds.md, *Where almost nothing agrees*).
"""

from __future__ import annotations

import numbers
from dataclasses import dataclass

import torch
from torch import Tensor

from roguenerf.errors import InputError


@dataclass(frozen=True)
class TrustConfig:
    full_share: float = 0.5
    """Share of the view's pixels with agreeing neighbours from which the enhancer's change is
    kept whole; below it, the change is scaled by share / full_share."""
    sigma: float = 2.0
    """Blur (pixels of the small copies) before neighbours are compared: as colour matching."""
    max_disagreement: float = 0.03
    """Two neighbours agree where their blurred colours differ by less than this: as colour matching."""
    local_below: float = 0.1
    """Below this share of agreeing pixels the share kept is set per pixel (agreement nearby over
    ``full_share``), not once for the view; 0 never."""
    local_sigma: float = 16.0
    """Reach (Gaussian sigma, pixels of the small copy) of "nearby" for ``local_below``."""

    def __post_init__(self):
        for name in ("full_share", "sigma", "max_disagreement", "local_sigma"):
            value = getattr(self, name)
            if not _positive(value):
                raise InputError(f"TrustConfig.{name}: expected a positive number, got {value!r}")
        if self.full_share > 1:
            raise InputError(f"TrustConfig.full_share: expected a share in (0, 1], got {self.full_share}")
        if not (isinstance(self.local_below, (int, float)) and 0 <= self.local_below <= 1):
            raise InputError(f"TrustConfig.local_below: expected a share in [0, 1], got {self.local_below!r}")


def _positive(value) -> bool:
    """A finite number > 0 (as :class:`TrustConfig` takes its settings)."""
    return isinstance(value, numbers.Real) and not isinstance(value, bool) and 0 < value < float("inf")


def _check_size(size) -> None:
    ok = isinstance(size, (tuple, list)) and len(size) == 2 and all(
        isinstance(v, numbers.Integral) and not isinstance(v, bool) and v >= 1 for v in size)
    if not ok:
        raise InputError(f"size: expected (H, W), two integers >= 1, got {size!r}")


def trust_factor(share: float, config: TrustConfig | None = None) -> float:
    """The share of the enhancer's change to keep, in [0, 1], for an agreement ``share``."""
    config = config or TrustConfig()
    share = float(share)
    if not 0 <= share <= 1:
        raise InputError(f"share: expected a share in [0, 1], got {share}")
    return min(1.0, share / config.full_share)


def kept_change(agree: Tensor, size, config: TrustConfig | None = None) -> float | Tensor:
    """How much of the enhancer's change to keep on a view, from its agreement map.

    Args:
        agree: ``(1, h, w)`` bool, where two or more neighbours agree (the small copy;
            :func:`~roguenerf.enhance.colour.neighbour_agreement`).
        size: ``(H, W)`` of the image the change is kept on (two integers >= 1).
        config: default :class:`TrustConfig`.
    Returns:
        A float in [0, 1] (:func:`trust_factor` of the share of agreeing pixels), or where that
        share is under ``config.local_below``, a ``(1, H, W)`` map in [0, 1]: the agreement
        around each pixel over ``full_share``.
    """
    config = config or TrustConfig()
    if agree.ndim != 3 or agree.shape[0] != 1:
        raise InputError(f"agree: expected shape (1, h, w), got {tuple(agree.shape)}")
    _check_size(size)
    share = float(agree.float().mean())
    factor = trust_factor(share, config)
    if factor >= 1 or share >= config.local_below:
        return factor
    return local_keep(agree, size, config.local_sigma, config.full_share)


def local_keep(agree: Tensor, size, sigma: float, full_share: float) -> Tensor:
    """``(1, H, W)`` share of the change to keep per pixel: the share of agreeing pixels of
    ``agree`` ``(1, h, w)`` within a Gaussian of ``sigma`` (pixels of ``agree``) over
    ``full_share``, clamped to [0, 1] and bilinearly resized to ``size``.

    ``sigma`` must be a positive number and ``full_share`` a share in (0, 1], as
    :class:`TrustConfig`'s ``local_sigma`` and ``full_share`` (else :class:`InputError`)."""
    from roguenerf.enhance.colour import blur

    _check_size(size)
    if not _positive(sigma):
        raise InputError(f"sigma: expected a positive number, got {sigma!r}")
    if not (_positive(full_share) and full_share <= 1):
        raise InputError(f"full_share: expected a share in (0, 1], got {full_share!r}")
    density = blur(agree[None].float(), sigma)
    keep = (density / full_share).clamp(0, 1)
    keep = torch.nn.functional.interpolate(keep, size=tuple(size), mode="bilinear", align_corners=False)
    return keep[0].clamp(0, 1)


def share_kept(keep: float | Tensor) -> float:
    """The mean share of the change kept, for :func:`kept_change`'s float or map."""
    return keep if isinstance(keep, float) else float(keep.mean())
