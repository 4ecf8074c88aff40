"""Where things live under ``data_dir`` (shared by the API and the workers).

::

    data_dir/
      roguenerf.db                 job + scene table (SQLite default)
      queue.db                     SqliteHuey queue (default)
      scenes/<id>/scene/           the uploaded scene folder (what load_scene reads)
      scenes/<id>/checkpoints/vN.safetensors   versioned enhancer checkpoints
      jobs/<job id>/               fine-tuning output_dir (resume state)
      tmp/                         uploads being validated; renamed into place when good
      .roguenerf-data              marks the folder as ours: any other non-empty folder is refused
"""

from __future__ import annotations

import os
import re
import shutil
import time
import uuid
from pathlib import Path

ID_RE = re.compile(r"^[0-9a-f]{32}$")
"""Scene and job ids: uuid4 hex. Anything else is never turned into a path."""

_VERSION_RE = re.compile(r"^v([1-9][0-9]*)\.safetensors$")


SERVER_PATH = "<server path>"
"""What a server path still left in a client message is replaced with."""


def public_message(message: str, *, root: Path | None = None, data_dir: Path | None = None,
                   root_name: str = "the scene") -> str:
    """``message`` (from a library exception) fit for a client: paths inside the uploaded folder
    ``root`` become relative to it (``depths/train_r_0.npy``), the folder itself ``root_name``
    ("the scene", or "the path archive" for a camera path's upload), and anything else under
    ``data_dir`` becomes :data:`SERVER_PATH`. Clients never learn the server's filesystem."""
    if root is not None:
        for base in dict.fromkeys((str(Path(root)), str(Path(root).resolve()))):
            message = message.replace(base + os.sep, "").replace("scene " + base, root_name)
            message = re.sub(re.escape(base) + r"(?![\w.-])", root_name, message)
    if data_dir is not None:
        for base in dict.fromkeys((str(Path(data_dir)), str(Path(data_dir).resolve()))):
            message = re.sub(re.escape(base) + r"[^\s'\",;)]*", SERVER_PATH, message)
    return message


IMPORT_DATASET = "dataset"
IMPORT_PLY = "point_cloud.ply"
IMPORT_CHECKPOINT = "checkpoint.safetensors"
"""Names inside an import job's ``input/`` folder: written by the API (``POST /scenes/import``),
read by the import task (``workers/imports.py``)."""


def new_id() -> str:
    return uuid.uuid4().hex


DATA_MARKER = ".roguenerf-data"
"""An empty file that marks a folder as a data directory of ours (written by :meth:`Layout.ensure`)."""


class Layout:
    def __init__(self, data_dir: Path):
        self.root = Path(data_dir)
        self.scenes = self.root / "scenes"
        self.jobs = self.root / "jobs"
        self.tmp = self.root / "tmp"

    def check_owned(self) -> None:
        """The data directory must be new, empty or ours (its marker, or the scenes/ jobs/ tmp/ an
        older version made): the service sweeps ``tmp/`` and removes folders under ``scenes/`` and
        ``jobs/``, so a folder of the user's (``--data-dir ~``) is refused before anything is touched."""
        from roguenerf import InputError

        root = self.root
        if not root.exists():
            return
        if not root.is_dir():
            raise InputError(f"data directory {root} exists and is not a folder; choose a new folder (--data-dir)")
        if (root / DATA_MARKER).is_file() or all(p.is_dir() for p in (self.scenes, self.jobs, self.tmp)):
            return
        if any(root.iterdir()):
            raise InputError(f"data directory {root} exists and is not empty: it holds other files, not a "
                             "RoGUENeRF data directory (whose tmp/ is swept and whose scenes/ and jobs/ are "
                             "removed as jobs end); choose a new folder (--data-dir)")

    def ensure(self) -> None:
        self.check_owned()
        self.root.mkdir(parents=True, exist_ok=True)
        (self.root / DATA_MARKER).touch(exist_ok=True)  # first: a second process starting meanwhile sees it
        for path in (self.scenes, self.jobs, self.tmp):
            path.mkdir(parents=True, exist_ok=True)

    @staticmethod
    def _check_id(value: str) -> str:
        if not ID_RE.match(value):
            raise ValueError(f"expected a 32-hex-digit id, got {value!r}")
        return value

    def scene_dir(self, scene_id: str) -> Path:
        return self.scenes / self._check_id(scene_id)

    def scene_files(self, scene_id: str) -> Path:
        return self.scene_dir(scene_id) / "scene"

    def checkpoint(self, scene_id: str, version: int) -> Path:
        if version < 1:
            raise ValueError(f"checkpoint versions start at 1, got {version}")
        return self.scene_dir(scene_id) / "checkpoints" / f"v{version}.safetensors"

    def versions(self, scene_id: str) -> list[int]:
        folder = self.scene_dir(scene_id) / "checkpoints"
        if not folder.is_dir():
            return []
        found = (_VERSION_RE.match(p.name) for p in folder.iterdir())
        return sorted(int(m.group(1)) for m in found if m)

    def sweep_stale_temp(self, older_than_s: float, *, now: float | None = None) -> list[Path]:
        """Remove what killed writers left behind: entries of ``tmp/`` (uploads, trash,
        readiness probes) and ``.NAME.HEX.tmp`` files of :func:`copy_atomic` under
        ``scenes/``, whose newest modification is older than ``older_than_s``. Younger ones
        may belong to a live process on another machine sharing the data directory."""
        now = time.time() if now is None else now
        removed: list[Path] = []
        candidates = list(self.tmp.iterdir()) if self.tmp.is_dir() else []
        if self.scenes.is_dir():
            candidates += [p for p in self.scenes.glob("*/*/.*.tmp") if _TEMP_RE.match(p.name)]
        for path in candidates:
            try:
                if now - _newest_mtime(path) <= older_than_s:
                    continue
                if path.is_dir() and not path.is_symlink():
                    shutil.rmtree(path)
                else:
                    path.unlink()
                removed.append(path)
            except FileNotFoundError:  # another process swept it first
                continue
        return removed

    def job_dir(self, job_id: str) -> Path:
        return self.jobs / self._check_id(job_id)

    def temp_dir(self) -> Path:
        path = self.tmp / new_id()
        path.mkdir(parents=True)
        return path

    def remove_tree(self, path: Path) -> None:
        """Rename out of sight first (atomic), then delete at leisure."""
        if not path.exists():
            return
        trash = self.tmp / f"trash-{new_id()}"
        os.replace(path, trash)
        shutil.rmtree(trash, ignore_errors=True)


_TEMP_RE = re.compile(r"^\..+\.[0-9a-f]{32}\.tmp$")
"""copy_atomic's temp names: ``.<name>.<uuid hex>.tmp``."""


def _newest_mtime(path: Path) -> float:
    newest = path.lstat().st_mtime
    if path.is_dir() and not path.is_symlink():
        for root, dirs, files in os.walk(path):
            for name in dirs + files:
                try:
                    newest = max(newest, os.lstat(os.path.join(root, name)).st_mtime)
                except FileNotFoundError:
                    pass
    return newest


def fsync_dir(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def copy_atomic(src: Path, dst: Path) -> Path:
    """Copy ``src`` to ``dst`` through a temp file in dst's folder: fsync, rename, fsync dir."""
    dst.parent.mkdir(parents=True, exist_ok=True)
    tmp = dst.with_name(f".{dst.name}.{uuid.uuid4().hex}.tmp")
    try:
        with open(src, "rb") as fin, open(tmp, "wb") as fout:
            shutil.copyfileobj(fin, fout, 1 << 20)
            fout.flush()
            os.fsync(fout.fileno())
        os.replace(tmp, dst)
    finally:
        tmp.unlink(missing_ok=True)
    fsync_dir(dst.parent)
    return dst
