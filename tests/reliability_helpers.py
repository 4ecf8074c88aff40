"""Shared parts of the reliability tests (tests/service/test_reliability_*.py).

What every rejected request must satisfy: the JSON error format, nothing stored changed
(files under the data directory *and* the rows of the job/scene table), and the process
still answers /healthz. Plus builders for hostile inputs (image bombs, pickled .npy,
pickled checkpoints) and a module-scoped live server with one registered toy scene.
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import signal
import sqlite3
import struct
import subprocess
import sys
import zlib
from dataclasses import dataclass
from pathlib import Path

import httpx
import numpy as np

from tests.service_helpers import (
    ROOT,
    LiveServer,
    free_port,
    view_request,
    wait_until,
)

SQLITE_FILES = (".db", ".db-wal", ".db-shm", ".db-journal")


def assert_error(r: httpx.Response, status: int | tuple[int, ...], code: str | None = None) -> str:
    """The answer is ``{"error": {"code", "message"}}`` with this status; returns the message."""
    statuses = (status,) if isinstance(status, int) else status
    assert r.status_code in statuses, f"expected {statuses}, got {r.status_code}: {r.text[:500]}"
    body = r.json()
    assert set(body) == {"error"}, body
    assert isinstance(body["error"]["code"], str) and body["error"]["message"], body
    if code is not None:
        assert body["error"]["code"] == code, body
    return body["error"]["message"]


def file_digest(root: Path) -> dict[str, str]:
    """{relative path: sha256} of every file under ``root`` but the SQLite files."""
    out = {}
    for path in sorted(root.rglob("*")):
        if path.is_file() and not path.name.endswith(SQLITE_FILES):
            out[path.relative_to(root).as_posix()] = hashlib.sha256(path.read_bytes()).hexdigest()
    return out


def db_rows(data_dir: Path) -> dict[str, list]:
    """Every row of the scenes and jobs tables (read-only connection)."""
    conn = sqlite3.connect(f"file:{data_dir / 'roguenerf.db'}?mode=ro", uri=True, timeout=30)
    try:
        return {table: conn.execute(f"SELECT * FROM {table} ORDER BY id").fetchall()
                for table in ("scenes", "jobs")}
    finally:
        conn.close()


def stored(data_dir: Path) -> dict:
    """What a rejected request must leave unchanged: files and table rows."""
    return {"files": file_digest(data_dir), "db": db_rows(data_dir)}


def assert_healthy(client: httpx.Client) -> None:
    r = client.get("/healthz")
    assert r.status_code == 200 and r.json() == {"status": "ok"}, r.text


@dataclass
class Site:
    """A live server with one registered toy scene (the shared fixture ``s``, tests/service/conftest.py)."""

    live: LiveServer
    client: httpx.Client
    scene: object
    scene_id: str
    checkpoint: bytes
    zip: bytes

    @property
    def data_dir(self) -> Path:
        return self.live.settings.data_dir

    def stored(self) -> dict:
        return stored(self.data_dir)

    def view(self, index: int = 6) -> dict:
        return view_request(self.scene, index)


def post_enhance(client: httpx.Client, scene_id: str, *, render: bytes, depth: bytes, camera: dict | str,
                 names: tuple[str, str] = ("render.png", "depth.npy"), **extra) -> httpx.Response:
    files = {"render": (names[0], render, "image/png"), "depth": (names[1], depth, "application/octet-stream")}
    data = {"scene_id": scene_id, "camera": camera if isinstance(camera, str) else json.dumps(camera), **extra}
    return client.post("/enhance", files=files, data=data)


# ----------------------------------------------------------------------------- hostile inputs
def png_chunk(kind: bytes, payload: bytes) -> bytes:
    return struct.pack(">I", len(payload)) + kind + payload + struct.pack(">I", zlib.crc32(kind + payload))


def png_header_bomb(width: int = 20000, height: int = 20000) -> bytes:
    """A tiny PNG whose header declares ``width x height`` 8-bit RGB (a few dozen bytes)."""
    ihdr = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    return (b"\x89PNG\r\n\x1a\n" + png_chunk(b"IHDR", ihdr) + png_chunk(b"IDAT", zlib.compress(b"\x00", 9))
            + png_chunk(b"IEND", b""))


def png_zlib_bomb(side: int) -> bytes:
    """A *valid* ``side x side`` black grayscale PNG: all-zero rows compress ~1000:1."""
    raw = zlib.compressobj(9)
    row = b"\x00" * (side + 1)
    data = b"".join(raw.compress(row) for _ in range(side)) + raw.flush()
    ihdr = struct.pack(">IIBBBBB", side, side, 8, 0, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + png_chunk(b"IHDR", ihdr) + png_chunk(b"IDAT", data) + png_chunk(b"IEND", b"")


def encode(img, fmt: str, **kw) -> bytes:
    buf = io.BytesIO()
    img.save(buf, format=fmt, **kw)
    return buf.getvalue()


def npy(array: np.ndarray, *, allow_pickle: bool = False) -> bytes:
    buf = io.BytesIO()
    np.save(buf, array, allow_pickle=allow_pickle)
    return buf.getvalue()


class MarkerPayload:
    """Unpickling this runs ``open(marker, 'w')``: proof that something unpickled user data."""

    def __init__(self, marker: Path):
        self.marker = str(marker)

    def __reduce__(self):
        return (open, (self.marker, "w"))


def pickled_npy(marker: Path) -> bytes:
    """An object-dtype ``.npy`` whose loading with allow_pickle=True creates ``marker``."""
    arr = np.empty((1,), dtype=object)
    arr[0] = MarkerPayload(marker)
    return npy(arr, allow_pickle=True)


def pickled_checkpoint(marker: Path) -> bytes:
    """A torch-style pickle "checkpoint" whose unpickling creates ``marker``."""
    import pickle

    return pickle.dumps({"state_dict": MarkerPayload(marker)}, protocol=2)


def read_png(content: bytes) -> np.ndarray:
    """(H, W, 3) uint8 of a PNG answer."""
    from PIL import Image

    return np.asarray(Image.open(io.BytesIO(content)).convert("RGB"))


class ApiProcess:
    """The API as its own process (uvicorn --factory), so it can be killed with SIGKILL."""

    def __init__(self, settings, log_path: Path, port: int | None = None):
        self.port = port or free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        env = {k: v for k, v in os.environ.items() if not k.startswith("ROGUENERF_")}
        env.update(settings.env())
        env["PYTHONPATH"] = str(ROOT)
        self.log_path = log_path
        self._log = open(log_path, "ab")
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "uvicorn", "--factory", "service.app:create_app", "--host", "127.0.0.1",
             "--port", str(self.port), "--log-level", "warning"],
            env=env, cwd=ROOT, stdout=self._log, stderr=subprocess.STDOUT)

    def wait_ready(self, timeout: float = 90) -> None:
        def up():
            if self.proc.poll() is not None:
                raise AssertionError(f"API exited early:\n{self.log_path.read_text(errors='replace')}")
            try:
                return httpx.get(f"{self.url}/healthz", timeout=1).status_code == 200
            except httpx.HTTPError:
                return False

        wait_until(up, timeout=timeout, interval=0.2, what="API startup")

    def client(self) -> httpx.Client:
        return httpx.Client(base_url=self.url, timeout=120)

    def kill9(self) -> None:
        self.proc.send_signal(signal.SIGKILL)
        self.proc.wait(10)

    def close(self) -> None:
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(15)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(10)
        self._log.close()
