"""What a new user hit (issue 17), over a real socket: /docs offline, no server paths in errors,
listing scenes and jobs, unparseable JSON, cancelling twice, and the job's evaluating phase.

Real parts throughout: uvicorn on a loopback port, SQLite files, zips of real toy scenes, the
worker's task function training a real (tiny) model.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
import textwrap
import time
from html.parser import HTMLParser
from pathlib import Path

import numpy as np
import pytest

from service.settings import Settings
from tests.service_helpers import FAST, ROOT, LiveServer, register, zip_folder

# The shared toy fixture's scene (tests/conftest.py): small, quick to register.
TOY_SCENE = {"height": 24, "width": 32, "n_train": 4, "n_test": 1}


# ----------------------------------------------------------------------------- /docs offline


class _Links(HTMLParser):
    def __init__(self):
        super().__init__()
        self.urls: list[str] = []

    def handle_starttag(self, tag, attrs):
        for name, value in attrs:
            if name in ("src", "href") and value:
                self.urls.append(value)


def test_docs_page_and_every_asset_come_from_the_app(client):
    page = client.get("/docs")
    assert page.status_code == 200 and page.headers["content-type"].startswith("text/html")
    parser = _Links()
    parser.feed(page.text)
    # The page's script and style sheet and icon, all from this server (no CDN, no internet).
    assert len(parser.urls) >= 3, parser.urls
    assert not [u for u in parser.urls if re.match(r"^(https?:)?//", u)], parser.urls
    scripts = re.findall(r"url: '([^']+)'", page.text)
    assert scripts == ["/openapi.json"]
    kinds = {}
    for url in parser.urls + scripts:
        r = client.get(url)
        assert r.status_code == 200, (url, r.status_code)
        assert len(r.content) > 100, url
        kinds[url.rsplit(".", 1)[-1]] = r.headers["content-type"]
    assert kinds["js"].startswith(("text/javascript", "application/javascript"))
    assert kinds["css"].startswith("text/css")
    assert kinds["png"] == "image/png"
    assert "SwaggerUIBundle" in client.get(next(u for u in parser.urls if u.endswith(".js"))).text
    assert client.get("/openapi.json").json()["openapi"].startswith("3.1")
    assert client.get("/docs/oauth2-redirect").status_code == 200
    assert client.get("/redoc").status_code == 404  # no offline ReDoc assets exist: not offered


# ----------------------------------------------------------------------------- no server paths


def _broken(root: Path, tmp: Path, name: str, change) -> bytes:
    folder = tmp / name
    shutil.copytree(root, folder)
    change(folder)
    return zip_folder(folder)


def _edit_json(folder: Path, fn) -> None:
    data = json.loads((folder / "transforms.json").read_text())
    fn(data)
    (folder / "transforms.json").write_text(json.dumps(data))


def _drop_focal(data):
    data.pop("fl_x", None)
    for frame in data["frames"]:
        frame.pop("fl_x", None)


def _depth_shape(folder):
    for p in (folder / "depths").iterdir():
        np.save(p, np.zeros((3, 4, 5), np.float32))


def _image_size(folder):
    from PIL import Image

    for p in (folder / "images").iterdir():
        Image.new("RGB", (5, 5)).save(p)


BROKEN = {  # name: (change, what the message must say, relative to the upload)
    "no depths folder": (lambda f: shutil.rmtree(f / "depths"), "depths/train_000.npy: missing file"),
    "no photos": (lambda f: shutil.rmtree(f / "images"), "images/train_000.png: missing file"),
    "render not an image": (lambda f: [p.write_bytes(b"not a png") for p in (f / "renders").iterdir()],
                            "renders/train_000.png: not a PNG or JPEG"),
    "transforms not JSON": (lambda f: (f / "transforms.json").write_text("{nope"), "transforms.json: invalid JSON"),
    "no transforms.json": (lambda f: (f / "transforms.json").unlink(), "not a scene"),
    "missing intrinsics": (lambda f: _edit_json(f, _drop_focal), "transforms.json: frames[0]: missing key 'fl_x'"),
    "depth of the wrong shape": (_depth_shape, "depths/train_000.npy: depth shape"),
    "photo of the wrong size": (_image_size, "images/train_000.png: image is 5x5"),
    "NaN pose": (lambda f: _edit_json(f, lambda d: d["frames"][0]["transform_matrix"][0].__setitem__(0, float("nan"))),
                 "transforms.json: frames[0].transform_matrix"),
    "absolute file path": (lambda f: _edit_json(f, lambda d: d["frames"][0].__setitem__("file_path", "/etc/hostname")),
                           "leads outside the scene folder"),
    "path up and out": (lambda f: _edit_json(f, lambda d: d["frames"][1].__setitem__("render_path", "../../x.png")),
                        "'../../x.png' leads outside the scene folder"),
    "no train views": (lambda f: _edit_json(f, lambda d: [fr.__setitem__("split", "test") for fr in d["frames"]]),
                       "no 'train' views"),
}


def _assert_no_server_path(text: str, data_dir: Path) -> None:
    text = text.replace("'/etc/hostname'", "")  # the client's own (refused) input, echoed
    for fragment in (str(data_dir), str(data_dir.resolve()), "/tmp/", "data/tmp", "/scene/", "/etc/"):
        assert fragment not in text, (fragment, text)
    assert not re.search(r"(^|[\s'\"(])/[A-Za-z0-9_.-]+/", text), text  # no absolute path at all


@pytest.mark.parametrize("case", sorted(BROKEN))
def test_broken_scene_errors_name_upload_paths_only(client, server, toy, tmp_path, case):
    change, expected = BROKEN[case]
    r = register(client, _broken(toy["folder"], tmp_path, re.sub(r"\W", "_", case), change))
    assert r.status_code == 422, r.text
    body = r.json()
    assert body["error"]["code"] in ("invalid_scene", "invalid_archive"), body
    assert expected in body["error"]["message"], body
    _assert_no_server_path(r.text, server.settings.data_dir)
    # Nothing of the refused upload stays behind.
    assert list((server.settings.data_dir / "tmp").iterdir()) == []


def test_job_error_names_no_server_path(server, toy, tmp_path):
    """A scene broken after registration fails its job with a relative path (GET /jobs shows it)."""
    from jobs.layout import Layout
    from jobs.lifecycle import WorkerContext
    from jobs.store import JobStore
    from service.schemas import JobPublic
    from workers.dispatch import run_job

    settings = server.settings
    with server.client() as c:
        scene_id = register(c, toy["zip"], toy["checkpoint"]).json()["id"]
        layout = Layout(settings.data_dir)
        (layout.scene_files(scene_id) / "depths" / "train_001.npy").unlink()
        job = c.post(f"/scenes/{scene_id}/finetune", json={"steps": 1}).json()
        store = JobStore(settings.db_url)
        ctx = WorkerContext(settings=settings, store=store, layout=layout, enqueue=lambda _id: None)
        assert run_job(ctx, job["id"]) == "failed"
        r = c.get(f"/jobs/{job['id']}")
        assert r.json()["error"]["message"] == "depths/train_001.npy: missing file", r.text
        _assert_no_server_path(r.text, settings.data_dir)
        assert JobPublic.from_row(store.get_job(job["id"])).error.message == "depths/train_001.npy: missing file"


# ----------------------------------------------------------------------------- listing


def test_list_scenes_and_jobs_newest_first_paginated_filtered(tmp_path, toy):
    settings = Settings(data_dir=tmp_path / "data", **FAST)
    with LiveServer(settings) as live, live.client() as c:
        assert c.get("/scenes").json() == {"items": [], "next_cursor": None}
        ids = []
        for _ in range(5):
            ids.append(register(c, toy["zip"], toy["checkpoint"]).json()["id"])
            time.sleep(0.01)
        newest_first = ids[::-1]
        seen, cursor = [], None
        pages = 0
        while True:
            r = c.get("/scenes", params={"limit": 2, **({"cursor": cursor} if cursor else {})})
            assert r.status_code == 200, r.text
            page = r.json()
            assert len(page["items"]) <= 2
            seen += [s["id"] for s in page["items"]]
            pages += 1
            cursor = page["next_cursor"]
            if cursor is None:
                break
        assert seen == newest_first and pages == 3
        assert c.get("/scenes", params={"limit": 5}).json()["next_cursor"] is None
        full = c.get("/scenes").json()["items"][0]
        assert full == c.get(f"/scenes/{ids[-1]}").json()  # the same view as GET /scenes/{id}

        # Jobs: two on scene 0 (the first cancelled), one on scene 1; no worker, so they stay queued.
        j0 = c.post(f"/scenes/{ids[0]}/finetune", json={"steps": 2}).json()
        assert c.post(f"/jobs/{j0['id']}/cancel").json()["state"] == "cancelled"
        time.sleep(0.01)
        j1 = c.post(f"/scenes/{ids[1]}/finetune", json={"steps": 2}).json()
        time.sleep(0.01)
        j2 = c.post(f"/scenes/{ids[0]}/finetune", json={"minutes": 1}).json()
        assert c.get(f"/scenes/{ids[0]}").json()["active_job"] == j2["id"]
        listed = {s["id"]: s["active_job"] for s in c.get("/scenes").json()["items"]}
        assert listed[ids[0]] == j2["id"] and listed[ids[1]] == j1["id"] and listed[ids[2]] is None

        def job_ids(**params):
            r = c.get("/jobs", params=params)
            assert r.status_code == 200, r.text
            return [j["id"] for j in r.json()["items"]]

        assert job_ids() == [j2["id"], j1["id"], j0["id"]]
        assert job_ids(scene_id=ids[0]) == [j2["id"], j0["id"]]
        assert job_ids(state="queued") == [j2["id"], j1["id"]]
        assert job_ids(state=["cancelled", "running"]) == [j0["id"]]
        assert job_ids(scene_id=ids[0], state="queued") == [j2["id"]]
        assert job_ids(scene_id="f" * 32) == []
        first = c.get("/jobs", params={"limit": 2}).json()
        assert [j["id"] for j in first["items"]] == [j2["id"], j1["id"]] and first["next_cursor"]
        assert job_ids(limit=2, cursor=first["next_cursor"]) == [j0["id"]]
        assert c.get("/jobs").json()["items"][0] == c.get(f"/jobs/{j2['id']}").json()

        for bad in ({"limit": 0}, {"limit": 10_000}, {"state": "sleeping"}):
            r = c.get("/jobs", params=bad)
            assert r.status_code == 422 and r.json()["error"]["code"] == "validation_error", (bad, r.text)
        for cursor in ("garbage!", "bm90IGpzb24", "WzEsMl0"):
            r = c.get("/scenes", params={"cursor": cursor})
            assert r.status_code == 400 and r.json()["error"]["code"] == "invalid_cursor", (cursor, r.text)
        paths = c.get("/openapi.json").json()["paths"]
        assert "get" in paths["/scenes"] and "get" in paths["/jobs"]


# ----------------------------------------------------------------------------- request edge cases


def test_unparseable_json_is_400_with_the_position(client, server, toy):
    scene_id = register(client, toy["zip"], toy["checkpoint"]).json()["id"]
    r = client.post(f"/scenes/{scene_id}/finetune", content=b'{"steps": 12,,}',
                    headers={"content-type": "application/json"})
    assert r.status_code == 400, r.text
    error = r.json()["error"]
    assert error["code"] == "invalid_json" and error["position"] == 13, error
    assert "at character 13" in error["message"] and "field" not in error["message"]
    # Valid JSON of the wrong shape is still a field-level 422.
    r = client.post(f"/scenes/{scene_id}/finetune", json={"steps": "many"})
    assert r.status_code == 422 and r.json()["error"]["details"][0]["field"] == "steps"


def test_cancel_of_a_finished_job_is_409_every_time(client, server, toy):
    scene_id = register(client, toy["zip"], toy["checkpoint"]).json()["id"]
    job = client.post(f"/scenes/{scene_id}/finetune", json={"steps": 2}).json()
    first = client.post(f"/jobs/{job['id']}/cancel")
    assert first.status_code == 200 and first.json()["state"] == "cancelled"
    for _ in range(2):
        again = client.post(f"/jobs/{job['id']}/cancel")
        assert again.status_code == 409 and again.json()["error"]["code"] == "job_finished", again.text
        assert "cancelled" in again.json()["error"]["message"]


# ----------------------------------------------------------------------------- job phase


def test_job_reports_evaluating_instead_of_done_while_it_evaluates(tmp_path, toy):
    """After the last step the job measures its held-out views: GET /jobs shows phase
    "evaluating" without an ETA then, never "progress 1.0, eta 0" while still running."""
    from jobs.layout import Layout
    from jobs.lifecycle import WorkerContext
    from jobs.store import JobStore
    from service.schemas import JobPublic
    from workers.dispatch import run_job

    settings = Settings(data_dir=tmp_path / "data", **{**FAST, "finetune_evaluate": True})
    seen: list[dict] = []

    class Recording(JobStore):
        """The real store; after each write the row is read back as GET /jobs would show it."""

        def record_progress(self, job_id, lease, **kw):
            ok = super().record_progress(job_id, lease, **kw)
            seen.append(JobPublic.from_row(self.get_job(job_id)).model_dump())
            return ok

        def record_phase(self, job_id, lease, phase):
            ok = super().record_phase(job_id, lease, phase)
            seen.append(JobPublic.from_row(self.get_job(job_id)).model_dump())
            return ok

    with LiveServer(settings) as live, live.client() as c:
        scene_id = register(c, toy["zip"], toy["checkpoint"]).json()["id"]
        job = c.post(f"/scenes/{scene_id}/finetune", json={"steps": 3}).json()
        assert job["phase"] is None
        store = Recording(settings.db_url)
        ctx = WorkerContext(settings=settings, store=store, layout=Layout(settings.data_dir),
                            enqueue=lambda _id: None)
        assert run_job(ctx, job["id"]) == "succeeded"
        final = c.get(f"/jobs/{job['id']}").json()
    phases = [s["phase"] for s in seen]
    assert phases == ["evaluating", "training", "training", "training", "evaluating"], phases
    before, last_step, after = seen[0], seen[3], seen[4]
    assert before["state"] == "running" and before["eta_s"] is None and before["progress"] == 0
    assert last_step["progress"] == 1.0 and last_step["step"] == 3
    assert after["state"] == "running" and after["eta_s"] is None and after["progress"] == 1.0
    assert final["state"] == "succeeded" and final["phase"] is None and final["after"] is not None


# An older job table getting the phase column (schema v3) is tested on SQLite and PostgreSQL in
# tests/workers/test_worker_jobs.py (test_a_v2_database_gets_the_phase_column).


# ----------------------------------------------------------------------------- CPU kernels


def test_the_service_builds_the_cpu_kernels_at_start_not_at_the_first_enhancement(tmp_path):
    """The fused kernels compile on first use (seconds); the service starts that compile at
    start-up beside the serving, so the first enhancement does not wait for the compiler. A fresh
    process with an empty kernel cache: the kernels are built and loaded with no request made."""
    code = f"""
        import sys
        sys.path.insert(0, {str(ROOT)!r})
        from roguenerf import native
        from service.settings import Settings
        from tests.service_helpers import FAST, LiveServer, wait_until
        assert native.library.cache_info().currsize == 0
        with LiveServer(Settings(data_dir={str(tmp_path / "data")!r}, **FAST)) as live, live.client() as c:
            assert c.get("/healthz").status_code == 200
            wait_until(lambda: native.library.cache_info().currsize == 1, timeout=120, what="the kernel build")
        print("built", native.library() is not None, len(list(native.cache_dir().glob("kernels-*.so"))))
    """
    env = {**os.environ, "ROGUENERF_NATIVE_CACHE": str(tmp_path / "cache")}
    run = subprocess.run([sys.executable, "-c", textwrap.dedent(code)], cwd=ROOT, env=env, capture_output=True,
                         text=True, timeout=300)
    assert run.returncode == 0, run.stderr[-3000:]
    assert "built True 1" in run.stdout
