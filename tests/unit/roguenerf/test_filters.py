"""The torch bodies of roguenerf.ops.filters against kornia's filters (the reference) and known answers."""

import pytest
import torch
from kornia.filters import gaussian_blur2d
from kornia.filters import spatial_gradient as kornia_gradient

from roguenerf.fastpath import reference_mode
from roguenerf.ops.filters import gaussian_blur, spatial_gradient


@pytest.fixture
def image():
    g = torch.Generator().manual_seed(3)
    return torch.rand(2, 3, 17, 23, generator=g)


@pytest.mark.parametrize("size,sigma", [(3, 0.5), (7, 1.0), (13, 2.0), (5, 3.0)])
@pytest.mark.parametrize("border", ["replicate", "reflect"])
def test_blur_is_kornias(image, size, sigma, border):
    expected = gaussian_blur2d(image, (size, size), (sigma, sigma), border_type=border)
    with torch.no_grad():
        got = gaussian_blur(image, size, sigma, border=border)
    assert got.shape == image.shape
    assert torch.allclose(got, expected, atol=2e-6)


def test_blur_keeps_a_constant_and_the_mass_of_a_spike():
    flat = torch.full((1, 2, 9, 11), 0.37)
    assert torch.allclose(gaussian_blur(flat, 7, 1.5), flat, atol=1e-7)
    spike = torch.zeros(1, 1, 15, 15)
    spike[0, 0, 7, 7] = 1.0
    out = gaussian_blur(spike, 5, 1.0)
    assert out.sum().item() == pytest.approx(1.0, abs=1e-6)  # no mass reaches the edges
    assert out[0, 0, 7, 7] == out.max()
    assert torch.allclose(out[0, 0], out[0, 0].T, atol=1e-7)


def test_float64_and_strided_inputs(image):
    x = image.double().transpose(-1, -2)  # not contiguous
    got = gaussian_blur(x, 5, 1.0)
    assert got.dtype == torch.float64
    assert torch.allclose(got, gaussian_blur2d(x, (5, 5), (1.0, 1.0), border_type="replicate"), atol=1e-12)
    assert torch.allclose(spatial_gradient(x), kornia_gradient(x, mode="diff", order=1, normalized=True), atol=1e-12)


def test_blur_refuses_an_even_size(image):
    with pytest.raises(ValueError, match="odd"):
        gaussian_blur(image, 4, 1.0)


def test_gradient_is_kornias(image):
    with torch.no_grad():
        got = spatial_gradient(image)
    assert torch.allclose(got, kornia_gradient(image, mode="diff", order=1, normalized=True), atol=1e-7)


def test_gradient_of_a_ramp():
    # x = 2u + 5v: central differences give 2 and 5 inside, half that on the repeated edges
    v, u = torch.meshgrid(torch.arange(6.0), torch.arange(8.0), indexing="ij")
    g = spatial_gradient((2 * u + 5 * v)[None, None])[0, 0]
    assert torch.equal(g[0, :, 1:-1], torch.full((6, 6), 2.0))
    assert torch.equal(g[0, :, 0], torch.full((6,), 1.0))
    assert torch.equal(g[1, 1:-1], torch.full((4, 8), 5.0))
    assert torch.equal(g[1, -1], torch.full((8,), 2.5))


def test_reference_mode_runs_kornia_and_gradients_flow(image):
    with reference_mode():
        ref = gaussian_blur(image, 7, 1.0)
    assert torch.equal(ref, gaussian_blur2d(image, (7, 7), (1.0, 1.0), border_type="replicate"))
    x = image.clone().requires_grad_(True)
    spatial_gradient(gaussian_blur(x, 5, 1.0)).square().sum().backward()
    assert x.grad is not None and torch.isfinite(x.grad).all() and x.grad.abs().sum() > 0


def test_channels_blurred_together_are_each_blurred_alone():
    """What the agreement test relies on when it blurs every neighbour's colour and mask in one
    call: no channel reaches another, at any batch size."""
    g = torch.Generator().manual_seed(5)
    x = torch.rand(2, 12, 40, 50, generator=g)
    together = gaussian_blur(x, 13, 2.0)
    alone = torch.cat([gaussian_blur(x[:, i:i + 1], 13, 2.0) for i in range(12)], dim=1)
    assert torch.allclose(together, alone, atol=1e-7)
    assert torch.allclose(together[1:], gaussian_blur(x[1:], 13, 2.0), atol=1e-7)
    assert together.is_contiguous()


def test_box_sum_is_the_pooling_and_sums_nine_pixels(image):
    from roguenerf.ops.filters import box_sum3

    expected = torch.nn.functional.avg_pool2d(image, 3, stride=1, padding=1) * 9
    assert torch.allclose(box_sum3(image), expected, atol=1e-5)
    with reference_mode():
        assert torch.allclose(box_sum3(image), expected, atol=1e-6)
    ones = box_sum3(torch.ones(1, 1, 4, 5))[0, 0]
    assert ones[1, 1] == pytest.approx(9.0) and ones[0, 0] == pytest.approx(4.0) and ones[0, 2] == pytest.approx(6.0)
