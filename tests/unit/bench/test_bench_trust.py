"""bench/stage_settings.py --stage trust end to end on a toy scene: one enhanced output per view,
each full_share setting applied to it as the share of its change kept."""

from __future__ import annotations

import argparse
import csv

import pytest

from bench import stage_settings
from tests.bench_helpers import summary_by_setting


def test_settings_side_by_side_on_one_output(tmp_path, bright_toy):
    # Renders too bright: colour matching (on, as shipped) changes them, so there is a change to keep.
    _, ckpt = bright_toy
    out = tmp_path / "trust"
    assert stage_settings.main(["--stage", "trust", str(tmp_path / "toy"), f"{tmp_path / 'toy'}={ckpt}",
                                "--checkpoint", str(ckpt), "--settings", "off,0.5,1,local4,below1,alone",
                                "--max-views", "1", "--output", str(out)]) == 0
    rows = list(csv.DictReader(open(tmp_path / "trust.csv")))
    assert [r["setting"] for r in rows] == ["off", "0.5", "1", "local4", "below1", "alone"] * 2
    assert [r["scene"] for r in rows] == ["toy"] * 6 + ["toy (fine-tuned)"] * 6
    off, half, whole, local, below, alone = rows[:6]
    agreement = float(off["agreement"])
    assert 0.5 < agreement < 1  # exact geometry: the neighbours agree on most of the view
    assert float(off["kept"]) == float(half["kept"]) == 1 and half["gain_db"] == off["gain_db"]
    # full_share 1: the share kept is the agreement, and the gain of a colour shift falls with it.
    assert float(whole["kept"]) == pytest.approx(agreement, abs=1e-4)
    assert 0 < float(whole["gain_db"]) < float(off["gain_db"])
    # Per pixel: all of the change where the neighbours agree around it, less where they do not
    # see (the view's edges), so less than all of it on the whole.
    assert 0.5 < float(local["kept"]) < 1 and 0 < float(local["gain_db"]) <= float(off["gain_db"])
    # The shipped rule, per pixel under any share: per view still where it keeps the change whole.
    assert float(below["kept"]) == 1 and below["gain_db"] == off["gain_db"]
    # The model alone as the fallback: nothing to fall back on where the whole change is kept.
    assert float(alone["kept"]) == 1 and alone["gain_db"] == off["gain_db"]
    assert all(r["date"] and r["machine"] and r["commit"] for r in rows)
    assert (tmp_path / "trust.png").stat().st_size > 1000
    s = summary_by_setting(rows, "trust")
    assert s["1"]["gain_db"] == pytest.approx(float(whole["gain_db"]))


@pytest.mark.parametrize("spec", ["", "x", "0", "1.5", "off,-0.2", "local", "local0", "localx",
                                  "below", "below2", "below-1"])
def test_a_bad_setting_is_refused(spec):
    with pytest.raises(argparse.ArgumentTypeError):
        stage_settings.trust_settings(spec)
