"""bench/finetune_guard.py with known answers: a fresh (identity) enhancer "fine-tuned" into the
shipped weights is kept by the guard and gains on the held-out views; the reverse is refused and
the guarded held-out gain is the starting weights'."""

from __future__ import annotations

import csv
import json

from bench import finetune_guard
from roguenerf.checkpoint import default_checkpoint_path, load_checkpoint, save_checkpoint
from roguenerf.data.degrade import Degradation
from roguenerf.data.toy import make_toy_scene
from roguenerf.models import build_enhancer


def test_the_bench_keeps_a_better_fine_tune_and_refuses_a_worse_one(tmp_path):
    scene = make_toy_scene(tmp_path / "scene", seed=5, n_train=6, n_test=2, height=40, width=56,
                           degradation=Degradation(), kind="orbit")
    shipped, _ = load_checkpoint(default_checkpoint_path())
    identity = tmp_path / "identity.safetensors"
    save_checkpoint(identity, build_enhancer(shipped.config))
    out = tmp_path / "guard"
    assert finetune_guard.main([f"{scene.root}={default_checkpoint_path()}", "--checkpoint", str(identity),
                                "--output", str(out)]) == 0
    assert finetune_guard.main([f"{scene.root}={identity}", "--output", str(tmp_path / "reverse")]) == 0
    (better,), (worse,) = (list(csv.DictReader(open(p.with_suffix(".csv")))) for p in (out, tmp_path / "reverse"))
    assert better["kept"] == "True" and worse["kept"] == "False"
    assert float(better["drawn_tuned_db"]) > float(better["drawn_start_db"])
    assert float(better["held_out_tuned_db"]) > float(better["held_out_start_db"]) + 0.3
    assert better["held_out_guarded_db"] == better["held_out_tuned_db"]
    assert worse["held_out_guarded_db"] == worse["held_out_start_db"] == better["held_out_tuned_db"]
    assert json.loads(out.with_suffix(".json").read_text())["rows"][0]["guard_views"] == 6
    assert out.with_suffix(".png").is_file()
