"""Training on neighbour windows (roguenerf/training/batches.py): the step that encodes only the
window of each neighbour photo a target crop can see equals the step on whole photos, in loss
and in every parameter gradient; the window geometry, conv_H's receptive radius, and the
background batch thread."""

from __future__ import annotations

import math
import threading

import pytest
import torch
from torch import nn

from roguenerf.data.toy import make_toy_scene
from roguenerf.errors import InputError
from roguenerf.models import build_enhancer
from roguenerf.models.layers import ConvEncoder, receptive_radius
from roguenerf.training import TrainConfig, finetune
from roguenerf.training import batches as batches_mod
from roguenerf.training.batches import Prefetcher, model_inputs, neighbour_windows, place_windows, prepare_batch
from roguenerf.training.loop import SceneData

pytestmark = pytest.mark.slow  # equality of whole training steps: minutes on 2 cores

H, W, CROP = 72, 96, 20


@pytest.fixture(scope="module", params=["orbit", "forward"])
def scene(request, tmp_path_factory):
    return make_toy_scene(tmp_path_factory.mktemp(f"toy-{request.param}"), seed=3, n_train=8, n_test=0,
                          height=H, width=W, kind=request.param)


def _model(dtype=torch.float64):
    """micro with refinement and attention, every weight random (the zero-initialised output
    projection and flow head too: otherwise every gradient before them would be 0 and the flow
    would be the identity, and the comparison would prove nothing)."""
    torch.manual_seed(0)
    model = build_enhancer("micro", num_neighbours=3)
    assert model.flow is not None and model.pixel_attention is not None and model.camera_attention is not None
    with torch.no_grad():
        for p in model.parameters():
            if not p.abs().max() > 0:
                p.normal_(0.0, 0.05)
    return model.to(dtype).train()


def _data(scene, dtype=torch.float64) -> SceneData:
    data = SceneData(scene, 3)
    for name in ("photos", "renders", "depths", "K", "poses"):
        setattr(data, name, getattr(data, name).to(dtype))
    return data


# Crops at the four corners of the target image and one inside: windows then meet the
# neighbours' image borders as well as interior edges.
TARGETS = torch.tensor([0, 3, 5, 7, 2])
ORIGINS = torch.tensor([[0, 0], [H - CROP, W - CROP], [0, W - CROP], [H - CROP, 0], [29, 41]])


def _step(model, batch):
    """Loss and {name: grad} of one step on a prepared batch (and the largest flow, in pixels)."""
    flows = []
    hook = model.flow.register_forward_hook(lambda m, i, out: flows.append(float(out.detach().abs().max())))
    model.zero_grad(set_to_none=True)
    args, photo = model_inputs(model, batch, torch.device("cpu"))
    loss = (model(*args) - photo).abs().mean()
    loss.backward()
    hook.remove()
    return loss.detach(), {n: p.grad.clone() for n, p in model.named_parameters()}, max(flows)


def _batches(data, model, **window_kwargs):
    margin = receptive_radius(model.conv_H)
    window = prepare_batch(data, TARGETS, ORIGINS, CROP, encoding="window", margin=margin, **window_kwargs)
    whole = prepare_batch(data, TARGETS, ORIGINS, CROP, encoding="whole", margin=margin)
    return window, whole


def test_window_step_equals_whole_photo_step(scene):
    model = _model()
    data = _data(scene)
    window, whole = _batches(data, model)
    # The windowed batch really is windowed: small windows, some at image borders, some not.
    assert window.encoding == "window" and whole.encoding == "whole"
    assert len(window.neighbour_photos) == 3 and all(p.shape[0] == len(TARGETS) for p in window.neighbour_photos)
    y0, x0, h, w = window.windows.unbind(-1)
    assert bool((h * w < H * W / 2).all())
    at_border = (y0 == 0) | (x0 == 0) | (y0 + h == H) | (x0 + w == W)
    assert bool(at_border.any()) and bool((~at_border).any())
    encoded = sum(p.numel() for p in window.neighbour_photos)
    assert encoded < whole.neighbour_photos.numel() / 2
    # Same neighbours per target, in another order (largest window first).
    assert torch.equal(window.neighbours.sort(dim=1).values, whole.neighbours.sort(dim=1).values)

    loss_w, grads_w, flow_w = _step(model, window)
    loss_o, grads_o, flow_o = _step(model, whole)
    assert flow_o > 0.5  # the refinement moves the neighbours by more than half a pixel
    assert flow_w == pytest.approx(flow_o, rel=1e-9)
    torch.testing.assert_close(loss_w, loss_o, rtol=1e-12, atol=0)
    assert set(grads_w) == set(grads_o) and len(grads_o) == len(list(model.parameters()))
    for name, g in grads_o.items():
        scale = float(g.abs().max())
        assert scale > 0 or name.startswith("uformer"), f"{name}: zero gradient, the comparison is empty"
        torch.testing.assert_close(grads_w[name], g, rtol=1e-9, atol=1e-12 * max(scale, 1e-30), msg=name)
    for prefix in ("conv_H", "flow", "pixel_attention", "camera_attention"):
        assert any(float(g.abs().max()) > 0 for n, g in grads_o.items() if n.startswith(prefix)), prefix


def test_the_margin_is_what_makes_the_windows_exact(scene, monkeypatch):
    """Without conv_H's receptive margin (and the slack pixel) the window path differs: the
    equality above is not vacuous, and the margin computed from the layers is needed."""
    model = _model()
    data = _data(scene)
    monkeypatch.setattr(batches_mod, "WINDOW_SLACK", 0)
    window = prepare_batch(data, TARGETS, ORIGINS, CROP, encoding="window", margin=0)
    whole = prepare_batch(data, TARGETS, ORIGINS, CROP, encoding="whole")
    _, grads_w, _ = _step(model, window)
    _, grads_o, _ = _step(model, whole)
    diff = (grads_w["conv_H.0.weight"] - grads_o["conv_H.0.weight"]).abs().max()
    assert diff > 1e-6 * grads_o["conv_H.0.weight"].abs().max()


def test_window_step_equals_whole_photo_step_in_float32(scene):
    """The dtype training runs in: equal to float32 rounding."""
    model = _model(torch.float32)
    data = _data(scene, torch.float32)
    window, whole = _batches(data, model)
    assert window.encoding == "window"
    loss_w, grads_w, _ = _step(model, window)
    loss_o, grads_o, _ = _step(model, whole)
    torch.testing.assert_close(loss_w, loss_o, rtol=1e-5, atol=0)
    for name, g in grads_o.items():
        scale = max(float(g.abs().max()), 1e-30)
        torch.testing.assert_close(grads_w[name], g, rtol=1e-3, atol=1e-4 * scale, msg=name)


def test_windows_of_an_identity_neighbour_are_the_crop_plus_margin():
    """A neighbour at the target's own pose sees each pixel where it is: the window is the
    crop's taps (x0 .. x0 + c, the last one the second bilinear tap) widened by margin + slack,
    clamped to the photo; a crop with no known depth gets pixel (0, 0)."""
    K = torch.tensor([[50.0, 0, 32], [0, 50.0, 24], [0, 0, 1]])
    pose = torch.eye(4)
    origins = torch.tensor([[10, 20], [0, 0], [40, 56], [5, 5]])  # inside, two corners, unknown depth
    c = 8
    Kc = K.repeat(4, 1, 1)
    Kc[:, 0, 2] -= origins[:, 1]
    Kc[:, 1, 2] -= origins[:, 0]
    depth = torch.full((4, 1, c, c), 2.0)
    depth[3] = 0.0
    bounds = neighbour_windows(depth, Kc, pose.repeat(4, 1, 1), K.repeat(4, 1, 1, 1), pose.repeat(4, 1, 1, 1),
                               (48, 64), margin=2)
    pad = 2 + batches_mod.WINDOW_SLACK
    assert bounds.shape == (4, 1, 4) and bounds.dtype == torch.int64
    assert bounds[:, 0].tolist() == [[10 - pad, 20 - pad, 10 + c + pad, 20 + c + pad],
                                     [0, 0, c + pad, c + pad],
                                     [40 - pad, 56 - pad, 47, 63],
                                     [0, 0, 0, 0]]


def test_windows_share_one_size_per_slot_largest_first():
    # (y_lo, x_lo, y_hi, x_hi) inclusive; two targets, two neighbours each.
    bounds = torch.tensor([[[0, 0, 3, 3], [5, 5, 14, 9]],      # areas 16, 50 -> order 1, 0
                           [[30, 50, 39, 63], [2, 2, 3, 4]]])  # areas 140, 6 -> order 0, 1
    order, origins, sizes = place_windows(bounds, (40, 64))
    assert order.tolist() == [[1, 0], [0, 1]]
    assert sizes.tolist() == [[10, 14], [4, 4]]
    # Slot 0: (5, 5) fits as it is; (30, 50) grows past the photo and moves back to (30, 50).
    # Slot 1: (0, 0) and (2, 2) take size 4 x 4 in place.
    assert origins.tolist() == [[[5, 5], [0, 0]], [[30, 50], [2, 2]]]
    limit = torch.tensor([40, 64])
    assert bool((origins + sizes[None] <= limit).all()) and bool((origins >= 0).all())


def test_windows_fall_back_to_whole_photos_when_they_would_cost_more(scene):
    """Crops as large as the image project onto (nearly) all of each neighbour: B x N windows
    would be more pixels than the distinct photos, so the batch encodes those (same values)."""
    data = _data(scene, torch.float32)
    batch = prepare_batch(data, torch.tensor([0, 1, 2, 3]), torch.zeros(4, 2, dtype=torch.int64), max(H, W),
                          encoding="window", margin=2)
    assert batch.encoding == "whole" and batch.windows is None
    assert batch.neighbour_photos.shape[-2:] == (H, W)


def test_receptive_radius_is_computed_from_the_layers():
    assert receptive_radius(ConvEncoder(features=4)) == 2
    assert receptive_radius(nn.Sequential(nn.Conv2d(3, 4, 5, padding=4, dilation=2), nn.ReLU(),
                                          nn.Conv2d(4, 4, 1))) == 4
    with pytest.raises(ValueError, match="stride-1"):
        receptive_radius(nn.Sequential(nn.Conv2d(3, 4, 3, padding=1, stride=2)))
    with pytest.raises(ValueError, match="stride-1"):
        receptive_radius(nn.Sequential(nn.Conv2d(3, 4, 3, padding=0)))
    with pytest.raises(ValueError, match="parameters"):
        receptive_radius(nn.Sequential(nn.Conv2d(3, 4, 3, padding=1), nn.BatchNorm2d(4)))


def test_prefetcher_keeps_order_raises_errors_and_stops():
    counter = iter(range(100))
    with Prefetcher(lambda: next(counter), depth=2) as pre:
        assert [next(pre) for _ in range(5)] == [0, 1, 2, 3, 4]
        thread = pre._thread
        assert thread.name == "roguenerf-batches" and thread is not threading.current_thread()
    assert not thread.is_alive()

    def failing():
        raise InputError("bad batch")

    with Prefetcher(failing) as pre, pytest.raises(InputError, match="bad batch"):
        next(pre)


def test_finetune_on_windows_matches_whole_photos(tmp_path, monkeypatch):
    """End to end: fine-tuning with either encoding draws the same batches (in the background
    thread) and reports the same losses step by step. (Weights are not compared: Adam divides
    each gradient by its own magnitude, so entries that are ~0 get +-lr from rounding alone.)"""
    scene = make_toy_scene(tmp_path / "scene", seed=4, n_train=6, n_test=0, height=60, width=80, kind="orbit")
    common = dict(steps=3, crop=16, batch=2, variant="micro", num_neighbours=3, evaluate=False,
                  progress_bar=False, checkpoint_every_s=1e9)
    from roguenerf.training import loop

    made = []

    def spy(*args, **kwargs):
        batch = prepare_batch(*args, **kwargs)
        made.append((batch.encoding, threading.current_thread().name))
        return batch

    monkeypatch.setattr(loop, "prepare_batch", spy)
    losses = {}
    for enc in ("window", "whole"):
        seen = []
        result = finetune(scene, tmp_path / enc, config=TrainConfig(neighbour_encoding=enc, **common),
                          progress=seen.append)
        assert result.config["neighbour_encoding"] == enc
        losses[enc] = [p.loss for p in seen]
    assert len(losses["window"]) == 3
    assert losses["window"] == pytest.approx(losses["whole"], rel=1e-5)
    assert len(set(losses["whole"])) == 3  # different batches each step
    assert {e for e, _ in made} == {"window", "whole"} and {t for _, t in made} == {"roguenerf-batches"}
    with pytest.raises(InputError, match="neighbour_encoding"):
        TrainConfig(neighbour_encoding="tiles").validate()


def test_cached_features_step_equals_the_frozen_encoder_step(scene):
    """conv_H frozen: windows cut from features encoded once, whole (``SceneData.features``, no
    receptive margin), give the loss and every gradient of the step that encodes whole photos
    with the frozen conv_H; conv_H gets no gradient in either."""
    model = _model()
    model.conv_H.requires_grad_(False)
    data = _data(scene)
    data.cache_features(model, torch.device("cpu"))
    assert data.features.shape == (len(data.train), model.config.features, H, W)
    cached = prepare_batch(data, TARGETS, ORIGINS, CROP, encoding="window", margin=receptive_radius(model.conv_H))
    assert cached.encoding == "window" and cached.neighbour_photos is None
    assert all(f.shape[1] == model.config.features for f in cached.neighbour_features)
    data.features = None
    _, whole = _batches(data, model)
    assert whole.neighbour_photos is not None and whole.neighbour_features is None
    # No receptive margin around cached features: windows are smaller than photo windows.
    photo_window = prepare_batch(data, TARGETS, ORIGINS, CROP, encoding="window", margin=receptive_radius(model.conv_H))
    assert bool(cached.windows[..., 2:].prod(-1).sum() < photo_window.windows[..., 2:].prod(-1).sum())

    model.zero_grad(set_to_none=True)
    args, photo = model_inputs(model, cached, torch.device("cpu"))
    loss_c = (model(*args) - photo).abs().mean()
    loss_c.backward()
    grads_c = {n: p.grad.clone() for n, p in model.named_parameters() if p.grad is not None}
    model.zero_grad(set_to_none=True)
    args, photo = model_inputs(model, whole, torch.device("cpu"))
    loss_o = (model(*args) - photo).abs().mean()
    loss_o.backward()
    grads_o = {n: p.grad.clone() for n, p in model.named_parameters() if p.grad is not None}
    torch.testing.assert_close(loss_c.detach(), loss_o.detach(), rtol=1e-12, atol=0)
    assert set(grads_c) == set(grads_o) and not any(n.startswith("conv_H") for n in grads_o)
    assert any(n.startswith("flow") for n in grads_o) and any(n.startswith("pixel_attention") for n in grads_o)
    for name, g in grads_o.items():
        scale = float(g.abs().max())
        torch.testing.assert_close(grads_c[name], g, rtol=1e-9, atol=1e-12 * max(scale, 1e-30), msg=name)


def test_finetune_with_a_frozen_encoder_keeps_conv_H(tmp_path):
    """The plan says so, conv_H's weights come out as they went in, the rest trains, and the
    encoder is trainable again afterwards (the caller's model is not left frozen)."""
    from roguenerf.checkpoint import load_checkpoint, save_checkpoint

    scene = make_toy_scene(tmp_path / "scene", seed=4, n_train=6, n_test=0, height=60, width=80, kind="orbit")
    torch.manual_seed(0)
    start = build_enhancer("micro", num_neighbours=3)
    save_checkpoint(tmp_path / "start.safetensors", start)
    common = dict(steps=3, crop=16, batch=2, evaluate=False, progress_bar=False, checkpoint_every_s=1e9)
    result = finetune(scene, tmp_path / "frozen", checkpoint=tmp_path / "start.safetensors",
                      config=TrainConfig(freeze_neighbour_encoder=True, **common))
    assert result.config["freeze_neighbour_encoder"] is True
    trained, _ = load_checkpoint(result.checkpoint)
    before, after = start.state_dict(), trained.state_dict()
    assert all(torch.equal(before[k], after[k]) for k in before if k.startswith("conv_H"))
    assert any(not torch.equal(before[k], after[k]) for k in before if k.startswith("conv_I"))
    # Trained conv_H by default (the plan's FREEZE_NEIGHBOUR_ENCODER) or when asked.
    result = finetune(scene, tmp_path / "trained", checkpoint=tmp_path / "start.safetensors",
                      config=TrainConfig(freeze_neighbour_encoder=False, **common))
    assert result.config["freeze_neighbour_encoder"] is False
    trained, _ = load_checkpoint(result.checkpoint)
    assert any(not torch.equal(before[k], trained.state_dict()[k]) for k in before if k.startswith("conv_H"))


# ----- fine-tuning targets that look like novel views (render_warp) -----

def test_displace_reads_each_pixel_at_its_shift():
    from roguenerf.training.batches import displace

    h, w = 6, 9
    render = torch.arange(h * w, dtype=torch.float32).reshape(1, 1, h, w).expand(1, 3, h, w).contiguous()
    depth = torch.rand(1, 1, h, w) + 1.0
    shift = torch.zeros(1, 2, h, w)
    shift[:, 0] = 2.0  # two pixels right: content moves left
    shift[:, 1, 3:] = -1.0  # and the lower half one row up
    warped, warped_depth = displace(render, depth, shift)
    torch.testing.assert_close(warped[0, :, :3, :7], render[0, :, :3, 2:])
    torch.testing.assert_close(warped[0, :, 3:, :7], render[0, :, 2:5, 2:])
    torch.testing.assert_close(warped[0, :, :3, 7:], render[0, :, :3, 8:].expand(3, 3, 2))  # border repeated
    torch.testing.assert_close(warped_depth[0, 0, :3, :7], depth[0, 0, :3, 2:])
    half = torch.full((1, 2, h, w), 0.5)
    _, between = displace(render, depth, half)  # the depth is never blended across pixels
    assert set(between.flatten().tolist()) <= set(depth.flatten().tolist())


def test_warp_renders_moves_a_share_of_crops_by_at_most_the_shift():
    from roguenerf.training.batches import warp_renders

    b, c = 64, 32
    ramp = torch.arange(c, dtype=torch.float32).expand(b, 3, c, c).contiguous()  # value = x
    depth = ramp[:, :1] + 1.0
    generator = torch.Generator().manual_seed(0)
    warped, warped_depth = warp_renders(ramp, depth, 4.0, generator)
    moved = (warped - ramp).abs().flatten(1).amax(dim=1)
    assert 16 < int((moved > 0).sum()) < 48  # about half the crops
    interior = (warped - ramp)[..., 4:-4]  # away from the repeated border the ramp reads off the shift
    assert float(interior.abs().max()) <= 4.0 + 1e-5
    assert float(interior.abs().max()) > 2.0
    torch.testing.assert_close(warped_depth[moved == 0], depth[moved == 0])
    same, _ = warp_renders(ramp, depth, 4.0, torch.Generator().manual_seed(0))
    assert torch.equal(same, warped)  # the generator alone decides
    assert warp_renders(ramp, depth, 0.0, generator)[0] is ramp


def test_corrupt_depths_scales_a_share_of_crops_smoothly_within_the_bound():
    from roguenerf.training.batches import corrupt_depths

    b, c = 64, 32
    depth = torch.full((b, 1, c, c), 2.0)
    depth[:, :, 0, 0] = 0.0  # unknown depth stays unknown
    depth[:, :, 0, 1] = float("inf")
    out = corrupt_depths(depth, 0.3, torch.Generator().manual_seed(0))
    changed = (out != depth)[:, :, 1:].flatten(1).any(dim=1)
    assert 16 < int(changed.sum()) < 48  # about half the crops
    ratio = (out / depth)[:, :, 1:]
    assert float(ratio.max()) <= math.exp(0.3) + 1e-5 and float(ratio.min()) >= math.exp(-0.3) - 1e-5
    assert float(ratio[changed].max()) > math.exp(0.15)  # errors of the size asked for
    assert float((ratio[changed][..., 1:] / ratio[changed][..., :-1]).log().abs().max()) < 0.1  # smooth
    assert torch.equal(out[:, :, 0, 0], depth[:, :, 0, 0]) and torch.equal(out[:, :, 0, 1], depth[:, :, 0, 1])
    assert torch.equal(out, corrupt_depths(depth, 0.3, torch.Generator().manual_seed(0)))  # the generator decides
    assert corrupt_depths(depth, 0.0, torch.Generator()) is depth


def test_windows_bound_the_warped_depth(scene):
    """With render_warp the windows are bounded from the displaced depth (prepare_batch's
    ``augment`` runs first), so the windowed step still equals the whole-photo step."""
    from roguenerf.training.batches import warp_renders

    model = _model()
    data = _data(scene)
    margin = receptive_radius(model.conv_H)

    def augment(render, depth):
        return warp_renders(render, depth, 6.0, torch.Generator().manual_seed(3), share=1.0)

    window = prepare_batch(data, TARGETS, ORIGINS, CROP, encoding="window", margin=margin, augment=augment)
    whole = prepare_batch(data, TARGETS, ORIGINS, CROP, encoding="whole", margin=margin, augment=augment)
    plain = prepare_batch(data, TARGETS, ORIGINS, CROP, encoding="window", margin=margin)
    assert not torch.equal(window.depth, plain.depth) and torch.equal(window.depth, whole.depth)
    assert window.encoding == "window"
    loss_w, grads_w, _ = _step(model, window)
    loss_o, grads_o, _ = _step(model, whole)
    torch.testing.assert_close(loss_w, loss_o, rtol=1e-12, atol=0)
    for name, g in grads_o.items():
        torch.testing.assert_close(grads_w[name], g, rtol=1e-9, atol=1e-12 * max(float(g.abs().max()), 1e-30),
                                   msg=name)
