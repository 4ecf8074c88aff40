"""The one Scene type every loader returns.

A :class:`Scene` is a list of :class:`Frame` records (pose, intrinsics, file paths) plus
lazy, cached loaders for the pixels. Nothing is decoded until asked for; decoded tensors
are kept in an LRU cache bounded in bytes.

Conventions (see :mod:`roguenerf.geometry`): poses are OpenCV camera-to-world float64,
``K`` uses the pixel-centre convention (centre of pixel (row v, col u) at (u + 0.5, v + 0.5)),
depth is z-depth in pose units, unknown where :func:`roguenerf.geometry.depth.known_depth_mask`
is False (non-finite, ``<= 1e-6`` or ``>= 1e10``).
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from dataclasses import dataclass, field
from pathlib import Path

import torch
from torch import Tensor

from roguenerf.errors import InputError, SceneFormatError

DEFAULT_CACHE_BYTES = 512 * 1024 * 1024
"""Decoded images/depths kept per scene (the 125-view 200x200 lego scene needs ~140 MB)."""

SPLITS = ("train", "test")


@dataclass(eq=False)
class Frame:
    name: str
    """Unique view name (file stem, e.g. ``train_r_0``)."""
    world_from_cam: Tensor
    """``(4, 4)`` float64 OpenCV camera-to-world."""
    K: Tensor
    """``(3, 3)`` float64, pixel-centre convention."""
    width: int
    height: int
    split: str
    """"train" or "test"."""
    image_path: Path | None = None
    render_path: Path | None = None
    depth_path: Path | None = None
    depth_scale: float = 1.0
    """Multiply stored depth by this to get pose units (nerfstudio mm PNG: 0.001 * scale)."""
    depth_type: str = "z"
    """"z" or "ray" (converted to z on load)."""


class ByteLRU:
    """Thread-safe LRU of tensors bounded by their total size in bytes (a tensor larger than the
    budget is not kept). The scene's read cache; also the enhancer's neighbour depths."""

    def __init__(self, max_bytes: int):
        self.max_bytes = max_bytes
        self.nbytes = 0
        self._items: OrderedDict[tuple, Tensor] = OrderedDict()
        self._lock = threading.Lock()

    def get(self, key: tuple) -> Tensor | None:
        with self._lock:
            value = self._items.get(key)
            if value is not None:
                self._items.move_to_end(key)
            return value

    def put(self, key: tuple, value: Tensor) -> None:
        size = value.numel() * value.element_size()
        if size > self.max_bytes:
            return
        with self._lock:
            old = self._items.pop(key, None)
            if old is not None:
                self.nbytes -= old.numel() * old.element_size()
            self._items[key] = value
            self.nbytes += size
            while self.nbytes > self.max_bytes:
                _, evicted = self._items.popitem(last=False)
                self.nbytes -= evicted.numel() * evicted.element_size()

    def clear(self) -> None:
        with self._lock:
            self._items.clear()
            self.nbytes = 0

    def __len__(self) -> int:
        return len(self._items)


@dataclass(eq=False)
class Scene:
    """Frames of one scene with lazy, cached pixel loaders.

    ``photo(i)``, ``render(i)`` and ``depth(i)`` accept an index or a frame name and return a
    fresh tensor each call (the cache keeps its own copy, so callers may modify the result).
    """

    root: Path
    frames: list[Frame]
    meta: dict = field(default_factory=dict)
    cache_bytes: int = field(default=DEFAULT_CACHE_BYTES, repr=False)
    """Upper bound of the decoded-pixel cache; 0 disables caching."""

    def __post_init__(self) -> None:
        self.root = Path(self.root)
        names = [f.name for f in self.frames]
        if len(set(names)) != len(names):
            dup = sorted({n for n in names if names.count(n) > 1})
            raise InputError(f"scene {self.root}: frame names must be unique, repeated: {dup[:5]}")
        for frame in self.frames:
            if frame.split not in SPLITS:
                raise InputError(
                    f"scene {self.root}: frame {frame.name!r} has split {frame.split!r}, "
                    f"expected one of {SPLITS}"
                )
            if frame.depth_type not in ("z", "ray"):
                raise InputError(
                    f"scene {self.root}: frame {frame.name!r} has depth_type "
                    f"{frame.depth_type!r}, expected 'z' or 'ray'"
                )
        self._index = {name: i for i, name in enumerate(names)}
        self._cache = ByteLRU(self.cache_bytes)

    # -- lookup ---------------------------------------------------------------------------

    def __len__(self) -> int:
        return len(self.frames)

    def index(self, name: str) -> int:
        """Position of the frame called ``name``; InputError listing a few names otherwise."""
        try:
            return self._index[name]
        except KeyError:
            some = ", ".join(list(self._index)[:5])
            raise InputError(f"scene {self.root} has no view named {name!r} (views: {some}, ...)") from None

    def _resolve(self, i: int | str) -> int:
        if isinstance(i, str):
            return self.index(i)
        if isinstance(i, bool) or not isinstance(i, int):
            try:
                i = int(i)  # numpy / 0-d tensor indices
            except (TypeError, ValueError):
                raise InputError(f"view index must be an int or a name, got {type(i).__name__}") from None
        if not -len(self.frames) <= i < len(self.frames):
            raise InputError(f"view index {i} out of range for a scene of {len(self.frames)} views")
        return i % len(self.frames)

    def indices(self, split: str) -> list[int]:
        """Indices of the views in ``split`` ("train", "test" or "all"), in frame order."""
        if split == "all":
            return list(range(len(self.frames)))
        if split not in SPLITS:
            raise InputError(f"split must be 'train', 'test' or 'all', got {split!r}")
        return [i for i, f in enumerate(self.frames) if f.split == split]

    def poses(self, indices: list[int] | None = None) -> Tensor:
        """``(M, 4, 4)`` float64 OpenCV camera-to-world of all (or the given) views."""
        frames = self.frames if indices is None else [self.frames[self._resolve(i)] for i in indices]
        if not frames:
            return torch.zeros(0, 4, 4, dtype=torch.float64)
        return torch.stack([f.world_from_cam for f in frames])

    def intrinsics(self, indices: list[int] | None = None) -> Tensor:
        """``(M, 3, 3)`` float64 pixel-centre intrinsics of all (or the given) views."""
        frames = self.frames if indices is None else [self.frames[self._resolve(i)] for i in indices]
        if not frames:
            return torch.zeros(0, 3, 3, dtype=torch.float64)
        return torch.stack([f.K for f in frames])

    @property
    def has_renders(self) -> bool:
        """True when every view has a radiance-field render (nerfstudio/LLFF data have none)."""
        return bool(self.frames) and all(f.render_path is not None for f in self.frames)

    @property
    def has_depths(self) -> bool:
        """True when every view has a depth map."""
        return bool(self.frames) and all(f.depth_path is not None for f in self.frames)

    # -- pixels ---------------------------------------------------------------------------

    def photo(self, i: int | str) -> Tensor:
        """Ground-truth photo ``(3, H, W)`` float32 in [0, 1]."""
        i = self._resolve(i)
        return self._cached("photo", i, self.frames[i].image_path, self._load_image)

    def render(self, i: int | str) -> Tensor:
        """Radiance-field render ``(3, H, W)`` float32 in [0, 1]; InputError if the scene has none."""
        i = self._resolve(i)
        return self._cached("render", i, self.frames[i].render_path, self._load_image)

    def depth(self, i: int | str) -> Tensor:
        """Rendered z-depth ``(1, H, W)`` float32 in pose units (ray distance converted)."""
        i = self._resolve(i)
        return self._cached("depth", i, self.frames[i].depth_path, self._load_depth)

    def clear_cache(self) -> None:
        self._cache.clear()

    def _cached(self, kind: str, i: int, path: Path | None, load, *, copy: bool = True) -> Tensor:
        """The file's tensor from the read cache (read and kept on a miss); a copy unless
        ``copy`` is False (then the caller must not modify it)."""
        if path is None:
            frame = self.frames[i]
            what = {"photo": "photo", "render": "radiance-field render", "depth": "depth map"}[kind]
            fmt = self.meta.get("format", "this")
            raise InputError(
                f"view {frame.name!r} of scene {self.root} has no {what} "
                f"({fmt} scenes carry none for it); supply {kind}s, e.g. as a scene folder "
                "written by roguenerf.data.writers.write_scene_folder"
            )
        key = (kind, i)
        value = self._cache.get(key)
        if value is None:
            value = load(self.frames[i], path)
            self._cache.put(key, value)
        return value.clone() if copy else value

    @staticmethod
    def _load_image(frame: Frame, path: Path) -> Tensor:
        from roguenerf.imageio import read_image

        return _read_frame_file(frame, path, "image", read_image)

    @staticmethod
    def _load_depth(frame: Frame, path: Path) -> Tensor:
        from roguenerf.imageio import read_depth

        depth = _read_frame_file(frame, path, "depth", lambda p: read_depth(p, scale=frame.depth_scale))
        if frame.depth_type == "ray":
            from roguenerf.geometry.cameras import ray_to_z_depth

            depth = ray_to_z_depth(depth.double(), frame.K).float()
        return depth

    def __repr__(self) -> str:
        n_train = sum(f.split == "train" for f in self.frames)
        size = ""
        if self.frames:
            sizes = {(f.width, f.height) for f in self.frames}
            size = ", {}x{}".format(*next(iter(sizes))) if len(sizes) == 1 else f", {len(sizes)} sizes"
        parts = [
            f"{len(self.frames)} views ({n_train} train, {len(self.frames) - n_train} test){size}",
            f"format={self.meta.get('format', '?')}",
            f"renders={'yes' if self.has_renders else 'no'}",
            f"depths={'yes' if self.has_depths else 'no'}",
        ]
        return f"Scene({str(self.root)!r}, {', '.join(parts)})"


def _read_frame_file(frame: Frame, path: Path, what: str, read) -> Tensor:
    """``read(path)``, a (C, H, W) tensor of the frame's size; a :class:`SceneFormatError` naming
    the file otherwise (a bad file, or ``what`` of another size than the scene says)."""
    try:
        value = read(path)
    except SceneFormatError:
        raise
    except InputError as exc:
        raise SceneFormatError(path, _problem(exc, path)) from None
    if value.shape[1:] != (frame.height, frame.width):
        raise SceneFormatError(
            path,
            f"{what} is {value.shape[2]}x{value.shape[1]} (WxH), "
            f"the scene says {frame.width}x{frame.height}",
        )
    return value


def _problem(exc: Exception, path: Path) -> str:
    """The message of an InputError without its leading ``path: `` (SceneFormatError adds it)."""
    message = str(exc)
    prefix = f"{path}: "
    return message[len(prefix):] if message.startswith(prefix) else message


MIN_KNOWN_DEPTH = 0.01
"""A view whose depth map has fewer known pixels than this share (the library's one rule,
:func:`~roguenerf.geometry.depth.known_depth_mask`) is unusable: nothing reprojects from it."""


@dataclass(frozen=True)
class UnusableView:
    index: int
    name: str
    split: str
    reason: str

    def __str__(self) -> str:
        return f"{self.name} ({self.split}): {self.reason}"


def unusable_views(scene: Scene, *, min_known_depth: float = MIN_KNOWN_DEPTH, indices=None, reads=None,
                   progress=None) -> list[UnusableView]:
    """The views of ``scene`` that cannot serve: a depth map with (almost) no known pixel (all
    zeros, NaN, negative ...), a blank photo or render (one value everywhere), a file that cannot
    be read. Training views among them are useless as neighbours and as training targets; test
    views cannot be enhanced or measured. Reads every view's files once (not cached); with
    ``indices``, only those views'.

    ``reads`` (instead of ``indices``): ``{view index: files}``, the files (``"depth"``,
    ``"photo"``, ``"render"``) a one-view command reads of each view (the view's render and
    depth, its neighbours' photos and depths). Only those are checked, through the scene's read
    cache: the command then reads them from there, and each file is decoded once (at 2016 x 1512
    a PNG takes about 0.15 s).

    Returns them in view order (empty when every view is usable); ``progress(done, total)``.
    """
    from roguenerf.geometry.depth import known_depth_mask

    kinds = ("depth", "photo", "render")
    if reads is not None:
        if indices is not None:
            raise InputError("unusable_views: pass indices or reads, not both")
        reads = {scene._resolve(i): tuple(files) for i, files in reads.items()}
        for files in reads.values():
            if not files or set(files) - set(kinds):
                raise InputError(f"unusable_views: reads: expected files among {kinds}, got {files!r}")
        which = sorted(reads)
    else:
        which = range(len(scene.frames)) if indices is None else sorted({int(i) for i in indices})
    out = []
    for n, i in enumerate(which):
        frame = scene.frames[i]
        reasons = []
        for kind, path in (("depth", frame.depth_path), ("photo", frame.image_path), ("render", frame.render_path)):
            if path is None or (reads is not None and kind not in reads[i]):
                continue
            try:
                if reads is None:  # not kept: a whole scene would only evict what the cache holds
                    value = (Scene._load_depth if kind == "depth" else Scene._load_image)(frame, path)
                else:  # read only: the cached tensor itself, no copy
                    value = scene._cached(kind, i, path, Scene._load_depth if kind == "depth" else Scene._load_image,
                                          copy=False)
            except InputError as exc:
                reasons.append(f"{kind} {path.name} cannot be read ({_problem(exc, path)})")
                continue
            if kind == "depth":
                known = float(known_depth_mask(value).float().mean()) if value.numel() else 0.0
                if known < min_known_depth:
                    values = value[torch.isfinite(value)]
                    what = ("all zeros" if values.numel() == value.numel() and bool((values == 0).all())
                            else f"{100 * known:.2f}% known pixels")
                    reasons.append(f"depth has no usable values ({what}; known: finite, > 1e-6 and < 1e10)")
            elif value.numel() and float(value.amax() - value.amin()) < 1 / 255:
                reasons.append(f"{kind} is blank (one value everywhere)")
        if reasons:
            out.append(UnusableView(index=i, name=frame.name, split=frame.split, reason="; ".join(reasons)))
        if progress is not None:
            progress(n + 1, len(which))
    return out
