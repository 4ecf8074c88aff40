"""The first stage of the pipeline: which training photos a view takes as neighbours, measured.

The paper ranks training views by camera position and angle. What decides whether a neighbour
helps is how well its photo lands on the view when it is reprojected through the render's depth
(issue 48: the nearest photo's reprojection scores 0.3 dB below the render on a scene that gains
+1.4 dB, 3.4 dB below on one that gains +0.6). :func:`measure_candidates` measures that for each
candidate at request time, on small copies (:data:`SELECT_SIDE`), with no photo of the view:

- ``coverage``: the share of the view's known-depth pixels the candidate sees (reprojection
  valid, visibility test passed);
- ``error``: the mean |reprojected photo - render| over those pixels (RGB mean, on the small
  copies, so at low frequency: the render is blurry, its colour and layout are not);
- ``consensus``: the share of those pixels where another candidate sees the same point and its
  reprojected photo agrees (mean RGB difference under :data:`AGREE`): where photos of two other
  cameras agree, the depth put them in the right place;
- ``angle`` (degrees) and ``baseline`` (camera distance over the view's median depth).

:class:`~roguenerf.enhance.options.NeighbourRule` uses these to choose which candidates and how
many (``measured=True``).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

SELECT_SIDE = 128
"""The measurement's copies (view and candidate photos) are no larger than this (long side)."""

AGREE = 0.06
"""Two reprojected photos agree at a pixel where their colours differ by less than this (mean
over RGB, photos in [0, 1], on the small copies)."""


@dataclass(frozen=True)
class Candidate:
    """What the enhancer measured of one candidate neighbour for one view."""

    position: int
    """Position in the enhancer's training list."""
    rank: int
    """Its place in the paper's ranking (0: nearest)."""
    angle: float
    """Degrees between its rotation and the view's."""
    baseline: float
    """Distance between the cameras over the view's median rendered depth."""
    coverage: float
    """Share of the view's known-depth pixels it sees."""
    error: float
    """Mean |reprojected photo - render| where it sees (RGB mean; 1.0 where it sees nothing)."""
    consensus: float
    """Share of the pixels it sees where another candidate sees and agrees (0 where it sees
    nothing or no other candidate is measured)."""

    def as_dict(self) -> dict:
        return {"rank": self.rank, "angle": round(self.angle, 3), "baseline": round(self.baseline, 4),
                "coverage": round(self.coverage, 4), "error": round(self.error, 5),
                "consensus": round(self.consensus, 4)}


def measure_candidates(render: Tensor, depth: Tensor, K: Tensor, world_from_cam: Tensor,
                       neighbours: list[tuple[Tensor, Tensor, Tensor, Tensor]], *, positions: list[int] | None = None,
                       leniency: float = 0.25) -> list[Candidate]:
    """Measure each candidate neighbour of one view (see the module docstring).

    Args:
        render: ``(3, H, W)`` the view's render; ``depth`` ``(1, H, W)`` its z-depth; ``K``
            ``(3, 3)``; ``world_from_cam`` ``(4, 4)`` OpenCV camera-to-world.
        neighbours: per candidate, in the paper's ranking: its photo ``(3, h, w)``, depth
            ``(1, h, w)``, K ``(3, 3)`` and camera-to-world ``(4, 4)``; any size (each is
            shrunk to :data:`SELECT_SIDE`).
        positions: the candidates' positions in the training list (default ``0..N-1``).
    Returns:
        one :class:`Candidate` per neighbour, in the given order.
    """
    from roguenerf.enhance.align import shrink
    from roguenerf.geometry import rotation_angle
    from roguenerf.geometry.depth import known_depth_mask
    from roguenerf.reprojection import reproject

    positions = list(range(len(neighbours))) if positions is None else list(positions)
    small, small_depth, small_K = shrink(render, depth, K, SELECT_SIDE)
    pose = torch.as_tensor(world_from_cam).to(torch.float64)
    known = known_depth_mask(small_depth)[0]
    z = small_depth[0][known]
    scale = float(z.median()) if z.numel() else 1.0
    warped, valid = [], []
    with torch.inference_mode():
        for photo, photo_depth, photo_K, photo_pose in neighbours:
            p, d, k = shrink(photo, photo_depth, photo_K, SELECT_SIDE)
            r = reproject(p[None], d[None], small_depth[None], k.float(), small_K.float(),
                          torch.as_tensor(photo_pose).to(torch.float64), pose, leniency=leniency)
            warped.append(r.features[0])
            valid.append(r.valid[0, 0] > 0.5)
    total = max(1, int(known.sum()))
    out = []
    for j, (w, v) in enumerate(zip(warped, valid, strict=True)):
        seen = int(v.sum())
        error = float((w - small).abs().mean(0)[v].mean()) if seen else 1.0
        agree = torch.zeros_like(v)
        for k, (w2, v2) in enumerate(zip(warped, valid, strict=True)):
            if k != j:
                agree |= v2 & ((w - w2).abs().mean(0) < AGREE)
        consensus = float((agree & v).sum()) / seen if seen else 0.0
        photo_pose = torch.as_tensor(neighbours[j][3]).to(torch.float64)
        angle = float(rotation_angle(pose[:3, :3], photo_pose[:3, :3]))
        baseline = float((photo_pose[:3, 3] - pose[:3, 3]).norm()) / max(scale, 1e-12)
        out.append(Candidate(position=positions[j], rank=j, angle=angle, baseline=baseline,
                             coverage=seen / total, error=error, consensus=consensus))
    return out


def choose(candidates: list[Candidate], *, least: int, most: int, min_coverage: float,
           error_ratio: float, near_degrees: float = 0.0) -> list[Candidate]:
    """The measured rule (:class:`~roguenerf.enhance.options.NeighbourRule` with
    ``measured=True``): of ``candidates`` (in the paper's ranking), those that see at least
    ``min_coverage`` of the view keep their order; the first ``least`` of them are taken, then
    each next one while its error is at most ``error_ratio`` times the best error taken so far
    or its rotation is within ``near_degrees`` of the view's, up to ``most``. Where fewer than
    ``least`` see enough, the best-covering ones fill in."""
    usable = [c for c in candidates if c.coverage >= min_coverage]
    if len(usable) < least:
        rest = sorted((c for c in candidates if c not in usable), key=lambda c: -c.coverage)
        usable = sorted(usable + rest[: least - len(usable)], key=lambda c: c.rank)
    chosen = usable[:least]
    if not chosen:
        return []
    best = min(c.error for c in chosen)
    for c in usable[least:most]:
        if c.error > best * error_ratio and c.angle > near_degrees:
            break
        chosen.append(c)
        best = min(best, c.error)
    return chosen
