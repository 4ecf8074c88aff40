"""roguefit: a CPU radiance-field fitter that makes render/photo pairs for pre-training.

A data tool beside the :mod:`roguenerf` library (which never imports it): it fits a DVGO-style
dense-grid field (or 3D Gaussian splats, :mod:`roguefit.splats`) to the training views of a
posed photo set and renders every view (RGB, z-depth, accumulated opacity) into the
scene-folder format that ``roguenerf`` reads.

``roguenerf make-pairs PHOTOS_DIR --output SCENE_DIR`` and ``python -m roguefit.batch`` use it.
"""

from roguefit.fit import PRESETS, FitConfig, make_pairs
from roguefit.photos import PhotoSet, read_photo_set
from roguefit.splats import SplatConfig

__all__ = ["PRESETS", "FitConfig", "PhotoSet", "SplatConfig", "make_pairs", "read_photo_set"]
