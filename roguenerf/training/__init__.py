"""Pre-training, per-scene fine-tuning and evaluation of the enhancer."""

from roguenerf.training.config import (
    COMPONENTS,
    TrainConfig,
    TrainPlan,
    TrainProgress,
    TrainResult,
    plan_training,
)
from roguenerf.training.evaluate import evaluate
from roguenerf.training.loop import MODEL_FILE, STATE_FILE, finetune, pretrain, transfer_weights

__all__ = [
    "COMPONENTS",
    "MODEL_FILE",
    "STATE_FILE",
    "TrainConfig",
    "TrainPlan",
    "TrainProgress",
    "TrainResult",
    "evaluate",
    "finetune",
    "plan_training",
    "pretrain",
    "transfer_weights",
]
