"""Enhancement as an explicit pipeline: ``select -> align -> model -> stages``.

- :class:`EnhanceOptions` (:mod:`.options`): the neighbour rule and each stage's config, one
  object passed from the CLI, the service, videos, ``evaluate`` and the benches.
- the stages after the model (:mod:`.stages`): colour matching, then trust.
- :class:`~roguenerf.inference.SceneEnhancer` runs the pipeline for one scene and records each
  stage in :class:`~roguenerf.inference.EnhanceResult`.
"""

from roguenerf.enhance.options import DEFAULT_TILE, DEVICE_TILE, NEAR_DEGREES, NEAR_EXTRA, EnhanceOptions, NeighbourRule
from roguenerf.enhance.stages import ColourStage, Stage, StageRecord, TrustStage, ViewState, stages_for
from roguenerf.enhance.temporal import TemporalConfig

__all__ = [
    "DEFAULT_TILE", "DEVICE_TILE", "NEAR_DEGREES", "NEAR_EXTRA", "ColourStage", "EnhanceOptions", "NeighbourRule",
    "Stage", "StageRecord", "TemporalConfig", "TrustStage", "ViewState", "stages_for",
]
