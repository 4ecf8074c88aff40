"""Camera trajectories: a path's cameras read from users' files, checked against the scene, enhanced
frame by frame, their flicker measured.

- :mod:`~roguenerf.trajectory.readers`: :class:`CameraPath`, :func:`read_camera_path` (nerfstudio,
  transforms list, Inria ``cameras.json``, COLMAP ``images.txt`` / ``.bin``), :func:`find_camera_file`,
  :func:`find_path_frames`, :func:`smooth_path`.
- :mod:`~roguenerf.trajectory.checks`: does a path (or one camera) live in the scene's world:
  :func:`check_camera_path`, :func:`check_camera`, :func:`check_path`, :class:`PathCheck`.
- :mod:`~roguenerf.trajectory.flicker`: :func:`pair_flicker`, :func:`summarise_flicker`.
- :mod:`~roguenerf.trajectory.enhancing`: :func:`enhance_path` -> :class:`PathResult`,
  :class:`PathClock` (the seconds left of a run, from its progress),
  :func:`check_path_output` and the names of the files it writes.
"""

from roguenerf.trajectory.checks import (
    CHECK_FRAMES,
    CHECK_PIXELS,
    DEPTH_AGREEMENT,
    FAR_FACTOR,
    MIN_SEEN,
    PathCheck,
    check_camera,
    check_camera_path,
    check_path,
)
from roguenerf.trajectory.enhancing import (
    FLICKER_FILE,
    FRAME_FOLDER,
    POSE_MATCH_TOL,
    SIDE_BY_SIDE_FILE,
    STATE_FILE,
    VIDEO_FILE,
    PathClock,
    PathResult,
    check_path_output,
    enhance_path,
)
from roguenerf.trajectory.flicker import pair_flicker, summarise_flicker
from roguenerf.trajectory.readers import (
    CAMERA_FILES,
    CameraPath,
    find_camera_file,
    find_path_frames,
    natural_key,
    read_camera_path,
    smooth_path,
)

__all__ = [
    "CAMERA_FILES",
    "CHECK_FRAMES",
    "CHECK_PIXELS",
    "DEPTH_AGREEMENT",
    "FAR_FACTOR",
    "FLICKER_FILE",
    "FRAME_FOLDER",
    "MIN_SEEN",
    "POSE_MATCH_TOL",
    "SIDE_BY_SIDE_FILE",
    "STATE_FILE",
    "VIDEO_FILE",
    "CameraPath",
    "PathCheck",
    "PathClock",
    "PathResult",
    "check_camera",
    "check_camera_path",
    "check_path",
    "check_path_output",
    "enhance_path",
    "find_camera_file",
    "find_path_frames",
    "natural_key",
    "pair_flicker",
    "read_camera_path",
    "smooth_path",
    "summarise_flicker",
]
