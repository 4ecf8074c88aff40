"""What a new user hit (issue 38), over a real socket: a scene with an unusable view is registered
with a warning naming it; Unicode file names in a scene zip are accepted when safe (NFC or NFD)
and otherwise answered with a safe name to rename to; a NaN budget is answered clearly.
"""

from __future__ import annotations

import io
import json
import unicodedata
import zipfile
from pathlib import Path

import numpy as np
import pytest

from tests.service_helpers import register, tree_digest

# The shared toy fixture's scene (tests/conftest.py): small, quick to register.
TOY_SCENE = {"height": 24, "width": 32, "n_train": 4, "n_test": 1}


@pytest.fixture(scope="module")
def folder(toy):
    return toy["folder"]


def _zip(folder: Path, rename: dict[str, str] | None = None, *, json_form: str | None = None) -> bytes:
    """The scene zipped as `scene/...`, with photo files renamed (``old name -> new name``) in the
    archive and in transforms.json (``json_form``: the Unicode form transforms.json spells them in)."""
    rename = rename or {}
    doc = json.loads((folder / "transforms.json").read_text())
    for frame in doc["frames"]:
        path = Path(frame["file_path"])
        if path.name in rename:
            new = rename[path.name]
            frame["file_path"] = str(path.with_name(unicodedata.normalize(json_form, new) if json_form else new))
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as zf:
        for path in sorted(folder.rglob("*")):
            if not path.is_file():
                continue
            rel = path.relative_to(folder)
            if rel.as_posix() == "transforms.json":
                zf.writestr("scene/transforms.json", json.dumps(doc))
                continue
            photo = rel.parts[0] == Path(_photo_path(doc)).parts[0]
            name = rename.get(rel.name, rel.name) if photo else rel.name
            zf.write(path, f"scene/{rel.with_name(name).as_posix()}")
    return buf.getvalue()


def _photo_path(doc: dict) -> str:
    return doc["frames"][0]["file_path"]


def _photo(folder: Path, k: int = 0) -> str:
    doc = json.loads((folder / "transforms.json").read_text())
    return Path(doc["frames"][k]["file_path"]).name


def test_a_scene_with_an_all_zero_training_depth_is_registered_with_a_warning(client, tmp_path, folder):
    import shutil

    from roguenerf.data.readers import load_scene

    copy = tmp_path / "scene"
    shutil.copytree(folder, copy)
    scene = load_scene(copy)
    bad = scene.frames[scene.indices("train")[2]]
    np.save(bad.depth_path, np.zeros((24, 32), np.float32))
    r = register(client, _zip(copy))
    assert r.status_code == 201, r.text
    warnings = r.json()["warnings"]
    assert len(warnings) == 1
    assert warnings[0].startswith(f"unusable view {bad.name} (train): depth has no usable values (all zeros")
    assert str(tmp_path) not in warnings[0]
    # A clean scene has none; the scene's later descriptions carry no stale list.
    clean = register(client, _zip(folder))
    assert clean.status_code == 201 and clean.json()["warnings"] == []
    assert client.get(f"/scenes/{r.json()['id']}").json()["warnings"] == []


@pytest.mark.parametrize("new, member_form, json_form", [
    ("phöto_été.png", "NFC", "NFC"),      # what most tools write
    ("phöto_été.png", "NFD", "NFC"),      # a macOS zip: decomposed member names
    ("phöto_été.png", "NFD", "NFD"),      # ... and decomposed in transforms.json too
    ("写真_0.png", "NFC", "NFC"),          # another script
])
def test_safe_unicode_names_are_accepted_nfc_normalised(client, server, folder, new, member_form, json_form):
    old = _photo(folder)
    r = register(client, _zip(folder, {old: unicodedata.normalize(member_form, new)}, json_form=json_form))
    assert r.status_code == 201, r.text
    stored = server.settings.data_dir / "scenes" / r.json()["id"] / "scene" / "images"
    assert unicodedata.normalize("NFC", new) in [p.name for p in stored.iterdir()]


@pytest.mark.parametrize("new, described, suggestion", [
    ("photo\u202egnp.png", "U+202E RIGHT-TO-LEFT OVERRIDE", "'photo_gnp.png'"),
    ("photo\u200b0.png", "U+200B ZERO WIDTH SPACE", "'photo_0.png'"),
    ("📷0.png", "U+1F4F7 CAMERA", "'_0.png'"),
    ("photo\u00a00.png", "U+00A0 NO-BREAK SPACE", "'photo_0.png'"),
])
def test_unsafe_unicode_names_are_refused_saying_how_to_rename(client, server, folder, new, described,
                                                               suggestion):
    before = tree_digest(server.settings.data_dir / "scenes")
    r = register(client, _zip(folder, {_photo(folder): new}))
    assert r.status_code == 422, r.text
    error = r.json()["error"]
    assert error["code"] == "invalid_archive"
    assert described in error["message"] and f"rename it, e.g. to {suggestion}" in error["message"]
    assert tree_digest(server.settings.data_dir / "scenes") == before


def test_a_nan_budget_is_answered_as_not_a_finite_number(client, folder):
    scene_id = register(client, _zip(folder)).json()["id"]
    for raw in ('{"minutes": NaN}', '{"minutes": Infinity}', '{"minutes": "NaN"}'):
        r = client.post(f"/scenes/{scene_id}/finetune", content=raw, headers={"content-type": "application/json"})
        assert r.status_code == 422, r.text
        message = r.json()["error"]["message"]
        assert "minutes" in message and "finite number" in message and "greater than 0" not in message
    r = client.post(f"/scenes/{scene_id}/finetune", json={"minutes": -1})
    assert r.status_code == 422 and "> 0" in r.json()["error"]["message"]


def test_utf8_names_without_the_zip_utf8_flag_are_decoded_again():
    from service.storage import _member_parts

    info = zipfile.ZipInfo("scene/images/x.png")
    # What zipfile reads from an older archiver: UTF-8 bytes, no flag 0x800, decoded as cp437.
    info.filename = "scene/images/phöto.png".encode().decode("cp437")
    info.flag_bits = 0
    assert _member_parts(info) == ["scene", "images", "phöto.png"]
    nfd = zipfile.ZipInfo(unicodedata.normalize("NFD", "scene/images/phöto.png"))
    nfd.flag_bits = 0x800
    assert _member_parts(nfd) == ["scene", "images", "phöto.png"]  # NFC
