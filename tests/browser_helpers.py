"""A real browser for the web page's tests and screenshots: Debian's ``chromium`` driven by
Playwright for Python (Playwright's own browser download is never used), and the embedded
server (API + worker) started on loopback with test settings."""

from __future__ import annotations

import contextlib
import io
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import httpx

from tests.service_helpers import FAST, ROOT, free_port, wait_until

CHROMIUM_ARGS = [
    "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
    "--disable-background-networking", "--disable-component-update", "--disable-sync",
    # Screenshots hold the page's sRGB pixels as they are (no display colour profile applied).
    "--force-color-profile=srgb",
]


def chromium_path() -> str | None:
    """``ROGUENERF_CHROMIUM`` or Debian's chromium on the PATH."""
    exe = os.environ.get("ROGUENERF_CHROMIUM") or shutil.which("chromium") or shutil.which("chromium-browser")
    return exe if exe and Path(exe).exists() else None


@contextlib.contextmanager
def browser():
    """A headless Chromium (Playwright sync API); skips the test where none is installed."""
    import pytest

    exe = chromium_path()
    if exe is None:
        pytest.skip("chromium is not installed (apt-get install -y chromium; ./dev test does it as root)")
    sync_api = pytest.importorskip("playwright.sync_api", reason="playwright is not installed (dev extra)")
    with sync_api.sync_playwright() as p:
        b = p.chromium.launch(executable_path=exe, args=CHROMIUM_ARGS, headless=True)
        try:
            yield b
        finally:
            b.close()


@contextlib.contextmanager
def embedded_server(data_dir: Path, *, log_path: Path, **settings):
    """``service.server.run`` (API + sibling worker) on a free loopback port; yields its URL."""
    port = free_port()
    env = {k: v for k, v in os.environ.items() if not k.startswith("ROGUENERF_")}
    env.update({f"ROGUENERF_{k.upper()}": str(v) for k, v in {**FAST, **settings}.items()})
    env["PYTHONPATH"] = str(ROOT)
    log = open(log_path, "wb")
    proc = subprocess.Popen(
        [sys.executable, "-c",
         f"from service.server import run; run(host='127.0.0.1', port={port}, data_dir={str(data_dir)!r})"],
        env=env, cwd=ROOT, stdout=log, stderr=subprocess.STDOUT)
    url = f"http://127.0.0.1:{port}"

    def up():
        try:
            return httpx.get(f"{url}/healthz", timeout=2).status_code == 200
        except httpx.HTTPError:
            return proc.poll() is not None

    try:
        wait_until(up, timeout=120, interval=0.1, what="embedded server")
        assert proc.poll() is None, log_path.read_text()
        yield url
    finally:
        if proc.poll() is None:
            proc.send_signal(2)  # SIGINT: API and worker stop cleanly
            try:
                proc.wait(60)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(10)
        log.close()


def path_zip(scene, *, seed: int, frames_per_segment: int = 2) -> tuple[bytes, int]:
    """A camera-path upload for ``POST /scenes/{id}/paths`` of a toy scene made with ``seed``: a
    nerfstudio camera_path.json through three of its views, rgb/ and depth/ of each frame.
    Returns (zip bytes, frame count)."""
    import math
    import zipfile

    from roguenerf.data.toy import make_toy_world, render_toy_view
    from roguenerf.geometry import opencv_to_opengl
    from roguenerf.imageio import encode_npy, encode_png
    from roguenerf.trajectory import smooth_path

    world = make_toy_world(seed)
    height, width = scene.frames[0].height, scene.frames[0].width
    poses = smooth_path(scene.poses([0, 1, 2]), frames_per_segment)
    K = scene.frames[0].K
    fov = math.degrees(2 * math.atan(height / 2 / float(K[1, 1])))
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        cams = []
        for t, pose in enumerate(poses):
            rgb, depth = render_toy_view(world, pose, K, height, width)
            zf.writestr(f"rgb/{t:04d}.png", encode_png((rgb * 0.9).clamp(0, 1)))
            zf.writestr(f"depth/{t:04d}.npy", encode_npy(depth[0].numpy()))
            cams.append({"camera_to_world": opencv_to_opengl(pose).flatten().tolist(), "fov": fov,
                         "aspect": width / height})
        zf.writestr("camera_path.json", json.dumps({"render_height": height, "render_width": width, "fps": 10,
                                                    "camera_path": cams}))
    return buf.getvalue(), len(poses)


def pixels_of_img(page, selector: str) -> tuple[int, int, bytes]:
    """``(width, height, RGB bytes)`` of an ``<img>``'s decoded image, read through a canvas."""
    data = page.evaluate(
        """(sel) => {
            const img = document.querySelector(sel);
            const c = document.createElement('canvas');
            c.width = img.naturalWidth; c.height = img.naturalHeight;
            const ctx = c.getContext('2d');
            ctx.drawImage(img, 0, 0);
            const d = ctx.getImageData(0, 0, c.width, c.height).data;
            const rgb = [];
            for (let i = 0; i < d.length; i += 4) rgb.push(d[i], d[i + 1], d[i + 2]);
            return [c.width, c.height, rgb];
        }""", selector)
    return data[0], data[1], bytes(data[2])


def wait_for(page, expression: str, *, timeout_s: float, arg=None):
    """``page.wait_for_function`` with seconds."""
    return page.wait_for_function(expression, arg=arg, timeout=timeout_s * 1000, polling=100)


def settle(seconds: float = 0.2) -> None:
    time.sleep(seconds)
