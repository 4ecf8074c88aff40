"""Pre-training, per-scene fine-tuning and evaluation of the enhancer.

The configuration and ``evaluate`` load without torch (the command line's ``--help`` takes its
defaults from :class:`TrainConfig`); the training loop's names are re-exported lazily.
"""

import importlib

from roguenerf.training.config import (
    COMPONENTS,
    TrainConfig,
    TrainPlan,
    TrainProgress,
    TrainResult,
    plan_training,
)
from roguenerf.training.evaluate import evaluate

_LAZY = {
    "MODEL_FILE": "roguenerf.training.loop",
    "STATE_FILE": "roguenerf.training.loop",
    "finetune": "roguenerf.training.loop",
    "pretrain": "roguenerf.training.loop",
    "transfer_weights": "roguenerf.training.loop",
}

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


def __getattr__(name: str):
    if name in _LAZY:
        value = getattr(importlib.import_module(_LAZY[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY))
