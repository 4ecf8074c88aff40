"""Cross-fitted pairs (issue 35): every view rendered by a field that never saw its photo."""

from __future__ import annotations

import dataclasses
import json

import pytest
import torch

from roguefit import FitConfig, make_pairs, read_photo_set
from roguefit.pairs import fold_of_views
from roguenerf.data.readers import load_scene
from roguenerf.errors import InputError, TrainingCancelled
from tests.fit_helpers import VIEWS, write_photo_set

SMALL = FitConfig(resolution=32, features=0, steps=120, minutes=None, rays=1024, samples=32, prune_every=40)


def test_folds_cover_every_training_view_once_and_never_a_held_out_view(tmp_path):
    write_photo_set(tmp_path, views=VIEWS)
    ps = read_photo_set(tmp_path)
    folds = fold_of_views(ps, 3)
    train = ps.indices("train")
    assert [folds[i] for i in ps.indices("test")] == [None] * len(ps.indices("test"))
    assert sorted(folds[i] for i in train) == sorted(k % 3 for k in range(len(train)))
    for f in range(3):  # neighbouring training views fall in different folds: no fold is one end of the path
        members = [k for k, i in enumerate(train) if folds[i] == f]
        assert all(b - a == 3 for a, b in zip(members, members[1:]))


@pytest.mark.slow
def test_cross_fitted_renders_are_novel_views_and_resume_after_a_stop(tmp_path):
    root = tmp_path / "photos"
    write_photo_set(root, views=VIEWS)
    plain = make_pairs(root, tmp_path / "plain", SMALL)
    config = dataclasses.replace(SMALL, folds=3)
    calls = {"n": 0}

    def stop_in_fold_1() -> bool:  # after fold 0 (120 steps + its renders), inside fold 1
        calls["n"] += 1
        return calls["n"] == 120 + 8 + 30

    with pytest.raises(TrainingCancelled):
        make_pairs(root, tmp_path / "cross", config, should_stop=stop_in_fold_1)
    assert (tmp_path / "cross" / ".fit" / "fold0" / "renders.safetensors").is_file()
    assert json.loads((tmp_path / "cross" / ".fit" / "fold1" / "state.json").read_text())["step"] == 30
    cross = make_pairs(root, tmp_path / "cross", config)
    assert cross["folds"] == 3 and cross["steps"] == 3 * SMALL.steps
    assert cross["config"]["folds"] == 3 and "folds" not in plain["config"]
    # A field renders views it saw far better than views it did not: the cross-fitted training
    # renders carry the error of novel views, as the held-out views of the plain fit do.
    assert cross["train"]["psnr"] < plain["train"]["psnr"] - 1.0, (cross["train"], plain["train"])
    assert min(cross["fold_train_psnr"]) > cross["train"]["psnr"] + 1.0, cross
    scene = load_scene(tmp_path / "cross")
    assert len(scene.frames) == VIEWS and [f.split for f in scene.frames] == [f.split for f in
                                                                             load_scene(tmp_path / "plain").frames]
    for i in range(VIEWS):
        assert torch.isfinite(scene.depth(i)).all() and scene.render(i).std() > 0.01
    assert make_pairs(root, tmp_path / "cross", config) == cross  # a finished folder is left as it is
    # Another configuration in the same folder never reuses a finished fold's renders.
    other = make_pairs(root, tmp_path / "cross", dataclasses.replace(config, steps=60))
    assert other["steps"] == 3 * 60 and other["train"]["psnr"] != cross["train"]["psnr"]


def test_too_few_training_views_for_the_folds_is_a_clear_error(tmp_path):
    write_photo_set(tmp_path / "photos", views=9)  # 7 training views
    with pytest.raises(InputError, match="4 folds need at least 8 training views"):
        make_pairs(tmp_path / "photos", tmp_path / "out", dataclasses.replace(SMALL, folds=4))
    with pytest.raises(InputError, match="folds"):
        FitConfig(folds=0)
