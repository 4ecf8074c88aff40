"""bench/cli_startup.py: the one-view enhance command at two commits, alternated, on a toy scene."""

from __future__ import annotations

import csv
import json
import subprocess

import pytest

from bench import cli_startup
from bench.common import REPO
from roguenerf.data.toy import make_toy_scene


@pytest.mark.slow
def test_both_trees_run_alternated_and_the_worktree_goes(tmp_path):
    make_toy_scene(tmp_path / "toy", seed=2, n_train=6, n_test=2, height=48, width=64)
    out = tmp_path / "res" / "startup"
    assert cli_startup.main(["--scene", str(tmp_path / "toy"), "--view", "test_000", "--before", "HEAD",
                             "--repeats", "1", "--output", str(out)]) == 0
    summary = json.loads((tmp_path / "res" / "startup.json").read_text())
    assert summary["repeats"] == 1 and summary["before"]
    for tree in ("before", "after"):
        assert summary[f"{tree}_wall_s"] > summary[f"{tree}_view_s"] > 0
        assert summary[f"{tree}_overhead_s"] == pytest.approx(summary[f"{tree}_wall_s"] - summary[f"{tree}_view_s"],
                                                             abs=2e-3)
    with open(tmp_path / "res" / "startup.csv", newline="") as f:
        assert [row["tree"] for row in csv.DictReader(f)] == ["before", "after"]
    worktrees = subprocess.run(["git", "worktree", "list"], cwd=REPO, capture_output=True, text=True).stdout
    assert str(tmp_path) not in worktrees  # removed after


def test_a_bad_revision_is_refused(tmp_path):
    with pytest.raises(SystemExit, match="--before: 'no-such-rev' is not a revision"):
        cli_startup.main(["--scene", str(tmp_path), "--view", "x", "--before", "no-such-rev"])


@pytest.mark.slow
def test_each_run_keeps_its_pose_judgements_where_it_is_told(tmp_path):
    """The command's judgements go to the folder the bench gives it (a fresh one per run unless
    --keep-judgements), never to the user's cache: a first command on the scene is timed."""
    make_toy_scene(tmp_path / "toy", seed=2, n_train=6, n_test=2, height=48, width=64)
    judgements = tmp_path / "judged"
    wall, view = cli_startup.run_enhance(REPO, tmp_path / "toy", "test_000", tmp_path / "out.png", judgements)
    assert wall > view > 0
    [kept] = judgements.glob("*.json")
    assert json.loads(kept.read_text())["views"]  # the toy scene's neighbours were judged
