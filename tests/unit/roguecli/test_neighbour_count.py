"""The neighbour count the docs state is the one every entry point uses (issue 17, item 8)."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest
from typer.testing import CliRunner

from roguecli import app
from roguenerf import SceneEnhancer, default_checkpoint_path, load_checkpoint, make_toy_scene

ROOT = Path(__file__).resolve().parents[3]


def _shipped_count() -> int:
    sidecar = json.loads((ROOT / "roguenerf" / "weights" / "default.json").read_text())
    return int(sidecar["config"]["num_neighbours"])


def test_readme_states_the_shipped_checkpoints_count():
    readme = (ROOT / "README.md").read_text()
    stated = re.findall(r"the shipped default checkpoint uses \*\*(\d+)\*\* neighbours", readme)
    assert stated == [str(_shipped_count())], stated
    assert "as the service serves a scene" not in readme  # the old, wrong claim (it said 5)


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return make_toy_scene(tmp_path_factory.mktemp("scene"), seed=2, n_train=6, n_test=1, height=24, width=32)


def test_library_cli_and_service_default_to_the_checkpoints_count(scene, tmp_path):
    model, _ = load_checkpoint(default_checkpoint_path())
    n = model.config.num_neighbours
    assert n == _shipped_count()
    assert len(SceneEnhancer(scene, model).enhance_view("test_000").neighbours) == n
    result = CliRunner().invoke(app, ["enhance", str(scene.root), "--view", "test_000",
                                      "--output", str(tmp_path / "x.png")])
    assert result.exit_code == 0, result.output
    used = re.search(r"with neighbours: (.*)$", result.stderr, re.M).group(1).split(", ")
    assert len(used) == n
    # The service: its cached SceneEnhancer of a scene on the default checkpoint (version 0).
    import shutil

    from jobs.layout import Layout
    from service.settings import Settings
    from service.state import EnhancerCache

    settings = Settings(data_dir=tmp_path / "data")
    layout = Layout(settings.data_dir)
    shutil.copytree(scene.root, layout.scene_files("a" * 32))
    served = EnhancerCache(settings, layout, model).get("a" * 32, 0)
    assert len(served.enhance_view("test_000").neighbours) == n
    # its pose judgements are kept in the scene's folder (a restarted service starts from them)
    assert served.settled_file == layout.scene_dir("a" * 32) / "settled.json"
    restarted = EnhancerCache(settings, layout, model).get("a" * 32, 0)
    assert served.settled and restarted.settled == served.settled
