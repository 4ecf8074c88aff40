"""roguefit: a CPU radiance-field fitter that makes render/photo pairs for pre-training.

A data tool beside the :mod:`roguenerf` library (which never imports it): it fits a field to the
training views of a posed photo set and renders every view (RGB, z-depth, accumulated opacity)
into the scene-folder format that ``roguenerf`` reads. The kinds of field (DVGO-style dense
grids, Instant-NGP hash grids, 3D Gaussian splats) and the named presets are registered in
:mod:`roguefit.registry`; :mod:`roguefit.pairs` (``make_pairs``) drives any of them through the
:class:`~roguefit.fitter.Fitter` protocol.

``roguenerf make-pairs PHOTOS_DIR --output SCENE_DIR`` and ``python -m roguefit.batch`` use it.
"""

from roguefit.fit import FitConfig
from roguefit.pairs import make_pairs
from roguefit.photos import PhotoSet, read_photo_set
from roguefit.registry import FITTERS, PRESETS
from roguefit.splats import SplatConfig

__all__ = ["FITTERS", "PRESETS", "FitConfig", "PhotoSet", "SplatConfig", "make_pairs", "read_photo_set"]
