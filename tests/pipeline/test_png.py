"""The fast decoder of a camera's grey PNG (pipeline.io.png) against libpng, each PNG row filter; the
RGB encoder of the inspection's pictures against libpng and Pillow."""

from __future__ import annotations

import struct
import zlib

import cv2
import numpy as np
import pytest

from pipeline.io.png import PngError, decode_grey_into, encode_rgb, write_rgb


def _chunk(kind: bytes, body: bytes) -> bytes:
    return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))


def _paeth(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    a, b, c = (x.astype(np.int32) for x in (a, b, c))
    pa, pb, pc = np.abs(b - c), np.abs(a - c), np.abs(a + b - 2 * c)
    return np.where((pa <= pb) & (pa <= pc), a, np.where(pb <= pc, b, c))


def _png(img: np.ndarray, filters: list[int], colour: int = 0, interlace: int = 0) -> bytes:
    """A PNG of ``img`` (grey, uint8 or uint16) whose row i is filtered with ``filters[i % len]``: an encoder
    written from the PNG specification, independent of the decoder under test."""
    h, w = img.shape
    bpp = img.dtype.itemsize
    rows = img.astype(">u2").view(np.uint8).reshape(h, -1) if bpp == 2 else img.reshape(h, -1)
    out, prev = [], np.zeros(w * bpp, np.uint8)
    for i, row in enumerate(rows):
        kind = filters[i % len(filters)]
        left = np.concatenate([np.zeros(bpp, np.uint8), row[:-bpp]])
        upleft = np.concatenate([np.zeros(bpp, np.uint8), prev[:-bpp]])
        pred = [
            np.zeros_like(row, np.int32),
            left.astype(np.int32),
            prev.astype(np.int32),
            (left.astype(np.int32) + prev) >> 1,
            _paeth(left, prev, upleft),
        ][kind]
        out.append(
            bytes([kind]) + ((row.astype(np.int32) - pred) & 0xFF).astype(np.uint8).tobytes()
        )
        prev = row
    ihdr = struct.pack(">IIBBBBB", w, h, 8 * bpp, colour, 0, 0, interlace)
    data = zlib.compress(b"".join(out), 6)
    # the image data split over two IDAT chunks, as encoders do
    idat = _chunk(b"IDAT", data[: len(data) // 3]) + _chunk(b"IDAT", data[len(data) // 3 :])
    text = _chunk(b"tEXt", b"Software\x00test")
    return b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", ihdr) + text + idat + _chunk(b"IEND", b"")


def _libpng(data: bytes) -> np.ndarray:
    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    assert img is not None
    return img


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
@pytest.mark.parametrize("filters", [[0], [1], [2], [3], [4], [0, 1, 2, 3, 4, 4, 3, 2]])
def test_each_row_filter_decodes_as_libpng_does(dtype: type, filters: list[int]) -> None:
    rng = np.random.default_rng(len(filters) * 7 + filters[0])
    top = np.iinfo(dtype).max
    # smooth image with noise and a few extremes: every byte value and every Paeth branch occur
    y, x = np.mgrid[:37, :53]
    img = (top * (0.5 + 0.4 * np.sin(x / 7.0) * np.cos(y / 5.0))).astype(np.int64)
    img += rng.integers(-top // 20, top // 20, img.shape)
    img[3, 5], img[20, 40] = 0, top
    img = np.clip(img, 0, top).astype(dtype)
    data = _png(img, filters)
    out = np.full(img.shape, np.nan, np.float32)
    got = decode_grey_into(data, out)
    assert got == (8 * np.dtype(dtype).itemsize, int(img.max()))
    np.testing.assert_array_equal(out, img.astype(np.float32))
    np.testing.assert_array_equal(_libpng(data), img)  # the test encoder itself is right


def test_files_written_by_opencv_and_pillow_decode_as_libpng_does(tmp_path) -> None:
    from PIL import Image

    rng = np.random.default_rng(3)
    img16 = rng.integers(0, 4096, (64, 80)).astype(np.uint16)
    img8 = rng.integers(0, 256, (64, 80)).astype(np.uint8)
    files = []
    for img in (img16, img8):
        ok, buf = cv2.imencode(".png", img)
        assert ok
        files.append((buf.tobytes(), img))
    Image.fromarray(img8).save(tmp_path / "p.png", optimize=True)  # adaptive filters per row
    files.append(((tmp_path / "p.png").read_bytes(), img8))
    for data, img in files:
        out = np.empty(img.shape, np.float32)
        assert decode_grey_into(data, out) is not None
        np.testing.assert_array_equal(out, _libpng(data).astype(np.float32))


def test_other_pngs_are_left_to_libpng() -> None:
    img = np.arange(12 * 10, dtype=np.uint8).reshape(12, 10)
    out = np.empty(img.shape, np.float32)
    _, bgr = cv2.imencode(".png", np.dstack([img, img, img]))
    assert decode_grey_into(bgr.tobytes(), out) is None  # colour
    assert decode_grey_into(_png(img, [1], interlace=1), out) is None  # interlaced
    assert decode_grey_into(_png(img, [1]), np.empty((10, 12), np.float32)) is None  # another size


def test_damaged_files_are_refused_with_the_reason() -> None:
    img = np.arange(40 * 30, dtype=np.uint16).reshape(40, 30) * 7
    data = bytearray(_png(img, [1]))
    out = np.empty(img.shape, np.float32)
    at = data.index(b"IDAT") + 10
    flipped = bytes(data[:at]) + bytes([data[at] ^ 0xFF]) + bytes(data[at + 1 :])
    with pytest.raises(PngError, match="CRC"):
        decode_grey_into(flipped, out)
    with pytest.raises(PngError, match="runs past the end"):
        decode_grey_into(bytes(data[: len(data) - 40]), out)
    # a valid chunk whose compressed data is not the image's
    bad = _chunk(b"IHDR", struct.pack(">IIBBBBB", 30, 40, 16, 0, 0, 0, 0)) + _chunk(
        b"IDAT", zlib.compress(b"\x01" * 100)
    )
    with pytest.raises(PngError, match="inflate"):
        decode_grey_into(b"\x89PNG\r\n\x1a\n" + bad + _chunk(b"IEND", b""), out)
    with pytest.raises(PngError, match="filter"):
        rows = b"".join(b"\x07" + b"\x00" * 60 for _ in range(40))
        ihdr = _chunk(b"IHDR", struct.pack(">IIBBBBB", 30, 40, 16, 0, 0, 0, 0))
        decode_grey_into(
            b"\x89PNG\r\n\x1a\n"
            + ihdr
            + _chunk(b"IDAT", zlib.compress(rows))
            + _chunk(b"IEND", b""),
            out,
        )


def test_rgb_images_encode_to_pngs_libpng_and_pillow_read_back(tmp_path) -> None:
    from PIL import Image

    rng = np.random.default_rng(5)
    rgb = rng.integers(0, 256, (37, 53, 3), dtype=np.uint8)
    rgb[10:20] = (128, 128, 128)  # a flat stretch, as off the plate
    bgr = np.ascontiguousarray(rgb[..., ::-1])
    write_rgb(tmp_path / "a.png", bgr[..., ::-1])  # a strided view (copied into the rows)
    np.testing.assert_array_equal(cv2.imread(str(tmp_path / "a.png"))[..., ::-1], rgb)
    with Image.open(tmp_path / "a.png") as im:
        im.verify()  # every chunk's CRC and the image data's Adler-32
    with Image.open(tmp_path / "a.png") as im:
        assert im.mode == "RGB"
        np.testing.assert_array_equal(np.asarray(im), rgb)
    assert (tmp_path / "a.png").read_bytes() == encode_rgb(rgb)
    with pytest.raises(ValueError, match=r"rgb: expected \(H, W, 3\) uint8"):
        encode_rgb(rgb[..., 0])
    with pytest.raises(OSError, match="cannot write the image"):
        write_rgb(tmp_path / "missing" / "a.png", rgb)
