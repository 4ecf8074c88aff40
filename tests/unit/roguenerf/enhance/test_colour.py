"""Colour matching to the neighbour photos (roguenerf.enhance.colour) on known answers and the
toy world's exact geometry."""

from __future__ import annotations

import pytest
import torch

from roguenerf.data.toy import make_toy_scene
from roguenerf.enhance.colour import ColourConfig, colour_match, colour_offset
from roguenerf.errors import InputError
from tests.model_helpers import Biased, textured

SHIFT = torch.tensor([0.02, -0.01, 0.03])


def test_the_offset_brings_a_shifted_image_back_to_the_neighbours():
    photo = textured(0)
    full = torch.ones(1, 1, 48, 64)
    offset = colour_offset(photo + SHIFT.view(1, 3, 1, 1), [(photo, full), (photo, full)])
    assert torch.allclose(offset, -SHIFT, atol=1e-5)
    # Three neighbours, one of which sees only the left half: the same answer.
    half = full.clone()
    half[..., 32:] = 0
    offset = colour_offset(photo + SHIFT.view(1, 3, 1, 1), [(photo, full), (photo * half, half), (photo, full)])
    assert torch.allclose(offset, -SHIFT, atol=1e-5)


def test_colour_where_a_neighbour_does_not_see_never_bleeds_in():
    photo = textured(1)
    seen = torch.zeros(1, 1, 48, 64)
    seen[..., 8:40, 8:56] = 1
    garbage = torch.where(seen > 0, photo, torch.ones_like(photo))  # white outside what it sees
    offset = colour_offset(photo + SHIFT.view(1, 3, 1, 1), [(garbage, seen), (garbage, seen)])
    assert torch.allclose(offset, -SHIFT, atol=1e-4)


def test_nothing_is_changed_without_two_agreeing_neighbours():
    photo, other = textured(2), textured(3)
    full = torch.ones(1, 1, 48, 64)
    image = photo + SHIFT.view(1, 3, 1, 1)
    assert colour_offset(image, [(photo, full)]) is None  # one neighbour: no agreement to check
    # Two neighbours that disagree everywhere (a broken field's depth lands them on other things).
    assert colour_offset(image, [(photo, full), ((photo + 0.1).clamp(0, 1), full)]) is None
    # They agree on 4 % of the pixels only, under the 5 % floor.
    little = torch.zeros_like(full)
    little[..., :2, :] = 1
    assert colour_offset(image, [(photo * little, little), (photo * little, little)]) is None
    assert colour_offset(image, [(photo * little, little), (photo * little, little)],
                         ColourConfig(min_share=0.01)) is not None
    # Blurred, two different random textures agree (their means are alike): the offset is
    # about colour, not detail.
    assert colour_offset(image, [(photo, full), (other, full)]) is not None


def test_the_field_follows_a_shift_that_varies_across_the_view():
    """The image is too bright on the left and too dark on the right (a smooth ramp): the field
    takes each side back; without a field (local_sigma 0) one median offset is all there is."""
    photo = textured(5, 64, 128)
    full = torch.ones(1, 1, 64, 128)
    ramp = torch.linspace(0.04, -0.04, 128).view(1, 1, 1, 128).expand(1, 3, 64, 128)
    match = colour_match(photo + ramp, [(photo, full), (photo, full)])
    assert match.share == 1.0
    inner = (..., slice(16, 48), slice(24, 104))  # away from the borders' replicate padding
    assert torch.allclose(match.field[inner], -ramp[inner], atol=2e-3)
    flat = colour_match(photo + ramp, [(photo, full), (photo, full)], ColourConfig(local_sigma=0))
    assert torch.allclose(flat.field, flat.offset.view(1, 3, 1, 1).expand(1, 3, 64, 128))
    assert flat.offset.abs().max() < 2e-3  # the ramp's median


def test_where_no_neighbours_agree_the_field_leans_on_the_views_offset():
    photo = textured(6, 64, 128)
    left = torch.zeros(1, 1, 64, 128)
    left[..., :80] = 1  # both see the left 62 %, none the rest
    match = colour_match(photo + SHIFT.view(1, 3, 1, 1), [(photo * left, left), (photo * left, left)])
    assert match.share == pytest.approx(80 / 128)
    assert torch.allclose(match.offset, -SHIFT, atol=1e-5)
    # Far from anything seen the field is the offset; inside, the local measure, the same here.
    assert torch.allclose(match.field[..., 120:], -SHIFT.view(1, 3, 1, 1).expand(1, 3, 64, 8), atol=1e-4)
    assert torch.allclose(match.field[..., 8:60], -SHIFT.view(1, 3, 1, 1).expand(1, 3, 64, 52), atol=5e-4)


@pytest.mark.parametrize("bad", [dict(sigma=0), dict(max_disagreement=-1), dict(min_share=2.0),
                                 dict(min_share=float("nan")), dict(local_sigma=-1), dict(local_support=0)])
def test_the_config_is_checked(bad):
    with pytest.raises(InputError, match="ColourConfig"):
        ColourConfig(**bad)


def test_shapes_are_checked():
    photo = textured(4)
    full = torch.ones(1, 1, 48, 64)
    with pytest.raises(InputError, match="image"):
        colour_offset(photo[0], [(photo, full), (photo, full)])
    with pytest.raises(InputError, match="neighbours"):
        colour_offset(photo, [(photo[..., :32], full), (photo, full)])


def test_the_scene_enhancer_takes_a_colour_bias_back_out(tmp_path):
    """On the toy world (exact geometry, the photos' own colour), a model that brightens every
    pixel by 0.04 is brought back to the render's colour; ``colour=False`` keeps the bias."""
    from roguenerf.enhance import EnhanceOptions
    from roguenerf.inference import SceneEnhancer
    from roguenerf.models import Enhancer, make_config
    from roguenerf.training import evaluate

    scene = make_toy_scene(tmp_path / "scene", n_train=6, n_test=1, height=72, width=96)
    test = scene.indices("test")[0]
    bias = torch.tensor([0.04, 0.04, 0.04])
    model = Biased(Enhancer(make_config("nano", num_neighbours=2)), bias)
    render = scene.render(test)
    on = SceneEnhancer(scene, model).enhance_view(test)
    off = SceneEnhancer(scene, model, colour=False).enhance_view(test)
    assert off.colour_offset is None
    assert torch.allclose(off.image, (render + bias.view(3, 1, 1)).clamp(0, 1))
    assert len(on.colour_offset) == 3
    assert torch.allclose(torch.tensor(on.colour_offset), -bias, atol=0.01)
    assert (on.image - render).abs().mean() < 0.01  # everywhere, not just on average
    assert (on.image - render).mean().abs() < 0.01 < (off.image - render).mean().abs()
    report = evaluate(scene, model)
    assert report["views"][0]["colour_offset"] == on.colour_offset
    plain = evaluate(scene, model, options=EnhanceOptions(colour=None))
    assert report["enhanced"]["psnr"] > plain["enhanced"]["psnr"] + 3
    with pytest.raises(InputError, match="colour"):
        SceneEnhancer(scene, model, colour="yes")


def test_values_where_a_neighbour_does_not_see_are_ignored_even_nan():
    photo = textured(4)
    seen = torch.zeros(1, 1, 48, 64)
    seen[..., 4:44, 6:58] = 1
    image = photo + SHIFT.view(1, 3, 1, 1)
    zeros = torch.where(seen > 0, photo, torch.zeros_like(photo))
    nan = torch.where(seen > 0, photo, torch.full_like(photo, float("nan")))  # NaN × 0 must not spread
    want = colour_match(image, [(zeros, seen), (zeros, seen)])
    got = colour_match(image, [(nan, seen), (zeros, seen)])
    assert want is not None and got is not None
    assert torch.allclose(want.offset, -SHIFT, atol=1e-4)
    assert torch.equal(got.offset, want.offset) and torch.equal(got.field, want.field)
    assert got.share == want.share
