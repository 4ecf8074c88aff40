"""scripts/pack_pairs.py: pair folders packed small enough for the GPU machine still load as scenes,
with the views, poses and pixels they had (within JPEG q90 and float16)."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import torch

from roguenerf.data.readers import load_scene
from roguenerf.data.toy import make_toy_scene
from roguenerf.metrics import psnr

ROOT = Path(__file__).resolve().parents[3]


def _pack_module():
    spec = importlib.util.spec_from_file_location("pack_pairs", ROOT / "scripts" / "pack_pairs.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_packed_folder_loads_with_every_second_training_view(tmp_path):
    source = make_toy_scene(tmp_path / "toy", seed=4, n_train=7, n_test=2, height=32, width=40)
    pack = _pack_module()
    assert pack.main([str(tmp_path / "toy"), "--out", str(tmp_path / "packed"), "--every", "2", "--quality", "90"]) == 0
    packed = load_scene(tmp_path / "packed" / "toy")
    train = list(source.indices("train"))
    kept = train[::2]  # training views only (held-out views are never pre-training targets), every 2nd
    assert [f.name for f in packed.frames] == [source.frames[i].name for i in kept]
    assert list(packed.indices("train")) == list(range(len(kept))) and not packed.indices("test")
    for j, i in enumerate(kept):
        assert torch.allclose(packed.poses([j]), source.poses([i]))
        assert torch.allclose(packed.intrinsics([j]), source.intrinsics([i]))
        assert float(psnr(packed.photo(j)[None], source.photo(i)[None])[0]) > 30
        assert float(psnr(packed.render(j)[None], source.render(i)[None])[0]) > 30
        depth, original = packed.depth(j), source.depth(i)
        valid = original > 0
        assert torch.all((depth[valid] - original[valid]).abs() <= 1e-3 * original[valid])  # float16
    meta = json.loads((tmp_path / "packed" / "toy" / "transforms.json").read_text())
    assert meta["packed_from"]["every"] == 2 and meta["packed_from"]["jpeg_quality"] == 90


def test_pack_never_deletes_a_folder_it_did_not_pack(tmp_path):
    """Issue 49: the output of a scene used to be removed whatever it held (shutil.rmtree)."""
    import pytest

    make_toy_scene(tmp_path / "toy", seed=4, n_train=3, n_test=1, height=16, width=20)
    pack = _pack_module()
    args = [str(tmp_path / "toy"), "--out", str(tmp_path / "packed")]
    mine = tmp_path / "packed" / "toy"  # e.g. the user's own dataset of that name
    mine.mkdir(parents=True)
    (mine / "transforms.json").write_text('{"frames": []}')
    (mine / "notes.txt").write_text("mine")
    with pytest.raises(SystemExit, match=rf"^{mine}: exists and is not empty: .* choose a new --out$"):
        pack.main(args)
    assert sorted(p.name for p in mine.iterdir()) == ["notes.txt", "transforms.json"]
    (mine / "transforms.json").unlink()
    (mine / "notes.txt").unlink()
    assert pack.main(args) == 0
    assert pack.main(args) == 0  # a folder it packed: replaced
    (mine / "images" / "extra.jpg").write_bytes(b"mine")
    with pytest.raises(SystemExit, match=r"also holds files this script did not write \(images/extra.jpg\)"):
        pack.main(args)
    assert (mine / "images" / "extra.jpg").read_bytes() == b"mine"
