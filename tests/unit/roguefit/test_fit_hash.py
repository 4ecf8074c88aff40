"""The hash-grid field (``roguefit.hashfield``, ``make-pairs --preset hash``): the encoding and the
spherical harmonics against direct computations, and a short fit on the toy photo set with exact
geometry (training-view PSNR, depth), its progress reports and its resume after a stop."""

from __future__ import annotations

import dataclasses
import json
import math

import pytest
import torch
import torch.nn.functional as F

from roguefit import PRESETS, FitConfig
from roguefit.hashfield import HASH_PRIMES, HashEncoding, HashField, level_resolutions, spherical_harmonics
from roguenerf.data.readers import load_scene
from roguenerf.errors import InputError
from tests import fit_helpers

# The preset's field, small: 4 levels (16 to 32; the first two dense, the others hashed into
# 2^14 rows), at a test's budget. On the 30 x 40 px toy views a hash field memorises the
# training views with floaters unless pulled together: a 3x higher table lr and 10x the
# distortion weight (measured: train 16.5 -> 24.8 dB, depth error 0.27 -> 0.23).
SMALL_HASH = dataclasses.replace(PRESETS["hash"], resolution=32, hash_levels=4, hash_log2_table=14, steps=200,
                                 rays=1024, samples=48, prune_every=50, lr_grid=0.03, distortion_weight=0.1)


def _direct_encoding(enc: HashEncoding, point: list[float]) -> list[float]:
    """The encoding of one point written out with Python integers and floats."""
    out = []
    t = enc.table_size
    for level, res in enumerate(enc.resolutions):
        pos = [min(max(c, 0.0), 1.0) * res for c in point]
        cell = [min(math.floor(p), res - 1) for p in pos]
        frac = [p - c for p, c in zip(pos, cell, strict=True)]
        acc = [0.0] * enc.features
        for dx in (0, 1):
            for dy in (0, 1):
                for dz in (0, 1):
                    x, y, z = cell[0] + dx, cell[1] + dy, cell[2] + dz
                    if (res + 1) ** 3 <= t:
                        row = x + (res + 1) * (y + (res + 1) * z)
                    else:
                        row = ((x * HASH_PRIMES[0]) ^ (y * HASH_PRIMES[1]) ^ (z * HASH_PRIMES[2])) % t
                    w = ((frac[0] if dx else 1 - frac[0]) * (frac[1] if dy else 1 - frac[1])
                         * (frac[2] if dz else 1 - frac[2]))
                    for f in range(enc.features):
                        acc[f] += w * float(enc.tables.detach()[level, row, f])
        out += acc
    return out


def test_hash_encoding_equals_a_direct_computation():
    torch.manual_seed(0)
    enc = HashEncoding(levels=5, log2_table=10, features=3, base=4, finest=64)
    assert enc.resolutions == level_resolutions(5, 4, 64) == [4, 8, 16, 32, 64]
    with torch.no_grad():
        enc.tables.uniform_(-1.0, 1.0)
    g = torch.Generator().manual_seed(1)
    pts = torch.rand(20, 3, generator=g, dtype=torch.float64).float()
    pts[0] = torch.tensor([0.0, 0.0, 0.0])
    pts[1] = torch.tensor([1.0, 1.0, 1.0])  # the far corner: the last cell's upper vertices
    pts[2] = torch.tensor([1.5, -0.2, 0.5])  # outside: clamped
    got = enc(pts)
    assert got.shape == (20, 15)
    for i in range(20):
        want = _direct_encoding(enc, pts[i].tolist())
        assert got[i].tolist() == pytest.approx(want, abs=1e-5), i
    # Levels 0 and 1 are dense ((4 + 1)^3, (8 + 1)^3 <= 1024 rows), levels 2..4 hashed.
    assert (4 + 1) ** 3 <= 1024 and (16 + 1) ** 3 > 1024


def test_a_dense_level_is_trilinear_interpolation_of_a_grid():
    """On a level whose vertices fit the table, the encoding is grid_sample of that grid (corners aligned)."""
    enc = HashEncoding(levels=1, log2_table=12, features=2, base=8, finest=8)
    with torch.no_grad():
        enc.tables.normal_()
    side = 9
    grid = enc.tables[0, : side**3].detach().reshape(side, side, side, 2).permute(3, 0, 1, 2)[None]  # (1, F, z, y, x)
    pts = torch.rand(50, 3, generator=torch.Generator().manual_seed(2))
    want = F.grid_sample(grid, (pts * 2 - 1).reshape(1, -1, 1, 1, 3), mode="bilinear", align_corners=True)
    assert torch.allclose(enc(pts), want.reshape(2, -1).t(), atol=1e-5)


def test_encoding_gradients_reach_only_the_rows_a_point_reads():
    enc = HashEncoding(levels=2, log2_table=8, features=2, base=4, finest=32)
    pts = torch.tensor([[0.3, 0.6, 0.2]])
    enc(pts).sum().backward()
    touched = (enc.tables.grad.abs().sum(dim=-1) > 0).sum(dim=1)
    assert touched.tolist() == [8, 8]  # 8 vertices per level (no collision here)
    assert torch.allclose(enc.tables.grad.sum(dim=1), torch.ones(2, 2))  # trilinear weights sum to 1


def test_spherical_harmonics_are_orthonormal_on_the_sphere():
    n = 40000
    k = torch.arange(n, dtype=torch.float64) + 0.5
    z = 1 - 2 * k / n
    phi = math.pi * (1 + 5**0.5) * k
    r = (1 - z * z).sqrt()
    dirs = torch.stack([r * torch.cos(phi), r * torch.sin(phi), z], dim=-1)  # Fibonacci sphere
    for degree in (0, 1, 2, 3):
        sh = spherical_harmonics(dirs, degree)
        assert sh.shape == (n, (degree + 1) ** 2)
        gram = sh.T @ sh * (4 * math.pi / n)
        assert torch.allclose(gram, torch.eye(sh.shape[1], dtype=torch.float64), atol=2e-3), degree
    assert spherical_harmonics(torch.tensor([[0.0, 0.0, 1.0]]), 1)[0].tolist() == pytest.approx(
        [0.2820948, 0.0, 0.4886025, 0.0])


def test_hash_config_is_checked_and_grid_identities_are_unchanged():
    assert "kind" not in FitConfig().identity() and "hash_levels" not in PRESETS["fine"].identity()
    assert PRESETS["hash"].identity()["kind"] == "hash"
    with pytest.raises(InputError, match="kind"):
        FitConfig(kind="voxels")
    with pytest.raises(InputError, match="hash_log2_table.*hash field.*40"):
        FitConfig(kind="hash", hash_log2_table=40)
    with pytest.raises(InputError, match="hash_base"):
        FitConfig(kind="hash", resolution=32, hash_base=64)


@pytest.fixture(scope="module")
def hash_fit(tmp_path_factory):
    reports = []
    fit = fit_helpers.fit_photo_set(tmp_path_factory, SMALL_HASH, "hash_pairs", photos="hash_photos",
                                    progress=reports.append)
    return *fit, reports


@pytest.mark.slow
def test_hash_fit_reaches_a_psnr_floor_and_the_true_depth(hash_fit):
    root, out, report, truth, reports = hash_fit
    constant = fit_helpers.constant_psnr(root)
    assert report["config"]["kind"] == "hash" and report["steps"] == SMALL_HASH.steps
    assert report["train"]["psnr"] > HASH_PSNR_FLOOR, report
    assert report["train"]["psnr"] > constant + 5.0, (report["train"], constant)  # measured + 6.5 dB
    errors, coverage = fit_helpers.depth_errors(out, truth)
    assert float(torch.stack(errors).median()) < HASH_DEPTH_BOUND, errors
    assert min(coverage) > 0.9, coverage
    # Progress: one report per step, rising PSNR, the finest level's resolution as the grid.
    assert [p["step"] for p in reports] == list(range(1, SMALL_HASH.steps + 1))
    assert reports[-1]["fraction"] == 1.0 and reports[-1]["resolution"] == 32
    assert reports[-1]["psnr"] > reports[20]["psnr"] + 3.0


HASH_PSNR_FLOOR = 22.0
"""Measured 24.8 dB (grid field: > 22 at a similar budget)."""
HASH_DEPTH_BOUND = 0.35
"""Median relative depth error on the near content, measured 0.23 (the grid field's: < 0.08):
the hash field's depth on these tiny views is much rougher; the bound catches a field with no
geometry (0.5 and more) or a transparent one (the coverage check)."""


@pytest.mark.slow
def test_stopped_hash_fit_resumes_from_its_saved_step(tmp_path):
    steps_seen = []
    config = dataclasses.replace(SMALL_HASH, steps=24, prune_every=8)
    run = fit_helpers.fit_stopped_and_resumed(tmp_path, config, stop_at=10,
                                              progress=lambda p: steps_seen.append(p["step"]))
    assert run.state_json["step"] == 10 and run.state_json["config"]["kind"] == "hash"
    assert steps_seen[0] == 11 and run.resumed["steps"] == 24  # resumed from the saved step, not from 0
    assert run.resumed["train"]["psnr"] == pytest.approx(run.whole["train"]["psnr"], abs=1e-3)
    assert run.render_difference(1) <= 2 / 255


def test_hash_field_renders_with_the_shared_renderers(monkeypatch):
    """render_fast equals render for the hash field too (same sampling and compositing), and the
    colour from the density pass's cached features equals a second full evaluation."""
    g = torch.Generator().manual_seed(0)
    torch.manual_seed(0)
    field = HashField(torch.zeros(3), 1.5, levels=4, log2_table=10, base=4, finest=32)
    with torch.no_grad():
        field.encoding.tables.normal_(0, 1, generator=g)
        for p in list(field.density_mlp.parameters()) + list(field.colour_mlp.parameters()):
            p.copy_(torch.randn(p.shape, generator=g) * 0.5)
    origins, dirs, near, far = fit_helpers.ray_bundle(300, g)
    with torch.no_grad():
        ref = field.render(origins, dirs, near, far, 32)
    exact = field.render_fast(origins, dirs, near, far, 32, segment=5, termination=0.0)
    for key in ("rgb", "acc", "depth"):
        assert torch.allclose(exact[key], ref[key], atol=1e-5), key
    assert 0.1 < float(ref["acc"].mean()) < 1.0
    from roguefit.field import GridField

    monkeypatch.setattr(HashField, "_rgb_of", GridField._rgb_of)  # recompute the encoding for colour
    with torch.no_grad():
        again = field.render(origins, dirs, near, far, 32)
    assert torch.allclose(again["rgb"], ref["rgb"], atol=1e-6)
    assert float((ref["rgb"] - 0.5).abs().max()) > 0.05  # colours that would differ if misassigned


@pytest.mark.slow
def test_make_pairs_cli_hash_preset_smoke(tmp_path):
    root = tmp_path / "photos"
    fit_helpers.write_photo_set(root, views=9)
    proc = fit_helpers.run_make_pairs(root, tmp_path / "out", "--preset", "hash", "--steps", "3", "--resolution", "32")
    assert proc.returncode == 0, proc.stderr
    assert "fitted 3 steps" in proc.stderr and "fitting photos" in proc.stderr  # the progress bar
    report = json.loads((tmp_path / "out" / "fit.json").read_text())
    assert report["config"]["kind"] == "hash" and report["config"]["resolution"] == 32
    assert len(load_scene(tmp_path / "out").frames) == 9
