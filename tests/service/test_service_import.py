"""A 3DGS user's upload: a COLMAP dataset zip plus the trained ``point_cloud.ply`` become a scene
through ``POST /scenes/import`` (a job: the worker calls the library's ``import_3dgs``); a COLMAP
zip sent to ``POST /scenes`` is refused naming that route and the CLI command (issue 49, item 12b).

The API runs in uvicorn (a thread); the worker's task runs in this process (``run_job``).
"""

from __future__ import annotations

import pytest

from service.settings import Settings
from tests.service_helpers import (
    FAST,
    LiveServer,
    make_checkpoint,
    make_scene,
    register,
    splat_dataset,
    tree_digest,
    wait_until,
    zip_folder,
)
from workers.dispatch import run_job
from workers.worker import build_worker


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    root = tmp_path_factory.mktemp("import")
    splats = splat_dataset(root)
    ckpt = make_checkpoint(root / "micro.safetensors")
    settings = Settings(data_dir=root / "data", **FAST)
    with LiveServer(settings) as live:
        ctx, _queue, _store = build_worker(settings)
        with live.client() as client:
            yield {"client": client, "ctx": ctx, "data": settings.data_dir, "root": root, "ckpt": ckpt,
                   "zip": zip_folder(splats["dataset"], prefix="garden"), **splats}


def stored(data) -> dict:
    return {k: tree_digest(data / k) for k in ("scenes", "tmp", "jobs")}


def post_import(client, archive: bytes, ply: bytes, **extra):
    files = {"archive": ("garden.zip", archive, "application/zip"),
             "ply": ("point_cloud.ply", ply, "application/octet-stream")}
    if "checkpoint" in extra:
        files["checkpoint"] = ("model.safetensors", extra.pop("checkpoint"), "application/octet-stream")
    return client.post("/scenes/import", files=files, data={k: str(v) for k, v in extra.items()})


@pytest.mark.parametrize("kind", ["colmap", "photos_only"])
def test_a_dataset_zip_sent_as_a_scene_is_refused_naming_the_import(setup, kind, tmp_path):
    """A COLMAP zip was refused with "import it first" (which import, how?); a transforms.json
    with photos only (nerfstudio's processed data) was registered as a scene with nothing to enhance."""
    import json

    client, data = setup["client"], setup["data"]
    archive = setup["zip"]
    if kind == "photos_only":
        scene = make_scene(tmp_path / "scene")
        doc = json.loads((tmp_path / "scene" / "transforms.json").read_text())
        for frame in doc["frames"]:
            del frame["render_path"], frame["depth_path"]
        (tmp_path / "scene" / "transforms.json").write_text(json.dumps(doc))
        assert scene.frames[0].render_path is not None  # the original scene had them
        archive = zip_folder(tmp_path / "scene")
    before = stored(data)
    r = register(client, archive)
    assert r.status_code == 422, r.text
    error = r.json()["error"]
    assert error["code"] == "invalid_scene"
    start = {"colmap": "archive: a COLMAP dataset (photos and poses), not a scene: ",
             "photos_only": "archive: photos and poses only (no view has a render or a depth), a dataset, not a "
                            "scene: "}[kind]
    assert error["message"].startswith(start), error
    assert "POST /scenes/import" in error["message"] and "roguenerf import-3dgs" in error["message"]
    assert str(data) not in error["message"]
    assert stored(data) == before and client.get("/scenes").json()["items"] == []


def test_a_colmap_zip_and_its_ply_become_a_scene(setup):
    from roguenerf.imageio import read_image
    from roguenerf.splats import render

    client, data = setup["client"], setup["data"]
    r = post_import(client, setup["zip"], setup["ply"].read_bytes(), name="Splat garden", hold=4,
                    checkpoint=setup["ckpt"].read_bytes())
    assert r.status_code == 202, r.text
    job = r.json()
    assert r.headers["location"] == f"/jobs/{job['id']}"
    assert job["request"] == {"kind": "import", "name": "Splat garden", "hold": 4, "views": 9}
    scene_id = job["scene_id"]
    assert client.get(f"/scenes/{scene_id}").status_code == 404  # no scene until the import is done
    assert run_job(setup["ctx"], job["id"]) == "succeeded"
    done = client.get(f"/jobs/{job['id']}").json()
    assert done["state"] == "succeeded" and done["step"] == 9 and done["total_steps"] == 9, done
    assert done["result"]["scene_id"] == scene_id and done["result"]["views"] == 9
    scene = client.get(f"/scenes/{scene_id}").json()
    assert scene["name"] == "Splat garden" and scene["views"] == 9 and scene["active_version"] == 1
    views = client.get(f"/scenes/{scene_id}/views").json()["items"]
    assert [v["name"] for v in views if v["split"] == "test"] == ["view_00", "view_04", "view_08"]
    assert all(v["has_render"] and v["has_depth"] and v["has_photo"] for v in views)
    # The render the service stores is the splats' render at the dataset's camera.
    png = client.get(f"/scenes/{scene_id}/views/5/render").content
    rgb, _, _ = render(setup["gaussians"], setup["poses"][5], setup["K"], 36, 48)
    assert (read_image(png) - rgb).abs().max() <= 0.5 / 255 + 1e-6
    assert not (data / "jobs" / job["id"]).exists()  # the upload is gone once imported
    assert list((data / "tmp").iterdir()) == []


@pytest.mark.parametrize("case", ["bad_ply", "not_a_dataset", "all_test"])
def test_a_bad_import_upload_is_a_clear_4xx_and_stores_nothing(setup, case, tmp_path):
    client, data = setup["client"], setup["data"]
    before = stored(data)
    archive, ply, form = setup["zip"], setup["ply"].read_bytes(), {}
    if case == "bad_ply":
        ply = b"ply\nformat ascii 1.0\nelement vertex 0\nend_header\n"
    elif case == "not_a_dataset":
        (tmp_path / "x").mkdir()
        (tmp_path / "x" / "notes.txt").write_text("hello")
        archive = zip_folder(tmp_path / "x")
    else:
        form = {"hold": 1}
    r = post_import(client, archive, ply, **form)
    assert r.status_code == 422, r.text
    message = r.json()["error"]["message"]
    want = {"bad_ply": "ply: ", "not_a_dataset": "not a scene", "all_test": "no 'train' views"}[case]
    assert want in message, message
    if case == "bad_ply":
        assert message.startswith("ply: ") and "binary_little_endian" in message
    assert str(data) not in message
    assert stored(data) == before


def test_the_import_job_is_listed_and_cancellable_while_queued(setup):
    client = setup["client"]
    r = post_import(client, setup["zip"], setup["ply"].read_bytes())
    assert r.status_code == 202, r.text
    job = r.json()
    assert job["request"]["name"] == "garden"  # the zip's file name
    assert [j["id"] for j in client.get("/jobs", params={"scene_id": job["scene_id"]}).json()["items"]] == [job["id"]]
    assert client.post(f"/jobs/{job['id']}/cancel").status_code == 200
    wait_until(lambda: client.get(f"/jobs/{job['id']}").json()["state"] == "cancelled", timeout=10,
               what="cancelled")
    assert run_job(setup["ctx"], job["id"]) == "skipped"
    assert client.get(f"/scenes/{job['scene_id']}").status_code == 404
