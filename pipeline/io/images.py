"""Image decoding: PNG and TIFF, sizes from their headers before any pixel is decoded."""

from __future__ import annotations

import os
from collections.abc import Mapping
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import TYPE_CHECKING, Literal

import cv2
import numpy as np

from ..formats import (
    InputError,
)
from .png import PNG_SIGNATURE, PngError, decode_grey_into

if TYPE_CHECKING:
    from .bundle import _Bundle


@dataclass(frozen=True)
class _ImageJob:
    rel: str
    field: str
    expected_size: tuple[int, int]  # (width, height)
    what: str  # "photometric image", "dark frame", ...


_TIFF_MAGICS = (b"II*\x00", b"MM\x00*")


def _header_size(data: bytes) -> tuple[int, int] | None:
    """``(width, height)`` from a PNG's IHDR or a TIFF's first IFD, without decoding; None if unreadable."""
    if data.startswith(PNG_SIGNATURE) and len(data) >= 24 and data[12:16] == b"IHDR":
        return int.from_bytes(data[16:20], "big"), int.from_bytes(data[20:24], "big")
    if data[:4] in _TIFF_MAGICS:
        order: Literal["little", "big"] = "little" if data[:2] == b"II" else "big"
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
    if not (data.startswith(PNG_SIGNATURE) or data[:4] in _TIFF_MAGICS):
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
        # a camera's grey PNG: decoded straight into ``out`` (pipeline.io.png); any other: libpng
        decoded = decode_grey_into(data, out) if data.startswith(PNG_SIGNATURE) else None
    except PngError as err:
        raise InputError(label, job.field, f"{name}: cannot decode as a PNG: {err}") from err
    if decoded is not None:
        _check_bits(*decoded, job, bit_depth=bit_depth, label=label)
        return
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
    _store(img, job, out, bit_depth=bit_depth, label=label)


def _store(img: np.ndarray, job: _ImageJob, out: np.ndarray, *, bit_depth: int, label: str) -> None:
    """Check one image's pixels (a decoded file, or a frame as the camera gave it) and write it as
    grey float32 into ``out`` (H, W)."""
    name = repr(job.rel)
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
    _check_bits(
        8 if img.dtype == np.uint8 else 16, int(img.max()), job, bit_depth=bit_depth, label=label
    )
    if img.ndim == 2:
        np.copyto(out, img, casting="unsafe")
    else:
        code = cv2.COLOR_BGR2GRAY if img.shape[2] == 3 else cv2.COLOR_BGRA2GRAY
        cv2.cvtColor(img.astype(np.float32), code, dst=out)


def _check_bits(file_bits: int, peak: int, job: _ImageJob, *, bit_depth: int, label: str) -> None:
    """An image of ``file_bits`` bits whose brightest pixel is ``peak`` checked against the capture's
    ``bit_depth``."""
    name = repr(job.rel)
    if bit_depth > file_bits:
        raise InputError(
            label,
            job.field,
            f"{name}: an {file_bits}-bit file cannot hold bit_depth {bit_depth} values",
        )
    limit = 2**bit_depth - 1
    if peak > limit:
        raise InputError(
            label,
            job.field,
            f"{name}: pixel value {peak} exceeds {limit} = 2^{bit_depth} - 1 (bit_depth {bit_depth})",
        )


def _load_images(
    bundle: _Bundle,
    jobs: list[_ImageJob],
    outs: list[np.ndarray],
    *,
    bit_depth: int,
    workers: int | None,
    frames: Mapping[str, np.ndarray] | None = None,
) -> None:
    """Read and decode ``jobs`` into ``outs`` (float32 (H, W) each) in a thread pool.

    ``frames``: images already in memory by their bundle path (``ps_00.png``: the frame the camera
    gave, which the file holds losslessly); they are checked as a decoded file is, not read again.
    The first failure in job order is raised.
    """

    def one(k: int) -> None:
        job = jobs[k]
        if frames is not None and job.rel in frames:
            _store(frames[job.rel], job, outs[k], bit_depth=bit_depth, label=bundle.capture_label)
            return
        data = bundle.read(job.rel, field=job.field)
        _decode_into(data, job, outs[k], bit_depth=bit_depth, label=bundle.capture_label)

    n = workers or min(len(jobs), os.cpu_count() or 1)
    if n <= 1:
        for k in range(len(jobs)):
            one(k)
        return
    with ThreadPoolExecutor(max_workers=n) as pool:
        futures = [pool.submit(one, k) for k in range(len(jobs))]
        for fut in futures:
            fut.result()
