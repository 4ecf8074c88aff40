"""Keep a fine-tune only where it helps views that look like novel ones.

A radiance field renders its training views better than any novel view, and a fine-tune learns
from its training views: where the gap is wide (a field that overfits, floaters in its novel
views), ten minutes teach the model to change little, or the wrong thing, and the novel views a
user enhances end worse than with the starting weights (`ollie`'s hash field: +0.52 dB zero-shot,
+0.33 after 10 minutes; docs/broad.md).

:func:`judge` measures both weights on the same few training views, each with the render and
depth its nearest other training view draws into its camera
(:meth:`~roguenerf.training.loop.SceneData.drawn_view`: that view's geometry errors and floaters
seen from a new camera, as a novel view has them), its own photo kept out of its neighbours: the
PSNR gain of the whole enhancement (:class:`~roguenerf.inference.SceneEnhancer`, default options)
over the drawn render. The fine-tuned weights are kept only where their mean gain is higher.
``TrainConfig.guard``, off by default (docs/broad.md, *A fine-tune kept only where it helps*): on
the broad figure's fine-tunes the sign of the difference on drawn views was the sign on the
held-out views, where the training views' own renders missed `ollie` / hash's loss; but lego's
drawn views (3.5 dB worse than its novel views) refused a 10-minute fine-tune that gains 0.57 dB
on its held-out views.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field

GUARD_VIEWS = 8
"""Training views the fine-tune is judged on (spread over the scene's order; all where fewer)."""


@dataclass
class GuardReport:
    """What :func:`judge` measured and decided."""

    views: list[str] = field(default_factory=list)
    """The training views judged on."""
    start_db: list[float] = field(default_factory=list)
    """Per view, the starting weights' PSNR gain over the drawn render (dB)."""
    tuned_db: list[float] = field(default_factory=list)
    """The same with the fine-tuned weights."""
    drawn_share: float = 0.0
    """Mean share of the views' pixels drawn from their nearest training view (the rest: their own render)."""
    kept: bool = True
    """Whether the fine-tuned weights are kept (True where no view could be judged)."""
    seconds: float = 0.0

    @property
    def start_mean(self) -> float | None:
        return sum(self.start_db) / len(self.start_db) if self.start_db else None

    @property
    def tuned_mean(self) -> float | None:
        return sum(self.tuned_db) / len(self.tuned_db) if self.tuned_db else None

    def to_dict(self) -> dict:
        return {**asdict(self), "start_mean_db": self.start_mean, "tuned_mean_db": self.tuned_mean}


def guard_positions(data, count: int = GUARD_VIEWS) -> list[int]:
    """Positions into ``data.train`` of up to ``count`` training views spread evenly over the
    scene's order; none where there are fewer than two training views (nothing to draw from)."""
    m = len(data.train)
    if m < 2 or count <= 0:
        return []
    step = max(1, m // count)
    return list(range(0, m, step))[:count]


def drawn_view_gains(data, model, positions: list[int], drawn: list[tuple], *, device="cpu") -> list[float]:
    """Per training position, the PSNR gain (dB) of ``model``'s enhancement of the ``drawn``
    render and depth over that render, against the view's photo (its photo never a neighbour)."""
    from roguenerf.inference import SceneEnhancer
    from roguenerf.metrics import psnr

    enhancer = SceneEnhancer(data.scene, model, device=device)
    gains = []
    for k, (render, depth) in zip(positions, drawn, strict=True):
        i = data.train[k]
        frame = data.scene.frames[i]
        image = enhancer.enhance(render, depth, frame.K, frame.world_from_cam, exclude=i).image
        photo = data.photos[k][None]
        gains.append(float(psnr(image[None], photo)[0] - psnr(render.clamp(0, 1)[None], photo)[0]))
    return gains


def judge(data, start, tuned, *, device="cpu", count: int = GUARD_VIEWS) -> GuardReport:
    """Whether the fine-tuned weights ``tuned`` enhance ``data``'s training views drawn like novel
    views (:meth:`~roguenerf.training.loop.SceneData.drawn_view`) better than the ``start``
    weights, on :func:`guard_positions` of them: :class:`GuardReport` (``kept``: the mean gain is
    higher with ``tuned``)."""
    began = time.perf_counter()
    positions = guard_positions(data, count)
    if not positions:
        return GuardReport(seconds=time.perf_counter() - began)
    drawn, shares = [], []
    for k in positions:
        render, depth, share = data.drawn_view(k)
        drawn.append((render, depth))
        shares.append(share)
    report = GuardReport(views=[data.scene.frames[data.train[k]].name for k in positions],
                         start_db=drawn_view_gains(data, start, positions, drawn, device=device),
                         tuned_db=drawn_view_gains(data, tuned, positions, drawn, device=device),
                         drawn_share=sum(shares) / len(shares))
    report.kept = report.tuned_mean > report.start_mean
    report.seconds = time.perf_counter() - began
    return report
