"""Images at /enhance: PNG/JPEG only; decompression bombs refused from the header (413) before
any large allocation; truncated/corrupt -> 422; size mismatches name both sizes; palette,
16-bit and alpha inputs follow the documented conversion (the same answer as the equivalent
8-bit RGB upload).
"""

from __future__ import annotations

import io
import resource
import time

import numpy as np
import pytest
from PIL import Image

from tests.reliability_helpers import (
    assert_error,
    assert_healthy,
    encode,
    npy,
    png_header_bomb,
    png_zlib_bomb,
    post_enhance,
    read_png,
)

# The shared server fixture `s` has the default pixel limit (4096 x 4096): bombs must be caught by the real guard.


@pytest.fixture(scope="module")
def base(s):
    view = s.view()
    img = Image.open(io.BytesIO(view["render"])).convert("RGB")
    ok = post_enhance(s.client, s.scene_id, render=view["render"], depth=view["depth"], camera=view["camera"])
    assert ok.status_code == 200, ok.text
    return {"view": view, "img": img, "answer": read_png(ok.content)}


def _send(s, base, *, render=None, depth=None, camera=None):
    view = base["view"]
    return post_enhance(s.client, s.scene_id, render=view["render"] if render is None else render,
                        depth=view["depth"] if depth is None else depth,
                        camera=view["camera"] if camera is None else camera)


def _max_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


@pytest.mark.parametrize("fmt", ["GIF", "BMP", "TIFF", "WEBP", "ICO"])
def test_only_png_and_jpeg(s, base, fmt):
    before = s.stored()
    other = encode(base["img"], fmt)
    message = assert_error(_send(s, base, render=other), 422, "invalid_input")
    assert "PNG" in message and "JPEG" in message
    assert s.stored() == before


def test_jpeg_is_accepted(s, base):
    r = _send(s, base, render=encode(base["img"], "JPEG", quality=95))
    assert r.status_code == 200, r.text
    assert read_png(r.content).shape == (48, 64, 3)


@pytest.mark.parametrize("kind", ["header_20000", "zlib_5000"])
def test_decompression_bombs_are_refused_before_allocating(s, base, kind):
    bomb = png_header_bomb(20000, 20000) if kind == "header_20000" else png_zlib_bomb(5000)
    if kind == "header_20000":
        assert len(bomb) < 80  # a few dozen bytes that claim 1.2 GB of pixels
    before = s.stored()
    rss = _max_rss_mb()
    start = time.perf_counter()
    r = _send(s, base, render=bomb)
    seconds = time.perf_counter() - start
    message = assert_error(r, 413, "image_too_large")
    assert "5000x5000" in message or "20000x20000" in message
    assert seconds < 2.0
    # Decoding would need >= 25 MB (uint8 gray) to 4.8 GB (float RGB); the peak stays put.
    assert _max_rss_mb() - rss < 20
    assert s.stored() == before
    assert_healthy(s.client)


def test_depth_bombs_are_refused_from_the_header(s, base):
    before = s.stored()
    header_only = npy(np.zeros((2, 2), np.float32)).replace(b"(2, 2)", b"(20000, 20000)")
    for depth in (header_only, png_zlib_bomb(5000)):
        rss = _max_rss_mb()
        r = _send(s, base, depth=depth)
        assert_error(r, (413, 422))
        assert _max_rss_mb() - rss < 20
    assert s.stored() == before


def test_truncated_or_corrupt_images_are_422(s, base):
    before = s.stored()
    png = base["view"]["render"]
    jpeg = encode(base["img"], "JPEG", quality=95)
    corrupt = bytearray(png)
    idat = png.index(b"IDAT")
    corrupt[idat + 20: idat + 60] = b"\xff" * 40
    cases = {"png_cut": png[: len(png) * 2 // 3], "png_header_only": png[:40], "png_corrupt": bytes(corrupt),
             "jpeg_cut": jpeg[: len(jpeg) // 2], "empty": b"", "text": b"hello"}
    for name, data in cases.items():
        message = assert_error(_send(s, base, render=data), 422)
        assert "render" in message, (name, message)
    assert s.stored() == before
    assert_healthy(s.client)


def test_size_mismatches_name_both_sizes(s, base):
    before = s.stored()
    small_depth = npy(np.ones((24, 32), np.float32))
    message = assert_error(_send(s, base, depth=small_depth), 422, "invalid_input")
    assert "48x64" in message and "24x32" in message
    camera = {**base["view"]["camera"], "w": 32, "h": 24}
    message = assert_error(_send(s, base, camera=camera), 422, "invalid_input")
    assert "32x24" in message and "64x48" in message
    assert s.stored() == before


def test_palette_image_equals_its_rgb_conversion(s, base):
    pal = base["img"].convert("P", palette=Image.Palette.ADAPTIVE, colors=32)
    as_palette = _send(s, base, render=encode(pal, "PNG"))
    as_rgb = _send(s, base, render=encode(pal.convert("RGB"), "PNG"))
    assert as_palette.status_code == as_rgb.status_code == 200
    assert np.array_equal(read_png(as_palette.content), read_png(as_rgb.content))


def test_alpha_is_composited_over_white(s, base):
    rgb = np.asarray(base["img"])
    alpha = np.where((np.indices(rgb.shape[:2]).sum(0) // 8) % 2 == 0, 255, 0).astype(np.uint8)
    rgba = Image.fromarray(np.dstack([rgb, alpha]), "RGBA")
    over_white = np.where(alpha[..., None] == 255, rgb, 255).astype(np.uint8)
    a = _send(s, base, render=encode(rgba, "PNG"))
    b = _send(s, base, render=encode(Image.fromarray(over_white, "RGB"), "PNG"))
    assert a.status_code == b.status_code == 200
    assert np.array_equal(read_png(a.content), read_png(b.content))
    # ... and not over black: fully transparent pixels differ from a black-composited upload.
    over_black = np.where(alpha[..., None] == 255, rgb, 0).astype(np.uint8)
    c = _send(s, base, render=encode(Image.fromarray(over_black, "RGB"), "PNG"))
    assert not np.array_equal(read_png(a.content), read_png(c.content))


def test_16bit_gray_equals_8bit_gray(s, base):
    gray8 = np.asarray(base["img"].convert("L"))
    gray16 = Image.fromarray(gray8.astype(np.uint16) * 257)  # v/255 == 257v/65535
    assert gray16.mode.startswith("I")
    a = _send(s, base, render=encode(gray16, "PNG"))
    b = _send(s, base, render=encode(Image.fromarray(gray8, "L"), "PNG"))
    assert a.status_code == b.status_code == 200, a.text
    diff = np.abs(read_png(a.content).astype(int) - read_png(b.content).astype(int))
    assert diff.max() <= 1
