"""The RoGUENeRF enhancer and its building blocks."""

from roguenerf.models.config import VARIANTS, EnhancerConfig, UformerConfig, build_enhancer, make_config
from roguenerf.models.enhancer import Enhancer, NeighbourBatch

__all__ = [
    "VARIANTS",
    "Enhancer",
    "EnhancerConfig",
    "NeighbourBatch",
    "UformerConfig",
    "build_enhancer",
    "make_config",
]
