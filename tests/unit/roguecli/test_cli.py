"""The `roguenerf` command (package roguecli, the one command line: every command, serve and
make-pairs included): exact flags, JSON output, exit codes and one-line errors."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from typer.testing import CliRunner

import roguenerf.checkpoint
from roguecli import app
from roguenerf.checkpoint import load_checkpoint, save_checkpoint
from roguenerf.data.toy import make_toy_scene
from roguenerf.enhance import EnhanceOptions
from roguenerf.models import build_enhancer
from roguenerf.training import evaluate

runner = CliRunner()
FAST = ["--variant", "micro", "--crop", "16", "--neighbours", "2"]


@pytest.fixture(scope="module")
def scene_dir(tmp_path_factory):
    root = tmp_path_factory.mktemp("scene")
    make_toy_scene(root, seed=4, n_train=5, n_test=2, height=24, width=32)
    return root


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory):
    torch.manual_seed(0)
    model = build_enhancer("micro", num_neighbours=2)
    with torch.no_grad():
        for p in model.parameters():
            p.add_(0.02 * torch.randn_like(p))
    return save_checkpoint(tmp_path_factory.mktemp("ckpt") / "m.safetensors", model)


def _run(*args):
    result = runner.invoke(app, [str(a) for a in args])
    return result


def test_evaluate_json_is_one_object_matching_the_library(scene_dir, checkpoint):
    result = _run("evaluate", scene_dir, "--checkpoint", checkpoint, "--json")
    assert result.exit_code == 0, result.output
    report = json.loads(result.stdout)
    assert set(report) >= {"views", "render", "enhanced"}
    assert [v["name"] for v in report["views"]] == ["test_000", "test_001"]
    assert set(report["render"]) >= {"psnr", "ssim", "flip"} and set(report["enhanced"]) >= {"psnr", "ssim", "flip"}
    assert all(0.0 <= v[k]["flip"] <= 1.0 for v in report["views"] for k in ("render", "enhanced"))
    from roguenerf.data.readers import load_scene

    model, _ = load_checkpoint(checkpoint)
    direct = evaluate(load_scene(scene_dir), model)
    assert report["render"]["psnr"] == pytest.approx(direct["render"]["psnr"], abs=1e-6)
    assert report["enhanced"]["psnr"] == pytest.approx(direct["enhanced"]["psnr"], abs=1e-4)
    assert report["render"]["flip"] == pytest.approx(direct["render"]["flip"], abs=1e-6)
    mean_flip = sum(v["render"]["flip"] for v in report["views"]) / len(report["views"])
    assert report["render"]["flip"] == pytest.approx(mean_flip, abs=1e-6)
    from roguenerf.metrics import flip

    scene = load_scene(scene_dir)
    first = scene.index(report["views"][0]["name"])
    assert report["views"][0]["render"]["flip"] == pytest.approx(
        float(flip(scene.render(first), scene.photo(first))[0]), abs=1e-6)


def test_evaluate_reports_trust_and_no_trust_keeps_the_whole_change(scene_dir, checkpoint):
    """Per view, the neighbours' agreement and the share of the change kept (as the library's
    SceneEnhancer gives them); with --no-trust the whole change is kept."""
    from roguenerf.data.readers import load_scene
    from roguenerf.enhance.trust import TrustConfig, trust_factor

    on = json.loads(_run("evaluate", scene_dir, "--checkpoint", checkpoint, "--json").stdout)
    off = json.loads(_run("evaluate", scene_dir, "--checkpoint", checkpoint, "--json", "--no-trust").stdout)
    model, _ = load_checkpoint(checkpoint)
    direct = evaluate(load_scene(scene_dir), model, options=EnhanceOptions(trust=None))
    for v_on, v_off, v_direct in zip(on["views"], off["views"], direct["views"], strict=True):
        assert 0 <= v_on["agreement"] <= 1
        if v_on["agreement"] >= TrustConfig().local_below:
            assert v_on["trust"] == pytest.approx(trust_factor(v_on["agreement"], TrustConfig()), abs=1e-3)
        else:  # per pixel: the mean share kept (tests/unit/roguenerf/enhance/test_trust.py)
            assert 0 <= v_on["trust"] < 1
        assert v_off["trust"] is None and v_off["agreement"] == v_on["agreement"]  # colour matching measured it
        assert v_off["enhanced"]["psnr"] == pytest.approx(v_direct["enhanced"]["psnr"], abs=1e-4)
        if v_on["trust"] == 1:
            assert v_on["enhanced"]["psnr"] == pytest.approx(v_off["enhanced"]["psnr"], abs=1e-4)


def test_evaluate_table(scene_dir, checkpoint):
    result = _run("evaluate", scene_dir, "--checkpoint", checkpoint, "--split", "train")
    assert result.exit_code == 0, result.output
    lines = result.stdout.strip().splitlines()
    assert len(lines) == 1 + 5 + 1 and lines[-1].startswith("mean")
    assert lines[0].split()[1:] == ["render", "PSNR", "SSIM", "FLIP", "enhanced", "PSNR", "SSIM", "FLIP", "kept"]
    assert len(lines[-1].split()) == 8
    # The share of the change kept, per view, as --json reports it.
    report = json.loads(_run("evaluate", scene_dir, "--checkpoint", checkpoint, "--split", "train", "--json").stdout)
    for line, view in zip(lines[1:-1], report["views"], strict=True):
        assert line.split()[-1] == ("-" if view["trust"] is None else f"{view['trust']:.0%}")


def test_bad_scene_dir_exits_2_naming_the_path(tmp_path, checkpoint):
    missing = tmp_path / "no_such_scene"
    result = _run("evaluate", missing, "--checkpoint", checkpoint, "--json")
    assert result.exit_code == 2
    assert str(missing) in result.stderr and result.stderr.startswith("error: ")
    assert len(result.stderr.strip().splitlines()) == 1 and "Traceback" not in result.output
    assert result.stdout == ""
    empty = tmp_path / "empty"
    empty.mkdir()
    result = _run("enhance", empty, "--view", "x", "--checkpoint", checkpoint, "--output", tmp_path / "o.png")
    assert result.exit_code == 2 and str(empty) in result.stderr


def test_missing_default_checkpoint_is_explained(scene_dir, tmp_path, monkeypatch):
    absent = tmp_path / "weights" / "default.safetensors"
    monkeypatch.setattr(roguenerf.checkpoint, "default_checkpoint_path", lambda must_exist=True: absent)
    result = _run("evaluate", scene_dir)
    assert result.exit_code == 2
    assert "default checkpoint" in result.stderr and str(absent) in result.stderr


def test_enhance_writes_the_png(scene_dir, checkpoint, tmp_path):
    from roguenerf.data.readers import load_scene
    from roguenerf.imageio import read_image
    from roguenerf.inference import SceneEnhancer

    out = tmp_path / "enhanced.png"
    result = _run("enhance", scene_dir, "--view", "test_001", "--checkpoint", checkpoint, "--output", out)
    assert result.exit_code == 0, result.output
    image = read_image(out)
    assert image.shape == (3, 24, 32)
    model, _ = load_checkpoint(checkpoint)
    expected = SceneEnhancer(load_scene(scene_dir), model).enhance_view("test_001").image
    assert float((image - expected).abs().max()) <= 1 / 255 + 1e-6  # 8-bit PNG rounding
    bad = _run("enhance", scene_dir, "--view", "nope", "--checkpoint", checkpoint, "--output", out)
    assert bad.exit_code == 2 and "nope" in bad.stderr


def test_enhance_keeps_its_pose_judgements_for_the_next_run(scene_dir, checkpoint, tmp_path, monkeypatch):
    """A second one-view command on the scene starts from the first one's pose judgements
    (roguenerf.enhance.settled, in the user's cache) and writes the same PNG."""
    import shutil

    from roguenerf.data.readers import load_scene
    from roguenerf.enhance import settled

    monkeypatch.setenv("ROGUENERF_SETTLED_CACHE", str(tmp_path / "cache"))
    copy = tmp_path / "scene"
    shutil.copytree(scene_dir, copy)
    kept = settled.default_path(copy)
    outputs = []
    for n in range(2):
        outputs.append(tmp_path / f"run{n}.png")
        result = _run("enhance", copy, "--view", "test_001", "--checkpoint", checkpoint, "--output", outputs[-1])
        assert result.exit_code == 0, result.output
        if n == 0:
            assert kept.is_file()
            names = set(json.loads(kept.read_text())["views"])
            assert names and names <= {f.name for f in load_scene(copy).frames if f.split == "train"}
    assert outputs[0].read_bytes() == outputs[1].read_bytes()


def test_enhance_never_imports_kornia(scene_dir, checkpoint, tmp_path):
    """Issue 51: importing kornia imports all of it, 0.3 s of a one-view command on 2 cores; a
    request (pose fits, reprojection, model, colour, trust) runs on roguenerf.ops' torch bodies."""
    out = tmp_path / "enhanced.png"
    code = ("import sys\nfrom roguecli import app\ntry:\n"
            f"    app(['enhance', {str(scene_dir)!r}, '--view', 'test_001', '--checkpoint', {str(checkpoint)!r},"
            f" '--output', {str(out)!r}])\nexcept SystemExit as exc:\n    assert not exc.code, exc.code\n"
            "print('aligned' if 'roguenerf.enhance.align' in sys.modules else 'not aligned', "
            "'kornia' in sys.modules)")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0 and out.exists(), proc.stdout + proc.stderr
    assert proc.stdout.strip().splitlines()[-1] == "aligned False", proc.stdout + proc.stderr


EXIT_PROBE = r"""
import atexit, sys, threading
from pathlib import Path
marks = Path(sys.argv[1])
atexit.register(lambda: (marks / "atexit").write_text("ran"))
# run by the interpreter's own shutdown (threading._shutdown, before it joins the threads),
# which os._exit skips
threading._register_atexit(lambda: (marks / "teardown").write_text("ran"))
if sys.argv[2] == "thread":  # a non-daemon thread still at work when the command ends
    shutdown = threading.Event()
    threading._register_atexit(shutdown.set)
    threading.Thread(target=lambda: (shutdown.wait(), (marks / "thread").write_text("done"))).start()
from roguecli import main
sys.argv = ["roguenerf", *sys.argv[3:]]
main()
"""


@pytest.mark.parametrize("thread", ["none", "thread"])
def test_enhance_ends_the_process_at_once_and_loses_nothing(scene_dir, checkpoint, tmp_path, thread):
    """Issue 51: a one-view ``enhance`` skips the interpreter's teardown (``os._exit`` once its PNG
    is written and closed): the atexit handlers still run, every line is printed, the PNG is
    whole, and a non-daemon thread still running gets its normal exit instead."""
    from roguenerf.imageio import read_image

    out = tmp_path / "enhanced.png"
    proc = subprocess.run([sys.executable, "-c", EXIT_PROBE, str(tmp_path), thread, "enhance", str(scene_dir),
                           "--view", "test_001", "--checkpoint", str(checkpoint), "--output", str(out)],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip().splitlines() == [str(out)] and "enhanced test_001 in" in proc.stderr
    assert (tmp_path / "atexit").read_text() == "ran"
    assert (tmp_path / "thread").exists() == (thread == "thread")  # never cut short
    assert (tmp_path / "teardown").exists() == (thread == "thread")  # no teardown unless a thread runs
    model, _ = load_checkpoint(checkpoint)
    from roguenerf.data.readers import load_scene
    from roguenerf.inference import SceneEnhancer

    expected = SceneEnhancer(load_scene(scene_dir), model).enhance_view("test_001").image
    assert float((read_image(out) - expected).abs().max()) <= 1 / 255 + 1e-6
    bad = subprocess.run([sys.executable, "-c", EXIT_PROBE, str(tmp_path), "none", "enhance", str(scene_dir),
                          "--view", "nope", "--checkpoint", str(checkpoint), "--output", str(out)],
                         capture_output=True, text=True, timeout=300)
    assert bad.returncode == 2 and "nope" in bad.stderr  # a failure exits as before


def test_enhance_tile_is_the_libraries_tile(scene_dir, checkpoint, tmp_path):
    """``--tile`` (issue 51: larger tiles are faster at full HD, and take more memory) is
    EnhanceOptions.tile: the same image as the library's tiled enhancement; bad sizes are refused."""
    from roguenerf.data.readers import load_scene
    from roguenerf.enhance import EnhanceOptions
    from roguenerf.imageio import read_image
    from roguenerf.inference import SceneEnhancer

    out = tmp_path / "tiled.png"
    result = _run("enhance", scene_dir, "--view", "test_001", "--checkpoint", checkpoint, "--output", out,
                  "--tile", "16")
    assert result.exit_code == 0, result.output
    model, _ = load_checkpoint(checkpoint)
    scene = load_scene(scene_dir)
    tiled = SceneEnhancer(scene, model, options=EnhanceOptions(tile=16)).enhance_view("test_001").image
    whole = SceneEnhancer(scene, model).enhance_view("test_001").image
    assert float((read_image(out) - tiled).abs().max()) <= 1 / 255 + 1e-6
    assert float((tiled - whole).abs().max()) > 1.5 / 255  # 16-pixel tiles do change this 24 x 32 view
    bad = _run("enhance", scene_dir, "--view", "test_001", "--checkpoint", checkpoint, "--output", out,
               "--tile", "8")
    assert bad.exit_code == 2 and "tile: expected >= 16 pixels, got 8" in bad.stderr


@pytest.mark.slow
def test_finetune_from_scratch_then_resume_to_more_steps(scene_dir, tmp_path):
    out = tmp_path / "ft"
    result = _run("finetune", scene_dir, "--scratch", "--steps", "2", "--output", out, "--no-eval", *FAST)
    assert result.exit_code == 0, result.output
    assert result.stdout.strip() == str(out / "model.safetensors")
    _, meta = load_checkpoint(out / "model.safetensors")
    assert meta["training"]["steps"] == 2
    assert "plan: cpu" in result.stderr and "L1 loss alone" in result.stderr
    assert "cosine to 0" in result.stderr  # the default schedule, printed with the plan
    constant = _run("finetune", scene_dir, "--scratch", "--steps", "1", "--output", tmp_path / "c", "--no-eval",
                    "--lr-schedule", "constant", *FAST)
    assert constant.exit_code == 0 and "cosine to 0" not in constant.stderr
    assert load_checkpoint(tmp_path / "c" / "model.safetensors")[1]["training"]["plan"]["lr_schedule"] == "constant"
    for flag, frozen in (("--freeze-neighbour-encoder", True), ("--train-neighbour-encoder", False)):
        run = _run("finetune", scene_dir, "--scratch", "--steps", "1", "--output", tmp_path / flag, "--no-eval",
                   flag, *FAST)
        assert run.exit_code == 0, run.output
        assert ("conv_H frozen" in run.stderr) is frozen
        assert load_checkpoint(tmp_path / flag / "model.safetensors")[1]["training"]["plan"][
            "freeze_neighbour_encoder"] is frozen
    warped = _run("finetune", scene_dir, "--scratch", "--steps", "1", "--output", tmp_path / "w", "--no-eval",
                  "--render-warp", "4", *FAST)
    assert warped.exit_code == 0 and "warped (up to 4 px)" in warped.stderr
    assert load_checkpoint(tmp_path / "w" / "model.safetensors")[1]["training"]["plan"]["render_warp"] == 4.0
    drawn = _run("finetune", scene_dir, "--scratch", "--steps", "1", "--output", tmp_path / "d", "--no-eval",
                 "--neighbour-renders", "0.5", *FAST)
    assert drawn.exit_code == 0 and "50% of the target renders drawn" in drawn.stderr, drawn.output
    assert load_checkpoint(tmp_path / "d" / "model.safetensors")[1]["training"]["plan"]["neighbour_renders"] == 0.5
    more = _run("finetune", scene_dir, "--scratch", "--steps", "3", "--output", out, "--no-eval", *FAST)
    assert more.exit_code == 0, more.output
    assert "resuming finetune from step 2" in more.stderr
    assert load_checkpoint(out / "model.safetensors")[1]["training"]["steps"] == 3


def test_finetune_ablation_from_a_full_checkpoint(scene_dir, checkpoint, tmp_path):
    out = tmp_path / "abl"
    result = _run("finetune", scene_dir, "--checkpoint", checkpoint, "--steps", "1", "--output", out, "--no-eval",
                  "--without", "attention", "--without", "refinement", "--crop", "16")
    assert result.exit_code == 0, result.output
    assert "dropped: camera_attention, flow, pixel_attention" in result.stderr
    model, _ = load_checkpoint(out / "model.safetensors")
    assert not model.config.use_attention and not model.config.use_refinement and model.config.use_alignment


def test_pretrain_with_toy_scenes(scene_dir, tmp_path):
    out = tmp_path / "pt"
    result = _run("pretrain", scene_dir, "--toy", "1", "--steps", "1", "--depth-noise", "0.3", "--batch", "3",
                  "--output", out, *FAST)
    assert result.exit_code == 0, result.output
    _, meta = load_checkpoint(out / "model.safetensors")
    assert len(meta["training"]["scenes"]) == 2 and meta["training"]["plan"]["depth_noise"] == 0.3
    assert meta["training"]["plan"]["batch"] == 3
    assert (out / "toy" / "toy_000" / "transforms.json").is_file()
    bad = _run("pretrain", "--toy", "1", "--steps", "1", "--depth-noise", "9", "--output", tmp_path / "x", *FAST)
    assert bad.exit_code == 2 and "depth_noise" in bad.stderr and "Traceback" not in bad.output
    bad = _run("pretrain", "--toy", "1", "--steps", "1", "--batch", "0", "--output", tmp_path / "x", *FAST)
    assert bad.exit_code == 2 and "batch" in bad.stderr and "Traceback" not in bad.output


@pytest.mark.slow
def test_pretrain_held_out_from_adds_the_scene_and_its_held_out_views(scene_dir, tmp_path):
    out = tmp_path / "pt"
    result = _run("pretrain", "--toy", "1", "--held-out-from", scene_dir, "--held-out-share", "0.3",
                  "--steps", "1", "--output", out, *FAST)
    assert result.exit_code == 0, result.output
    assert "held-out views 30%" in result.stderr
    _, meta = load_checkpoint(out / "model.safetensors")
    assert len(meta["training"]["scenes"]) == 2 and meta["training"]["plan"]["held_out_share"] == 0.3
    # a scene without held-out views is refused before training, with the reason
    from roguenerf.data.toy import make_toy_scene

    make_toy_scene(tmp_path / "bare", seed=3, n_train=3, n_test=0, height=20, width=24)
    bare = _run("pretrain", "--held-out-from", tmp_path / "bare", "--steps", "1", "--output", tmp_path / "x", *FAST)
    assert bare.exit_code == 2 and "no held-out views" in bare.stderr and "Traceback" not in bare.output


@pytest.mark.parametrize("args, message", [
    (["--steps", "1", "--minutes", "1"], "either --minutes or --steps"),
    (["--steps", "1", "--without", "uformer"], "--without"),
    (["--steps", "1", "--variant", "huge"], "variant"),
    (["--steps", "1", "--lr-schedule", "step"], "lr_schedule"),
    (["--steps", "1", "--render-warp", "100"], "render_warp"),
    (["--steps", "1", "--depth-noise", "-1"], "depth_noise"),
    (["--steps", "1", "--neighbour-renders", "1.5"], "neighbour_renders"),
])
def test_finetune_bad_flags_exit_2(scene_dir, tmp_path, args, message):
    result = _run("finetune", scene_dir, "--scratch", "--output", tmp_path / "x", *args)
    assert result.exit_code == 2
    assert message in result.stderr and "Traceback" not in result.output


def _files(folder: Path) -> dict:
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in folder.rglob("*") if p.is_file()}


def test_training_and_make_pairs_never_write_into_a_folder_they_did_not_write(scene_dir, tmp_path):
    """Issue 49: a dataset (or any folder of the user's) given as --output is refused before any work,
    in one line naming it; nothing in it is written or deleted."""
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "transforms.json").write_text('{"frames": []}')
    (mine / "model.safetensors").write_bytes(b"someone else's model")
    scene_before, mine_before = _files(scene_dir), _files(mine)
    for output in (scene_dir, mine):
        for args in (["finetune", scene_dir, "--scratch", "--steps", "1", *FAST],
                     ["pretrain", "--toy", "1", "--steps", "1", *FAST]):
            result = _run(*args, "--output", output)
            assert result.exit_code == 2, result.output
            assert result.stderr.splitlines() == [
                f"error: output: {output} exists and is not empty: it holds other files, not an earlier training "
                "run (which would be resumed); choose a new folder"]
        result = _run("make-pairs", scene_dir, "--output", output, "--steps", "1")
        assert result.exit_code == 2, result.output
        assert result.stderr.splitlines()[-1] == (
            f"error: output: {output} exists and is not empty: it holds other files, not an earlier output of "
            "this command (which would be replaced); choose a new folder")
    assert _files(scene_dir) == scene_before and _files(mine) == mine_before


def test_pretrain_without_scenes_exits_2(tmp_path):
    result = _run("pretrain", "--output", tmp_path / "x", "--steps", "1")
    assert result.exit_code == 2 and "no scenes" in result.stderr


def test_serve_without_the_service_is_a_clear_error(monkeypatch):
    monkeypatch.setitem(sys.modules, "service.server", None)  # import fails as if not installed
    result = _run("serve", "--port", "8123")
    assert result.exit_code == 1
    assert "roguenerf[service]" in result.stderr


def test_serve_refuses_a_data_dir_it_did_not_make(tmp_path):
    """Issue 49: `serve --data-dir ~` swept ~/tmp of entries older than six hours."""
    from jobs.layout import Layout

    home = tmp_path / "home"
    (home / "tmp").mkdir(parents=True)
    (home / "tmp" / "old.txt").write_text("mine")
    os.utime(home / "tmp" / "old.txt", (0, 0))  # 1970: "stale" to the sweep
    (home / "notes.txt").write_text("mine")
    from roguenerf.errors import InputError

    with pytest.raises(InputError, match="not a RoGUENeRF data directory"):
        Layout(home).ensure()  # the API's and the workers' start-up
    result = _run("serve", "--data-dir", home, "--port", "8124")
    assert result.exit_code == 2, result.output
    assert result.stderr.splitlines()[-1] == (
        f"error: data directory {home} exists and is not empty: it holds other files, not a RoGUENeRF data "
        "directory (whose tmp/ is swept and whose scenes/ and jobs/ are removed as jobs end); choose a new "
        "folder (--data-dir)")
    assert sorted(p.relative_to(home).as_posix() for p in home.rglob("*")) == ["notes.txt", "tmp", "tmp/old.txt"]
    # Ours: new, or made by an older version (scenes/ jobs/ tmp/, no marker): the marker is added.
    Layout(tmp_path / "new").ensure()
    old = tmp_path / "old"
    for sub in ("scenes", "jobs", "tmp"):
        (old / sub).mkdir(parents=True)
    (old / "roguenerf.db").write_bytes(b"")
    Layout(old).ensure()
    assert (tmp_path / "new" / ".roguenerf-data").is_file() and (old / ".roguenerf-data").is_file()
    assert Layout(old).sweep_stale_temp(1.0) == []


def test_console_entry_point_runs_as_a_module(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "roguecli", "evaluate", str(tmp_path / "nope"), "--json"],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2
    assert proc.stdout == "" and str(tmp_path / "nope") in proc.stderr and "Traceback" not in proc.stderr


SERVE_PROBE = r"""
import os, sys
import service.server
from roguecli import app

def fake_run(**kwargs):
    import torch  # noqa: F401  (the real server loads it after this point)
    print("policy", os.environ.get("OMP_WAIT_POLICY"))

service.server.run = fake_run
print("torch loaded before serve", "torch" in sys.modules)
try:
    app(["serve", "--port", "8123"])
except SystemExit:
    pass
"""


@pytest.mark.slow
@pytest.mark.parametrize("env, expected", [({}, "PASSIVE"), ({"OMP_WAIT_POLICY": "ACTIVE"}, "ACTIVE"),
                                           ({"GOMP_SPINCOUNT": "300000"}, "None")])
def test_serve_sets_passive_openmp_wait_before_torch_loads(env, expected):
    # The API and its worker share the cores; the user's own choice of wait policy wins.
    base = {k: v for k, v in os.environ.items() if k not in ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT")}
    proc = subprocess.run([sys.executable, "-c", SERVE_PROBE], env={**base, **env}, capture_output=True,
                          text=True, timeout=120)
    assert "torch loaded before serve False" in proc.stdout, proc.stdout + proc.stderr
    assert f"policy {expected}" in proc.stdout, proc.stdout + proc.stderr


# ------------------------------------------------------------------ issue 17: CLI edge cases


@pytest.mark.parametrize("budget, message", [
    (["--minutes", "0"], "--minutes: expected a number > 0, got 0"),
    (["--minutes", "-1"], "--minutes: expected a number > 0"),
    (["--steps", "0"], "--steps: expected > 0, got 0"),
    (["--minutes", "nan"], "--minutes must be a finite number > 0, got nan"),
])
def test_finetune_refuses_an_empty_budget(scene_dir, tmp_path, budget, message):
    out = tmp_path / "ft"
    result = _run("finetune", scene_dir, "--scratch", "--output", out, *budget, *FAST)
    assert result.exit_code == 2, result.output
    assert message in result.stderr and "roguenerf evaluate" in result.stderr
    assert not out.exists()  # refused before anything was written


def test_help_states_the_default_budget_and_shows_flags_as_flags():
    from roguenerf.training.config import CPU_LR, CPU_MINUTES, GPU_LR, GPU_MINUTES

    assert (CPU_MINUTES, GPU_MINUTES, CPU_LR, GPU_LR) == (10, 60, 5e-4, 1e-4)  # as the help and docs/cli.md say
    text = " ".join(_run("finetune", "--help").stdout.split())
    assert "Default without --steps: 10 minutes on a CPU, 60 on a GPU." in text
    assert "(default: 5e-4 on a CPU, chosen by measured gain per minute; 1e-4 on a GPU, the paper's)" in text
    for command in ("finetune", "evaluate", "enhance", "pretrain", "serve"):
        help_text = _run(command, "--help").stdout
        assert "<bool>" not in help_text and "BOOLEAN" not in help_text, help_text
        assert re.search(r"^\s+--help\s+Show this message and exit", help_text, re.M), help_text
    evaluate_help = _run("evaluate", "--help").stdout
    assert re.search(r"^\s+--json\s+Print one JSON object", evaluate_help, re.M), evaluate_help


def test_enhance_creates_only_the_file(scene_dir, checkpoint, tmp_path):
    missing = tmp_path / "no_such_dir"
    result = _run("enhance", scene_dir, "--view", "test_001", "--checkpoint", checkpoint,
                  "--output", missing / "x.png")
    assert result.exit_code == 2
    assert f"--output: folder {missing} does not exist" in result.stderr
    assert not missing.exists()
    a_file = tmp_path / "plain"
    a_file.write_text("x")
    result = _run("enhance", scene_dir, "--view", "test_001", "--checkpoint", checkpoint,
                  "--output", a_file / "x.png")
    assert result.exit_code == 2 and "is not a folder" in result.stderr


def test_evaluate_draws_a_bar_per_view_on_stderr(scene_dir, checkpoint):
    result = _run("evaluate", scene_dir, "--checkpoint", checkpoint, "--split", "train", "--json")
    assert result.exit_code == 0, result.output
    json.loads(result.stdout)  # stdout stays one JSON object
    assert "evaluating train views" in result.stderr and "5/5" in result.stderr, result.stderr


def test_time_budget_bar_counts_seconds_not_a_moving_step_total(scene_dir, tmp_path):
    result = _run("finetune", scene_dir, "--scratch", "--minutes", "0.05", "--output", tmp_path / "ft",
                  "--no-eval", *FAST)
    assert result.exit_code == 0, result.output
    totals = set(re.findall(r"\d+/(\d+) s\b", result.stderr))
    assert totals == {"3"}, result.stderr  # 0.05 min = 3 s, the whole way
    assert "step=" in result.stderr


UMASK_PROBE = r"""
import os, sys
os.umask(int(sys.argv[1], 8))
from roguecli import main
sys.argv = ["roguenerf"] + sys.argv[2:]
main()
"""


@pytest.mark.slow
@pytest.mark.parametrize("umask, mode", [("022", 0o644), ("077", 0o600), ("002", 0o664)])
def test_written_files_get_the_mode_open_would_give(scene_dir, checkpoint, tmp_path, umask, mode):
    out = tmp_path / "x.png"
    proc = subprocess.run([sys.executable, "-c", UMASK_PROBE, umask, "enhance", str(scene_dir), "--view",
                           "test_001", "--checkpoint", str(checkpoint), "--output", str(out)],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert oct(out.stat().st_mode & 0o777) == oct(mode)
    ft = tmp_path / "ft"
    proc = subprocess.run([sys.executable, "-c", UMASK_PROBE, umask, "finetune", str(scene_dir), "--scratch",
                           "--steps", "1", "--no-eval", "--output", str(ft), *FAST],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    written = sorted(p for p in ft.iterdir() if p.is_file())
    assert {p.name for p in written} >= {"model.safetensors", "model.json"}
    assert {p.name: oct(p.stat().st_mode & 0o777) for p in written} == {p.name: oct(mode) for p in written}


def test_replacing_a_file_keeps_its_mode(tmp_path):
    from roguenerf.imageio import atomic_write

    path = tmp_path / "f.bin"
    path.write_bytes(b"old")
    os.chmod(path, 0o640)
    atomic_write(path, b"new")
    assert path.read_bytes() == b"new" and (path.stat().st_mode & 0o777) == 0o640
    assert [p.name for p in tmp_path.iterdir()] == ["f.bin"]  # no temp file left
    with pytest.raises(FileNotFoundError):
        atomic_write(tmp_path / "absent" / "f.bin", b"x")
    assert not (tmp_path / "absent").exists()


# ------------------------------------------------------------------ issue 17: OpenMP wait policy

POLICY_PROBE = r"""
import os, sys
first = sys.argv[1]
if first == "torch":
    import torch  # noqa: F401
import roguenerf
from roguenerf import runtime
import torch
print("env", os.environ.get("OMP_WAIT_POLICY"), "configure", runtime.configure()["omp_wait_policy"])
"""


@pytest.mark.slow
@pytest.mark.parametrize("first, env, expected", [
    ("roguenerf", {}, "env PASSIVE configure PASSIVE"),
    ("roguenerf", {"OMP_WAIT_POLICY": "active"}, "env active configure ACTIVE"),
    ("roguenerf", {"GOMP_SPINCOUNT": "300000"}, "env None configure GOMP_SPINCOUNT=300000"),
    ("torch", {}, "env None configure default"),  # too late to choose: say so, change nothing
])
def test_library_and_cli_choose_passive_wait_before_torch_loads(first, env, expected):
    base = {k: v for k, v in os.environ.items() if k not in ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT")}
    proc = subprocess.run([sys.executable, "-c", POLICY_PROBE, first], env={**base, **env},
                          capture_output=True, text=True, timeout=120)
    assert proc.stdout.strip() == expected, proc.stdout + proc.stderr


def test_cli_process_runs_with_passive_wait():
    # The console command: importing its module alone (what the entry point does) decides it.
    base = {k: v for k, v in os.environ.items() if k not in ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT")}
    code = "import os, sys, roguecli; print(os.environ.get('OMP_WAIT_POLICY'), 'torch' in sys.modules)"
    proc = subprocess.run([sys.executable, "-c", code], env=base, capture_output=True, text=True, timeout=120)
    assert proc.stdout.strip() == "PASSIVE False", proc.stdout + proc.stderr


# ------------------------------------------------------------------ issue 36, issue 50: one CLI


def test_console_script_is_the_top_level_cli_with_every_command():
    import tomllib

    project = tomllib.loads((Path(__file__).resolve().parents[3] / "pyproject.toml").read_text())
    assert project["project"]["scripts"]["roguenerf"] == "roguecli:main"
    assert "roguecli*" in project["tool"]["setuptools"]["packages"]["find"]["include"]
    names = [c.name or c.callback.__name__.replace("_", "-") for c in app.registered_commands]
    assert names == ["finetune", "pretrain", "make-pairs", "evaluate", "enhance", "import-nerfstudio",
                     "import-gsplat", "import-3dgs", "enhance-path", "serve"]
    library = Path(__file__).resolve().parents[3] / "roguenerf"
    assert not (library / "cli.py").exists() and not (library / "cli").exists()  # one command line: roguecli
    # --help names no module above the library and loads none of them.
    code = ("import sys; from roguecli import app\ntry:\n    app(['--help'])\nexcept SystemExit:\n    pass\n"
            "print(sorted(m for m in sys.modules if m.split('.')[0] in ('service', 'workers', 'roguefit')))")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert proc.stdout.strip().splitlines()[-1] == "[]", proc.stdout + proc.stderr


@pytest.mark.parametrize("command", ["serve", "make-pairs", "evaluate"])
def test_the_library_module_says_where_the_command_line_is(command):
    proc = subprocess.run([sys.executable, "-m", "roguenerf", command, "--help"], capture_output=True, text=True,
                          timeout=120)
    assert proc.returncode == 2 and proc.stdout == ""
    assert f"`roguenerf {command}`" in proc.stderr and f"python -m roguecli {command}" in proc.stderr
    assert "Traceback" not in proc.stderr
    proc = subprocess.run([sys.executable, "-m", "roguecli", command, "--help"], capture_output=True, text=True,
                          timeout=120)
    assert proc.returncode == 0 and f"Usage: python -m roguecli {command}" in proc.stdout, proc.stderr


# --- issue 38 ---------------------------------------------------------------------------------------


def test_evaluate_takes_the_folder_a_finetune_wrote(scene_dir, checkpoint, tmp_path):
    out = tmp_path / "ft"
    trained = _run("finetune", scene_dir, "--checkpoint", checkpoint, "--steps", "1", "--output", out,
                   "--no-eval", *FAST)
    assert trained.exit_code == 0, trained.output
    by_folder = _run("evaluate", scene_dir, "--checkpoint", out, "--json")
    by_file = _run("evaluate", scene_dir, "--checkpoint", out / "model.safetensors", "--json")
    assert by_folder.exit_code == 0, by_folder.output
    folder_report, file_report = json.loads(by_folder.stdout), json.loads(by_file.stdout)
    for report in (folder_report, file_report):  # timings differ; the figures do not
        report.pop("seconds_per_view", None)
        for view in report["views"]:
            view.pop("seconds", None)
    assert folder_report == file_report
    # A folder without a finished checkpoint says so (and what to do), in one line.
    (out / "model.safetensors").unlink()
    unfinished = _run("evaluate", scene_dir, "--checkpoint", out)
    assert unfinished.exit_code == 2 and "no finished checkpoint (model.safetensors)" in unfinished.stderr
    assert "run the same fine-tune again" in unfinished.stderr
    (tmp_path / "empty").mkdir()
    empty = _run("evaluate", scene_dir, "--checkpoint", tmp_path / "empty")
    assert empty.exit_code == 2 and "holds no checkpoint: expected model.safetensors" in empty.stderr
    assert "Traceback" not in empty.output


def test_the_cli_takes_the_training_defaults_from_the_library_without_loading_torch():
    import inspect

    from roguecli import training
    from roguenerf.training import TrainConfig

    pretrain = inspect.signature(training.pretrain).parameters
    assert (pretrain["batch"].default, pretrain["seed"].default, pretrain["held_out_share"].default) == (
        TrainConfig().batch, TrainConfig().seed, TrainConfig().held_out_share)
    text = " ".join(_run("pretrain", "--help").stdout.split())
    assert f"Crops per optimiser step. [default: {TrainConfig().batch}]" in text
    code = "import sys, roguenerf.training; print('torch' in sys.modules)"
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert proc.stdout.strip() == "False", proc.stdout + proc.stderr


def test_checkpoint_folder_resolution_is_the_library_s(checkpoint, tmp_path):
    from roguenerf.checkpoint import MODEL_FILE, resolve_checkpoint
    from roguenerf.errors import InputError
    from roguenerf.training import STATE_FILE

    assert resolve_checkpoint(checkpoint) == checkpoint
    folder = tmp_path / "run"
    folder.mkdir()
    (folder / STATE_FILE).write_bytes(b"")
    with pytest.raises(InputError, match="no finished checkpoint"):
        resolve_checkpoint(folder)
    (folder / MODEL_FILE).write_bytes(checkpoint.read_bytes())
    assert resolve_checkpoint(folder) == folder / MODEL_FILE
    with pytest.raises(InputError, match="does not exist"):
        resolve_checkpoint(tmp_path / "absent.safetensors")


def test_a_nan_budget_is_refused_by_the_library_with_a_clear_message():
    from roguenerf.errors import InputError
    from roguenerf.training import TrainConfig

    for bad in (float("nan"), float("inf")):
        with pytest.raises(InputError, match=r"minutes must be a finite number >= 0, got"):
            TrainConfig(minutes=bad).validate()
    with pytest.raises(InputError, match=r"minutes: expected a number >= 0, got -1"):
        TrainConfig(minutes=-1.0).validate()
    assert TrainConfig(minutes=0.5).validate().minutes == 0.5


def test_a_view_with_unusable_depth_is_loaded_with_a_warning_naming_it(scene_dir, checkpoint, tmp_path):
    import shutil

    import numpy as np

    from roguenerf.data.readers import load_scene
    from roguenerf.data.scene import unusable_views

    copy = tmp_path / "scene"
    shutil.copytree(scene_dir, copy)
    scene = load_scene(copy)
    assert unusable_views(scene) == []
    bad = scene.indices("train")[1]
    frame = scene.frames[bad]
    depth = np.load(frame.depth_path)
    np.save(frame.depth_path, np.zeros_like(depth))  # what the user had: one training depth all zeros
    found = unusable_views(load_scene(copy))
    assert [(v.index, v.name, v.split) for v in found] == [(bad, frame.name, "train")]
    assert "depth has no usable values (all zeros" in found[0].reason
    result = _run("evaluate", copy, "--checkpoint", checkpoint)
    assert result.exit_code == 0, result.output
    assert f"warning: 1 of {len(scene.frames)} views of {copy} are unusable" in result.stderr
    assert f"{frame.name} (train): depth has no usable values (all zeros" in result.stderr
    clean = _run("evaluate", scene_dir, "--checkpoint", checkpoint)
    assert "warning" not in clean.stderr


def test_enhance_checks_only_the_views_it_reads(scene_dir, checkpoint, tmp_path):
    """A one-view enhance reads the view's render and depth and its neighbours' photos and depths,
    not every file of the scene (issue 51: start-up time): an unusable one among them is named,
    one elsewhere is not read at all."""
    import shutil

    import numpy as np

    from roguenerf.data.readers import load_scene
    from roguenerf.imageio import write_png
    from roguenerf.inference import SceneEnhancer

    copy = tmp_path / "scene"
    shutil.copytree(scene_dir, copy)
    scene = load_scene(copy)
    test = scene.indices("test")[0]
    used = SceneEnhancer(scene, load_checkpoint(checkpoint)[0]).select(scene.frames[test].world_from_cam)
    unused = [i for i in scene.indices("train") if i not in used]
    assert used and unused
    blank = scene.frames[unused[0]]  # a blank photo, never read by this command
    write_png(blank.image_path, torch.full((3, blank.height, blank.width), 0.5))
    # nor are a neighbour's render and the view's photo: the command reads neither
    for path in (scene.frames[used[0]].render_path, scene.frames[test].image_path):
        write_png(path, torch.full((3, blank.height, blank.width), 0.5))
    args = ["enhance", copy, "--view", scene.frames[test].name, "--checkpoint", checkpoint,
            "--output", tmp_path / "out.png"]
    result = _run(*args)
    assert result.exit_code == 0, result.output
    assert "warning" not in result.stderr
    neighbour = scene.frames[used[0]]
    np.save(neighbour.depth_path, np.zeros_like(np.load(neighbour.depth_path)))
    result = _run(*args)
    assert result.exit_code == 0, result.output
    assert (f"warning: 1 of the {1 + len(used)} views of {copy} this command reads are unusable and contribute "
            f"nothing: {neighbour.name} (train): depth has no usable values (all zeros") in result.stderr
    evaluate = _run("evaluate", copy, "--checkpoint", checkpoint)  # a whole-scene command reads them all
    assert f"warning: 3 of {len(scene.frames)} views of {copy} are unusable" in evaluate.stderr


INTERRUPT_PROBE = """
import _thread, signal, sys, threading
from roguecli import main
# A terminal's Ctrl-C reaches a Python that handles SIGINT; a shell's background job (``cmd &``)
# starts with SIGINT ignored, which interrupt_main then does nothing about: handle it here.
signal.signal(signal.SIGINT, signal.default_int_handler)
threading.Timer(float(sys.argv[1]), _thread.interrupt_main).start()  # what Ctrl-C does
sys.argv = ["roguenerf", *sys.argv[2:]]
main()
"""


def _interrupted_finetune(scene_dir, out, after: float, timeout: float = 120) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", INTERRUPT_PROBE, str(after), "finetune", str(scene_dir), "--scratch",
                           "--minutes", "5", "--output", str(out), "--no-eval", *FAST],
                          capture_output=True, text=True, timeout=timeout)


def _assert_one_interrupted_line(proc: subprocess.CompletedProcess) -> None:
    assert proc.returncode == 130, proc.stderr
    assert proc.stderr.strip().splitlines()[-1] == "error: interrupted"
    assert proc.stderr.count("error: interrupted") == 1 and "Traceback" not in proc.stderr


@pytest.mark.slow
@pytest.mark.parametrize("after", [0.3, 6.0])  # in the start-up (before the error handling), training
def test_ctrl_c_exits_130_with_one_line(scene_dir, tmp_path, after):
    """Issue 49: Ctrl-C gave exit status 1 (in a command) or a silent 130 (before it)."""
    _assert_one_interrupted_line(_interrupted_finetune(scene_dir, tmp_path / "out", after))


@pytest.mark.slow
def test_ctrl_c_anywhere_in_the_start_up_exits_130(scene_dir, tmp_path):
    """A Ctrl-C that landed inside an import (torch importing ``torch._dynamo`` or NumPy from C++)
    was swallowed there: the fine-tune ran on to its end, or a later import failed (RecursionError,
    "cannot load module more than once per process"), for interrupts 0.42-0.62 s after the start
    on this machine. Every 75 ms from 0.3 to 0.9 s is tried (the interrupt is deferred until
    the import is done: ``roguecli.common._on_interrupt``)."""
    for i in range(9):
        after = 0.3 + 0.075 * i
        proc = _interrupted_finetune(scene_dir, tmp_path / f"out{i}", after, timeout=30)
        assert proc.returncode == 130, (after, proc.stderr[-2000:])
        _assert_one_interrupted_line(proc)



def test_the_collector_is_rare_in_the_start_up_and_everything_frozen_after(monkeypatch):
    """``run_app`` lets the garbage collector run rarely through the imports; ``handle_errors``
    brings its thresholds back; at the end everything is frozen (a fast exit)."""
    import gc

    import typer

    from roguecli.common import START_UP_THRESHOLD, handle_errors, run_app

    seen = {}
    probe = typer.Typer()

    @probe.command()
    def work() -> None:
        seen["before"] = gc.get_threshold()[0]
        with handle_errors():
            seen["inside"] = gc.get_threshold()[0]

    monkeypatch.setattr(sys, "argv", ["probe"])
    usual = gc.get_threshold()
    frozen = gc.get_freeze_count()
    try:
        with pytest.raises(SystemExit) as exit_:
            run_app(probe)
        after = gc.get_freeze_count()
    finally:
        gc.unfreeze()
    assert exit_.value.code == 0
    assert seen == {"before": START_UP_THRESHOLD, "inside": usual[0]} and gc.get_threshold() == usual
    assert after > frozen
