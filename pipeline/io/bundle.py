"""Capture bundles: a folder, or a zip read in memory after every member is checked."""

from __future__ import annotations

import math
import posixpath
import re
import stat
import threading
import zipfile
import zlib
from pathlib import Path
from typing import IO

from ..formats import (
    InputError,
)
from .validation import _short

MAX_ZIP_TOTAL_BYTES = 2 * 1024**3
#: Default limit on a zip member's uncompressed / compressed size.
MAX_ZIP_RATIO = 200.0
#: Members smaller than this (uncompressed, bytes) are exempt from the ratio limit:
#: they cannot hurt, and short JSON files compress well.
ZIP_RATIO_EXEMPT_BYTES = 1024**2


def _check_relative(name: str, *, label: str, field: str, what: str = "path") -> str:
    """A bundle-relative path: no absolute path, no drive, no ``..``; '/' separators.

    Returns the normalised POSIX path.
    """
    if not isinstance(name, str) or not name:
        raise InputError(label, field, f"expected a non-empty relative {what}, got {_short(name)}")
    if "\x00" in name:
        raise InputError(label, field, f"{what} {_short(name)} contains a NUL character")
    if "\\" in name:
        raise InputError(
            label, field, f"{what} {_short(name)} contains '\\'; use '/' as the separator"
        )
    if name.startswith("/") or re.match(r"^[A-Za-z]:", name):
        raise InputError(
            label,
            field,
            f"{what} {_short(name)} is absolute; expected a path relative to the bundle",
        )
    if ".." in name.split("/"):
        raise InputError(label, field, f"{what} {_short(name)} leaves the bundle ('..')")
    norm = posixpath.normpath(name)
    if norm in (".", ""):
        raise InputError(label, field, f"expected a file {what}, got {_short(name)}")
    return norm


class _FolderBundle:
    def __init__(self, root: Path) -> None:
        self.root = root
        self._real_root = root.resolve()
        self.capture_label = str(root / "capture.json")
        if not (root / "capture.json").is_file():
            raise InputError(
                self.capture_label,
                "",
                "file not found (a capture bundle folder must hold capture.json)",
            )

    def label(self, rel: str) -> str:
        return str(self.root / rel)

    def read(self, rel: str, *, field: str) -> bytes:
        with self.open(rel, field=field) as fh:
            return fh.read()

    def open(self, rel: str, *, field: str) -> IO[bytes]:
        """The file ``rel`` of the bundle as an open binary file."""
        path = self.root / rel
        real = path.resolve()
        if not real.is_relative_to(self._real_root):
            raise InputError(
                self.capture_label, field, f"{rel!r} leaves the bundle folder (through a symlink)"
            )
        try:
            return open(real, "rb")
        except FileNotFoundError:
            raise InputError(
                self.capture_label, field, f"{rel!r}: file not found in the bundle"
            ) from None
        except IsADirectoryError:
            raise InputError(
                self.capture_label, field, f"{rel!r}: expected a file, got a folder"
            ) from None
        except OSError as exc:
            raise InputError(
                self.capture_label, field, f"{rel!r}: cannot read: {exc.strerror or exc}"
            ) from None

    def close(self) -> None:
        pass


class _ZipBundle:
    def __init__(self, path: Path, *, max_total_bytes: int, max_ratio: float) -> None:
        self.path = path
        try:
            self._zf = zipfile.ZipFile(path)
        except zipfile.BadZipFile as exc:
            raise InputError(str(path), "", f"not a valid zip file: {exc}") from None
        except OSError as exc:
            raise InputError(str(path), "", f"cannot read: {exc.strerror or exc}") from None
        try:
            self._members = self._check_members(
                max_total_bytes=max_total_bytes, max_ratio=max_ratio
            )
            self.prefix = self._find_prefix()
        except BaseException:
            self._zf.close()
            raise
        self.capture_label = self.label("capture.json")
        self._lock = threading.Lock()

    def _check_members(
        self, *, max_total_bytes: int, max_ratio: float
    ) -> dict[str, zipfile.ZipInfo]:
        """Check every member before anything is read; the map of file members by name."""
        return check_zip_members(
            self._zf, str(self.path), max_total_bytes=max_total_bytes, max_ratio=max_ratio
        )

    def _find_prefix(self) -> str:
        if "capture.json" in self._members:
            return ""
        names = [n for n in self._members if not n.startswith("__MACOSX/")]
        tops = {n.split("/", 1)[0] for n in names}
        if len(tops) == 1:
            top = tops.pop()
            if f"{top}/capture.json" in self._members:
                return f"{top}/"
        raise InputError(
            str(self.path),
            "capture.json",
            "missing: expected capture.json at the root of the zip or in its one top folder",
        )

    def label(self, rel: str) -> str:
        return f"{self.path}:{self.prefix}{rel}"

    def read(self, rel: str, *, field: str) -> bytes:
        info = self._members.get(self.prefix + rel)
        if info is None:
            raise InputError(self.capture_label, field, f"{rel!r}: file not found in the bundle")
        try:
            with self._lock:
                return self._zf.read(info)
        except (zipfile.BadZipFile, zlib.error, EOFError, NotImplementedError) as exc:
            raise InputError(
                self.capture_label, field, f"{rel!r}: corrupt zip member: {exc}"
            ) from None

    def open(self, rel: str, *, field: str) -> IO[bytes]:
        """The member ``rel`` as a binary stream (decompressed as it is read; seeking forward reads on)."""
        info = self._members.get(self.prefix + rel)
        if info is None:
            raise InputError(self.capture_label, field, f"{rel!r}: file not found in the bundle")
        try:
            return self._zf.open(info)
        except (zipfile.BadZipFile, NotImplementedError) as exc:
            raise InputError(
                self.capture_label, field, f"{rel!r}: corrupt zip member: {exc}"
            ) from None

    def close(self) -> None:
        self._zf.close()


#: An open capture bundle: a folder or a zip.
_Bundle = _FolderBundle | _ZipBundle


def _open_bundle(path: Path, *, max_total_bytes: int, max_ratio: float) -> _Bundle:
    if path.name == "capture.json" and path.is_file():
        return _FolderBundle(path.parent)
    if path.is_dir():
        return _FolderBundle(path)
    if path.is_file() and zipfile.is_zipfile(path):
        return _ZipBundle(path, max_total_bytes=max_total_bytes, max_ratio=max_ratio)
    if not path.exists():
        raise InputError(
            str(path), "", "not found: expected a capture bundle folder or a .zip of one"
        )
    if path.suffix.lower() == ".zip":
        raise InputError(str(path), "", "not a valid zip file")
    raise InputError(
        str(path), "", "expected a capture bundle folder holding capture.json, or a .zip of one"
    )


def check_zip_members(
    zf: zipfile.ZipFile, where: str, *, max_total_bytes: int, max_ratio: float
) -> dict[str, zipfile.ZipInfo]:
    """Every member of a bundle zip checked before anything is read (paths that leave the zip,
    absolute paths, symbolic links, encryption, duplicate names, the uncompressed total and each
    member's compression ratio: :class:`~pipeline.formats.InputError` naming ``where`` and the
    member); the map of its file members by name."""
    members: dict[str, zipfile.ZipInfo] = {}
    total = 0
    for info in zf.infolist():
        name = info.filename
        field = f"member {name!r}"
        # A backslash is no separator in zip names, but one on Windows: treat it as one here.
        if "\\" in name and ".." in re.split(r"[\\/]", name):
            raise InputError(where, field, "refused: the member path leaves the bundle ('..')")
        if name.startswith(("/", "\\")) or re.match(r"^[A-Za-z]:", name):
            raise InputError(where, field, "refused: absolute member path")
        if ".." in name.split("/"):
            raise InputError(where, field, "refused: the member path leaves the bundle ('..')")
        mode = info.external_attr >> 16
        if stat.S_ISLNK(mode):
            raise InputError(where, field, "refused: symbolic link")
        if info.flag_bits & 0x1:
            raise InputError(where, field, "refused: encrypted member")
        if info.is_dir():
            continue
        if name in members:
            raise InputError(where, field, "refused: duplicate member name")
        total += info.file_size
        if total > max_total_bytes:
            raise InputError(
                where,
                "",
                f"refused: uncompressed size exceeds the limit of {max_total_bytes} bytes (zip bomb?)",
            )
        if info.file_size > ZIP_RATIO_EXEMPT_BYTES:
            ratio = info.file_size / info.compress_size if info.compress_size else math.inf
            if ratio > max_ratio:
                raise InputError(
                    where,
                    field,
                    f"refused: compression ratio {ratio:.0f}:1 exceeds the limit of {max_ratio:g}:1 (zip bomb?)",
                )
        members[name] = info
    return members
