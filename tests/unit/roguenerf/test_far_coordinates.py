"""World coordinates far from the origin (UTM / ECEF, translations ~5e6) keep the geometry.

Relative poses C_i^-1 C_k are formed in float64 from the scene's float64 poses and only then
cast to float32 (reprojection, camera attention, neighbour ranking, training), so translating
a whole scene leaves every output unchanged to float32 rounding. float32 itself cannot even
store 5e6 + x to better than 0.5 units.
"""

from __future__ import annotations

import pytest
import torch

from roguenerf.data.readers import load_scene
from roguenerf.data.toy import make_toy_scene
from roguenerf.data.writers import write_scene_folder
from roguenerf.geometry import relative_pose, select_neighbours
from roguenerf.inference import SceneEnhancer
from roguenerf.models import build_enhancer
from roguenerf.reprojection import reproject
from roguenerf.training import TrainConfig
from roguenerf.training.loop import SceneData, training_step_inputs

OFFSET = (5e5, 5e6, 1e2)


pytestmark = pytest.mark.usefixtures("one_thread")


def _translated(poses: torch.Tensor, offset=OFFSET) -> torch.Tensor:
    out = poses.clone().to(torch.float64)
    out[..., :3, 3] += torch.tensor(offset, dtype=torch.float64)
    return out


@pytest.fixture(scope="module")
def scenes(tmp_path_factory):
    """The toy scene and the same scene written again with every pose translated by OFFSET."""
    root = tmp_path_factory.mktemp("far")
    near = make_toy_scene(root / "near", seed=3, n_train=6, n_test=2, height=32, width=40)
    n = len(near.frames)
    write_scene_folder(root / "far", names=[f.name for f in near.frames],
                       photos=torch.stack([near.photo(i) for i in range(n)]),
                       renders=torch.stack([near.render(i) for i in range(n)]),
                       depths=torch.stack([near.depth(i) for i in range(n)]),
                       world_from_cam=_translated(near.poses()), K=near.intrinsics(),
                       splits=[f.split for f in near.frames])
    far = load_scene(root / "far")
    torch.testing.assert_close(far.poses(), _translated(near.poses()), atol=1e-9, rtol=0)
    return near, far


def _model(seed: int = 0):
    torch.manual_seed(seed)
    model = build_enhancer("micro", num_neighbours=3)
    with torch.no_grad():
        for p in model.parameters():
            p.add_(0.05 * torch.randn_like(p))
    return model


def test_relative_pose_is_exact_far_from_the_origin():
    g = torch.Generator().manual_seed(0)
    q = torch.linalg.qr(torch.randn(2, 3, 3, generator=g, dtype=torch.float64)).Q
    q = q * torch.linalg.det(q)[:, None, None]  # rotations (det +1)
    poses = torch.eye(4, dtype=torch.float64).repeat(2, 1, 1)
    poses[:, :3, :3] = q
    poses[:, :3, 3] = torch.randn(2, 3, generator=g, dtype=torch.float64)
    want = torch.linalg.inv(poses[0]) @ poses[1]
    far = _translated(poses)
    got = relative_pose(far[0], far[1])
    assert got.dtype == torch.float64
    torch.testing.assert_close(got, want, atol=1e-8, rtol=0)
    # from float32 poses the same quantity is off by ~0.5 units: the reason for float64
    lossy = relative_pose(far[0].float(), far[1].float())
    assert float((lossy - want).abs().max()) > 1e-2


def test_reprojection_far_from_the_origin_matches_the_origin():
    K = torch.tensor([[20.0, 0, 8], [0, 20.0, 6], [0, 0, 1]])
    feats = torch.rand(1, 3, 12, 16, generator=torch.Generator().manual_seed(1))
    depth = torch.full((1, 1, 12, 16), 3.0)
    dst = torch.eye(4, dtype=torch.float64)
    src = torch.eye(4, dtype=torch.float64)
    src[:3, 3] = torch.tensor([0.3, -0.1, 0.05], dtype=torch.float64)
    a = reproject(feats, depth, depth, K, K, src, dst)
    b = reproject(feats, depth, depth, K, K, _translated(src), _translated(dst))
    assert a.valid.sum() > 50
    assert torch.equal(a.valid, b.valid)
    torch.testing.assert_close(b.coords, a.coords, atol=1e-4, rtol=0)
    torch.testing.assert_close(b.features, a.features, atol=1e-5, rtol=0)


def test_neighbour_choice_is_unchanged_by_a_far_translation(scenes):
    near, far = scenes
    for i in range(len(near.frames)):
        exclude = [i] if near.frames[i].split == "train" else None
        a = select_neighbours(near.poses()[i], near.poses(), 3, exclude=exclude)
        b = select_neighbours(far.poses()[i], far.poses(), 3, exclude=exclude)
        assert a.tolist() == b.tolist()


@pytest.mark.parametrize("tile", [512, 16])
def test_translated_scene_gives_the_same_enhanced_image(scenes, tile):
    near, far = scenes
    model = _model()
    a_enh = SceneEnhancer(near, model, tile=tile)
    b_enh = SceneEnhancer(far, model, tile=tile)
    for view in ("test_000", "test_001", "train_002"):
        a, b = a_enh.enhance_view(view), b_enh.enhance_view(view)
        assert a.neighbours == b.neighbours and len(a.neighbours) == 3
        torch.testing.assert_close(b.image, a.image, atol=2e-5, rtol=0)
    # the neighbours do contribute: without them the image is visibly different
    alone = SceneEnhancer(near, model, num_neighbours=0).enhance_view("test_000")
    assert float((alone.image - a_enh.enhance_view("test_000").image).abs().max()) > 1e-2


def test_training_inputs_far_from_the_origin_give_the_same_output(scenes):
    near, far = scenes
    model = _model()
    outs = []
    for scene in (near, far):
        data = SceneData(scene, TrainConfig().num_neighbours or 2)
        assert data.poses.dtype == torch.float64
        args, _ = training_step_inputs(model, data, torch.tensor([0, 3]), 24, torch.Generator().manual_seed(0),
                                       torch.device("cpu"))
        with torch.no_grad():
            outs.append(model(*args))
    torch.testing.assert_close(outs[1], outs[0], atol=2e-5, rtol=0)
