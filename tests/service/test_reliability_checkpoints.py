"""Checkpoint uploads (at registration and POST /scenes/{id}/checkpoints): only safetensors
that load; a pickle is never unpickled (its marker file never appears); a header larger than
the file, wrong keys / shapes, non-finite weights, an oversize file -> 4xx; the scene keeps
its previous checkpoint and answers /enhance exactly as before.
"""

from __future__ import annotations

import json
import struct

import numpy as np
import pytest
import torch
from safetensors import safe_open
from safetensors.torch import save

from tests.reliability_helpers import (
    assert_error,
    assert_healthy,
    pickled_checkpoint,
    post_enhance,
    read_png,
)

MAX_CKPT = 4 << 20


SERVER = {"max_checkpoint_bytes": MAX_CKPT}  # the shared server fixture's settings


@pytest.fixture(scope="module")
def parts(s, tmp_path_factory):
    """The valid checkpoint's tensors and metadata, to forge variants from."""
    path = tmp_path_factory.mktemp("ck") / "good.safetensors"
    path.write_bytes(s.checkpoint)
    with safe_open(str(path), "pt") as f:
        return {k: f.get_tensor(k) for k in f.keys()}, f.metadata()


def _enhanced(s) -> tuple[np.ndarray, str]:
    view = s.view()
    r = post_enhance(s.client, s.scene_id, render=view["render"], depth=view["depth"], camera=view["camera"])
    assert r.status_code == 200, r.text
    return read_png(r.content), r.headers["X-Checkpoint-Version"]


def _forge(parts, case: str) -> bytes:
    tensors, meta = parts
    tensors = dict(tensors)
    name = sorted(k for k in tensors if tensors[k].ndim >= 2)[0]
    if case == "missing_key":
        del tensors[name]
    elif case == "extra_key":
        tensors["surprise.weight"] = torch.zeros(3)
    elif case == "wrong_shape":
        tensors[name] = torch.zeros(*tensors[name].shape[:-1], tensors[name].shape[-1] + 1)
    elif case in ("nan", "inf"):
        t = tensors[name].clone()
        t.view(-1)[0] = float(case)
        tensors[name] = t
    elif case == "no_metadata":
        meta = None
    elif case == "wrong_format":
        meta = {**meta, "format": "someone-else"}
    elif case == "bad_config":
        meta = {**meta, "config": json.dumps({"variant": "micro", "channels": -4})}
    return save(tensors, metadata=meta)


def _header_larger_than_file(good: bytes) -> bytes:
    return struct.pack("<Q", 10**9) + good[8:200]


def _bad_json_header(good: bytes) -> bytes:
    n = struct.unpack("<Q", good[:8])[0]
    return good[:8] + b"{" * n + good[8 + n:]


CASES = ["pickle", "header_larger_than_file", "bad_json_header", "missing_key", "extra_key", "wrong_shape",
         "nan", "inf", "no_metadata", "wrong_format", "bad_config", "oversize", "empty", "zeros"]


@pytest.mark.parametrize("case", CASES)
def test_bad_checkpoint_is_refused_and_the_scene_keeps_its_own(s, parts, case, tmp_path):
    marker = tmp_path / "unpickled-marker"
    if case == "pickle":
        data = pickled_checkpoint(marker)
    elif case == "header_larger_than_file":
        data = _header_larger_than_file(s.checkpoint)
    elif case == "bad_json_header":
        data = _bad_json_header(s.checkpoint)
    elif case == "oversize":
        data = s.checkpoint + b"\x00" * (MAX_CKPT + 1 - len(s.checkpoint))
    elif case == "empty":
        data = b""
    elif case == "zeros":
        data = b"\x00" * 4096
    else:
        data = _forge(parts, case)
    image_before, version_before = _enhanced(s)
    before = s.stored()

    replaced = s.client.post(f"/scenes/{s.scene_id}/checkpoints", files={"checkpoint": ("m.safetensors", data)})
    registered = s.client.post("/scenes", files={"archive": ("a.zip", s.zip), "checkpoint": ("m.safetensors", data)})
    for r in (replaced, registered):
        if case == "oversize":
            assert str(MAX_CKPT) in assert_error(r, 413, "payload_too_large")
        else:
            message = assert_error(r, 422)
            assert "checkpoint" in message.lower(), message

    assert not marker.exists()
    assert s.stored() == before  # no new scene, no new version, nothing left in tmp/
    image_after, version_after = _enhanced(s)
    assert version_after == version_before
    assert np.array_equal(image_after, image_before)
    assert_healthy(s.client)


def test_the_pickle_marker_is_live(tmp_path):
    """Guards the test above: the payload really creates its marker when unpickled."""
    import pickle

    marker = tmp_path / "m"
    pickle.loads(pickled_checkpoint(marker))
    assert marker.exists()


def test_a_good_checkpoint_replaces_the_active_one(s, tmp_path):
    image_before, version_before = _enhanced(s)
    from roguenerf import build_enhancer, save_checkpoint

    torch.manual_seed(7)
    model = build_enhancer("micro", num_neighbours=2)
    with torch.no_grad():
        for p in model.parameters():
            p.add_(0.05 * torch.randn_like(p))  # a fresh enhancer is the identity; make it differ
    other = save_checkpoint(tmp_path / "other.safetensors", model).read_bytes()
    r = s.client.post(f"/scenes/{s.scene_id}/checkpoints", files={"checkpoint": ("x", other)})
    assert r.status_code == 201, r.text
    assert r.json()["active_version"] == int(version_before) + 1
    image_after, version_after = _enhanced(s)
    assert version_after == str(int(version_before) + 1)
    assert not np.array_equal(image_after, image_before)
    stored = s.data_dir / "scenes" / s.scene_id / "checkpoints" / f"v{version_after}.safetensors"
    assert stored.read_bytes() == other
    assert_error(s.client.post(f"/scenes/{'0' * 32}/checkpoints", files={"checkpoint": ("x", other)}), 404)
