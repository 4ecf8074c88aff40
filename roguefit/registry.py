"""The kinds of field and the presets: where a new kind of field or a new preset is registered.

:data:`FITTERS` maps a configuration's ``kind`` to the :class:`~roguefit.fitter.Fitter` class
that fits it (:func:`roguefit.pairs.make_pairs` looks it up there, and nowhere else);
:data:`PRESETS` names the configurations that ``make-pairs --preset``, ``python -m roguefit.batch
--presets`` and the benches offer, and :data:`PRESET_NOTES` says what each looks like (the help
strings list them with :func:`describe_presets`).

Imports: this module imports every kind's module; none of them imports it, nor
:mod:`roguefit.pairs` (tests/unit/repo/test_layers.py checks roguefit for import circles).
"""

from __future__ import annotations

from roguefit.fit import FitConfig, GridFitter
from roguefit.fitter import FieldConfig, FitterType
from roguefit.hashfield import HashFitter
from roguefit.splats import SplatConfig, SplatFitter
from roguenerf.errors import InputError

FITTERS: dict[str, FitterType] = {
    "grid": GridFitter,  # FitConfig(): dense grids, roguefit/fit.py + field.py
    "hash": HashFitter,  # FitConfig(kind="hash"): Instant-NGP's hash encoding, roguefit/hashfield.py
    "splat": SplatFitter,  # SplatConfig(): 3D Gaussian splats, roguefit/splats.py
}
"""Each kind of field's fitter, keyed by the configurations' ``kind``."""

# Looks per scene for pre-training, from blurriest to sharpest: a short fit on a 64³ RGB grid
# (rendered at half size: its voxels span several pixels, so that costs a quarter of the rays and
# changes little), a 96³ RGB grid, and a view-dependent 160³ field with a longer budget. Budgets
# are in steps, so the pairs do not depend on how busy the machine was (--minutes overrides).
PRESETS: dict[str, FieldConfig] = {
    "blur": FitConfig(resolution=64, features=0, minutes=None, steps=250, samples=64, render_scale=2),
    "coarse": FitConfig(resolution=96, features=0, minutes=None, steps=500, samples=64),
    "fine": FitConfig(resolution=160, features=6, minutes=None, steps=1500, samples=80),
    # 3D Gaussian splats (roguefit.splats), fitted at half the photo size: another kind of field.
    "splat": SplatConfig(),
    # Another kind of field (issue 35): Instant-NGP's hash encoding, finest level 512 over the
    # contracted cube, SH-degree-3 view dependence; its own learning rates (Instant-NGP: 1e-2).
    "hash": FitConfig(kind="hash", resolution=512, features=0, minutes=None, steps=1500, samples=64,
                      lr_grid=1e-2, lr_mlp=1e-2, tv_weight=0.0, grow_at=(), prune_every=100),
}
"""The named configurations, in the order the help strings list them."""

PRESET_NOTES: dict[str, str] = {
    "blur": "64³ RGB grid, half-size render",
    "coarse": "96³ RGB grid",
    "fine": "160³, view-dependent",
    "splat": "3D Gaussian splats",
    "hash": "Instant-NGP hash grid, SH colour",
}
"""What each preset's renders look like, for the help strings (one entry per preset)."""


def fitter_type(config: FieldConfig) -> FitterType:
    """The fitter class of ``config``'s kind; :class:`InputError` for a kind nobody registered."""
    kind = getattr(config, "kind", None)
    if kind not in FITTERS:
        raise InputError(f"make_pairs: expected a configuration of one of the kinds {', '.join(FITTERS)} "
                         f"(roguefit.registry.FITTERS), got {type(config).__name__} of kind {kind!r}")
    return FITTERS[kind]


def presets_of(kind: str) -> list[str]:
    """The names of the presets of one kind of field, in :data:`PRESETS`' order."""
    return [name for name, config in PRESETS.items() if config.kind == kind]


def describe_presets() -> str:
    """``"blur (64³ RGB grid, half-size render), coarse (96³ RGB grid), ..."``: for help strings."""
    return ", ".join(f"{name} ({PRESET_NOTES[name]})" for name in PRESETS)
