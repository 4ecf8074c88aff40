"""Metrics: per-image PSNR/SSIM with known answers, lego's published numbers, FLIP against the
``flip-evaluator`` package, LPIPS from local weights."""

from __future__ import annotations

import kornia
import numpy as np
import pytest
import torch
from safetensors.torch import save_file

from roguenerf.data.readers import load_scene
from roguenerf.errors import InputError
from roguenerf.metrics import FLIPUnavailableError, LPIPSUnavailableError, flip, lpips, lpips_available, psnr, ssim


def test_psnr_known_values_per_image():
    a = torch.zeros(2, 3, 8, 8)
    b = torch.stack([torch.full((3, 8, 8), 0.1), torch.full((3, 8, 8), 0.01)])
    out = psnr(a, b)
    assert out.shape == (2,)
    assert out.tolist() == pytest.approx([20.0, 40.0], abs=1e-4)
    # kornia pools the MSE over the batch: 10 log10(1 / mean(0.01, 0.0001)) = 22.97 dB, not 30
    pooled = kornia.metrics.psnr(a, b, 1.0).item()
    assert pooled == pytest.approx(22.967, abs=1e-3)
    assert out.mean().item() == pytest.approx(30.0, abs=1e-4)
    assert psnr(a, a).tolist() == [float("inf")] * 2
    assert psnr(a[0], b[0]).shape == (1,)
    assert psnr(a * 255, b * 255, max_val=255.0).tolist() == pytest.approx([20.0, 40.0], abs=1e-4)


def test_ssim_per_image_equals_single_image_calls():
    g = torch.Generator().manual_seed(0)
    a = torch.rand(3, 3, 24, 24, generator=g)
    b = (a + 0.1 * torch.randn(3, 3, 24, 24, generator=g) * torch.tensor([0.0, 1.0, 3.0]).view(3, 1, 1, 1)).clamp(0, 1)
    out = ssim(a, b)
    assert out.shape == (3,)
    assert out[0].item() == pytest.approx(1.0, abs=1e-5)
    assert out[0] > out[1] > out[2]
    for i in range(3):
        single = kornia.metrics.ssim(a[i : i + 1], b[i : i + 1], window_size=11).mean()
        assert out[i].item() == pytest.approx(single.item(), abs=1e-6)


def _ssim_reference(a: np.ndarray, b: np.ndarray, window: int, max_val: float = 1.0) -> float:
    """SSIM written out in NumPy (float64): Gaussian window of ``window`` taps, sigma 1.5,
    reflect padding, C1 = (0.01 L)^2, C2 = (0.03 L)^2, eps 1e-12, mean over channels and pixels."""
    x = np.arange(window) - window // 2
    g = np.exp(-(x**2) / (2 * 1.5**2))
    g /= g.sum()
    r = window // 2

    def blur(img):  # (C, H, W), separable, reflect padding as torch's "reflect"
        out = np.pad(img, ((0, 0), (0, 0), (r, r)), mode="reflect")
        out = sum(g[k] * out[..., k:k + img.shape[2]] for k in range(window))
        out = np.pad(out, ((0, 0), (r, r), (0, 0)), mode="reflect")
        return sum(g[k] * out[:, k:k + img.shape[1]] for k in range(window))

    c1, c2 = (0.01 * max_val) ** 2, (0.03 * max_val) ** 2
    mu_a, mu_b = blur(a), blur(b)
    var_a, var_b, cov = blur(a * a) - mu_a**2, blur(b * b) - mu_b**2, blur(a * b) - mu_a * mu_b
    num = (2 * mu_a * mu_b + c1) * (2 * cov + c2)
    den = (mu_a**2 + mu_b**2 + c1) * (var_a + var_b + c2)
    return float((num / (den + 1e-12)).mean())


@pytest.mark.parametrize("size, window", [((1, 1), 1), ((3, 5), 5), ((2, 9), 3), ((1, 20), 1),
                                          ((5, 5), 9), ((10, 10), 11), ((24, 7), 11)])
def test_ssim_any_size_uses_the_documented_window(size, window):
    """Images smaller than the window: min(11, 2 * min(H, W) - 1) taps, known answers."""
    from roguenerf.metrics import ssim_window

    assert ssim_window(11, *size) == window
    g = torch.Generator().manual_seed(sum(size))
    a = torch.rand(2, 3, *size, generator=g, dtype=torch.float64)
    b = (a + 0.2 * torch.randn(2, 3, *size, generator=g, dtype=torch.float64)).clamp(0, 1)
    out = ssim(a, b)
    assert out.shape == (2,) and torch.isfinite(out).all()
    for i in range(2):
        assert out[i].item() == pytest.approx(_ssim_reference(a[i].numpy(), b[i].numpy(), window), abs=1e-9)
    assert ssim(a, a).tolist() == pytest.approx([1.0, 1.0], abs=1e-6)


def test_ssim_of_single_pixels_is_the_luminance_term():
    a = torch.tensor([0.2, 0.9]).view(2, 1, 1, 1)
    b = torch.tensor([0.6, 0.9]).view(2, 1, 1, 1)
    c1 = 1e-4
    want = [(2 * 0.2 * 0.6 + c1) / (0.2**2 + 0.6**2 + c1), 1.0]
    assert ssim(a, b).tolist() == pytest.approx(want, abs=1e-6)
    assert ssim(a[0], b[0]).tolist() == pytest.approx(want[:1], abs=1e-6)  # one (C, H, W) image


def test_ssim_10x10_is_kornia_with_the_full_window():
    g = torch.Generator().manual_seed(4)
    a, b = torch.rand(1, 3, 10, 10, generator=g), torch.rand(1, 3, 10, 10, generator=g)
    assert ssim(a, b).item() == kornia.metrics.ssim(a, b, window_size=11).mean().item()


def test_empty_images_and_bad_windows_are_input_errors():
    with pytest.raises(InputError, match=r"ssim: expected non-empty images .*\(1, 3, 0, 4\)"):
        ssim(torch.zeros(1, 3, 0, 4), torch.zeros(1, 3, 0, 4))
    with pytest.raises(InputError, match=r"psnr: expected non-empty images .*\(1, 3, 4, 0\)"):
        psnr(torch.zeros(1, 3, 4, 0), torch.zeros(1, 3, 4, 0))
    for window in (0, 4, -3, 2.5, True):
        with pytest.raises(InputError, match="window_size"):
            ssim(torch.zeros(1, 3, 8, 8), torch.zeros(1, 3, 8, 8), window_size=window)


def test_shape_mismatch_refused():
    with pytest.raises(InputError, match="same shape"):
        psnr(torch.zeros(1, 3, 4, 4), torch.zeros(1, 3, 4, 5))
    with pytest.raises(InputError, match="float"):
        ssim(torch.zeros(1, 3, 4, 4, dtype=torch.uint8), torch.zeros(1, 3, 4, 4, dtype=torch.uint8))


def test_lego_readme_numbers_for_test_r_0(lego_dir):
    scene = load_scene(lego_dir)
    i = scene.index("test_r_0")
    render, photo = scene.render(i)[None], scene.photo(i)[None]
    assert round(psnr(render, photo).item(), 2) == 26.77
    assert round(ssim(render, photo).item(), 4) == 0.9286


def test_lpips_unavailable_without_weights(monkeypatch, tmp_path):
    monkeypatch.delenv("ROGUENERF_LPIPS_WEIGHTS", raising=False)
    assert not lpips_available()
    assert not lpips_available(tmp_path / "missing.pth")
    x = torch.rand(1, 3, 64, 64)
    with pytest.raises(LPIPSUnavailableError, match="never downloaded"):
        lpips(x, x)
    with pytest.raises(LPIPSUnavailableError, match="missing.pth not found"):
        lpips(x, x, weights=tmp_path / "missing.pth")


def _random_lpips_weights(g):
    convs = {0: (64, 3, 11), 3: (192, 64, 5), 6: (384, 192, 3), 8: (256, 384, 3), 10: (256, 256, 3)}
    backbone = {}
    for idx, (o, i, k) in convs.items():
        backbone[f"features.{idx}.weight"] = torch.randn(o, i, k, k, generator=g) * (2 / (i * k * k)) ** 0.5
        backbone[f"features.{idx}.bias"] = torch.zeros(o)
    lins = {f"lin{n}.model.1.weight": torch.rand(1, c, 1, 1, generator=g)
            for n, c in enumerate((64, 192, 384, 256, 256))}
    return backbone, lins


def test_lpips_from_local_files(tmp_path):
    g = torch.Generator().manual_seed(0)
    backbone, lins = _random_lpips_weights(g)
    save_file(backbone, tmp_path / "alexnet.safetensors")
    torch.save(lins, tmp_path / "lin.pth")
    files = [tmp_path / "alexnet.safetensors", tmp_path / "lin.pth"]
    assert lpips_available(files)
    x = torch.rand(2, 3, 64, 64, generator=g)
    y = x.clone()
    y[1] = (y[1] + 0.3 * torch.randn(3, 64, 64, generator=g)).clamp(0, 1)
    out = lpips(x, y, weights=files)
    assert out.shape == (2,)
    assert out[0].item() == pytest.approx(0.0, abs=1e-7)
    assert out[1].item() > 1e-3
    with pytest.raises(InputError, match=r"missing \['lin0.model.1.weight'"):
        lpips(x, y, weights=[tmp_path / "alexnet.safetensors"])


# -- FLIP ---------------------------------------------------------------------------------


def _flip_direct(test: torch.Tensor, reference: torch.Tensor) -> float:
    """The package called as its README shows: HxWxC float arrays in [0, 1], reference first."""
    import flip_evaluator

    def hwc(x):
        return np.ascontiguousarray(x.permute(1, 2, 0).numpy().astype(np.float32))

    _, mean, _ = flip_evaluator.evaluate(hwc(reference), hwc(test), "LDR")
    return float(mean)


def test_flip_of_identical_images_is_zero_and_a_uniform_pair_is_the_packages_answer():
    g = torch.Generator().manual_seed(5)
    a = torch.rand(2, 3, 20, 24, generator=g)
    out = flip(a, a)
    assert out.shape == (2,) and out.tolist() == [0.0, 0.0]
    black, white = torch.zeros(1, 3, 16, 16), torch.ones(1, 3, 16, 16)
    # Uniform images have no edge or point features: only the colour term, near its maximum.
    assert flip(black, white).item() == pytest.approx(0.9674, abs=5e-4)
    assert flip(black, white).item() == pytest.approx(_flip_direct(black[0], white[0]), abs=1e-6)


def test_flip_per_image_equals_the_package_on_a_lego_view_and_on_noise(lego_dir):
    scene = load_scene(lego_dir)
    i = scene.index("test_r_0")
    render, photo = scene.render(i), scene.photo(i)
    g = torch.Generator().manual_seed(6)
    ref = torch.rand(3, 30, 40, generator=g)
    noisy = (ref + 0.1 * torch.randn(3, 30, 40, generator=g)).clamp(0, 1)
    assert flip(render, photo).item() == pytest.approx(_flip_direct(render, photo), abs=1e-6)
    assert 0.02 < flip(render, photo).item() < 0.3
    # A batch gives each image's own value; the order is (test, reference): not symmetric.
    pair = flip(torch.stack([noisy, ref]), torch.stack([ref, noisy]))
    assert pair[0].item() == pytest.approx(_flip_direct(noisy, ref), abs=1e-6)
    assert pair[1].item() == pytest.approx(_flip_direct(ref, noisy), abs=1e-6)
    assert flip(noisy, ref, ppd=30.0).item() != pytest.approx(pair[0].item(), abs=1e-4)  # the viewing condition counts


def test_flip_grows_with_blur(lego_dir):
    from kornia.filters import gaussian_blur2d

    scene = load_scene(lego_dir)
    photo = scene.photo(scene.index("test_r_0"))[None]
    photo = photo[..., photo.shape[-2] // 4:, photo.shape[-1] // 4:][..., :96, :96]  # the model's edges
    errors = [flip(gaussian_blur2d(photo, 13, (s, s)), photo).item() for s in (0.5, 1.0, 2.0)]
    assert 0.0 < errors[0] < errors[1] < errors[2], errors


def test_flip_refuses_integers_other_channels_and_bad_viewing_conditions():
    with pytest.raises(InputError, match=r"flip: first image.*uint8"):
        flip(torch.zeros(1, 3, 4, 4, dtype=torch.uint8), torch.zeros(1, 3, 4, 4))
    with pytest.raises(InputError, match=r"RGB"):
        flip(torch.zeros(1, 1, 4, 4), torch.zeros(1, 1, 4, 4))
    for bad in (0, -1.0, float("inf"), True):
        with pytest.raises(InputError, match="ppd"):
            flip(torch.zeros(1, 3, 4, 4), torch.zeros(1, 3, 4, 4), ppd=bad)


def test_flip_without_the_package_is_a_clear_error(monkeypatch):
    import sys

    from roguenerf.metrics import flip_available

    monkeypatch.setitem(sys.modules, "flip_evaluator", None)  # import raises ImportError
    assert not flip_available()
    with pytest.raises(FLIPUnavailableError, match="pip install flip-evaluator"):
        flip(torch.zeros(1, 3, 4, 4), torch.zeros(1, 3, 4, 4))
