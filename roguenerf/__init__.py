"""RoGUENeRF: geometry-consistent enhancement of radiance-field renders (ECCV 2024).

The public API is re-exported here lazily, so ``import roguenerf`` stays cheap and never
imports the service stack (fastapi, huey, uvicorn).
"""

from __future__ import annotations

import importlib

from roguenerf import runtime as _runtime

# Before anything loads torch: OpenMP's default spin-wait collapses beside any busy process
# (docs/results.md, *Process settings*); PASSIVE unless the user chose a policy.
_runtime.prefer_passive_wait()

from roguenerf.errors import (  # noqa: E402
    CameraMismatchError,
    CheckpointError,
    InputError,
    NonFiniteOutputError,
    PathCancelled,
    RoGUENeRFError,
    SceneFormatError,
    TrainingCancelled,
    TrainingDivergedError,
)

__version__ = "0.1.0"

_LAZY = {
    # models
    "EnhancerConfig": "roguenerf.models",
    "Enhancer": "roguenerf.models",
    "VARIANTS": "roguenerf.models",
    "build_enhancer": "roguenerf.models",
    "make_config": "roguenerf.models",
    # data
    "Scene": "roguenerf.data.scene",
    "Frame": "roguenerf.data.scene",
    "load_scene": "roguenerf.data.readers",
    "unusable_views": "roguenerf.data.scene",
    "write_scene_folder": "roguenerf.data.writers",
    "make_toy_scene": "roguenerf.data.toy",
    # checkpoints and metrics
    "save_checkpoint": "roguenerf.checkpoint",
    "load_checkpoint": "roguenerf.checkpoint",
    "default_checkpoint_path": "roguenerf.checkpoint",
    "psnr": "roguenerf.metrics",
    "ssim": "roguenerf.metrics",
    "flip": "roguenerf.metrics",
    # inference and training
    "SceneEnhancer": "roguenerf.inference",
    "EnhanceOptions": "roguenerf.enhance",
    "NeighbourRule": "roguenerf.enhance",
    "TemporalConfig": "roguenerf.enhance",
    "EnhanceResult": "roguenerf.inference",
    "TrainConfig": "roguenerf.training",
    "TrainProgress": "roguenerf.training",
    "TrainResult": "roguenerf.training",
    "finetune": "roguenerf.training",
    "pretrain": "roguenerf.training",
    "evaluate": "roguenerf.training",
    # camera paths and exports of other tools
    "CameraPath": "roguenerf.trajectory",
    "PathResult": "roguenerf.trajectory",
    "read_camera_path": "roguenerf.trajectory",
    "enhance_path": "roguenerf.trajectory",
    "PathClock": "roguenerf.trajectory",
    "check_path": "roguenerf.trajectory",
    "check_camera": "roguenerf.trajectory",
    "import_3dgs": "roguenerf.splats.importer",
    "import_renders": "roguenerf.data.exports",
    "DataparserTransform": "roguenerf.data.exports",
    "read_colmap": "roguenerf.data.colmap",
    "write_colmap": "roguenerf.data.colmap",
    # what the service and the workers read, write and check with
    "DATAPARSER_FILE": "roguenerf.data.exports",
    "DEPTH_EPS": "roguenerf.geometry.depth",
    "ImageTooLargeError": "roguenerf.imageio",
    "MAX_DEPTH": "roguenerf.geometry.depth",
    "check_intrinsics": "roguenerf.geometry",
    "check_pose": "roguenerf.geometry",
    "encode_png": "roguenerf.imageio",
    "find_camera_file": "roguenerf.trajectory",
    "find_path_frames": "roguenerf.trajectory",
    "intrinsics_matrix": "roguenerf.geometry",
    "is_colmap_dataset": "roguenerf.data.colmap",
    "known_depth_mask": "roguenerf.geometry.depth",
    "opencv_to_opengl": "roguenerf.geometry",
    "opengl_to_opencv": "roguenerf.geometry",
    "ray_to_z_depth": "roguenerf.geometry",
    "read_dataset_views": "roguenerf.splats.importer",
    "read_depth": "roguenerf.imageio",
    "read_image": "roguenerf.imageio",
    "read_image_size": "roguenerf.imageio",
    "read_ply": "roguenerf.splats.ply",
}

__all__ = [
    "CameraMismatchError",
    "CheckpointError",
    "InputError",
    "NonFiniteOutputError",
    "PathCancelled",
    "RoGUENeRFError",
    "SceneFormatError",
    "TrainingCancelled",
    "TrainingDivergedError",
    "__version__",
    "native",  # public submodules: the C kernels' status, the process settings
    "runtime",
    *_LAZY,
]


def __getattr__(name: str):
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'roguenerf' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value
