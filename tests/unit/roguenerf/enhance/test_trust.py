"""Trusting the neighbours by their agreement (roguenerf.enhance.trust): known answers, and on
the toy world with exact and with wrong geometry."""

from __future__ import annotations

import pytest
import torch

from roguenerf.data.toy import make_toy_scene
from roguenerf.enhance.colour import neighbour_agreement
from roguenerf.enhance.trust import TrustConfig, kept_change, trust_factor
from roguenerf.errors import InputError
from tests.model_helpers import Biased, textured


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
                                 {"sigma": -1}, {"max_disagreement": 0}, {"local_below": -0.1},
                                 {"local_below": 1.5}, {"local_sigma": 0}])
def test_the_config_is_checked(bad):
    with pytest.raises(InputError, match="TrustConfig"):
        TrustConfig(**bad)


def test_where_almost_nothing_agrees_the_change_is_kept_only_where_neighbours_agree_nearby():
    size = (96, 128)
    # Half the view agrees: one share for the whole view, 1 (at full_share 0.5).
    half = torch.zeros(1, 48, 64, dtype=torch.bool)
    half[..., :32] = True
    assert kept_change(half, size) == 1.0
    # A quarter: half the change, everywhere (above local_below).
    quarter = torch.zeros(1, 48, 64, dtype=torch.bool)
    quarter[..., :16] = True
    assert kept_change(quarter, size) == pytest.approx(0.5)
    # A 6 x 8 patch (1.6 %): under local_below, so per pixel. Far from the patch nothing is kept;
    # at its centre, the agreement within a Gaussian of 2 px around it over full_share: all of it.
    patch = torch.zeros(1, 48, 64, dtype=torch.bool)
    patch[..., 20:26, 40:48] = True
    keep = kept_change(patch, size, TrustConfig(local_sigma=2.0))
    assert isinstance(keep, torch.Tensor) and keep.shape == (1, 96, 128)
    assert float(keep.min()) >= 0 and float(keep.max()) <= 1
    assert float(keep[0, :20, :40].max()) < 1e-3 and float(keep[0, 80:, :].max()) < 1e-3
    assert float(keep[0, 46, 88]) == pytest.approx(1.0, abs=0.02)  # the patch's centre, doubled
    # With the default reach (16 px) the kept change is spread around the patch; its mean is
    # about the agreement's share over full_share (a blur keeps the total, less what spills past
    # the image's edge: this reach is wider than the 48 x 64 copy).
    wide = kept_change(patch, size)
    assert 0.6 * (48 / 3072 / 0.5) < float(wide.mean()) < 48 / 3072 / 0.5
    assert float(wide[0, 46, 88]) < 0.5  # too little agreement around it to keep it whole
    # local_below 0: one share for the view, as before.
    assert kept_change(patch, size, TrustConfig(local_below=0)) == pytest.approx(48 / 3072 / 0.5)
    # Nothing agrees: nothing kept.
    none = kept_change(torch.zeros(1, 48, 64, dtype=torch.bool), size)
    assert float(none.abs().max()) == 0
    with pytest.raises(InputError, match="agree"):
        kept_change(torch.zeros(48, 64, dtype=torch.bool), size)


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
    from roguenerf.enhance import EnhanceOptions
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
    # Per pixel (every share under local_below): the change is kept where the neighbours agree
    # nearby, so unevenly, and the share reported is its mean.
    local = SceneEnhancer(scene, model, colour=False, align=False, trust=TrustConfig(local_below=1.0)).enhance(
        render, wrong, frame.K, frame.world_from_cam)
    kept = ((local.image - render) / (full - render).clamp_min(1e-6))[:, (full - render).amin(0) > 0.03]
    assert float(kept.max()) - float(kept.min()) > 0.2
    assert local.trust == pytest.approx(float(kept.mean()), abs=0.02) and 0 < local.trust < 1
    assert "where they agree" in local.note

    # One neighbour: nothing to compare, the change is kept whole and nothing is reported.
    one = SceneEnhancer(scene, model, colour=False, align=False, num_neighbours=1).enhance(
        render, wrong, frame.K, frame.world_from_cam)
    assert one.trust is None and one.agreement is None and torch.equal(one.image, full)

    report = evaluate(scene, model, options=EnhanceOptions(colour=None, align=None))
    assert report["views"][0]["trust"] == exact.trust and report["views"][0]["agreement"] == exact.agreement
    with pytest.raises(InputError, match="trust"):
        SceneEnhancer(scene, model, trust="yes")


def test_the_public_helpers_check_their_arguments_as_the_config_does():
    from roguenerf.enhance.trust import local_keep

    patch = torch.zeros(1, 12, 16, dtype=torch.bool)
    patch[..., 4:8, 6:10] = True
    for sigma in (float("nan"), float("inf"), 0.0, -2.0):
        with pytest.raises(InputError) as err:
            local_keep(patch, (24, 32), sigma, 0.5)
        assert str(err.value) == f"sigma: expected a positive number, got {sigma!r}"
    for full_share in (float("nan"), 0.0, 1.5):
        with pytest.raises(InputError) as err:
            local_keep(patch, (24, 32), 2.0, full_share)
        assert str(err.value) == f"full_share: expected a share in (0, 1], got {full_share!r}"
    for size in ((), (0, 32), (24,), (24, -1), (24.5, 32)):
        with pytest.raises(InputError) as err:
            kept_change(patch, size)
        assert str(err.value) == f"size: expected (H, W), two integers >= 1, got {size!r}"
        with pytest.raises(InputError):
            local_keep(patch, size, 2.0, 0.5)
    keep = local_keep(patch, (24, 32), 2.0, 0.5)
    assert keep.shape == (1, 24, 32) and float(keep[0, :, :4].max()) < 0.05 and float(keep.max()) > 0.8
    assert torch.equal(keep, kept_change(patch, (24, 32), TrustConfig(local_sigma=2.0)))  # 8 %: per pixel
