"""Trusting the neighbours by their agreement (roguenerf.geometry.trust): known answers, and on
the toy world with exact and with wrong geometry."""

from __future__ import annotations

import pytest
import torch

from roguenerf.data.toy import make_toy_scene
from roguenerf.errors import InputError
from roguenerf.geometry.colour import neighbour_agreement
from roguenerf.geometry.trust import TrustConfig, trust_factor
from tests.test_colour import Biased, textured


def test_the_share_kept_rises_with_the_agreement_up_to_full_share():
    assert trust_factor(0.0) == 0.0
    assert trust_factor(0.25) == pytest.approx(0.5)  # full_share 0.5 by default
    assert trust_factor(0.5) == 1.0
    assert trust_factor(0.97) == 1.0
    assert trust_factor(0.3, TrustConfig(full_share=0.6)) == pytest.approx(0.5)
    assert trust_factor(0.3, TrustConfig(full_share=0.3)) == 1.0
    with pytest.raises(InputError, match="share"):
        trust_factor(1.2)
    with pytest.raises(InputError, match="share"):
        trust_factor(float("nan"))


@pytest.mark.parametrize("bad", [{"full_share": 0}, {"full_share": 1.5}, {"full_share": float("nan")},
                                 {"sigma": -1}, {"max_disagreement": 0}])
def test_the_config_is_checked(bad):
    with pytest.raises(InputError, match="TrustConfig"):
        TrustConfig(**bad)


def test_agreement_is_where_two_neighbours_see_the_same_colour():
    photo = textured(0)
    full = torch.ones(1, 1, 48, 64)
    agree, mean = neighbour_agreement([(photo, full), (photo, full)], (48, 64), 2.0, 0.03)
    assert agree.shape == (1, 48, 64) and bool(agree.all())
    assert mean.shape == (1, 3, 48, 64)
    # The second sees only the left half: they can agree only there.
    half = full.clone()
    half[..., 32:] = 0
    agree, _ = neighbour_agreement([(photo, full), (photo * half, half)], (48, 64), 2.0, 0.03)
    assert float(agree.float().mean()) == pytest.approx(0.5)
    # 0.1 brighter everywhere: they disagree everywhere.
    agree, _ = neighbour_agreement([(photo, full), ((photo + 0.1).clamp(0, 1), full)], (48, 64), 2.0, 0.03)
    assert not bool(agree.any())
    # A third neighbour that disagrees with the other two where all three see: no agreement there.
    agree, _ = neighbour_agreement([(photo, full), (photo, full), ((photo + 0.1).clamp(0, 1), half)],
                                   (48, 64), 2.0, 0.03)
    assert not bool(agree[..., :, :31].any()) and bool(agree[..., :, 34:].all())
    with pytest.raises(InputError, match="two or more"):
        neighbour_agreement([(photo, full)], (48, 64), 2.0, 0.03)
    with pytest.raises(InputError, match="size"):
        neighbour_agreement([(photo, full), (photo[..., :32], full)], (48, 64), 2.0, 0.03)


def test_the_scene_enhancer_keeps_the_change_in_proportion_to_the_agreement(tmp_path):
    """A stand-in model that brightens every pixel by 0.04 (its change over the render). With the
    toy world's exact depth its two neighbours agree on most of the view and all of the change is
    kept; with the depth halved (a field whose geometry is off) they agree on less, and the change
    kept is share / full_share of it, everywhere."""
    from roguenerf.inference import SceneEnhancer
    from roguenerf.models import Enhancer, make_config
    from roguenerf.training import evaluate

    scene = make_toy_scene(tmp_path / "scene", n_train=6, n_test=1, height=72, width=96)
    test = scene.indices("test")[0]
    frame = scene.frames[test]
    bias = torch.tensor([0.04, 0.04, 0.04])
    model = Biased(Enhancer(make_config("nano", num_neighbours=2)), bias)
    render = scene.render(test)
    full = (render + bias.view(3, 1, 1)).clamp(0, 1)

    exact = SceneEnhancer(scene, model, colour=False, align=False).enhance_view(test)
    assert exact.agreement > 0.8 and exact.trust == 1.0 and exact.note is None
    assert torch.equal(exact.image, full)

    wrong = scene.depth(test) * 0.5
    on = SceneEnhancer(scene, model, colour=False, align=False).enhance(render, wrong, frame.K, frame.world_from_cam)
    assert on.agreement < exact.agreement
    assert on.agreement < 0.5 and on.trust == pytest.approx(on.agreement / 0.5, abs=1e-3)
    assert torch.allclose(on.image, (render + on.trust * (full - render)), atol=2e-4)
    assert "agree on" in on.note and f"{on.trust:.0%}" in on.note
    off = SceneEnhancer(scene, model, colour=False, align=False, trust=False).enhance(
        render, wrong, frame.K, frame.world_from_cam)
    assert off.trust is None and torch.equal(off.image, full)
    strict = SceneEnhancer(scene, model, colour=False, align=False, trust=TrustConfig(full_share=1.0)).enhance(
        render, wrong, frame.K, frame.world_from_cam)
    assert strict.trust == pytest.approx(on.agreement, abs=1e-3)

    # One neighbour: nothing to compare, the change is kept whole and nothing is reported.
    one = SceneEnhancer(scene, model, colour=False, align=False, num_neighbours=1).enhance(
        render, wrong, frame.K, frame.world_from_cam)
    assert one.trust is None and one.agreement is None and torch.equal(one.image, full)

    report = evaluate(scene, model, colour=False, align=False)
    assert report["views"][0]["trust"] == exact.trust and report["views"][0]["agreement"] == exact.agreement
    with pytest.raises(InputError, match="trust"):
        SceneEnhancer(scene, model, trust="yes")
