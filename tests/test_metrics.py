"""Metrics: per-image PSNR/SSIM with known answers, lego's published numbers, LPIPS from local weights."""

from __future__ import annotations


import kornia
import pytest
import torch
from safetensors.torch import save_file

from roguenerf.data.readers import load_scene
from roguenerf.errors import InputError
from roguenerf.metrics import LPIPSUnavailableError, lpips, lpips_available, psnr, ssim
from tests.conftest import SHARED_DATA

LEGO = SHARED_DATA / "lego"


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


def test_shape_mismatch_refused():
    with pytest.raises(InputError, match="same shape"):
        psnr(torch.zeros(1, 3, 4, 4), torch.zeros(1, 3, 4, 5))
    with pytest.raises(InputError, match="float"):
        ssim(torch.zeros(1, 3, 4, 4, dtype=torch.uint8), torch.zeros(1, 3, 4, 4, dtype=torch.uint8))


def test_lego_readme_numbers_for_test_r_0():
    scene = load_scene(LEGO)
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
    lins = {f"lin{n}.model.1.weight": torch.rand(1, c, 1, 1, generator=g) for n, c in enumerate((64, 192, 384, 256, 256))}
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
