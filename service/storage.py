"""Scene uploads: safe unzip, validation with the library, atomic placement.

A zip from a client is hostile until proven otherwise. Every member name is checked
(relative, no ``..``, no absolute or drive paths, no backslashes, no symlinks, no
encryption, a conservative character set) before anything is written; member count and
total uncompressed size are limited, and the bytes actually inflated are counted as well
(a zip can lie about its sizes). Files land in a temporary directory; only after
``load_scene`` accepted it is the directory renamed into ``scenes/<id>``, so a rejected
upload leaves nothing behind.
"""

from __future__ import annotations

import os
import re
import shutil
import stat
import zipfile
import zlib
from dataclasses import dataclass
from pathlib import Path, PurePosixPath
from typing import BinaryIO

from service.errors import ApiError

_PART_RE = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_.+@=, -]{0,254}$")
"""A path component: starts with a letter, digit or underscore (so never '.', '..' or hidden)."""
MAX_DEPTH = 8
SKIPPED_PREFIXES = ("__MACOSX",)
"""Archiver droppings that are silently left out (never written)."""
_COPY_CHUNK = 1 << 20


@dataclass
class ZipLimits:
    max_files: int
    max_bytes: int


def _reject(message: str) -> ApiError:
    return ApiError(422, "invalid_archive", message)


def _member_parts(info: zipfile.ZipInfo) -> list[str] | None:
    """Validated path components of a member, or None for a member that is skipped."""
    name = info.filename
    if "\\" in name or "\x00" in name:
        raise _reject(f"archive member {name!r}: backslashes and NUL are not allowed in names")
    if name.startswith("/") or re.match(r"^[A-Za-z]:", name):
        raise _reject(f"archive member {name!r}: absolute paths are not allowed")
    parts = [p for p in PurePosixPath(name).parts if p != "."]
    if not parts:
        return None
    if parts[0] in SKIPPED_PREFIXES or any(p.startswith(".") and p not in ("..",) for p in parts):
        return None
    for part in parts:
        if part == "..":
            raise _reject(f"archive member {name!r}: '..' is not allowed")
        if not _PART_RE.match(part):
            raise _reject(
                f"archive member {name!r}: component {part!r} has characters outside "
                "[A-Za-z0-9_.+@=, -] or does not start with a letter, digit or '_'"
            )
    if len(parts) > MAX_DEPTH:
        raise _reject(f"archive member {name!r}: nested deeper than {MAX_DEPTH} folders")
    # Unix file type bits live in the high half of external_attr; 0 means "not recorded"
    # (Python's writestr, DOS archivers): such members are plain files.
    kind = stat.S_IFMT(info.external_attr >> 16)
    if kind == stat.S_IFLNK:
        raise _reject(f"archive member {name!r}: symbolic links are not allowed")
    if kind not in (0, stat.S_IFREG, stat.S_IFDIR):
        raise _reject(f"archive member {name!r}: only regular files and folders are allowed")
    if info.flag_bits & 0x1:
        raise _reject(f"archive member {name!r}: encrypted members are not supported")
    return parts


def extract_scene_zip(source: BinaryIO, dest: Path, limits: ZipLimits) -> Path:
    """Extract a zipped scene folder into ``dest`` (which must be empty) and return the
    scene root: ``dest`` itself, or its single top-level folder when everything sits in one
    (``zip -r lego.zip lego/``)."""
    try:
        archive = zipfile.ZipFile(source)
    except zipfile.BadZipFile as exc:
        raise _reject(f"archive: not a zip file ({exc})") from None
    with archive:
        infos = archive.infolist()
        if len(infos) > limits.max_files:
            raise _reject(f"archive: {len(infos)} members, more than the allowed {limits.max_files}")
        declared = sum(i.file_size for i in infos)
        if declared > limits.max_bytes:
            raise _reject(f"archive: {declared} bytes uncompressed, more than the allowed {limits.max_bytes}")
        plan: list[tuple[zipfile.ZipInfo, list[str]]] = []
        seen: set[str] = set()
        for info in infos:
            parts = _member_parts(info)
            if parts is None:
                continue
            key = "/".join(parts).lower()
            if key in seen:
                raise _reject(f"archive member {info.filename!r}: duplicate name")
            seen.add(key)
            plan.append((info, parts))
        if not any(not info.is_dir() for info, _ in plan):
            raise _reject("archive: contains no files")

        dest.mkdir(parents=True, exist_ok=True)
        written = 0
        for info, parts in plan:
            target = dest.joinpath(*parts)
            # The name checks above already exclude escapes; this is the belt to their braces.
            if not target.resolve().is_relative_to(dest.resolve()):
                raise _reject(f"archive member {info.filename!r}: escapes the scene folder")
            if info.is_dir():
                target.mkdir(parents=True, exist_ok=True)
                continue
            target.parent.mkdir(parents=True, exist_ok=True)
            if target.exists():
                raise _reject(f"archive member {info.filename!r}: a file and a folder share this name")
            try:
                with archive.open(info) as fin, open(target, "xb") as fout:
                    while chunk := fin.read(_COPY_CHUNK):
                        written += len(chunk)
                        if written > limits.max_bytes:
                            raise _reject(
                                f"archive: inflates to more than the allowed {limits.max_bytes} bytes"
                            )
                        fout.write(chunk)
            except (zipfile.BadZipFile, zlib.error, EOFError, NotImplementedError) as exc:
                raise _reject(f"archive member {info.filename!r}: cannot be decompressed ({exc})") from None

    entries = [p for p in dest.iterdir()]
    if len(entries) == 1 and entries[0].is_dir():
        return entries[0]
    return dest


def save_upload(source: BinaryIO, dest: Path, *, max_bytes: int, what: str) -> Path:
    """Copy an uploaded file to ``dest`` (never a client-chosen name), at most ``max_bytes``."""
    written = 0
    with open(dest, "xb") as fout:
        while chunk := source.read(_COPY_CHUNK):
            written += len(chunk)
            if written > max_bytes:
                raise ApiError(413, "payload_too_large", f"{what}: larger than the allowed {max_bytes} bytes")
            fout.write(chunk)
        fout.flush()
        os.fsync(fout.fileno())
    if written == 0:
        raise ApiError(422, "validation_error", f"{what}: the uploaded file is empty")
    return dest


def place(tmp: Path, final: Path) -> None:
    """Move a validated temp directory into place in one rename."""
    final.parent.mkdir(parents=True, exist_ok=True)
    os.replace(tmp, final)


def discard(path: Path) -> None:
    shutil.rmtree(path, ignore_errors=True)
