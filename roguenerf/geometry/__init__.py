"""Camera geometry: conventions, Euler angles, neighbour selection and reprojection.

Conventions used everywhere in the library:

* Poses are camera-to-world 4x4 matrices in the **OpenCV** camera frame
  (x right, y down, z forward), named ``world_from_cam``.
* Intrinsics ``K`` are 3x3 with the **pixel-centre convention** of nerfstudio/COLMAP:
  the centre of pixel (row v, col u) is at image coordinates (u + 0.5, v + 0.5).
* Depth is z-depth along the optical axis, in the poses' units; ``<= 0`` or non-finite
  depth means "unknown".
"""

from roguenerf.geometry.cameras import (
    check_intrinsics,
    check_pose,
    intrinsics_matrix,
    llff_to_opencv,
    opencv_to_opengl,
    opengl_to_opencv,
    ray_to_z_depth,
    scale_intrinsics,
)
from roguenerf.geometry.euler import angular_distance, euler_angles, euler_distance, wrap_angle
from roguenerf.geometry.neighbours import select_neighbours
from roguenerf.geometry.reproject import Reprojection, reproject, sampling_source

__all__ = [
    "Reprojection",
    "angular_distance",
    "check_intrinsics",
    "check_pose",
    "euler_angles",
    "euler_distance",
    "intrinsics_matrix",
    "llff_to_opencv",
    "opencv_to_opengl",
    "opengl_to_opencv",
    "ray_to_z_depth",
    "reproject",
    "sampling_source",
    "scale_intrinsics",
    "select_neighbours",
    "wrap_angle",
]
