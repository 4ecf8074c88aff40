"""What an enhancement does, in one object: :class:`EnhanceOptions`.

The enhancer is a pipeline (:mod:`roguenerf.enhance`): choose the neighbours
(:class:`NeighbourRule`), refine their poses against the render (``align``), run the model, then
the stages after it in order (``colour``, then ``trust``). Each part is a frozen config, or None
where it is off. The CLI, the service, camera-path videos, ``evaluate`` and the benches build one
:class:`EnhanceOptions` and pass it on; :meth:`EnhanceOptions.fingerprint` (its ``asdict``) is
what a resumable run compares to refuse mixing frames made with other settings.
"""

from __future__ import annotations

import math
import operator
from dataclasses import asdict, dataclass, field, replace

import torch

from roguenerf.enhance.align import AlignConfig
from roguenerf.enhance.colour import ColourConfig
from roguenerf.enhance.temporal import TemporalConfig
from roguenerf.enhance.trust import TrustConfig
from roguenerf.errors import InputError

DEFAULT_TILE = 512
"""On the CPU, images whose height or width exceed this are enhanced tile by tile (bounded
memory: a 2016 x 1512 view under 1.5 GB), unless they have at most :data:`LARGE_TILE_PIXELS`."""

LARGE_TILE = 1024
"""On the CPU, the tile of images of at most :data:`LARGE_TILE_PIXELS`: fewer tiles, less work
wasted on their overlaps."""

LARGE_TILE_PIXELS = 1920 * 1080
"""The largest image (height x width) enhanced in :data:`LARGE_TILE` tiles on the CPU; larger
ones use :data:`DEFAULT_TILE`, which bounds their memory (their neighbour photos, cached or
encoded per tile, grow with them)."""

DEVICE_TILE = 2048
"""The same on an accelerator (CUDA, ...), where memory is not what binds and every tile is a
sequence of small kernel launches: on an H200, 1920 x 1080 views took 0.26 s with it against
0.46-0.72 s in 512-px tiles (the model 0.08 against 0.28-0.30 s), the same gain to 1e-3 dB
(``scripts/gpu_speed.py --tiles``; docs/results.md)."""


def tile_for(tile: int | None, device, size: tuple[int, int] | None = None) -> int:
    """The tile size a view of ``size`` (height, width) is enhanced in: ``tile`` where given, else
    by the ``device`` (a ``torch.device`` or its name) and the size: :data:`DEVICE_TILE` on an
    accelerator; on the CPU :data:`LARGE_TILE` up to :data:`LARGE_TILE_PIXELS`, else (and where the
    size is not given) :data:`DEFAULT_TILE`."""
    if tile is not None:
        return tile
    if torch.device(device).type != "cpu":
        return DEVICE_TILE
    if size is not None and size[0] * size[1] <= LARGE_TILE_PIXELS:
        return LARGE_TILE
    return DEFAULT_TILE


def tile_overlap(tile: int) -> int:
    """Pixels each tile of ``tile`` px shares with its neighbours (:func:`~roguenerf.models.tiling.enhance_tiled`)."""
    return min(32, tile // 4)


NEAR_EXTRA = 1
"""How many neighbours beyond the model's count the default rule may add, each only where it is
a near view (:data:`NEAR_DEGREES`)."""

NEAR_DEGREES = 4.0
"""A neighbour beyond the model's count is added when its camera's rotation differs from the
view's by at most this (the geodesic angle). A near photo's detail lands where the render's
depth puts it with little error; a far one's does not. On the leave-one-kind-out figure
(forward-facing captures, third neighbours 2-6 degrees off) a third neighbour within 3 or 4
degrees gains most, +0.23 dB zero-shot and +0.49 after 10 minutes (5: +0.20 / +0.45; any: +0.15
/ +0.41); on our own look, whose third neighbours are 9-31 degrees off, any third neighbour
costs up to 0.28 dB (docs/kinds.md, *A third neighbour where it is near*)."""


@dataclass(frozen=True)
class NeighbourRule:
    """Which training photos a view takes as neighbours (nearest first, by the paper's rule).

    ``count=None`` (the default): the model's own count (``model.config.num_neighbours``), plus
    up to ``near_extra`` more of the next nearest whose rotation is within ``near_degrees`` of
    the view's. An explicit ``count``: exactly that many (fewer where the scene has fewer
    training views), no near extras.
    """

    count: int | None = None
    near_extra: int = NEAR_EXTRA
    near_degrees: float = NEAR_DEGREES
    measured: bool = False
    """Choose per view by measurement (:func:`roguenerf.enhance.select.choose`): of the
    ``candidates`` nearest, those that see at least ``min_coverage`` of the view; at least
    ``least``, then more while their reprojected photo's error against the render is within
    ``error_ratio`` of the best taken or their rotation within ``near_degrees`` of the view's, up
    to ``most``. ``count`` and ``near_extra`` are then unused."""
    candidates: int = 6
    least: int = 2
    most: int = 3
    min_coverage: float = 0.0
    error_ratio: float = 1.1
    """The measured rule's settings were chosen on the choice half of the broad figure
    (``python -m bench.neighbour_rule ... --search``; docs/broad.md): the model's 2, and a third
    where it is within ``near_degrees`` or its reprojected photo's error is within 10 % of the
    best of the first two. It is not the default: on the report half it equals the default rule."""

    def __post_init__(self):
        if self.count is not None and (isinstance(self.count, bool) or not isinstance(self.count, int)
                                       or self.count < 0):
            raise InputError(f"neighbours: expected a count >= 0 or None (the model's), got {self.count!r}")
        if isinstance(self.near_extra, bool) or not isinstance(self.near_extra, int) or self.near_extra < 0:
            raise InputError(f"NeighbourRule.near_extra: expected an integer >= 0, got {self.near_extra!r}")
        if not (isinstance(self.near_degrees, (int, float)) and 0 <= self.near_degrees <= 180):
            raise InputError(f"NeighbourRule.near_degrees: expected degrees in [0, 180], got {self.near_degrees!r}")
        if not isinstance(self.measured, bool):
            raise InputError(f"NeighbourRule.measured: expected True or False, got {self.measured!r}")
        for name in ("candidates", "least", "most"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise InputError(f"NeighbourRule.{name}: expected an integer >= 1, got {value!r}")
        if not self.least <= self.most <= self.candidates:
            raise InputError(f"NeighbourRule: expected least <= most <= candidates, got {self.least}, {self.most}, "
                             f"{self.candidates}")
        if not (isinstance(self.min_coverage, (int, float)) and 0 <= self.min_coverage <= 1):
            raise InputError(f"NeighbourRule.min_coverage: expected a share in [0, 1], got {self.min_coverage!r}")
        if not (isinstance(self.error_ratio, (int, float)) and math.isfinite(self.error_ratio)
                and self.error_ratio >= 1):
            raise InputError(f"NeighbourRule.error_ratio: expected a finite number >= 1, got {self.error_ratio!r}")
        if self.measured and self.count is not None:
            raise InputError("NeighbourRule: a measured rule chooses the count itself; give count=None")

    def counts(self, model_count: int) -> tuple[int, int]:
        """``(count, near extras)`` for a model whose own count is ``model_count`` (a measured
        rule: ``(least, most - least)``, the fewest and the extras it may add)."""
        if self.measured:
            return self.least, self.most - self.least
        if self.count is not None:
            return self.count, 0
        return model_count, self.near_extra if model_count > 0 else 0


def _integer(value) -> int | None:
    """``value`` as an int where it is a whole number (numpy integers and 3.0 included), else None."""
    if isinstance(value, bool):
        return None
    try:
        return operator.index(value)
    except TypeError:
        return int(value) if isinstance(value, float) and value.is_integer() else None


def _stage(value, config_type, name: str):
    """A stage's setting: True (its defaults), False/None (off) or its config."""
    if value is True:
        return config_type()
    if value is False or value is None:
        return None
    if isinstance(value, config_type):
        return value
    raise InputError(f"{name}: expected True, False or a {config_type.__name__}, got {type(value).__name__}")


@dataclass(frozen=True)
class EnhanceOptions:
    """Everything that decides what an enhanced view looks like, besides the model's weights.

    Attributes:
        neighbours: the :class:`NeighbourRule`.
        align: refine each neighbour's pose against the render before reprojecting it
            (:func:`~roguenerf.enhance.align.align_neighbour`); None: the dataset's poses.
        colour: after the model, bring the image's low-frequency colour to the agreeing
            neighbours' (:func:`~roguenerf.enhance.colour.colour_match`); None: off.
        trust: keep only part of the model's change where the neighbours mostly disagree
            (:mod:`roguenerf.enhance.trust`); None: off.
        tile: images larger than this (height or width) are enhanced tile by tile; None (the
            default): by the device and the image (:func:`tile_for`).
        temporal: along a camera path (:func:`~roguenerf.trajectory.enhance_path`), blend each
            frame with the previous one, reprojected, less where their renders disagree
            (:mod:`roguenerf.enhance.temporal`); None: every frame on its own. Single views ignore it.
    """

    neighbours: NeighbourRule = field(default_factory=NeighbourRule)
    align: AlignConfig | None = field(default_factory=AlignConfig)
    colour: ColourConfig | None = field(default_factory=ColourConfig)
    trust: TrustConfig | None = field(default_factory=TrustConfig)
    tile: int | None = None
    temporal: TemporalConfig | None = field(default_factory=TemporalConfig)

    def __post_init__(self):
        if not isinstance(self.neighbours, NeighbourRule):
            raise InputError(f"neighbours: expected a NeighbourRule, got {type(self.neighbours).__name__}")
        object.__setattr__(self, "align", _stage(self.align, AlignConfig, "align"))
        object.__setattr__(self, "colour", _stage(self.colour, ColourConfig, "colour"))
        object.__setattr__(self, "trust", _stage(self.trust, TrustConfig, "trust"))
        object.__setattr__(self, "temporal", _stage(self.temporal, TemporalConfig, "temporal"))
        if self.tile is not None and (isinstance(self.tile, bool) or not isinstance(self.tile, int) or self.tile < 16):
            raise InputError(f"tile: expected an integer >= 16 pixels or None (by the device), got {self.tile!r}")

    @classmethod
    def from_flags(cls, *, neighbours: int | None = None, align=True, colour=True, trust=True,
                   tile: int | None = None, temporal=True) -> EnhanceOptions:
        """The options of a command line or a request: a neighbour count (None: the model's
        rule), and each stage True, False or its config."""
        if neighbours is not None:
            count = _integer(neighbours)
            if count is None or count < 0:
                raise InputError(f"num_neighbours: expected >= 0, got {neighbours}")
            neighbours = count
        if tile is not None:
            size = _integer(tile)
            if size is None or size < 16:
                raise InputError(f"tile: expected >= 16 pixels, got {tile}")
            tile = size
        return cls(neighbours=NeighbourRule(count=neighbours), align=align, colour=colour, trust=trust,
                   tile=tile, temporal=temporal)

    def with_(self, **changes) -> EnhanceOptions:
        """A copy with some fields changed (``dataclasses.replace``)."""
        return replace(self, **changes)

    def fingerprint(self) -> dict:
        """Every setting as plain JSON values (``asdict``): what resumable runs compare."""
        def plain(x):
            if isinstance(x, dict):
                return {k: plain(v) for k, v in x.items()}
            if isinstance(x, (list, tuple)):
                return [plain(v) for v in x]
            if isinstance(x, float) and not math.isfinite(x):
                return str(x)
            return x

        return plain(asdict(self))

    def describe(self) -> str:
        """One line for logs and notes: the neighbour rule and which stages are on."""
        n = self.neighbours
        rule = (f"{n.least}-{n.most} of {n.candidates} neighbours, measured" if n.measured
                else f"{n.count} neighbours" if n.count is not None
                else f"model's count + {n.near_extra} within {n.near_degrees:g} deg")
        on = [name for name in ("align", "colour", "trust", "temporal") if getattr(self, name) is not None]
        return f"{rule}; stages: {', '.join(on) or 'none'}"
