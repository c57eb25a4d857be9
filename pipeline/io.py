"""Reading and writing the project's files: calibrations, capture bundles, targets, results.

Every failure on bad input is an :class:`~pipeline.formats.InputError` naming the
file and the field (``"capture.json: photometric.lights[3].direction: ..."``); the
field is a dotted path into the JSON document, list indices in brackets.

Capture bundles (``plate-capture/1``) are a folder holding ``capture.json`` and
the images it names, or a ``.zip`` of such a folder. A zip is read in memory,
never extracted to disk: every member name, type and size is checked first
(no absolute paths, no ``..``, no symlinks, no encrypted members, no duplicate
names, a total uncompressed size limit and a per-member compression-ratio
limit); only then are the members the capture names read and decoded with
``cv2.imdecode`` from bytes. Images must be PNG or TIFF; their size is read
from the file header and checked against the calibration before decoding, so a
small file claiming a huge image is refused without allocating it.
:func:`read_capture_header` checks a bundle as far as that goes without decoding
any image (capture.json, the calibration, each image's format and size from its
header), for a process that must not hold the images (the web service).
"""

from __future__ import annotations

import json
import math
import os
import posixpath
import re
import stat
import sys
import threading
import types
import zipfile
import zlib
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, Union, get_args, get_origin

import cv2
import numpy as np
import pydantic
from PIL import Image
from pydantic import BaseModel

from .camera import CameraModel, StereoRig
from .formats import (
    CALIBRATION_FORMAT,
    CAPTURE_FORMAT,
    LIGHT_CALIBRATION_FORMAT,
    TARGET_FORMAT,
    CaptureFile,
    InputError,
    LightCalibrationFile,
    StereoCalibrationFile,
    TargetFile,
)
from .lights import CAMERA_HEAD_RADIUS_MM, Lights

#: Default limit on the summed uncompressed size of all members of a capture zip (bytes).
MAX_ZIP_TOTAL_BYTES = 2 * 1024**3
#: Default limit on a zip member's uncompressed / compressed size.
MAX_ZIP_RATIO = 200.0
#: Members smaller than this (uncompressed, bytes) are exempt from the ratio limit:
#: they cannot hurt, and short JSON files compress well.
ZIP_RATIO_EXEMPT_BYTES = 1024**2
#: Mesh file types a ``mesh`` target may name.
MESH_SUFFIXES = (".stl", ".ply", ".obj")
#: Deepest nesting of objects and lists accepted in a JSON file (the formats nest a few levels).
MAX_JSON_DEPTH = 32


@dataclass(frozen=True)
class Capture:
    """A loaded capture bundle (``plate-capture/1``); images as the camera gave them.

    Attributes
    ----------
    plate_id : str
    captured_at : str or None
        ISO 8601 time stamp from the bundle.
    rig : StereoRig
        The calibration the bundle names; ``rig.image_size`` matches every image.
    bit_depth : int
        Significant bits per pixel; every pixel is ``<= 2**bit_depth - 1``.
    lights : pipeline.lights.Lights
        The N lights (distant or point lights), left-camera frame, mm.
    images : (N, H, W) float32
        Photometric images of the left camera, raw counts (distorted, dark not
        subtracted). Colour images are converted to grey on loading.
    dark : (H, W) float32 or None
        Dark frame, raw counts.
    stereo_left, stereo_right : (H, W) float32 or None
        The stereo pair, raw counts.
    working_distance_mm : float or None
    source : Path
        The folder or .zip the bundle was read from.
    """

    plate_id: str
    captured_at: str | None
    rig: StereoRig
    bit_depth: int
    lights: Lights
    images: np.ndarray
    dark: np.ndarray | None
    stereo_left: np.ndarray | None
    stereo_right: np.ndarray | None
    working_distance_mm: float | None
    source: Path

    @property
    def n_lights(self) -> int:
        return self.lights.n

    @property
    def light_dirs(self) -> np.ndarray:
        """(N, 3) float64 unit directions of distant lights (NaN rows for point lights)."""
        return self.lights.directions

    @property
    def light_intensity(self) -> np.ndarray:
        """(N,) float64 relative intensity ``e_k`` of light k."""
        return self.lights.intensity

    @property
    def has_stereo(self) -> bool:
        return self.stereo_left is not None and self.stereo_right is not None


@dataclass(frozen=True)
class Target:
    """The CAD target of a plate (``plate-target/1``).

    Attributes
    ----------
    shape : {"plane", "cylinder", "sphere", "mesh"}
    radius_mm : float or None
        Cylinder or sphere radius; None for plane and mesh.
    size_mm : (float, float)
        Plate size; a cylinder's axis runs along the second size axis.
    tolerance_mm : float
        Allowed absolute deviation.
    mesh_vertices_mm : (V, 3) float64 or None
        For ``mesh``: vertices in the target's own frame, mm.
    mesh_faces : (F, 3) int64 or None
    source : Path or None
    """

    shape: str
    radius_mm: float | None
    size_mm: tuple[float, float]
    tolerance_mm: float
    mesh_vertices_mm: np.ndarray | None = None
    mesh_faces: np.ndarray | None = None
    source: Path | None = None


# =========================================================================== JSON


def read_json(path, *, label: str | None = None) -> dict:
    """Read a JSON file that must hold one object.

    Parameters
    ----------
    path : str or Path
    label : str, optional
        How error messages name the file (default: the path).

    Returns
    -------
    dict
        The parsed object. ``NaN``/``Infinity`` literals parse (Python's json
        accepts them); the loaders reject non-finite numbers with their field.

    Raises
    ------
    InputError
        Missing, unreadable, empty, not UTF-8, not JSON, or not a JSON object.
    """
    path = Path(path)
    label = str(path) if label is None else label
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise InputError(label, "", "file not found") from None
    except IsADirectoryError:
        raise InputError(label, "", "expected a JSON file, got a folder") from None
    except OSError as exc:
        raise InputError(label, "", f"cannot read: {exc.strerror or exc}") from None
    return _parse_json(data, label)


def _parse_json(data: bytes, label: str) -> dict:
    if not data.strip():
        raise InputError(label, "", "file is empty, expected a JSON object")
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise InputError(label, "", f"not UTF-8 text (byte {exc.start})") from None
    try:
        doc = json.loads(text, parse_int=_parse_int)
    except json.JSONDecodeError as exc:
        raise InputError(
            label, "", f"not valid JSON: {exc.msg} at line {exc.lineno} column {exc.colno}"
        ) from None
    except RecursionError:
        raise InputError(
            label, "", f"objects and lists nested deeper than {MAX_JSON_DEPTH} levels"
        ) from None
    if not isinstance(doc, dict):
        raise InputError(label, "", f"expected a JSON object, got {_json_type(doc)}")
    _check_json_tree(doc, label)
    return doc


class _LongInteger:
    """Stands in for an integer literal too long for Python to convert (found with its field after parsing)."""

    def __init__(self, digits: int) -> None:
        self.digits = digits


def _parse_int(literal: str):
    try:
        return int(literal)
    except ValueError:  # more digits than sys.get_int_max_str_digits()
        return _LongInteger(len(literal.lstrip("-")))


def _check_json_tree(doc: dict, label: str) -> None:
    """Refuse nesting deeper than :data:`MAX_JSON_DEPTH` and over-long integers, naming the field.

    Walks the tree without recursion, so no document can exhaust the stack here.
    """
    stack: list[tuple[Any, str, int]] = [(doc, "", 1)]
    while stack:
        value, field, depth = stack.pop()
        if isinstance(value, _LongInteger):
            limit = sys.get_int_max_str_digits()
            raise InputError(
                label,
                field,
                f"expected a number of at most {limit} digits, got one of {value.digits}",
            )
        if isinstance(value, dict):
            items = [(f"{field}.{key}" if field else str(key), item) for key, item in value.items()]
        elif isinstance(value, list):
            items = [(f"{field}[{i}]", item) for i, item in enumerate(value)]
        else:
            continue
        if depth > MAX_JSON_DEPTH:
            raise InputError(
                label, field, f"objects and lists nested deeper than {MAX_JSON_DEPTH} levels"
            )
        stack.extend((item, name, depth + 1) for name, item in items)


def _json_type(value) -> str:
    if value is None:
        return "null"
    names = {
        bool: "a boolean",
        int: "a number",
        float: "a number",
        str: "a string",
        list: "a list",
        dict: "an object",
    }
    return names.get(type(value), type(value).__name__)


def _reject_non_finite(value, label: str, field: str = "") -> None:
    """Raise on the first NaN/Infinity anywhere in a parsed JSON document."""
    if isinstance(value, float) and not math.isfinite(value):
        raise InputError(label, field, f"expected a finite number, got {value}")
    if isinstance(value, dict):
        for key, item in value.items():
            _reject_non_finite(item, label, f"{field}.{key}" if field else str(key))
    elif isinstance(value, (list, tuple)):
        for i, item in enumerate(value):
            _reject_non_finite(item, label, f"{field}[{i}]")


# =========================================================================== validation errors


def _unwrap(tp):
    """Strip ``Annotated[...]`` and ``X | None`` down to the type pydantic walks into."""
    while True:
        origin = get_origin(tp)
        if origin is Annotated:
            tp = get_args(tp)[0]
            continue
        if origin in (Union, types.UnionType):
            args = [a for a in get_args(tp) if a is not type(None)]
            if len(args) == 1:
                tp = args[0]
                continue
        return tp


def _is_model(tp) -> bool:
    return isinstance(tp, type) and issubclass(tp, BaseModel)


def _union_member(members, tag):
    """The member of a union that pydantic's loc element ``tag`` names (class name or discriminator)."""
    for member in members:
        member = _unwrap(member)
        if getattr(member, "__name__", None) == tag:
            return member
        if (
            _is_model(member)
            and "type" in member.model_fields
            and tag in get_args(_unwrap(member.model_fields["type"].annotation))
        ):
            return member
    return None


def _walk_loc(model, loc) -> tuple[str, Any, Any]:
    """Dotted field path of a pydantic error ``loc``; union branch tags are dropped.

    Returns ``(field, type at the end of loc, type holding the last element)``.
    """
    parts: list[str] = []
    tp, parent = model, None
    for item in loc:
        tp = _unwrap(tp)
        if isinstance(item, int):
            parts.append(f"[{item}]")
            args = get_args(tp)
            parent, tp = tp, (args[0] if get_origin(tp) is list and args else None)
            continue
        if _is_model(tp) and item in tp.model_fields:
            parts.append(f".{item}" if parts else item)
            parent, tp = tp, tp.model_fields[item].annotation
            continue
        if get_origin(tp) in (Union, types.UnionType):
            member = _union_member(get_args(tp), item)
            if member is not None:
                tp = member
                continue
        parts.append(f".{item}" if parts else str(item))
        parent, tp = tp, None
    return "".join(parts), _unwrap(tp) if tp is not None else None, parent


def _short(value, limit: int = 60) -> str:
    text = (
        json.dumps(value)
        if isinstance(value, (dict, list, str, int, float, bool, type(None)))
        else repr(value)
    )
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _describe_error(model, err: dict) -> tuple[str, str]:
    field, end_tp, parent = _walk_loc(model, err["loc"])
    kind = err["type"]
    ctx = err.get("ctx") or {}
    if kind == "missing":
        return field, "missing required key"
    if kind == "extra_forbidden":
        allowed = ", ".join(parent.model_fields) if _is_model(parent) else "?"
        return field, f"unknown key (allowed here: {allowed})"
    if kind == "literal_error":
        return field, f"expected {ctx.get('expected')}, got {_short(err.get('input'))}"
    if kind == "union_tag_invalid":
        key, tag = ctx.get("discriminator", "type"), ctx.get("tag")
        return field, f"unknown {key} {tag!r}, expected one of {ctx.get('expected_tags')}"
    if kind == "value_error":
        reason = str(ctx["error"]) if "error" in ctx else err["msg"].removeprefix("Value error, ")
        # A model-level check names the key it is about: "lights: expected ...".
        m = re.match(r"^(\w+): (.*)$", reason)
        if m and _is_model(end_tp) and m.group(1) in end_tp.model_fields:
            field = f"{field}.{m.group(1)}" if field else m.group(1)
            reason = m.group(2)
        return field, reason
    reason = err["msg"]
    if "input" in err and kind not in ("missing",):
        reason += f", got {_short(err['input'])}"
    return field, reason


def _validate(model, doc: dict, *, label: str, expected_format: str, prefix: str = ""):
    """Validate ``doc`` against ``model``; the first problem becomes an InputError."""
    fmt_field = prefix + "format"
    if "format" not in doc:
        raise InputError(label, fmt_field, f"missing required key, expected {expected_format!r}")
    if doc["format"] != expected_format:
        raise InputError(
            label,
            fmt_field,
            f"unknown format {_short(doc['format'])}, expected {expected_format!r}",
        )
    _reject_non_finite(doc, label, prefix.rstrip("."))
    try:
        return model.model_validate(doc)
    except pydantic.ValidationError as exc:
        errors = exc.errors()
        field, reason = _describe_error(model, errors[0])
        if len(errors) > 1:
            more = len(errors) - 1
            reason += f" (and {more} more problem{'s' if more > 1 else ''})"
        raise InputError(label, prefix + field, reason) from None


# =========================================================================== calibration


def load_calibration(source, *, file_label: str | None = None) -> StereoRig:
    """Read a ``stereo-calibration/1`` document into a :class:`StereoRig`.

    Parameters
    ----------
    source : str, Path or dict
        A path to the JSON file, or the parsed object itself.
    file_label : str, optional
        How error messages name the document (default: the path, or
        ``"calibration.json"`` for a dict).

    Returns
    -------
    StereoRig
        ``K`` in pixels, ``dist`` = ``k1 k2 p1 p2 k3``, ``X_right = R X_left + T``
        with ``T`` in mm; ``image_size`` = ``(width, height)`` px; ``rms_px`` and
        ``board`` (``{"inner_corners": [cols, rows], "square_mm": s}``) kept when given.

    Raises
    ------
    InputError
        Unreadable file, unknown format, unknown or missing keys, non-finite
        numbers, a K that is not ``[[fx, s, cx], [0, fy, cy], [0, 0, 1]]``, an R
        that is not a rotation.
    """
    if isinstance(source, dict):
        return _calibration_from_doc(source, label=file_label or "calibration.json")
    if isinstance(source, (str, os.PathLike)):
        label = file_label or str(source)
        return _calibration_from_doc(read_json(source, label=label), label=label)
    raise TypeError(f"source: expected a path or a dict, got {type(source).__name__}")


def _calibration_from_doc(doc: dict, *, label: str, prefix: str = "") -> StereoRig:
    cal = _validate(
        StereoCalibrationFile, doc, label=label, expected_format=CALIBRATION_FORMAT, prefix=prefix
    )
    size = (int(cal.image_size[0]), int(cal.image_size[1]))
    cams = {}
    for side in ("left", "right"):
        intr = getattr(cal, side)
        try:
            cams[side] = CameraModel(K=np.array(intr.K), dist=np.array(intr.dist), image_size=size)
        except ValueError as exc:
            raise _value_error_to_input(exc, label, f"{prefix}{side}") from None
    board = cal.board.model_dump() if cal.board is not None else None
    try:
        return StereoRig(
            left=cams["left"],
            right=cams["right"],
            R=np.array(cal.R),
            T=np.array(cal.T),
            rms_px=cal.rms_px,
            board=board,
        )
    except ValueError as exc:
        raise _value_error_to_input(exc, label, prefix.rstrip(".")) from None


def _value_error_to_input(exc: ValueError, label: str, field: str) -> InputError:
    """``"K: expected ..."`` from a dataclass check -> field ``<field>.K``."""
    m = re.match(r"^(\w+): (.*)$", str(exc))
    if m:
        return InputError(label, f"{field}.{m.group(1)}" if field else m.group(1), m.group(2))
    return InputError(label, field, str(exc))


def calibration_document(rig: StereoRig) -> dict:
    """A :class:`StereoRig` as a ``stereo-calibration/1`` object (inverse of :func:`load_calibration`).

    Parameters
    ----------
    rig : StereoRig

    Returns
    -------
    dict
        JSON-ready (plain floats and lists); ``rms_px`` and ``board`` only when
        the rig has them.
    """
    if not isinstance(rig, StereoRig):
        raise TypeError(f"rig: expected a StereoRig, got {type(rig).__name__}")
    doc: dict = {
        "format": CALIBRATION_FORMAT,
        "image_size": [int(rig.image_size[0]), int(rig.image_size[1])],
        "left": {"K": rig.left.K.tolist(), "dist": rig.left.dist.tolist()},
        "right": {"K": rig.right.K.tolist(), "dist": rig.right.dist.tolist()},
        "R": rig.R.tolist(),
        "T": rig.T.tolist(),
    }
    if rig.rms_px is not None:
        doc["rms_px"] = float(rig.rms_px)
    if rig.board is not None:
        doc["board"] = {
            "inner_corners": [int(v) for v in rig.board["inner_corners"]],
            "square_mm": float(rig.board["square_mm"]),
        }
    return doc


# =========================================================================== bundles


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

    def open(self, rel: str, *, field: str):
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
        where = str(self.path)
        members: dict[str, zipfile.ZipInfo] = {}
        total = 0
        for info in self._zf.infolist():
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

    def open(self, rel: str, *, field: str):
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


def _open_bundle(path: Path, *, max_total_bytes: int, max_ratio: float):
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


# =========================================================================== images


@dataclass(frozen=True)
class _ImageJob:
    rel: str
    field: str
    expected_size: tuple[int, int]  # (width, height)
    what: str  # "photometric image", "dark frame", ...


_PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
_TIFF_MAGICS = (b"II*\x00", b"MM\x00*")


def _header_size(data: bytes) -> tuple[int, int] | None:
    """``(width, height)`` from a PNG's IHDR or a TIFF's first IFD, without decoding; None if unreadable."""
    if data.startswith(_PNG_MAGIC) and len(data) >= 24 and data[12:16] == b"IHDR":
        return int.from_bytes(data[16:20], "big"), int.from_bytes(data[20:24], "big")
    if data[:4] in _TIFF_MAGICS:
        order = "little" if data[:2] == b"II" else "big"
        ifd = int.from_bytes(data[4:8], order)
        if ifd + 2 > len(data):
            return None
        count = int.from_bytes(data[ifd : ifd + 2], order)
        size: dict[int, int] = {}
        for i in range(count):
            entry = data[ifd + 2 + 12 * i : ifd + 14 + 12 * i]
            if len(entry) < 12:
                return None
            tag, kind = int.from_bytes(entry[0:2], order), int.from_bytes(entry[2:4], order)
            if tag in (256, 257):  # ImageWidth, ImageLength: SHORT (3) or LONG (4)
                size[tag] = int.from_bytes(entry[8:10] if kind == 3 else entry[8:12], order)
        return (size[256], size[257]) if len(size) == 2 else None
    return None


def _decode_into(
    data: bytes, job: _ImageJob, out: np.ndarray, *, bit_depth: int, label: str
) -> None:
    """Check one image file's header, decode it, check it, and write it as grey float32 into ``out`` (H, W).

    The size is read from the header first, so a small file claiming a huge
    image is refused before anything is allocated for it.
    """
    name = repr(job.rel)
    if not (data.startswith(_PNG_MAGIC) or data[:4] in _TIFF_MAGICS):
        raise InputError(
            label,
            job.field,
            f"{name}: not a PNG or TIFF file (expected an 8- or 16-bit PNG or TIFF)",
        )
    header = _header_size(data)
    if header is not None and header != job.expected_size:
        ew, eh = job.expected_size
        raise InputError(
            label,
            job.field,
            f"{name} ({job.what}) is {header[0]}x{header[1]} px, expected {ew}x{eh} (calibration image_size, width x height)",
        )
    try:
        img = (
            cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
            if data
            else None
        )
    except cv2.error:
        img = None
    if img is None:
        raise InputError(
            label,
            job.field,
            f"{name}: cannot decode as an image (expected an 8- or 16-bit PNG or TIFF)",
        )
    if img.dtype not in (np.uint8, np.uint16):
        raise InputError(
            label, job.field, f"{name}: expected 8- or 16-bit unsigned pixels, got {img.dtype}"
        )
    if img.ndim == 3 and img.shape[2] == 1:
        img = img[:, :, 0]
    if img.ndim == 3 and img.shape[2] not in (3, 4):
        raise InputError(
            label,
            job.field,
            f"{name}: expected grey, BGR or BGRA pixels, got {img.shape[2]} channels",
        )
    h, w = img.shape[:2]
    if (w, h) != job.expected_size:
        ew, eh = job.expected_size
        raise InputError(
            label,
            job.field,
            f"{name} ({job.what}) is {w}x{h} px, expected {ew}x{eh} (calibration image_size, width x height)",
        )
    file_bits = 8 if img.dtype == np.uint8 else 16
    if bit_depth > file_bits:
        raise InputError(
            label,
            job.field,
            f"{name}: an {file_bits}-bit file cannot hold bit_depth {bit_depth} values",
        )
    limit = 2**bit_depth - 1
    peak = int(img.max())
    if peak > limit:
        raise InputError(
            label,
            job.field,
            f"{name}: pixel value {peak} exceeds {limit} = 2^{bit_depth} - 1 (bit_depth {bit_depth})",
        )
    if img.ndim == 2:
        np.copyto(out, img, casting="unsafe")
    else:
        code = cv2.COLOR_BGR2GRAY if img.shape[2] == 3 else cv2.COLOR_BGRA2GRAY
        cv2.cvtColor(img.astype(np.float32), code, dst=out)


def _load_images(
    bundle, jobs: list[_ImageJob], outs: list[np.ndarray], *, bit_depth: int, workers: int | None
) -> None:
    """Read and decode ``jobs`` into ``outs`` (float32 (H, W) each) in a thread pool.

    The first failure in job order is raised.
    """

    def one(k: int) -> None:
        data = bundle.read(jobs[k].rel, field=jobs[k].field)
        _decode_into(data, jobs[k], outs[k], bit_depth=bit_depth, label=bundle.capture_label)

    n = workers or min(len(jobs), os.cpu_count() or 1)
    if n <= 1:
        for k in range(len(jobs)):
            one(k)
        return
    with ThreadPoolExecutor(max_workers=n) as pool:
        futures = [pool.submit(one, k) for k in range(len(jobs))]
        for fut in futures:
            fut.result()


# =========================================================================== capture


def load_capture(
    path,
    *,
    max_total_bytes: int = MAX_ZIP_TOTAL_BYTES,
    max_ratio: float = MAX_ZIP_RATIO,
    workers: int | None = None,
) -> Capture:
    """Load a ``plate-capture/1`` bundle: a folder holding capture.json, or a .zip of one.

    Parameters
    ----------
    path : str or Path
        The bundle folder (or its ``capture.json``), or a ``.zip`` with
        ``capture.json`` at its root or inside its one top folder.
    max_total_bytes : int
        Zip only: refuse a zip whose members add up to more uncompressed bytes.
    max_ratio : float
        Zip only: refuse a member (over 1 MiB uncompressed) whose uncompressed
        size is more than ``max_ratio`` times its compressed size.
    workers : int, optional
        Decoding threads (default: the number of CPUs).

    Returns
    -------
    Capture
        Images as float32 raw counts (H, W) = the calibration's ``image_size``
        (width, height) reversed; colour images are converted to grey with
        ``cv2.COLOR_BGR2GRAY``, Y = 0.299 R + 0.587 G + 0.114 B (alpha dropped).
        Light directions are normalised to unit length (the file's are within
        ``formats.UNIT_TOLERANCE`` of it).

    Raises
    ------
    InputError
        Any bad input, naming the file and the field: bundle or capture.json
        missing, empty or not JSON; unknown format, unknown or missing keys,
        non-finite numbers; bad light directions or counts; image paths that
        leave the bundle; missing, undecodable or wrongly sized images (photometric,
        dark, stereo); pixels above ``2**bit_depth - 1``; zip members that
        leave the bundle, are links, or break the size limits.

    Notes
    -----
    Zips are read in memory, never extracted: all member names and sizes are
    checked before any member is read.
    """
    if not isinstance(path, (str, os.PathLike)):
        raise TypeError(f"path: expected a path, got {type(path).__name__}")
    if not max_total_bytes > 0:
        raise ValueError(f"max_total_bytes: expected a positive byte count, got {max_total_bytes}")
    if not max_ratio >= 1:
        raise ValueError(f"max_ratio: expected a ratio >= 1, got {max_ratio}")
    path = Path(path)
    bundle = _open_bundle(path, max_total_bytes=max_total_bytes, max_ratio=max_ratio)
    try:
        return _load_capture(bundle, path, workers=workers)
    finally:
        bundle.close()


def _read_capture_json(bundle) -> tuple[CaptureFile, StereoRig, list[tuple[str | None, _ImageJob]]]:
    """capture.json and its calibration, validated; the image files it names, every path checked.

    Returns ``(capture file, rig, [(key, job), ...])``: photometric images first (key None),
    then ``"dark"``, ``"left"``, ``"right"`` when the bundle has them.
    """
    label = bundle.capture_label
    doc = _parse_json(bundle.read("capture.json", field=""), label)

    # The calibration first: a dict or a file name, never the union's error noise.
    cal = doc.get("calibration")
    if isinstance(cal, dict):
        _validate(
            StereoCalibrationFile,
            cal,
            label=label,
            expected_format=CALIBRATION_FORMAT,
            prefix="calibration.",
        )
    elif "calibration" in doc and not isinstance(cal, str):
        raise InputError(
            label,
            "calibration",
            f"expected a file name in the bundle or a calibration object, got {_json_type(cal)}",
        )
    cap = _validate(CaptureFile, doc, label=label, expected_format=CAPTURE_FORMAT)

    if isinstance(cap.calibration, str):
        rel = _check_relative(cap.calibration, label=label, field="calibration")
        cal_label = bundle.label(rel)
        rig = _calibration_from_doc(
            _parse_json(bundle.read(rel, field="calibration"), cal_label), label=cal_label
        )
    else:
        rig = _calibration_from_doc(doc["calibration"], label=label, prefix="calibration.")

    # Every path is checked before any image is read.
    size = rig.image_size
    wanted = [
        (None, name, f"photometric.images[{k}]", size, "photometric image")
        for k, name in enumerate(cap.photometric.images)
    ]
    if cap.photometric.dark is not None:
        wanted.append(("dark", cap.photometric.dark, "photometric.dark", size, "dark frame"))
    if cap.stereo is not None:
        for side in ("left", "right"):
            cam_size = getattr(rig, side).image_size
            wanted.append(
                (
                    side,
                    getattr(cap.stereo, side),
                    f"stereo.{side}",
                    cam_size,
                    f"stereo {side} image",
                )
            )
    return (
        cap,
        rig,
        [
            (key, _ImageJob(_check_relative(name, label=label, field=field), field, sz, what))
            for key, name, field, sz, what in wanted
        ],
    )


def _load_capture(bundle, source: Path, *, workers: int | None) -> Capture:
    label = bundle.capture_label
    cap, rig, wanted = _read_capture_json(bundle)
    size = rig.image_size
    n = len(cap.photometric.images)
    images = np.empty((n, size[1], size[0]), dtype=np.float32)
    named = {
        key: np.empty((job.expected_size[1], job.expected_size[0]), np.float32)
        for key, job in wanted[n:]
    }
    jobs = [job for _, job in wanted]
    _load_images(bundle, jobs, [*images, *named.values()], bit_depth=cap.bit_depth, workers=workers)

    lights = Lights.from_documents(cap.photometric.lights)
    _check_light_positions(lights, rig, cap.working_distance_mm, label=label)
    return Capture(
        plate_id=cap.plate_id,
        captured_at=cap.captured_at,
        rig=rig,
        bit_depth=int(cap.bit_depth),
        lights=lights,
        images=images,
        dark=named.get("dark"),
        stereo_left=named.get("left"),
        stereo_right=named.get("right"),
        working_distance_mm=cap.working_distance_mm,
        source=source,
    )


def _check_light_positions(
    lights: Lights, rig: StereoRig, working_distance_mm: float | None, *, label: str
) -> None:
    """Point lights must lie between the camera head and the plate: not inside the head, not behind the plate."""
    centres = {"left": np.zeros(3), "right": -rig.R.T @ rig.T}
    for k in np.flatnonzero(lights.is_point):
        p = lights.positions_mm[k]
        field = f"photometric.lights[{k}].position_mm"
        for side, c in centres.items():
            if np.linalg.norm(p - c) < CAMERA_HEAD_RADIUS_MM:
                raise InputError(
                    label,
                    field,
                    f"a light {np.linalg.norm(p - c):.0f} mm from the {side} camera's centre is inside the camera head "
                    f"(expected at least {CAMERA_HEAD_RADIUS_MM:.0f} mm; positions are mm in the left camera frame), "
                    f"got {[round(float(v), 1) for v in p]}",
                )
        if working_distance_mm is not None and p[2] >= working_distance_mm:
            raise InputError(
                label,
                field,
                f"a light at z = {p[2]:.0f} mm is behind the plate (working_distance_mm {working_distance_mm:.0f}; "
                f"positions are mm in the left camera frame, z forward), got {[round(float(v), 1) for v in p]}",
            )


# =========================================================================== capture, headers only


class InputLimitError(InputError):
    """Input refused by a limit the caller set (not by the format); ``limit`` names which one.

    Attributes
    ----------
    limit : {"lights", "image_pixels"}
        The parameter of :func:`read_capture_header` that refused the input (``max_<limit>``).
    """

    def __init__(self, file: str, field: str, reason: str, *, limit: str) -> None:
        super().__init__(file, field, reason)
        self.limit = limit


@dataclass(frozen=True)
class ImageHeader:
    """One image file of a capture bundle as its header describes it (nothing decoded).

    Attributes
    ----------
    field : str
        Where capture.json names it: ``"photometric.images[3]"``, ``"photometric.dark"``, ``"stereo.left"``.
    name : str
        Its path in the bundle.
    what : str
        ``"photometric image"``, ``"dark frame"``, ``"stereo left image"``, ...
    width, height : int
        Pixels, from the header.
    """

    field: str
    name: str
    what: str
    width: int
    height: int


@dataclass(frozen=True)
class CaptureHeader:
    """A capture bundle checked as far as that goes without decoding an image (:func:`read_capture_header`).

    Attributes
    ----------
    label : str
        How error messages name the bundle's capture.json (``<bundle.zip>:capture.json``).
    plate_id, captured_at, rig, bit_depth, lights, working_distance_mm
        As in :class:`Capture`.
    images : tuple of ImageHeader
        Every image file the bundle names: photometric images in order, then the dark frame
        and the stereo pair when given.
    """

    label: str
    plate_id: str
    captured_at: str | None
    rig: StereoRig
    bit_depth: int
    lights: Lights
    working_distance_mm: float | None
    images: tuple[ImageHeader, ...]

    @property
    def n_lights(self) -> int:
        return self.lights.n


def read_capture_header(
    path,
    *,
    max_lights: int | None = None,
    max_image_pixels: int | None = None,
    max_total_bytes: int = MAX_ZIP_TOTAL_BYTES,
    max_ratio: float = MAX_ZIP_RATIO,
) -> CaptureHeader:
    """Check a ``plate-capture/1`` bundle without decoding its images.

    Everything :func:`load_capture` checks before it decodes: the zip's members, capture.json
    and the calibration, the lights, every image path; then each image's format and size from
    its header only (Pillow reads the header lazily from the member's stream, so a small file
    claiming a huge image costs nothing). Pixel values are not read: an image that is corrupt
    past its header, or whose pixels exceed ``bit_depth``, is found by :func:`load_capture`.

    Parameters
    ----------
    path : str or Path
        As for :func:`load_capture`.
    max_lights : int, optional
        Refuse more lights (and so photometric images) than this, before any image is opened.
    max_image_pixels : int, optional
        Refuse an image whose header declares more pixels than this.
    max_total_bytes, max_ratio
        As for :func:`load_capture`.

    Returns
    -------
    CaptureHeader

    Raises
    ------
    InputLimitError
        Over ``max_lights`` or ``max_image_pixels`` (names the file and the field; ``limit`` says which).
    InputError
        Anything :func:`load_capture` refuses before decoding: bad zip, capture.json or
        calibration, image paths that leave the bundle or are missing, files that are not PNG
        or TIFF, headers whose size is not the calibration's ``image_size``.
    """
    if not isinstance(path, (str, os.PathLike)):
        raise TypeError(f"path: expected a path, got {type(path).__name__}")
    for name, value in (("max_lights", max_lights), ("max_image_pixels", max_image_pixels)):
        if value is not None and not value >= 1:
            raise ValueError(f"{name}: expected a positive count or None, got {value}")
    path = Path(path)
    bundle = _open_bundle(path, max_total_bytes=max_total_bytes, max_ratio=max_ratio)
    try:
        label = bundle.capture_label
        cap, rig, wanted = _read_capture_json(bundle)
        n = len(cap.photometric.lights)
        if max_lights is not None and n > max_lights:
            raise InputLimitError(
                label,
                "photometric.lights",
                f"{n} lights (and images), more than the limit of {max_lights}",
                limit="lights",
            )
        lights = Lights.from_documents(cap.photometric.lights)
        _check_light_positions(lights, rig, cap.working_distance_mm, label=label)
        headers = tuple(
            _image_header(bundle, job, label=label, max_pixels=max_image_pixels)
            for _, job in wanted
        )
    finally:
        bundle.close()
    return CaptureHeader(
        label=label,
        plate_id=cap.plate_id,
        captured_at=cap.captured_at,
        rig=rig,
        bit_depth=int(cap.bit_depth),
        lights=lights,
        working_distance_mm=cap.working_distance_mm,
        images=headers,
    )


def _image_header(bundle, job: _ImageJob, *, label: str, max_pixels: int | None) -> ImageHeader:
    """Format and size of one image from its header (Pillow's lazy open); nothing is decoded."""
    name = repr(job.rel)
    with bundle.open(job.rel, field=job.field) as fh:
        try:
            with Image.open(fh, formats=("PNG", "TIFF")) as img:
                width, height = img.size
        except Image.DecompressionBombError:
            bomb = 2 * Image.MAX_IMAGE_PIXELS  # Pillow refuses to open more
            raise InputError(
                label,
                job.field,
                f"{name} ({job.what}): its header declares more than {bomb} px (a decompression bomb?)",
            ) from None
        except Image.UnidentifiedImageError:
            raise InputError(
                label,
                job.field,
                f"{name}: not a PNG or TIFF file (expected an 8- or 16-bit PNG or TIFF)",
            ) from None
        except Exception as exc:
            raise InputError(
                label, job.field, f"{name}: cannot read the image header: {exc}"
            ) from None
    if (width, height) != job.expected_size:
        ew, eh = job.expected_size
        raise InputError(
            label,
            job.field,
            f"{name} ({job.what}) is {width}x{height} px, expected {ew}x{eh} (calibration image_size, width x height)",
        )
    if max_pixels is not None and width * height > max_pixels:
        raise InputLimitError(
            label,
            job.field,
            f"{name} ({job.what}) is {width}x{height} px = {width * height} px, more than the limit of {max_pixels} px",
            limit="image_pixels",
        )
    return ImageHeader(field=job.field, name=job.rel, what=job.what, width=width, height=height)


# =========================================================================== light calibration


def load_light_calibration(source, *, file_label: str | None = None) -> tuple[Lights, float | None]:
    """Read a ``light-calibration/1`` document.

    Parameters
    ----------
    source : str, Path or dict
        A path to the JSON file, or the parsed object itself.
    file_label : str, optional
        How error messages name the document.

    Returns
    -------
    (Lights, rms)
        The calibrated point lights in image order (left-camera frame, mm) and the fit's
        residual (None when the file does not give it).

    Raises
    ------
    InputError
        Unreadable file, unknown format, unknown or missing keys, non-finite numbers, an axis that
        is not a unit vector, a negative mu, fewer than 3 lights.
    """
    if isinstance(source, dict):
        label, doc = file_label or "lights.json", source
    elif isinstance(source, (str, os.PathLike)):
        label = file_label or str(source)
        doc = read_json(source, label=label)
    else:
        raise TypeError(f"source: expected a path or a dict, got {type(source).__name__}")
    cal = _validate(
        LightCalibrationFile, doc, label=label, expected_format=LIGHT_CALIBRATION_FORMAT
    )
    return Lights.from_documents(cal.lights), cal.rms


def light_calibration_document(lights: Lights, rms: float | None) -> dict:
    """Point lights as a ``light-calibration/1`` object (inverse of :func:`load_light_calibration`)."""
    if not lights.is_point.all():
        raise ValueError("lights: a light calibration holds point lights only, got distant ones")
    doc = {
        "format": LIGHT_CALIBRATION_FORMAT,
        "lights": [],
        "rms": None if rms is None else float(rms),
    }
    for k in range(lights.n):
        axis = lights.axes[k] if np.isfinite(lights.axes[k]).all() else np.array([0.0, 0.0, 1.0])
        doc["lights"].append(
            {
                "position_mm": [float(v) for v in lights.positions_mm[k]],
                "axis": [float(v) for v in axis],
                "mu": float(lights.mu[k]),
                "intensity": float(lights.intensity[k]),
            }
        )
    if rms is None:
        doc.pop("rms")
    LightCalibrationFile.model_validate(doc)
    return doc


# =========================================================================== target


def load_target(source, *, base_dir=None, file_label: str | None = None) -> Target:
    """Read a ``plate-target/1`` document.

    Parameters
    ----------
    source : str, Path or dict
        A path to target.json, or the parsed object.
    base_dir : str or Path, optional
        Folder that a ``mesh`` shape's ``file`` is relative to (default: the
        folder of ``source`` when it is a path; required for a mesh given as a dict).
    file_label : str, optional
        How error messages name the document (default: the path, or
        ``"target.json"`` for a dict).

    Returns
    -------
    Target
        For ``mesh``: vertices (V, 3) float64 in mm in the target's own frame
        and faces (F, 3) int64, read with trimesh (STL, PLY or OBJ; several
        bodies are concatenated).

    Raises
    ------
    InputError
        Unreadable file, unknown format or shape type, unknown or missing keys,
        non-finite or non-positive sizes; a mesh file that is missing, leaves
        ``base_dir``, has an unknown type, cannot be read, or holds no triangles.
    """
    if isinstance(source, dict):
        doc, label, src = source, file_label or "target.json", None
    elif isinstance(source, (str, os.PathLike)):
        src = Path(source)
        label = file_label or str(src)
        doc = read_json(src, label=label)
        if base_dir is None:
            base_dir = src.parent
    else:
        raise TypeError(f"source: expected a path or a dict, got {type(source).__name__}")
    tgt = _validate(TargetFile, doc, label=label, expected_format=TARGET_FORMAT)
    shape = tgt.shape
    vertices = faces = None
    if shape.type == "mesh":
        if base_dir is None:
            reason = f"{shape.file!r}: a target given as an object needs base_dir to find its mesh"
            raise InputError(label, "shape.file", reason)
        vertices, faces = _load_mesh(Path(base_dir), shape.file, label=label)
    return Target(
        shape=shape.type,
        radius_mm=float(shape.radius_mm) if shape.type in ("cylinder", "sphere") else None,
        size_mm=(float(tgt.size_mm[0]), float(tgt.size_mm[1])),
        tolerance_mm=float(tgt.tolerance_mm),
        mesh_vertices_mm=vertices,
        mesh_faces=faces,
        source=src,
    )


def _load_mesh(base_dir: Path, name: str, *, label: str) -> tuple[np.ndarray, np.ndarray]:
    import trimesh

    field = "shape.file"
    rel = _check_relative(name, label=label, field=field)
    suffix = Path(rel).suffix.lower()
    if suffix not in MESH_SUFFIXES:
        raise InputError(
            label,
            field,
            f"{name!r}: expected an STL, PLY or OBJ file, got {suffix or 'no extension'!r}",
        )
    path = base_dir / rel
    if not path.resolve().is_relative_to(base_dir.resolve()):
        raise InputError(label, field, f"{name!r} leaves the target's folder (through a symlink)")
    if not path.is_file():
        raise InputError(label, field, f"{name!r}: file not found in {base_dir}")
    try:
        mesh = trimesh.load(path, force="mesh", process=False)
    except Exception as exc:  # trimesh raises many types on bad files
        raise InputError(label, field, f"{name!r}: cannot read the mesh: {exc}") from None
    vertices = np.asarray(getattr(mesh, "vertices", np.empty((0, 3))), dtype=np.float64)
    faces = np.asarray(getattr(mesh, "faces", np.empty((0, 3))), dtype=np.int64)
    if faces.ndim != 2 or faces.shape[0] == 0 or faces.shape[1] != 3:
        count = faces.shape[0] if faces.ndim == 2 else 0
        raise InputError(label, field, f"{name!r}: expected a triangle mesh, got {count} triangles")
    if not np.all(np.isfinite(vertices)):
        raise InputError(label, field, f"{name!r}: vertices hold non-finite coordinates")
    return vertices, faces


__all__ = [
    "Capture",
    "CaptureHeader",
    "ImageHeader",
    "InputError",
    "InputLimitError",
    "Target",
    "calibration_document",
    "load_calibration",
    "load_capture",
    "load_target",
    "read_capture_header",
    "read_json",
]
