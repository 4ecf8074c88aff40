"""3D Gaussian splats: Inria's ``point_cloud.ply``, spherical harmonics and a CPU rasterizer.

See ``docs/splats.md``. Pure PyTorch; ``gsplat`` is used only by :mod:`roguenerf.splats.importer`
when CUDA is there.
"""

from roguenerf.splats.gaussians import Gaussians, covariances, logit, quat_to_rotmat, sh_degree_of
from roguenerf.splats.ply import read_ply, write_ply
from roguenerf.splats.raster import Projected, project, render
from roguenerf.splats.sh import eval_sh, sh_basis

__all__ = ["Gaussians", "Projected", "covariances", "eval_sh", "logit", "project", "quat_to_rotmat", "read_ply",
           "render", "sh_basis", "sh_degree_of", "write_ply"]
