"""The training forward runs all neighbours as one batch and shares the target's work
(``Enhancer._fuse_batched``): it equals the per-neighbour loop of ``reference_mode()`` in
output and in every parameter (and input) gradient, on windowed and whole-photo batches."""

from __future__ import annotations

import pytest
import torch

from roguenerf.data.toy import make_toy_scene
from roguenerf.fastpath import reference_mode
from roguenerf.models import Enhancer, build_enhancer
from roguenerf.models.layers import receptive_radius
from roguenerf.training.batches import model_inputs, prepare_batch
from roguenerf.training.loop import SceneData

pytestmark = pytest.mark.slow  # equality of whole training steps: minutes on 2 cores

H, W, CROP = 72, 96, 24
TARGETS = torch.tensor([0, 3, 5, 7])
ORIGINS = torch.tensor([[0, 0], [H - CROP, W - CROP], [0, W - CROP], [29, 41]])


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    scene = make_toy_scene(tmp_path_factory.mktemp("toy"), seed=5, n_train=8, n_test=0, height=H, width=W,
                           kind="forward")
    d = SceneData(scene, 4)
    for name in ("photos", "renders", "depths", "K", "poses"):
        setattr(d, name, getattr(d, name).to(torch.float64))
    return d


def _model(**overrides):
    """micro, every weight random (the zero-initialised heads too, so that the flow moves the
    neighbours and every gradient before the output is non-zero), float64."""
    torch.manual_seed(1)
    model = build_enhancer("micro", num_neighbours=4, **overrides)
    with torch.no_grad():
        for p in model.parameters():
            if not p.abs().max() > 0:
                p.normal_(0.0, 0.05)
        if model.flow is not None:
            model.flow.to_delta[-1].weight.normal_(0.0, 0.2)  # flows of a pixel or more
    return model.double().train()


def _run(model, batch, reference: bool):
    """Output, loss, {name: grad}, grad of the render, and the shapes the flow network was called with."""
    calls = []
    def record(m, i, out):
        calls.append((tuple(i[0].shape), float(out.detach().abs().max())))

    hook = model.flow.register_forward_hook(record) if model.flow is not None else None
    model.zero_grad(set_to_none=True)
    args, photo = model_inputs(model, batch, torch.device("cpu"))
    render = args[0].clone().requires_grad_(True)
    with reference_mode(reference):
        out = model(render, *args[1:])
    loss = (out - photo).abs().mean()
    loss.backward()
    if hook is not None:
        hook.remove()
    return out.detach(), loss.detach(), {n: p.grad.clone() for n, p in model.named_parameters()}, render.grad, calls


@pytest.mark.parametrize("encoding", ["window", "whole"])
@pytest.mark.parametrize("switches", [{}, {"use_refinement": False}, {"use_attention": False}, {"pool_spread": True}])
def test_batched_training_fusion_equals_per_neighbour_loop(data, encoding, switches, monkeypatch):
    model = _model(**switches)
    batch = prepare_batch(data, TARGETS, ORIGINS, CROP, encoding=encoding, margin=receptive_radius(model.conv_H))
    assert batch.encoding == encoding
    n, b = batch.neighbours.shape[1], len(TARGETS)
    assert n == 4

    taken = []
    original = Enhancer._fuse_batched
    monkeypatch.setattr(Enhancer, "_fuse_batched", lambda self, *a, **k: taken.append(1) or original(self, *a, **k))
    out_b, loss_b, grads_b, rgrad_b, calls_b = _run(model, batch, reference=False)
    assert taken == [1]  # the batched path ran, and only outside reference mode
    out_r, loss_r, grads_r, rgrad_r, calls_r = _run(model, batch, reference=True)
    assert taken == [1]

    if model.flow is not None:
        # One flow call on all N * B neighbours against N calls of B; the flow really moves them.
        assert [c[0][0] for c in calls_b] == [n * b] and [c[0][0] for c in calls_r] == [b] * n
        assert max(c[1] for c in calls_r) > 0.5
        assert max(c[1] for c in calls_b) == pytest.approx(max(c[1] for c in calls_r), rel=1e-9)
    torch.testing.assert_close(out_b, out_r, rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(loss_b, loss_r, rtol=1e-12, atol=0)
    torch.testing.assert_close(rgrad_b, rgrad_r, rtol=1e-9, atol=1e-14)
    assert set(grads_b) == set(grads_r) == {name for name, _ in model.named_parameters()}
    for name, g in grads_r.items():
        scale = float(g.abs().max())
        assert scale > 0 or name.startswith("uformer"), f"{name}: zero gradient, the comparison is empty"
        torch.testing.assert_close(grads_b[name], g, rtol=1e-9, atol=1e-12 * max(scale, 1e-30), msg=name)


def test_batched_fusion_is_not_vacuous(data):
    """The comparison above would catch a batched path that pairs a neighbour's aligned
    features with another neighbour's camera attention (a transposed (B, N) -> N * B layout):
    such a pairing changes the output far beyond the tolerance."""
    model = _model()
    batch = prepare_batch(data, TARGETS, ORIGINS, CROP, encoding="window", margin=receptive_radius(model.conv_H))
    out_b, *_ = _run(model, batch, reference=False)
    original = Enhancer._camera_inputs
    try:
        Enhancer._camera_inputs = staticmethod(lambda t, nb, s: original(t, nb, s).roll(1, dims=1))
        out_wrong, *_ = _run(model, batch, reference=False)
    finally:
        Enhancer._camera_inputs = staticmethod(original)
    assert float((out_wrong - out_b).abs().max()) > 1e-6


def test_float32_training_runs_channels_last_and_equals_the_reference(data):
    """float32 on the CPU (what training runs in): the pixel attention's and the merge's
    convolutions get channels-last inputs outside reference mode (NCHW inside it), and the
    output and every gradient equal the reference to float32 rounding."""
    model = _model().float()
    d32 = SceneData.__new__(SceneData)
    d32.__dict__.update({k: (v.float() if torch.is_tensor(v) and v.is_floating_point() and k != "poses" else v)
                         for k, v in data.__dict__.items()})
    batch = prepare_batch(d32, TARGETS, ORIGINS, CROP, encoding="window", margin=receptive_radius(model.conv_H))
    layouts = {}

    def record(name):
        def hook(module, inputs):
            x = inputs[0]
            layouts.setdefault(name, []).append(x.is_contiguous(memory_format=torch.channels_last)
                                                and not x.is_contiguous())
        return hook

    handles = [model.conv_merge[0].register_forward_pre_hook(record("merge")),
               model.pixel_attention.net[2].register_forward_pre_hook(record("attention_out"))]
    out_f, loss_f, grads_f, rgrad_f, _ = _run(model, batch, reference=False)
    fast_layouts, layouts = layouts, {}
    out_r, loss_r, grads_r, rgrad_r, _ = _run(model, batch, reference=True)
    for h in handles:
        h.remove()
    assert fast_layouts == {"merge": [True], "attention_out": [True]}
    assert layouts == {"merge": [False], "attention_out": [False] * 4}
    torch.testing.assert_close(out_f, out_r, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(loss_f, loss_r, rtol=1e-5, atol=0)
    for name, g in grads_r.items():
        scale = max(float(g.abs().max()), 1e-30)
        torch.testing.assert_close(grads_f[name], g, rtol=1e-3, atol=1e-4 * scale, msg=name)
