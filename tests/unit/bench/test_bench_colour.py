"""bench/stage_settings.py --stage colour end to end on a toy scene: one model output per view, each
colour setting applied to it; matching takes a model's colour bias out."""

from __future__ import annotations

import csv

import pytest

from bench import stage_settings
from roguenerf.errors import InputError
from tests.bench_helpers import summary_by_setting


def test_settings_side_by_side_on_one_output(tmp_path, bright_toy):
    # The test views' renders come out too bright (as a field that learned another exposure):
    # a fresh enhancer is the identity, so only colour matching can take it back out.
    _, ckpt = bright_toy
    out = tmp_path / "colour_0.5"
    assert stage_settings.main(["--stage", "colour", str(tmp_path / "toy"), "--checkpoint", str(ckpt),
                                "--settings", "off,local_sigma=0,default", "--max-views", "1",
                                "--output", str(out)]) == 0
    rows = list(csv.DictReader(open(tmp_path / "colour_0.5.csv")))
    assert [r["config"] for r in rows] == ["off", "local_sigma=0", "default"]
    off, flat, default = rows
    assert off["changed"] == "False" and off["agree_share"] == ""
    # The neighbours (the photos, exact geometry) agree: their colour replaces the render's.
    assert default["changed"] == "True" and float(default["agree_share"]) > 0.3
    assert float(default["gain_db"]) > float(off["gain_db"]) + 1 and float(flat["gain_db"]) > float(off["gain_db"])
    assert all(r["date"] and r["machine"] and r["commit"] for r in rows)
    assert (tmp_path / "colour_0.5.png").stat().st_size > 1000
    s = summary_by_setting(rows, "colour")
    assert s["default"]["gain_db"] == pytest.approx(float(default["gain_db"]))


@pytest.mark.parametrize("spec", ["sigma", "nope=1", "local_sigma=-1"])
def test_a_bad_setting_is_refused(spec):
    with pytest.raises(InputError):
        stage_settings.colour_config(spec)
