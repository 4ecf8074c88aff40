"""Strict image and depth decoding, shared by the readers, the CLI and the service.

Everything that turns bytes from a user into pixels goes through this module, so the rules
are in one place:

* Images: only PNG and JPEG are decoded. The pixel count is read from the header and
  checked against ``max_pixels`` *before* any pixel data is decompressed, so a
  decompression bomb (a tiny file declaring a huge image) costs a header read.
* Depth: ``.npy`` files are parsed with ``allow_pickle=False`` after their header (dtype,
  shape) has been checked; 16-bit PNG depth is multiplied by ``scale``.
* Files are written atomically (temporary file in the same folder, fsync, rename), so a
  reader never sees half a file.
"""

from __future__ import annotations

import contextlib
import io
import json
import math
import os
import secrets
import shutil
import stat
import tempfile
import zlib
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path, PurePosixPath
from typing import BinaryIO

import numpy as np
import torch
from PIL import Image, ImageFile
from torch import Tensor

from roguenerf.errors import InputError

DEFAULT_MAX_PIXELS = 64 * 1024 * 1024
"""Largest image / depth map accepted by default (about 8192 x 8192)."""

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
NPY_MAGIC = b"\x93NUMPY"

PNG_COMPRESS_LEVEL = 6
"""zlib level of the PNGs written by default."""

PNG_STRATEGIES = {"default": zlib.Z_DEFAULT_STRATEGY, "rle": zlib.Z_RLE}
"""zlib strategies :func:`encode_png` offers. ``"rle"`` only finds runs of one repeated byte:
after PNG's row filters, photographs and renders come out about as small as with the default
strategy at level 6 (flat areas are runs of zeros), in a quarter of the time; files whose
content repeats at longer distances (text, tiled patterns) come out larger. The level does
not matter with ``"rle"`` (1 to 9 give the same bytes); 0 still means "stored"."""

Source = str | os.PathLike | bytes | bytearray | memoryview

# Pillow's own bomb guard raises (instead of warning) above twice this value, while decoding
# headers. Our max_pixels check is the real gate; keep Pillow's guard at least as strict as
# the library default so that a caller who never passes max_pixels is still protected by it,
# and never disabled (``None``) by whichever library imported Pillow first.
if Image.MAX_IMAGE_PIXELS is None or Image.MAX_IMAGE_PIXELS > 2 * DEFAULT_MAX_PIXELS:
    Image.MAX_IMAGE_PIXELS = 2 * DEFAULT_MAX_PIXELS


class ImageTooLargeError(InputError):
    """The image or depth map declares more pixels than allowed (the service maps it to 413)."""

    def __init__(self, name: str, width: int, height: int, max_pixels: int):
        self.width = width
        self.height = height
        self.max_pixels = max_pixels
        size = f"{width}x{height} = {width * height} pixels" if width > 0 else "a size"
        super().__init__(f"{name}: image declares {size}, more than the allowed {max_pixels} pixels")


def _name(source: Source | BinaryIO) -> str:
    if isinstance(source, (bytes, bytearray, memoryview)):
        return f"<{len(source)} bytes>"
    return str(source)


def _open_bytes(source: Source) -> tuple[BinaryIO, str]:
    """Binary stream and a display name; raises InputError for missing files."""
    if isinstance(source, (bytes, bytearray, memoryview)):
        return io.BytesIO(bytes(source)), _name(source)
    if not isinstance(source, (str, os.PathLike)):
        raise InputError(f"expected a path or bytes, got {type(source).__name__}")
    path = Path(source)
    try:
        return open(path, "rb"), str(path)
    except FileNotFoundError:
        raise InputError(f"{path}: file not found") from None
    except IsADirectoryError:
        raise InputError(f"{path}: is a directory, expected a file") from None
    except OSError as exc:
        raise InputError(f"{path}: cannot open ({exc.strerror or exc})") from None


def _check_pixels(name: str, width: int, height: int, max_pixels: int) -> None:
    if width <= 0 or height <= 0:
        raise InputError(f"{name}: image has an empty size {width}x{height}")
    if width * height > max_pixels:
        raise ImageTooLargeError(name, width, height, max_pixels)


def _open_image(stream: BinaryIO, name: str, formats: list[str], max_pixels: int) -> Image.Image:
    """Open lazily (header only) and check the declared size."""
    try:
        img = Image.open(stream, formats=formats)
    except Image.DecompressionBombError:
        # Pillow's guard fired while reading the header; report the declared size ourselves.
        stream.seek(0)
        width, height = _png_header_size(stream.read(33))
        raise ImageTooLargeError(name, width, height, max_pixels) from None
    except Image.UnidentifiedImageError:
        raise InputError(
            f"{name}: not a {' or '.join(formats)} image (other formats are refused)"
        ) from None
    except (OSError, SyntaxError, ValueError, EOFError, zlib.error) as exc:
        raise InputError(f"{name}: corrupt image header ({exc})") from None
    _check_pixels(name, img.width, img.height, max_pixels)
    return img


def _png_header_size(head: bytes) -> tuple[int, int]:
    if head[:8] == PNG_SIGNATURE and head[12:16] == b"IHDR":
        return int.from_bytes(head[16:20], "big"), int.from_bytes(head[20:24], "big")
    return -1, -1


def _load_pixels(img: Image.Image, name: str) -> None:
    # Pillow can be told globally to accept truncated files; never for our inputs.
    if ImageFile.LOAD_TRUNCATED_IMAGES:
        raise InputError(
            "PIL.ImageFile.LOAD_TRUNCATED_IMAGES is set, refusing to decode "
            f"{name} (truncated images would pass silently)"
        )
    try:
        img.load()
    except (OSError, SyntaxError, ValueError, EOFError, zlib.error) as exc:
        raise InputError(f"{name}: truncated or corrupt image data ({exc})") from None


def read_image_size(source: Source, *, max_pixels: int = DEFAULT_MAX_PIXELS) -> tuple[int, int]:
    """``(width, height)`` of a PNG/JPEG from its header, without decoding pixels."""
    stream, name = _open_bytes(source)
    with stream:
        img = _open_image(stream, name, ["PNG", "JPEG"], max_pixels)
        return img.width, img.height


def read_image(source: Source, *, max_pixels: int = DEFAULT_MAX_PIXELS) -> Tensor:
    """Decode a PNG or JPEG into float32 RGB in [0, 1], as stored (sRGB, no linearisation).

    Conversions (so any PNG/JPEG a user has gives a sensible RGB image):

    * 8-bit RGB / grayscale ``L`` / bilevel ``1``: ``value / 255``, grayscale copied to R, G, B.
    * 16-bit grayscale (``I;16``, ``I``): ``value / 65535`` copied to R, G, B. Pillow reduces
      16-bit *colour* PNGs to 8 bits per channel while decoding, so those arrive as 8-bit RGB.
    * Palette (``P``): palette colours; a palette with transparency is treated as RGBA.
    * Alpha (``RGBA``, ``LA``, transparent palette): composited over **white**
      (``rgb * a + (1 - a)``, straight alpha), the convention of Blender/NeRF synthetic data.
    * CMYK / YCbCr JPEG: converted to RGB by Pillow.
    * EXIF orientation is ignored: pixels are returned as stored, because camera intrinsics
      refer to the stored pixel grid.
    * Animated PNG: the first frame.

    Args:
        source: path or the file's bytes.
        max_pixels: images declaring more pixels in their header raise
            :class:`ImageTooLargeError` before any pixel data is decompressed.
    Returns:
        ``(3, H, W)`` float32 in [0, 1].
    Raises:
        ImageTooLargeError: too many pixels (an :class:`~roguenerf.errors.InputError`).
        InputError: missing file, not PNG/JPEG, truncated or corrupt data.
    """
    stream, name = _open_bytes(source)
    with stream:
        img = _open_image(stream, name, ["PNG", "JPEG"], max_pixels)
        _load_pixels(img, name)
        return _to_rgb(img, name)


def _to_rgb(img: Image.Image, name: str) -> Tensor:
    mode = img.mode
    if mode == "P":
        img = img.convert("RGBA" if "transparency" in img.info else "RGB")
        mode = img.mode
    elif mode == "PA":
        img = img.convert("RGBA")
        mode = "RGBA"
    if mode in ("I;16", "I;16B", "I;16L", "I"):
        gray = np.asarray(img).astype(np.float32) / 65535.0
        rgb = np.repeat(gray[None], 3, axis=0)
        return torch.from_numpy(np.clip(rgb, 0.0, 1.0))
    if mode in ("1", "L"):
        gray = np.asarray(img.convert("L"), dtype=np.float32) / 255.0
        return torch.from_numpy(np.repeat(gray[None], 3, axis=0))
    if mode == "LA":
        la = np.asarray(img, dtype=np.float32) / 255.0
        rgb = np.repeat(la[None, ..., 0], 3, axis=0)
        return torch.from_numpy(_over_white(rgb, la[..., 1]))
    if mode == "RGBA":
        rgba = np.asarray(img, dtype=np.float32) / 255.0
        return torch.from_numpy(_over_white(rgba[..., :3].transpose(2, 0, 1), rgba[..., 3]))
    if mode != "RGB":
        try:
            img = img.convert("RGB")
        except (ValueError, OSError) as exc:
            raise InputError(f"{name}: cannot convert image mode {mode!r} to RGB ({exc})") from None
    rgb = np.asarray(img, dtype=np.float32) / 255.0
    return torch.from_numpy(np.ascontiguousarray(rgb.transpose(2, 0, 1)))


def _over_white(rgb: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """``rgb`` (3, H, W) with straight ``alpha`` (H, W) composited over white."""
    return np.ascontiguousarray(rgb * alpha[None] + (1.0 - alpha[None]), dtype=np.float32)


GZIP_MAGIC = b"\x1f\x8b"
ZIP_MAGIC = b"PK\x03\x04"
TIFF_MAGICS = (b"II*\x00", b"MM\x00*")
EXR_MAGIC = b"\x76\x2f\x31\x01"
DEPTH_KINDS = ("npy", "png", "gz", "npz", "tiff")
"""What :func:`read_depth` decodes (``kind``); detected from the content by default."""


def read_depth(
    source: Source,
    *,
    scale: float = 1.0,
    max_pixels: int = DEFAULT_MAX_PIXELS,
    kind: str | None = None,
) -> Tensor:
    """Read a depth map, times ``scale``, from any of the files radiance-field tools write.

    * ``.npy`` (any real float/int dtype), checked from its header first (shape ``(H, W)``,
      ``(1, H, W)`` or ``(H, W, 1)`` as nerfstudio writes it, a real numeric dtype, size within
      ``max_pixels``) and then loaded with ``allow_pickle=False``: object arrays and pickles are
      refused, never unpickled.
    * ``.npy.gz``: a gzip-compressed ``.npy`` (nerfstudio ``ns-render dataset`` raw depth);
      decompression stops as soon as more bytes come out than a ``max_pixels`` float64 map
      needs (a gzip bomb costs nothing).
    * ``.npz``: the array named ``depth`` or the archive's only array, checked like ``.npy``.
    * PNG: single-channel 16-bit (e.g. millimetres with ``scale=0.001``); an 8-bit PNG cannot
      hold depth and is refused.
    * TIFF: single-channel 32-bit float (or 16-bit integer), decoded by Pillow, already a
      dependency. OpenEXR is refused with a message: no EXR reader is a dependency.

    Values are returned as stored times ``scale``; unknown values
    (:func:`roguenerf.geometry.depth.known_depth_mask`: non-finite, ``<= 1e-6`` or ``>= 1e10``)
    are not altered: every consumer applies that one rule.

    Args:
        source: path or the file's bytes.
        scale: multiplier to pose units; finite and > 0.
        max_pixels: larger maps raise :class:`ImageTooLargeError` before the data is read.
        kind: one of :data:`DEPTH_KINDS`; by default detected from the content's magic bytes.
    Returns:
        ``(1, H, W)`` float32.
    """
    if not (isinstance(scale, (int, float)) and np.isfinite(scale) and scale > 0):
        raise InputError(f"depth scale must be a finite number > 0, got {scale!r}")
    stream, name = _open_bytes(source)
    with stream:
        depth = _read_depth_stream(stream, name, max_pixels, kind, nested=False)
    if scale != 1.0:
        depth = depth * np.float32(scale)
    return torch.from_numpy(np.ascontiguousarray(depth, dtype=np.float32)[None])


def _depth_kind(head: bytes, name: str) -> str:
    if head.startswith(NPY_MAGIC):
        return "npy"
    if head.startswith(PNG_SIGNATURE):
        return "png"
    if head.startswith(GZIP_MAGIC):
        return "gz"
    if head.startswith(ZIP_MAGIC):
        return "npz"
    if head.startswith(TIFF_MAGICS):
        return "tiff"
    if head.startswith(EXR_MAGIC):
        raise InputError(f"{name}: OpenEXR depth is not supported (no EXR reader is a dependency); "
                         "save it as .npy, .npy.gz, .npz, 32-bit float TIFF or 16-bit PNG")
    raise InputError(
        f"{name}: not a depth file: expected .npy, .npy.gz, .npz, a 32-bit float TIFF or a 16-bit PNG "
        f"(first bytes {head!r})"
    )


def _read_depth_stream(stream: BinaryIO, name: str, max_pixels: int, kind: str | None, *,
                       nested: bool) -> np.ndarray:
    head = stream.read(8)
    stream.seek(0)
    if kind is None:
        kind = _depth_kind(head, name)
    if kind not in DEPTH_KINDS:
        raise InputError(f"depth kind must be one of {', '.join(DEPTH_KINDS)}, got {kind!r}")
    if kind == "npy":
        return _read_npy(stream, name, max_pixels)
    if kind == "png":
        return _read_png_depth(stream, name, max_pixels)
    if kind == "tiff":
        return _read_tiff_depth(stream, name, max_pixels)
    if nested:
        raise InputError(f"{name}: a compressed archive inside a compressed archive is not a depth map")
    if kind == "gz":
        return _read_gz_depth(stream, name, max_pixels)
    return _read_npz_depth(stream, name, max_pixels)


def _bounded_bytes(max_pixels: int) -> int:
    """Largest decompressed depth file accepted: a float64 map of ``max_pixels`` plus a header."""
    return max_pixels * 8 + 4096


def _read_gz_depth(stream: BinaryIO, name: str, max_pixels: int) -> np.ndarray:
    limit = _bounded_bytes(max_pixels)
    inflater = zlib.decompressobj(16 + zlib.MAX_WBITS)
    out = bytearray()
    try:
        while chunk := stream.read(1 << 20):
            out += inflater.decompress(chunk, limit + 1 - len(out))
            if len(out) > limit or inflater.unconsumed_tail:
                raise ImageTooLargeError(f"{name} (decompressed)", -1, -1, max_pixels)
            if inflater.eof:
                break
        out += inflater.flush()
    except zlib.error as exc:
        raise InputError(f"{name}: corrupt gzip data ({exc})") from None
    if not inflater.eof:
        raise InputError(f"{name}: truncated gzip data")
    return _read_depth_stream(io.BytesIO(bytes(out)), f"{name} (decompressed)", max_pixels, None, nested=True)


def _read_npz_depth(stream: BinaryIO, name: str, max_pixels: int) -> np.ndarray:
    import zipfile

    try:
        with zipfile.ZipFile(stream) as archive:
            members = [i for i in archive.infolist() if i.filename.endswith(".npy")]
            chosen = [i for i in members if i.filename == "depth.npy"] or members
            if len(chosen) != 1:
                found = ", ".join(i.filename[:-4] for i in members) or "none"
                raise InputError(f"{name}: .npz must hold one array or one named 'depth', found: {found}")
            info = chosen[0]
            if info.file_size > _bounded_bytes(max_pixels):
                raise ImageTooLargeError(f"{name}:{info.filename}", -1, -1, max_pixels)
            data = archive.read(info)
    except zipfile.BadZipFile as exc:
        raise InputError(f"{name}: not a valid .npz file ({exc})") from None
    except (zlib.error, EOFError, NotImplementedError) as exc:
        raise InputError(f"{name}: corrupt .npz data ({exc})") from None
    return _read_npy(io.BytesIO(data), f"{name}:{info.filename[:-4]}", max_pixels)


def _read_tiff_depth(stream: BinaryIO, name: str, max_pixels: int) -> np.ndarray:
    img = _open_image(stream, name, ["TIFF"], max_pixels)
    if img.mode not in ("F", "I;16", "I;16B", "I;16L", "I"):
        raise InputError(f"{name}: depth TIFF must be single-channel 32-bit float (or 16-bit), "
                         f"got mode {img.mode!r}")
    _load_pixels(img, name)
    return np.asarray(img).astype(np.float32)


def _read_npy(stream: BinaryIO, name: str, max_pixels: int) -> np.ndarray:
    fmt = np.lib.format
    try:
        version = fmt.read_magic(stream)
        if version == (1, 0):
            shape, fortran, dtype = fmt.read_array_header_1_0(stream)
        elif version in ((2, 0), (3, 0)):
            shape, fortran, dtype = fmt.read_array_header_2_0(stream)
        else:
            raise ValueError(f"unsupported .npy version {version}")
    except (ValueError, EOFError, OSError) as exc:
        raise InputError(f"{name}: not a valid .npy file ({exc})") from None
    if dtype.hasobject:
        raise InputError(
            f"{name}: .npy holds Python objects (dtype {dtype}); refusing to unpickle, "
            "expected a float or integer array"
        )
    if dtype.kind not in "fiu" or dtype.fields is not None or dtype.subdtype is not None:
        raise InputError(f"{name}: depth dtype must be a real float or integer type, got {dtype}")
    if len(shape) == 3 and shape[0] == 1:
        shape = shape[1:]
    elif len(shape) == 3 and shape[2] == 1:  # nerfstudio's raw depth: (H, W, 1)
        shape = shape[:2]
    if len(shape) != 2:
        raise InputError(f"{name}: depth shape must be (H, W), (1, H, W) or (H, W, 1), got {tuple(shape)}")
    height, width = shape
    _check_pixels(name, width, height, max_pixels)
    stream.seek(0)
    try:
        array = np.load(stream, allow_pickle=False)
    except (ValueError, EOFError, OSError) as exc:
        raise InputError(f"{name}: truncated or corrupt .npy data ({exc})") from None
    return np.asarray(array, dtype=np.float32).reshape(height, width)


def _read_png_depth(stream: BinaryIO, name: str, max_pixels: int) -> np.ndarray:
    img = _open_image(stream, name, ["PNG"], max_pixels)
    if img.mode not in ("I;16", "I;16B", "I;16L", "I"):
        raise InputError(
            f"{name}: depth PNG must be single-channel 16-bit, got mode {img.mode!r}"
        )
    _load_pixels(img, name)
    return np.asarray(img).astype(np.float32)


def finite_for_json(obj):
    """JSON has no inf/NaN (PSNR of identical images is inf): floats that are not finite become
    None, through dicts and lists."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: finite_for_json(v) for k, v in obj.items()}
    if isinstance(obj, list):
        return [finite_for_json(v) for v in obj]
    return obj


def atomic_write(path: str | os.PathLike, data: bytes, *, make_parents: bool = False) -> Path:
    """Write ``data`` to ``path`` atomically: temporary file in the same folder, fsync, rename.

    The file gets the permissions an ordinary ``open(path, "wb")`` would give it: a new file
    ``0o666`` less the process umask, a replaced file keeps its mode (``tempfile.mkstemp``
    would make it ``0o600``). The folder must exist unless ``make_parents`` is true.
    """
    path = Path(path)
    if make_parents:
        path.parent.mkdir(parents=True, exist_ok=True)
    try:
        mode = stat.S_IMODE(os.stat(path).st_mode)
    except (FileNotFoundError, NotADirectoryError):
        mode = None
    for _ in range(100):
        tmp = path.parent / f".{path.name}.{secrets.token_hex(6)}.tmp"
        try:
            # O_EXCL: never follows or reuses an existing name; 0o666 & ~umask, as open() does.
            fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_CLOEXEC", 0), 0o666)
            break
        except FileExistsError:
            continue
    else:  # pragma: no cover - 100 collisions of 48 random bits
        raise FileExistsError(f"cannot create a temporary file beside {path}")
    try:
        if mode is not None:
            os.fchmod(fd, mode)
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise
    try:
        dir_fd = os.open(path.parent, os.O_RDONLY)
    except OSError:
        return path
    try:
        os.fsync(dir_fd)
    except OSError:
        pass  # some filesystems cannot fsync directories; the rename is still atomic
    finally:
        os.close(dir_fd)
    return path


def read_json(path: Path, fail: Callable[[str], Exception], *, missing: str, unreadable: str):
    """The JSON value in the UTF-8 file ``path``; ``fail(message)`` is raised where there is no such
    file (``missing``) or it cannot be read or parsed (``unreadable``, the reason in brackets)."""
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise fail(missing) from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise fail(f"{unreadable} ({exc})") from None


def holds_files(folder: Path, not_a_folder: Callable[[], Exception]) -> bool:
    """Whether the would-be output ``folder`` exists and holds anything: False where it does not
    exist or is empty; ``not_a_folder()`` is raised where it is something else than a folder."""
    if not folder.exists():
        return False
    if not folder.is_dir():
        raise not_a_folder()
    return any(folder.iterdir())


def check_output_folder(final: Path, replaceable: Callable[[Path], bool], what: str = "output", *,
                        owned: Callable[[Path], Iterable[str]] | None = None) -> None:
    """An output folder may be new, empty, or an earlier output of the same command
    (``replaceable(final)``: the command's own marker), which is then replaced whole; anything else
    is an :class:`InputError`. ``owned(final)``: the files (relative POSIX paths) that earlier output
    wrote; a folder holding any other file is refused too, since replacing it would delete that file."""
    if not holds_files(final, lambda: InputError(f"{what}: {final} exists and is not a folder; choose a new folder")):
        return
    if not replaceable(final):
        raise InputError(f"{what}: {final} exists and is not empty: it holds other files, not an earlier "
                         "output of this command (which would be replaced); choose a new folder")
    if owned is not None:
        foreign = foreign_files(final, owned(final))
        if foreign:
            more = f" and {len(foreign) - 3} more" if len(foreign) > 3 else ""
            raise InputError(f"{what}: {final} is an earlier output of this command but also holds files it did "
                             f"not write ({', '.join(foreign[:3])}{more}), which replacing it would delete; "
                             "move them out or choose a new folder")


def foreign_files(folder: Path, owned: Iterable[str]) -> list[str]:
    """The files under ``folder`` (relative POSIX paths, sorted) that are not in ``owned``."""
    owned = {str(PurePosixPath(p)) for p in owned}
    return sorted(rel for rel in (p.relative_to(folder).as_posix() for p in folder.rglob("*")
                                  if p.is_symlink() or not p.is_dir())
                  if rel not in owned)


@contextlib.contextmanager
def atomic_folder(final: str | os.PathLike, *, replaceable: Callable[[Path], bool],
                  what: str = "output", owned: Callable[[Path], Iterable[str]] | None = None) -> Iterator[Path]:
    """Build a folder in a temporary sibling (yielded) and rename it to ``final`` at the end, so a
    failure half-way leaves no half-written folder: the temporary one is removed, and an earlier
    output at ``final`` stays until the new one is complete (see :func:`check_output_folder`)."""
    final = Path(final)
    check_output_folder(final, replaceable, what, owned=owned)
    final.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{final.name}.", suffix=".partial", dir=final.parent))
    try:
        yield tmp
        check_output_folder(final, replaceable, what, owned=owned)
        if final.is_dir() and not any(final.iterdir()):
            final.rmdir()
        if final.exists():
            old = final.parent / f".{final.name}.replaced-{os.getpid()}"
            shutil.rmtree(old, ignore_errors=True)
            os.replace(final, old)
            os.replace(tmp, final)
            shutil.rmtree(old, ignore_errors=True)
        else:
            os.replace(tmp, final)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def _image_array(image, name: str) -> np.ndarray:
    array = image.detach().cpu().numpy() if isinstance(image, Tensor) else np.asarray(image)
    if array.ndim != 3 or array.shape[0] not in (1, 3) or array.shape[1] == 0 or array.shape[2] == 0:
        raise InputError(f"{name} must have shape (3, H, W) or (1, H, W), got {tuple(array.shape)}")
    if not np.issubdtype(array.dtype, np.floating):
        from roguenerf.images import float_image_error

        raise float_image_error(name, array.dtype)
    if not np.isfinite(array).all():
        raise InputError(f"{name} contains NaN or inf")
    return array


def _png_options(level, strategy) -> dict:
    if isinstance(level, bool) or not isinstance(level, (int, np.integer)) or not 0 <= level <= 9:
        raise InputError(f"compress_level: expected an integer from 0 to 9, got {level!r}")
    if strategy not in PNG_STRATEGIES:
        raise InputError(f"strategy: expected one of {sorted(PNG_STRATEGIES)}, got {strategy!r}")
    options = {"compress_level": int(level)}
    if strategy != "default":  # Pillow's own default otherwise: the bytes written so far stay the same
        options["compress_type"] = PNG_STRATEGIES[strategy]
    return options


def encode_png(image: Tensor | np.ndarray, *, name: str = "image",
               compress_level: int = PNG_COMPRESS_LEVEL, strategy: str = "default") -> bytes:
    """8-bit PNG bytes of ``(3, H, W)`` (or ``(1, H, W)`` gray) float in [0, 1] (clipped, rounded).

    ``compress_level`` (zlib, 0-9) and ``strategy`` (see :data:`PNG_STRATEGIES`) change only
    the size of the file and the time spent compressing it, never its pixels.
    """
    options = _png_options(compress_level, strategy)
    array = _image_array(image, name)
    u8 = np.round(np.clip(array, 0.0, 1.0) * 255.0).astype(np.uint8)
    img = Image.fromarray(u8[0]) if u8.shape[0] == 1 else Image.fromarray(u8.transpose(1, 2, 0))
    buf = io.BytesIO()
    img.save(buf, format="PNG", **options)
    return buf.getvalue()


def write_png(path: str | os.PathLike | None, image: Tensor | np.ndarray, *,
              compress_level: int = PNG_COMPRESS_LEVEL, strategy: str = "default") -> bytes:
    """Encode ``image`` ``(3, H, W)`` float in [0, 1] as 8-bit PNG; write atomically if ``path``.

    Values are clipped to [0, 1] and rounded (``round(255 * x)``); NaN/inf raise InputError.
    ``compress_level`` (zlib, 0-9; default 6) and ``strategy`` (``"default"`` or ``"rle"``,
    see :data:`PNG_STRATEGIES`) trade file size for encoding time; the pixels are the same
    whatever they are. Returns the PNG bytes. The file's folder must exist (as for ``open``);
    the file gets ``open``'s permissions (:func:`atomic_write`).
    """
    data = encode_png(image, compress_level=compress_level, strategy=strategy)
    if path is not None:
        atomic_write(path, data)
    return data


def encode_npy(array: np.ndarray) -> bytes:
    """``.npy`` bytes of a numeric array (never pickled)."""
    buf = io.BytesIO()
    np.save(buf, np.ascontiguousarray(array), allow_pickle=False)
    return buf.getvalue()
