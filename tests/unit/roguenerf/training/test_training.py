"""Fine-tuning / pre-training loops: smoke runs, resume, divergence, cancellation, VGG loss,
ablation weight transfer, the per-machine plan, and evaluate's numbers."""

from __future__ import annotations

import json
import math

import pytest
import torch

from roguenerf.checkpoint import load_checkpoint, save_checkpoint
from roguenerf.data.degrade import Degradation
from roguenerf.data.toy import make_toy_scene
from roguenerf.errors import InputError, TrainingCancelled, TrainingDivergedError
from roguenerf.models import build_enhancer
from roguenerf.training import (
    MODEL_FILE,
    STATE_FILE,
    TrainConfig,
    evaluate,
    finetune,
    plan_training,
    pretrain,
)
from roguenerf.training.config import FREEZE_NEIGHBOUR_ENCODER
from roguenerf.training.loop import SceneData, _crop_batch
from roguenerf.training.losses import EnhancerLoss, VGG19Features, _vgg19_layers, build_loss
from roguenerf.training.state import load_state

FAST = dict(crop=16, batch=2, variant="micro", checkpoint_every_s=0.0, evaluate=False, progress_bar=False,
            num_neighbours=2)


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return make_toy_scene(tmp_path_factory.mktemp("toy"), seed=1, n_train=5, n_test=2, height=24, width=32,
                          degradation=Degradation())


@pytest.fixture(scope="module")
def other_scene(tmp_path_factory):
    return make_toy_scene(tmp_path_factory.mktemp("toy2"), seed=2, n_train=4, n_test=0, height=20, width=28)


def _params(model) -> dict:
    return {k: v.clone() for k, v in model.state_dict().items()}


def test_finetune_smoke_two_steps(scene, tmp_path):
    seen = []
    result = finetune(scene, tmp_path, config=TrainConfig(steps=2, **FAST), progress=seen.append)
    assert result.steps == 2 and [p.step for p in seen] == [1, 2]
    assert seen[-1].fraction == 1.0 and seen[-1].total_steps == 2 and seen[-1].eta_s == 0.0
    assert math.isfinite(result.final_loss) and result.final_loss > 0
    assert result.loss_kind == "l1"
    assert result.checkpoint == tmp_path / MODEL_FILE
    model, meta = load_checkpoint(result.checkpoint)
    assert model.config.variant == "micro" and model.config.num_neighbours == 2
    assert meta["training"]["steps"] == 2 and meta["training"]["loss_kind"] == "l1"
    assert result.config["crop_used"] == 16 and result.config["batch"] == 2
    # the weights moved away from the identity-initialised start
    fresh = build_enhancer("micro")
    moved = any(not torch.equal(a, b) for a, b in zip(model.state_dict().values(), fresh.state_dict().values()))
    assert moved


def test_finetune_reports_before_and_after(scene, tmp_path, monkeypatch):
    from roguenerf.enhance import EnhanceOptions
    from roguenerf.training import loop

    plain = loop.evaluate  # the model's own output, not colour-matched
    no_colour = EnhanceOptions(colour=None)
    monkeypatch.setattr(loop, "evaluate", lambda scene, model, **kw: plain(scene, model, options=no_colour, **kw))
    result = finetune(scene, tmp_path, config=TrainConfig(steps=1, **{**FAST, "evaluate": True}))
    assert set(result.before) == {"render", "enhanced"} and set(result.after) == {"render", "enhanced"}
    assert result.before["render"] == result.after["render"]  # the renders do not change
    # a fresh enhancer is the identity: before fine-tuning, enhanced == render
    assert result.before["enhanced"]["psnr"] == pytest.approx(result.before["render"]["psnr"], abs=1e-3)


def test_pretrain_over_scenes_of_different_sizes(scene, other_scene, tmp_path):
    result = pretrain([scene, other_scene], tmp_path, config=TrainConfig(steps=3, **FAST))
    assert result.steps == 3 and result.before is None and result.after is None
    _, meta = load_checkpoint(result.checkpoint)
    assert meta["training"]["kind"] == "pretrain" and len(meta["training"]["scenes"]) == 2


def test_held_out_targets_take_training_view_neighbours(scene):
    from roguenerf.geometry import select_neighbours

    data = SceneData(scene, 2, held_out=True)
    train, test = scene.indices("train"), scene.indices("test")
    assert len(data) == len(train) == 5 and data.held_out == list(test) and data.photos.shape[0] == 7
    assert torch.equal(data.photos[5], scene.photo(test[0])) and torch.equal(data.renders[6], scene.render(test[1]))
    train_poses = scene.poses(train).double()
    for k, view in enumerate(test):
        expected = select_neighbours(scene.poses([view])[0].double(), train_poses, 2)
        assert torch.equal(data.neighbours[5 + k], expected)
        assert int(data.neighbours[5 + k].max()) < 5  # a held-out view never serves as a neighbour
    assert torch.equal(data.neighbours[:5], SceneData(scene, 2).neighbours)


@pytest.mark.parametrize("share", [0.0, 0.25, 1.0])
def test_draw_targets_takes_held_out_views_at_the_share(scene, share):
    data = SceneData(scene, 2, held_out=True)
    drawn = data.draw_targets(4000, torch.Generator().manual_seed(0), share)
    held = drawn >= 5
    assert drawn.min() >= 0 and drawn.max() < 7
    assert float(held.float().mean()) == pytest.approx(share, abs=0.03)
    if 0 < share:
        assert set(drawn[held].tolist()) == {5, 6}
    # without held-out views the share changes nothing, not even the random stream
    plain = SceneData(scene, 2)
    g1, g2 = torch.Generator().manual_seed(3), torch.Generator().manual_seed(3)
    assert torch.equal(plain.draw_targets(50, g1, share), torch.randint(0, 5, (50,), generator=g2))


def test_pretrain_trains_on_held_out_views_of_the_scenes_named(scene, other_scene, tmp_path, monkeypatch):
    import roguenerf.training.loop as loop

    seen = []
    original = loop.prepare_batch

    def spy(data, targets, *args, **kwargs):
        seen.append((data.scene.root, targets.tolist()))
        return original(data, targets, *args, **kwargs)

    monkeypatch.setattr(loop, "prepare_batch", spy)
    config = TrainConfig(steps=6, held_out_share=1.0, **FAST)
    result = pretrain([other_scene, scene], tmp_path, config=config, held_out_scenes=[1])
    assert result.config["held_out_share"] == 1.0 and "held-out views 100%" in loop.describe_plan(result.config)
    by_scene = {root: [t for r, ts in seen if r == root for t in ts] for root, _ in seen}
    assert set(by_scene) == {scene.root, other_scene.root}  # both scenes were drawn in 6+ batches
    assert all(t >= 5 for t in by_scene[scene.root])  # share 1: held-out views only
    assert all(t < 4 for t in by_scene[other_scene.root])  # not named: training views only
    assert pretrain([scene], tmp_path / "plain", config=TrainConfig(steps=1, **FAST)).config["held_out_share"] == 0.0


@pytest.mark.parametrize("held, message", [([2], "positions in 0..1"), ([0], "no held-out views")])
def test_pretrain_refuses_bad_held_out_scenes(scene, other_scene, tmp_path, held, message):
    with pytest.raises(InputError, match=message):
        pretrain([other_scene, scene], tmp_path, config=TrainConfig(steps=1, **FAST), held_out_scenes=held)


def test_the_printed_plan_says_why(scene):
    from roguenerf.training.config import describe_plan

    cpu = describe_plan(plan_training(scene, TrainConfig(), "cpu"))
    assert "2 neighbours" in cpu and "chosen by measured gain after 1, 3 and 10 min" in cpu
    assert "the paper's" in describe_plan(plan_training(scene, TrainConfig(), "cuda"))


@pytest.mark.parametrize("field,value", [("render_warp", -1.0), ("render_warp", 100.0),
                                         ("neighbour_renders", -0.1), ("neighbour_renders", 1.5)])
def test_render_augmentation_must_be_in_range(field, value):
    with pytest.raises(InputError, match=field):
        TrainConfig(**{field: value}).validate()


@pytest.mark.parametrize("field,value,described", [("render_warp", 3.0, "warped (up to 3 px)"),
                                                   ("neighbour_renders", 0.5, "50% of the target renders drawn")])
def test_render_augmentation_is_planned_saved_and_resumed(scene, tmp_path, field, value, described):
    from roguenerf.training.config import describe_plan

    config = TrainConfig(steps=1, **{field: value}, **FAST)
    plan = plan_training(scene, config, "cpu")
    assert getattr(plan, field) == value and described in describe_plan(plan)
    assert getattr(plan_training(scene, TrainConfig(), "cpu", kind="pretrain"), field) == 0.0
    finetune(scene, tmp_path, config=config)
    # resumed with other wishes: the saved run keeps its own augmentation
    resumed = finetune(scene, tmp_path, config=TrainConfig(**{**FAST, "steps": 2}))
    assert resumed.steps == 2
    saved = load_state(tmp_path / STATE_FILE)["info"]["plan"]
    assert saved[field] == value


def test_training_views_drawn_from_their_nearest_view(scene):
    """Each training view drawn from its nearest other training view's render (a forward warp
    through that view's depth): on the toy scene, whose renders are its photos degraded, the
    drawn views differ from the views' own renders but land on the same image (closer to the
    view's photo than to any other training view's), and hold the view's own render where
    nothing lands."""
    from roguenerf.geometry import select_neighbours
    from roguenerf.metrics import psnr

    data = SceneData(scene, 2, held_out=True)
    share = data.draw_from_neighbours()
    m = len(data.train)
    assert data.drawn_renders.shape == (m, 3, data.height, data.width) and data.drawn_depths.shape[1] == 1
    assert 0.3 < share <= 1.0
    for k in range(m):
        s = int(select_neighbours(data.poses[k], data.poses[:m], 1, exclude=k)[0])
        assert not torch.equal(data.drawn_renders[k], data.renders[k])
        own = float(psnr(data.drawn_renders[k][None], data.photos[k][None]))
        assert own > float(psnr(data.drawn_renders[k][None], data.photos[s][None]))  # the view's image, not s's


def test_drawn_crops_come_from_the_drawn_renders(scene):
    from roguenerf.training.batches import prepare_batch

    data = SceneData(scene, 2)
    data.draw_from_neighbours()
    targets, origins = torch.tensor([0, 1, 2]), torch.tensor([[0, 0], [4, 8], [8, 16]])
    drawn = torch.tensor([True, False, True])
    batch = prepare_batch(data, targets, origins, 16, drawn=drawn)
    plain = prepare_batch(data, targets, origins, 16)
    for b, (t, (y, x)) in enumerate(zip(targets.tolist(), origins.tolist())):
        source = (data.drawn_renders, data.drawn_depths) if drawn[b] else (data.renders, data.depths)
        assert torch.equal(batch.render[b], source[0][t, :, y:y + 16, x:x + 16])
        assert torch.equal(batch.depth[b], source[1][t, :, y:y + 16, x:x + 16])
        assert torch.equal(batch.photo[b], plain.photo[b])  # the target stays the view's photo


def test_depth_noise_is_validated_planned_described_and_resumed(scene, tmp_path):
    from roguenerf.training.config import describe_plan

    for bad in (-0.1, 5.0):
        with pytest.raises(InputError, match="depth_noise"):
            TrainConfig(depth_noise=bad).validate()
    assert plan_training(scene, TrainConfig(), "cpu", kind="pretrain").depth_noise == 0.0
    config = TrainConfig(steps=1, depth_noise=0.3, **FAST)
    plan = plan_training(scene, config, "cpu", kind="pretrain")
    assert plan.depth_noise == 0.3 and "target depths off by a smooth error up to x1.35" in describe_plan(plan)
    finetune(scene, tmp_path, config=config)
    resumed = finetune(scene, tmp_path, config=TrainConfig(**{**FAST, "steps": 2}))
    assert resumed.steps == 2 and load_state(tmp_path / STATE_FILE)["info"]["plan"]["depth_noise"] == 0.3


def test_held_out_share_must_be_a_probability():
    with pytest.raises(InputError, match="held_out_share"):
        TrainConfig(held_out_share=1.5).validate()


@pytest.mark.slow
def test_resume_continues_from_the_saved_step(scene, tmp_path):
    config = TrainConfig(steps=4, **FAST)
    reference = finetune(scene, tmp_path / "straight", config=config)

    calls = {"n": 0}

    def stop_after_two():
        calls["n"] += 1
        return calls["n"] > 2  # polled before steps 1, 2, 3: stop before the third

    with pytest.raises(TrainingCancelled) as info:
        finetune(scene, tmp_path / "run", config=config, should_stop=stop_after_two)
    assert info.value.step == 2
    assert load_state(tmp_path / "run" / STATE_FILE)["step"] == 2

    seen = []
    resumed = finetune(scene, tmp_path / "run", config=config, progress=seen.append)
    assert [p.step for p in seen] == [3, 4]
    assert resumed.steps == 4
    # Adam state, RNG state and crops all resumed: the same weights as the uninterrupted run.
    a, _ = load_checkpoint(reference.checkpoint)
    b, _ = load_checkpoint(resumed.checkpoint)
    for (name, x), y in zip(a.state_dict().items(), b.state_dict().values()):
        torch.testing.assert_close(x, y, atol=1e-6, rtol=1e-5, msg=name)


def test_cosine_schedule_values():
    from roguenerf.training.config import budget_fraction, lr_factor

    assert lr_factor("cosine", 0.0) == 1.0 and lr_factor("cosine", 1.0) == pytest.approx(0.0, abs=1e-12)
    assert lr_factor("cosine", 0.5) == pytest.approx(0.5) and lr_factor("cosine", 0.25) == pytest.approx(0.8535534)
    assert lr_factor("cosine", 2.0) == pytest.approx(0.0, abs=1e-12)  # past the budget: stays at 0
    assert lr_factor("constant", 0.7) == 1.0
    assert budget_fraction({"steps": 8, "minutes": None}, 2, 999.0) == 0.25
    assert budget_fraction({"steps": None, "minutes": 2.0}, 50, 30.0) == 0.25
    assert budget_fraction({"steps": 10, "minutes": 1.0}, 2, 45.0) == 0.75  # the budget that runs out first
    with pytest.raises(InputError, match="lr_schedule"):
        TrainConfig(lr_schedule="step").validate()


@pytest.mark.slow
def test_the_lr_follows_the_schedule_and_resumes_in_place(scene, tmp_path):
    config = TrainConfig(steps=4, lr=1e-3, lr_schedule="cosine", **FAST)
    seen = []
    finetune(scene, tmp_path / "straight", config=config, progress=seen.append)
    # step k (0-based) runs at lr * 0.5 (1 + cos(pi k / 4))
    assert [p.lr for p in seen] == pytest.approx([1e-3, 0.8535534e-3, 0.5e-3, 0.1464466e-3])
    calls = {"n": 0}

    def stop_after_two():
        calls["n"] += 1
        return calls["n"] > 2

    with pytest.raises(TrainingCancelled):
        finetune(scene, tmp_path / "run", config=config, should_stop=stop_after_two)
    resumed = []
    # resumed with another schedule asked for: the saved run keeps its own
    finetune(scene, tmp_path / "run", config=TrainConfig(steps=4, lr=1e-3, lr_schedule="constant", **FAST),
             progress=resumed.append)
    assert [p.lr for p in resumed] == pytest.approx([p.lr for p in seen[2:]])
    constant = []
    finetune(scene, tmp_path / "constant", config=TrainConfig(steps=2, lr=1e-3, lr_schedule="constant", **FAST),
             progress=constant.append)
    assert [p.lr for p in constant] == [1e-3, 1e-3]


def test_resume_false_starts_over(scene, tmp_path):
    finetune(scene, tmp_path, config=TrainConfig(steps=2, **FAST))
    seen = []
    finetune(scene, tmp_path, config=TrainConfig(steps=1, **FAST), progress=seen.append, resume=False)
    assert [p.step for p in seen] == [1]


def test_divergence_raises_with_step_and_keeps_last_good_checkpoint(scene, tmp_path, monkeypatch):
    real_forward = EnhancerLoss.forward
    calls = {"n": 0}

    def nan_on_third(self, output, target):
        calls["n"] += 1
        loss = real_forward(self, output, target)
        return loss * math.nan if calls["n"] == 3 else loss

    monkeypatch.setattr(EnhancerLoss, "forward", nan_on_third)
    with pytest.raises(TrainingDivergedError) as info:
        finetune(scene, tmp_path, config=TrainConfig(steps=5, **FAST))
    assert info.value.step == 3
    assert info.value.checkpoint == str(tmp_path / MODEL_FILE)
    model, meta = load_checkpoint(tmp_path / MODEL_FILE)
    assert meta["training"]["steps"] == 2
    assert all(torch.isfinite(v).all() for v in model.state_dict().values() if v.is_floating_point())


def test_cancel_saves_state_and_raises(scene, tmp_path):
    with pytest.raises(TrainingCancelled) as info:
        finetune(scene, tmp_path, config=TrainConfig(steps=10, **FAST), should_stop=lambda: True)
    assert info.value.step == 0
    assert (tmp_path / MODEL_FILE).is_file() and load_state(tmp_path / STATE_FILE)["step"] == 0


def test_minutes_budget_stops_in_time(scene, tmp_path):
    seen = []
    result = finetune(scene, tmp_path, config=TrainConfig(minutes=0.0, **FAST), progress=seen.append)
    assert result.steps == 0 and seen == []
    assert result.config["minutes"] == 0.0 and result.config["steps"] is None


def test_crop_is_shared_and_shifts_the_principal_point(scene):
    data = SceneData(scene, 2)
    h, w = data.height, data.width
    code = torch.arange(h * w, dtype=torch.float32).view(1, 1, h, w)
    data.renders = code.expand(len(data), 3, h, w).clone()
    data.photos = data.renders.clone() + 0.5
    data.depths = code.expand(len(data), 1, h, w).clone()
    targets = torch.tensor([0, 3, 1])
    render, depth, photo, K = _crop_batch(data, targets, 10, torch.Generator().manual_seed(7))
    assert render.shape == (3, 3, 10, 10) and depth.shape == (3, 1, 10, 10)
    for b in range(3):
        first = int(render[b, 0, 0, 0])
        y0, x0 = divmod(first, w)
        assert torch.equal(render[b, 0], code[0, 0, y0:y0 + 10, x0:x0 + 10])
        assert torch.equal(depth[b, 0], render[b, 0]) and torch.equal(photo[b], render[b] + 0.5)
        original = data.K[targets[b]]
        assert K[b, 0, 2] == pytest.approx(float(original[0, 2]) - x0)
        assert K[b, 1, 2] == pytest.approx(float(original[1, 2]) - y0)
        assert torch.equal(K[b, :2, :2], original[:2, :2])


def test_neighbour_lists_exclude_the_target(scene):
    data = SceneData(scene, 3)
    assert data.neighbours.shape == (len(data), 3)
    for m, row in enumerate(data.neighbours.tolist()):
        assert m not in row and len(set(row)) == 3


def _random_vgg_file(tmp_path, suffix):
    torch.manual_seed(0)
    layers = _vgg19_layers()
    state = {f"features.{k}": v for k, v in layers.state_dict().items()}
    state["classifier.0.weight"] = torch.zeros(2, 2)  # the full torchvision dict also has these
    path = tmp_path / f"vgg19{suffix}"
    if suffix == ".safetensors":
        from safetensors.torch import save_file

        save_file(state, str(path))
    else:
        torch.save(state, path)
    return path


@pytest.mark.parametrize("suffix", [".safetensors", ".pth"])
def test_vgg_weights_enable_the_perceptual_loss(tmp_path, suffix):
    path = _random_vgg_file(tmp_path, suffix)
    loss = build_loss(path)
    assert loss.kind == "l1+vgg19"
    x = torch.rand(2, 3, 32, 32)
    y = torch.rand(2, 3, 32, 32)
    l1 = (x - y).abs().mean()
    perceptual = (loss.vgg(x) - loss.vgg(y)).abs().mean()
    assert float(perceptual) > 0
    torch.testing.assert_close(loss(x, y), l1 + 1e-3 * perceptual)
    assert float(loss(x, x)) == 0.0
    assert loss.vgg(x).shape == (2, 512, 2, 2)
    assert not any(p.requires_grad for p in loss.vgg.parameters())


def test_finetune_with_vgg_weights_reports_the_loss_kind(scene, tmp_path):
    path = _random_vgg_file(tmp_path, ".safetensors")
    result = finetune(scene, tmp_path / "out", config=TrainConfig(steps=1, vgg_weights=path, **{**FAST, "crop": 16}))
    assert result.loss_kind == "l1+vgg19" and result.config["loss_kind"] == "l1+vgg19"


def test_bad_vgg_weights_are_input_errors(tmp_path):
    with pytest.raises(InputError, match="does not exist"):
        VGG19Features.from_file(tmp_path / "missing.pth")
    from safetensors.torch import save_file

    save_file({"features.0.weight": torch.zeros(1)}, str(tmp_path / "bad.safetensors"))
    with pytest.raises(InputError, match="features.0.weight"):
        VGG19Features.from_file(tmp_path / "bad.safetensors")


@pytest.mark.slow
def test_ablation_from_a_full_checkpoint_transfers_matching_weights(scene, tmp_path):
    torch.manual_seed(0)
    full = build_enhancer("micro")
    save_checkpoint(tmp_path / "full.safetensors", full)
    result = finetune(scene, tmp_path / "ablated", checkpoint=tmp_path / "full.safetensors",
                      config=TrainConfig(steps=1, without=("neighbours",), **FAST))
    transfer = result.config["transfer"]
    assert {"conv_H", "flow", "pixel_attention", "camera_attention"} <= set(transfer["dropped"])
    assert "conv_merge" in transfer["fresh"]  # its input channels halve without neighbours
    model, _ = load_checkpoint(result.checkpoint)
    assert model.config.use_neighbours is False and model.conv_H is None
    assert result.config["num_neighbours"] == 0
    before_training = full.conv_I.state_dict()
    # one step of Adam at lr 1e-4 moves each weight by at most ~1e-4
    for k, v in model.conv_I.state_dict().items():
        torch.testing.assert_close(v, before_training[k], atol=2e-4, rtol=0)

    partial = finetune(scene, tmp_path / "partial", checkpoint=full,
                       config=TrainConfig(steps=1, without=("attention", "refinement"), **FAST))
    assert set(partial.config["transfer"]["dropped"]) == {"flow", "pixel_attention", "camera_attention"}
    assert partial.config["transfer"]["fresh"] == []


def test_pool_spread_from_a_checkpoint_without_it_widens_the_merge(scene, tmp_path):
    torch.manual_seed(0)
    plain = build_enhancer("micro")
    save_checkpoint(tmp_path / "plain.safetensors", plain)
    result = finetune(scene, tmp_path / "spread", checkpoint=tmp_path / "plain.safetensors",
                      config=TrainConfig(steps=1, pool_spread=True, **FAST))
    transfer = result.config["transfer"]
    assert transfer["widened"] == ["conv_merge"] and transfer["fresh"] == [] and transfer["dropped"] == []
    model, _ = load_checkpoint(result.checkpoint)
    assert model.config.pool_spread is True
    f = model.config.features
    # the new inputs start at zero weight, and one Adam step moves a weight by at most ~lr
    new_inputs = model.conv_merge[0].weight.detach()[:, 2 * f:]
    assert new_inputs.shape[1] == f and float(new_inputs.abs().max()) <= 1.5 * result.config["lr"]
    # a fine-tune of that checkpoint keeps its config (no transfer)
    again = finetune(scene, tmp_path / "again", checkpoint=result.checkpoint, config=TrainConfig(steps=1, **FAST))
    assert again.config.get("transfer") is None
    assert load_checkpoint(again.checkpoint)[0].config.pool_spread is True


def test_unknown_component_is_an_input_error(scene, tmp_path):
    with pytest.raises(InputError, match="without"):
        finetune(scene, tmp_path, config=TrainConfig(steps=1, without=("uformer",), **{**FAST}))


def test_plan_for_a_cpu():
    class _Frame:
        height, width = 200, 200

    class _Scene:
        frames = [_Frame()] * 3

    plan = plan_training(_Scene(), TrainConfig(), "cpu")
    assert plan.variant == "micro" and plan.crop == 64 and plan.crop_used == 64
    assert plan.num_neighbours == 2 and plan.batch == 4 and plan.lr == 5e-4
    assert plan.lr_schedule == "cosine"
    assert plan.freeze_neighbour_encoder is FREEZE_NEIGHBOUR_ENCODER
    assert plan_training(_Scene(), TrainConfig(), "cpu", kind="pretrain").freeze_neighbour_encoder is False
    assert plan_training(_Scene(), TrainConfig(freeze_neighbour_encoder=True), "cpu",
                         kind="pretrain").freeze_neighbour_encoder is True
    assert plan.minutes == 10.0 and plan.steps is None
    small = plan_training(_Scene(), TrainConfig(crop=512, steps=7, variant="micro", num_neighbours=4), "cpu")
    assert small.crop_used == 200 and small.steps == 7 and small.minutes is None
    assert small.variant == "micro" and small.num_neighbours == 4
    gpu = plan_training(_Scene(), TrainConfig(), "cuda")
    assert gpu.crop == 512 and gpu.variant == "T" and gpu.num_neighbours == 5 and gpu.minutes == 60.0
    assert gpu.lr == 1e-4 and plan_training(_Scene(), TrainConfig(lr=2e-4), "cpu").lr == 2e-4
    json.dumps(plan.to_dict())
    with pytest.raises(InputError, match="variant"):
        plan_training(_Scene(), TrainConfig(variant="huge"), "cpu")


def test_evaluate_shape_and_render_psnr(scene):
    torch.manual_seed(0)
    model = build_enhancer("micro", num_neighbours=2)
    report = evaluate(scene, model)
    assert [v["name"] for v in report["views"]] == [scene.frames[i].name for i in scene.indices("test")]
    for view in report["views"]:
        i = scene.index(view["name"])
        mse = float(((scene.render(i) - scene.photo(i)) ** 2).mean())
        assert view["render"]["psnr"] == pytest.approx(-10 * math.log10(mse), abs=1e-4)
        assert set(view["render"]) >= {"psnr", "ssim"} and set(view["enhanced"]) >= {"psnr", "ssim"}
        assert 0 < view["render"]["ssim"] <= 1
        assert all(n.startswith("train_") for n in view["neighbours"]) and len(view["neighbours"]) == 2
    mean = sum(v["render"]["psnr"] for v in report["views"]) / len(report["views"])
    assert report["render"]["psnr"] == pytest.approx(mean)
    json.dumps(report)
    train = evaluate(scene, model, split="train", max_views=2)
    for view in train["views"]:
        assert view["name"] not in view["neighbours"]


def test_the_plan_is_a_frozen_dataclass_saved_as_before():
    import dataclasses

    from roguenerf.training import TrainPlan
    from roguenerf.training.config import budget_fraction, describe_plan

    class _Frame:
        height, width = 200, 200

    class _Scene:
        frames = [_Frame()] * 3

    plan = plan_training(_Scene(), TrainConfig(steps=8, without=("attention",)), "cpu")
    with pytest.raises(dataclasses.FrozenInstanceError):
        plan.lr = 1.0
    saved = json.loads(json.dumps(plan.to_dict()))
    assert list(saved)[:4] == ["device", "variant", "crop", "crop_used"] and saved["without"] == ["attention"]
    assert TrainPlan.from_dict({**saved, "loss_kind": "l1"}) == plan  # a result's extra keys are ignored
    assert describe_plan(saved) == describe_plan(plan) and "without attention" in describe_plan(plan)
    assert plan.budget_fraction(2, 0.0) == budget_fraction(saved, 2, 0.0) == 0.25
    assert not plan.budget_done(7, 1e9) and plan.budget_done(8, 0.0)
    # A plan saved before a field existed: the default that run trained with.
    old = {k: v for k, v in saved.items() if k not in ("lr_schedule", "freeze_neighbour_encoder",
                                                         "render_warp", "held_out_share")}
    restored = TrainPlan.from_dict(old)
    assert (restored.lr_schedule, restored.freeze_neighbour_encoder, restored.render_warp) == ("constant", False, 0.0)
