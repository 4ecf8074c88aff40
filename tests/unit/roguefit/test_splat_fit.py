"""The CPU Gaussian-splat fitter (``roguefit.splats``, ``make-pairs --preset splat``) on a toy
photo set with exact geometry."""

from __future__ import annotations

import dataclasses
import json

import pytest
import torch
from typer.testing import CliRunner

from roguecli import app
from roguefit import PRESETS, SplatConfig, make_pairs, read_photo_set
from roguefit.splats import PLY_FILE, STATE_FILE
from roguenerf.data.readers import load_scene
from roguenerf.errors import InputError
from roguenerf.splats import read_ply, render
from tests.fit_helpers import constant_psnr, depth_errors, fit_photo_set, fit_stopped_and_resumed, write_photo_set

SMALL = SplatConfig(steps=150, scale=1, init_points=2000, checkpoint_every=50)
# Measured at this budget (9 views, 30x40, seeds 0, 1, 2): training PSNR 32.3 / 32.8 / 32.5 dB,
# median (over views) of the median relative depth error 0.100 / 0.104 / 0.103 (worst view 0.132),
# coverage 100 %. Floors with margin:
FLOOR_PSNR, DEPTH_BOUND = 28.0, 0.14


pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.fixture(scope="module")
def fitted(tmp_path_factory):
    torch.set_num_threads(1)
    return fit_photo_set(tmp_path_factory, SMALL, "splat_pairs", views=9)


@pytest.mark.slow
def test_splat_fit_reaches_a_psnr_floor_and_the_true_depth(fitted):
    root, out, report, truth = fitted
    constant = constant_psnr(root)
    assert report["steps"] == SMALL.steps and report["config"] == SMALL.identity()
    assert report["train"]["psnr"] > FLOOR_PSNR, report
    assert report["train"]["psnr"] > constant + 10.0, (report["train"], constant)
    scene = load_scene(out)
    assert [f.name for f in scene.frames if f.split == "test"] == ["000", "008"]
    errors, coverage = depth_errors(out, truth, acc=False)
    assert float(torch.stack(errors).median()) < DEPTH_BOUND, errors
    assert min(coverage) > 0.95, coverage


@pytest.mark.slow
def test_splat_fit_writes_its_splats_and_they_render_the_scene_folder(fitted):
    root, out, report, _ = fitted
    g = read_ply(out / PLY_FILE)
    assert len(g) == report["gaussians"] and g.sh_degree == SMALL.sh_degree
    scene = load_scene(out)
    rgb, depth, _ = render(g, scene.frames[3].world_from_cam, scene.frames[3].K, scene.frames[3].height,
                           scene.frames[3].width)
    assert (scene.render(3) - rgb.clamp(0, 1)).abs().max() <= 0.5 / 255 + 1e-5
    assert (scene.depth(3) - depth).abs().max() < 1e-4
    # A finished folder with this configuration is left as it is.
    stamp = (out / "fit.json").stat().st_mtime_ns
    assert make_pairs(root, out, SMALL)["train"] == report["train"]
    assert (out / "fit.json").stat().st_mtime_ns == stamp


@pytest.mark.slow
def test_interrupted_splat_fit_resumes_to_the_same_result(tmp_path):
    config = dataclasses.replace(SMALL, steps=30, init_points=600, densify_every=5, checkpoint_every=7)
    run = fit_stopped_and_resumed(tmp_path, config, stop_at=12)
    assert "step 12" in run.stopped
    assert STATE_FILE in run.saved
    whole, resumed = run.whole, run.resumed
    assert resumed["steps"] == 30 and resumed["gaussians"] == whole["gaussians"]
    a, b = read_ply(tmp_path / "whole" / PLY_FILE), read_ply(tmp_path / "resumed" / PLY_FILE)
    for name in ("means", "sh", "opacity", "log_scales", "quats"):
        assert torch.allclose(getattr(a, name), getattr(b, name), atol=1e-5), name
    assert abs(resumed["train"]["psnr"] - whole["train"]["psnr"]) < 1e-3


def test_make_pairs_splat_preset_from_the_command_line(tmp_path):
    root = tmp_path / "photos"
    write_photo_set(root, views=5)
    runner = CliRunner()
    refused = runner.invoke(app, ["make-pairs", str(root), "--output", str(tmp_path / "x"), "--preset", "splat",
                                  "--resolution", "64"])
    assert refused.exit_code == 2 and "no grid" in refused.output
    result = runner.invoke(app, ["make-pairs", str(root), "--output", str(tmp_path / "out"), "--preset", "splat",
                                 "--steps", "4"])
    assert result.exit_code == 0, result.output
    report = json.loads((tmp_path / "out" / "fit.json").read_text())
    assert report["steps"] == 4 and report["config"]["field"] == "splat"
    assert report["config"]["scale"] == PRESETS["splat"].scale == 2  # fitted at half the photo size
    assert len(load_scene(tmp_path / "out").frames) == 5


def test_splat_config_refuses_nonsense():
    with pytest.raises(InputError, match="steps or minutes"):
        SplatConfig(steps=None, minutes=None)
    with pytest.raises(InputError, match="sh_degree"):
        SplatConfig(sh_degree=4)


def test_the_fit_runs_on_one_thread_and_gives_the_threads_back():
    from roguefit.splats import one_thread

    torch.set_num_threads(2)
    seen = []
    with pytest.raises(RuntimeError, match="boom"), one_thread():
        seen.append(torch.get_num_threads())
        raise RuntimeError("boom")
    assert seen == [1] and torch.get_num_threads() == 2


def test_diverged_splats_are_called_divergence_not_bad_input(tmp_path):
    """render refuses non-finite splats as input; a fit whose parameters diverged says so instead."""
    from roguefit.splats import SplatFitter
    from roguenerf.errors import TrainingDivergedError

    root = tmp_path / "photos"
    write_photo_set(root, views=3)
    fitter = SplatFitter(read_photo_set(root), dataclasses.replace(SMALL, steps=3, init_points=50), tmp_path / "s")
    with torch.no_grad():
        fitter.params["sh"][7, 0, 1] = float("nan")  # as a diverged Adam step leaves it
    with pytest.raises(TrainingDivergedError, match=r"non-finite training loss \(nan\) at step 1"):
        fitter.run(None, None)
