"""Neighbour pose refinement (roguenerf.enhance.align) on the toy world's exact geometry."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch
from kornia.filters import gaussian_blur2d

from roguenerf.data.toy import make_toy_scene, make_toy_world, render_toy_view, toy_camera_path, toy_intrinsics
from roguenerf.enhance.align import AlignConfig, align_neighbour, shrink
from roguenerf.errors import InputError
from roguenerf.geometry.noise import perturb_poses
from roguenerf.reprojection import reproject

H, W = 96, 128


@pytest.fixture(scope="module")
def views():
    world = make_toy_world(0)
    poses = toy_camera_path(world, 6, seed=0)
    K = toy_intrinsics(H, W)
    target, neighbour = poses[2], poses[3]
    photo_t, depth_t = render_toy_view(world, target, K, H, W)
    photo_n, depth_n = render_toy_view(world, neighbour, K, H, W)
    render = gaussian_blur2d(photo_t[None], (5, 5), (1.0, 1.0), border_type="replicate")[0]
    return {"K": K, "target": target, "neighbour": neighbour, "render": render, "depth": depth_t,
            "photo": photo_n, "photo_depth": depth_n, "poses": poses}


def pixel_error(v, pose) -> float:
    """Mean distance (pixels) between where the target's pixels land in the neighbour with
    ``pose`` and with the true pose, over the pixels the true pose sees."""
    def land(p):
        return reproject(v["photo"][None], v["photo_depth"][None], v["depth"][None], v["K"].float(), v["K"].float(),
                         p, v["target"])
    true, moved = land(v["neighbour"]), land(pose)
    seen = true.valid[0, 0] > 0
    return float((true.coords[0] - moved.coords[0]).norm(dim=-1)[seen].mean())


def fit(v, pose, **config):
    return align_neighbour(v["photo"], v["photo_depth"], v["K"], pose, v["render"], v["depth"], v["K"],
                           v["target"], config=AlignConfig(**config) if config else None)


@pytest.mark.parametrize("deg,share,seed", [(0.25, 0.02, 1), (0.5, 0.05, 2), (1.0, 0.1, 3)])
def test_a_wrong_pose_is_found_again(views, deg, share, seed):
    spread = float(views["poses"][:, :3, 3].std(dim=0).norm())
    wrong = perturb_poses(views["neighbour"], deg, share * spread, torch.Generator().manual_seed(seed))
    before = pixel_error(views, wrong)
    assert before > 0.2  # the noise moves the reprojection by a fair share of a pixel, or more
    result = fit(views, wrong)
    assert result.accepted and result.refusal == ""
    assert result.error_after < 0.95 * result.error_before
    # Every fit ends within a tenth of a pixel of the truth (a small bias: the render is blurred).
    assert pixel_error(views, result.world_from_cam) < 0.1
    assert result.world_from_cam.dtype == torch.float64


def test_a_right_pose_is_kept(views):
    result = fit(views, views["neighbour"])
    assert pixel_error(views, result.world_from_cam) < 0.1
    if not result.accepted:
        assert torch.equal(result.world_from_cam, views["neighbour"])


def test_the_fit_does_not_depend_on_the_scene_units(views):
    """Depths and translations x1000: the same correction, in the new units."""
    wrong = perturb_poses(views["neighbour"], 0.5, 0.1, torch.Generator().manual_seed(5))
    a = fit(views, wrong)
    scaled = dict(views)
    scaled["depth"], scaled["photo_depth"] = views["depth"] * 1000, views["photo_depth"] * 1000
    scaled["target"] = views["target"].clone()
    scaled["target"][:3, 3] *= 1000
    wrong_scaled = wrong.clone()
    wrong_scaled[:3, 3] *= 1000
    b = align_neighbour(scaled["photo"], scaled["photo_depth"], views["K"], wrong_scaled, views["render"],
                        scaled["depth"], views["K"], scaled["target"])
    assert a.accepted and b.accepted
    assert b.rotation_deg == pytest.approx(a.rotation_deg, abs=1e-3)
    assert b.translation == pytest.approx(a.translation, abs=1e-4)
    assert torch.allclose(b.world_from_cam[:3, :3], a.world_from_cam[:3, :3], atol=1e-6)
    assert torch.allclose(b.world_from_cam[:3, 3], a.world_from_cam[:3, 3] * 1000, atol=1e-3)


def test_nothing_to_fit_keeps_the_dataset_pose(views):
    # A neighbour that looks the other way sees none of the target.
    away = views["neighbour"].clone()
    away[:3, :3] = away[:3, :3] @ torch.diag(torch.tensor([-1.0, 1.0, -1.0], dtype=torch.float64))
    result = fit(views, away)
    assert not result.accepted and torch.equal(result.world_from_cam, away)
    assert math.isnan(result.error_before) and result.refusal == "overlap"
    # A featureless photo and render: no gradient to follow.
    wrong = perturb_poses(views["neighbour"], 0.5, 0.05, torch.Generator().manual_seed(1))
    flat = align_neighbour(torch.full_like(views["photo"], 0.5), views["photo_depth"], views["K"], wrong,
                           torch.full_like(views["render"], 0.5), views["depth"], views["K"], views["target"])
    assert not flat.accepted and torch.equal(flat.world_from_cam, wrong)


def test_the_trust_region_bounds_the_fit(views):
    """A pose 6 degrees off is outside a 3-degree trust region: the fit may not go there, and
    one that ends against the edge is refused."""
    wrong = views["neighbour"].clone()
    wrong[:3, :3] = wrong[:3, :3] @ torch.linalg.matrix_exp(torch.tensor(
        [[0.0, 0.0, 0.1], [0.0, 0.0, 0.0], [-0.1, 0.0, 0.0]], dtype=torch.float64))  # ~5.7 deg about y
    result = fit(views, wrong, max_rotation_deg=3.0)
    assert result.rotation_deg <= 3.0 + 1e-6
    assert not result.accepted and torch.equal(result.world_from_cam, wrong)
    assert result.refusal == "edge"  # no minimum near the dataset pose, not "nothing to gain"


def test_bad_inputs_are_refused(views):
    with pytest.raises(InputError, match="photo"):
        align_neighbour(views["photo"][0], views["photo_depth"], views["K"], views["neighbour"], views["render"],
                        views["depth"], views["K"], views["target"])
    with pytest.raises(InputError, match="render_depth"):
        align_neighbour(views["photo"], views["photo_depth"], views["K"], views["neighbour"], views["render"],
                        views["depth"][:, :10], views["K"], views["target"])


def test_shrink_keeps_the_geometry(views):
    """The half-size copy with its scaled K lands each pixel where the full-size one does."""
    photo, depth, K = shrink(views["photo"], views["photo_depth"], views["K"], 64)
    assert max(photo.shape[-2:]) == 64 and depth.shape[-2:] == photo.shape[-2:]
    assert K[0, 0] == pytest.approx(float(views["K"][0, 0]) * 64 / W)
    same = shrink(views["photo"], views["photo_depth"], views["K"], 512)
    assert same[0].shape == views["photo"].shape


def test_the_scene_enhancer_refines_wrong_neighbour_poses(tmp_path):
    """SceneEnhancer(align=True) hands the model refined poses; align=False the dataset's."""
    from roguenerf.inference import SceneEnhancer
    from roguenerf.models import Enhancer, make_config

    scene = make_toy_scene(tmp_path / "scene", n_train=6, n_test=1, height=72, width=96)
    test = scene.indices("test")[0]
    frame = scene.frames[test]
    model = Enhancer(make_config("nano", num_neighbours=2))
    exact = SceneEnhancer(scene, model, align=False)
    positions = [exact.train.index(i) for i in exact.select(frame.world_from_cam)]
    true = exact.train_poses[positions].clone()
    wrong = perturb_poses(true, 0.5, 0.05, torch.Generator().manual_seed(0))
    exact.train_poses[positions] = wrong
    render, depth = scene.render(test), scene.depth(test)
    kept, done = exact.neighbour_poses(positions, render, depth, frame.K, frame.world_from_cam)
    assert done == [False, False] and torch.equal(kept, wrong)
    aligned = SceneEnhancer(scene, model)
    aligned.train_poses[positions] = wrong
    refined, done = aligned.neighbour_poses(positions, render, depth, frame.K, frame.world_from_cam)
    assert all(done)
    for j in range(2):
        before = (wrong[j, :3, 3] - true[j, :3, 3]).norm()
        after = (refined[j, :3, 3] - true[j, :3, 3]).norm()
        assert after < 0.5 * before
    result = aligned.enhance_view(test)
    assert result.aligned == [True, True] and len(result.neighbours) == 2
    assert exact.enhance_view(test).aligned is None
    with pytest.raises(InputError, match="align"):
        SceneEnhancer(scene, model, align="yes")


def test_a_path_fits_each_neighbour_once_and_again_from_nearer(tmp_path, monkeypatch):
    """PoseMemory: a neighbour is fitted on the first frame that uses it and reused after; with
    refit_nearer 0.5 a frame at under half the distance of the last fit fits it again (and that
    fit is what later frames reuse); with 0 it never is, nor where the fit found nothing to gain."""
    from roguenerf.enhance import align
    from roguenerf.enhance.temporal import TemporalConfig
    from roguenerf.inference import PoseMemory, SceneEnhancer
    from roguenerf.models import Enhancer, make_config

    scene = make_toy_scene(tmp_path / "scene", n_train=6, n_test=1, height=48, width=64)
    test = scene.indices("test")[0]
    enhancer = SceneEnhancer(scene, Enhancer(make_config("nano", num_neighbours=2)))
    position = enhancer.train.index(enhancer.select(scene.frames[test].world_from_cam)[0])
    photo_pose = enhancer.train_poses[position]
    render, depth, K = scene.render(test), scene.depth(test), scene.frames[test].K
    fitted_from = []
    real = align.align_neighbour

    def counting(*args, **kwargs):  # a fit that always finds something to gain
        fitted_from.append(round(float((args[-1][:3, 3] - photo_pose[:3, 3]).norm()), 6))
        return dataclasses.replace(real(*args, **kwargs), accepted=True, refusal="")

    monkeypatch.setattr(align, "align_neighbour", counting)

    def at(distance: float) -> torch.Tensor:
        pose = photo_pose.clone()
        pose[0, 3] += distance
        return pose

    for refit, expected in ((0.5, [0.4, 0.15]), (0.0, [0.4])):
        memory = PoseMemory(refit)
        fitted_from.clear()
        for distance in (0.4, 0.3, 0.21, 0.15, 0.1, 0.08):
            enhancer.neighbour_poses([position], render, depth, K, at(distance), memory=memory)
        assert fitted_from == expected
        assert memory.fits[position][2] == pytest.approx(expected[-1])
    monkeypatch.setattr(align, "align_neighbour",
                        lambda *a, **k: dataclasses.replace(real(*a, **k), accepted=False, refusal="gain"))
    memory = PoseMemory(0.5)
    for distance in (0.4, 0.15):
        enhancer.neighbour_poses([position], render, depth, K, at(distance), memory=memory)
    assert memory.fits[position][2] == pytest.approx(0.4)  # settled: not fitted again
    with pytest.raises(InputError, match="refit_nearer"):
        TemporalConfig(refit_nearer=1.0)


def test_evaluate_reports_which_neighbours_were_refined(tmp_path):
    from roguenerf.enhance import EnhanceOptions
    from roguenerf.models import Enhancer, make_config
    from roguenerf.training import evaluate

    scene = make_toy_scene(tmp_path / "scene", n_train=6, n_test=1, height=48, width=64)
    model = Enhancer(make_config("nano", num_neighbours=2))
    on, off = evaluate(scene, model), evaluate(scene, model, options=EnhanceOptions(align=None))
    assert on["views"][0]["aligned"] == [False, False]  # exact poses: nothing to refine
    assert off["views"][0]["aligned"] is None
    assert on["enhanced"]["psnr"] == pytest.approx(off["enhanced"]["psnr"], abs=1e-6)


def test_the_small_copies_are_a_bounded_cache(tmp_path, monkeypatch):
    from roguenerf import inference
    from roguenerf.inference import SceneEnhancer
    from roguenerf.models import Enhancer, make_config

    monkeypatch.setattr(inference, "ALIGN_CACHE", 3)
    scene = make_toy_scene(tmp_path / "scene", n_train=8, n_test=2, height=48, width=64)
    enhancer = SceneEnhancer(scene, Enhancer(make_config("nano", num_neighbours=2)))
    for i in scene.indices("train"):
        enhancer.enhance_view(i)
        assert len(enhancer._small) <= 3
    assert len(enhancer._small) == 3


# --- issue 51: the finest level is paid for only where the fit may be kept -------------------------


@pytest.mark.parametrize("deg,share,seed", [(0.25, 0.02, 1), (0.5, 0.05, 2)])
def test_early_refusal_keeps_every_fit_of_a_wrong_pose(views, deg, share, seed):
    spread = float(views["poses"][:, :3, 3].std(dim=0).norm())
    wrong = perturb_poses(views["neighbour"], deg, share * spread, torch.Generator().manual_seed(seed))
    full, early = fit(views, wrong, early_refusal=0.0), fit(views, wrong)  # the default refuses early
    assert full.accepted and early.accepted and not early.stopped_early
    assert full.coarse_gain > 0.1  # the level before the finest already sees the wrong pose
    assert torch.equal(early.world_from_cam, full.world_from_cam)  # the same fit, to the bit
    assert early.coarse_gain == full.coarse_gain


def test_early_refusal_stops_a_fit_with_nothing_to_find(views):
    full = fit(views, views["neighbour"], levels=(32, 64, 128), early_refusal=0.0)
    early = fit(views, views["neighbour"], levels=(32, 64, 128), early_refusal=0.5)
    assert not full.stopped_early and math.isfinite(full.coarse_gain) and full.coarse_gain < 0.5
    assert not full.accepted and full.refusal == "gain"  # the right pose: nothing to gain
    assert early.stopped_early and not early.accepted and early.refusal == "early"
    assert torch.equal(early.world_from_cam, views["neighbour"])
    assert early.error_after == early.error_before == pytest.approx(full.error_before, rel=1e-3)  # all it sees
    assert early.coarse_gain == full.coarse_gain
    one_level = fit(views, views["neighbour"], levels=(64,), early_refusal=0.5)  # no level before the finest
    assert not one_level.stopped_early and math.isnan(one_level.coarse_gain)


def test_a_views_fits_share_its_levels_and_find_the_same_poses(views):
    """The target's levels are built by its first neighbour's fit and read by the others', with the
    same fits to the bit as fits that build their own."""
    spread = float(views["poses"][:, :3, 3].std(dim=0).norm())
    starts = [perturb_poses(views["neighbour"], 0.5, 0.05 * spread, torch.Generator().manual_seed(s))
              for s in range(3)] + [views["neighbour"]]
    target: dict = {}
    for start in starts:
        alone = fit(views, start)
        shared = align_neighbour(views["photo"], views["photo_depth"], views["K"], start, views["render"],
                                 views["depth"], views["K"], views["target"], target_cache=target)
        assert torch.equal(shared.world_from_cam, alone.world_from_cam)
        assert (shared.accepted, shared.error_after, shared.coarse_gain) == (alone.accepted, alone.error_after,
                                                                             alone.coarse_gain)
    # the median depth and one entry per level (64 and 128 px: the target is 128 px wide); the
    # known-depth mask the levels were built from is not kept
    assert sorted(k if isinstance(k, str) else k[0] for k in target) == ["level", "level", "scale"]
    built = target.copy()
    align_neighbour(views["photo"], views["photo_depth"], views["K"], starts[0], views["render"], views["depth"],
                    views["K"], views["target"], target_cache=target)
    assert all(target[k] is built[k] for k in built)  # read, not rebuilt


@pytest.mark.parametrize("deg,share,seed", [(0.25, 0.02, 1), (0.5, 0.05, 2)])
def test_judging_the_first_level_keeps_every_fit_of_a_wrong_pose(views, deg, share, seed):
    spread = float(views["poses"][:, :3, 3].std(dim=0).norm())
    wrong = perturb_poses(views["neighbour"], deg, share * spread, torch.Generator().manual_seed(seed))
    # three levels: the target is 128 px wide
    full = fit(views, wrong, levels=(32, 64, 128), early_refusal=0.0)
    first = fit(views, wrong, levels=(32, 64, 128), early_level=0)
    assert first.accepted and not first.stopped_early
    assert torch.equal(first.world_from_cam, full.world_from_cam)  # the same fit, to the bit
    assert first.coarse_gain == full.coarse_gain  # the last level judged: the one before the finest


def test_judging_the_first_level_stops_before_the_second(views, monkeypatch):
    """With three levels, a fit with nothing to find stops after the first with ``early_level=0``
    and after the second by default: it never samples the levels after the judged one."""
    import roguenerf.enhance.align as align

    sampled = []
    real = align._Level.sample

    def counting(self, pose):
        sampled.append(self.points.shape[1])  # the level's width
        return real(self, pose)

    monkeypatch.setattr(align._Level, "sample", counting)
    widths = {}
    for level in (0, -2):
        sampled.clear()
        result = fit(views, views["neighbour"], levels=(32, 64, 128), early_refusal=0.5, early_level=level)
        assert result.stopped_early and not result.accepted
        assert torch.equal(result.world_from_cam, views["neighbour"])
        widths[level] = set(sampled[1:])  # the first sample is the finest level's, at the dataset pose
    assert widths[0] == {32} and widths[-2] == {32, 64}
    with pytest.raises(InputError, match="early_level"):
        AlignConfig(early_level=0.5)


# --- issue 51: a neighbour with nothing to gain is judged once per scene ---------------------------


def _counting_fits(monkeypatch) -> list:
    """Each call of align_neighbour as the scene enhancer makes it, recorded."""
    import roguenerf.enhance.align as align

    calls, real = [], align.align_neighbour

    def counting(*args, **kwargs):
        out = real(*args, **kwargs)
        calls.append(out)
        return out

    monkeypatch.setattr(align, "align_neighbour", counting)
    return calls


def test_a_neighbour_with_nothing_to_gain_is_fitted_once_per_scene(tmp_path, monkeypatch):
    """With the dataset's poses right, reuse fits each neighbour on the first view that judges it
    and never again, and gives the images of an enhancer that fits on every view."""
    from roguenerf.enhance import EnhanceOptions
    from roguenerf.inference import SceneEnhancer
    from roguenerf.models import Enhancer, make_config

    scene = make_toy_scene(tmp_path / "scene", n_train=6, n_test=3, height=48, width=64)
    model = Enhancer(make_config("nano", num_neighbours=2))
    each = SceneEnhancer(scene, model, options=EnhanceOptions(align=AlignConfig(reuse=False)))
    once = SceneEnhancer(scene, model, options=EnhanceOptions(align=AlignConfig(reuse=True)))
    calls = _counting_fits(monkeypatch)
    views = scene.indices("test") + scene.indices("test")  # every view twice
    fitted, used = {"each": [], "once": []}, 0
    for i in views:
        for name, enhancer in (("each", each), ("once", once)):
            calls.clear()
            result = enhancer.enhance_view(i)
            fitted[name] += calls
            assert result.aligned == [False] * len(result.neighbours)
            if name == "each":
                image, used = result.image, used + len(result.neighbours)
            else:
                assert torch.equal(result.image, image)
    assert len(fitted["each"]) == used  # every neighbour of every view fitted
    assert not each.settled and once.settled
    # each settled neighbour was fitted exactly once; only the others were fitted again
    settling = [c for c in fitted["once"] if c.refusal in ("early", "gain")]
    assert len(settling) == len(once.settled)
    assert len(fitted["once"]) < len(fitted["each"]) / 2


def test_a_wrong_pose_is_fitted_on_every_view_with_reuse(tmp_path, monkeypatch):
    """A neighbour whose fit was kept is fitted again on each view (a fit is never carried to
    another view), so reuse changes nothing where the poses are wrong."""
    from roguenerf.enhance import EnhanceOptions, NeighbourRule
    from roguenerf.inference import SceneEnhancer
    from roguenerf.models import Enhancer, make_config

    scene = make_toy_scene(tmp_path / "scene", n_train=6, n_test=2, height=72, width=96)
    model = Enhancer(make_config("nano", num_neighbours=2))
    enhancers = [SceneEnhancer(scene, model, options=EnhanceOptions(neighbours=NeighbourRule(count=2),
                                                                    align=AlignConfig(reuse=r))) for r in (False, True)]
    for enhancer in enhancers:
        enhancer.train_poses = perturb_poses(enhancer.train_poses, 0.5, 0.05, torch.Generator().manual_seed(0))
    calls = _counting_fits(monkeypatch)
    for i in scene.indices("test") * 2:
        results = []
        for enhancer in enhancers:
            calls.clear()
            results.append(enhancer.enhance_view(i))
            assert len(calls) == 2 and all(c.accepted for c in calls)
        assert results[0].aligned == results[1].aligned == [True, True]
        assert torch.equal(results[0].image, results[1].image)
    assert not enhancers[1].settled
    with pytest.raises(InputError, match="reuse"):
        AlignConfig(reuse=1)


def test_levels_built_from_one_known_depth_mask_equal_levels_built_alone(views):
    """An image's levels share one known-depth mask and filled depth (computed once, issue 51):
    each level's depth is the one computed from the depth alone, to the bit, and a neighbour's
    cache keeps the levels, not the mask."""
    from roguenerf.enhance.align import _known_filled, _Level, _level_depth

    depth = views["photo_depth"][None].clone()
    depth[..., :5, :7] = float("nan")
    depth[..., 9, :] = 0.0
    filled = _known_filled(depth)
    for to in [(48, 64), (24, 32), (13, 17)]:
        assert torch.equal(_level_depth(depth, to, filled), _level_depth(depth, to))
    cache: dict = {}
    spread = float(views["poses"][:, :3, 3].std(dim=0).norm())
    start = perturb_poses(views["neighbour"], 0.5, 0.05 * spread, torch.Generator().manual_seed(3))
    for _ in range(2):
        cached = align_neighbour(views["photo"], views["photo_depth"], views["K"], start, views["render"],
                                 views["depth"], views["K"], views["target"], cache=cache)
        assert torch.equal(cached.world_from_cam, fit(views, start).world_from_cam)
    assert "filled" not in cache and all(isinstance(k, tuple) for k in cache)
    level = _Level(64, views["photo"], views["photo_depth"], views["K"], views["render"], views["depth"],
                   views["K"], 1.0, 1.0)  # no caches: the level computes its own mask
    assert torch.equal(level.depth, _level_depth(views["depth"][None], tuple(level.depth.shape[-2:])))
