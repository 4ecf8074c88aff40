"""The HTTP API over a real socket (uvicorn in a thread), without a worker.

Covers the contract that does not need training: error format, auth, body limits (also
chunked), safe unzip, validation of /enhance inputs, capacity (503), the job table rules
(409 on a second job, idempotency, cancel of a queued job, delete refused while a job is
active) and CORS. Every rejected request is checked to leave nothing stored.
"""

from __future__ import annotations

import asyncio
import io
import json
import logging
import socket
import threading
import zipfile

import numpy as np
import pytest

from service.settings import Settings
from tests.service_helpers import (
    FAST,
    LiveServer,
    enhance,
    make_checkpoint,
    register,
    tree_digest,
    view_request,
)

MAX_BODY = 4 << 20
# The shared server fixture's settings (tests/service/conftest.py).
SERVER = {"max_body_bytes": MAX_BODY, "max_scene_files": 40, "max_upload_pixels": 64 * 64}


def stored(server) -> dict:
    """Files under scenes/ and tmp/ (what a rejected request must not change)."""
    data = server.settings.data_dir
    return {"scenes": tree_digest(data / "scenes"), "tmp": tree_digest(data / "tmp")}


def assert_error(r, status: int, code: str):
    assert r.status_code == status, r.text
    body = r.json()
    assert set(body) == {"error"}
    assert body["error"]["code"] == code, body
    assert body["error"]["message"]
    return body["error"]["message"]


def test_health_ready_and_error_format(client):
    assert client.get("/healthz").json() == {"status": "ok"}
    ready = client.get("/readyz")
    assert ready.status_code == 200
    assert ready.json()["checks"] == {"data_dir": "ok", "database": "ok", "queue": "ok"}
    assert "no route GET /nothing" in assert_error(client.get("/nothing"), 404, "not_found")
    assert_error(client.delete("/healthz"), 405, "method_not_allowed")
    # FastAPI's own validation errors use the same format and name the field.
    msg = assert_error(client.post(f"/scenes/{'0' * 32}/finetune", json={"steps": "many"}), 422,
                       "validation_error")
    assert "steps" in msg
    docs = client.get("/docs")
    assert docs.status_code == 200 and "swagger" in docs.text.lower()
    paths = client.get("/openapi.json").json()["paths"]
    assert {"/scenes", "/scenes/{scene_id}", "/enhance", "/scenes/{scene_id}/finetune", "/jobs/{job_id}",
            "/jobs/{job_id}/cancel", "/healthz", "/readyz"} <= set(paths)


def test_register_describe_and_unknown_ids(client, scene_id, toy, server):
    scene = client.get(f"/scenes/{scene_id}").json()
    assert scene["views"] == len(toy["scene"].frames) == 8
    assert (scene["train_views"], scene["test_views"]) == (6, 2)
    assert (scene["width"], scene["height"]) == (64, 48)
    assert scene["active_version"] == 1 and scene["checkpoint_versions"] == [1]
    # The zip's top folder "scene/" was unwrapped; the client's file names survive only inside.
    folder = server.settings.data_dir / "scenes" / scene_id / "scene"
    assert (folder / "transforms.json").is_file()
    assert (server.settings.data_dir / "scenes" / scene_id / "checkpoints" / "v1.safetensors").read_bytes() \
        == toy["checkpoint"]
    assert_error(client.get(f"/scenes/{'f' * 32}"), 404, "not_found")
    assert_error(client.get("/scenes/..%2F..%2Fetc"), 404, "not_found")
    assert_error(client.get(f"/jobs/{'f' * 32}"), 404, "not_found")


def _zip(members: list[tuple[zipfile.ZipInfo | str, bytes]]) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        for info, data in members:
            zf.writestr(info, data)
    return buf.getvalue()


def _symlink(name: str, target: str) -> zipfile.ZipInfo:
    info = zipfile.ZipInfo(name)
    info.external_attr = (0o120777 << 16)
    return info


@pytest.mark.parametrize("case, code, needle", [
    ("dotdot", "invalid_archive", "'..'"),
    ("absolute", "invalid_archive", "absolute"),
    ("symlink", "invalid_archive", "symbolic link"),
    ("backslash", "invalid_archive", "backslash"),
    ("too_many", "invalid_archive", "more than the allowed 40"),
    ("not_zip", "invalid_archive", "not a zip"),
    ("no_scene", "invalid_scene", ""),
    ("bad_checkpoint", "invalid_checkpoint", ""),
])
def test_rejected_uploads_store_nothing(client, server, toy, scene_id, case, code, needle):
    good = zipfile.ZipFile(io.BytesIO(toy["zip"]))
    members = [(i.filename, good.read(i)) for i in good.infolist()]
    checkpoint = None
    if case == "dotdot":
        archive = _zip(members + [("scene/../../evil.txt", b"x")])
    elif case == "absolute":
        archive = _zip(members + [("/tmp/evil.txt", b"x")])
    elif case == "symlink":
        archive = _zip(members + [(_symlink("scene/images/link.png", "/etc/passwd"), b"/etc/passwd")])
    elif case == "backslash":
        archive = _zip(members + [("scene\\..\\evil.txt", b"x")])
    elif case == "too_many":
        archive = _zip(members + [(f"scene/extra/{i}.txt", b"x") for i in range(41 - len(members))])
    elif case == "not_zip":
        archive = b"PK\x03\x04 this is not really a zip"
    elif case == "no_scene":
        archive = _zip([("scene/readme.txt", b"no transforms here")])
    else:
        archive, checkpoint = toy["zip"], b"\x00" * 64 + b"not a safetensors file"
    before = stored(server)
    message = assert_error(register(client, archive, checkpoint), 422, code)
    assert needle in message
    assert stored(server) == before


def test_uncompressed_size_limit(tmp_path, toy):
    settings = Settings(data_dir=tmp_path, max_scene_bytes=4096, **FAST)
    bomb = _zip([("scene/transforms.json", b"{}"), ("scene/big.bin", b"\x00" * 100_000)])
    with LiveServer(settings) as live, live.client() as c:
        message = assert_error(register(c, bomb), 422, "invalid_archive")
        assert "more than the allowed 4096" in message
        assert tree_digest(tmp_path / "scenes") == {} and tree_digest(tmp_path / "tmp") == {}


def _raw_chunked_post(port: int, path: str, total: int) -> tuple[int, dict]:
    """POST a chunked body (no Content-Length) over a raw socket; returns (status, json).

    A reader thread collects the answer while the body is still being sent: the server
    answers 413 mid-body and closes, and a reset would discard an answer read only later.
    """
    boundary = "b0undary"
    head = (f"POST {path} HTTP/1.1\r\nHost: 127.0.0.1\r\nTransfer-Encoding: chunked\r\n"
            f"Content-Type: multipart/form-data; boundary={boundary}\r\nConnection: close\r\n\r\n")
    received = bytearray()

    def read(sock):
        try:
            while data := sock.recv(65536):
                received.extend(data)
        except OSError:
            pass

    with socket.create_connection(("127.0.0.1", port), timeout=30) as s:
        reader = threading.Thread(target=read, args=(s,))
        reader.start()
        first = (f"--{boundary}\r\nContent-Disposition: form-data; name=\"archive\"; filename=\"a.zip\"\r\n"
                 "Content-Type: application/zip\r\n\r\n").encode()
        try:
            s.sendall(head.encode())
            s.sendall(f"{len(first):x}\r\n".encode() + first + b"\r\n")
            chunk = b"z" * 65536
            sent = 0
            while sent < total and not received:
                s.sendall(f"{len(chunk):x}\r\n".encode() + chunk + b"\r\n")
                sent += len(chunk)
            if not received:
                s.sendall(b"0\r\n\r\n")
        except OSError:
            pass  # the server answered and closed before the whole body was sent
        reader.join(30)
    header, _, body = bytes(received).partition(b"\r\n\r\n")
    status = int(header.split()[1])
    return status, json.loads(body.split(b"\r\n")[1] if b"chunked" in header.lower() else body)


def test_body_limit_declared_and_chunked(client, server):
    before = stored(server)
    r = client.post("/scenes", files={"archive": ("a.zip", b"\x00" * (MAX_BODY + 1))})
    assert "larger than the allowed" in assert_error(r, 413, "payload_too_large")
    # Chunked transfer: no Content-Length, so only counting the received bytes can stop it.
    status, body = _raw_chunked_post(server.port, "/scenes", 2 * MAX_BODY)
    assert status == 413 and body["error"]["code"] == "payload_too_large", body
    assert stored(server) == before


def _png(height: int, width: int) -> bytes:
    from PIL import Image

    buf = io.BytesIO()
    Image.new("RGB", (width, height), (10, 20, 30)).save(buf, format="PNG")
    return buf.getvalue()


def test_enhance_input_validation(client, scene_id, toy, server):
    view = view_request(toy["scene"], 6)
    before = stored(server)
    assert_error(enhance(client, "f" * 32, view), 404, "not_found")
    r = client.post("/enhance", data={"scene_id": scene_id, "camera": "{not json"},
                    files={"render": ("r.png", view["render"]), "depth": ("d.npy", view["depth"])})
    assert "not valid JSON" in assert_error(r, 422, "validation_error")
    missing = {**view, "camera": {k: v for k, v in view["camera"].items() if k != "convention"}}
    assert "convention" in assert_error(enhance(client, scene_id, missing), 422, "validation_error")
    two = {**view, "camera": {**view["camera"], "transform_matrix": view["camera"]["transform_matrix"][:2]}}
    assert "4x4 or 3x4" in assert_error(enhance(client, scene_id, two), 422, "validation_error")
    skew = np.array(view["camera"]["transform_matrix"])
    skew[:3, 0] *= 3.0
    bad_pose = {**view, "camera": {**view["camera"], "transform_matrix": skew.tolist()}}
    assert "camera.transform_matrix" in assert_error(enhance(client, scene_id, bad_pose), 422, "invalid_input")
    neg_f = {**view, "camera": {**view["camera"], "fl_x": -5.0}}
    assert_error(enhance(client, scene_id, neg_f), 422, "invalid_input")
    buf = io.BytesIO()
    np.save(buf, np.ones((10, 10), np.float32))
    small_depth = {**view, "depth": buf.getvalue()}
    assert "48x64" in assert_error(enhance(client, scene_id, small_depth), 422, "invalid_input")
    not_png = {**view, "render": b"GIF89a not an image"}
    assert_error(enhance(client, scene_id, not_png), 422, "invalid_input")
    huge = {**view, "render": _png(65, 64)}  # one row over max_upload_pixels = 64 * 64
    assert_error(enhance(client, scene_id, huge), 413, "image_too_large")
    wrong_size = {**view, "camera": {**view["camera"], "w": 100, "h": 48}}
    assert_error(enhance(client, scene_id, wrong_size), 422, "invalid_input")
    assert_error(enhance(client, scene_id, view, depth_scale="0"), 422, "validation_error")
    assert stored(server) == before


def test_enhance_ok_and_over_capacity(client, scene_id, toy, server):
    from PIL import Image

    view = view_request(toy["scene"], 6)
    r = enhance(client, scene_id, view)
    assert r.status_code == 200, r.text
    assert r.headers["content-type"] == "image/png"
    assert Image.open(io.BytesIO(r.content)).size == (64, 48)
    assert float(r.headers["X-Enhance-Seconds"]) > 0
    # The checkpoint's 2 neighbours, plus a third where it is a near view (the library's rule).
    used = r.headers["X-Neighbours"].split(",")
    assert len(used) in (2, 3)
    scene = toy["scene"]
    import torch

    from roguenerf.geometry import rotation_angle
    from roguenerf.inference import NEAR_DEGREES

    pose = scene.frames[6].world_from_cam.to(torch.float64)
    angles = [float(rotation_angle(pose[:3, :3], scene.frames[scene.index(n)].world_from_cam.to(torch.float64)[:3, :3]))
              for n in used]
    assert all(a <= NEAR_DEGREES for a in angles[2:])
    assert r.headers["X-Checkpoint-Version"] == "1"
    # Hold the only slot from the server's own event loop; the next call is refused at once.
    services = server.app.state.services
    loop = services.extras["loop"]
    asyncio.run_coroutine_threadsafe(services.enhance_slots.acquire(), loop).result(5)
    try:
        busy = enhance(client, scene_id, view)
        assert_error(busy, 503, "over_capacity")
        assert busy.headers["Retry-After"] == "1"
    finally:
        loop.call_soon_threadsafe(services.enhance_slots.release)
    assert enhance(client, scene_id, view).status_code == 200


@pytest.mark.parametrize("convention", ["opengl", "opencv"])
def test_enhance_takes_3x4_poses_and_checks_their_rotation(client, scene_id, toy, convention):
    """A 3x4 camera-to-world (as most tools print poses) gives the 4x4 answer, byte for byte;
    its rotation is checked the same way (a reflection or a scaled matrix is a 422)."""
    view = view_request(toy["scene"], 6)
    pose = np.array(view["camera"]["transform_matrix"])
    if convention == "opencv":
        pose = pose * np.array([1.0, -1.0, -1.0, 1.0])  # OpenGL -> OpenCV axes
    four = {**view, "camera": {**view["camera"], "convention": convention, "transform_matrix": pose.tolist()}}
    three = {**four, "camera": {**four["camera"], "transform_matrix": pose[:3].tolist()}}
    r4, r3 = enhance(client, scene_id, four), enhance(client, scene_id, three)
    assert r4.status_code == 200 and r3.status_code == 200, (r4.text, r3.text)
    assert r3.content == r4.content and r3.headers["X-Neighbours"] == r4.headers["X-Neighbours"]
    reflected = pose[:3].copy()
    reflected[:, 0] *= -1
    bad = {**four, "camera": {**four["camera"], "transform_matrix": reflected.tolist()}}
    message = assert_error(enhance(client, scene_id, bad), 422, "invalid_input")
    assert "camera.transform_matrix" in message and "det" in message
    scaled = pose[:3].copy()
    scaled[:, :3] *= 1.1
    bad = {**four, "camera": {**four["camera"], "transform_matrix": scaled.tolist()}}
    assert "orthonormal" in assert_error(enhance(client, scene_id, bad), 422, "invalid_input")


@pytest.mark.parametrize("mistake, code, needle, fix", [
    ("convention", "wrong_convention", "with the y and z axes flipped", '"convention": "opengl"'),
    ("scale", "wrong_scale", "another unit: with its position scaled by 0.1", "in the scene's units"),
    ("world", "wrong_world", "lies", "GET /scenes/{id}/views"),
])
def test_enhance_refuses_a_camera_that_does_not_fit_the_scene(client, scene_id, toy, server, mistake, code,
                                                              needle, fix):
    """Issue 49: an OpenGL pose sent as "opencv", a pose translated x10 or one in another world
    gave 200 and an image worse than the render; now a 422 naming the likely cause and the fix
    (the library's check_camera, the test enhance-path runs), and force=true goes on."""
    view = view_request(toy["scene"], 6)
    pose = np.array(view["camera"]["transform_matrix"])
    camera = dict(view["camera"])
    if mistake == "convention":
        camera["convention"] = "opencv"
    elif mistake == "scale":
        pose[:3, 3] *= 10
    else:
        pose[:3, 3] += [40.0, -25.0, 30.0]
    wrong = {**view, "camera": {**camera, "transform_matrix": pose.tolist()}}
    before = stored(server)
    message = assert_error(enhance(client, scene_id, wrong), 422, code)
    assert message.startswith("the camera does not fit the scene: the camera "), message
    assert needle in message and fix in message, message
    assert message.endswith("; to enhance it anyway: force=true (a form field of this request)"), message
    assert "--force" not in message, message
    assert stored(server) == before
    forced = enhance(client, scene_id, wrong, force="true")
    assert forced.status_code == 200, forced.text
    assert forced.headers["X-Enhance-Note"].startswith("forced: the camera does not fit the scene")
    right = enhance(client, scene_id, view)
    assert right.status_code == 200 and "X-Enhance-Note" not in right.headers


def _png_of(array: np.ndarray) -> bytes:
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(array).save(buf, format="PNG")
    return buf.getvalue()


def test_enhance_integer_png_renders_follow_the_documented_rule(client, scene_id, toy):
    """8-bit, 16-bit and 1-bit (bool) PNG renders are decoded by read_image's rule (/ 255,
    / 65535, 0/1): the same image in any of these encodings gives the same answer, and the
    answer is the library's for the float render (never the all-white image of a clamp)."""
    import torch
    from PIL import Image

    from roguenerf import load_checkpoint, load_scene
    from roguenerf.imageio import read_image
    from roguenerf.inference import SceneEnhancer

    scene = toy["scene"]
    view = view_request(scene, 6)

    def answer(render: bytes) -> bytes:
        r = enhance(client, scene_id, {**view, "render": render})
        assert r.status_code == 200, r.text
        return r.content

    rgb8 = np.asarray(Image.open(io.BytesIO(view["render"])).convert("RGB"))
    gray8 = np.asarray(Image.fromarray(rgb8).convert("L"))
    gray16 = gray8.astype(np.uint16) * 257  # v / 255 == 257 v / 65535
    assert answer(_png_of(gray16)) == answer(_png_of(gray8))
    mask = gray8 > 100
    assert answer(_bool_png(mask)) == answer(_png_of(np.where(mask, 255, 0).astype(np.uint8)))

    got = read_image(answer(view["render"]))
    model, _ = load_checkpoint_from_bytes(toy["checkpoint"], load_checkpoint)
    frame = scene.frames[6]
    with torch.no_grad():
        want = SceneEnhancer(load_scene(scene.root), model).enhance(
            read_image(view["render"]), scene.depth(6), frame.K, frame.world_from_cam).image
    assert float(got.mean()) < 0.9
    assert float((got - want).abs().max()) <= 1.5 / 255


def _bool_png(mask: np.ndarray) -> bytes:
    """A 1-bit PNG (Pillow mode "1") of a bool mask."""
    from PIL import Image

    img = Image.new("1", (mask.shape[1], mask.shape[0]))
    img.putdata([int(v) for v in mask.reshape(-1)])
    buf = io.BytesIO()
    img.save(buf, format="PNG")
    return buf.getvalue()


def load_checkpoint_from_bytes(data: bytes, load_checkpoint):
    import tempfile
    from pathlib import Path

    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "model.safetensors"
        path.write_bytes(data)
        return load_checkpoint(path)


def test_job_rules_without_worker(client, scene_id, server):
    # No worker runs here, so a job stays queued: the rules are checked deterministically.
    r = client.post(f"/scenes/{scene_id}/finetune", json={"steps": 3}, headers={"Idempotency-Key": "k-1"})
    assert r.status_code == 202, r.text
    job = r.json()
    assert job["state"] == "queued" and job["progress"] == 0 and job["request"] == {"steps": 3}
    assert r.headers["Location"] == f"/jobs/{job['id']}"
    assert client.get(f"/scenes/{scene_id}").json()["active_job"] == job["id"]
    again = client.post(f"/scenes/{scene_id}/finetune", json={"steps": 3}, headers={"Idempotency-Key": "k-1"})
    assert again.status_code == 202 and again.json()["id"] == job["id"]
    other = client.post(f"/scenes/{scene_id}/finetune", json={"steps": 4}, headers={"Idempotency-Key": "k-1"})
    assert_error(other, 409, "idempotency_conflict")
    assert_error(client.post(f"/scenes/{scene_id}/finetune", json={"minutes": 1}), 409, "job_active")
    assert_error(client.post(f"/scenes/{scene_id}/finetune", json={"steps": 10**9}), 422, "validation_error")
    assert_error(client.delete(f"/scenes/{scene_id}"), 409, "scene_busy")
    assert (server.settings.data_dir / "scenes" / scene_id).is_dir()
    cancelled = client.post(f"/jobs/{job['id']}/cancel")
    assert cancelled.status_code == 200
    assert cancelled.json()["state"] == "cancelled" and cancelled.json()["error"]["code"] == "cancelled"
    # The scene is free again; the same key still names the cancelled job.
    assert client.post(f"/scenes/{scene_id}/finetune", json={"steps": 3},
                       headers={"Idempotency-Key": "k-1"}).json()["id"] == job["id"]
    second = client.post(f"/scenes/{scene_id}/finetune", json={"minutes": 0.5})
    assert second.status_code == 202 and second.json()["id"] != job["id"]
    client.post(f"/jobs/{second.json()['id']}/cancel")


def test_delete_scene(client, toy, server):
    r = register(client, toy["zip"], toy["checkpoint"])
    sid = r.json()["id"]
    assert (server.settings.data_dir / "scenes" / sid).is_dir()
    assert client.delete(f"/scenes/{sid}").status_code == 204
    assert_error(client.get(f"/scenes/{sid}"), 404, "not_found")
    assert_error(client.delete(f"/scenes/{sid}"), 404, "not_found")
    assert not (server.settings.data_dir / "scenes" / sid).exists()
    assert_error(enhance(client, sid, view_request(toy["scene"], 6)), 404, "not_found")


def test_api_key(tmp_path, caplog):
    key = "s3cret-key-value"
    settings = Settings(data_dir=tmp_path, api_key=key, **FAST)
    assert key not in repr(settings)
    with caplog.at_level(logging.DEBUG), LiveServer(settings) as live, live.client() as c:
        assert c.get("/healthz").status_code == 200
        for path in ("/readyz", "/docs", "/openapi.json", f"/jobs/{'0' * 32}", "/nothing"):
            r = c.get(path)
            assert_error(r, 401, "unauthorized")
            assert r.headers["WWW-Authenticate"].startswith("Bearer")
        assert_error(c.get("/readyz", headers={"Authorization": "Bearer wrong"}), 401, "unauthorized")
        assert_error(c.get("/readyz", headers={"Authorization": f"Basic {key}"}), 401, "unauthorized")
        ok = {"Authorization": f"Bearer {key}"}
        assert c.get("/readyz", headers=ok).status_code == 200
        assert_error(c.get(f"/jobs/{'0' * 32}", headers=ok), 404, "not_found")
    assert key not in caplog.text


def test_cors_only_when_configured(tmp_path, client):
    preflight = {"Origin": "https://app.example", "Access-Control-Request-Method": "POST"}
    plain = client.options("/enhance", headers=preflight)
    assert "access-control-allow-origin" not in plain.headers
    settings = Settings(data_dir=tmp_path, cors_origins=["https://app.example"], **FAST)
    with LiveServer(settings) as live, live.client() as c:
        r = c.options("/enhance", headers=preflight)
        assert r.status_code == 200
        assert r.headers["access-control-allow-origin"] == "https://app.example"
        assert "access-control-allow-credentials" not in r.headers
        other = c.options("/enhance", headers={**preflight, "Origin": "https://evil.example"})
        assert "access-control-allow-origin" not in other.headers


def test_scene_names_at_upload(client, toy, server):
    """A scene's name: the ``name`` field, else the zip's file name without ``.zip``; shown by
    every scene answer; a bad name is refused before anything is stored."""
    files = {"archive": ("Garden scan 2.zip", toy["zip"], "application/zip")}
    by_file = client.post("/scenes", files=files)
    assert by_file.status_code == 201, by_file.text
    assert by_file.json()["name"] == "Garden scan 2"
    given = client.post("/scenes", files=files, data={"name": "  Lego   bulldozer\tv2 "})
    assert given.status_code == 201 and given.json()["name"] == "Lego bulldozer v2"
    windows = client.post("/scenes", files={"archive": ("C:\\Users\\me\\kitchen.ZIP", toy["zip"], "application/zip")})
    assert windows.json()["name"] == "kitchen"
    unicode = client.post("/scenes", files=files, data={"name": "Cafe\u0301 \u00e9t\u00e9"})
    assert unicode.json()["name"] == "Caf\u00e9 \u00e9t\u00e9"  # NFC
    ids = {r.json()["id"]: r.json()["name"] for r in (by_file, given, windows, unicode)}
    listed = {s["id"]: s["name"] for s in client.get("/scenes", params={"limit": 200}).json()["items"]}
    assert {k: listed[k] for k in ids} == ids
    assert all(client.get(f"/scenes/{k}").json()["name"] == v for k, v in ids.items())

    before = stored(server)
    assert "at most 120" in assert_error(client.post("/scenes", files=files, data={"name": "x" * 121}),
                                         422, "validation_error")
    assert "control" in assert_error(client.post("/scenes", files=files, data={"name": "a\nb"}),
                                     422, "validation_error")
    assert "empty" in assert_error(client.post("/scenes", files=files, data={"name": "   "}),
                                   422, "validation_error")
    assert stored(server) == before

    # Renamed later: the same rules; the id, views and checkpoints stay.
    sid = by_file.json()["id"]
    renamed = client.patch(f"/scenes/{sid}", json={"name": " Garden,  final "})
    assert renamed.status_code == 200 and renamed.json()["name"] == "Garden, final"
    assert {k: v for k, v in renamed.json().items() if k != "name"} == \
        {k: v for k, v in by_file.json().items() if k != "name"}
    assert client.get(f"/scenes/{sid}").json()["name"] == "Garden, final"
    assert_error(client.patch(f"/scenes/{sid}", json={"name": ""}), 422, "validation_error")
    assert_error(client.patch(f"/scenes/{sid}", json={"name": "x" * 121}), 422, "validation_error")
    assert_error(client.patch(f"/scenes/{sid}", json={"name": "ok", "views": 3}), 422, "validation_error")
    assert_error(client.patch(f"/scenes/{sid}", json={}), 422, "validation_error")
    assert_error(client.patch(f"/scenes/{'0' * 32}", json={"name": "x"}), 404, "not_found")
    assert client.get(f"/scenes/{sid}").json()["name"] == "Garden, final"
    for sid in ids:
        assert client.delete(f"/scenes/{sid}").status_code == 204


def test_checkpoint_download(client, toy, server):
    r = register(client, toy["zip"], toy["checkpoint"])
    sid = r.json()["id"]
    one = client.get(f"/scenes/{sid}/checkpoints/1")
    assert one.status_code == 200 and one.content == toy["checkpoint"]
    assert one.headers["content-type"] == "application/octet-stream"
    assert one.headers["content-disposition"] == 'attachment; filename="scene-v1.safetensors"'
    assert client.get(f"/scenes/{sid}/checkpoints/active").content == toy["checkpoint"]
    # An uploaded replacement becomes v2 and the active one; v1 stays downloadable.
    other = make_checkpoint(server.settings.data_dir.parent / "other.safetensors", seed=5).read_bytes()
    assert client.post(f"/scenes/{sid}/checkpoints",
                       files={"checkpoint": ("o.safetensors", other, "application/octet-stream")}).status_code == 201
    assert client.get(f"/scenes/{sid}/checkpoints/active").content == other
    assert client.get(f"/scenes/{sid}/checkpoints/2").content == other
    assert client.get(f"/scenes/{sid}/checkpoints/1").content == toy["checkpoint"]
    assert "stored: [1, 2]" in assert_error(client.get(f"/scenes/{sid}/checkpoints/3"), 404, "not_found")
    assert_error(client.get(f"/scenes/{sid}/checkpoints/-1"), 422, "validation_error")
    assert_error(client.get(f"/scenes/{sid}/checkpoints/..%2Fv1"), 404, "not_found")
    assert_error(client.get(f"/scenes/{'0' * 32}/checkpoints/1"), 404, "not_found")
    # A scene on the server's default checkpoint has nothing of its own to download.
    bare = register(client, toy["zip"]).json()["id"]
    assert "default checkpoint" in assert_error(client.get(f"/scenes/{bare}/checkpoints/active"), 404, "not_found")
    for s in (sid, bare):
        assert client.delete(f"/scenes/{s}").status_code == 204
    assert_error(client.get(f"/scenes/{sid}/checkpoints/1"), 404, "not_found")
