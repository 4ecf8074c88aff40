"""The measured neighbour rule (roguenerf.enhance.select): what it measures, what it chooses,
and the enhancer's explicit neighbour list."""

from __future__ import annotations

import math

import pytest
import torch

from roguenerf.enhance import EnhanceOptions, NeighbourRule
from roguenerf.enhance.select import Candidate, choose, measure_candidates
from roguenerf.errors import InputError
from roguenerf.inference import SceneEnhancer
from tests.geometry_helpers import turned
from tests.model_helpers import perturbed_micro


def _K(h: int, w: int, f: float = 40.0) -> torch.Tensor:
    return torch.tensor([[f, 0, w / 2], [0, f, h / 2], [0, 0, 1]], dtype=torch.float32)


def _candidate(rank: int, coverage: float, error: float) -> Candidate:
    return Candidate(position=10 + rank, rank=rank, angle=float(rank), baseline=0.1, coverage=coverage, error=error,
                     consensus=0.5)


def test_measure_candidates_known_answers():
    """A photo taken where the view stands, identical to the render, covers the view and has no
    error; a camera turned away sees nothing (error 1); a second exact copy agrees with the
    first everywhere (consensus 1); a brighter copy does not agree with them."""
    h, w = 24, 32
    torch.manual_seed(0)
    render = torch.rand(3, h, w)
    depth = torch.full((1, h, w), 2.0)
    K = _K(h, w)
    pose = torch.eye(4, dtype=torch.float64)
    away = turned(pose, 180.0)
    brighter = (render + 0.3).clamp(0, 1)
    neighbours = [(render, depth, K, pose), (render.clone(), depth, K, pose), (brighter, depth, K, pose),
                  (render, depth, K, away)]
    out = measure_candidates(render, depth, K, pose, neighbours, positions=[7, 8, 9, 11])
    assert [c.position for c in out] == [7, 8, 9, 11] and [c.rank for c in out] == [0, 1, 2, 3]
    assert out[0].coverage == pytest.approx(1.0) and out[0].error == pytest.approx(0.0, abs=1e-5)
    assert out[0].consensus == pytest.approx(1.0) and out[1].consensus == pytest.approx(1.0)
    assert out[0].angle == pytest.approx(0.0, abs=1e-6) and out[0].baseline == pytest.approx(0.0)
    assert out[2].consensus < 0.2 and out[2].error > 0.15
    assert out[3].coverage == 0.0 and out[3].error == 1.0 and out[3].consensus == 0.0
    assert out[3].angle == pytest.approx(180.0, abs=1e-4)


def test_measure_baseline_is_distance_over_median_depth():
    h, w = 16, 16
    render, depth, K = torch.rand(3, h, w), torch.full((1, h, w), 4.0), _K(h, w)
    pose = torch.eye(4, dtype=torch.float64)
    moved = pose.clone()
    moved[0, 3] = 0.5
    (c,) = measure_candidates(render, depth, K, pose, [(render, depth, K, moved)])
    assert c.baseline == pytest.approx(0.5 / 4.0)


def test_choose_keeps_order_drops_low_coverage_and_stops_at_a_worse_error():
    cands = [_candidate(0, 0.9, 0.10), _candidate(1, 0.05, 0.01), _candidate(2, 0.8, 0.20),
             _candidate(3, 0.8, 0.12), _candidate(4, 0.9, 0.11), _candidate(5, 0.9, 0.30)]
    # rank 1 sees too little; ranks 0, 2 are the least two; 3 is within 1.25 x 0.10; 4 too but most = 4.
    picked = choose(cands, least=2, most=4, min_coverage=0.2, error_ratio=1.25)
    assert [c.rank for c in picked] == [0, 2, 3, 4]
    assert [c.rank for c in choose(cands, least=2, most=3, min_coverage=0.2, error_ratio=1.25)] == [0, 2, 3]
    # a tighter ratio stops at rank 3 (0.12 > 1.1 x 0.10), and nothing after it is looked at
    assert [c.rank for c in choose(cands, least=2, most=4, min_coverage=0.2, error_ratio=1.1)] == [0, 2]
    # a near candidate is taken whatever its error: rank 3 is 3 degrees off (angle = rank here), rank 4 is 4
    assert [c.rank for c in choose(cands, least=2, most=4, min_coverage=0.2, error_ratio=1.0,
                                   near_degrees=3.5)] == [0, 2, 3]
    # where fewer than `least` see enough, the best-covering others fill in, in rank order
    few = [_candidate(0, 0.1, 0.1), _candidate(1, 0.3, 0.1), _candidate(2, 0.15, 0.1)]
    assert [c.rank for c in choose(few, least=2, most=3, min_coverage=0.2, error_ratio=2.0)] == [1, 2]
    assert choose([], least=2, most=3, min_coverage=0.2, error_ratio=2.0) == []


@pytest.mark.parametrize("kwargs", [dict(measured=True, count=3), dict(measured=True, least=3, most=2),
                                    dict(measured=True, most=7, candidates=6), dict(least=0),
                                    dict(min_coverage=1.5), dict(error_ratio=0.5), dict(error_ratio=math.inf),
                                    dict(measured="yes")])
def test_neighbour_rule_refuses_bad_settings(kwargs):
    with pytest.raises(InputError):
        NeighbourRule(**kwargs)


def test_measured_rule_in_the_enhancer(scene):
    model = perturbed_micro(num_neighbours=2)
    rule = NeighbourRule(measured=True, candidates=4, least=2, most=3, min_coverage=0.0, error_ratio=100.0)
    enhancer = SceneEnhancer(scene, model, options=EnhanceOptions(neighbours=rule))
    assert enhancer.options.describe().startswith("2-3 of 4 neighbours, measured")
    i = scene.index("test_000")
    frame = scene.frames[i]
    # without the view, the rule names every candidate it may read (what a caller must load)
    assert len(enhancer.select(frame.world_from_cam)) == 4
    result = enhancer.enhance_view(i)
    assert len(result.neighbours) == 3  # any error is within 100 x: up to `most`
    assert [c["name"] for c in result.candidates if c["chosen"]] == result.neighbours
    assert len(result.candidates) == 4 and all(0 <= c["coverage"] <= 1 for c in result.candidates)
    # the same neighbours given explicitly give the same image
    explicit = enhancer.enhance(scene.render(i), scene.depth(i), frame.K, frame.world_from_cam,
                                neighbours=result.neighbours)
    assert explicit.neighbours == result.neighbours and explicit.candidates is None
    assert torch.equal(explicit.image, result.image)
    strict = SceneEnhancer(scene, model, options=EnhanceOptions(neighbours=rule.__class__(
        measured=True, candidates=4, least=2, most=3, min_coverage=0.0, error_ratio=1.0)))
    assert len(strict.enhance_view(i).neighbours) in (2, 3)


def test_explicit_neighbours_must_be_training_views(scene):
    enhancer = SceneEnhancer(scene, perturbed_micro())
    i = scene.index("test_000")
    frame = scene.frames[i]
    args = (scene.render(i), scene.depth(i), frame.K, frame.world_from_cam)
    assert enhancer.enhance(*args, neighbours=["train_002"]).neighbours == ["train_002"]
    assert enhancer.enhance(*args, neighbours=[]).neighbours == []
    with pytest.raises(InputError, match="not training views"):
        enhancer.enhance(*args, neighbours=["test_001"])


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    from roguenerf.data.toy import make_toy_scene

    return make_toy_scene(tmp_path_factory.mktemp("toy"), seed=3, n_train=6, n_test=2, height=32, width=40)
