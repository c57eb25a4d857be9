"""A camera's PNG decoded fast: 8- or 16-bit grey, not interlaced, straight into float32.

A capture's images are what a machine-vision camera gives: one grey channel of 8 or 16 bits. Decoding
them was the largest single cost of an inspection (libpng through ``cv2.imdecode``: 12 ms for a
1224x1024 16-bit image, two thirds of it zlib's inflate, then a copy into float32). Here libdeflate
inflates the image data (the ``deflate`` package; about twice zlib's speed, the GIL released, the
zlib stream's Adler-32 checked) and one compiled pass undoes the PNG row filters and writes the
pixels as float32, returning the brightest pixel for the bit-depth check (5-6 ms in all).

Every other PNG (colour, palette, alpha, interlaced, 1-4 bits) is left to libpng:
:func:`decode_grey_into` returns None for it. A damaged file (a bad chunk CRC, truncated or corrupt
image data) raises :class:`PngError` with what is wrong.

The inspection's own pictures (deviation.png, normals.png, uncertainty.png: 8-bit RGB) are written by
:func:`write_rgb`: rows without a filter, deflated by libdeflate at level :data:`RGB_LEVEL`. libpng
through ``cv2.imwrite`` took about twice as long for the same pixels (its zlib, and its search for
each row's filter), and the files are of a size.
"""

from __future__ import annotations

import os

import deflate
import numba as nb
import numpy as np

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"

#: Colour type of a grey PNG without alpha (PNG specification, IHDR).
_GREY = 0
#: Colour type of an RGB PNG without alpha.
_RGB = 2
#: libdeflate's compression level for :func:`write_rgb` (1-12): level 2 made the smallest files of
#: the levels as quick as level 1 on the inspection's three pictures.
RGB_LEVEL = 2


class PngError(ValueError):
    """A PNG file that cannot be decoded: its message says what is wrong."""


def decode_grey_into(data: bytes, out: np.ndarray) -> tuple[int, int] | None:
    """Decode a grey 8- or 16-bit, non-interlaced PNG into ``out`` (float32, (H, W), the file's size).

    Returns
    -------
    (bit_depth, peak) : the file's bit depth (8 or 16) and its brightest pixel value, or None when the file
    is another kind of PNG (decode it with libpng) or its size is not ``out``'s.

    Raises
    ------
    PngError
        The file is damaged: a chunk runs past its end or fails its CRC, the image data is missing, does not
        inflate to the size its header gives, or uses an unknown row filter.
    """
    header, idat = _chunks(data)
    width, height, bits, colour, interlace = header
    if colour != _GREY or bits not in (8, 16) or interlace != 0:
        return None
    if out.shape != (height, width) or out.dtype != np.float32:
        return None
    bpp = bits // 8
    size = height * (1 + width * bpp)
    try:
        raw = deflate.zlib_decompress(idat, size)
    except deflate.DeflateError as err:
        raise PngError(
            f"image data does not inflate to the {width}x{height} of its header ({err})"
        ) from err
    if len(raw) != size:
        raise PngError(
            f"image data inflates to {len(raw)} bytes, expected {size} for {width}x{height}"
        )
    peak = _unfilter_into(np.frombuffer(raw, np.uint8), bpp, out)
    if peak < 0:
        raise PngError(f"row {-peak - 1}: unknown filter type (expected 0-4)")
    return bits, int(peak)


def _chunks(data: bytes) -> tuple[tuple[int, int, int, int, int], bytes]:
    """The IHDR fields (width, height, bit depth, colour type, interlace) and the joined IDAT data, each chunk's
    CRC checked; an unknown critical chunk makes the file one for libpng (colour type -1)."""
    if not data.startswith(PNG_SIGNATURE):
        raise PngError("not a PNG file (no PNG signature)")
    pos, parts = len(PNG_SIGNATURE), []
    header: tuple[int, int, int, int, int] | None = None
    view = memoryview(data)
    while pos + 12 <= len(data):
        length = int.from_bytes(data[pos : pos + 4], "big")
        kind = data[pos + 4 : pos + 8]
        end = pos + 12 + length
        if end > len(data):
            raise PngError(f"chunk {kind!r} at byte {pos} runs past the end of the file")
        body = view[pos + 8 : pos + 8 + length]
        if deflate.crc32(body, deflate.crc32(kind)) != int.from_bytes(data[end - 4 : end], "big"):
            raise PngError(f"chunk {kind!r} at byte {pos} fails its CRC (the file is damaged)")
        if kind == b"IHDR" and length == 13:
            b = bytes(body)
            header = (
                int.from_bytes(b[0:4], "big"),
                int.from_bytes(b[4:8], "big"),
                b[8],
                b[9]
                if b[10] == 0 and b[11] == 0
                else -1,  # other compression / filter methods: libpng's
                b[12],
            )
        elif kind == b"IDAT":
            parts.append(body)
        elif kind == b"IEND":
            break
        elif kind[0] & 0x20 == 0 and kind != b"PLTE":  # an unknown critical chunk: libpng decides
            header = (0, 0, 0, -1, 0)
        pos = end
    if header is None:
        raise PngError("no IHDR chunk")
    if not parts:
        raise PngError("no image data (IDAT chunk)")
    return header, b"".join(parts)


@nb.njit(nogil=True, cache=True, inline="always")
def _unfiltered(  # pragma: no cover - compiled
    kind: int, x: np.int32, a: np.int32, b: np.int32, c: np.int32
) -> np.int32:
    """One byte unfiltered: ``x`` filtered, ``a`` the byte one pixel left, ``b`` above, ``c`` above-left
    (unfiltered, 0 outside the image)."""
    if kind == 1:  # Sub
        pred = a
    elif kind == 2:  # Up
        pred = b
    elif kind == 3:  # Average
        pred = (a + b) >> 1
    elif kind == 4:  # Paeth: the neighbour nearest a + b - c
        pa, pb, pc = abs(b - c), abs(a - c), abs(a + b - 2 * c)
        pred = a if pa <= pb and pa <= pc else (b if pb <= pc else c)
    else:  # None
        pred = np.int32(0)
    return np.int32((x + pred) & 0xFF)


@nb.njit(nogil=True, cache=True, inline="always")
def _row(  # pragma: no cover - compiled
    kind: int, raw: np.ndarray, j0: int, bpp: int, prev: np.ndarray, out_row: np.ndarray
) -> int:
    """One row unfiltered (its filter ``kind``, its bytes from ``raw[j0]``) into ``out_row`` and ``prev``
    (the row above, replaced by this one); returns the row's brightest value. Called with ``kind`` a
    constant, so that each filter gets its own loop."""
    peak = np.int32(0)
    a_hi = a_lo = c_hi = c_lo = np.int32(0)
    for x in range(out_row.size):
        j = j0 + x * bpp
        b_hi = prev[x * bpp]
        v = _unfiltered(kind, np.int32(raw[j]), a_hi, b_hi, c_hi)
        prev[x * bpp], a_hi, c_hi = v, v, b_hi
        if bpp == 2:
            b_lo = prev[x * 2 + 1]
            lo = _unfiltered(kind, np.int32(raw[j + 1]), a_lo, b_lo, c_lo)
            prev[x * 2 + 1], a_lo, c_lo = lo, lo, b_lo
            v = (v << 8) | lo
        out_row[x] = v
        peak = max(peak, v)
    return int(peak)


@nb.njit(nogil=True, cache=True)
def _unfilter_into(
    raw: np.ndarray, bpp: int, out: np.ndarray
) -> int:  # pragma: no cover - compiled
    """Undo the PNG row filters of ``raw`` (each row: a filter byte, then ``W * bpp`` bytes; 16-bit samples
    big-endian) into ``out`` (H, W) float32. Returns the brightest value, or ``-(row + 1)`` for a row with
    an unknown filter type.

    The bytes one pixel to the left are carried in registers (``a_hi``, ``a_lo``), not read back from the
    row just written: a filter's chain from pixel to pixel then costs no store-to-load round trip."""
    if bpp == 2:
        return _rows(raw, 2, out)
    return _rows(raw, 1, out)


@nb.njit(nogil=True, cache=True, inline="always")
def _rows(raw: np.ndarray, bpp: int, out: np.ndarray) -> int:  # pragma: no cover - compiled
    """:func:`_unfilter_into` with ``bpp`` a constant: one loop for each filter and sample size."""
    h, w = out.shape
    stride = w * bpp
    prev = np.zeros(stride, np.int32)  # the row above, unfiltered (0 above the first)
    peak = 0
    for i in range(h):
        j0 = i * (stride + 1) + 1
        kind = raw[j0 - 1]
        if kind == 0:
            row_peak = _row(0, raw, j0, bpp, prev, out[i])
        elif kind == 1:
            row_peak = _row(1, raw, j0, bpp, prev, out[i])
        elif kind == 2:
            row_peak = _row(2, raw, j0, bpp, prev, out[i])
        elif kind == 3:
            row_peak = _row(3, raw, j0, bpp, prev, out[i])
        elif kind == 4:
            row_peak = _row(4, raw, j0, bpp, prev, out[i])
        else:
            return -(i + 1)
        peak = max(peak, row_peak)
    return peak


def encode_rgb(rgb: np.ndarray) -> bytes:
    """An 8-bit RGB image (H, W, 3) uint8 as the bytes of a PNG file: one IDAT chunk, every row without
    a filter, libdeflate at :data:`RGB_LEVEL` (a C-contiguous image is copied once, into the rows)."""
    if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
        raise ValueError(f"rgb: expected (H, W, 3) uint8, got {rgb.shape} {rgb.dtype}")
    h, w = rgb.shape[:2]
    rows = np.empty((h, 1 + 3 * w), np.uint8)
    rows[:, 0] = 0  # filter type None
    rows[:, 1:] = rgb.reshape(h, 3 * w)
    # width, height, bit depth, colour type, deflate, adaptive filtering, no interlace
    header = w.to_bytes(4, "big") + h.to_bytes(4, "big") + bytes((8, _RGB, 0, 0, 0))
    return b"".join(
        (
            PNG_SIGNATURE,
            _chunk(b"IHDR", header),
            _chunk(b"IDAT", deflate.zlib_compress(rows, RGB_LEVEL)),
            _chunk(b"IEND", b""),
        )
    )


def write_rgb(path: str | os.PathLike[str], rgb: np.ndarray) -> None:
    """Write :func:`encode_rgb` of ``rgb`` to ``path``; OSError naming the path when it cannot."""
    data = encode_rgb(rgb)
    try:
        with open(path, "wb") as f:
            f.write(data)
    except OSError as err:
        raise OSError(f"{path}: cannot write the image ({err.strerror or err})") from err


def _chunk(kind: bytes, body: bytes | bytearray) -> bytes:
    """One PNG chunk: length, type, data and the CRC of type and data."""
    crc = deflate.crc32(body, deflate.crc32(kind))
    return len(body).to_bytes(4, "big") + kind + body + crc.to_bytes(4, "big")
