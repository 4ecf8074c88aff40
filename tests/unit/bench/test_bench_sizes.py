"""bench/sizes.py: scenes brought to a size (crop to the aspect ratio, then resample, K with
them) and the per-step timings of a real run on a toy scene."""

from __future__ import annotations

import csv
import json
import math
import subprocess

import pytest
import torch

from bench import sizes
from bench.common import REPO
from roguenerf.data.readers import load_scene
from roguenerf.data.toy import make_toy_scene


def test_a_sized_scene_keeps_its_geometry(tmp_path):
    src = make_toy_scene(tmp_path / "toy", seed=1, n_train=4, n_test=1, height=48, width=64)
    out = sizes.sized_scene(tmp_path / "toy", (90, 90), tmp_path / "square")
    scene = load_scene(out)
    assert [f.name for f in scene.frames] == [f.name for f in src.frames]
    assert (scene.frames[0].width, scene.frames[0].height) == (90, 90)
    # The 48x64 view is cropped to its central 48x48 (8 px off each side), then scaled by 90/48:
    # a point projects to where it did, moved and scaled the same way.
    point = torch.tensor([0.1, -0.2, 0.3, 1.0], dtype=torch.float64)

    def project(frame):
        cam = torch.linalg.inv(frame.world_from_cam.double()) @ point
        uvw = frame.K.double() @ cam[:3]
        return uvw[:2] / uvw[2]

    for a, b in zip(src.frames, scene.frames, strict=True):
        uv_a, uv_b = project(a), project(b)
        want = (uv_a - torch.tensor([8.0, 0.0], dtype=torch.float64)) * 90 / 48
        assert torch.allclose(uv_b, want, atol=1e-3)
    # Depth is resampled with nearest: no value the source does not have.
    assert set(scene.depth(0).unique().tolist()) <= set(src.depth(0).unique().tolist())
    assert sizes.sized_scene(tmp_path / "toy", (90, 90), out) == out  # written once


def test_settings_and_sizes_are_checked():
    assert sizes.parse_setting("defaults") == ({}, {})
    assert sizes.parse_setting("no-align+no-trust+neighbours=3+cache=0.5") == (
        {"align": False, "trust": False, "neighbours": 3}, {"cache_bytes": 2**19})
    from roguenerf.enhance.align import AlignConfig

    flags, _ = sizes.parse_setting("early=0")
    assert flags == {"align": AlignConfig(early_refusal=0.0)}
    assert eval(repr(flags), {"AlignConfig": AlignConfig}) == flags  # what the child process reads
    assert sizes.parse_setting("judged") == ({}, {"judged": True})
    assert sizes.parse_setting("measured+no-trust") == ({"trust": False}, {"measured": True})
    with pytest.raises(SystemExit, match="unknown switch 'no-model'"):
        sizes.parse_setting("no-model")
    assert sizes.parse_size("1920x1080") == (1920, 1080)
    with pytest.raises(SystemExit, match="WIDTHxHEIGHT"):
        sizes.parse_size("1920")


@pytest.mark.slow
def test_a_run_reports_every_step_and_the_memory(tmp_path):
    make_toy_scene(tmp_path / "toy", seed=2, n_train=6, n_test=2, height=72, width=96)
    out = tmp_path / "res" / "sizes"
    assert sizes.main(["--scene", str(tmp_path / "toy"), "--sizes", "64x48", "--views", "2",
                       "--settings", "defaults,no-align+no-colour+no-trust+cache=0,judged,measured",
                       "--work", str(tmp_path / "work"), "--output", str(out)]) == 0
    summary = json.loads((tmp_path / "res" / "sizes.json").read_text())["summary"]
    assert [(s["size"], s["setting"]) for s in summary] == [("64x48", "defaults"),
                                                            ("64x48", "no-align+no-colour+no-trust+cache=0"),
                                                            ("64x48", "judged"), ("64x48", "measured")]
    on, off, judged, measured = summary
    assert measured["views"] == 2 and math.isfinite(measured["gain_db"])
    with open(tmp_path / "res" / "sizes.csv", newline="") as f:
        measured_by = {r["setting"]: int(r["candidates"]) for r in csv.DictReader(f)}
    assert measured_by["measured"] > 0 and measured_by["defaults"] == 0  # only that rule measures candidates
    # the poses judged by an earlier enhancer: the same images, fits only where one was kept
    assert judged["gain_db"] == pytest.approx(on["gain_db"], abs=1e-6) and judged["align_s"] < 0.5 * on["align_s"]
    assert on["align_s"] > 0 and off["align_s"] < on["align_s"]
    assert off["colour_s"] == off["trust_s"] == 0  # stages off: never run
    assert 100 < on["peak_mb"] < 4000 and on["cli_wall_s"] > on["cli_view_s"] > 0
    assert (tmp_path / "res" / "sizes.csv").is_file() and (tmp_path / "res" / "sizes.png").is_file()


@pytest.mark.slow
def test_an_older_revision_runs_beside_this_one_alternated(tmp_path):
    make_toy_scene(tmp_path / "toy", seed=2, n_train=6, n_test=2, height=72, width=96)
    out = tmp_path / "res" / "sizes"
    assert sizes.main(["--scene", str(tmp_path / "toy"), "--sizes", "64x48", "--views", "2", "--no-cli",
                       "--settings", "no-align", "--before", "HEAD", "--rounds", "2", "--work", str(tmp_path / "work"),
                       "--output", str(out)]) == 0
    report = json.loads((tmp_path / "res" / "sizes.json").read_text())
    (older, newer) = report["summary"]
    assert older["setting"].startswith("no-align@") and newer["setting"] == "no-align"
    assert older["children"] == newer["children"] == 2 and older["views"] == newer["views"] == 4
    assert "--before HEAD" in report["command"]
    assert older["gain_db"] == pytest.approx(newer["gain_db"], abs=1e-6)  # HEAD's code against this checkout's
    with open(tmp_path / "res" / "sizes.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    # children alternate: older, newer, older, newer; each child's first view marked
    assert [r["setting"] for r in rows[::2]] == [older["setting"], "no-align"] * 2
    assert [r["first"] for r in rows] == ["True", "False"] * 4
    worktrees = subprocess.run(["git", "worktree", "list"], cwd=REPO, capture_output=True, text=True).stdout
    assert not [line for line in worktrees.splitlines() if line.split()[0].endswith("/before")]  # removed after
