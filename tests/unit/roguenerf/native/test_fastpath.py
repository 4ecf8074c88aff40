"""The inference fast paths compute what the plain implementation computes.

Every fast path (fused oneDNN kernels, channels-last layouts, gather-based bilinear sampling,
target work shared across neighbours, cached attention biases, cached neighbour sampling
sources) is compared with ``reference_mode()`` on the same weights and inputs: equal to float32
rounding. The tolerance is an absolute 2e-4 on images in [0, 1] (8-bit quantisation is 4e-3);
the fast path also must not be a no-op (it really runs: checked by the kernels it calls).
"""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

from roguenerf.fastpath import fast_enabled, reference_mode
from roguenerf.geometry.sampling import bilinear_sample
from roguenerf.models import NeighbourBatch, build_enhancer
from roguenerf.models.flow import FlowRefiner, flow_warp
from roguenerf.ops import fused
from roguenerf.reprojection import reproject, sampling_source
from tests.model_helpers import make_views, randomise

TOL = 2e-4


def both(fn):
    """(fast, reference) results of ``fn()``."""
    with torch.inference_mode():
        fast = fn()
    with torch.no_grad(), reference_mode():
        ref = fn()
    return fast, ref


def test_switch_conditions():
    x = torch.zeros(2)
    assert not fast_enabled(x)  # gradient mode (the default) is always the plain path
    with torch.no_grad():
        assert fast_enabled(x)
        assert not fast_enabled(x.double())
        with reference_mode():
            assert not fast_enabled(x)
        assert fast_enabled(x)


@pytest.mark.parametrize("padding", ["zeros", "border"])
def test_bilinear_sample_equals_grid_sample(padding):
    g = torch.Generator().manual_seed(0)
    src = torch.randn(2, 5, 13, 17, generator=g)
    # Coordinates inside, on and beyond every edge, and exact integers.
    x = torch.rand(2, 7, 11, generator=g) * 21 - 2
    y = torch.rand(2, 7, 11, generator=g) * 17 - 2
    x[:, 0, :3] = torch.tensor([0.0, 16.0, 3.0])
    y[:, 0, :3] = torch.tensor([0.0, 12.0, 12.0])
    grid = torch.stack([2 * x / 16 - 1, 2 * y / 12 - 1], dim=-1)  # align_corners=True frame
    ref = F.grid_sample(src, grid, mode="bilinear", padding_mode=padding, align_corners=True)
    with torch.no_grad():
        out = bilinear_sample(src.contiguous(memory_format=torch.channels_last), x, y, padding=padding)
    assert out.shape == ref.shape and out.is_contiguous(memory_format=torch.channels_last)
    torch.testing.assert_close(out, ref, atol=1e-5, rtol=0)


def test_fused_linear_and_conv_equal_plain_layers():
    torch.manual_seed(0)
    lin = torch.nn.Linear(16, 48)
    conv = torch.nn.Conv2d(8, 8, 3, padding=1, groups=8)
    x = torch.randn(2, 9, 7, 16)
    xc = torch.randn(2, 8, 9, 7).contiguous(memory_format=torch.channels_last)
    for act, ref_fn in [("none", lambda t: t), ("gelu", F.gelu), ("leaky_relu", lambda t: F.leaky_relu(t, 0.01))]:
        if act != "leaky_relu":
            fast, ref = both(lambda act=act: fused.linear(x, lin, act))
            torch.testing.assert_close(fast, ref, atol=1e-5, rtol=1e-5)
            torch.testing.assert_close(ref, ref_fn(lin(x)))
        fast, ref = both(lambda act=act: fused.conv2d(xc, conv, act))
        torch.testing.assert_close(fast, ref, atol=1e-5, rtol=1e-5)


def test_reproject_with_cached_source_and_fast_sampler():
    model = build_enhancer("micro")
    render, depth, K, P, nb = make_views(model, n=1, h=40, w=56)
    src, src_depth = nb.features[:, 0], nb.depth[:, 0]
    src_depth = src_depth.clone()
    src_depth[..., 5:9, 10:20] = 0.0  # some unknown neighbour depth
    args = (src, src_depth, depth, nb.K[:, 0], K, nb.world_from_cam[:, 0], P)

    def fast_with_source():
        return reproject(*args, source=sampling_source(src, src_depth))

    fast, ref = both(fast_with_source)
    assert ref.valid.sum() > 0.5 * ref.valid.numel()
    torch.testing.assert_close(fast.valid, ref.valid)
    torch.testing.assert_close(fast.features, ref.features, atol=1e-4, rtol=0)
    torch.testing.assert_close(fast.depth, ref.depth, atol=1e-4, rtol=0)


def test_flow_shared_target_encoding_and_fast_warp():
    torch.manual_seed(0)
    flow_net = FlowRefiner(features=8, hidden=8, iters=2)
    torch.nn.init.normal_(flow_net.to_delta[-1].weight, std=0.05)
    nb, tg = torch.randn(1, 8, 30, 44), torch.randn(1, 8, 30, 44)

    def run():
        flow = flow_net(nb, tg, flow_net.encode_target(tg)) if fast_enabled(tg) else flow_net(nb, tg)
        return flow, flow_warp(torch.cat([nb, tg[:, :1]], dim=1), flow)

    (flow_f, warp_f), (flow_r, warp_r) = both(run)
    assert flow_r.abs().max() > 0.1  # a real, non-zero flow
    torch.testing.assert_close(flow_f, flow_r, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(warp_f, warp_r, atol=1e-4, rtol=0)


@pytest.mark.parametrize(("variant", "h", "w", "spread"),
                         [("micro", 48, 64, False), ("nano", 56, 72, False),
                          pytest.param("T", 40, 136, False, marks=pytest.mark.slow), ("micro", 48, 64, True)])
def test_whole_enhancer_fast_equals_reference(variant, h, w, spread):
    torch.manual_seed(0)
    model = randomise(build_enhancer(variant, pool_spread=spread), std=0.05).eval()
    render, depth, K, P, nb = make_views(model, n=3, h=h, w=w)
    depth[..., :4, :6] = 0.0  # missing target depth
    with torch.no_grad():
        sources = [model.neighbour_source(nb.features[:, j], nb.depth[:, j]) for j in range(len(nb))]
    cached = NeighbourBatch(None, nb.depth, nb.K, nb.world_from_cam, sources=sources)
    fast, ref = both(lambda: model(render, depth, K, P, nb))
    with torch.inference_mode():
        fast_cached = model(render, depth, K, P, cached)
    assert (ref - render).abs().max() > 0.01  # the model does change the image
    torch.testing.assert_close(fast, ref, atol=TOL, rtol=0)
    torch.testing.assert_close(fast_cached, ref, atol=TOL, rtol=0)


def test_cached_attention_bias_follows_new_weights():
    """The fast path caches bias + shift mask; changing the weights must not serve a stale cache."""
    torch.manual_seed(0)
    model = randomise(build_enhancer("micro"), std=0.05).eval()
    render, depth, K, P, nb = make_views(model, n=1, h=64, w=64)
    with torch.inference_mode():
        before = model(render, depth, K, P, nb)
    with torch.no_grad():
        for m in model.modules():
            if hasattr(m, "relative_position_bias_table"):
                m.relative_position_bias_table.add_(torch.randn_like(m.relative_position_bias_table))
    fast, ref = both(lambda: model(render, depth, K, P, nb))
    assert (fast - before).abs().max() > 1e-4
    torch.testing.assert_close(fast, ref, atol=TOL, rtol=0)


def test_training_mode_never_takes_the_fast_path():
    """With gradients recorded, every parameter still gets a gradient (fused kernels have none)."""
    torch.manual_seed(0)
    model = randomise(build_enhancer("micro"), std=0.05).train()
    render, depth, K, P, nb = make_views(model, n=2)
    model(render, depth, K, P, nb).square().mean().backward()
    missing = [n for n, p in model.named_parameters() if p.grad is None]
    assert not missing


@pytest.mark.parametrize("offset", [0.0, 5e6])
def test_composed_projection_equals_plain_projection(offset):
    """The fast path's projection (one float64 matrix per batch item, per-row and per-column
    terms) gives the plain path's coordinates and masks, also 5e6 units from the origin."""
    model = build_enhancer("micro")
    render, depth, K, P, nb = make_views(model, n=1, h=40, w=56)
    depth = depth.clone()
    depth[..., :3, :5] = 0.0  # unknown target depth
    depth[..., 10, 10] = float("nan")
    P64, nbP = P.double(), nb.world_from_cam[:, 0].double()
    P64[..., :3, 3] += offset
    nbP[..., :3, 3] += offset
    args = (nb.features[:, 0], nb.depth[:, 0], depth, nb.K[:, 0], K, nbP, P64)
    with torch.inference_mode():
        fast = reproject(*args)
    with torch.no_grad(), reference_mode():
        ref = reproject(*args)
    valid = ref.valid.bool()
    assert 0.3 * valid.numel() < valid.sum() < valid.numel()  # some pixels fall outside or are unknown
    torch.testing.assert_close(fast.valid, ref.valid)
    torch.testing.assert_close(fast.coords, ref.coords, atol=2e-3, rtol=0)
    torch.testing.assert_close(fast.features, ref.features, atol=1e-4, rtol=0)
    torch.testing.assert_close(fast.depth, ref.depth, atol=1e-4, rtol=0)
