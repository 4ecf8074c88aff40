"""The Uformer: official architecture (parameter counts), any input size, attention paths."""

from __future__ import annotations

import pytest
import torch

from roguenerf.models import make_config
from roguenerf.models.uformer import LeWinBlock, Uformer, WindowAttention, _shift_mask

pytestmark = pytest.mark.usefixtures("one_thread")


def _perturb_output(u: Uformer, std: float = 0.05) -> Uformer:
    """The output projection is zero-initialised; give it weights so outputs carry signal."""
    torch.nn.init.normal_(u.output_proj.weight, std=std)
    return u


@pytest.mark.parametrize(("variant", "millions"), [("T", 5.23), ("S", 20.63), ("B", 50.88)])
def test_parameter_counts_match_the_official_models(variant, millions):
    """Uformer paper, Table 1: T 5.23 M, S 20.63 M, B 50.88 M parameters (RGB in and out)."""
    u = Uformer(make_config(variant).uformer, in_channels=3, out_channels=3)
    assert round(sum(p.numel() for p in u.parameters()) / 1e6, 2) == millions


@pytest.mark.parametrize(("h", "w"), [(1, 1), (5, 7), (37, 53), (64, 64), (70, 130)])
def test_any_size_in_same_size_out(h, w):
    torch.manual_seed(0)
    u = _perturb_output(Uformer(make_config("nano").uformer, in_channels=64))
    y = u(torch.randn(2, 64, h, w))
    assert y.shape == (2, 3, h, w)
    assert torch.isfinite(y).all()
    assert y.abs().max() > 0


def test_untrained_output_is_exactly_zero():
    u = Uformer(make_config("nano").uformer, in_channels=64)
    assert torch.equal(u(torch.randn(1, 64, 20, 30)), torch.zeros(1, 3, 20, 30))


def test_output_does_not_depend_on_the_padding_content():
    """Padding is cropped away, and a multiple-sized input is not padded: cropping the
    padded-size result of a bigger input differs, but a same-size input gives itself."""
    torch.manual_seed(0)
    u = _perturb_output(Uformer(make_config("micro").uformer, in_channels=8)).eval()
    x = torch.randn(1, 8, 64, 64)
    padded = u(x)
    assert torch.allclose(u(x.clone()), padded)
    small = u(x[..., :50, :50])
    assert small.shape == (1, 3, 50, 50)
    assert not torch.allclose(small, padded[..., :50, :50], atol=1e-6)


def test_fused_attention_equals_reference_path():
    torch.manual_seed(0)
    attn = WindowAttention(dim=32, heads=4, win_size=4)
    torch.nn.init.normal_(attn.relative_position_bias_table, std=1.0)
    x = torch.randn(2 * 4, 16, 32)
    mask = _shift_mask(8, 8, 4, 2, x.device)
    fused = attn(x, mask)
    attn.fused = False
    reference = attn(x, mask)
    assert torch.allclose(fused, reference, atol=1e-5)


def test_relative_position_index_known_answer():
    """2x2 window: tokens (0,0),(0,1),(1,0),(1,1); offset (dy+1)*3 + (dx+1)."""
    attn = WindowAttention(dim=4, heads=1, win_size=2)
    expected = torch.tensor([[4, 3, 1, 0], [5, 4, 2, 1], [7, 6, 4, 3], [8, 7, 5, 4]])
    assert torch.equal(attn.relative_position_index, expected)


def test_shift_mask_known_answer():
    """8x8 tokens, windows of 4, shift 2: the first window is one region (no mask); in the
    last window the four 2x2 quadrants come from different image regions and are masked."""
    mask = _shift_mask(8, 8, 4, 2, "cpu")
    assert mask.shape == (4, 16, 16)
    assert (mask[0] == 0).all()
    quadrant = torch.tensor([0, 0, 1, 1, 0, 0, 1, 1, 2, 2, 3, 3, 2, 2, 3, 3])
    expected = torch.where(quadrant[:, None] == quadrant[None, :], 0.0, -100.0)
    assert torch.equal(mask[3], expected)


def test_shifted_windows_reach_across_the_window_border():
    """16x16 tokens, windows of 8: output token (2, 6) of an unshifted block depends only on
    window 0 (rows/cols 0..7; LeFF's 3x3 conv stays inside it). Shifted by 4, its window
    holds original columns 4..11, so inputs in columns 9..11 must matter."""
    torch.manual_seed(0)

    def grad_beyond(shift: bool) -> float:
        block = LeWinBlock(dim=8, heads=1, win_size=8, shift=shift, mlp_ratio=2.0)
        x = torch.randn(1, 16, 16, 8, requires_grad=True)
        block(x)[0, 2, 6].sum().backward()
        return float(x.grad[0, :, 8:].abs().sum())

    assert grad_beyond(False) == 0.0
    assert grad_beyond(True) > 0.0
