"""Model hyper-parameters as dataclasses; named variants as data; one factory (STUB)."""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass
class UformerConfig:
    """Uformer (Wang et al. 2022) hyper-parameters."""

    embed_dim: int = 16
    """Channels of the first stage (T: 16, S: 32, B: 32)."""
    depths: tuple[int, ...] = (2, 2, 2, 2, 2, 2, 2, 2, 2)
    """LeWin blocks per stage: 4 encoder stages, bottleneck, 4 decoder stages."""
    num_heads: tuple[int, ...] = (1, 2, 4, 8, 16, 16, 8, 4, 2)
    win_size: int = 8
    mlp_ratio: float = 4.0


@dataclass
class EnhancerConfig:
    """The whole enhancer. ``use_*`` switches are the paper's ablations."""

    variant: str = "nano"
    features: int = 64
    """Encoder / merge channels (64 in the paper)."""
    uformer: UformerConfig = field(default_factory=UformerConfig)
    flow_iters: int = 4
    """Recurrent update iterations of the refinement flow network (at 1/8 resolution)."""
    flow_hidden: int = 64
    num_neighbours: int = 5
    leniency: float = 0.25
    use_neighbours: bool = True
    use_alignment: bool = True
    """3D alignment (reprojection); off: neighbour features are used unwarped (Uformer+NN)."""
    use_refinement: bool = True
    use_attention: bool = True


VARIANTS: dict[str, dict] = {}
"""Named variants: name -> overrides of EnhancerConfig / UformerConfig fields. T, S, B from the
Uformer paper plus small CPU variants ("nano", "micro")."""


def make_config(variant: str = "nano", **overrides) -> EnhancerConfig:
    """Config of a named variant with caller overrides winning (unknown keys raise InputError)."""
    raise NotImplementedError


def build_enhancer(variant: str | EnhancerConfig = "nano", **overrides):
    """Build an :class:`~roguenerf.models.enhancer.Enhancer` from a variant name or config."""
    raise NotImplementedError
