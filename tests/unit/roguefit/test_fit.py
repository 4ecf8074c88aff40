"""The pair-making radiance field (``roguefit``) on a toy photo set with exact geometry."""

from __future__ import annotations

import dataclasses
import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from PIL import Image

from roguefit import FitConfig, make_pairs, read_photo_set
from roguefit.field import GridField
from roguenerf.data.readers import load_scene
from roguenerf.errors import InputError
from tests.fit_helpers import (
    VIEWS,
    H,
    W,
    constant_psnr,
    depth_errors,
    fit_photo_set,
    fit_stopped_and_resumed,
    ray_bundle,
    run_make_pairs,
    write_photo_set,
)

SMALL = FitConfig(resolution=40, features=0, steps=240, minutes=None, rays=1024, samples=48, prune_every=40)


@pytest.fixture(scope="module")
def fitted(tmp_path_factory):
    return fit_photo_set(tmp_path_factory, SMALL, "pairs")


@pytest.mark.slow
def test_fit_writes_a_scene_folder_with_every_view(fitted):
    root, out, report, _ = fitted
    scene = load_scene(out)
    assert len(scene.frames) == VIEWS
    assert [f.name for f in scene.frames if f.split == "test"] == ["000", "008", "016"]  # every 8th held out
    for i in range(len(scene.frames)):
        assert scene.render(i).shape == (3, H, W) and scene.depth(i).shape == (1, H, W)
        assert torch.isfinite(scene.depth(i)).all() and (scene.depth(i) > 0).all()
    assert (out / "acc" / "000.png").is_file()
    assert report["steps"] == SMALL.steps and report["config"] == SMALL.identity()
    assert json.loads((out / "fit.json").read_text())["train"] == report["train"]


@pytest.mark.slow
def test_fit_reaches_a_psnr_floor_and_beats_a_constant_image(fitted):
    root, out, report, _ = fitted
    constant = constant_psnr(root)
    assert report["train"]["psnr"] > 22.0, report
    assert report["train"]["psnr"] > constant + 8.0, (report["train"], constant)
    assert report["test"]["psnr"] > constant + 4.0, (report["test"], constant)  # held-out views include both path ends


@pytest.mark.slow
def test_rendered_depth_is_close_to_the_true_depth(fitted):
    _, out, _, truth = fitted
    errors, coverage = depth_errors(out, truth)
    assert float(torch.stack(errors).median()) < 0.08, errors
    assert min(coverage) > 0.9, coverage


@pytest.mark.slow
def test_interrupted_fit_resumes_to_the_same_result(tmp_path):
    config = dataclasses.replace(SMALL, steps=30, prune_every=10)
    run = fit_stopped_and_resumed(tmp_path, config, stop_at=12)
    assert run.state_json["step"] == 12
    assert run.resumed["steps"] == 30
    assert run.resumed["train"]["psnr"] == pytest.approx(run.whole["train"]["psnr"], abs=1e-4)
    assert run.render_difference(1) <= 1 / 255
    # A finished folder is left as it is (no refit: the report is returned from fit.json).
    again = make_pairs(tmp_path / "photos", tmp_path / "resumed", config)
    assert again == run.resumed


def test_contraction_round_trips_and_bounds_the_world():
    field = GridField(torch.tensor([1.0, -2.0, 0.5]), 2.0, 8)
    pts = torch.tensor([[1.0, -2.0, 0.5], [2.0, -1.0, 1.0], [50.0, -2.0, 0.5], [-1e6, 3e5, 2.0]])
    u = field.contract(pts)
    assert (u.abs() <= 1.0).all()
    assert torch.allclose(u[0], torch.zeros(3))
    assert torch.allclose(u[1], torch.tensor([0.25, 0.25, 0.125]))  # inside the radius: linear
    assert torch.allclose(field.uncontract(u[:3]), pts[:3], rtol=1e-4, atol=1e-4)


UNREADABLE = {  # how a photo set is broken: what the error says
    "missing_photo": "images/003.png: missing file",
    "bad_bounds": "expected 0 < near < far",
    "bad_json": "transforms.json: cannot be read as JSON",
    "no_transforms": "expected a posed photo set with transforms.json",
}


@pytest.mark.parametrize("breakage, message", UNREADABLE.items())
def test_a_photo_set_it_cannot_read_is_a_clear_error(tmp_path, breakage, message):
    root = tmp_path / "photos"
    write_photo_set(root, views=5)
    if breakage == "missing_photo":
        (root / "images" / "003.png").unlink()
    elif breakage == "bad_bounds":
        meta = json.loads((root / "transforms.json").read_text())
        meta["frames"][2]["far"] = meta["frames"][2]["near"] / 2
        (root / "transforms.json").write_text(json.dumps(meta))
    elif breakage == "bad_json":
        (root / "transforms.json").write_text("{not json")
    else:
        (root / "transforms.json").unlink()
    with pytest.raises(InputError, match=message.replace("(", r"\(")):
        read_photo_set(root)
    # The CLI says the same in one line, exit code 2, no traceback.
    proc = run_make_pairs(root, tmp_path / "out", "--steps", "2", timeout=120)
    assert proc.returncode == 2, proc.stderr
    assert message in proc.stderr and "Traceback" not in proc.stderr


@pytest.mark.slow
def test_make_pairs_cli_runs_and_the_library_never_imports_the_fitter(tmp_path):
    root = tmp_path / "photos"
    write_photo_set(root, views=9)
    proc = run_make_pairs(root, tmp_path / "out", "--preset", "coarse", "--steps", "3", "--resolution", "24")
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == str(tmp_path / "out")
    assert "fitted 3 steps" in proc.stderr
    assert len(load_scene(tmp_path / "out").frames) == 9
    code = ("import sys, roguenerf, roguenerf.inference, roguenerf.training; "
            "print(sorted(m for m in sys.modules if m.startswith('roguefit')))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=True)
    assert out.stdout.strip() == "[]"


def test_manifest_keeps_the_rows_of_fits_made_in_another_cache(tmp_path):
    """``--manifest`` rewrites the rows of the fits in the cache and keeps the others: a session
    whose cache holds one new fit must not drop the project's other rows."""
    from roguefit.batch import write_manifest
    from roguefit.pairs import FIT_FILE

    def fit(scene: str, preset: str, psnr: float) -> None:
        folder = tmp_path / "cache" / scene / preset
        folder.mkdir(parents=True)
        (folder / FIT_FILE).write_text(json.dumps({
            "config": {"resolution": 96, "features": 0, "minutes": None}, "steps": 500, "fit_seconds": 1.0,
            "render_seconds": 2.0, "train": {"views": 8, "psnr": psnr, "ssim": 0.5},
            "test": {"views": 1, "psnr": psnr - 1, "ssim": 0.4}}))

    manifest = tmp_path / "manifest.csv"
    fit("beta", "blur", 20.0)
    fit("alpha", "coarse", 21.0)
    write_manifest(tmp_path / "cache", manifest)
    # Another session: a new cache with alpha/fine and a re-made alpha/coarse.
    shutil.rmtree(tmp_path / "cache")
    fit("alpha", "coarse", 25.0)
    fit("alpha", "fine", 23.0)
    write_manifest(tmp_path / "cache", manifest)
    lines = manifest.read_text().splitlines()
    rows = [line.split(",") for line in lines[1:]]
    assert [(r[0], r[1], r[10]) for r in rows] == [  # sorted; the re-made fit's row replaced
        ("alpha", "coarse", "25.0"), ("alpha", "fine", "23.0"), ("beta", "blur", "20.0")]
    write_manifest(tmp_path / "cache", manifest)
    assert manifest.read_text().splitlines() == lines  # rewriting changes nothing


@pytest.mark.slow
def test_pretraining_pipeline_smoke(tmp_path):
    """scripts/pretrain_real.sh end to end on two toy photo sets, one held out: pairs (tiny
    budgets), a manifest, a 2-step pre-training that never sees the held-out scene (and trains
    on the other's held-out views too), the shipped
    copy, and the held-out evaluation bench."""
    data = tmp_path / "real"
    write_photo_set(data / "alpha", views=9, seed=1)
    write_photo_set(data / "beta", views=9, seed=2)
    repo = Path(__file__).resolve().parents[3]
    env = {**__import__("os").environ, "DATA": str(data), "CACHE": str(tmp_path / "cache"), "PRESETS": "blur,coarse",
           "HOLDOUT": "beta", "EXTRA": "", "HELD_OUT_SHARE": "0.5", "BUDGET_SCALE": "0.01", "STEPS": "2",
           "OUT": str(tmp_path / "run"), "DEST": str(tmp_path / "weights" / "default.safetensors"),
           "MANIFEST": str(tmp_path / "docs" / "manifest.csv"),
           "PY": sys.executable,
           "EVAL_ARGS": f"--quick --plans default,whole --output {tmp_path / 'bench' / 'real'}"}
    proc = subprocess.run(["bash", str(repo / "scripts" / "pretrain_real.sh")], env=env, capture_output=True,
                          text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    manifest = (tmp_path / "docs" / "manifest.csv").read_text().splitlines()
    assert manifest[0].startswith("scene,fit,") and len(manifest) == 5  # two looks of two scenes
    assert {tuple(line.split(",")[:2]) for line in manifest[1:]} == {
        (s, p) for s in ("alpha", "beta") for p in ("blur", "coarse")}
    assert (tmp_path / "docs" / "alpha_coarse.png").is_file()
    # Pre-training saw both looks of alpha only, never the held-out beta.
    cache = tmp_path / "cache"
    assert f"pre-training on 2 scene folders: {cache / 'alpha' / 'blur'} {cache / 'alpha' / 'coarse'}" in proc.stderr
    assert "held-out views 50% of their scenes' targets" in proc.stderr  # the fits' novel views are targets too
    assert "cosine to 0" in proc.stderr  # the script's schedule, the shipped checkpoint's
    assert (tmp_path / "weights" / "default.safetensors").is_file()
    sidecar = json.loads((tmp_path / "weights" / "default.json").read_text())
    assert sidecar["weights"] == "default.safetensors" and sidecar["meta"]["training"]["kind"] == "pretrain"
    import csv

    with (tmp_path / "bench" / "real_quick.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    assert [(r["kind"], r["plan_name"]) for r in rows] == [  # zero-shot new, two budgets per plan
        ("zero-shot new", ""), ("finetune", "default"), ("finetune", "default"), ("finetune", "whole"),
        ("finetune", "whole")]
    assert all(r["scene"] == "beta/coarse" for r in rows)
    plans = [r["plan"].split() for r in rows[1:]]  # "micro crop C batch B nN ENCODING lr LR SCHEDULE"
    assert [p[6] for p in plans] == ["window", "window", "whole", "whole"]
    assert all(p[-1] == "cosine" for p in plans)  # the default schedule: each budget a fresh run
    for r in rows:  # every view's gain is listed, and the worst view is the lowest of them
        gains = {name: float(g) for name, g in (pair.split(":") for pair in r["view_gains_db"].split())}
        assert len(gains) == int(r["views"]) and min(gains, key=gains.get) == r["worst_view"]
        assert abs(gains[r["worst_view"]] - float(r["worst_view_gain_db"])) < 6e-4
    # --replot merges sittings: the same CSV twice keeps the scene's zero-shot row once.
    quick_csv = tmp_path / "bench" / "real_quick.csv"
    subprocess.run([sys.executable, "-m", "bench.real_scenes", "--replot", str(quick_csv), str(quick_csv),
                    "--output", str(tmp_path / "bench" / "merged")], check=True, capture_output=True, timeout=120,
                   cwd=repo)
    with (tmp_path / "bench" / "merged.csv").open() as fh:
        merged = [r["kind"] for r in csv.DictReader(fh)]
    assert merged == ["zero-shot new"] + ["finetune"] * 8 and (tmp_path / "bench" / "merged.png").is_file()
    # Naming the fits exactly: a held-out scene or an unfinished fit is refused before any training.
    for fits, message in (("alpha/coarse,beta/coarse", "beta is a held-out scene"),
                          ("alpha/fine", "is not a finished fit")):
        refused = subprocess.run(["bash", str(repo / "scripts" / "pretrain_real.sh")], capture_output=True, text=True,
                                 env={**env, "STAGE": "pretrain", "FITS": fits, "OUT": str(tmp_path / "refused")},
                                 timeout=60)
        assert refused.returncode == 2 and message in refused.stderr, refused.stderr
        assert not (tmp_path / "refused").exists()


def test_zero_shot_only_results_plot_as_bars_per_scene(tmp_path):
    """A zero-shot-only run (``--minutes ""``, how checkpoints are chosen on many fits) is summed up
    per scene, old and new checkpoint side by side, and drawn as bars whose height grows with the
    scene count, not as one crowded column of points at minute 0."""
    from bench import real_scenes

    stamp = {"machine": "test machine", "commit": "abc1234", "date": "2026-11-25T00:00:00+00:00", "minutes": 0.0}
    rows = [{**stamp, "scene": "a/coarse", "kind": "zero-shot old", "gain_db": 0.5, "worst_view_gain_db": -0.2},
            {**stamp, "scene": "a/coarse", "kind": "zero-shot new", "gain_db": 0.7, "worst_view_gain_db": 0.1},
            {**stamp, "scene": "b/fine", "kind": "zero-shot new", "gain_db": 0.3, "worst_view_gain_db": -0.4}]
    assert real_scenes.zero_shot_summary(rows) == [
        {"scene": "a/coarse", "new": 0.7, "new_worst": 0.1, "old": 0.5, "old_worst": -0.2},
        {"scene": "b/fine", "new": 0.3, "new_worst": -0.4, "old": None, "old_worst": None}]
    two = Image.open(real_scenes.plot(rows, tmp_path / "two.png"))
    more = [{**r, "scene": f"{r['scene']}{k}"} for k in range(6) for r in rows]
    twelve = Image.open(real_scenes.plot(more, tmp_path / "twelve.png"))
    assert two.width == twelve.width and twelve.height > 2 * two.height  # bars: one row per scene
    curve = Image.open(real_scenes.plot(rows + [{**rows[1], "kind": "finetune", "minutes": 1.0}], tmp_path / "c.png"))
    assert curve.size == (780, 480)  # with a fine-tune: the gain-per-minute curve, as before


def test_early_terminating_renderer_equals_the_training_renderer():
    """render_fast (segments, early ray termination) gives render's image, depth and opacity: exactly
    up to rounding without termination, and within the termination threshold with it."""
    g = torch.Generator().manual_seed(0)
    field = GridField(torch.zeros(3), 1.5, 24, features=4)
    with torch.no_grad():
        field.density.copy_(torch.randn(field.density.shape, generator=g) * 3 + 1)
        field.colour.copy_(torch.randn(field.colour.shape, generator=g))
        for p in field.mlp.parameters():
            p.copy_(torch.randn(p.shape, generator=g) * 0.3)
    field.use_mlp = True
    origins, dirs, near, far = ray_bundle(500, g)
    with torch.no_grad():
        ref = field.render(origins, dirs, near, far, 40)
    exact = field.render_fast(origins, dirs, near, far, 40, segment=7, termination=0.0)
    fast = field.render_fast(origins, dirs, near, far, 40, segment=8, termination=1e-4)
    for key in ("rgb", "acc", "depth"):
        assert torch.allclose(exact[key], ref[key], atol=1e-5), key
        assert torch.allclose(fast[key], ref[key], atol=2e-4 if key != "depth" else 1e-5), key
    assert 0.2 < float(ref["acc"].mean()) < 1.0  # a field with both opaque and open rays


def test_distortion_loss_prefers_a_surface_to_fog():
    from roguefit.field import _distortion

    s = ((torch.arange(32) + 0.5) / 32).expand(2, 32)
    surface = torch.zeros(2, 32)
    surface[:, 10] = 1.0
    fog = torch.full((2, 32), 1 / 32)
    d_surface, d_fog = _distortion(surface, s, 32), _distortion(fog, s, 32)
    assert torch.allclose(d_surface, torch.full((2,), 1 / 96))  # a single bin: w^2 ds / 3
    pairs = sum(fog[0, i] * fog[0, j] * abs(s[0, i] - s[0, j]) for i in range(32) for j in range(32))
    brute = pairs + (fog[0] ** 2).sum() / 96
    assert torch.allclose(d_fog[0], torch.as_tensor(brute, dtype=torch.float32), rtol=1e-5)
    assert (d_fog > 10 * d_surface).all()


@pytest.mark.slow
def test_half_size_render_upsamples_to_the_photo_size_and_stays_close(fitted):
    """The blur preset renders at half size: same shape, nearly the same image and depth on a
    field whose voxels span pixels, and its identity differs from the full-size fit's."""
    from roguefit.fit import GridFitter
    from roguefit.pairs import STATE_DIR

    root, out, _, _ = fitted
    fitter = GridFitter(read_photo_set(root), SMALL, out / STATE_DIR)
    assert fitter.load()
    full = fitter.render_view(3)
    fitter.config = dataclasses.replace(SMALL, render_scale=2)
    half = fitter.render_view(3)
    for a, b in zip(full, half):
        assert a.shape == b.shape and a.dtype == b.dtype
    assert (full[0] - half[0]).abs().mean() < 0.03
    assert ((full[1] - half[1]).abs() / full[1]).median() < 0.02
    assert "render_scale" not in SMALL.identity()  # fits made before the option stay complete
    assert dataclasses.replace(SMALL, render_scale=2).identity()["render_scale"] == 2
    with pytest.raises(InputError, match="render_scale"):
        FitConfig(render_scale=0)


def test_render_scales_bench_known_answers(tmp_path):
    """bench/render_scales.py: a render that is the photo plus a constant has the same PSNR at
    every pooling (a colour error is all large-scale), which an affine colour fit removes; a
    render that is the photo plus a checkerboard loses its error when pooled by 2."""
    from bench import render_scales

    g = torch.Generator().manual_seed(0)
    photo = torch.rand(3, 32, 48, generator=g) * 0.8 + 0.1
    checks = ((torch.arange(32)[:, None] + torch.arange(48)[None, :]) % 2).float() * 0.1 - 0.05

    class _Scene:
        def indices(self, split):
            return [0] if split == "train" else [1]

        def photo(self, i):
            return photo

        def render(self, i):
            return photo + 0.05 if i == 0 else photo + checks

    train, test = render_scales.measure(_Scene())
    assert (train["split"], test["split"], train["views"]) == ("train", "test", 1)
    for k in render_scales.POOLS:
        assert train[f"psnr_pool{k}"] == pytest.approx(26.021, abs=1e-3)  # -10 log10(0.05^2)
    assert train["psnr_affine_colour"] > 60
    assert test["psnr_pool1"] == pytest.approx(26.021, abs=1e-3) and test["psnr_pool2"] > 60
    rows = [{"date": "2026-11-25T00:00:00+00:00", "machine": "test machine", "commit": "abc1234", "scene": "toy",
             **r} for r in (train, test)]
    assert Image.open(render_scales.plot(rows, tmp_path / "scales.png")).size == (900, 540)


@pytest.mark.slow
def test_real_scenes_blends_span_the_start_and_the_fine_tuned_weights(lego_dir, tmp_path):
    """``python -m bench.real_scenes --blends 0,1`` (weight-space ensembling of each fine-tune with its
    starting checkpoint) reproduces both ends exactly: blend 0 is the zero-shot row, blend 1 the
    fine-tune's own row; a blend outside [0, 1] is refused before anything runs."""
    import csv

    from roguenerf.checkpoint import blend_state

    repo = Path(__file__).resolve().parents[3]
    out = tmp_path / "blends"
    proc = subprocess.run([sys.executable, "-m", "bench.real_scenes", str(lego_dir), "--minutes", "0.03",
                           "--max-views", "1", "--blends", "0,1", "--output", str(out)],
                          capture_output=True, text=True, timeout=300, cwd=repo)
    assert proc.returncode == 0, proc.stderr[-3000:]
    with out.with_suffix(".csv").open() as fh:
        rows = {(r["kind"], r["plan_name"]): r for r in csv.DictReader(fh)}
    assert set(rows) == {("zero-shot new", ""), ("finetune", "default"), ("finetune", "default+blend0"),
                         ("finetune", "default+blend1")}
    tuned, start = rows["finetune", "default"], rows["zero-shot new", ""]
    assert int(tuned["steps"]) > 0 and tuned["enhanced_psnr"] != start["enhanced_psnr"]  # the run changed the model
    assert rows["finetune", "default+blend1"]["enhanced_psnr"] == tuned["enhanced_psnr"]
    assert abs(float(rows["finetune", "default+blend0"]["enhanced_psnr"]) - float(start["enhanced_psnr"])) < 1e-4
    # The blend itself: linear in every float tensor, integer buffers from the fine-tuned side.
    a = {"w": torch.tensor([0.0, 2.0]), "n": torch.tensor([3])}
    b = {"w": torch.tensor([4.0, -2.0]), "n": torch.tensor([7])}
    mid = blend_state(a, b, 0.25)
    assert torch.equal(mid["w"], torch.tensor([1.0, 1.0])) and torch.equal(mid["n"], torch.tensor([7]))
    refused = subprocess.run([sys.executable, "-m", "bench.real_scenes", str(lego_dir), "--blends", "1.5",
                              "--output", str(tmp_path / "refused")], capture_output=True, text=True, timeout=120,
                             cwd=repo)
    assert refused.returncode == 2 and "--blends" in refused.stderr and not (tmp_path / "refused.csv").exists()


# --- issue 38: one validation of fit configurations, before any work -------------------------------


@pytest.mark.parametrize("field, value", [
    ("resolution", 0), ("resolution", -8), ("samples", 0), ("samples", -1), ("rays", 0), ("rays", -1024),
    ("features", -1), ("steps", 0), ("steps", -5), ("minutes", float("nan")), ("minutes", float("inf")),
    ("minutes", 0.0), ("minutes", -1.0), ("lr_grid", float("nan")), ("lr_mlp", 0.0), ("tv_weight", -1.0),
    ("resolution", 40.5), ("rays", True), ("prune_every", 0), ("checkpoint_every_s", float("nan")),
    ("grow_at", (0.5, 0.2)), ("grow_at", (1.5,)),
])
def test_a_bad_fit_configuration_is_refused_naming_the_field(field, value):
    changes = {field: value}
    if field == "minutes":
        changes["steps"] = None
    with pytest.raises(InputError, match=rf"FitConfig\.{field}: expected"):
        dataclasses.replace(SMALL, **changes)  # at construction: before make_pairs does any work


def test_a_fit_config_needs_a_budget_and_a_good_one_passes():
    with pytest.raises(InputError, match="budget"):
        FitConfig(minutes=None, steps=None)
    assert FitConfig(minutes=0.5).minutes == 0.5 and SMALL.steps == 240
    assert dataclasses.replace(SMALL, features=0, resolution=4, samples=2, rays=1).rays == 1


def test_real_divergence_is_called_divergence(tmp_path, monkeypatch):
    from roguefit.fit import GridFitter
    from roguenerf.errors import TrainingDivergedError

    root = tmp_path / "photos"
    write_photo_set(root, views=5)
    monkeypatch.setattr(GridFitter, "train_step", lambda self: float("nan"))
    with pytest.raises(TrainingDivergedError, match="non-finite training loss"):
        make_pairs(root, tmp_path / "out", dataclasses.replace(SMALL, steps=3))
    assert not (tmp_path / "out" / "transforms.json").exists()


def test_make_pairs_never_writes_into_a_folder_it_did_not_write(tmp_path):
    """Issue 49: the photo set itself (or any folder of the user's) as the output is refused before any
    work; write_scene_folder would overwrite its transforms.json and photos."""
    root = tmp_path / "photos"
    write_photo_set(root, views=5)
    before = {p: p.read_bytes() for p in root.rglob("*") if p.is_file()}
    for output in (root, tmp_path / "mine"):
        output.mkdir(exist_ok=True)
        (output / "notes.txt").write_text("mine")
        before[output / "notes.txt"] = b"mine"
        with pytest.raises(InputError, match=rf"^output: {output} exists and is not empty: it holds other files, "
                                             r"not an earlier output of this command .*; choose a new folder$"):
            make_pairs(root, output, dataclasses.replace(SMALL, steps=3))
    assert {p: p.read_bytes() for p in before} == before
    assert sorted(p.name for p in (tmp_path / "mine").iterdir()) == ["notes.txt"]


def test_every_kind_and_preset_is_registered_and_an_unknown_kind_is_refused(tmp_path):
    """roguefit.registry: each kind a config can name has a fitter with the Fitter protocol's
    methods, each preset a registered kind and a note for the help strings; make_pairs refuses a
    configuration of an unregistered kind before it reads anything."""
    from roguefit.fit import FIELD_KINDS, GridFitter
    from roguefit.fitter import Fitter
    from roguefit.hashfield import HashFitter
    from roguefit.registry import FITTERS, PRESET_NOTES, PRESETS, describe_presets, fitter_type, presets_of
    from roguefit.splats import SplatConfig, SplatFitter

    assert set(FIELD_KINDS) | {SplatConfig.kind} == set(FITTERS)
    methods = {name for name in vars(Fitter) if not name.startswith("_")}
    assert methods == {"load", "run", "render_view", "summary", "write_extras"}
    for fitter in FITTERS.values():
        assert all(callable(getattr(fitter, name)) for name in methods)
    assert list(PRESETS) == ["blur", "coarse", "fine", "splat", "hash"] and set(PRESET_NOTES) == set(PRESETS)
    assert [fitter_type(PRESETS[p]) for p in PRESETS] == [GridFitter] * 3 + [SplatFitter, HashFitter]
    assert presets_of("grid") == ["blur", "coarse", "fine"] and presets_of("splat") == ["splat"]
    assert describe_presets().startswith("blur (64³ RGB grid, half-size render), coarse (96³ RGB grid)")
    assert "kind" not in SplatConfig().to_dict()  # a class constant: the splat identity is unchanged

    @dataclasses.dataclass(frozen=True)
    class Unknown:
        kind: str = "nerf"
        hold: int = 8

    with pytest.raises(InputError, match=r"kinds grid, hash, splat .* got Unknown of kind 'nerf'"):
        make_pairs(tmp_path / "nowhere", tmp_path / "out", Unknown())
    assert not (tmp_path / "out").exists()
