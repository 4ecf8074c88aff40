"""bench.drawn_views on a toy scene: a row per view, the scene's means, and a refusal without
held-out views."""

from __future__ import annotations

import json

import pytest

from bench import drawn_views
from roguenerf.data.degrade import Degradation
from roguenerf.data.toy import make_toy_scene


def test_drawn_views_writes_rows_means_and_a_plot(tmp_path):
    scene = make_toy_scene(tmp_path / "toy", seed=1, n_train=5, n_test=2, height=24, width=32,
                           degradation=Degradation())
    out = tmp_path / "out" / "drawn"
    assert drawn_views.main([str(scene.root), "--output", str(out)]) == 0
    lines = (tmp_path / "out" / "drawn.csv").read_text().splitlines()
    assert len(lines) == 1 + 7 and "drawn_psnr" in lines[0]
    summary = json.loads((tmp_path / "out" / "drawn.json").read_text())["scenes"][0]
    assert (summary["train_views"], summary["held_out_views"]) == (5, 2)
    assert 0.3 < summary["drawn_share"] <= 1.0
    # the toy's renders are its photos degraded alike in every view: drawn from another camera,
    # a training view is further from its photo than its own render
    assert summary["train_drawn_psnr"] < summary["train_render_psnr"]
    assert (tmp_path / "out" / "drawn.png").stat().st_size > 0


def test_a_scene_without_held_out_views_is_refused(tmp_path):
    scene = make_toy_scene(tmp_path / "toy", seed=1, n_train=4, n_test=0, height=16, width=20)
    with pytest.raises(SystemExit, match="held-out views"):
        drawn_views.main([str(scene.root), "--output", str(tmp_path / "x")])
