"""Videos: each enhanced frame blended with the one before it, along a camera path.

A radiance field's render of a path is mostly consistent from frame to frame: every frame comes
from the same 3D field (floaters aside, which come and go). The enhancer adds to it detail and colour taken from
neighbour photos, and that addition (the *residual*, enhanced minus render) is decided per frame:
where the neighbour set changes, a pose fit lands a little differently, or the colour field and
the trust share move, the residual jumps, and the video flickers more than the render.

:class:`TemporalFilter` keeps the previous frame's result, reprojects it into the current frame
through the render's depth (the same warp :func:`~roguenerf.reprojection.reproject` gives the
neighbours, with its visibility test), and blends, wherever the previous frame sees the pixel
(elsewhere the frame is its own)::

    out_t = (1 - w) * enhanced_t + w * warp(out_{t-1})              blend="image" (the default)
    out_t = render_t + (1 - w) * (enhanced_t - render_t) + w * warp(out_{t-1} - render_{t-1})
                                                                     blend="residual"

The weight falls where the two frames' *renders* disagree after the same warp
(:attr:`TemporalConfig.reject`, :func:`render_disagreement`): ``w = weight * 0.5 ** (d / reject)
** 2``. There the warp is wrong (the field's depth is off) or the point looks different from the
two cameras, and blending the last frame in would ghost: on ``dtu_scan37``'s hash field the blend
without it left the frames with photos up to 1 dB below their renders (docs/broad.md).

The weight also falls with the parallax at each pixel (:attr:`TemporalConfig.fade_deg`), the
angle at its 3-D point between the two frames' rays: ``w = weight * 0.5 ** (angle / fade_deg)``.
Without it the average carried frames seen from several degrees away, resampled again at every
step: on ``can_clip``'s 49-frame path the enhanced frames kept 0.30 dB less of the gain than
frame by frame (frame 16: 0.72 dB less); with ``fade_deg=4`` (the default from 2026-12-07)
0.09 dB less, the flicker 0.70 times the render's (frame by frame: 1.37; docs/broad.md,
*Blend fading with parallax*). With :attr:`TemporalConfig.fade_along` (the default since
2026-12-07, with ``fade_deg=16``) the angle is the one *accumulated* along the average: each pixel
carries the mean parallax of the frames blended into it (:attr:`TemporalFilter.last_parallax`),
so a slow path blends many frames and a fast one few (docs/broad.md, *The fade along the path*).

Along a path (:func:`~roguenerf.trajectory.enhance_path`) with :attr:`TemporalConfig.both_ways`
(the default) a second filter then runs from the last frame back to the first over the first
pass's frames: each is blended the same way with the frame after it as written. The two passes
make a forward-backward moving average, which has no lag: a frame's result is a mean of frames
on both sides of it rather than of the frames before it only.

Because the carried frame is the blended one, the filter is an exponential moving average along
the path: with ``w = 0.75`` (the default) a frame's own result counts 0.25, the one before
0.1875, the one before that 0.14, and so on (with 0.5, the default before 2026-12-07: 1/2, 1/4,
...), before the rejection and the fade lower ``w``.
Blending the image smooths the render's own flicker too (a field's floaters that come and
go; the rejection keeps each frame's own where they differ much); blending only the residual
carries those back in, and flickered more on a hash field's path than no blending at all
(docs/broad.md, *Videos that do not flicker*). A cut (a pose far from the last) needs no
special case: the warp then sees nothing of it, and the frame keeps its own.

With :attr:`TemporalConfig.model_every` = k > 1 the model runs on one frame in k; a frame
between is *carried* (:meth:`TemporalFilter.carry`): the previous frame's result reprojected
into it, which is what the blend would give that frame with ``w = 1``::

    out_t = warp(out_{t-1})   where the previous frame sees the pixel, render_t elsewhere

(with :attr:`TemporalConfig.reject`, drawn toward ``render_t`` where the two renders disagree),
and the model runs on it after all where the previous frame sees less than
:attr:`TemporalConfig.min_seen` of it (a cut, a fast turn, a disocclusion), or, with
:attr:`TemporalConfig.carry_agreement`, where its render moved the same way does not predict
this frame's render (the field's depth is off, or the move long: the moved frame would put
detail in the wrong place). With :attr:`TemporalConfig.carry_from` ``"model"`` (the default)
the frame moved is the last one the model ran on rather than the one before (``warp`` then
moves ``out_m``, m the model's frame: resampled once, not once per carried frame).

With :attr:`TemporalConfig.carry_between` the model runs on the frames ``a`` = 0, k, 2k, ...
(and the last) first, and a frame ``t`` between two of them, ``a < t < b``, is carried from
both (:meth:`TemporalFilter.carry`'s ``between``)::

    out_t = ((b - t) * warp(out_a) + (t - a) * warp(out_b)) / (b - a)    where both see

(where only one sees, that one). No frame is then moved further than half of k frames, and the
frames between cross-fade from one model frame to the next instead of drifting away from the
last one.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import torch
from torch import Tensor

from roguenerf.errors import InputError


@dataclass(frozen=True)
class TemporalConfig:
    weight: float = 0.75
    """Share of the previous frame's result (reprojected) in each frame's, in [0, 1), before
    :attr:`reject` and :attr:`fade_deg` lower it. 0.75 since 2026-12-07 (0.8 from earlier that day,
    0.5 before): chosen on the choice half's paths (``can_clip``'s smooth 154- and 49-frame paths,
    ``dtu_scan37``'s 49- and 13-frame ones, about 2.5 and 10 degrees a frame) by the rule that chose
    :attr:`reject`: the least mean flicker of the weights (0.6, 0.7, 0.75, 0.8) that cost no path
    more than 0.1 dB on its frames with photos against frame by frame and leave none flickering more
    than its render. 0.8 was chosen so before both ways and the fade along the path; with them it
    cost ``can_clip``'s 49 frames 0.11 dB (0.75: 0.05), and 0.6 left its 154 frames at 1.002 of
    the render's flicker. Reported on ``ollie``'s and ``mary_rose``'s paths (docs/broad.md, *The
    blend's weight again*)."""
    change_weight: float = 0.9
    """``weight`` at a frame whose neighbours differ from the previous frame's, and at the
    :attr:`change_frames` - 1 frames after it (only with :attr:`change_frames` > 0): the jump a
    new neighbour set brings (the model's output with one photo swapped) is spread over more
    frames."""
    change_frames: int = 0
    """How many frames, from a change of the neighbour set on, take :attr:`change_weight`
    (:func:`settling`); 0 (the default): none. Along ``can_clip``'s 154-frame path the set changes
    15 times, and those pairs flicker twice as much as the others; 3 frames at 0.9 lowered the
    flicker less than the heavier :attr:`weight` and cost 0.08-0.15 dB there (docs/broad.md)."""
    both_ways: bool = True
    """Along a path, blend each frame with the frames after it too: a second pass, from the last
    frame back to the first, blends each frame of the first pass (blended with the frames before
    it) with the frame after it as written (:func:`~roguenerf.trajectory.enhance_path`), the same
    way (:attr:`weight`, :attr:`reject`, :attr:`fade_deg`). A forward-backward moving average: it
    smooths as much or more with no lag, so a frame where a nearer photo comes in keeps more of
    what that photo brings. True since 2026-12-07: chosen on the choice half's paths by the rule
    that chose :attr:`weight` (``can_clip``'s 154 frames: flicker 0.983 -> 0.917 of the render's,
    +3.083 -> +3.092 dB; ``dtu_scan37``'s 49 and 13: 0.560 -> 0.490, 0.709 -> 0.667, +0.517 ->
    +0.563, +0.515 -> +0.549; docs/broad.md, *Both ways along the path*). On the report half's
    seven paths: less flicker than one way on all, the mean gain of frame by frame (+1.887 against
    +1.881 dB; one way +1.831), but ``mary_rose``'s orbits 0.10-0.20 dB below frame by frame (a
    mean over both sides averages more view-dependent detail). False: the first pass alone
    (frames written as they are made, no second read of them)."""
    blend: str = "image"
    """What is carried and blended: ``"residual"`` (the enhancer's change over the render, the
    module docstring) or ``"image"`` (the enhanced frame itself: the render's own flicker, a
    field's floaters that come and go, is smoothed too)."""
    reuse_poses: bool = True
    """Fit each neighbour's pose (pose refinement) the first time a frame uses it, and reuse it
    for the frames after (fitted again from nearer: :attr:`refit_nearer`): the same photo lands
    the same way on every frame, and the fits are paid a few times per neighbour rather than
    once per frame."""
    refit_nearer: float = 0.5
    """With :attr:`reuse_poses`: a frame whose camera is nearer a neighbour photo's than
    ``refit_nearer`` times the distance its pose was last fitted from fits it again, unless that
    fit found nothing to gain (:class:`~roguenerf.inference.PoseMemory`). 0: each neighbour is
    fitted once per path (the default before 2026-12-07). A fit made from far matches worse:
    on ``can_clip``'s half-size splat path frame 16 kept +0.52 dB fitted once, +1.05 with 0.5,
    +1.63 frame by frame; no other path of the figure changed (docs/broad.md, *Pose fits made
    again from nearer*)."""
    keep_within: int = 0
    """A frame keeps the previous frame's neighbours that are still among its ``keep_within``
    nearest training views (the paper's ranking), and takes the rule's choice only for the
    rest; 0: every frame takes the rule's choice. Along a path the rule's choice changes every
    few frames, and each change makes the enhanced frame jump (:func:`sticky_neighbours`)."""

    model_every: int = 1
    """Run the model on one frame in this many (the first, then every ``model_every``-th; with
    :attr:`carry_between` also the last, without it every frame whose neighbours changed); carry the
    model frames' results into the frames between (:meth:`TemporalFilter.carry`: from the two
    around, :attr:`carry_between`, or from the last). 1: the model on every frame. A carried
    frame costs a reprojection or two instead of the model, its pose fits, colour and trust."""
    resample: str = "bicubic"
    """How the last frame is sampled where its points land: ``"bicubic"`` (sharper) or
    ``"bilinear"`` (the reprojection's own sampling: a sample between pixels averages them, and
    the carried frame loses its finest detail). Chosen on ``can_clip``'s hash field, reported on
    ``ollie``'s grid field (a 46-frame path each): +0.04 dB on the frames with photos on both,
    flicker 0.440 -> 0.451 and 0.506 -> 0.512 of the render's (docs/results.md, *Speed at users'
    sizes*)."""
    carry_from: str = "model"
    """Which frame a carried frame is moved from: ``"model"`` (the last frame the model ran on:
    one resampling, over a longer move, which :attr:`carry_agreement` then judges whole) or
    ``"last"`` (the frame before it, itself perhaps carried: with ``model_every`` >= 3 a frame
    is resampled once per carried frame before it; the default before 2026-12-06). The same at
    ``model_every`` <= 2; only with :attr:`carry_between` off."""
    carry_agreement: float = 0.0
    """A frame is carried only where the frame it would be moved from predicts its render: that
    frame's render, moved the same way, matches this frame's render to at least this PSNR (dB)
    on the pixels it sees (:attr:`TemporalFilter.last_agreement`); otherwise the model runs on
    it. Where the field's depth is off, or the move is long, the moved frame puts detail in the
    wrong place, and the renders say so: along ``ollie``'s and ``can_clip``'s paths a carried
    frame came within about 1-3 dB of this PSNR to the model's own output. 0 (the default): no
    such test (only :attr:`min_seen`). 46 from 2026-12-06 to 2026-12-07 (chosen on ``can_clip``'s
    154-frame path carrying from the last model frame, before :attr:`carry_between`); chosen again
    with :attr:`carry_between` (the fourteenth session), by a rule stated before the runs, on the
    choice half's paths whose frames with photos are carried (``can_clip``'s 49 frames at
    ``model_every`` 3 and 154 at 4, ``dtu_scan37``'s 49 and 13 at 3): of no gate, 46 dB and
    :attr:`carry_share` 0.02-0.2, every one kept each path's gain on those frames within 0.05 dB
    of frame by frame's, and no gate carried the most frames (61 % over the four against 33 % with
    46 dB, which refused every frame of ``dtu_scan37``'s, whose renders agree at 21-39 dB).
    Reported on ``ollie``'s and ``mary_rose``'s paths (docs/results.md, *Speed at users' sizes*):
    ``ollie``'s 49 frames at 3, 1.83x frame by frame with more gain (+2.56 against +2.48 dB; 46:
    1.44x); ``mary_rose``'s orbit (10 degrees a frame) 0.41 dB below frame by frame, where 46 and
    :attr:`carry_share` 0.05-0.2 kept its gain: on fast orbits pass one of them. Chosen again per
    carried frame for :meth:`fast` (28 dB, then :attr:`carry_nearer` instead: :data:`FAST`)."""
    carry_share: float = 0.0
    """A frame is carried only where the frame(s) it would be moved from predict its render well
    *against the size of the enhancer's change*: the mean square of what their renders, moved the
    same way, miss of this frame's render (:attr:`TemporalFilter.last_agreement`) at most this
    share of the mean square of the change the model frames made over their own renders
    (:attr:`TemporalFilter.last_change`; with :attr:`carry_between` the two mixed by position);
    otherwise the model runs on it. A moved frame misplaces about as much as its render's miss, and
    that matters against what the enhancer adds, not in dB alone: a field whose renders move less
    faithfully (view-dependent colour) and whose enhancer changes more lets the same carries
    through. 0 (the default): no such test (only :attr:`carry_agreement` and :attr:`min_seen`).
    Not chosen (docs/results.md, *Speed at users' sizes*, fourteenth session): on the choice half
    it carried fewer frames than no gate for no more gain (it refuses every frame of
    ``dtu_scan37``'s paths, whose renders agree about as much as its enhancer changes, where carrying cost
    0.01 dB); on the report half 0.2 carried 49 % of ``ollie``'s 49 frames (46 dB: 18 %) and kept
    the gain of ``mary_rose``'s orbit, which no gate lost 0.41 dB of."""
    carry_between: bool = True
    """With ``model_every`` = k > 1, run the model on frames 0, k, 2k, ... (and the last) first,
    and carry each frame between two of them from *both*: the two moved into it and mixed by how
    near each is along the path (frame ``t`` between model frames ``a`` and ``b``: weights
    ``(b - t)`` and ``(t - a)``, wherever each sees), so no frame is carried further than half of
    ``k`` frames. False: from the last model frame only (:attr:`carry_from`; the default before
    2026-12-07). The frames are still written, measured and resumed in order; a frame between
    whose carry is refused (:attr:`min_seen`, :attr:`carry_agreement`) is enhanced by the model as
    before. Chosen on ``can_clip``'s 49-frame path (k = 3, frames with photos carried: +2.99 dB
    against +2.71 from the last model frame without the gate, +3.02 with it at 0.6 times the
    frames per second; flicker 0.78-0.80 of the render's against 0.90), reported on ``ollie``'s
    and ``mary_rose``'s (docs/results.md, *Speed at users' sizes*)."""
    between_agreement: float = 0.0
    """With :attr:`carry_between`: a frame between two model frames is carried only where the
    two, moved into it, also agree with each other to at least this PSNR (dB) on the pixels both
    see (:attr:`TemporalFilter.last_mutual`); otherwise the model runs on it. Where the two model
    frames' results disagree about the frame between them, the mix is neither's. Along
    ``can_clip``'s 49-frame path this agreement predicts how close a carried frame comes to the
    model's own output there (correlation 0.79; the renders' agreement: -0.18), but as a PSNR it
    depends on the scene: 42 dB kept ``can_clip``'s gain at 1.2 times frame by frame's speed, and
    on ``dtu_scan37`` (renders at 18 dB) 38 already refused every frame (docs/results.md, *Speed
    at users' sizes*). 0 (the default): no such test."""
    carry_nearer: float = 0.0
    """A frame is carried only where the model frame(s) it would be moved from are at most this
    many times as far from it (camera centres; with :attr:`carry_between` the two distances mixed
    by position) as the nearest training photo (:attr:`TemporalFilter.last_nearer`); otherwise
    the model runs on it. Where a photo is nearer than the model frames, the model brings from it
    what no model frame around has: a carried frame at a photo's position kept 1.7 dB less
    (``mary_rose``'s orbit frame 32, a training camera where it stands). 0 (the default): no
    such test; 1 in :meth:`fast` (:data:`FAST`, chosen per carried frame). Needs the photo's
    distance (:meth:`TemporalFilter.carry`'s ``photo_distance``, which
    :func:`~roguenerf.trajectory.enhance_path` gives)."""
    schedule: str = "fixed"
    """Where the model frames of :attr:`carry_between` go: ``"fixed"``, on every
    :attr:`model_every`-th frame (and the last); ``"gate"``, as far apart as
    :attr:`carry_nearer` lets every frame between them be carried, at most :attr:`model_every`
    frames (:func:`gated_schedule`, worked out from the cameras before the first frame). With
    ``"fixed"`` a frame the gate refuses gets the model on its own and the stretch around it is
    still carried from the fixed model frames, which are then farther from the frames beside it
    than a model frame at the refused one would be; ``"gate"`` puts the model frames where the
    photos call for them, and as far apart as ``model_every`` allows where none does. Needs
    :attr:`carry_between` (refused without it) and ``model_every`` > 1 (at 1 the same as
    ``"fixed"``); without :attr:`carry_nearer` every stretch is ``model_every`` long. Not the fast setting's
    (docs/results.md, *Speed at users' sizes*, sixteenth session): chosen by :data:`FAST`'s rule at
    8 with ``carry_nearer`` 0.5 (at 1 and 0.75 a frame of ``dtu_scan37``'s 13-frame path, which the
    fixed schedule makes a model frame, lost 0.11 dB), it then lost 0.79 dB on a carried frame of
    ``can_clip``'s 49-frame path and carried fewer frames there."""
    min_seen: float = 0.95
    """A frame is carried only where the previous frame sees at least this share of its
    pixels; otherwise the model runs on it."""
    reject: float = 0.04
    """The blend's weight halves where the last frame's *render*, reprojected into this one,
    differs from this frame's render by ``reject`` (mean absolute difference over the colour
    channels, a 3 x 3 mean; :func:`render_disagreement`), falls to 1/16 at twice that
    (``0.5 ** (d / reject) ** 2``). The renders disagree where the reprojection is wrong (the
    field's depth is off, a disocclusion the visibility test missed) or the point looks
    different from the two frames: there the last frame's result is not this frame's, and
    blending it in ghosts. 0: no rejection. Chosen on the paths of the figure's choice half
    (``dtu_scan37``'s and ``can_clip``'s hash fields: the least flicker of the settings that
    cost no path more than 0.1 dB against frame by frame), reported on the report half's
    (docs/broad.md, *Videos that do not flicker*)."""
    fade_deg: float = 16.0
    """The blend's weight halves for every ``fade_deg`` degrees of parallax at a pixel: the
    angle, at the pixel's 3-D point, between the rays of this frame's camera and the last
    frame's (:func:`parallax_deg`), with :attr:`fade_along` (the default) plus the parallax of
    what the last frame carried. Two frames far apart around the object see a point from
    different sides (its view-dependent colour, the resampling's blur), and the last frame's
    result is then a worse guess of this one. 0: the weight does not depend on it (the default
    before 2026-12-07). Chosen on the paths of the figure's choice half: of the settings that
    kept every path within 0.1 dB of frame by frame (``can_clip``'s half-size splat path aside,
    which no setting kept) and its flicker at most the render's, the least flicker; reported on
    the report half's (docs/broad.md, *Blend fading with parallax*): 4 of the plain fade (the
    default from 2026-12-07), **16** along the path (the default since, chosen the same way of 8,
    12, 16 and 20: *The fade along the path*)."""

    fade_along: bool = True
    """With :attr:`fade_deg`: fade by the parallax *accumulated* along the moving average rather
    than by the angle between two frames only. The frame carried into a blend is itself a mix of
    frames seen from further back along the path; each pixel keeps the mean parallax of what it
    carries (:attr:`TemporalFilter.last_parallax`: the angle to the last frame plus what that
    frame carried, moved with it, times the weight it took), and the weight halves for every
    :attr:`fade_deg` of that sum. A frame's far history then counts less than its near one, where
    the plain fade weighs a whole moving average by its last step: a slow path is blended over many
    frames, a fast one over few. True since 2026-12-07 (with :attr:`fade_deg` 16): chosen on the
    choice half's nine paths by the rule that chose :attr:`fade_deg`, less flicker on every one of
    them than the plain fade of 4 (mean 0.753 against 0.779 of the render's) for the same mean gain
    (+1.437 dB); reported on the report half's seven: less flicker on every one (mean 0.616 against
    0.643), 0.00-0.04 dB less gain (mean +1.926 against +1.945; frame by frame +1.882); docs/broad.md,
    *The fade along the path*. A resumed path works a read-back frame's map out again
    (:meth:`TemporalFilter.remember`). False: the angle of the last step alone."""

    @classmethod
    def fast(cls, **changes) -> TemporalConfig:
        """The path's fast setting (``enhance-path --fast``): :data:`FAST`, then ``changes``
        (any field)."""
        return cls(**{**FAST, **changes})

    def __post_init__(self):
        if not isinstance(self.fade_along, bool):
            raise InputError(f"TemporalConfig.fade_along: expected True or False, got {self.fade_along!r}")
        if isinstance(self.model_every, bool) or not isinstance(self.model_every, int) or self.model_every < 1:
            raise InputError(f"TemporalConfig.model_every: expected an integer >= 1, got {self.model_every!r}")
        if self.carry_from not in ("last", "model"):
            raise InputError(f"TemporalConfig.carry_from: expected 'last' or 'model', got {self.carry_from!r}")
        if self.schedule not in ("fixed", "gate"):
            raise InputError(f"TemporalConfig.schedule: expected 'fixed' or 'gate', got {self.schedule!r}")
        if self.schedule == "gate" and not self.carry_between:
            raise InputError("TemporalConfig.schedule: 'gate' places the model frames that frames are carried "
                             "between: needs carry_between=True")
        if self.resample not in ("bilinear", "bicubic"):
            raise InputError(f"TemporalConfig.resample: expected 'bilinear' or 'bicubic', got {self.resample!r}")
        for name, what in (("carry_agreement", "a PSNR in dB"), ("between_agreement", "a PSNR in dB"),
                           ("carry_share", "a share"), ("carry_nearer", "a ratio of distances")):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
                    and value >= 0):
                raise InputError(f"TemporalConfig.{name}: expected {what} >= 0 (0: off), got {value!r}")
        if not (isinstance(self.min_seen, (int, float)) and 0 <= self.min_seen <= 1):
            raise InputError(f"TemporalConfig.min_seen: expected a share in [0, 1], got {self.min_seen!r}")
        if not (isinstance(self.reject, (int, float)) and math.isfinite(self.reject) and self.reject >= 0):
            raise InputError(f"TemporalConfig.reject: expected a colour difference >= 0 (0: off), got {self.reject!r}")
        if not (isinstance(self.fade_deg, (int, float)) and math.isfinite(self.fade_deg) and self.fade_deg >= 0):
            raise InputError(f"TemporalConfig.fade_deg: expected degrees >= 0 (0: no fade), got {self.fade_deg!r}")
        for name in ("weight", "change_weight"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and 0 <= value < 1):
                raise InputError(f"TemporalConfig.{name}: expected a share in [0, 1), got {value!r}")
        if self.blend not in ("residual", "image"):
            raise InputError(f"TemporalConfig.blend: expected 'residual' or 'image', got {self.blend!r}")
        if not isinstance(self.both_ways, bool):
            raise InputError(f"TemporalConfig.both_ways: expected True or False, got {self.both_ways!r}")
        if not isinstance(self.reuse_poses, bool):
            raise InputError(f"TemporalConfig.reuse_poses: expected True or False, got {self.reuse_poses!r}")
        if not (isinstance(self.refit_nearer, (int, float)) and not isinstance(self.refit_nearer, bool)
                and 0 <= self.refit_nearer < 1):
            raise InputError(f"TemporalConfig.refit_nearer: expected a share in [0, 1) (0: off), "
                             f"got {self.refit_nearer!r}")
        if isinstance(self.change_frames, bool) or not isinstance(self.change_frames, int) or self.change_frames < 0:
            raise InputError(f"TemporalConfig.change_frames: expected an integer >= 0, got {self.change_frames!r}")
        if isinstance(self.keep_within, bool) or not isinstance(self.keep_within, int) or self.keep_within < 0:
            raise InputError(f"TemporalConfig.keep_within: expected an integer >= 0, got {self.keep_within!r}")
        if not isinstance(self.carry_between, bool):
            raise InputError(f"TemporalConfig.carry_between: expected True or False, got {self.carry_between!r}")
        if self.carry_between and self.model_every > 1 and self.keep_within > 0:
            raise InputError("TemporalConfig.carry_between: needs keep_within 0 or carry_between=False (a "
                             "frame's neighbours would depend on the frame before it, made after the next "
                             "model frame)")


FAST = {"model_every": 4, "carry_nearer": 1.0, "both_ways": False}
"""The fields :meth:`TemporalConfig.fast` sets (the rest are the defaults): the model on one
frame in 4, each frame between two model frames carried from both where they are no farther from
it (mixed by position) than its nearest training photo, and one pass. Chosen on 2026-12-08
(fifteenth session) on ``mary_rose``'s and ``dtu_scan37``'s paths (a 24-view path of each through
its photos, where every frame carried is judged, the 49-frame orbit and smooth paths, the 13-frame
one at 10 degrees a frame) by a rule stated before the runs: keep the settings where no carried
frame with a photo loses more than 0.1 dB against frame by frame and no path flickers more than
its render; of those, the most frames carried. First of :attr:`TemporalConfig.carry_agreement` 0,
24, 28, 32, 36, 40 and 46 at ``model_every`` 3 and 4 (28 at 3 won: 44 of the 159 frames; 0 and 24
lost up to 1.7 dB on frames whose renders agreed at 15-27.5 dB, ``mary_rose``'s orbit frame 32 at
22.8 dB: +2.16 against +3.87, a training camera where it stands); that failed per frame on the
report half (a carried frame near a photo lost 0.2-0.4 dB on smooth paths, up to 3.9 on the photo
paths, whose renders agreed at 28-51 dB), so again with :attr:`TemporalConfig.carry_nearer` 0,
0.25, 0.5, 1 and 2 beside ``carry_agreement`` 0 and 28: ``carry_nearer`` 1 at 4 carried the most,
51 (at 4 no frame with a photo of the choice half's smooth paths is carried: none was judged
there; at 3 it lost 0.11 dB on ``dtu_scan37``'s 13-frame path). Reported on ``ollie``'s and
``can_clip``'s paths (docs/results.md, *Speed at users' sizes*). Judged again on 2026-12-08
(sixteenth session) on 46-frame paths whose frames with photos fall between model frames (15, 30):
a carried frame with a photo lost 0.49 dB on ``can_clip`` and 0.74 on ``ollie`` (on
``dtu_scan37`` 0.00-0.01), though its model frames were 2-3 times nearer to it than its nearest
training photo: the carry itself loses detail where the enhancer adds most, which
:attr:`TemporalConfig.carry_nearer` does not see. Tried with :attr:`TemporalConfig.schedule`
``"gate"`` (at 8 with 0.5, chosen on the choice half by the same rule): 0.79 dB lost on a carried
frame of ``can_clip``'s 49-frame path; not shipped."""


def mixed_distance(centres: Tensor, t: int, before: int, after: int) -> float:
    """How far frame ``t`` is from the model frames ``before`` < ``t`` < ``after`` it is carried
    between, for :attr:`TemporalConfig.carry_nearer`: their camera centres' distances to its
    (``centres`` ``(T, 3)``, float64) mixed by position, as :meth:`TemporalFilter.carry` mixes them."""
    position = (t - before) / (after - before)
    return ((1.0 - position) * float((centres[before] - centres[t]).norm())
            + position * float((centres[after] - centres[t]).norm()))


def gated_schedule(centres: Tensor, photo_distances: list[float], most: int, nearer: float) -> list[int]:
    """The model frames of a path for :attr:`TemporalConfig.schedule` ``"gate"``: frame 0, then each
    next one as far on as every frame between passes :attr:`TemporalConfig.carry_nearer`
    (:func:`mixed_distance` at most ``nearer`` times its nearest photo's; 0: no test), at most
    ``most`` frames on (the very next frame where no later one lets them all pass), and the last
    frame. ``centres`` ``(T, 3)`` float64 camera centres; ``photo_distances``: each frame's
    distance to its nearest training photo (:meth:`~roguenerf.inference.SceneEnhancer.photo_distance`)."""
    total = len(centres)
    if isinstance(most, bool) or not isinstance(most, int) or most < 1:
        raise InputError(f"most: expected an integer >= 1, got {most!r}")
    if len(photo_distances) != total:
        raise InputError(f"photo_distances: expected one per frame ({total}), got {len(photo_distances)}")
    if total == 0:
        return []
    frames, before = [0], 0
    while before < total - 1:
        after = before + 1
        for candidate in range(before + 2, min(before + most, total - 1) + 1):
            # carry's own test (far > nearer * photo: refused), on the same numbers
            if nearer <= 0 or not any(mixed_distance(centres, t, before, candidate) > nearer * photo_distances[t]
                                      for t in range(before + 1, candidate)):
                after = candidate
        frames.append(after)
        before = after
    return frames


def render_disagreement(warped_render: Tensor, render: Tensor, valid: Tensor) -> Tensor:
    """Per pixel, how much the last frame's render reprojected into this frame (``(3, H, W)``, seen
    where ``valid`` ``(1, H, W)``) differs from this frame's ``render``: the mean absolute
    difference over the channels, averaged over the 3 x 3 pixels around it that are seen;
    ``(1, H, W)``, 0 where nothing around is seen."""
    from roguenerf.ops import box_sum3

    seen = valid.float()
    diff = (warped_render - render).abs().mean(0, keepdim=True) * seen
    total, count = box_sum3(torch.cat([diff, seen])[None])[0]
    return torch.where(count > 0, total / count.clamp_min(1e-12), 0.0)[None]


def _masked_psnr(image: Tensor, reference: Tensor, seen: Tensor, *, none_seen: float = 0.0) -> float:
    """PSNR (dB, peak 1) of ``image`` against ``reference`` (``(3, H, W)``) on the pixels ``seen``
    (``(1, H, W)`` bool); ``none_seen`` where none is, 120 where they are equal."""
    mask = seen.float()
    count = 3.0 * float(mask.sum())
    if count == 0:
        return none_seen
    mse = float(((image - reference).square() * mask).sum()) / count
    return -10.0 * math.log10(max(mse, 1e-12))


def parallax_deg(depth: Tensor, K: Tensor, world_from_cam: Tensor, other_centre: Tensor) -> Tensor:
    """Per pixel, the angle in degrees at its 3-D point (``depth`` ``(1, H, W)`` z-depth through
    ``K`` and camera-to-world ``world_from_cam``) between the ray from this camera and the ray from
    a camera centred at ``other_centre`` ``(3,)``: ``(1, H, W)``; 0 where the depth is unknown.

    In this camera's axes, with ``r = K^-1 [u + 0.5, v + 0.5, 1]`` the pixel's ray and ``delta``
    this centre minus the other one, the point is ``z r`` and the angle is
    ``atan2(|z r x (z r + delta)|, z r . (z r + delta))``; dividing both by ``z > 0`` leaves
    ``atan2(|r x delta|, z |r|^2 + r . delta)``. ``delta`` is taken in float64 (both centres may
    be far from the origin, their difference small), the per-pixel work in float32 on separable
    rays: 5 ms at 504 x 378 on 2 cores against 42 ms for the float64 point-by-point form."""
    from roguenerf.geometry import known_depth_mask

    pose = torch.as_tensor(world_from_cam).to(torch.float64)
    h, w = depth.shape[-2:]
    delta = (pose[:3, :3].T @ (pose[:3, 3] - torch.as_tensor(other_centre).to(torch.float64))).float()
    inv = torch.linalg.inv(torch.as_tensor(K).to(torch.float64)).float()
    u = torch.arange(w, dtype=torch.float32) + 0.5
    v = torch.arange(h, dtype=torch.float32) + 0.5
    r = [inv[i, 0] * u[None, :] + inv[i, 1] * v[:, None] + inv[i, 2] for i in range(3)]
    cross = torch.sqrt((r[1] * delta[2] - r[2] * delta[1]) ** 2 + (r[2] * delta[0] - r[0] * delta[2]) ** 2
                       + (r[0] * delta[1] - r[1] * delta[0]) ** 2)
    known = known_depth_mask(depth)[0]
    z = torch.where(known, depth[0].float(), 0.0)
    dot = z * (r[0] * r[0] + r[1] * r[1] + r[2] * r[2]) + (r[0] * delta[0] + r[1] * delta[1] + r[2] * delta[2])
    # atan2 of the sine and cosine (not acos of the cosine): exact at 0 and stable near it
    return torch.where(known, torch.rad2deg(torch.atan2(cross, dot)), 0.0)[None]


def settling(changes: list[int], t: int, frames: int) -> bool:
    """Whether frame ``t`` takes :attr:`TemporalConfig.change_weight`: a frame in ``changes`` (the
    frames whose neighbour set differs from the frame before's) is among the ``frames`` frames
    up to and including ``t``."""
    return any(t - frames < c <= t for c in changes)


def sticky_neighbours(previous: list[int] | None, chosen: list[int], nearest: list[int]) -> list[int]:
    """A frame's neighbours along a path: of the ``previous`` frame's, those still in
    ``nearest`` (this frame's nearest training views), in their order; then the rule's
    ``chosen`` ones not kept, up to as many as the rule chose."""
    if not previous:
        return list(chosen)
    pool = set(nearest)
    kept = [i for i in previous if i in pool][: len(chosen)]
    return kept + [i for i in chosen if i not in kept][: len(chosen) - len(kept)]


class _LastFrame(NamedTuple):
    """What :class:`TemporalFilter` keeps of the last frame."""

    carried: Tensor
    """``(3, H, W)``: the frame as written (``blend="image"``) or its change over the render."""
    depth: Tensor
    K: Tensor
    pose: Tensor
    """Camera-to-world, float64."""
    render: Tensor
    """The render it was made from (compared with the next frame's by ``reject``)."""
    parallax: Tensor | None = None
    """``(1, H, W)``: the mean parallax (degrees) of what the frame carries from the frames before
    it (:attr:`TemporalConfig.fade_along`); None: nothing carried, or not kept."""


class _Move(NamedTuple):
    """A kept frame's reprojection into another (:meth:`TemporalFilter._move`)."""

    frame: Tensor
    """``(3, H, W)``: the kept frame (its :attr:`_LastFrame.carried`), to be sampled."""
    coords: Tensor
    """``(1, H, W, 2)``: where each pixel's point lands in it."""
    valid: Tensor
    """``(1, H, W)`` bool: seen."""
    render: Tensor | None
    """``(3, H, W)``: its render moved (bilinear), where asked for; else None."""
    bilinear: Tensor | None
    """``(3, H, W)``: the frame moved bilinear by the reprojection itself (``resample="bilinear"``); else None."""
    parallax: Tensor | None = None
    """``(1, H, W)``: the kept frame's :attr:`_LastFrame.parallax` moved (bilinear), where it has one
    and :attr:`TemporalConfig.fade_along` is on; else None."""


class TemporalFilter:
    """The last frame's result carried along one camera path (see the module docstring); one per
    path, frames given in order."""

    def __init__(self, config: TemporalConfig | None = None):
        self.config = config or TemporalConfig()
        self._previous: _LastFrame | None = None
        self._anchor: _LastFrame | None = None
        """The last frame the model ran on (:attr:`TemporalConfig.carry_from` ``"model"``)."""
        self._sources: dict[tuple[int, bool], tuple[_LastFrame, Tensor, Tensor]] = {}
        """What the reprojection samples from the last two kept frames moved (the channels moved and
        their ``sampling_source``: 10 floats a pixel each, 14 with ``resample="bilinear"``),
        by the frame's ``id`` (the frame kept beside it: an id is reused only once it is freed)."""
        self.last_share: float = 0.0
        """Share of the last frame's pixels that took the previous frame's residual."""
        self.last_agreement: float | None = None
        """PSNR (dB) of the render of the frame the last :meth:`carry` moved, moved into that
        frame, against its own render, on the pixels seen (:attr:`TemporalConfig.carry_agreement`);
        None where it was not measured, and again after :meth:`__call__`, :meth:`remember` and
        :meth:`reset`."""
        self.last_change: float | None = None
        """PSNR (dB) of the model frame(s) the last :meth:`carry` moved against their renders: the size
        of the enhancer's change there (with ``between`` the two mean squares mixed by position;
        :attr:`TemporalConfig.carry_share`); None where it was not measured."""
        self.last_nearer: float | None = None
        """How many times as far from the frame the last :meth:`carry` moved are the model frame(s)
        it moved from as its nearest training photo (:attr:`TemporalConfig.carry_nearer`); None
        where it was not measured."""
        self.last_mutual: float | None = None
        """PSNR (dB) of the two model frames the last :meth:`carry` between them moved, against each
        other on the pixels both see (:attr:`TemporalConfig.between_agreement`); None where it was
        not measured."""
        self.last_parallax: Tensor | None = None
        """With :attr:`TemporalConfig.fade_along`: ``(1, H, W)`` the mean parallax (degrees) of what
        the last frame given to :meth:`__call__` carries from the frames before it, for the caller
        to hand back to :meth:`remember` with that frame as written; None otherwise."""
        self.last_warp: tuple[Tensor, Tensor] | None = None
        """``(coords, valid)`` of the reprojection that moved the kept frame into the last one
        given to :meth:`__call__` or :meth:`carry` (``(1, H, W, 2)``, ``(1, 1, H, W)``:
        :class:`~roguenerf.reprojection.Reprojection`), for a caller that measures the same
        pair (:func:`~roguenerf.trajectory.pair_flicker`'s ``warp``); None where no frame was
        moved, and again after :meth:`remember` and :meth:`reset`."""

    def reset(self) -> None:
        """Forget the previous frame (a new path, or a frame not enhanced here)."""
        self._previous = None
        self._anchor = None
        self._sources.clear()
        self.last_share = 0.0
        self.last_agreement = None
        self.last_change = None
        self.last_nearer = None
        self.last_mutual = None
        self.last_warp = None
        self.last_parallax = None

    @property
    def kept(self) -> _LastFrame | None:
        """What is kept of the last frame (its result, depth, camera and render), for
        :meth:`carry`'s ``between``; None before the first frame."""
        return self._previous

    def restore(self, kept: _LastFrame | None) -> None:
        """Make ``kept`` (an earlier :attr:`kept`) the last frame again, and the last model frame."""
        self._previous = self._anchor = kept

    def remember(self, render: Tensor, enhanced: Tensor, depth: Tensor, K: Tensor, world_from_cam: Tensor, *,
                 model: bool = True, parallax: Tensor | None = None,
                 blended: tuple[bool, int] | None = None) -> None:
        """Take ``enhanced`` (of ``render``) as the last frame's result without blending: the frame
        as written (a resumed path reads its finished frames back, so the frames after them
        come out the same as without the stop). ``model``: the model ran on it (not carried),
        so later frames may be carried from it (:attr:`TemporalConfig.carry_from`).

        With :attr:`TemporalConfig.fade_along`, what the frame carries from before: ``parallax``,
        the :attr:`last_parallax` of the call that made it; or, for a frame read back that a call
        made (``blended``: that call's ``(changed, frames_apart)``), worked out again from the
        frame remembered before it (the weights depend on the renders, depths and cameras only, not
        on the images: the same map); else nothing (a carried frame)."""
        render, depth = render.float(), depth.float()
        K, pose = torch.as_tensor(K).to(torch.float32), torch.as_tensor(world_from_cam).to(torch.float64)
        carried = enhanced.float() - render if self.config.blend == "residual" else enhanced.float()
        along = self._along
        if along and parallax is None and blended is not None:
            parallax = self._carried_parallax(render, depth, K, pose, *blended)
        self.last_warp = None
        self.last_agreement = None
        self.last_change = None
        self.last_nearer = None
        self.last_mutual = None
        self.last_parallax = None
        self._previous = _LastFrame(carried, depth, K, pose, render, parallax if along else None)
        if model:
            self._anchor = self._previous

    def _move(self, depth: Tensor, K: Tensor, pose: Tensor, frame: _LastFrame | None = None, *,
              with_render: bool = False) -> _Move:
        """The reprojection of the kept last frame (or ``frame``) into this one, its render moved
        (where needed) but not yet the frame itself (:meth:`_moved_frame`): a carry the renders
        refuse skips that sampling."""
        from roguenerf.reprojection import reproject, sampling_source

        frame = self._previous if frame is None else frame
        last = frame is self._previous
        prev, prev_depth, prev_K, prev_pose, prev_render = frame.carried, frame.depth, frame.K, frame.pose, frame.render
        bilinear = self.config.resample == "bilinear"
        reject = self.config.reject > 0 or with_render
        along = self.config.fade_along and frame.parallax is not None
        with torch.inference_mode():
            # a kept frame is moved into several (the frames between two model frames, the blend):
            # what the reprojection samples from it is built once
            key = (id(frame), reject)  # whether its map is moved too is the frame's own
            cached = self._sources.get(key)
            if cached is None or cached[0] is not frame:
                # bicubic: only the points and what sees is needed of the reprojection (the depth:
                # one channel sampled, not three), and the render where it is compared
                source = prev if bilinear else prev_depth
                parts = [source, frame.parallax] if along else [source]
                features = torch.cat(parts + [prev_render] if reject else parts)[None]
                cached = (frame, features, sampling_source(features, prev_depth[None]))
                self._sources[key] = cached
                while len(self._sources) > 2:  # the two model frames a stretch is carried from
                    self._sources.pop(next(iter(self._sources)))
            _, features, source = cached
            warped = reproject(features, prev_depth[None], depth[None], prev_K, K, prev_pose, pose, source=source)
        self.last_warp = (warped.coords, warped.valid) if last else None
        features = warped.features[0]
        return _Move(prev, warped.coords, warped.valid[0] > 0.5, features[-3:] if reject else None,
                     features[:3] if bilinear else None,
                     features[len(source):len(source) + 1] if along else None)

    def _moved_frame(self, move: _Move) -> Tensor:
        """``(3, H, W)``: the frame of a :meth:`_move`, sampled where its points land (0 where not seen)."""
        if move.bilinear is not None:
            return move.bilinear
        from roguenerf.reprojection import sample_at

        with torch.inference_mode():
            # at the last frame's pixels; channels-last: the same values, 10-15 % faster on the CPU
            sampled = sample_at(move.frame[None].contiguous(memory_format=torch.channels_last), move.coords,
                                mode="bicubic")[0]
            return torch.where(move.valid, sampled, 0.0)

    def _agreement(self, warped_render: Tensor, render: Tensor, valid: Tensor) -> Tensor:
        """``0.5 ** (d / reject) ** 2`` of the renders' disagreement ``d`` (:attr:`TemporalConfig.reject`)."""
        d = render_disagreement(warped_render, render, valid)
        return torch.exp2(-(d / self.config.reject).square())

    def _weight0(self, changed: bool, frames_apart: int) -> float:
        """The blend's weight before the fade and the rejection."""
        return float(self.config.change_weight if changed else self.config.weight) ** frames_apart

    def _weights(self, move: _Move, render: Tensor, depth: Tensor, K: Tensor, pose: Tensor, changed: bool,
                 frames_apart: int) -> tuple[Tensor | float, Tensor | None]:
        """The blend's weight per pixel of the kept last frame moved into this one (``move``), and
        the parallax it faded by (None without :attr:`TemporalConfig.fade_deg`): the angle to the
        last frame, plus what that frame carried (:attr:`TemporalConfig.fade_along`)."""
        w = self._weight0(changed, frames_apart)
        angle = None
        if self.config.fade_deg > 0:
            angle = parallax_deg(depth, K, pose, self._previous.pose[:3, 3])
            if move.parallax is not None:  # what the last frame carried, seen from further back
                angle = angle + torch.where(move.valid, move.parallax, 0.0)
            w = w * 0.5 ** (angle / self.config.fade_deg)
        if move.render is not None:
            w = w * self._agreement(move.render, render, move.valid)
        return w, angle

    @property
    def _along(self) -> bool:
        """Whether blended frames keep the map of what they carry (:attr:`TemporalConfig.fade_along`)."""
        return self.config.fade_along and self.config.fade_deg > 0

    @staticmethod
    def _parallax_after(w: Tensor | float, angle: Tensor, valid: Tensor) -> Tensor:
        """``(1, H, W)``: the mean parallax of what a frame carries once blended (its own: 0), kept
        at float16's precision (a frame's map is the same whether it is made or worked out again)."""
        return torch.where(valid, w * angle, 0.0).half().float()

    def _carried_parallax(self, render: Tensor, depth: Tensor, K: Tensor, pose: Tensor, changed: bool,
                          frames_apart: int) -> Tensor:
        """:attr:`last_parallax` of a :meth:`__call__` on this frame after the frame kept now,
        without its images (:meth:`remember` of a frame read back)."""
        zeros = torch.zeros(1, *render.shape[1:])
        if self._previous is None or self._weight0(changed, frames_apart) <= 0:
            return zeros
        move = self._move(depth, K, pose)
        w, angle = self._weights(move, render, depth, K, pose, changed, frames_apart)
        return self._parallax_after(w, angle, move.valid)

    def _change_power(self, frame: _LastFrame) -> float:
        """Mean square of a kept frame's change over its render (:attr:`TemporalConfig.carry_share`)."""
        change = frame.carried - frame.render if self.config.blend == "image" else frame.carried
        return float(change.square().mean())

    def model_due(self, t: int, *, changed: bool = False) -> bool:
        """Whether frame ``t`` of the path (from 0) is one the model runs on by
        :attr:`TemporalConfig.model_every` (before :meth:`carry` is tried)."""
        return self._previous is None or changed or t % self.config.model_every == 0

    def carry(self, render: Tensor, depth: Tensor, K: Tensor, world_from_cam: Tensor, *,
              between: tuple[_LastFrame, _LastFrame, float] | None = None,
              photo_distance: float | None = None) -> Tensor | None:
        """The previous frame's result (or the last model frame's: :attr:`TemporalConfig.carry_from`)
        reprojected into this frame (``render`` ``(3, H, W)``, its z-depth ``(1, H, W)``, ``K``,
        camera-to-world ``(4, 4)``), the render where that frame does not see; kept as the last
        frame's result. None (nothing kept) where there is no previous frame or it sees less than
        :attr:`TemporalConfig.min_seen` of this one: the model must run on it.

        ``between`` ``(before, after, position)``: two model frames' :attr:`kept` states instead,
        both moved into this frame and mixed, ``after`` weighing ``position`` (in (0, 1): how far
        along from ``before`` this frame is) and ``before`` the rest, each only where it sees
        (:attr:`TemporalConfig.carry_between`); ``min_seen``, ``carry_agreement`` and ``carry_share``
        judge the mix, and ``between_agreement`` (where set) the two against each other.

        ``photo_distance``: how far this frame's camera centre is from the nearest training
        photo's, for :attr:`TemporalConfig.carry_nearer` (judged first, from the poses alone; no
        test where None)."""
        self.last_share = 0.0
        self.last_agreement = None
        self.last_change = None
        self.last_nearer = None
        self.last_mutual = None
        self.last_warp = None
        if self._previous is None and between is None:
            return None
        if between is not None and not 0 < between[2] < 1:
            raise InputError(f"carry: expected a position between the two frames in (0, 1), got {between[2]!r}")
        render, depth = render.float(), depth.float()
        pose = torch.as_tensor(world_from_cam).to(torch.float64)
        K = torch.as_tensor(K).to(torch.float32)
        # the kept frame(s) moved into this one, each with its share of the mix
        if between is None:
            model = self.config.carry_from == "model" and self._anchor is not None
            sources = [(self._anchor if model else self._previous, 1.0)]
        else:
            sources = [(between[0], 1.0 - between[2]), (between[1], between[2])]
        if self.config.carry_nearer > 0 and photo_distance is not None:
            # the poses alone decide, before anything is moved
            far = sum(part * float((frame.pose[:3, 3] - pose[:3, 3]).norm()) for frame, part in sources)
            self.last_nearer = far / photo_distance if photo_distance > 0 else (0.0 if far == 0 else math.inf)
            if far > self.config.carry_nearer * photo_distance:
                return None
        share_gate = self.config.carry_share > 0
        gate = self.config.carry_agreement > 0 or share_gate
        # The frames themselves are sampled (bicubic: half a move's cost) only once the renders
        # have let the carry through.
        if between is None:
            move = self._move(depth, K, pose, sources[0][0], with_render=gate)
            valid, warped_render = move.valid, move.render
        else:
            before, after, position = between
            moves = [self._move(depth, K, pose, frame, with_render=gate) for frame in (before, after)]
            self.last_warp = None  # two moves, neither the last frame's
            weights = [(1.0 - position) * moves[0].valid.float(), position * moves[1].valid.float()]
            total = weights[0] + weights[1]
            valid = total > 0
            share = [w / total.clamp_min(1e-12) for w in weights]
            warped_render = None if moves[0].render is None else share[0] * moves[0].render + share[1] * moves[1].render
        self.last_share = float(valid.float().mean())
        if self.last_share < self.config.min_seen:
            return None
        if gate:
            # nothing seen (min_seen 0): nothing moved that could disagree, as before
            self.last_agreement = _masked_psnr(warped_render, render, valid, none_seen=120.0)
            if self.last_agreement < self.config.carry_agreement:
                return None
        if share_gate:
            change = sum(part * self._change_power(frame) for frame, part in sources)
            self.last_change = -10.0 * math.log10(max(change, 1e-12))
            miss = 10.0 ** (-self.last_agreement / 10.0)
            if miss > self.config.carry_share * change:
                return None
        if between is None:
            warped = self._moved_frame(move)
        else:
            moved = [self._moved_frame(m) for m in moves]
            warped = share[0] * moved[0] + share[1] * moved[1]
        if between is not None and self.config.between_agreement > 0:
            # the two model frames' results, moved, against each other where both see
            self.last_mutual = _masked_psnr(moved[0], moved[1], moves[0].valid & moves[1].valid)
            if self.last_mutual < self.config.between_agreement:
                return None
        keep = 1.0
        if self.config.reject > 0:  # where the renders disagree, the render rather than the last result
            keep = self._agreement(warped_render, render, valid)
        carried = render + keep * (warped - render) if self.config.blend == "image" else render + keep * warped
        out = torch.where(valid, carried, render).clamp(0, 1)
        self._previous = _LastFrame(out if self.config.blend == "image" else out - render, depth, K, pose, render)
        return out

    def __call__(self, render: Tensor, enhanced: Tensor, depth: Tensor, K: Tensor, world_from_cam: Tensor, *,
                 changed: bool = False, frames_apart: int = 1) -> Tensor:
        """The frame ``enhanced`` (of ``render``, ``(3, H, W)``, its z-depth ``(1, H, W)``, ``K``,
        camera-to-world ``(4, 4)``) with the previous frame's residual blended in (with
        ``change_weight`` where ``changed``: its neighbours differ from the last frame's); the
        frame's blended residual is kept for the next.

        ``frames_apart``: how many frames of the path the last frame kept lies before this one
        (:attr:`TemporalConfig.carry_between`'s model frames: ``model_every``). Its weight is then
        ``weight ** frames_apart``, the share a moving average along every frame between would
        leave it; the frames between, carried from the two, add nothing of their own, so the rest
        is this frame's. (With ``weight`` itself over 4 frames, 0.8 instead of 0.41 when 0.8 was the
        default, the model frames of ``can_clip``'s and ``ollie``'s 154-frame paths kept 0.2-0.7 dB
        less on their frames with photos.)"""
        if isinstance(frames_apart, bool) or not isinstance(frames_apart, int) or frames_apart < 1:
            raise InputError(f"frames_apart: expected an integer >= 1, got {frames_apart!r}")
        if render.shape != enhanced.shape or render.ndim != 3 or render.shape[0] != 3:
            raise InputError(f"render, enhanced: expected the same (3, H, W) shape, got {tuple(render.shape)} "
                             f"and {tuple(enhanced.shape)}")
        if depth.shape != (1, *render.shape[1:]):
            raise InputError(f"depth: expected (1, {render.shape[1]}, {render.shape[2]}), got {tuple(depth.shape)}")
        render, enhanced, depth = render.float(), enhanced.float(), depth.float()
        pose = torch.as_tensor(world_from_cam).to(torch.float64)
        K = torch.as_tensor(K).to(torch.float32)
        image = self.config.blend == "image"
        residual = enhanced if image else enhanced - render
        self.last_share = 0.0
        self.last_agreement = None
        self.last_change = None
        self.last_nearer = None
        self.last_mutual = None
        self.last_warp = None
        self.last_parallax = None
        along = self._along
        if along:
            self.last_parallax = torch.zeros(1, *render.shape[1:])
        if self._previous is not None and self._weight0(changed, frames_apart) > 0:
            move = self._move(depth, K, pose)
            w, angle = self._weights(move, render, depth, K, pose, changed, frames_apart)
            warped, valid = self._moved_frame(move), move.valid
            self.last_share = float(valid.float().mean())
            residual = torch.where(valid, (1 - w) * residual + w * warped, residual)
            if along:
                self.last_parallax = self._parallax_after(w, angle, valid)
        out = (residual if image else render + residual).clamp(0, 1)
        self._previous = self._anchor = _LastFrame(out if image else out - render, depth, K, pose, render,
                                                   self.last_parallax)
        return out
