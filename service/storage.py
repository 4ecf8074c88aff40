"""Scene uploads: safe unzip, validation with the library, atomic placement.

A zip from a client is hostile until proven otherwise. Every member name is checked
(relative, no ``..``, no absolute or drive paths, no backslashes, no symlinks, no
encryption, a conservative character set: letters and digits of any script after NFC
normalisation, combining marks and ``_.+@=, -``; a refused name is answered with a safe name to
rename it to) before anything is written; member count and
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
import unicodedata
import zipfile
import zlib
from dataclasses import dataclass
from pathlib import Path, PurePosixPath
from typing import BinaryIO

from service.errors import ApiError

_PART_RE = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_.+@=, -]{0,254}$")
"""A path component: starts with a letter, digit or underscore (so never '.', '..' or hidden)."""
_PUNCTUATION = "_.+@=, -"
"""Besides letters, digits and combining marks (any script), the characters a name may hold."""
_SAFE_CATEGORIES = ("Lu", "Ll", "Lt", "Lm", "Lo", "Nd", "Mn", "Mc")
"""Unicode letters, decimal digits and the combining marks that belong to them: safe in a file
name. Never accepted: controls and invisible format characters (bidi overrides, zero-width
joiners), separators other than the ASCII space, symbols, private-use and unassigned code points."""
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


def _zip_name(info: zipfile.ZipInfo) -> str:
    """The member's name as its archiver meant it: UTF-8 names written without the UTF-8 flag
    (older archivers) come out of zipfile decoded as cp437 and are decoded again."""
    name = info.filename
    if not info.flag_bits & 0x800 and not name.isascii():
        try:
            name = name.encode("cp437").decode("utf-8")
        except (UnicodeEncodeError, UnicodeDecodeError):
            pass
    return name


def _safe_part(part: str) -> bool:
    """A path component of letters and digits of any script (NFC), marks and :data:`_PUNCTUATION`,
    starting with a letter, digit or '_' (so never '.', '..' or hidden), at most 255 characters."""
    if _PART_RE.match(part):
        return True
    if not 0 < len(part.encode("utf-8")) <= 255:
        return False
    first = unicodedata.category(part[0])
    if not (first in ("Lu", "Ll", "Lt", "Lm", "Lo", "Nd") or part[0] == "_"):
        return False
    return all(c in _PUNCTUATION or unicodedata.category(c) in _SAFE_CATEGORIES for c in part)


def _rename_hint(part: str) -> str:
    """What is wrong with an unsafe component and a safe name to rename it to."""
    bad = []
    for c in part:
        if not (c in _PUNCTUATION or unicodedata.category(c) in _SAFE_CATEGORIES) and c not in bad:
            bad.append(c)
    described = ", ".join(f"U+{ord(c):04X} {unicodedata.name(c, 'unnamed')}" for c in bad[:4])
    suggestion = "".join(c if c in _PUNCTUATION or unicodedata.category(c) in _SAFE_CATEGORIES else "_"
                         for c in part).strip(" ")
    if not suggestion or not _safe_part(suggestion):
        suggestion = "_" + suggestion.lstrip(".-+@=, ")
    why = f"it holds {described}" if bad else "it must start with a letter, digit or '_'"
    return (f"{why}; names may use letters and digits of any script, combining marks and "
            f"'{_PUNCTUATION}': rename it, e.g. to {suggestion!r} (and the same in transforms.json)")


def _member_parts(info: zipfile.ZipInfo) -> list[str] | None:
    """Validated path components of a member (NFC-normalised), or None for a member that is skipped."""
    name = unicodedata.normalize("NFC", _zip_name(info))
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
        if not _safe_part(part):
            raise _reject(f"archive member {name!r}: component {part!r} is not a safe file name: "
                          + _rename_hint(part))
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
            key = "/".join(parts).casefold()
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
