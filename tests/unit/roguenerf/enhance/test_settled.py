"""Pose judgements kept between processes (roguenerf.enhance.settled, issue 51)."""

from __future__ import annotations

import json
import os

import pytest
import torch

from roguenerf.data.toy import make_toy_scene
from roguenerf.enhance import EnhanceOptions, settled
from roguenerf.enhance.align import AlignConfig
from tests.unit.roguenerf.enhance.test_align import _counting_fits

pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.fixture
def scene_and_model(tmp_path):
    from roguenerf.models import Enhancer, make_config

    scene = make_toy_scene(tmp_path / "scene", n_train=6, n_test=3, height=48, width=64)
    return scene, Enhancer(make_config("nano", num_neighbours=2))


def test_a_later_process_starts_from_the_judgements_of_an_earlier_one(scene_and_model, tmp_path, monkeypatch):
    """A second enhancer reading the first one's file fits none of the neighbours the first
    judged settled, and gives the same images; an enhancer without the file fits them again."""
    from roguenerf.inference import SceneEnhancer

    scene, model = scene_and_model
    path = tmp_path / "settled.json"
    first = SceneEnhancer(scene, model, settled_file=path)
    images = [first.enhance_view(i).image for i in scene.indices("test")]
    assert first.settled and path.is_file()
    data = json.loads(path.read_text())
    assert sorted(data["views"]) == sorted(first.train_names[p] for p in first.settled)
    assert "reuse" not in data["align"] and data["align"]["min_gain"] == AlignConfig().min_gain

    calls = _counting_fits(monkeypatch)
    second = SceneEnhancer(scene, model, settled_file=path)
    assert second.settled == first.settled
    skipped = 0
    for i, image in zip(scene.indices("test"), images, strict=True):
        calls.clear()
        result = second.enhance_view(i)
        assert torch.equal(result.image, image)
        used = {first.train_names.index(n) for n in result.neighbours}
        assert len(calls) == len(used - first.settled)  # only the neighbours not settled are fitted
        skipped += len(used & first.settled)
    assert skipped >= len(first.settled)
    calls.clear()
    alone = SceneEnhancer(scene, model)  # no file: judges again
    for i in scene.indices("test"):
        alone.enhance_view(i)
    assert alone.settled == first.settled and len(calls) >= len(first.settled)


def test_a_judgement_is_dropped_when_what_it_read_changed(scene_and_model, tmp_path):
    from roguenerf.inference import SceneEnhancer

    scene, model = scene_and_model
    path = tmp_path / "settled.json"
    first = SceneEnhancer(scene, model, settled_file=path)
    for i in scene.indices("test"):
        first.enhance_view(i)
    names = {first.train_names[p] for p in first.settled}
    assert len(names) >= 2
    moved, *rest = sorted(names)
    photo = scene.frames[scene.index(moved)].image_path
    st = os.stat(photo)
    os.utime(photo, ns=(st.st_atime_ns, st.st_mtime_ns + 10**9))  # a new photo (or render) there
    assert settled.load(path, scene, first.train_names, AlignConfig()) == set(rest)
    # other settings of the pose fit: nothing carries over
    assert settled.load(path, scene, first.train_names, AlignConfig(min_gain=0.2)) == set()
    # reuse off: the file is not read
    assert not SceneEnhancer(scene, model, settled_file=path,
                             options=EnhanceOptions(align=AlignConfig(reuse=False))).settled


def test_a_broken_or_unwritable_file_costs_only_the_fits(scene_and_model, tmp_path, caplog):
    from roguenerf.inference import SceneEnhancer

    scene, model = scene_and_model
    path = tmp_path / "settled.json"
    path.write_text("{not json")
    enhancer = SceneEnhancer(scene, model, settled_file=path)
    assert not enhancer.settled and "not read" in caplog.text
    for i in scene.indices("test"):
        enhancer.enhance_view(i)
    assert json.loads(path.read_text())["version"] == settled.VERSION  # written anew
    blocked = tmp_path / "a_file"
    blocked.write_text("")
    assert settled.save(blocked / "settled.json", scene, [enhancer.train_names[0]], AlignConfig()) is False
    SceneEnhancer(scene, model, settled_file=blocked / "settled.json").enhance_view(scene.indices("test")[0])
    # a folder that went away (a scene deleted while a request ran) is not made again
    gone = tmp_path / "deleted_scene" / "settled.json"
    assert settled.save(gone, scene, [enhancer.train_names[0]], AlignConfig()) is False
    assert not gone.parent.exists()


def test_default_path_is_one_file_per_scene_folder(tmp_path, monkeypatch):
    monkeypatch.setenv("ROGUENERF_SETTLED_CACHE", str(tmp_path / "store"))
    a, b = settled.default_path(tmp_path / "a"), settled.default_path(tmp_path / "b")
    assert a.parent == tmp_path / "store" and a.suffix == ".json" and a != b
    assert a.parent.is_dir()  # made here, where save() will write
    assert settled.default_path(tmp_path / "x" / ".." / "a") == a  # the resolved folder
    monkeypatch.delenv("ROGUENERF_SETTLED_CACHE")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert settled.default_path(tmp_path / "a").parent == tmp_path / "xdg" / "roguenerf" / "settled"
