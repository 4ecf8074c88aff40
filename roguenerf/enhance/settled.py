"""Pose judgements kept between processes.

A :class:`~roguenerf.inference.SceneEnhancer` judges each neighbour's dataset pose once
(:attr:`AlignConfig.reuse <roguenerf.enhance.align.AlignConfig.reuse>`): a neighbour whose fit
found nothing to gain keeps its dataset pose on every later view without a fit. Within one
process that is :attr:`SceneEnhancer.settled <roguenerf.inference.SceneEnhancer.settled>`; this
module keeps the same set in a small JSON file, so that the next process (the next one-view
``roguenerf enhance`` of the scene) starts from it instead of fitting those neighbours again.

An entry names a training view and fingerprints what the judgement read: the photo's and the
depth's file (size and modification time), the view's pose and intrinsics. The file carries the
pose fit's settings (every :class:`~roguenerf.enhance.align.AlignConfig` field but ``reuse``).
An entry whose fingerprint differs from the scene's now (a new render, a moved camera), or a
file written with other settings, is not used; a file that cannot be read or written is
ignored (the fits are then paid as without it). Nothing here changes an image: a settled
neighbour gets what the first judgement gave it, its dataset pose.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
from dataclasses import asdict
from pathlib import Path

from roguenerf.enhance.align import AlignConfig

log = logging.getLogger(__name__)

VERSION = 1


def default_path(scene_root: str | os.PathLike) -> Path:
    """Where the judgements of the scene at ``scene_root`` are kept:
    ``$XDG_CACHE_HOME/roguenerf/settled/<hash of the resolved folder>.json`` (``~/.cache`` by
    default; ``$ROGUENERF_SETTLED_CACHE`` instead of the folder when set). The folder is made
    here where it can be (:func:`save` makes none: a file whose folder went away, a deleted
    scene's, is not written)."""
    from roguenerf.runtime import user_cache_dir

    base = user_cache_dir("settled", "ROGUENERF_SETTLED_CACHE")
    try:
        base.mkdir(parents=True, exist_ok=True)
    except OSError:
        pass  # save() then reports it
    key = hashlib.sha256(str(Path(scene_root).resolve()).encode()).hexdigest()[:24]
    return base / f"{key}.json"


def _file(path) -> list[int] | None:
    try:
        st = os.stat(path)
    except (OSError, TypeError):
        return None
    return [st.st_size, st.st_mtime_ns]


def fingerprint(frame) -> dict | None:
    """What a judgement of ``frame`` (a scene :class:`~roguenerf.data.scene.Frame`) read; None
    when its photo or depth is not a file (nothing to check a later process against)."""
    photo, depth = _file(frame.image_path), _file(frame.depth_path)
    if photo is None or depth is None:
        return None
    return {"photo": photo, "depth": depth,
            "pose": [round(float(x), 12) for x in frame.world_from_cam.reshape(-1)],
            "K": [round(float(x), 9) for x in frame.K.reshape(-1)]}


def settings(config: AlignConfig) -> dict:
    """The pose fit's settings a judgement depends on (all but ``reuse``), JSON-ready."""
    out = asdict(config)
    out.pop("reuse", None)
    return json.loads(json.dumps(out))


def _read(path: Path, config: AlignConfig) -> dict:
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        return {}
    except (OSError, ValueError) as exc:
        log.warning("pose judgements in %s not read (%s): the fits are made again", path, exc)
        return {}
    if not isinstance(data, dict) or data.get("version") != VERSION or data.get("align") != settings(config):
        return {}
    views = data.get("views")
    return views if isinstance(views, dict) else {}


def load(path: str | os.PathLike, scene, names, config: AlignConfig) -> set[str]:
    """The names among ``names`` (training views of ``scene``) judged settled by an earlier
    process whose fingerprint still holds."""
    views = _read(Path(path), config)
    frames = {f.name: f for f in scene.frames}
    out = set()
    for name in names:
        entry = views.get(name)
        if entry is not None and name in frames and entry == fingerprint(frames[name]):
            out.add(name)
    return out


def save(path: str | os.PathLike, scene, names, config: AlignConfig) -> bool:
    """Add the settled training views ``names`` of ``scene`` to the file (the entries already
    there kept, those of other settings dropped); written atomically. Whether it was written."""
    from roguenerf.imageio import atomic_write

    path = Path(path)
    views = dict(_read(path, config))
    frames = {f.name: f for f in scene.frames}
    for name in names:
        entry = fingerprint(frames[name]) if name in frames else None
        if entry is not None:
            views[name] = entry
    data = {"version": VERSION, "align": settings(config), "views": dict(sorted(views.items()))}
    try:
        atomic_write(path, json.dumps(data).encode())
    except OSError as exc:
        log.warning("pose judgements not kept in %s (%s)", path, exc)
        return False
    return True
