"""Strict image/depth decoding: known conversions and every refusal."""

from __future__ import annotations

import io
import os
import pickle
import struct
import time
import tracemalloc
import zlib

import numpy as np
import pytest
import torch
from PIL import Image

from roguenerf.errors import InputError
from roguenerf.imageio import ImageTooLargeError, read_depth, read_image, read_image_size, write_png


def _chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)


def _png_bomb(width: int, height: int) -> bytes:
    """A tiny PNG whose header declares width x height 8-bit gray pixels."""
    ihdr = struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)
    idat = zlib.compress(b"\x00", 9)
    return b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", ihdr) + _chunk(b"IDAT", idat) + _chunk(b"IEND", b"")


def _encode(img: Image.Image, fmt: str = "PNG", **kw) -> bytes:
    buf = io.BytesIO()
    img.save(buf, format=fmt, **kw)
    return buf.getvalue()


# -- bombs, corrupt files, other formats --------------------------------------------------


def test_png_bomb_20000x20000_rejected_before_decoding():
    bomb = _png_bomb(20000, 20000)
    assert len(bomb) == 66
    tracemalloc.start()
    start = time.perf_counter()
    with pytest.raises(ImageTooLargeError, match="20000x20000") as info:
        read_image(bomb)
    elapsed = time.perf_counter() - start
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    assert isinstance(info.value, InputError)
    assert elapsed < 2.0
    assert peak < 5 * 2**20  # decoding would need 400 MB


def test_bomb_below_pillow_guard_caught_by_max_pixels():
    # 5000x5000 passes Pillow's own guard; our header check must stop it.
    with pytest.raises(ImageTooLargeError, match="5000x5000 = 25000000 pixels, more than the allowed 1000000"):
        read_image(_png_bomb(5000, 5000), max_pixels=1_000_000)
    with pytest.raises(ImageTooLargeError):
        read_image_size(_png_bomb(5000, 5000), max_pixels=1_000_000)


def test_truncated_png_is_input_error():
    data = _encode(Image.fromarray(np.random.default_rng(0).integers(0, 255, (64, 64, 3), dtype=np.uint8)))
    with pytest.raises(InputError, match="truncated or corrupt") as info:
        read_image(data[: len(data) // 2])
    assert not isinstance(info.value, ImageTooLargeError)


def test_garbage_bytes_are_input_error():
    with pytest.raises(InputError, match="not a PNG or JPEG"):
        read_image(b"hello, this is not an image at all")


@pytest.mark.parametrize("fmt", ["GIF", "BMP", "TIFF"])
def test_other_formats_refused(fmt):
    data = _encode(Image.new("RGB", (8, 8), (10, 20, 30)), fmt)
    with pytest.raises(InputError, match="not a PNG or JPEG"):
        read_image(data)


def test_missing_file_named(tmp_path):
    with pytest.raises(InputError, match="nope.png: file not found"):
        read_image(tmp_path / "nope.png")


# -- conversions with known values ----------------------------------------------------------


def test_rgb8_values_and_layout(tmp_path):
    array = np.zeros((2, 3, 3), dtype=np.uint8)
    array[0, 1] = (255, 0, 51)
    path = tmp_path / "a.png"
    path.write_bytes(_encode(Image.fromarray(array)))
    image = read_image(path)
    assert image.shape == (3, 2, 3) and image.dtype == torch.float32
    assert image[:, 0, 1].tolist() == pytest.approx([1.0, 0.0, 0.2])
    assert image.sum() == pytest.approx(1.2)


def test_palette_and_transparent_palette():
    img = Image.new("P", (2, 1))
    img.putpalette([255, 0, 0, 0, 0, 255] + [0] * 762)
    img.putpixel((0, 0), 0)
    img.putpixel((1, 0), 1)
    out = read_image(_encode(img))
    assert out[:, 0, 0].tolist() == [1.0, 0.0, 0.0]
    assert out[:, 0, 1].tolist() == [0.0, 0.0, 1.0]
    # index 1 fully transparent -> white
    out = read_image(_encode(img, transparency=1))
    assert out[:, 0, 0].tolist() == [1.0, 0.0, 0.0]
    assert out[:, 0, 1].tolist() == [1.0, 1.0, 1.0]


def test_rgba_and_la_composited_over_white():
    rgba = Image.fromarray(np.array([[[255, 0, 0, 128], [0, 0, 0, 0]]], dtype=np.uint8), "RGBA")
    out = read_image(_encode(rgba))
    a = 128 / 255
    assert out[:, 0, 0].tolist() == pytest.approx([1.0, 1 - a, 1 - a], abs=1e-6)
    assert out[:, 0, 1].tolist() == [1.0, 1.0, 1.0]
    la = Image.fromarray(np.array([[[0, 255], [100, 0]]], dtype=np.uint8), "LA")
    out = read_image(_encode(la))
    assert out[:, 0, 0].tolist() == [0.0, 0.0, 0.0]
    assert out[:, 0, 1].tolist() == [1.0, 1.0, 1.0]


def test_16bit_gray_divided_by_65535_and_gray8_replicated():
    values = np.array([[0, 65535, 32768]], dtype=np.uint16)
    out = read_image(_encode(Image.fromarray(values)))
    assert out.shape == (3, 1, 3)
    assert out[0, 0].tolist() == pytest.approx([0.0, 1.0, 32768 / 65535])
    assert torch.equal(out[0], out[1]) and torch.equal(out[0], out[2])
    out = read_image(_encode(Image.fromarray(np.array([[0, 51]], dtype=np.uint8), "L")))
    assert out[:, 0, 1].tolist() == pytest.approx([0.2, 0.2, 0.2])


def test_jpeg_decodes_close_to_source():
    array = np.full((16, 16, 3), (200, 100, 50), dtype=np.uint8)
    out = read_image(_encode(Image.fromarray(array), "JPEG", quality=95))
    assert out.shape == (3, 16, 16)
    assert (out.mean(dim=(1, 2)) * 255).tolist() == pytest.approx([200, 100, 50], abs=3)


# -- write_png ----------------------------------------------------------------------------


def test_write_png_round_trip_atomic(tmp_path):
    image = torch.rand(3, 5, 7, generator=torch.Generator().manual_seed(0))
    path = tmp_path / "sub" / "x.png"
    with pytest.raises(FileNotFoundError):  # like open(): the folder must exist
        write_png(path, image)
    assert not path.parent.exists()
    path.parent.mkdir()
    data = write_png(path, image)
    assert path.read_bytes() == data
    assert os.listdir(path.parent) == ["x.png"]  # no temporary file left behind
    back = read_image(path)
    assert (back - image).abs().max() <= 0.5 / 255 + 1e-6
    assert write_png(None, image) == data


def test_write_png_compression_changes_bytes_never_pixels():
    gen = torch.Generator().manual_seed(1)
    smooth = torch.linspace(0, 1, 64 * 48).reshape(1, 48, 64).expand(3, 48, 64) * 0.8
    image = (smooth + 0.05 * torch.rand(3, 48, 64, generator=gen)).clamp(0, 1)
    default = write_png(None, image)
    assert write_png(None, image, compress_level=6, strategy="default") == default
    for options in ({"compress_level": 1}, {"compress_level": 0}, {"compress_level": 1, "strategy": "rle"},
                    {"compress_level": 9, "strategy": "rle"}):
        data = write_png(None, image, **options)
        assert torch.equal(read_image(data), read_image(default)), options
    assert len(write_png(None, image, compress_level=0)) > len(default)
    for bad in ({"compress_level": 10}, {"compress_level": -1}, {"compress_level": True},
                {"compress_level": 1.5}, {"strategy": "fast"}):
        with pytest.raises(InputError, match="compress_level|strategy"):
            write_png(None, image, **bad)


def test_write_png_refuses_nan_and_bad_shape():
    with pytest.raises(InputError, match="NaN"):
        write_png(None, torch.full((3, 2, 2), float("nan")))
    with pytest.raises(InputError, match=r"\(3, H, W\)"):
        write_png(None, torch.zeros(2, 2))


# -- depth --------------------------------------------------------------------------------


def _npy(array) -> bytes:
    buf = io.BytesIO()
    np.save(buf, array, allow_pickle=True)
    return buf.getvalue()


def test_depth_npy_and_scale(tmp_path):
    depth = np.arange(6, dtype=np.float32).reshape(2, 3) + 0.5
    path = tmp_path / "d.npy"
    np.save(path, depth)
    out = read_depth(path)
    assert out.shape == (1, 2, 3) and out.dtype == torch.float32
    assert torch.equal(out[0], torch.from_numpy(depth))
    assert torch.allclose(read_depth(_npy(depth[None]), scale=2.0)[0], torch.from_numpy(depth * 2))
    ints = read_depth(_npy(np.array([[1000, 2500]], dtype=np.uint16)), scale=0.001)
    assert ints.tolist() == [[[1.0, 2.5]]]


class _Marker:
    def __init__(self, path):
        self.path = path

    def __reduce__(self):
        return (open, (self.path, "w"))


def test_depth_npy_pickle_refused_without_unpickling(tmp_path):
    marker = tmp_path / "marker"
    data = _npy(np.array([_Marker(str(marker))], dtype=object))
    with pytest.raises(InputError, match="refusing to unpickle"):
        read_depth(data)
    assert not marker.exists()
    # a bare pickle under a .npy name is not a depth file either
    path = tmp_path / "evil.npy"
    path.write_bytes(pickle.dumps(_Marker(str(marker))))
    with pytest.raises(InputError, match="not a depth file"):
        read_depth(path)
    assert not marker.exists()


@pytest.mark.parametrize(
    ("array", "match"),
    [
        (np.zeros((2, 2), dtype=np.complex64), "real float or integer"),
        (np.zeros((2, 2), dtype=bool), "real float or integer"),
        (np.array([["ab", "cd"]]), "real float or integer"),
        (np.zeros((2, 2), dtype=[("a", "f4")]), "real float or integer"),
        (np.zeros((3, 2, 2), dtype=np.float32), r"\(H, W\), \(1, H, W\) or \(H, W, 1\), got \(3, 2, 2\)"),
        (np.zeros(5, dtype=np.float32), r"got \(5,\)"),
    ],
)
def test_depth_npy_bad_dtype_or_shape(array, match):
    with pytest.raises(InputError, match=match):
        read_depth(_npy(array))


def test_depth_npy_header_size_checked_before_loading():
    header = np.lib.format.header_data_from_array_1_0(np.zeros((1, 1), dtype=np.float32))
    header["shape"] = (100_000, 100_000)
    buf = io.BytesIO()
    np.lib.format.write_array_header_1_0(buf, header)
    data = buf.getvalue() + b"\x00" * 16
    with pytest.raises(ImageTooLargeError, match="100000x100000"):
        read_depth(data)
    header["shape"] = (100, 100)
    buf = io.BytesIO()
    np.lib.format.write_array_header_1_0(buf, header)
    with pytest.raises(InputError, match="truncated or corrupt"):
        read_depth(buf.getvalue() + b"\x00" * 16)


def test_depth_png16_times_scale_and_png8_refused():
    mm = np.array([[0, 1500, 65535]], dtype=np.uint16)
    out = read_depth(_encode(Image.fromarray(mm)), scale=0.001)
    assert out[0, 0].tolist() == pytest.approx([0.0, 1.5, 65.535])
    with pytest.raises(InputError, match="16-bit"):
        read_depth(_encode(Image.fromarray(np.zeros((2, 2), dtype=np.uint8))))
    with pytest.raises(InputError, match="scale"):
        read_depth(_encode(Image.fromarray(mm)), scale=0.0)
    with pytest.raises(InputError, match="not a depth file"):
        read_depth(_encode(Image.new("RGB", (2, 2)), "JPEG"))
