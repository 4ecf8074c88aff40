"""bench/stage_settings.py --stage align end to end on a toy scene: both settings per view, in one
run, with the pose-noise level; the refinement is used where the poses are wrong."""

from __future__ import annotations

import csv

from bench import stage_settings
from roguenerf.checkpoint import save_checkpoint
from roguenerf.data.toy import make_toy_scene
from roguenerf.models import Enhancer, make_config


def test_both_settings_side_by_side(tmp_path):
    make_toy_scene(tmp_path / "toy", seed=2, n_train=6, n_test=2, height=72, width=96)
    ckpt = save_checkpoint(tmp_path / "m.safetensors", Enhancer(make_config("nano", num_neighbours=2)))
    out = tmp_path / "cost"
    assert stage_settings.main(["--stage", "align", str(tmp_path / "toy"), "--checkpoint", str(ckpt),
                                "--noise", "0/0,0.5/0.05", "--max-views", "1", "--settings", "off,on,early0",
                                "--output", str(out)]) == 0
    rows = list(csv.DictReader(open(out.with_suffix(".csv"))))
    assert [(r["noise_deg"], r["align"]) for r in rows] == [("0.0", "off"), ("0.0", "on"), ("0.0", "early0"),
                                                            ("0.5", "off"), ("0.5", "on"), ("0.5", "early0")]
    assert [r["early_refusal"] for r in rows[:3]] == ["", "0.05", "0.0"]  # off, the shipped one, every level
    assert all(float(r["seconds"]) > 0 and r["date"] and r["machine"] and r["commit"] for r in rows)
    assert float(rows[1]["aligned_share"]) == 0.0  # exact poses: no fit clears the bar
    assert float(rows[4]["aligned_share"]) == 1.0  # wrong poses: both neighbours refined
    assert float(rows[5]["aligned_share"]) == 1.0  # ... and the same with every level fitted
    assert rows[5]["gain_db"] == rows[4]["gain_db"]
    assert out.with_suffix(".png").stat().st_size > 1000
