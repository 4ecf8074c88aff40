"""One definition of "unknown depth" (roguenerf.geometry.depth), used everywhere.

A radiance field's expected depth in empty space can underflow to ~1e-40 (a float32
denormal). Such values are unknown for every consumer: reprojection, the enhancer's scene
scale, tiling, scenes read from disk, the degradation model, ray-to-z conversion and the
service's coverage check. Each test compares a map holding such values with the same map
holding 0 (the plainest "unknown") and expects the same answer.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from roguenerf.data.degrade import Degradation
from roguenerf.data.readers import load_scene
from roguenerf.data.toy import make_toy_scene
from roguenerf.data.writers import write_scene_folder
from roguenerf.errors import InputError
from roguenerf.geometry import DEPTH_EPS, MAX_DEPTH, known_depth, known_depth_mask, median_known_depth, ray_to_z_depth
from roguenerf.inference import SceneEnhancer
from roguenerf.models.enhancer import median_depth
from roguenerf.reprojection import reproject
from tests.model_helpers import perturbed_micro

DENORMAL = 1e-40  # a float32 subnormal: 1 / DENORMAL overflows float32 to inf
VALUES = [1.0, 0.0, -1.0, math.nan, math.inf, -math.inf, DENORMAL, 1e-30, 1e-7, DEPTH_EPS, 2e-6,
          3.5, 9e9, MAX_DEPTH, 1e12]
KNOWN = [True, False, False, False, False, False, False, False, False, False, True,
         True, True, False, False]


pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64, torch.bfloat16])
def test_known_depth_mask_table(dtype):
    depth = torch.tensor(VALUES, dtype=dtype)
    assert known_depth_mask(depth).tolist() == KNOWN
    # the rule as written (finite, eps < z < MAX_DEPTH), which the mask computes without isfinite
    assert torch.equal(known_depth_mask(depth), torch.isfinite(depth) & (depth > DEPTH_EPS) & (depth < MAX_DEPTH))
    if dtype == torch.bfloat16:
        return  # NumPy has no bfloat16
    # the NumPy form (the service's coverage check) gives the same answer
    assert known_depth_mask(depth.numpy()).tolist() == KNOWN
    filled = known_depth(depth)
    assert torch.isfinite(filled).all()
    assert filled.tolist() == [v if k else 0.0 for v, k in zip(depth.tolist(), KNOWN)]


def test_median_of_mostly_denormal_map_is_the_median_of_the_true_depths():
    d = torch.full((2, 1, 10, 10), DENORMAL)
    d[0, 0, 0, :3] = torch.tensor([2.0, 3.0, 4.0])
    d[1, 0, 5, 5] = 7.0
    d[1, 0, 0, 0] = 1e-7  # tiny but not denormal: still unknown
    assert median_known_depth(d).tolist() == [3.0, 7.0]
    assert torch.equal(median_depth(d), median_known_depth(d))  # the enhancer's name for it
    # nothing known at all: scale 1, never a tiny number whose reciprocal overflows
    assert median_known_depth(torch.full((1, 1, 4, 4), DENORMAL)).tolist() == [1.0]


def test_reproject_treats_denormals_as_missing_in_both_views():
    g = torch.Generator().manual_seed(0)
    K = torch.tensor([[8.0, 0, 4], [0, 8.0, 3], [0, 0, 1]])
    feats = torch.rand(1, 2, 6, 8, generator=g)
    dst = 2.0 + torch.rand(1, 1, 6, 8, generator=g)
    src = dst.clone()
    holes = torch.rand(1, 1, 6, 8, generator=g) < 0.5
    pose = torch.eye(4, dtype=torch.float64)
    near = pose.clone()
    near[0, 3] = 0.05

    def run(fill):
        return reproject(feats, torch.where(holes, fill, src), torch.where(holes, fill, dst), K, K, near, pose)

    a, b = run(DENORMAL), run(0.0)
    assert torch.equal(a.valid, b.valid) and torch.equal(a.features, b.features) and torch.equal(a.depth, b.depth)
    assert not a.valid[holes].any() and a.valid.any()


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return make_toy_scene(tmp_path_factory.mktemp("toy"), seed=3, n_train=6, n_test=2, height=32, width=40)


def _holes(shape, seed: int, fraction: float) -> torch.Tensor:
    return torch.rand(shape, generator=torch.Generator().manual_seed(seed)) < fraction


@pytest.mark.parametrize("tile", [512, 16])  # whole image, and tiled (scene scale shared by the tiles)
def test_enhance_with_mostly_denormal_depth_equals_enhance_with_zeros(scene, tile):
    """The outside check's case: most pixels ~1e-40, the rest true depths. Before, the median was
    ~1e-40, 1 / scale overflowed and enhance raised NonFiniteOutputError for an accepted input."""
    enhancer = SceneEnhancer(scene, perturbed_micro(), num_neighbours=3, tile=tile)
    i = scene.index("test_000")
    frame = scene.frames[i]
    render, depth = scene.render(i), scene.depth(i)
    holes = _holes(depth.shape, 1, 0.8)
    with_denormals = enhancer.enhance(render, torch.where(holes, DENORMAL, depth), frame.K, frame.world_from_cam)
    with_zeros = enhancer.enhance(render, torch.where(holes, 0.0, depth), frame.K, frame.world_from_cam)
    assert torch.isfinite(with_denormals.image).all()
    assert with_denormals.neighbours == with_zeros.neighbours and len(with_zeros.neighbours) == 3
    assert torch.equal(with_denormals.image, with_zeros.image)
    # the true depths still count: the image differs from the one without any depth
    no_depth = enhancer.enhance(render, torch.zeros_like(depth), frame.K, frame.world_from_cam)
    assert not torch.allclose(no_depth.image, with_zeros.image, atol=1e-4)


def _copy_scene(scene, root, fill: float):
    """The scene written again with every other training view's depth holes set to ``fill``."""
    n = len(scene.frames)
    depths = torch.stack([scene.depth(i) for i in range(n)])
    holes = _holes(depths.shape, 2, 0.4)
    holes[[f.split != "train" for f in scene.frames]] = False
    write_scene_folder(root, names=[f.name for f in scene.frames],
                       photos=torch.stack([scene.photo(i) for i in range(n)]),
                       renders=torch.stack([scene.render(i) for i in range(n)]),
                       depths=torch.where(holes, fill, depths), world_from_cam=scene.poses(),
                       K=scene.intrinsics(), splits=[f.split for f in scene.frames])
    return load_scene(root)


def test_denormal_depth_read_from_a_scene_folder_is_unknown(scene, tmp_path):
    a = _copy_scene(scene, tmp_path / "denormal", DENORMAL)
    b = _copy_scene(scene, tmp_path / "zero", 0.0)
    i = a.index("train_000")
    assert float(a.depth(i).abs().min()) == pytest.approx(DENORMAL, rel=1e-2)  # stored and read as is
    model = perturbed_micro()
    for view in ("test_000", "train_002"):
        ra = SceneEnhancer(a, model, num_neighbours=3).enhance_view(view)
        rb = SceneEnhancer(b, model, num_neighbours=3).enhance_view(view)
        assert ra.neighbours == rb.neighbours
        torch.testing.assert_close(ra.image, rb.image, atol=0, rtol=0)


def test_explicit_tiny_depth_scale_is_refused_not_nan():
    model = perturbed_micro()
    render = torch.rand(1, 3, 16, 16)
    depth = torch.full((1, 1, 16, 16), 2.0)
    K = torch.tensor([[16.0, 0, 8], [0, 16.0, 8], [0, 0, 1]])[None]
    pose = torch.eye(4)[None]
    from roguenerf.models import NeighbourBatch

    feats = model.encode_neighbours(torch.rand(1, 3, 16, 16))
    nb = NeighbourBatch(feats[None], depth[None], K[:, None], pose[:, None])
    with torch.no_grad():
        for bad in (DENORMAL, 0.0, math.inf):
            with pytest.raises(InputError, match="depth_scale"):
                model(render, depth, K, pose, nb, depth_scale=torch.tensor([bad]))
        assert torch.isfinite(model(render, depth, K, pose, nb, depth_scale=torch.tensor([2e-6]))).all()


@pytest.mark.parametrize("pose_noise", [0.0, 0.5])
def test_degradation_treats_denormal_depth_as_missing(pose_noise):
    """Before: without pose noise 1 / 1e-40 = inf made the defocus mix NaN; with it, the
    denormals were moved like real points and came out as depths of ~0.006 units."""
    g = torch.Generator().manual_seed(0)
    photos = torch.rand(2, 3, 16, 20, generator=g)
    depths = 1.0 + torch.rand(2, 1, 16, 20, generator=g)
    holes = _holes(depths.shape, 3, 0.6)
    deg = Degradation(defocus=(1.0, 2.0), haze=(0.2, 0.3), pose_noise_deg=pose_noise,
                      pose_noise_trans=pose_noise / 50)
    ra, da = deg(photos, torch.where(holes, DENORMAL, depths), torch.Generator().manual_seed(1))
    rb, db = deg(photos, torch.where(holes, 0.0, depths), torch.Generator().manual_seed(1))
    assert torch.isfinite(ra).all()
    torch.testing.assert_close(ra, rb, atol=0, rtol=0)
    assert torch.equal(known_depth_mask(da), known_depth_mask(db))
    assert known_depth_mask(da).float().mean() > 0.3


def test_ray_to_z_depth_maps_denormals_to_zero():
    K = torch.tensor([[4.0, 0, 2], [0, 4.0, 2], [0, 0, 1]])
    ray = torch.tensor([[2.0, DENORMAL], [1e-7, 3.0]])
    z = ray_to_z_depth(ray, K)
    assert z[0, 1] == 0 and z[1, 0] == 0 and bool((z[known_depth_mask(ray)] > 0).all())


def test_service_coverage_check_uses_the_same_rule():
    from service.errors import ApiError
    from service.limits import check_depth_coverage

    depth = torch.full((1, 20, 20), DENORMAL)
    depth[0, 0, :2] = 3.0  # 2 of 400 known: 0.5 % < 1 %
    with pytest.raises(ApiError, match="2 of 400"):
        check_depth_coverage(depth)
    depth[0, 1, :] = 3.0  # 22 of 400
    assert check_depth_coverage(depth) == pytest.approx(22 / 400)
    assert check_depth_coverage(np.where(np.isnan(depth.numpy()), 0, depth.numpy())) == pytest.approx(22 / 400)
