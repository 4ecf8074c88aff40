"""Auth and isolation: 401 + WWW-Authenticate on every route but /healthz, the key never in
logs or answers; hostile ids never become paths; client file names never reach the disk;
no CORS unless configured and never credentials.
"""

from __future__ import annotations

import logging

import httpx
import pytest

from service.settings import Settings
from tests.reliability_helpers import assert_error, assert_healthy, post_enhance
from tests.service_helpers import FAST, LiveServer

KEY = "rel-Key-7f3a9c1e5b-never-log-me"


SERVER = {"api_key": KEY}  # the shared server fixture's settings (tests/service/conftest.py)


@pytest.fixture()
def all_logs():
    """Every record of every logger (uvicorn's access log included) as text."""
    records: list[str] = []

    class Collect(logging.Handler):
        def emit(self, record):
            records.append(self.format(record) + repr(record.args))

    handler = Collect(level=logging.DEBUG)
    root = logging.getLogger()
    old_level = root.level
    root.addHandler(handler)
    root.setLevel(logging.DEBUG)
    access = logging.getLogger("uvicorn.access")
    access_state = (access.level, access.disabled)
    access.setLevel(logging.DEBUG)
    access.disabled = False
    try:
        yield records
    finally:
        root.removeHandler(handler)
        root.setLevel(old_level)
        access.setLevel(access_state[0])
        access.disabled = access_state[1]


def _routes(scene_id: str) -> list[tuple[str, str]]:
    job = "0" * 32
    return [("GET", "/readyz"), ("GET", "/docs"), ("GET", "/openapi.json"), ("GET", f"/scenes/{scene_id}"),
            ("DELETE", f"/scenes/{scene_id}"), ("POST", "/scenes"), ("POST", f"/scenes/{scene_id}/finetune"),
            ("POST", f"/scenes/{scene_id}/checkpoints"), ("POST", "/enhance"), ("GET", f"/jobs/{job}"),
            ("POST", f"/jobs/{job}/cancel"), ("GET", "/no/such/route"), ("GET", "/scenes"),
            ("GET", f"/scenes/{scene_id}/views"), ("GET", f"/scenes/{scene_id}/views/0/render"),
            ("GET", f"/scenes/{scene_id}/views/0/photo"), ("GET", f"/scenes/{scene_id}/views/0/depth"),
            ("POST", f"/scenes/{scene_id}/views/0/score"), ("POST", "/"), ("POST", "/ui/app.js")]


@pytest.mark.parametrize("auth", [None, "Bearer wrong-key", f"Basic {KEY}", f"Bearer {KEY}x", "Bearer"])
def test_every_route_needs_the_key(s, auth, all_logs):
    before = s.stored()
    headers = {} if auth is None else {"Authorization": auth}
    with httpx.Client(base_url=s.live.url, timeout=30) as anon:
        for method, path in _routes(s.scene_id):
            r = anon.request(method, path, headers=headers, json={"steps": 1} if method == "POST" else None)
            message = assert_error(r, 401, "unauthorized")
            assert r.headers["WWW-Authenticate"] == 'Bearer realm="roguenerf"', (method, path)
            assert ("missing" in message) == (auth is None)
            assert KEY not in r.text
        assert anon.get("/healthz").status_code == 200
    # The scene is still there: the unauthenticated DELETE did nothing.
    assert s.stored() == before
    assert s.client.get(f"/scenes/{s.scene_id}").status_code == 200
    assert not any(KEY in line for line in all_logs)


def test_the_key_is_never_logged(s, all_logs):
    view = s.view()
    ok = post_enhance(s.client, s.scene_id, render=view["render"], depth=view["depth"], camera=view["camera"])
    assert ok.status_code == 200, ok.text
    bad = post_enhance(s.client, s.scene_id, render=b"junk", depth=view["depth"], camera=view["camera"])
    assert_error(bad, 422)
    assert s.client.get("/readyz").status_code == 200
    assert_error(s.client.get("/nothing"), 404)
    assert len(all_logs) > 0  # the capture works: requests were logged ...
    assert not any(KEY in line for line in all_logs)  # ... and never with the key
    assert KEY not in repr(s.live.settings) and KEY not in str(s.live.settings.model_dump())


def test_the_embedded_worker_does_not_get_the_key(tmp_path):
    from service.server import EmbeddedWorker

    env = EmbeddedWorker(Settings(data_dir=tmp_path, api_key=KEY, **FAST))._env()
    assert "ROGUENERF_API_KEY" not in env and KEY not in env.values()
    assert env["ROGUENERF_DATA_DIR"] == str(tmp_path.resolve())


HOSTILE_IDS = [
    "..", "../victim", "..%2Fvictim", "%2e%2e%2fvictim", "%2E%2E", "..%2F..%2F..%2Fetc%2Fpasswd",
    "abc%00def", "%00", "0" * 31, "0" * 33, "G" * 32, "A" * 32, "%20" + "0" * 32, "0" * 32 + "%0A",
    "~", "%5C..%5Cvictim",
]


@pytest.mark.parametrize("hostile", HOSTILE_IDS)
def test_hostile_ids_are_404_or_422_and_touch_nothing(s, hostile):
    data = s.data_dir
    victim = data.parent / "victim"
    (victim / "scene").mkdir(parents=True, exist_ok=True)
    (victim / "scene" / "keep.txt").write_text("outside the data dir")
    before = s.stored()
    calls = [
        s.client.get(f"/scenes/{hostile}"),
        s.client.delete(f"/scenes/{hostile}"),
        s.client.post(f"/scenes/{hostile}/finetune", json={"steps": 1}),
        s.client.post(f"/scenes/{hostile}/checkpoints", files={"checkpoint": ("c", s.checkpoint)}),
        s.client.get(f"/jobs/{hostile}"),
        s.client.post(f"/jobs/{hostile}/cancel"),
    ]
    for r in calls:
        if r.request.method == "GET" and r.request.url.path == "/":
            # The client itself resolved "/scenes/.." to "/": the web page's static file, no data.
            assert r.status_code == 200 and r.headers["content-type"].startswith("text/html")
            assert s.scene_id not in r.text
            continue
        assert_error(r, (404, 405, 422))
    view = s.view()
    raw = hostile.replace("%2F", "/").replace("%2f", "/").replace("%00", "\x00").replace("%2e", ".")
    r = post_enhance(s.client, raw, render=view["render"], depth=view["depth"], camera=view["camera"])
    assert_error(r, (404, 422))
    assert (victim / "scene" / "keep.txt").read_text() == "outside the data dir"
    assert s.stored() == before
    assert_healthy(s.client)


def test_client_file_names_never_reach_the_disk(s):
    evil = "..%2F..%2Fevil-name"
    names = {"archive": f"../../{evil}.zip", "checkpoint": f"/tmp/{evil}.safetensors"}
    r = s.client.post("/scenes", files={"archive": (names["archive"], s.zip, "application/zip"),
                                         "checkpoint": (names["checkpoint"], s.checkpoint, "x")})
    assert r.status_code == 201, r.text
    sid = r.json()["id"]
    r = s.client.post(f"/scenes/{sid}/checkpoints", files={"checkpoint": (f"../{evil}.safetensors", s.checkpoint)})
    assert r.status_code == 201 and r.json()["active_version"] == 2, r.text
    view = s.view()
    r = post_enhance(s.client, sid, render=view["render"], depth=view["depth"], camera=view["camera"],
                     names=(f"../../{evil}.png", f"/etc/{evil}.npy"))
    assert r.status_code == 200, r.text
    roots = [s.data_dir.parent, s.data_dir.parent.parent]
    found = [p for root in roots for p in root.rglob("*evil-name*")]
    assert found == []
    # What is on disk instead: server-chosen names only.
    assert sorted(p.name for p in (s.data_dir / "scenes" / sid / "checkpoints").iterdir()) == [
        "v1.safetensors", "v2.safetensors"]
    assert s.client.delete(f"/scenes/{sid}").status_code == 204


def _cors(url: str, origin: str) -> tuple[httpx.Response, httpx.Response]:
    with httpx.Client(base_url=url, timeout=30) as c:
        pre = c.options("/enhance", headers={"Origin": origin, "Access-Control-Request-Method": "POST",
                                             "Access-Control-Request-Headers": "authorization"})
        simple = c.get("/healthz", headers={"Origin": origin, "Cookie": "session=1"})
    return pre, simple


def test_no_cors_unless_configured_and_never_credentials(tmp_path):
    with LiveServer(Settings(data_dir=tmp_path / "a", **FAST)) as live:
        pre, simple = _cors(live.url, "https://app.example")
        for r in (pre, simple):
            assert not [h for h in r.headers if h.lower().startswith("access-control-")], r.headers
    with LiveServer(Settings(data_dir=tmp_path / "b", cors_origins=["https://app.example"], **FAST)) as live:
        pre, simple = _cors(live.url, "https://app.example")
        assert pre.status_code == 200
        assert pre.headers["access-control-allow-origin"] == simple.headers["access-control-allow-origin"] \
            == "https://app.example"
        for r in (pre, simple):
            assert "access-control-allow-credentials" not in r.headers
        other, other_simple = _cors(live.url, "https://evil.example")
        assert "access-control-allow-origin" not in other.headers
        assert "access-control-allow-origin" not in other_simple.headers
    # Even a wildcard configuration never pairs "*" with credentials.
    with LiveServer(Settings(data_dir=tmp_path / "c", cors_origins=["*"], **FAST)) as live:
        pre, simple = _cors(live.url, "https://anyone.example")
        assert simple.headers["access-control-allow-origin"] == "*"
        for r in (pre, simple):
            assert r.headers.get("access-control-allow-credentials", "false") != "true"
