"""Camera geometry: conventions, Euler angles, neighbour selection, depth rules and sampling.

Camera maths only: it imports nothing of the library but :mod:`roguenerf.errors`. Reprojection
(which runs the kernels of :mod:`roguenerf.ops`) is :mod:`roguenerf.reprojection`, one layer up;
pose refinement, colour matching and trust are stages of :mod:`roguenerf.enhance`.

Conventions used everywhere in the library:

* Poses are camera-to-world 4x4 matrices in the **OpenCV** camera frame
  (x right, y down, z forward), named ``world_from_cam``.
* Intrinsics ``K`` are 3x3 with the **pixel-centre convention** of nerfstudio/COLMAP:
  the centre of pixel (row v, col u) is at image coordinates (u + 0.5, v + 0.5).
* Depth is z-depth along the optical axis, in the poses' units. It is **known** where
  :func:`~roguenerf.geometry.depth.known_depth_mask` is True: finite and
  ``DEPTH_EPS (1e-6) < z < MAX_DEPTH (1e10)``; anything else (0, negative, NaN, inf,
  denormals such as 1e-40) means "unknown". One rule, used everywhere.
* Poses may be float64 and stay so until a relative pose ``C_i^-1 C_k`` is formed
  (:func:`relative_pose`, float64); only relative quantities are cast to float32.
"""

from roguenerf.geometry.cameras import (
    as_world_from_cam,
    check_intrinsics,
    check_pose,
    intrinsics_matrix,
    llff_to_opencv,
    opencv_to_opengl,
    opengl_to_opencv,
    pixel_rays,
    ray_to_z_depth,
    relative_pose,
    scale_intrinsics,
)
from roguenerf.geometry.depth import DEPTH_EPS, MAX_DEPTH, known_depth, known_depth_mask, median_known_depth
from roguenerf.geometry.euler import angular_distance, euler_angles, euler_distance, rotation_angle, wrap_angle
from roguenerf.geometry.neighbours import select_neighbours

__all__ = [
    "DEPTH_EPS",
    "MAX_DEPTH",
    "angular_distance",
    "as_world_from_cam",
    "check_intrinsics",
    "check_pose",
    "euler_angles",
    "euler_distance",
    "intrinsics_matrix",
    "known_depth",
    "known_depth_mask",
    "llff_to_opencv",
    "median_known_depth",
    "opencv_to_opengl",
    "opengl_to_opencv",
    "pixel_rays",
    "ray_to_z_depth",
    "relative_pose",
    "rotation_angle",
    "scale_intrinsics",
    "select_neighbours",
    "wrap_angle",
]
