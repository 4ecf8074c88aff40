"""The stages after the model: each a frozen config plus ``apply``, run in order on one view.

A stage reads and updates a :class:`ViewState` (the enhanced image, the render it came from,
the neighbours reprojected into the view's small copy and where two or more of them agree) and
returns a :class:`StageRecord` of what it did; :class:`~roguenerf.inference.EnhanceResult` keeps
the records. A new stage is a :class:`ConfiguredStage` with ``name`` and ``apply`` added to
:func:`stages_for` (CONTRIBUTING.md, *Adding a stage*).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import ClassVar, Generic, Protocol, TypeVar

import torch
from torch import Tensor

from roguenerf.enhance.colour import ColourConfig, apply_match, colour_match
from roguenerf.enhance.trust import TrustConfig, kept_change, share_kept


@dataclass
class ViewState:
    """One view between the stages (CPU tensors)."""

    image: Tensor
    """``(3, H, W)`` the enhanced view so far, float32 in [0, 1]."""
    render: Tensor
    """``(3, H, W)`` the field's render it started from."""
    seen: list[tuple[Tensor, Tensor]]
    """Each neighbour reprojected into the view's small copy, ``(colour, valid)``."""
    small_image: Tensor
    """``(3, h, w)`` the model's output at the small copy's size (before any stage)."""
    agreement: Tensor
    """``(1, 1, h, w)`` bool: where two or more neighbours agree (the test of :func:`agreement_test`)."""
    test: tuple[float, float]
    """``(sigma, max_disagreement)`` that ``agreement`` was measured with."""
    note: str | None = None

    @property
    def share(self) -> float:
        return float(self.agreement[0].float().mean())


@dataclass
class StageRecord:
    name: str
    applied: bool
    """Whether the stage changed the image."""
    detail: dict = field(default_factory=dict)


class Stage(Protocol):
    name: str

    def apply(self, state: ViewState) -> StageRecord: ...


C = TypeVar("C")


@dataclass(frozen=True)
class ConfiguredStage(Generic[C]):
    """A stage run with its frozen config; ``name``: the subclass's key in the records and in
    :func:`agreement_test`."""

    config: C
    name: ClassVar[str]


class ColourStage(ConfiguredStage[ColourConfig]):
    """Match the view's low-frequency colour to the agreeing neighbours'
    (:func:`~roguenerf.enhance.colour.colour_match`)."""

    name = "colour"

    def apply(self, state: ViewState) -> StageRecord:
        same = (self.config.sigma, self.config.max_disagreement) == state.test
        match = colour_match(state.small_image[None], state.seen, self.config,
                             agreement=state.agreement if same else None)
        if match is None:
            return StageRecord(self.name, False)
        state.image = apply_match(state.image, match)
        return StageRecord(self.name, True, {"offset": [round(float(x), 6) for x in match.offset]})


class TrustStage(ConfiguredStage[TrustConfig]):
    """Keep only part of the model's change where the neighbours mostly disagree
    (:func:`~roguenerf.enhance.trust.kept_change`)."""

    name = "trust"

    def apply(self, state: ViewState) -> StageRecord:
        keep = kept_change(state.agreement[0], state.image.shape[-2:], self.config)
        factor = share_kept(keep)
        if factor < 1:
            base = state.render.to("cpu", torch.float32).clamp(0, 1)
            state.image = (base + keep * (state.image - base)).clamp(0, 1)
            if state.note is None:
                where = "" if isinstance(keep, float) else ", where they agree"
                state.note = (f"the neighbours agree on {state.share:.0%} of this view (its geometry is off): "
                              f"{factor:.0%} of the enhancer's change kept{where}")
        return StageRecord(self.name, factor < 1, {"kept": round(factor, 4)})


def stages_for(options) -> list[Stage]:
    """The stages an :class:`~roguenerf.enhance.options.EnhanceOptions` turns on, in order."""
    out: list[Stage] = []
    if options.colour is not None:
        out.append(ColourStage(options.colour))
    if options.trust is not None:
        out.append(TrustStage(options.trust))
    return out


def agreement_test(stages: list[Stage]) -> tuple[float, float] | None:
    """``(sigma, max_disagreement)`` of the neighbour agreement the stages read: trust's where
    it is on, else colour's (one measurement serves both by default); None without stages."""
    configs = {s.name: s.config for s in stages}
    test = configs.get("trust") or configs.get("colour")
    return None if test is None else (test.sigma, test.max_disagreement)
