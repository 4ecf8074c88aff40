"""scripts/gpu_speed.py on the CPU alone (the GPU rows need a lent card): every row is written,
with the seconds and the gain, and a CUDA request without a card is a clear error."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import pytest

from roguenerf.data.toy import make_toy_scene

SCRIPT = Path(__file__).resolve().parents[3] / "scripts" / "gpu_speed.py"


def _script():
    spec = importlib.util.spec_from_file_location("gpu_speed", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.slow
def test_the_cpu_rows_are_written(tmp_path):
    make_toy_scene(tmp_path / "toy", seed=3, n_train=6, n_test=1, height=48, width=64)
    assert _script().main([str(tmp_path / "toy"), "--devices", "cpu", "--sizes", "64x48,32x24", "--views", "2",
                           "--frames", "3", "--out", str(tmp_path / "out")]) == 0
    rows = json.loads((tmp_path / "out" / "gpu_speed.json").read_text())["rows"]
    views = [r for r in rows if "seconds_per_view" in r]
    assert [(r["size"], r["device"], r["precision"]) for r in views] == [("64x48", "cpu", "float32"),
                                                                         ("32x24", "cpu", "float32")]
    assert all(r["seconds_per_view"] > 0 and r["views"] == 1 for r in views)
    path = [r for r in rows if "path_frames" in r]
    assert [(r["temporal"], r["path_frames"]) for r in path] == [(False, 3), (True, 3)]
    assert all(r["frames_per_second"] > 0 for r in path)


def test_cuda_without_a_card_is_refused(tmp_path, monkeypatch):
    import torch

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    with pytest.raises(SystemExit, match="no CUDA device here"):
        _script().main([str(tmp_path), "--out", str(tmp_path / "out")])
