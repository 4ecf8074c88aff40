"""Model hyper-parameters as dataclasses; named variants as data; one config factory.

``make_config("T", flow_iters=2, embed_dim=24)`` starts from :class:`EnhancerConfig` defaults,
applies the variant's entries from :data:`VARIANTS`, then the caller's overrides (caller wins).
Keys may name an :class:`EnhancerConfig` field or, flat, a :class:`UformerConfig` field.

This module imports no model code (imports run one way: ``config`` <- ``enhancer``); the model
factory ``build_enhancer`` lives in :mod:`roguenerf.models.enhancer` and is exported by
:mod:`roguenerf.models`.
"""

from __future__ import annotations

import dataclasses
import typing
from dataclasses import dataclass, field
from typing import Any

from roguenerf.errors import InputError

STAGES = 9
"""Uformer stages: 4 encoder stages, the bottleneck, 4 decoder stages."""


@dataclass
class UformerConfig:
    """Uformer (Wang et al. 2022) hyper-parameters."""

    embed_dim: int = 16
    """Channels of the first stage (T: 16, S: 32, B: 32); stage s of the encoder has embed_dim * 2**s."""
    depths: tuple[int, ...] = (2, 2, 2, 2, 2, 2, 2, 2, 2)
    """LeWin blocks per stage: 4 encoder stages, bottleneck, 4 decoder stages."""
    num_heads: tuple[int, ...] = (1, 2, 4, 8, 16, 16, 8, 4, 2)
    """Attention heads per stage; each stage's channels must be divisible by its heads."""
    win_size: int = 8
    """Side of the square attention windows (tokens)."""
    mlp_ratio: float = 4.0
    """Hidden channels of the LeFF feed-forward = mlp_ratio * stage channels."""
    shift_windows: bool = True
    """Every second LeWin block of a stage uses windows shifted by win_size // 2 (official default)."""
    drop_path_rate: float = 0.0
    """Stochastic depth, linearly increasing over the encoder blocks (official Uformer: 0.1)."""
    modulator: bool = False
    """Decoder blocks add a learned embedding per window position to the attention input
    (the multi-scale restoration modulator of the official Uformer-B)."""

    def __post_init__(self) -> None:
        self.depths = tuple(self.depths)
        self.num_heads = tuple(self.num_heads)
        if self.embed_dim < 1:
            raise InputError(f"uformer.embed_dim: expected >= 1, got {self.embed_dim}")
        for name in ("depths", "num_heads"):
            value = getattr(self, name)
            if len(value) != STAGES or any(v < 1 for v in value):
                raise InputError(f"uformer.{name}: expected {STAGES} positive integers, got {value}")
        if self.win_size < 1:
            raise InputError(f"uformer.win_size: expected >= 1, got {self.win_size}")
        if self.mlp_ratio <= 0:
            raise InputError(f"uformer.mlp_ratio: expected > 0, got {self.mlp_ratio}")
        if not 0.0 <= self.drop_path_rate < 1.0:
            raise InputError(f"uformer.drop_path_rate: expected in [0, 1), got {self.drop_path_rate}")
        for stage, (dim, heads) in enumerate(zip(self.stage_dims(), self.num_heads)):
            if dim % heads:
                raise InputError(
                    f"uformer.num_heads[{stage}]: stage {stage} has {dim} channels, not divisible "
                    f"by {heads} heads"
                )

    def stage_dims(self) -> tuple[int, ...]:
        """Channels of the token sequence in each of the 9 stages (decoder stages hold the skip concat)."""
        e = self.embed_dim
        return (e, 2 * e, 4 * e, 8 * e, 16 * e, 16 * e, 8 * e, 4 * e, 2 * e)

    @property
    def size_multiple(self) -> int:
        """Inputs are padded internally to a multiple of this (2^4 downsamplings x window)."""
        return 16 * self.win_size


@dataclass
class EnhancerConfig:
    """The whole enhancer. ``use_*`` switches are the paper's ablations."""

    variant: str = "nano"
    """Name of the variant this config was made from (informational)."""
    features: int = 64
    """Encoder / merge channels (64 in the paper)."""
    uformer: UformerConfig = field(default_factory=UformerConfig)
    flow_iters: int = 4
    """Recurrent update iterations of the refinement flow network (at 1/8 resolution)."""
    flow_hidden: int = 64
    """Channels of the flow network's features and recurrent state."""
    attention_hidden: int = 32
    """Hidden channels of the pixel attention (conv) and the camera attention (fc)."""
    num_neighbours: int = 5
    """Neighbours to use by default (callers may pass any number, including 0)."""
    leniency: float = 0.25
    """Visibility-test leniency l of the 3D alignment."""
    use_neighbours: bool = True
    """Off: no neighbour branch at all (H_pool = 0; the merge conv sees only I^f): plain Uformer."""
    use_alignment: bool = True
    """3D alignment (reprojection); off: neighbour features are used unwarped (Uformer+NN)."""
    use_refinement: bool = True
    """Non-rigid refinement with the iterative flow network."""
    use_attention: bool = True
    """Geometry-aware attention (pixel x camera weights); off: H^a = H'."""
    use_uformer: bool = True
    """Off: a single 3x3 conv maps the merged features to RGB. Not a paper ablation: a conv-only,
    translation-equivariant model for tiling tests and the cheapest possible enhancer."""
    pool_spread: bool = False
    """Not in the paper. On: conv_merge also sees the spread of the weighted neighbour features,
    ``max_i H^a_i - min_i H^a_i``, next to their max-pool. Where neighbours reproject different
    content onto the same pixel (wrong depth), the max-pool alone keeps both copies' strongest
    responses (a ghost); the spread tells the merge that they disagree. Zero with one neighbour."""

    def __post_init__(self) -> None:
        if isinstance(self.uformer, dict):
            self.uformer = UformerConfig(**self.uformer)
        for name in ("features", "flow_hidden", "attention_hidden"):
            if getattr(self, name) < 1:
                raise InputError(f"{name}: expected >= 1, got {getattr(self, name)}")
        if self.flow_iters < 0:
            raise InputError(f"flow_iters: expected >= 0, got {self.flow_iters}")
        if self.num_neighbours < 0:
            raise InputError(f"num_neighbours: expected >= 0, got {self.num_neighbours}")
        if self.leniency < 0:
            raise InputError(f"leniency: expected >= 0, got {self.leniency}")

    def to_dict(self) -> dict:
        """JSON-able dict (tuples become lists); ``from_dict(to_dict())`` round-trips."""
        d = dataclasses.asdict(self)
        d["uformer"] = {k: list(v) if isinstance(v, tuple) else v for k, v in d["uformer"].items()}
        return d

    @classmethod
    def from_dict(cls, d: dict) -> EnhancerConfig:
        """Inverse of :meth:`to_dict`. Missing keys take defaults; unknown keys or wrong types raise InputError."""
        if not isinstance(d, dict):
            raise InputError(f"config: expected a dict, got {type(d).__name__}")
        d = dict(d)
        uformer = d.pop("uformer", {})
        if not isinstance(uformer, (dict, UformerConfig)):
            raise InputError(f"config.uformer: expected a dict, got {type(uformer).__name__}")
        if isinstance(uformer, UformerConfig):
            uformer = dataclasses.asdict(uformer)
        top = _typed_kwargs(cls, d, "config")
        sub = _typed_kwargs(UformerConfig, uformer, "config.uformer")
        return cls(**top, uformer=UformerConfig(**sub))


def _typed_kwargs(cls: type, d: dict, where: str) -> dict:
    """Check keys and value types of ``d`` against the fields of dataclass ``cls``."""
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)} - {"uformer"}
    unknown = sorted(set(d) - names)
    if unknown:
        raise InputError(f"{where}: unknown keys {unknown}; expected some of {sorted(names)}")
    out = {}
    for key, value in d.items():
        out[key] = _coerce(value, hints[key], f"{where}.{key}")
    return out


def _coerce(value: Any, hint: Any, where: str) -> Any:
    if hint is bool:
        if isinstance(value, bool):
            return value
    elif hint is int:
        if isinstance(value, int) and not isinstance(value, bool):
            return value
    elif hint is float:
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            return float(value)
    elif hint is str:
        if isinstance(value, str):
            return value
    elif typing.get_origin(hint) is tuple:
        if isinstance(value, (list, tuple)) and all(
            isinstance(v, int) and not isinstance(v, bool) for v in value
        ):
            return tuple(value)
    else:  # pragma: no cover - every field type is listed above
        raise TypeError(f"{where}: unsupported field type {hint}")
    name = getattr(hint, "__name__", str(hint))
    raise InputError(f"{where}: expected {name}, got {type(value).__name__} {value!r}")


VARIANTS: dict[str, dict] = {
    "T": dict(embed_dim=16, depths=(2,) * STAGES, win_size=8),
    "S": dict(embed_dim=32, depths=(2,) * STAGES, win_size=8),
    "B": dict(embed_dim=32, depths=(1, 2, 8, 8, 2, 8, 8, 2, 1), win_size=8, modulator=True),
    "nano": dict(embed_dim=16, depths=(1,) * STAGES, win_size=4, features=32, flow_iters=2,
                 flow_hidden=32, attention_hidden=16),
    "micro": dict(embed_dim=8, depths=(1,) * STAGES, num_heads=(1, 1, 2, 4, 8, 8, 4, 2, 1),
                  win_size=4, features=16, flow_iters=1, flow_hidden=16, attention_hidden=8),
}
"""Named variants: name -> overrides of EnhancerConfig / UformerConfig fields. T, S, B from the
Uformer paper (heads 1,2,4,8,16,16,8,4,2, window 8, 64 feature channels) plus small CPU
variants ("nano", "micro") with fewer feature channels, depth-1 stages, small windows
and fewer flow iterations. Inputs are padded to a multiple of 16 x win_size (128 for T/S/B,
64 for nano/micro): training crops of that multiple waste no compute."""

_UFORMER_KEYS = {f.name for f in dataclasses.fields(UformerConfig)}
_ENHANCER_KEYS = {f.name for f in dataclasses.fields(EnhancerConfig)}


def make_config(variant: str = "nano", **overrides) -> EnhancerConfig:
    """Config of a named variant with caller overrides winning (unknown keys raise InputError).

    Overrides may name EnhancerConfig fields, UformerConfig fields (flat, e.g. ``win_size=4``),
    or ``uformer=`` a dict / UformerConfig whose entries are applied on top of the variant's.
    """
    if variant not in VARIANTS:
        raise InputError(f"variant: expected one of {sorted(VARIANTS)}, got {variant!r}")
    merged = {**VARIANTS[variant]}
    uformer_over = overrides.pop("uformer", None)
    if isinstance(uformer_over, UformerConfig):
        uformer_over = dataclasses.asdict(uformer_over)
    if uformer_over is not None and not isinstance(uformer_over, dict):
        raise InputError(f"uformer: expected a dict or UformerConfig, got {type(uformer_over).__name__}")
    merged.update(uformer_over or {})
    merged.update(overrides)
    unknown = sorted(set(merged) - _UFORMER_KEYS - _ENHANCER_KEYS)
    if unknown:
        raise InputError(
            f"make_config: unknown keys {unknown}; expected fields of EnhancerConfig "
            f"{sorted(_ENHANCER_KEYS - {'uformer'})} or UformerConfig {sorted(_UFORMER_KEYS)}"
        )
    top = {k: v for k, v in merged.items() if k in _ENHANCER_KEYS}
    sub = {k: v for k, v in merged.items() if k in _UFORMER_KEYS}
    top.setdefault("variant", variant)
    return EnhancerConfig.from_dict({**top, "uformer": sub})
