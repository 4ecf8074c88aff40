"""SceneEnhancer: neighbour choice, feature cache, no-neighbour fallback, NaN guard, threads."""

from __future__ import annotations

import math
from concurrent.futures import ThreadPoolExecutor

import pytest
import torch

from roguenerf.data.toy import make_toy_scene
from roguenerf.errors import InputError, RoGUENeRFError
from roguenerf.inference import NO_NEIGHBOUR_NOTE, SceneEnhancer, tile_for
from tests.geometry_helpers import turned
from tests.model_helpers import perturbed_micro


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return make_toy_scene(tmp_path_factory.mktemp("toy"), seed=3, n_train=6, n_test=2, height=32, width=40)


def _counting(model):
    calls = []
    original = model.encode_neighbours

    def encode(photos):
        calls.append(photos.shape[0])
        return original(photos)

    model.encode_neighbours = encode
    return calls


def test_enhance_shape_range_and_neighbours_from_train(scene):
    enhancer = SceneEnhancer(scene, perturbed_micro(), num_neighbours=3)
    result = enhancer.enhance_view("test_000")
    assert result.image.shape == (3, 32, 40)
    assert result.image.dtype == torch.float32
    assert 0.0 <= float(result.image.min()) and float(result.image.max()) <= 1.0
    assert len(result.neighbours) == 3
    assert all(name.startswith("train_") for name in result.neighbours)
    assert result.note is None and result.seconds > 0


def test_training_view_is_never_its_own_neighbour(scene):
    enhancer = SceneEnhancer(scene, perturbed_micro(), num_neighbours=5)
    for name in ("train_000", "train_003"):
        result = enhancer.enhance_view(name)
        assert name not in result.neighbours
        assert len(result.neighbours) == 5  # all the other training views
    i = scene.index("train_002")
    frame = scene.frames[i]
    by_index = enhancer.enhance(scene.render(i), scene.depth(i), frame.K, frame.world_from_cam, exclude=i)
    by_name = enhancer.enhance(scene.render(i), scene.depth(i), frame.K, frame.world_from_cam, exclude="train_002")
    assert "train_002" not in by_index.neighbours and by_index.neighbours == by_name.neighbours
    assert torch.equal(by_index.image, by_name.image)


def test_num_neighbours_defaults_to_model_config(scene):
    model = perturbed_micro(num_neighbours=2)
    assert len(SceneEnhancer(scene, model).enhance_view("test_001").neighbours) == 2
    assert SceneEnhancer(scene, model, num_neighbours=0).enhance_view("test_001").neighbours == []


@pytest.mark.parametrize(("third", "expected"), [(3.5, 3), (4.5, 2)])
def test_a_third_neighbour_is_added_only_where_it_is_near(tmp_path, third, expected):
    """Left at the model's count (2), the enhancer adds the next nearest training view only when
    its rotation is within NEAR_DEGREES (4) of the view's; asked for 2, it takes exactly 2."""
    from roguenerf.data.readers import load_scene
    from roguenerf.data.writers import write_scene_folder
    from roguenerf.geometry import rotation_angle
    from roguenerf.inference import NEAR_DEGREES

    assert NEAR_DEGREES == 4.0
    toy = make_toy_scene(tmp_path / "toy", seed=3, n_train=5, n_test=1, height=16, width=20)
    target = toy.frames[toy.indices("test")[0]].world_from_cam.to(torch.float64)
    # Training cameras where the test camera stands, turned 1, 2 and `third` degrees, and two far ones.
    poses = [turned(target, 1.0), turned(target, 2.0), turned(target, third, axis=0),
             turned(target, 30.0), turned(target, 60.0), target]
    assert float(rotation_angle(target[:3, :3], poses[2][:3, :3])) == pytest.approx(third, abs=1e-6)
    n = len(poses)
    root = write_scene_folder(tmp_path / "near", names=[f"v{k}" for k in range(n)],
                              photos=torch.rand(n, 3, 16, 20), renders=torch.rand(n, 3, 16, 20),
                              depths=torch.ones(n, 1, 16, 20), world_from_cam=torch.stack(poses),
                              K=toy.intrinsics()[:1].expand(n, 3, 3).clone(), splits=["train"] * (n - 1) + ["test"])
    scene = load_scene(root)
    model = perturbed_micro(num_neighbours=2)
    default = SceneEnhancer(scene, model)
    assert [scene.frames[i].name for i in default.select(target)] == ["v0", "v1", "v2"][:expected]
    assert [scene.frames[i].name for i in SceneEnhancer(scene, model, num_neighbours=2).select(target)] == ["v0", "v1"]
    assert len(SceneEnhancer(scene, model, num_neighbours=4).select(target)) == 4


def test_rotation_angle_is_the_geodesic_angle():
    from roguenerf.geometry import rotation_angle

    pose = torch.eye(4, dtype=torch.float64)
    for degrees, axis in ((0.0, 0), (3.0, 1), (45.0, 2), (179.0, 0)):
        assert float(rotation_angle(pose[:3, :3], turned(pose, degrees, axis)[:3, :3])) == pytest.approx(degrees,
                                                                                                         abs=1e-5)


def test_features_are_encoded_once_and_reused(scene):
    model = perturbed_micro()
    calls = _counting(model)
    enhancer = SceneEnhancer(scene, model, num_neighbours=2)
    first = enhancer.enhance_view("test_000")
    encoded = sum(calls)
    assert encoded == 2 and enhancer.cached_views() == 2
    again = enhancer.enhance_view("test_000")
    assert sum(calls) == encoded  # nothing re-encoded
    assert torch.equal(first.image, again.image)


def test_the_neighbour_depths_kept_are_bounded_and_give_the_same_images(scene, monkeypatch):
    """A budget of two depths: enhancing every view keeps the last two used, and the images are
    those of an enhancer that keeps them all."""
    from roguenerf import inference

    model = perturbed_micro()
    unbounded = SceneEnhancer(scene, model, num_neighbours=2)
    views = list(range(len(scene)))  # training views too: each uses other neighbours
    images = [unbounded.enhance_view(i).image for i in views]
    one = scene.depth(scene.indices("train")[0])
    monkeypatch.setattr(inference, "DEPTH_CACHE_BYTES", 2 * one.numel() * one.element_size())
    bounded = SceneEnhancer(scene, model, num_neighbours=2)
    for i, image in zip(views, images, strict=True):
        assert torch.equal(bounded.enhance_view(i).image, image)
        assert len(bounded._depths) <= 2
    assert len(unbounded._depths) > 2 and len(bounded._depths) == 2  # the unbounded one keeps every one read


def test_cached_result_equals_direct_model_call(scene):
    from roguenerf.models import NeighbourBatch

    model = perturbed_micro()
    enhancer = SceneEnhancer(scene, model, num_neighbours=2, colour=False)
    i = scene.index("test_001")
    frame = scene.frames[i]
    result = enhancer.enhance_view(i)
    matcher = SceneEnhancer(scene, model, num_neighbours=2)
    matched = matcher.enhance_view(i)
    idx = [scene.index(n) for n in result.neighbours]
    with torch.no_grad():
        feats = model.encode_neighbours(torch.stack([scene.photo(j) for j in idx]))
        batch = NeighbourBatch(features=feats[None], depth=torch.stack([scene.depth(j) for j in idx])[None],
                               K=scene.intrinsics(idx).float()[None], world_from_cam=scene.poses(idx).float()[None])
        direct = model(scene.render(i)[None], scene.depth(i)[None], frame.K.float()[None],
                       frame.world_from_cam.float()[None], batch)[0].clamp(0, 1)
    torch.testing.assert_close(result.image, direct, atol=1e-5, rtol=0)
    # With colour matching (the default) the same image plus the colour field, upsampled.
    assert result.colour_offset is None and matched.colour_offset is not None
    positions = [matcher.train.index(j) for j in idx]
    match = matcher.colour_match(positions, direct, scene.depth(i), frame.K, frame.world_from_cam,
                                  scene.poses(idx).to(torch.float64))
    assert match.offset.tolist() == pytest.approx(matched.colour_offset, abs=1e-6)
    field = torch.nn.functional.interpolate(match.field, size=direct.shape[-2:], mode="bilinear", align_corners=False)
    torch.testing.assert_close(matched.image, (direct + field[0]).clamp(0, 1), atol=1e-5, rtol=0)


def test_view_seen_by_no_neighbour_runs_without_them(scene):
    model = perturbed_micro()
    enhancer = SceneEnhancer(scene, model, num_neighbours=3)
    i = scene.index("test_000")
    frame = scene.frames[i]
    # Turn the camera around (180 degrees about its y axis): its pixels, 1 unit deep, lie
    # behind the camera's old position and behind every training camera near it.
    flip = torch.diag(torch.tensor([-1.0, 1.0, -1.0, 1.0], dtype=torch.float64))
    pose = frame.world_from_cam @ flip
    depth = torch.full((1, 32, 40), 1e-3)
    result = enhancer.enhance(scene.render(i), depth, frame.K, pose)
    assert result.note == NO_NEIGHBOUR_NOTE
    assert result.neighbours == []
    with torch.no_grad():
        alone = model(scene.render(i)[None], depth[None], frame.K.float()[None], pose.float()[None], None)
    torch.testing.assert_close(result.image, alone[0].clamp(0, 1), atol=1e-5, rtol=0)


def test_non_finite_output_raises_instead_of_returning_nan(scene):
    model = perturbed_micro()
    with torch.no_grad():
        for p in model.conv_merge.parameters():
            p.fill_(math.nan)
    with pytest.raises(RoGUENeRFError, match="non-finite"):
        SceneEnhancer(scene, model).enhance_view("test_000")


def test_input_errors_name_the_argument(scene):
    enhancer = SceneEnhancer(scene, perturbed_micro())
    frame = scene.frames[0]
    render, depth = scene.render(0), scene.depth(0)
    with pytest.raises(InputError, match="render"):
        enhancer.enhance(render[:2], depth, frame.K, frame.world_from_cam)
    with pytest.raises(InputError, match="depth"):
        enhancer.enhance(render, depth[:, :10], frame.K, frame.world_from_cam)
    bad = render.clone()
    bad[0, 0, 0] = math.nan
    with pytest.raises(InputError, match="render"):
        enhancer.enhance(bad, depth, frame.K, frame.world_from_cam)
    with pytest.raises(InputError, match="num_neighbours"):
        SceneEnhancer(scene, perturbed_micro(), num_neighbours=-1)


def test_3x4_pose_is_the_4x4_pose_and_still_checked(scene):
    """Poses as tools print them (3x4) give the same image as the 4x4 form; an improper rotation
    is refused the same way (one check: geometry.check_pose)."""
    enhancer = SceneEnhancer(scene, perturbed_micro())
    i = next(n for n, f in enumerate(scene.frames) if f.split == "test")
    frame = scene.frames[i]
    render, depth = scene.render(i), scene.depth(i)
    four = enhancer.enhance(render, depth, frame.K, frame.world_from_cam)
    three = enhancer.enhance(render, depth, frame.K, frame.world_from_cam[:3])
    assert torch.equal(four.image, three.image) and four.neighbours == three.neighbours
    reflected = frame.world_from_cam[:3].clone()
    reflected[:, 0] *= -1
    with pytest.raises(InputError, match=r"world_from_cam.*det"):
        enhancer.enhance(render, depth, frame.K, reflected)
    scaled = frame.world_from_cam[:3].clone()
    scaled[:, :3] *= 1.1
    with pytest.raises(InputError, match=r"world_from_cam.*orthonormal"):
        enhancer.enhance(render, depth, frame.K, scaled)
    with pytest.raises(InputError, match=r"world_from_cam.*4x4 or 3x4"):
        enhancer.enhance(render, depth, frame.K, frame.world_from_cam[:2])


def test_concurrent_calls_match_sequential_and_encode_once(scene):
    model = perturbed_micro()
    calls = _counting(model)
    enhancer = SceneEnhancer(scene, model, num_neighbours=3)
    names = ["test_000", "test_001", "train_001", "train_004"] * 2
    with ThreadPoolExecutor(max_workers=4) as pool:
        results = list(pool.map(enhancer.enhance_view, names))
    assert sum(calls) == enhancer.cached_views() <= 6  # every training photo encoded at most once
    fresh = SceneEnhancer(scene, model, num_neighbours=3)
    for name, result in zip(names, results):
        torch.testing.assert_close(result.image, fresh.enhance_view(name).image, atol=1e-6, rtol=0)


def test_large_images_are_tiled(scene):
    model = perturbed_micro(use_uformer=False)
    on_cpu = SceneEnhancer(scene, model, num_neighbours=2)
    assert on_cpu.tile == 512  # the CPU's default (2048 on an accelerator: tile_for)
    # on the CPU, views up to 1920 x 1080 in 1024-px tiles, larger ones in 512-px tiles; a tile given wins
    assert [on_cpu.view_tile(size) for size in ((378, 504), (1080, 1920), (1920, 1080), (1081, 1920), (1512, 2016))] \
        == [1024, 1024, 1024, 512, 512]
    assert SceneEnhancer(scene, model, num_neighbours=2, tile=640).view_tile((1080, 1920)) == 640
    assert tile_for(None, "cuda", (1512, 2016)) == 2048 and tile_for(None, "cpu") == 512
    whole = on_cpu.enhance_view("test_000")
    tiled = SceneEnhancer(scene, model, num_neighbours=2, tile=16).enhance_view("test_000")
    assert tiled.image.shape == whole.image.shape
    assert tiled.neighbours == whole.neighbours
    # conv-only model with overlapping tiles: the seams must not change the image much
    assert float((tiled.image - whole.image).abs().mean()) < 0.02


@pytest.mark.slow
def test_uncacheable_photos_use_per_tile_crops_with_the_same_result(scene):
    """Photos too large for the cache budget are encoded per tile, only the part each tile
    sees (plus margins): the image equals the cached path's (same tiles), and nothing is cached."""
    model = perturbed_micro()
    for tile in (16, 512):  # tiled, and one whole-image "tile"
        cached = SceneEnhancer(scene, model, num_neighbours=3, tile=tile)
        cropped = SceneEnhancer(scene, model, num_neighbours=3, tile=tile, cache_bytes=1)
        calls = _counting(model)
        for view in ("test_000", "test_001", "train_002"):
            a, b = cached.enhance_view(view), cropped.enhance_view(view)
            assert a.neighbours == b.neighbours
            torch.testing.assert_close(b.image, a.image, atol=2e-4, rtol=0)
        del model.encode_neighbours  # undo _counting
        assert cropped.cached_views() == 0 and cached.cached_views() > 0
        # every crop is smaller than the photo (32 x 40) whenever the image is tiled
        if tile == 16:
            assert calls and all(n == 1 for n in calls)


def test_neighbour_cache_keeps_to_its_byte_budget(scene):
    model = perturbed_micro()
    one = (model.config.features + 2) * 32 * 40 * 4
    enhancer = SceneEnhancer(scene, model, num_neighbours=2, cache_bytes=3 * one)
    seen = set()
    for view in ("test_000", "test_001", "train_000", "train_004"):
        seen.update(enhancer.enhance_view(view).neighbours)
        assert enhancer.cached_views() <= 3
    assert len(seen) > 3  # the budget really evicted something


def test_tiled_enhancement_reports_progress_per_tile(scene):
    calls = []
    SceneEnhancer(scene, perturbed_micro(), num_neighbours=2, tile=16).enhance_view(
        "test_000", progress=lambda done, total: calls.append((done, total)))
    total = calls[-1][1]
    assert total > 1 and calls == [(k, total) for k in range(1, total + 1)]


def test_large_photos_are_encoded_in_strips_with_the_whole_photos_features(scene, monkeypatch):
    """A photo larger than two strips is encoded strip by strip with conv_H's margin: the same
    features as the whole photo's, and the enhanced image the same."""
    import roguenerf.inference as inference

    model = perturbed_micro()
    enhancer = SceneEnhancer(scene, model, num_neighbours=3)
    photo = scene.photo(scene.indices("train")[0])[None]
    whole = model.encode_neighbours(photo)
    monkeypatch.setattr(inference, "ENCODE_PIXELS", 40 * 8)  # strips of 8 rows of the 32 x 40 photo
    calls = _counting(model)
    strips = enhancer._encode(photo)
    assert calls == [1] * 4 and strips.shape == whole.shape
    torch.testing.assert_close(strips, whole, atol=1e-5, rtol=0)
    del model.encode_neighbours
    striped = enhancer.enhance_view("test_000").image
    monkeypatch.setattr(inference, "ENCODE_PIXELS", 10**9)
    torch.testing.assert_close(SceneEnhancer(scene, model, num_neighbours=3).enhance_view("test_000").image,
                               striped, atol=1e-5, rtol=0)
