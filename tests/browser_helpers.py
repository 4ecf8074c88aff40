"""A real browser for the web page's tests and screenshots: Debian's ``chromium`` driven by
Playwright for Python (Playwright's own browser download is never used); the embedded server
(API + worker) they drive is ``service_helpers.EmbeddedServer``."""

from __future__ import annotations

import contextlib
import os
import shutil
import time
from pathlib import Path

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
