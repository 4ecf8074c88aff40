"""Checkpoints: bit-exact round trip, and every refusal says what is wrong."""

from __future__ import annotations

import dataclasses
import json
import os
import pickle
import re
import struct

import pytest
import torch
from safetensors import safe_open
from safetensors.torch import load_file, save_file

from roguenerf.checkpoint import FORMAT, default_checkpoint_path, load_checkpoint, save_checkpoint
from roguenerf.errors import CheckpointError
from roguenerf.models import build_enhancer


@pytest.fixture(scope="module")
def saved(tmp_path_factory):
    torch.manual_seed(0)
    model = build_enhancer("micro")
    path = save_checkpoint(tmp_path_factory.mktemp("ck") / "model.safetensors", model, meta={"steps": 7, "loss": 0.25})
    return model, path


def _parts(path):
    tensors = load_file(path)
    with safe_open(path, framework="pt") as f:
        metadata = f.metadata()
    return tensors, metadata


def _rewrite(src, dst, *, tensors=None, metadata=None):
    t, m = _parts(src)
    save_file(tensors if tensors is not None else t, dst, metadata=metadata if metadata is not None else m)
    return dst


def test_round_trip_bit_exact(saved, tmp_path):
    model, path = saved
    loaded, meta = load_checkpoint(path)
    assert meta == {"steps": 7, "loss": 0.25}
    assert loaded.config == model.config
    assert loaded.config.to_dict() == model.config.to_dict()
    expected = model.state_dict()
    got = loaded.state_dict()
    assert list(got) == list(expected)
    for name, tensor in expected.items():
        assert torch.equal(got[name], tensor), name
    assert not loaded.training
    sidecar = json.loads(path.with_suffix(".json").read_text())
    assert sidecar["format"] == FORMAT and sidecar["config"] == model.config.to_dict()
    assert sorted(os.listdir(path.parent)) == ["model.json", "model.safetensors"]  # no temp files


def test_pickle_refused_never_unpickled(tmp_path):
    marker = tmp_path / "marker"

    class Evil:
        def __reduce__(self):
            return (open, (str(marker), "w"))

    # sanity: unpickling this object does create the marker
    pickle.loads(pickle.dumps(Evil()))
    assert marker.exists()
    marker.unlink()
    raw = tmp_path / "raw.safetensors"
    raw.write_bytes(pickle.dumps({"weights": Evil()}))
    with pytest.raises(CheckpointError, match="pickle"):
        load_checkpoint(raw)
    zipped = tmp_path / "torch.safetensors"
    torch.save({"weights": Evil()}, zipped)
    with pytest.raises(CheckpointError, match="zip archive"):
        load_checkpoint(zipped)
    legacy = tmp_path / "legacy.pt"
    torch.save({"weights": Evil()}, legacy, _use_new_zipfile_serialization=False)
    with pytest.raises(CheckpointError, match="pickle"):
        load_checkpoint(legacy)
    assert not marker.exists()


def test_header_length_beyond_file(tmp_path):
    path = tmp_path / "short.safetensors"
    path.write_bytes(struct.pack("<Q", 1000) + b'{"a": 1}')
    with pytest.raises(CheckpointError, match="header length 1000 does not fit a file of 16 bytes"):
        load_checkpoint(path)
    path.write_bytes(b"\x01\x02")
    with pytest.raises(CheckpointError, match="need at least 8"):
        load_checkpoint(path)
    path.write_bytes(struct.pack("<Q", 4) + b"nope")
    with pytest.raises(CheckpointError, match="header is not JSON"):
        load_checkpoint(path)


def test_oversize_and_missing(saved, tmp_path):
    _, path = saved
    size = path.stat().st_size
    with pytest.raises(CheckpointError, match=f"{size} bytes, more than the allowed 1000 bytes"):
        load_checkpoint(path, max_bytes=1000)
    with pytest.raises(CheckpointError, match="not found"):
        load_checkpoint(tmp_path / "none.safetensors")
    with pytest.raises(CheckpointError, match="directory"):
        load_checkpoint(tmp_path)


def test_wrong_format_and_version(saved, tmp_path):
    _, path = saved
    _, meta = _parts(path)
    plain = tmp_path / "plain.safetensors"
    save_file({"x": torch.zeros(2)}, plain)
    with pytest.raises(CheckpointError, match="not a RoGUENeRF enhancer checkpoint: metadata format is None"):
        load_checkpoint(plain)
    newer = _rewrite(path, tmp_path / "v2.safetensors", metadata={**meta, "format_version": "2"})
    with pytest.raises(CheckpointError, match=r"format_version '2' is not supported .*\(expected '1'\)"):
        load_checkpoint(newer)
    cfg = json.loads(meta["config"])
    cfg["wings"] = 2
    odd = _rewrite(path, tmp_path / "cfg.safetensors", metadata={**meta, "config": json.dumps(cfg)})
    with pytest.raises(CheckpointError, match="invalid config: .*wings"):
        load_checkpoint(odd)
    broken = _rewrite(path, tmp_path / "json.safetensors", metadata={**meta, "config": "{oops"})
    with pytest.raises(CheckpointError, match="not valid JSON"):
        load_checkpoint(broken)


def test_missing_and_unexpected_keys_listed(saved, tmp_path):
    _, path = saved
    tensors, _ = _parts(path)
    first, second = list(tensors)[:2]
    tensors.pop(first)
    tensors.pop(second)
    tensors["extra.weight"] = torch.zeros(3)
    bad = _rewrite(path, tmp_path / "keys.safetensors", tensors=tensors)
    with pytest.raises(CheckpointError) as info:
        load_checkpoint(bad)
    message = str(info.value)
    assert f"missing keys {sorted([first, second])}" in message
    assert "unexpected keys ['extra.weight']" in message


def test_shape_mismatch_names_tensor_and_shapes(saved, tmp_path):
    _, path = saved
    tensors, _ = _parts(path)
    name = "conv_I.0.weight"
    shape = tuple(tensors[name].shape)
    tensors[name] = torch.zeros(shape[0] + 1, *shape[1:])
    bad = _rewrite(path, tmp_path / "shape.safetensors", tensors=tensors)
    wrong = (shape[0] + 1, *shape[1:])
    with pytest.raises(CheckpointError, match=re.escape(f"'{name}' has shape {wrong}, the config expects {shape}")):
        load_checkpoint(bad)


def test_nan_weights_name_tensor(saved, tmp_path):
    _, path = saved
    tensors, _ = _parts(path)
    name = list(tensors)[5]
    tensors[name] = tensors[name].clone()
    tensors[name].view(-1)[0] = float("nan")
    bad = _rewrite(path, tmp_path / "nan.safetensors", tensors=tensors)
    with pytest.raises(CheckpointError, match=f"tensor '{name}' contains NaN or inf"):
        load_checkpoint(bad)


def test_corrupt_body_after_valid_header(saved, tmp_path):
    _, path = saved
    data = path.read_bytes()
    bad = tmp_path / "cut.safetensors"
    bad.write_bytes(data[: len(data) - 100])
    with pytest.raises(CheckpointError, match="corrupt safetensors data"):
        load_checkpoint(bad)


def test_save_refuses_nan_and_non_json_meta(tmp_path):
    model = build_enhancer("micro")
    with pytest.raises(Exception, match="JSON"):
        save_checkpoint(tmp_path / "m.safetensors", model, meta={"loss": float("nan")})
    with torch.no_grad():
        next(model.parameters()).view(-1)[0] = float("inf")
    with pytest.raises(CheckpointError, match="NaN or inf"):
        save_checkpoint(tmp_path / "m.safetensors", model)
    assert os.listdir(tmp_path) == []


def test_default_checkpoint_path():
    path = default_checkpoint_path(must_exist=False)
    assert path.parts[-3:] == ("roguenerf", "weights", "default.safetensors")
    if not path.exists():
        with pytest.raises(CheckpointError, match="roguenerf pretrain"):
            default_checkpoint_path()
    else:
        assert default_checkpoint_path() == path


def test_blended_checkpoint_is_the_weighted_mean_and_other_architectures_are_refused(tmp_path):
    from roguenerf.checkpoint import blend_checkpoints
    from roguenerf.errors import InputError
    from roguenerf.models import build_enhancer

    torch.manual_seed(0)
    a, b = build_enhancer("nano"), build_enhancer("nano")
    save_checkpoint(tmp_path / "a.safetensors", a, meta={"training": {"kind": "pretrain"}})
    save_checkpoint(tmp_path / "b.safetensors", b, meta={"training": {"kind": "finetune"}})
    for w in (0.0, 0.25, 1.0):
        blend_checkpoints(tmp_path / "a.safetensors", tmp_path / "b.safetensors", w, tmp_path / f"m{w}.safetensors")
        model, meta = load_checkpoint(tmp_path / f"m{w}.safetensors")
        for k, v in model.state_dict().items():
            want = a.state_dict()[k] + w * (b.state_dict()[k] - a.state_dict()[k])
            assert torch.allclose(v, want, atol=1e-6), k
        assert meta["blend"]["weight"] == w and meta["training"]["kind"] == "finetune"
        assert meta["blend"]["start_training"] == {"kind": "pretrain"}
    # Another default neighbour count is no other architecture: the blend keeps the tuned one's.
    c = build_enhancer("nano")
    c.load_state_dict(b.state_dict())
    c.config = dataclasses.replace(c.config, num_neighbours=a.config.num_neighbours + 3)
    save_checkpoint(tmp_path / "c.safetensors", c)
    blend_checkpoints(tmp_path / "a.safetensors", tmp_path / "c.safetensors", 0.5, tmp_path / "mc.safetensors")
    model, _ = load_checkpoint(tmp_path / "mc.safetensors")
    assert model.config.num_neighbours == a.config.num_neighbours + 3
    key = next(iter(a.state_dict()))
    assert torch.allclose(model.state_dict()[key], (a.state_dict()[key] + b.state_dict()[key]) / 2, atol=1e-6)
    save_checkpoint(tmp_path / "other.safetensors", build_enhancer("micro"))
    with pytest.raises(InputError, match="blend"):
        blend_checkpoints(tmp_path / "a.safetensors", tmp_path / "other.safetensors", 0.5, tmp_path / "x.safetensors")
    with pytest.raises(InputError, match=r"\[0, 1\]"):
        blend_checkpoints(tmp_path / "a.safetensors", tmp_path / "b.safetensors", 1.5, tmp_path / "x.safetensors")
    assert not (tmp_path / "x.safetensors").exists()
