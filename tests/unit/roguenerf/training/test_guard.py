"""The fine-tune guard: weights judged on training views drawn like novel views; a fine-tune that
does worse there leaves the starting weights in the output checkpoint (the state keeps its own)."""

from __future__ import annotations

import pytest
import torch
from typer.testing import CliRunner

from roguecli import app
from roguenerf.checkpoint import default_checkpoint_path, load_checkpoint, save_checkpoint
from roguenerf.data.degrade import Degradation
from roguenerf.data.toy import make_toy_scene
from roguenerf.models import build_enhancer
from roguenerf.training import TrainConfig, finetune
from roguenerf.training import guard as guard_module
from roguenerf.training.guard import GuardReport, guard_positions, judge
from roguenerf.training.loop import MODEL_FILE, START_FILE, STATE_FILE, SceneData, check_training_output
from roguenerf.training.state import load_state

FAST = dict(steps=2, crop=16, batch=2, checkpoint_every_s=1e9, evaluate=False, progress_bar=False, guard=True)


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    # blurred renders the shipped model sharpens from its sharp neighbours
    return make_toy_scene(tmp_path_factory.mktemp("guard"), seed=3, n_train=8, n_test=1, height=48, width=64,
                          degradation=Degradation(), kind="orbit")


@pytest.fixture(scope="module")
def shipped():
    return load_checkpoint(default_checkpoint_path())[0]


def test_the_guard_keeps_weights_that_enhance_drawn_views_better_and_refuses_worse_ones(scene, shipped):
    data = SceneData(scene, 0)
    assert guard_positions(data) == list(range(8)) and guard_positions(data, 3) == [0, 2, 4]
    identity = build_enhancer(shipped.config)  # a fresh enhancer changes nothing but what the stages do
    better = judge(data, identity, shipped)
    assert better.kept and better.views == [scene.frames[i].name for i in data.train]
    assert better.tuned_mean > better.start_mean + 0.3 and 0.3 < better.drawn_share < 1.0
    worse = judge(data, shipped, identity)
    assert not worse.kept
    assert worse.start_db == pytest.approx(better.tuned_db, abs=1e-6)  # the same views, the same measure
    assert GuardReport().kept and judge(SceneData(scene, 0), shipped, identity, count=0).views == []


def _weights(model) -> dict:
    return {k: v.detach().clone() for k, v in model.state_dict().items()}


def test_a_refused_fine_tune_leaves_the_starting_weights_and_the_state_keeps_its_own(scene, shipped, tmp_path,
                                                                                      monkeypatch):
    refusal = GuardReport(views=["v"], start_db=[0.5], tuned_db=[0.25], kept=False)
    monkeypatch.setattr(guard_module, "judge", lambda data, start, tuned, **kw: refusal)
    out = tmp_path / "refused"
    result = finetune(scene, out, checkpoint=default_checkpoint_path(), config=TrainConfig(**FAST))
    assert result.guard["kept"] is False and result.guard["tuned_mean_db"] == 0.25
    kept, meta = load_checkpoint(result.checkpoint)
    start, _ = load_checkpoint(out / START_FILE)
    assert all(torch.equal(a, b) for a, b in zip(_weights(kept).values(), _weights(shipped).values(), strict=True))
    assert all(torch.equal(a, b) for a, b in zip(_weights(start).values(), _weights(shipped).values(), strict=True))
    assert meta["training"]["guard"]["kept"] is False and meta["training"]["steps"] == 2
    tuned = load_state(out / STATE_FILE)["model"]
    assert any(not torch.equal(tuned[k], v) for k, v in _weights(shipped).items())
    # Resumed for two more steps from the fine-tuned state, judged again (now kept).
    monkeypatch.setattr(guard_module, "judge", lambda data, start, tuned, **kw: GuardReport(
        views=["v"], start_db=[0.5], tuned_db=[0.75], kept=True))
    again = finetune(scene, out, checkpoint=default_checkpoint_path(), config=TrainConfig(**{**FAST, "steps": 4}))
    assert again.steps == 4 and again.guard["kept"] is True
    final, _ = load_checkpoint(again.checkpoint)
    assert all(torch.equal(final.state_dict()[k], v) for k, v in load_state(out / STATE_FILE)["model"].items())


def test_without_the_guard_nothing_is_judged_and_with_it_the_cli_says_what_it_decided(scene, tmp_path, monkeypatch):
    def never(*args, **kwargs):
        raise AssertionError("judged")

    monkeypatch.setattr(guard_module, "judge", never)
    result = finetune(scene, tmp_path / "off", checkpoint=default_checkpoint_path(),
                      config=TrainConfig(**{**FAST, "guard": False}))
    assert result.guard is None and not TrainConfig().guard  # off by default
    monkeypatch.setattr(guard_module, "judge", lambda data, start, tuned, **kw: GuardReport(
        views=["a", "b"], start_db=[0.5, 0.5], tuned_db=[0.0, 0.25], kept=False))
    r = CliRunner().invoke(app, ["finetune", str(scene.root), "--output", str(tmp_path / "cli"), "--steps", "1",
                                 "--crop", "16", "--no-eval", "--guard"])
    assert r.exit_code == 0, r.output
    assert "fine-tuned weights not kept" in r.output and "+0.12 dB, the starting weights +0.50 dB" in r.output
    r = CliRunner().invoke(app, ["finetune", str(scene.root), "--output", str(tmp_path / "cli_off"), "--steps", "1",
                                 "--crop", "16", "--no-eval"])
    assert r.exit_code == 0, r.output
    assert "fine-tuned weights" not in r.output


def test_a_fine_tune_stopped_before_its_first_save_can_be_started_again(tmp_path, shipped):
    out = tmp_path / "run"
    save_checkpoint(out / START_FILE, shipped)
    check_training_output(out)  # only its starting weights: ours
    (out / "notes.txt").write_text("x")
    check_training_output(out)
    other = tmp_path / "other"
    other.mkdir()
    (other / "notes.txt").write_text("x")
    with pytest.raises(Exception, match="not empty"):
        check_training_output(other)
    assert not (out / MODEL_FILE).exists()
