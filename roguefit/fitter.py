"""What a kind of field provides to make pairs: its configuration and its :class:`Fitter`.

:func:`roguefit.pairs.make_pairs` knows nothing of grids, hash tables or splats: it looks the
configuration's ``kind`` up in :data:`roguefit.registry.FITTERS` and drives the fitter through
this protocol (fit, resume, render every view, report). A new kind of field is one module with
a frozen config dataclass (a :class:`FieldConfig`) and a :class:`Fitter` class, plus one line in
:data:`roguefit.registry.FITTERS` (CONTRIBUTING.md, "Adding a kind of field").
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from pathlib import Path
from typing import Protocol

from torch import Tensor

from roguefit.photos import PhotoSet
from roguenerf.errors import InputError, TrainingCancelled, TrainingDivergedError

Progress = Callable[[dict], None]
"""Called after every step with ``step``, ``fraction`` (of the budget, 0..1), ``psnr`` (a running
mean of the training loss's), and the kind's own size (``resolution`` or ``gaussians``)."""
ShouldStop = Callable[[], bool]


class ConfigCheck:
    """The validation of a kind's configuration fields, in its ``__post_init__`` (so before any
    work, and on ``dataclasses.replace``): :class:`InputError` naming ``Config.field`` and the
    rule, never an error from deep inside torch, nor a NaN budget that fits 0 steps."""

    def __init__(self, config) -> None:
        self.config, self.owner = config, type(config).__name__

    def fail(self, name: str, want: str) -> None:
        raise InputError(f"{self.owner}.{name}: expected {want}, got {getattr(self.config, name)!r}")

    def integer(self, name: str, low: int | None = None, high: int | None = None) -> None:
        """An int (not a bool) within ``[low, high]`` (each bound where given)."""
        value = getattr(self.config, name)
        if isinstance(value, bool) or not isinstance(value, int) or (low is not None and value < low) \
                or (high is not None and value > high):
            rule = (f" in [{low}, {high}]" if low is not None and high is not None
                    else f" >= {low}" if low is not None else "")
            self.fail(name, "an integer" + rule)

    def number(self, name: str, *, positive: bool, optional: bool = False, high: float | None = None) -> None:
        """A finite int or float (not a bool), > 0 (``positive``) or >= 0, at most ``high``;
        None passes where ``optional``."""
        value = getattr(self.config, name)
        if value is None and optional:
            return
        ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
        if not ok or (value <= 0 if positive else value < 0) or (high is not None and value > high):
            want = "a finite number > 0" if positive else "a finite number >= 0"
            self.fail(name, want + (f" and <= {high:g}" if high is not None else ""))

    def budget(self) -> None:
        """``steps`` (an integer >= 1) or ``minutes`` (> 0), at least one of them."""
        if self.config.steps is not None:
            self.integer("steps", 1)
        self.number("minutes", positive=True, optional=True)
        if self.config.minutes is None and self.config.steps is None:
            raise InputError(f"{self.owner}: expected a budget, steps or minutes (both are None)")


class FieldConfig(Protocol):
    """How to fit one field of some kind (a frozen dataclass; validated when made)."""

    @property
    def kind(self) -> str:
        """The key of :data:`roguefit.registry.FITTERS` that fits it."""

    @property
    def steps(self) -> int | None:
        """The budget in steps (wins over ``minutes``; progress bars count it)."""

    @property
    def minutes(self) -> float | None: ...

    @property
    def seed(self) -> int: ...

    @property
    def hold(self) -> int:
        """Every ``hold``-th view of the photo set is held out (:func:`~roguefit.photos.read_photo_set`)."""

    @property
    def folds(self) -> int:
        """Cross-fitting (:func:`roguefit.pairs.make_pairs`): 1 is one field."""

    def identity(self) -> dict:
        """The keys that define the result (not the checkpoint cadence): ``fit.json``'s
        ``config``; a finished output or saved state made with another identity is redone."""


class Fitter(Protocol):
    """One field being fitted to a photo set's training views, resumably.

    Made as ``FitterClass(photo_set, config, state_dir)``: it fits ``photo_set.indices("train")``
    and keeps its resume state in ``state_dir`` (a folder of its own).
    """

    step: int
    """Steps done (the report's ``steps``)."""
    elapsed: float
    """Seconds spent fitting, resumed runs included (the report's ``fit_seconds``)."""

    def load(self) -> bool:
        """Resume from ``state_dir``; False (and a fresh start) when there is no state of this config."""

    def run(self, progress: Progress | None, should_stop: ShouldStop | None) -> None:
        """Fit until the budget is spent, saving the state now and then, on a stop (then raising
        :class:`~roguenerf.errors.TrainingCancelled`) and at the end. A non-finite loss raises
        :class:`~roguenerf.errors.TrainingDivergedError`."""

    def render_view(self, i: int) -> tuple[Tensor, Tensor, Tensor]:
        """View ``i`` of the photo set at the photo size: RGB ``(3, H, W)`` in [0, 1], z-depth
        ``(1, H, W)`` float32 (0 where unknown) and accumulated opacity ``(1, H, W)`` in [0, 1]."""

    def summary(self) -> dict:
        """This kind's own entries of the fit report (``fit.json``) of a one-field fit."""

    def write_extras(self, output: Path) -> None:
        """Files beside the scene folder that only this kind writes (a one-field fit)."""


def fit_steps(fitter, progress: Progress | None, should_stop: ShouldStop | None, *, report: Callable[[], dict],
              after_step: Callable[[], None], checkpoint: Callable[[], None],
              before_step: Callable[[], None] | None = None) -> None:
    """The fitting loop of every kind (:meth:`Fitter.run`): ``fitter.train_step()`` (which returns
    the step's MSE) until ``fitter.fraction()`` of the budget is 1, counting ``fitter.step`` and
    ``fitter.elapsed`` (``after_step`` included: the kind's pruning or densifying), then
    ``fitter.save()`` at the end, on Ctrl-C inside a step (re-raised) and on a stop (raising
    :class:`~roguenerf.errors.TrainingCancelled`). ``before_step`` (growing a grid) runs untimed;
    ``progress`` gets ``step``, ``fraction``, ``psnr`` (a running mean's) and ``report()``;
    ``checkpoint()`` then saves when the kind's cadence says so. A non-finite MSE raises
    :class:`~roguenerf.errors.TrainingDivergedError`."""
    mse_avg = None
    while fitter.fraction() < 1.0:
        if before_step is not None:
            before_step()
        t0 = time.perf_counter()
        try:
            mse = fitter.train_step()
        except KeyboardInterrupt:
            fitter.save()
            raise
        fitter.step += 1
        after_step()
        fitter.elapsed += time.perf_counter() - t0
        if not math.isfinite(mse):  # the configuration was checked: this is real divergence
            raise TrainingDivergedError(fitter.step, mse)
        mse_avg = mse if mse_avg is None else 0.95 * mse_avg + 0.05 * mse
        if progress is not None:
            progress({"step": fitter.step, "fraction": min(fitter.fraction(), 1.0),
                      "psnr": -10 * math.log10(max(mse_avg, 1e-10)), **report()})
        if should_stop is not None and should_stop():
            fitter.save()
            raise TrainingCancelled(f"fit stopped at step {fitter.step}; run again to resume")
        checkpoint()
    fitter.save()


FitterType = Callable[[PhotoSet, FieldConfig, Path], Fitter]
"""A :class:`Fitter` class: what :data:`roguefit.registry.FITTERS` maps a kind to."""
