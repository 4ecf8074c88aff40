"""bench.paths_summary: the names it reads and the rows it writes, on files made here."""

from __future__ import annotations

import json

import pytest

from bench.paths_summary import main, parse_name


@pytest.mark.parametrize(("stem", "expected"), [
    ("paths_ollie_hash_s1_400steps_1024rays_48samples_4x8", ("ollie_hash_s1_400steps_1024rays_48samples_4x8", "on")),
    ("paths_dtu_scan37_fine_4x16_notemporal", ("dtu_scan37_fine_4x16", "off")),
    ("paths_can_clip_hash_4x8_temporal_reject0.04_fade_deg4", ("can_clip_hash_4x8", "reject0.04_fade_deg4")),
    ("paths_can_clip_fine_s1_600steps", None),  # an older name, without the path's shape
    ("paths_toy", None),
    ("path_speed_ollie_fine_reject", None),
])
def test_names(stem, expected):
    assert parse_name(stem) == expected


def test_rows_and_means(tmp_path):
    def result(name, ratio, gain, turn=5.0):
        (tmp_path / f"{name}.json").write_text(json.dumps({
            "frames": 25, "size": "252x189", "turn_deg": {"mean": turn, "max": turn}, "checkpoint": "a/b.safetensors",
            "flicker": {"ratio": ratio}, "psnr": {"mean_gain_db": gain}, "date": "d", "commit": "c"}))

    result("paths_a_fit_4x8_notemporal", 1.0, 0.5)
    result("paths_a_fit_4x8_temporal_reject0.04", 0.8, 0.4)
    result("paths_b_fit_4x4_temporal_reject0.04", 0.6, 0.2)
    result("paths_old_name", 0.1, 9.0)  # not read
    (tmp_path / "paths_c_fit_4x8.json").write_text(json.dumps({"frames": 3}))  # no flicker: skipped
    out = tmp_path / "out" / "summary"
    assert main(["--results", str(tmp_path), "--output", str(out)]) == 0
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert [(r["path"], r["setting"], r["checkpoint"]) for r in summary["rows"]] == [
        ("a_fit_4x8", "off", "b.safetensors"), ("a_fit_4x8", "reject0.04", "b.safetensors"),
        ("b_fit_4x4", "reject0.04", "b.safetensors")]
    assert summary["by_setting"]["reject0.04"] == {"paths": 2, "flicker_ratio": pytest.approx(0.7),
                                                   "gain_db": pytest.approx(0.3)}
    assert (tmp_path / "out" / "summary.png").is_file() and (tmp_path / "out" / "summary.csv").is_file()
    with pytest.raises(SystemExit, match="no bench.paths results"):
        main(["--results", str(tmp_path / "out"), "--output", str(out)])
