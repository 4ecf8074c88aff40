"""The enhancement pipeline's options (roguenerf.enhance): one object for the neighbour rule and
the stages, its fingerprint, and the stages recorded in what the enhancer returns."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from roguenerf.data.toy import make_toy_scene
from roguenerf.enhance import EnhanceOptions, NeighbourRule
from roguenerf.enhance.align import AlignConfig
from roguenerf.enhance.colour import ColourConfig
from roguenerf.enhance.trust import TrustConfig
from roguenerf.errors import InputError


def test_the_defaults_are_every_stage_on_and_the_models_count_plus_a_near_one():
    options = EnhanceOptions()
    assert options == EnhanceOptions.from_flags()
    assert (options.align, options.colour, options.trust) == (AlignConfig(), ColourConfig(), TrustConfig())
    assert options.neighbours.counts(2) == (2, 1)  # the model's 2, plus one within 4 degrees
    assert options.neighbours.counts(0) == (0, 0)
    assert EnhanceOptions.from_flags(neighbours=3).neighbours.counts(2) == (3, 0)  # exactly 3
    assert EnhanceOptions.from_flags(neighbours=np.int64(4)).neighbours.count == 4
    assert EnhanceOptions.from_flags(neighbours=3.0, tile=64.0).tile == 64
    off = EnhanceOptions.from_flags(align=False, colour=False, trust=False, temporal=False)
    assert (off.align, off.colour, off.trust, off.temporal) == (None, None, None, None)
    assert off.describe() == "model's count + 1 within 4 deg; stages: none"
    assert EnhanceOptions(trust=False).trust is None and EnhanceOptions(colour=True).colour == ColourConfig()


def test_the_tile_is_chosen_by_the_device_unless_given():
    from roguenerf.enhance.options import DEFAULT_TILE, DEVICE_TILE, tile_for

    assert EnhanceOptions().tile is None and EnhanceOptions.from_flags().tile is None
    assert tile_for(None, "cpu") == DEFAULT_TILE == 512
    assert tile_for(None, torch.device("cuda", 0)) == tile_for(None, "mps") == DEVICE_TILE == 2048
    assert tile_for(96, "cuda") == 96 and tile_for(4096, torch.device("cpu")) == 4096
    with pytest.raises(InputError, match="tile"):
        EnhanceOptions(tile=8)


@pytest.mark.parametrize(("make", "message"), [
    (lambda: EnhanceOptions.from_flags(neighbours=-1), "num_neighbours: expected >= 0, got -1"),
    (lambda: EnhanceOptions.from_flags(neighbours=2.5), "num_neighbours: expected >= 0, got 2.5"),
    (lambda: EnhanceOptions.from_flags(neighbours=True), "num_neighbours: expected >= 0, got True"),
    (lambda: EnhanceOptions.from_flags(tile=8), "tile: expected >= 16 pixels, got 8"),
    (lambda: EnhanceOptions(colour="yes"), "colour: expected True, False or a ColourConfig, got str"),
    (lambda: EnhanceOptions(align=TrustConfig()), "align: expected True, False or a AlignConfig, got TrustConfig"),
    (lambda: EnhanceOptions(neighbours=3), "neighbours: expected a NeighbourRule, got int"),
    (lambda: NeighbourRule(near_degrees=float("nan")), "near_degrees"),
    (lambda: NeighbourRule(near_extra=-1), "near_extra"),
])
def test_bad_options_are_refused_with_the_argument_named(make, message):
    with pytest.raises(InputError, match=message.replace("(", r"\(").replace(")", r"\)")):
        make()


def test_the_fingerprint_is_plain_json_and_changes_with_every_setting():
    base = EnhanceOptions().fingerprint()
    assert json.loads(json.dumps(base)) == base
    assert base["colour"]["local_sigma"] == 3.0 and base["neighbours"]["count"] is None
    assert set(base["neighbours"]) == {"count", "near_extra", "near_degrees", "measured", "candidates", "least",
                                       "most", "min_coverage", "error_ratio"}
    changed = [EnhanceOptions.from_flags(neighbours=3), EnhanceOptions(colour=ColourConfig(local_sigma=2.0)),
               EnhanceOptions(trust=None), EnhanceOptions(align=None), EnhanceOptions(tile=256),
               EnhanceOptions(neighbours=NeighbourRule(near_degrees=5.0)),
               EnhanceOptions(neighbours=NeighbourRule(measured=not NeighbourRule().measured)),
               EnhanceOptions(neighbours=NeighbourRule(error_ratio=1.5))]
    prints = [json.dumps(o.fingerprint(), sort_keys=True) for o in changed]
    assert len(set(prints)) == len(prints) and json.dumps(base, sort_keys=True) not in prints
    assert EnhanceOptions().fingerprint() == base  # equal options, equal fingerprints


def test_the_enhancer_takes_one_options_object_and_records_its_stages(tmp_path):
    from roguenerf.inference import SceneEnhancer
    from roguenerf.models import Enhancer, make_config

    scene = make_toy_scene(tmp_path / "scene", n_train=6, n_test=1, height=72, width=96)
    test = scene.indices("test")[0]
    model = Enhancer(make_config("nano", num_neighbours=2))
    with pytest.raises(InputError, match="align: give them in options"):
        SceneEnhancer(scene, model, options=EnhanceOptions(), align=False)
    with pytest.raises(InputError, match="options: expected an EnhanceOptions, got dict"):
        SceneEnhancer(scene, model, options={"align": False})
    full = SceneEnhancer(scene, model, options=EnhanceOptions()).enhance_view(test)
    assert [s.name for s in full.stages] == ["colour", "trust"]
    by_name = {s.name: s for s in full.stages}
    assert by_name["trust"].detail == {"kept": full.trust} and full.trust == 1.0 and not by_name["trust"].applied
    assert by_name["colour"].applied and by_name["colour"].detail["offset"] == full.colour_offset
    assert len(full.colour_offset) == 3 and full.agreement > 0.5
    shortcut = SceneEnhancer(scene, model, colour=False).enhance_view(test)
    explicit = SceneEnhancer(scene, model, options=EnhanceOptions(colour=None)).enhance_view(test)
    assert [s.name for s in explicit.stages] == ["trust"] and explicit.colour_offset is None
    assert torch.equal(shortcut.image, explicit.image)
    none = SceneEnhancer(scene, model, options=EnhanceOptions.from_flags(colour=False, trust=False)).enhance_view(test)
    assert none.stages == [] and none.agreement is None and none.trust is None
