"""The RoGUENeRF enhancer and its building blocks."""

from roguenerf.models.config import VARIANTS, EnhancerConfig, UformerConfig, make_config
from roguenerf.models.enhancer import Enhancer, NeighbourBatch, build_enhancer
from roguenerf.models.tiling import enhance_tiled
from roguenerf.models.uformer import Uformer

__all__ = [
    "VARIANTS",
    "Enhancer",
    "EnhancerConfig",
    "NeighbourBatch",
    "Uformer",
    "UformerConfig",
    "build_enhancer",
    "enhance_tiled",
    "make_config",
]
