"""The fused C kernels (``roguenerf.native``) compute what the torch fast path computes.

Each kernel is compared with the torch code it replaces (``native.disabled()``) on inputs with
the hard cases that code handles: unknown and non-finite depths, points behind the neighbour
camera or outside its image, occlusion, half-known neighbour depth, samples beyond the edges,
NaN in the pooled maps, odd sizes, batches. The whole enhancer is compared with the plain
implementation (``reference_mode()``). Masks must agree exactly; values to float32 rounding.
The build is checked too: it happens here (``./dev test`` installs a C compiler), it is
cached, and without a compiler or with a failing one the library falls back to the torch path
with a warning, giving the same output.
"""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
import torch

from roguenerf import native
from roguenerf.fastpath import reference_mode
from roguenerf.models import build_enhancer
from roguenerf.models.flow import FlowRefiner, flow_warp, upsample_flow
from roguenerf.models.layers import PixelAttention
from roguenerf.models.uformer import LeWinBlock
from roguenerf.reprojection import reproject
from tests.model_helpers import KernelCalls, make_views, randomise

ROOT = Path(__file__).resolve().parents[4]


def test_kernels_are_built_here_and_cached():
    lib = native.library()
    assert lib is not None, "a C compiler is part of the test set-up (./dev test installs gcc)"
    path = Path(lib._name)
    assert path.parent == native.cache_dir() and path.exists()
    assert native._build(native.compiler()) == path  # the second build is the cached file


def test_reprojection_kernel_equals_the_torch_fast_path_on_hard_cases():
    g = torch.Generator().manual_seed(3)
    model = build_enhancer("micro")
    _, depth, K, P, nb = make_views(model, b=2, n=1, h=37, w=53)
    depth = depth.clone()
    depth[0, 0, :4, :6] = 0.0
    depth[0, 0, 5, 5:9] = torch.tensor([float("nan"), float("inf"), -1.0, 1e-40])
    depth[1, 0, 7, 7] = 1e11  # beyond MAX_DEPTH: unknown
    depth[1, 0, 20:, :] = 0.5  # near the camera: projects outside the neighbour or behind it
    depth[1, 0, 30:, :10] = 40.0  # far behind the neighbour's wall: occluded
    src_depth = nb.depth[:, 0].clone()
    src_depth[:, :, 10:14, 20:30] = float("nan")  # unknown neighbour depth: the weight < 0.5 cases
    src_depth[:, :, 15:17, :] = 0.0
    feats = torch.randn(nb.features[:, 0].shape, generator=g)
    poses = nb.world_from_cam[:, 0].clone()
    poses[1, 2, 3] = 3.0  # the second target's neighbour stands inside the scene: points behind it
    args = (feats, src_depth, depth, nb.K[:, 0], K, poses, P)
    with torch.inference_mode():
        with KernelCalls() as calls:
            fast = reproject(*args, leniency=0.1)
        with native.disabled():
            plain = reproject(*args, leniency=0.1)
    assert calls.names == ["reproject"]
    valid = plain.valid.bool()
    assert 0.2 * valid.numel() < valid.sum() < 0.9 * valid.numel()
    torch.testing.assert_close(fast.valid, plain.valid, atol=0, rtol=0)
    torch.testing.assert_close(fast.coords, plain.coords, atol=1e-5, rtol=0)
    torch.testing.assert_close(fast.features, plain.features, atol=1e-6, rtol=1e-6)
    torch.testing.assert_close(fast.depth, plain.depth, atol=1e-6, rtol=1e-6)
    assert fast.packed.is_contiguous(memory_format=torch.channels_last)
    assert fast.features.data_ptr() == fast.packed.data_ptr()
    with torch.no_grad(), reference_mode():
        ref = reproject(*args, leniency=0.1)
    torch.testing.assert_close(fast.valid, ref.valid, atol=0, rtol=0)
    torch.testing.assert_close(fast.features, ref.features, atol=1e-4, rtol=0)


def test_reprojection_without_neighbour_depth_keeps_the_torch_path():
    model = build_enhancer("micro")
    _, depth, K, P, nb = make_views(model, n=1, h=20, w=24)
    with torch.inference_mode(), KernelCalls() as calls:
        rp = reproject(nb.features[:, 0], None, depth, nb.K[:, 0], K, nb.world_from_cam[:, 0], P)
    assert calls.names == [] and rp.packed is None


@pytest.mark.parametrize("normalise", [False, True])
def test_flow_warp_kernel_equals_upsample_and_warp(normalise):
    g = torch.Generator().manual_seed(4)
    h, w = 37, 53
    buf = torch.randn(2, 18, h, w, generator=g).contiguous(memory_format=torch.channels_last)
    buf[:, 16] = buf[:, 16].abs() * 5
    low = torch.randn(2, 2, 5, 7, generator=g) * 3  # up to ~ +-70 px at full resolution: samples leave the image
    scale = torch.tensor([2.0, 0.7])
    with torch.inference_mode():
        with native.disabled():
            want = flow_warp(buf, upsample_flow(low, h, w))
            if normalise:
                want[:, 16:17] = (want[:, 16:17] / scale[:, None, None, None]).clamp(0, 10.0)
        got = native.flow_warp(buf, low, depth_scale=scale if normalise else None, depth_channel=16, depth_max=10.0)
    assert got.is_contiguous(memory_format=torch.channels_last)
    assert float((want == 0).all(dim=1).float().mean()) > 0.02  # some samples fall outside
    # Sample positions up to ~70 px carry float32 rounding of ~4e-6 px (the flow's upsampling
    # sums in its own order); times the map's gradients (~10 per px) that is ~4e-5.
    torch.testing.assert_close(got, want, atol=1e-4, rtol=1e-5)


def test_flow_warp_kernel_refuses_a_non_finite_flow():
    buf = torch.rand(1, 18, 16, 16).contiguous(memory_format=torch.channels_last)
    low = torch.zeros(1, 2, 2, 2)
    low[0, 0, 1, 1] = float("inf")
    with torch.inference_mode():
        assert native.flow_warp(buf, low) is None
        assert native.flow_warp(buf, torch.zeros(1, 2, 2, 2)) is not None


@pytest.mark.parametrize("size", [(16, 24), (13, 21), (1, 9), (9, 8001)])
def test_pool_kernel_equals_padded_average_pool(size):
    flow = FlowRefiner(features=16, hidden=8, iters=1)
    x = torch.randn(2, 18, *size).contiguous(memory_format=torch.channels_last)
    with torch.inference_mode():
        with KernelCalls() as calls:
            got = flow._pool(x)
        with native.disabled():
            want = flow._pool(x)
    assert calls.names == ["pool8"]
    assert got.shape == want.shape == (2, 16, -(-size[0] // 8), -(-size[1] // 8))
    torch.testing.assert_close(got, want, atol=1e-6, rtol=1e-6)


@pytest.mark.parametrize("n", [1, 7, 49152])
def test_gauss_newton_kernel_equals_the_torch_normal_equations(n):
    """The pose fit's normal equations: unused pixels (a point at z = 0 among them: skipped, as
    the reference zeroes them), a turned and moved pose."""
    from roguenerf.geometry.noise import axis_angle_to_matrix
    from roguenerf.ops import gauss_newton

    g = torch.Generator().manual_seed(n)
    points = torch.randn(n, 3, generator=g) * 0.3 + torch.tensor([0.0, 0.0, 3.0])
    sampled, render = torch.rand(9, n, generator=g) - 0.5, torch.rand(3, n, generator=g)
    use = torch.rand(n, generator=g) > 0.2
    use[0] = True
    if n > 2:
        use[1], points[1] = False, torch.tensor([0.0, 0.0, 0.0])
    pose = torch.eye(4, dtype=torch.float64)
    pose[:3, :3] = axis_angle_to_matrix(torch.tensor([0.01, -0.02, 0.005], dtype=torch.float64))
    pose[:3, 3] = torch.tensor([0.05, -0.02, 0.1])
    K = torch.tensor([[200.0, 0, 128], [0, 210, 96], [0, 0, 1]], dtype=torch.float64)
    with torch.inference_mode():
        with KernelCalls() as calls:
            A, b = gauss_newton.normal_equations(points, sampled, render, use, pose, K, 0.01)
        with native.disabled():
            A_ref, b_ref = gauss_newton.normal_equations(points, sampled, render, use, pose, K, 0.01)
    assert calls.names == ["gauss_newton"] and A.dtype == b.dtype == torch.float64
    assert torch.isfinite(A).all() and torch.isfinite(b).all()
    torch.testing.assert_close(A, A.T, rtol=1e-6, atol=0)
    # float32 sums against double ones: relative to the largest entry
    torch.testing.assert_close(A, A_ref, atol=1e-5 * float(A_ref.abs().max()), rtol=0)
    torch.testing.assert_close(b, b_ref, atol=1e-5 * float(b_ref.abs().max()), rtol=0)


@pytest.mark.parametrize("spread, hidden, size", [(False, 8, (19, 23)), (True, 8, (19, 23)), (True, 32, (3, 6001))])
def test_attention_and_pooling_kernel_equals_the_torch_composition(spread, hidden, size):
    """Also rows 6001 pixels wide with 32 hidden channels: the row buffers (2.3 MB) live on the
    heap, not on an OpenMP thread's stack."""
    g = torch.Generator().manual_seed(5)
    pa = PixelAttention(features=16, hidden=hidden)
    h, w = size
    term = torch.randn(2, hidden, h, w, generator=g).contiguous(memory_format=torch.channels_last)
    bufs = [torch.randn(2, 18, h, w, generator=g).contiguous(memory_format=torch.channels_last) for _ in range(3)]
    bufs[1][0, 3, 1, 5] = float("nan")  # NaN propagates through max and min, as torch.maximum
    cams = [torch.rand(2, 1, generator=g) for _ in range(3)]
    with torch.inference_mode():
        pooled = low = None
        for buf, cam in zip(bufs, cams):
            pooled, low = native.attend_pool(pa.neighbour_term(buf), term, pa.net[2], pa.net[1].negative_slope,
                                             cam, buf, 16, pooled, low, spread=spread)
        want_p = want_l = None
        for buf, cam in zip(bufs, cams):
            a = buf[:, :16] * (cam[:, :, None, None] * pa.from_target_term(buf, term))
            want_p = a if want_p is None else torch.maximum(want_p, a)
            want_l = a if want_l is None else torch.minimum(want_l, a)
    assert torch.isnan(pooled[0, 3, 1, 5]) and (low is None or torch.isnan(low[0, 3, 1, 5]))
    torch.testing.assert_close(pooled, want_p, atol=1e-6, rtol=1e-5, equal_nan=True)
    if spread:
        torch.testing.assert_close(low, want_l, atol=1e-6, rtol=1e-5, equal_nan=True)
    else:
        assert low is None


@pytest.mark.parametrize("dim, heads", [(16, 2), (64, 1), (12, 2)])
@pytest.mark.parametrize("shift", [False, True])
def test_lewin_block_kernels_equal_the_torch_block(shift, dim, heads):
    """16 and 64 channels (d = 8, 64): the attention half in one kernel, window by window; 12 channels
    (not a multiple of 8): LayerNorm + partition, the attention kernel and merge + LayerNorm."""
    g = torch.Generator().manual_seed(6)
    block = LeWinBlock(dim=dim, heads=heads, win_size=4, shift=shift, mlp_ratio=4.0).eval()
    with torch.no_grad():
        for p in block.parameters():
            p.copy_(torch.randn(p.shape, generator=g) * 0.3 + (1.0 if p.ndim == 1 and p is block.norm1.weight else 0.0))
    x = torch.randn(2, 16, 24, dim, generator=g)
    with torch.inference_mode():
        with KernelCalls() as calls:
            got = block(x)
        with native.disabled():
            want = block(x)
    fused = dim % 8 == 0
    assert native.lewin_attention_supported(4, dim, heads) == fused
    leff = ["leff"] if native.leff_supported(dim, 4 * dim) else []  # (not with a portable build's 4-lane vectors)
    attention = ["lewin_attention"] if fused else ["ln_partition", "window_attention", "merge_ln"]
    assert calls.names == [*attention, *leff]
    with torch.no_grad(), reference_mode():
        exact = block.double()(x.double())
        block.float()
    # Sums of C products: errors on the outputs' scale (about 6 at 16 channels, 26 at 64), the
    # kernels' within twice the torch fast path's.
    scale = exact.abs().max().item()
    err, err_torch = (got - exact).abs().max().item(), (want - exact).abs().max().item()
    assert err <= max(2 * err_torch, 1e-6 * scale), (err, err_torch, scale)
    torch.testing.assert_close(got, want, atol=2e-6 * scale, rtol=1e-5)


@pytest.mark.parametrize("size, cs, cin, co, bias", [
    ((19, 37), 18, 17, 8, False),   # the pixel attention's neighbour half: 17 of 18 packed channels
    ((2, 13), 17, 17, 16, True),    # the target half (with bias); two output blocks
    ((1, 1), 5, 3, 8, True),        # one pixel: only the centre tap lands inside
    ((6, 9), 4, 4, 8, False),       # one full 8-pixel block between the edge pixels
    ((5, 21), 16, 16, 3, True),     # the Uformer's output: 3 channels computed in a block of 8
])
def test_small_conv_kernel_equals_conv2d(size, cs, cin, co, bias):
    import torch.nn.functional as F

    g = torch.Generator().manual_seed(12)
    x = torch.randn(2, cs, *size, generator=g).contiguous(memory_format=torch.channels_last)
    x[0, :, size[0] // 2, size[1] // 2] = float("nan")  # spreads to its 3 x 3 neighbourhood, as in torch
    weight = torch.randn(co, cin, 3, 3, generator=g)
    b = torch.randn(co, generator=g) if bias else None
    with torch.inference_mode():
        with KernelCalls() as calls:
            got = native.conv3x3(x, weight, b)
    want = F.conv2d(x[:, :cin], weight, b, padding=1)
    assert calls.names == ["conv3x3"] and got.shape == want.shape
    torch.testing.assert_close(got, want, atol=1e-5, rtol=1e-5, equal_nan=True)
    with pytest.raises(ValueError, match="does not fit"):
        native.conv3x3(x, torch.randn(4, cs + 1, 3, 3))


@pytest.mark.parametrize("dim, size, batch, residual", [
    (8, (13, 23), 2, True),    # 8 channels: the 8-lane output tiles; width not a multiple of the 6-pixel blocks
    (16, (1, 7), 1, True),     # one row: both neighbour rows are the zero padding
    (24, (5, 40), 3, False),   # 16 + 8 output channels; no residual
    (40, (6, 9), 1, True),     # 32 + 8 output channels, hidden 160 = 2 x 2 x 32 + 32 (16-lane) tiles
])
def test_leff_kernel_equals_the_torch_feed_forward(dim, size, batch, residual):
    """The fused LeFF against oneDNN's linear, depthwise conv and GELUs (``native.disabled``) and
    the plain layers, with inputs from -12 to 12 standard deviations: the GELU's clamped tails
    (erf = +-1) and its curved middle both occur. The kernel's packed weights follow a change."""
    from roguenerf.models.uformer import LeFF

    if not native.leff_supported(dim, 4 * dim):
        pytest.skip(f"{dim} channels take the oneDNN path with {native.vector_width()}-lane vectors")
    g = torch.Generator().manual_seed(11)
    leff = LeFF(dim=dim, hidden=4 * dim).eval()
    with torch.no_grad():
        for p in leff.parameters():
            p.copy_(torch.randn(p.shape, generator=g) * 0.5)
    x = torch.randn(batch, *size, dim, generator=g) * torch.linspace(0.1, 12, dim)
    res = torch.randn(batch, *size, dim, generator=g) if residual else None
    for step in range(2):
        with torch.inference_mode():
            with KernelCalls() as calls:
                got = leff(x, residual=res)
            with native.disabled():
                want = leff(x, residual=res)
        assert calls.names == ["leff"]
        with torch.no_grad(), reference_mode():
            exact = leff.double()(x.double()) + (res.double() if residual else 0)
            leff.float()
        # Sums of up to 4 C products of size ~10: compare errors on the outputs' scale.
        scale = exact.abs().max().item()
        err, err_torch = (got - exact).abs().max().item(), (want - exact).abs().max().item()
        print(f"step {step}: scale {scale:.1f}, error {err:.2e} (torch fast path {err_torch:.2e})")
        assert err <= max(2 * err_torch, 1e-6 * scale)
        with torch.no_grad():
            leff.dwconv[0].weight.mul_(-1.5)  # a fine-tuning step: the second pass must see it
    with torch.inference_mode():  # weights made in inference mode (no version counter): packed per call
        made = LeFF(dim=dim, hidden=4 * dim).eval()
        with native.disabled():
            want = made(x, residual=res)
        got = made(x, residual=res)
        made.linear2.bias.add_(1.0)
        torch.testing.assert_close(made(x, residual=res), got + 1.0, atol=1e-4, rtol=1e-5)
    torch.testing.assert_close(got, want, atol=1e-4, rtol=1e-5)


def test_leff_gelu_is_the_exact_erf_gelu():
    """The kernel's GELU alone (identity linears, a centre-tap-only depthwise conv): within 1e-6
    of float64 GELU over [-40, 40]; exactly 0 far out on the negative side and x on the positive."""
    from roguenerf.models.uformer import LeFF

    dim = 16
    leff = LeFF(dim=dim, hidden=4 * dim).eval()
    if not native.leff_supported(dim, 4 * dim):
        pytest.skip("16 channels take the oneDNN path here")
    with torch.no_grad():
        for p in leff.parameters():
            p.zero_()
        leff.linear1[0].weight[:dim] = torch.eye(dim)        # hidden[:dim] = x
        leff.dwconv[0].weight[:, 0, 1, 1] = 1.0              # centre tap: gelu(gelu(x))
        leff.linear2.weight[:, :dim] = torch.eye(dim)
    x = torch.linspace(-40, 40, 16 * 9 * 11 * dim).reshape(1, 16 * 9, 11, dim)
    x[0, 0, 0, :3] = torch.tensor([-1e30, 1e30, -0.0])
    with torch.inference_mode():
        got = leff(x, residual=None)
    want = torch.nn.functional.gelu(torch.nn.functional.gelu(x.double())).float()
    assert got[0, 0, 0, :3].tolist() == [0.0, x[0, 0, 0, 1].item(), 0.0]
    got = got.clone()
    got[0, 0, 0, :3] = want[0, 0, 0, :3]  # (float64 rounds 1e30 differently)
    torch.testing.assert_close(got, want, atol=1e-6, rtol=1e-6)


@pytest.mark.parametrize("dim, heads, shifted", [(8, 1, False), (16, 1, True), (64, 4, True), (40, 5, True)])
def test_window_attention_kernel_equals_torch_attention(dim, heads, shifted):
    """Two images of 3 x 4 windows; with the shift mask the last row and column of windows mix
    regions that must not see each other (mask -100); d = 8, 16 (16-wide vectors), 40/5 = 8."""
    from roguenerf.models.uformer import WindowAttention, _shift_mask

    g = torch.Generator().manual_seed(8)
    attn = WindowAttention(dim=dim, heads=heads, win_size=4)
    with torch.no_grad():
        attn.relative_position_bias_table.copy_(torch.randn(attn.relative_position_bias_table.shape, generator=g))
        attn.to_qkv.weight.mul_(5)  # larger logits than at initialisation: a sharper softmax
    mask = _shift_mask(12, 16, 4, 2, "cpu") if shifted else None
    x = torch.randn(2 * 12, 16, dim, generator=g)
    with torch.inference_mode():
        with KernelCalls() as calls:
            got = attn(x, mask)
        with native.disabled():
            want = attn(x, mask)
    assert calls.names == ["window_attention"]
    torch.testing.assert_close(got, want, atol=2e-5, rtol=2e-5)
    with torch.no_grad(), reference_mode():
        ref = attn(x, mask)
    torch.testing.assert_close(got, ref, atol=2e-5, rtol=2e-5)


def test_enhancer_with_kernels_equals_the_plain_implementation():
    model = randomise(build_enhancer("micro", num_neighbours=3).eval())
    render, depth, K, P, nb = make_views(model, b=2, n=3, h=40, w=56)
    depth = depth.clone()
    depth[0, 0, :5, :7] = float("nan")
    with torch.inference_mode(), KernelCalls() as calls:
        fast = model(render, depth, K, P, nb)
    with torch.inference_mode(), native.disabled():
        torch_fast = model(render, depth, K, P, nb)
    with torch.no_grad(), reference_mode():
        ref = model(render, depth, K, P, nb)
    assert {"reproject", "pool8", "flow_warp", "attend_pool", "lewin_attention", "conv3x3"} <= set(calls.names)
    assert ("leff" in calls.names) == native.leff_supported(8, 32)  # micro's first level
    torch.testing.assert_close(fast, torch_fast, atol=1e-5, rtol=0)
    torch.testing.assert_close(fast, ref, atol=2e-4, rtol=0)


def _run(code: str, env: dict) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", textwrap.dedent(code)], cwd=ROOT, env=env, capture_output=True,
                          text=True, timeout=300)


@pytest.mark.slow
@pytest.mark.parametrize("how", ["off", "failing compiler", "no compiler"])
def test_without_kernels_the_torch_path_gives_the_same_output(how, tmp_path):
    env = {**os.environ, "ROGUENERF_NATIVE_CACHE": str(tmp_path / "cache")}
    if how == "off":
        env["ROGUENERF_NATIVE"] = "0"
    elif how == "failing compiler":
        env["CC"] = "false"
    else:
        env.pop("CC", None)
        env["PATH"] = str(tmp_path)  # no cc, gcc or clang on it
    code = """
        import logging, sys, torch
        logging.basicConfig(level=logging.WARNING)
        sys.path.insert(0, ".")
        from roguenerf import native
        from roguenerf.fastpath import reference_mode
        from roguenerf.models import build_enhancer
        from tests.model_helpers import KernelCalls, make_views, randomise
        assert native.library() is None
        model = randomise(build_enhancer("micro").eval())
        views = make_views(model, n=2, h=24, w=32)
        with torch.inference_mode():
            fast = model(*views)
        with torch.no_grad(), reference_mode():
            ref = model(*views)
        torch.testing.assert_close(fast, ref, atol=2e-4, rtol=0)
        print("same output")
    """
    run = _run(code, env)
    assert run.returncode == 0, run.stderr
    assert "same output" in run.stdout
    if how == "off":
        assert "roguenerf.native" not in run.stderr  # turned off on purpose: no warning
    else:
        assert "roguenerf.native" in run.stderr  # the user is told why it is slower
    assert not list((tmp_path / "cache").glob("*.so"))


@pytest.mark.slow
def test_a_portable_build_passes_the_kernel_tests(tmp_path):
    """Built without -march=native (a compiler that refuses it, FLAG_SETS' fallback), the kernels
    use 4-lane vectors: they must still pass every kernel test above. Vectors wider than the
    target's are never used (kernels.c, VW): GCC lowers their comparisons lane by lane."""
    cc = native.compiler()
    wrapper = tmp_path / "cc"
    wrapper.write_text(f"#!{sys.executable}\nimport os, sys\n"
                       f"os.execv({cc!r}, [{cc!r}] + [a for a in sys.argv[1:] if a != '-march=native'])\n")
    wrapper.chmod(0o755)
    env = {**os.environ, "CC": str(wrapper), "ROGUENERF_NATIVE_CACHE": str(tmp_path / "cache")}
    lanes = _run("import sys; sys.path.insert(0, '.')\nfrom roguenerf import native\nprint(native.vector_width())",
                 env)
    assert lanes.returncode == 0 and lanes.stdout.split() == ["4"], lanes.stderr
    run = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-k",
                          "not without_kernels and not portable", __file__], cwd=ROOT, env=env,
                         capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stdout[-3000:]
    assert " passed" in run.stdout.splitlines()[-1]
