"""Reading calibrations, capture bundles and targets; every bad input named by file and field."""

from __future__ import annotations

import json
import re
import stat
import zipfile
from pathlib import Path

import cv2
import numpy as np
import pytest

from pipeline.camera import StereoRig
from pipeline.formats import InputError, TargetFile
from pipeline.io import (
    Capture,
    Target,
    calibration_document,
    load_calibration,
    load_capture,
    load_target,
    read_json,
)
from tests.pipeline.bundles import (
    DELETE,
    HEIGHT,
    WIDTH,
    calibration_doc,
    light_ring,
    target_doc,
    write_bundle,
    zip_folder,
)
from tests.realdata import DATA_ROOT


def _err(*parts: str) -> str:
    """A regex that finds the given message parts in order (each escaped)."""
    return ".*".join(re.escape(p) for p in parts)


def _set(path: list, value):
    """A ``mutate`` callback that sets ``doc[path[0]][path[1]]... = value``."""

    def mutate(doc):
        node = doc
        for key in path[:-1]:
            node = node[key]
        node[path[-1]] = value

    return mutate


# --------------------------------------------------------------------------- valid bundles


def test_folder_bundle_loads_every_part(tmp_path):
    bundle = write_bundle(tmp_path, n_lights=5)
    cap = load_capture(bundle)
    assert isinstance(cap, Capture)
    assert cap.plate_id == "TEST-P01" and cap.bit_depth == 16 and cap.n_lights == 5
    assert cap.images.shape == (5, HEIGHT, WIDTH) and cap.images.dtype == np.float32
    # Values are the 16-bit counts as written, exactly (float32 holds every uint16).
    raw = cv2.imread(str(bundle / "ps_03.png"), cv2.IMREAD_UNCHANGED)
    np.testing.assert_array_equal(cap.images[3], raw.astype(np.float32))
    np.testing.assert_array_equal(
        cap.dark, cv2.imread(str(bundle / "dark.png"), cv2.IMREAD_UNCHANGED)
    )
    assert cap.stereo_left.shape == cap.stereo_right.shape == (HEIGHT, WIDTH)
    assert cap.has_stereo and cap.working_distance_mm == 1000.0
    np.testing.assert_allclose(np.linalg.norm(cap.light_dirs, axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose(cap.light_dirs, light_ring(5), atol=1e-12)
    np.testing.assert_array_equal(cap.light_intensity, np.ones(5))
    assert isinstance(cap.rig, StereoRig) and cap.rig.image_size == (WIDTH, HEIGHT)
    assert cap.rig.rms_px == 0.25 and cap.rig.board == {"inner_corners": [9, 6], "square_mm": 30.0}
    assert cap.source == bundle


@pytest.mark.parametrize("top_folder", [None, "plate7"])
def test_zip_bundle_equals_folder(tmp_path, top_folder):
    folder = write_bundle(tmp_path, name="f")
    zpath = zip_folder(folder, tmp_path / "b.zip", top_folder=top_folder)
    a, b = load_capture(folder), load_capture(zpath)
    np.testing.assert_array_equal(a.images, b.images)
    np.testing.assert_array_equal(a.stereo_right, b.stereo_right)
    np.testing.assert_array_equal(a.light_dirs, b.light_dirs)
    assert b.source == zpath


def test_capture_json_path_names_its_folder(tmp_path):
    bundle = write_bundle(tmp_path)
    assert load_capture(bundle / "capture.json").source == bundle / "capture.json"
    np.testing.assert_array_equal(
        load_capture(bundle / "capture.json").images, load_capture(bundle).images
    )


def test_optional_parts_may_be_missing(tmp_path):
    cap = load_capture(
        write_bundle(tmp_path, with_dark=False, with_stereo=False, working_distance_mm=DELETE)
    )
    assert (
        cap.dark is None
        and cap.stereo_left is None
        and not cap.has_stereo
        and cap.working_distance_mm is None
    )


def test_inline_calibration_object(tmp_path):
    cap = load_capture(write_bundle(tmp_path, inline_calibration=True))
    assert cap.rig.image_size == (WIDTH, HEIGHT)
    np.testing.assert_array_equal(cap.rig.T, [-100.0, 0.0, 0.0])


def test_eight_bit_bundle(tmp_path):
    cap = load_capture(write_bundle(tmp_path, bit_depth=8))
    assert cap.bit_depth == 8 and 100 < cap.images.max() <= 255


def test_colour_images_become_bt601_grey(tmp_path):
    rng = np.random.default_rng(3)
    bgr = rng.integers(0, 65536, (HEIGHT, WIDTH, 3), dtype=np.uint16)
    bgra = np.dstack([bgr, np.full((HEIGHT, WIDTH), 65535, np.uint16)])
    cap = load_capture(write_bundle(tmp_path, files={"ps_00.png": bgr, "ps_01.png": bgra}))
    b, g, r = (bgr[..., i].astype(np.float64) for i in range(3))
    grey = 0.299 * r + 0.587 * g + 0.114 * b
    # Tolerance: float32 arithmetic inside cvtColor, relative 1e-6 of counts up to 65535.
    np.testing.assert_allclose(cap.images[0], grey, rtol=0, atol=0.1)
    np.testing.assert_allclose(cap.images[1], grey, rtol=0, atol=0.1)


def test_real_diligent_16bit_rgb_frames(tmp_path):
    src = DATA_ROOT / "diligent" / "ball16"
    if not src.is_dir():
        pytest.skip(f"real data folder absent: {src}")
    crops = sorted((src / "images_crop16").glob("*.png"))[:3]
    dirs = np.loadtxt(src / "light_directions.txt")[:3]
    # DiLiGenT: x right, y up, z towards the camera -> ours: flip y and z.
    dirs = dirs * np.array([1.0, -1.0, -1.0])
    raw = [cv2.imread(str(p), cv2.IMREAD_UNCHANGED) for p in crops]
    h, w = raw[0].shape[:2]

    def use_real(doc):
        doc["photometric"] = {
            "lights": [{"direction": d.tolist()} for d in dirs],
            "images": [f"real/{p.name}" for p in crops],
        }

    real = {f"real/{p.name}": p.read_bytes() for p in crops}
    bundle = write_bundle(
        tmp_path,
        width=w,
        height=h,
        n_lights=3,
        with_stereo=False,
        with_dark=False,
        files=real,
        mutate=use_real,
    )
    cap = load_capture(bundle)
    assert cap.images.shape == (3, h, w) and raw[0].dtype == np.uint16 and raw[0].ndim == 3
    for k in range(3):
        expected = cv2.cvtColor(raw[k].astype(np.float32), cv2.COLOR_BGR2GRAY)
        np.testing.assert_array_equal(cap.images[k], expected)


# --------------------------------------------------------------------------- images


def test_missing_image_file(tmp_path):
    bundle = write_bundle(tmp_path, omit=["ps_02.png"])
    with pytest.raises(
        InputError, match=_err("capture.json: photometric.images[2]: 'ps_02.png'", "not found")
    ):
        load_capture(bundle)


def test_corrupt_image(tmp_path):
    good = (write_bundle(tmp_path, name="g") / "ps_01.png").read_bytes()
    mid = len(good) // 2
    flipped = good[:mid] + bytes([good[mid] ^ 0xFF]) + good[mid + 1 :]  # fails its chunk's CRC
    for content in (good[:mid], good[:40] + bytes(200), flipped):
        bundle = write_bundle(tmp_path, name="bad", files={"ps_01.png": content})
        with pytest.raises(
            InputError,
            match=_err("capture.json: photometric.images[1]: 'ps_01.png'", "cannot decode"),
        ):
            load_capture(bundle)
    for content in (b"not an image at all", b""):
        bundle = write_bundle(tmp_path, name="bad", files={"ps_01.png": content})
        with pytest.raises(
            InputError,
            match=_err("capture.json: photometric.images[1]: 'ps_01.png'", "not a PNG or TIFF"),
        ):
            load_capture(bundle)


def test_image_size_differs_from_calibration(tmp_path):
    bundle = write_bundle(tmp_path, files={"ps_03.png": np.zeros((HEIGHT, WIDTH + 2), np.uint16)})
    with pytest.raises(
        InputError,
        match=_err(
            "photometric.images[3]: 'ps_03.png'",
            f"is {WIDTH + 2}x{HEIGHT}",
            f"expected {WIDTH}x{HEIGHT}",
        ),
    ):
        load_capture(bundle)


@pytest.mark.parametrize("ext", [".png", ".tiff"])
def test_huge_image_header_refused_before_decoding(tmp_path, ext, monkeypatch):
    """A small file whose header claims 100000 x 90000 px is refused from the header alone."""
    big = np.zeros((HEIGHT, WIDTH), np.uint16)
    _ok, buf = cv2.imencode(ext, big)
    data = bytearray(buf.tobytes())
    if ext == ".png":
        data[16:24] = (100_000).to_bytes(4, "big") + (90_000).to_bytes(4, "big")
    else:  # little-endian TIFF: patch the ImageWidth / ImageLength entries of IFD 0
        order = "little" if data[:2] == b"II" else "big"
        ifd = int.from_bytes(data[4:8], order)
        for i in range(int.from_bytes(data[ifd : ifd + 2], order)):
            e = ifd + 2 + 12 * i
            tag = int.from_bytes(data[e : e + 2], order)
            if tag in (256, 257):
                data[e + 2 : e + 4] = (4).to_bytes(2, order)  # LONG
                data[e + 8 : e + 12] = (100_000 if tag == 256 else 90_000).to_bytes(4, order)
    bundle = write_bundle(tmp_path, files={"ps_01.png": bytes(data)})
    real_imdecode = cv2.imdecode

    def imdecode(buf, flags):
        if buf.tobytes() == bytes(data):
            pytest.fail("decoded a file whose header is already wrong")
        return real_imdecode(buf, flags)

    monkeypatch.setattr(cv2, "imdecode", imdecode)
    with pytest.raises(
        InputError,
        match=_err("photometric.images[1]: 'ps_01.png'", "is 100000x90000 px", "expected 64x48"),
    ):
        load_capture(bundle, workers=1)


def test_image_of_another_type_refused(tmp_path):
    _ok, jpeg = cv2.imencode(".jpg", np.zeros((HEIGHT, WIDTH), np.uint8))
    bundle = write_bundle(tmp_path, files={"ps_01.png": jpeg.tobytes()})
    with pytest.raises(
        InputError, match=_err("photometric.images[1]: 'ps_01.png': not a PNG or TIFF")
    ):
        load_capture(bundle)


def test_sixteen_bit_tiff_images(tmp_path):
    imgs = {
        f"ps_{k:02d}.tif": np.full((HEIGHT, WIDTH), 1000 * (k + 1), np.uint16) for k in range(4)
    }
    bundle = write_bundle(
        tmp_path, files=imgs, mutate=_set(["photometric", "images"], sorted(imgs))
    )
    cap = load_capture(bundle)
    np.testing.assert_array_equal(cap.images[:, 0, 0], [1000, 2000, 3000, 4000])


def test_dark_frame_of_wrong_size(tmp_path):
    bundle = write_bundle(tmp_path, files={"dark.png": np.zeros((HEIGHT - 1, WIDTH), np.uint16)})
    with pytest.raises(
        InputError,
        match=_err("capture.json: photometric.dark: 'dark.png'", f"expected {WIDTH}x{HEIGHT}"),
    ):
        load_capture(bundle)


@pytest.mark.parametrize("side", ["left", "right"])
def test_stereo_image_of_wrong_size(tmp_path, side):
    bundle = write_bundle(tmp_path, files={f"stereo_{side}.png": np.zeros((20, 30), np.uint16)})
    with pytest.raises(
        InputError, match=_err(f"capture.json: stereo.{side}: 'stereo_{side}.png'", "is 30x20")
    ):
        load_capture(bundle)


def test_pixel_above_bit_depth(tmp_path):
    img = np.full((HEIGHT, WIDTH), 100, np.uint16)
    img[5, 7] = 4100
    bundle = write_bundle(tmp_path, bit_depth=12, files={"ps_01.png": img})
    with pytest.raises(
        InputError, match=_err("photometric.images[1]: 'ps_01.png'", "4100", "4095", "bit_depth 12")
    ):
        load_capture(bundle)


def test_twelve_bit_values_in_16bit_files_load(tmp_path):
    cap = load_capture(write_bundle(tmp_path, bit_depth=12))
    assert cap.bit_depth == 12 and cap.images.max() <= 4095


def test_eight_bit_file_cannot_hold_twelve_bits(tmp_path):
    bundle = write_bundle(
        tmp_path, bit_depth=12, files={"ps_00.png": np.zeros((HEIGHT, WIDTH), np.uint8)}
    )
    with pytest.raises(
        InputError, match=_err("photometric.images[0]: 'ps_00.png'", "8-bit file", "bit_depth 12")
    ):
        load_capture(bundle)


@pytest.mark.parametrize("bad", ["../outside.png", "/etc/hostname", "C:/x.png", "a\\..\\x.png", ""])
def test_image_path_leaving_the_bundle(tmp_path, bad):
    (tmp_path / "outside.png").write_bytes(
        (write_bundle(tmp_path, name="o") / "ps_00.png").read_bytes()
    )
    bundle = write_bundle(tmp_path, mutate=_set(["photometric", "images", 1], bad))
    with pytest.raises(InputError, match=_err("capture.json: photometric.images[1]:")):
        load_capture(bundle)


def test_image_symlink_leaving_the_folder(tmp_path):
    outside = write_bundle(tmp_path, name="o") / "ps_00.png"
    bundle = write_bundle(tmp_path, omit=["ps_02.png"])
    (bundle / "ps_02.png").symlink_to(outside)
    with pytest.raises(
        InputError, match=_err("capture.json: photometric.images[2]: 'ps_02.png' leaves the bundle")
    ):
        load_capture(bundle)


def test_dark_path_leaving_the_bundle(tmp_path):
    bundle = write_bundle(tmp_path, mutate=_set(["photometric", "dark"], "../dark.png"))
    with pytest.raises(
        InputError, match=_err("capture.json: photometric.dark:", "leaves the bundle")
    ):
        load_capture(bundle)


# --------------------------------------------------------------------------- lights


def test_light_count_differs_from_image_count(tmp_path):
    bundle = write_bundle(tmp_path, n_lights=5, mutate=lambda d: d["photometric"]["lights"].pop())
    with pytest.raises(
        InputError, match=_err("capture.json: photometric.lights: expected 5 lights", "got 4")
    ):
        load_capture(bundle)


def test_fewer_than_three_lights(tmp_path):
    bundle = write_bundle(tmp_path, n_lights=2)
    with pytest.raises(
        InputError, match=_err("capture.json: photometric.lights: expected at least 3", "got 2")
    ):
        load_capture(bundle)


@pytest.mark.parametrize(
    ("direction", "problem"),
    [
        ([0.0, 0.0, 0.0], "zero vector"),
        ([0.0, 0.3, -0.7], "unit vector, got length 0.7616"),
        ([float("nan"), 0.0, -1.0], "finite number, got nan"),
        ([0.0, float("inf"), -1.0], "finite number, got inf"),
    ],
)
def test_bad_light_direction(tmp_path, direction, problem):
    bundle = write_bundle(
        tmp_path, mutate=_set(["photometric", "lights", 2, "direction"], direction)
    )
    with pytest.raises(
        InputError, match=_err("capture.json: photometric.lights[2].direction", problem)
    ):
        load_capture(bundle)


def test_bad_light_intensity(tmp_path):
    bundle = write_bundle(tmp_path, mutate=_set(["photometric", "lights", 0, "intensity"], -1.0))
    with pytest.raises(
        InputError, match=_err("capture.json: photometric.lights[0].intensity", "greater than 0")
    ):
        load_capture(bundle)


# --------------------------------------------------------------------------- capture.json


def test_unknown_format(tmp_path):
    bundle = write_bundle(tmp_path, format="plate-capture/2")
    with pytest.raises(
        InputError,
        match=_err("capture.json: format:", "plate-capture/2", "expected 'plate-capture/1'"),
    ):
        load_capture(bundle)


def test_missing_format(tmp_path):
    with pytest.raises(
        InputError, match=_err("capture.json: format: missing", "'plate-capture/1'")
    ):
        load_capture(write_bundle(tmp_path, format=DELETE))


def test_unknown_top_level_key(tmp_path):
    with pytest.raises(InputError, match=_err("capture.json: operator: unknown key", "plate_id")):
        load_capture(write_bundle(tmp_path, operator="Jo"))


def test_unknown_nested_key(tmp_path):
    bundle = write_bundle(tmp_path, mutate=_set(["photometric", "lights", 1, "colour"], "red"))
    with pytest.raises(
        InputError,
        match=_err("capture.json: photometric.lights[1].colour: unknown key", "direction"),
    ):
        load_capture(bundle)


@pytest.mark.parametrize("key", ["plate_id", "bit_depth", "photometric", "calibration"])
def test_missing_required_key(tmp_path, key):
    with pytest.raises(InputError, match=_err(f"capture.json: {key}: missing required key")):
        load_capture(write_bundle(tmp_path, **{key: DELETE}))


def test_missing_nested_required_key(tmp_path):
    bundle = write_bundle(tmp_path, mutate=lambda d: d["photometric"].pop("images"))
    with pytest.raises(
        InputError, match=_err("capture.json: photometric.images: missing required key")
    ):
        load_capture(bundle)


def test_bad_bit_depth(tmp_path):
    with pytest.raises(InputError, match=_err("capture.json: bit_depth:", "got 11")):
        load_capture(write_bundle(tmp_path, bit_depth=11))


@pytest.mark.parametrize(
    ("content", "problem"),
    [
        (b"", "empty"),
        (b"  \n", "empty"),
        (b"{not json", "not valid JSON"),
        (b"[1, 2]", "expected a JSON object, got a list"),
    ],
)
def test_bad_capture_json(tmp_path, content, problem):
    bundle = write_bundle(tmp_path, files={"capture.json": content})
    with pytest.raises(InputError, match=_err("capture.json:", problem)):
        load_capture(bundle)


def test_folder_without_capture_json(tmp_path):
    bundle = write_bundle(tmp_path, omit=["capture.json"])
    with pytest.raises(InputError, match=_err("capture.json: file not found")):
        load_capture(bundle)


def test_not_a_bundle(tmp_path):
    (tmp_path / "x.txt").write_text("hello")
    with pytest.raises(InputError, match=_err("x.txt: expected a capture bundle folder")):
        load_capture(tmp_path / "x.txt")
    with pytest.raises(InputError, match=_err("nope: not found")):
        load_capture(tmp_path / "nope")
    (tmp_path / "y.zip").write_bytes(b"PK not really")
    with pytest.raises(InputError, match=_err("y.zip: not a valid zip")):
        load_capture(tmp_path / "y.zip")


# --------------------------------------------------------------------------- calibration in the bundle


def test_calibration_file_missing_from_bundle(tmp_path):
    bundle = write_bundle(tmp_path, omit=["calibration.json"])
    with pytest.raises(
        InputError, match=_err("capture.json: calibration: 'calibration.json'", "not found")
    ):
        load_capture(bundle)


def test_calibration_file_errors_name_the_calibration_file(tmp_path):
    bad = calibration_doc()
    bad["left"]["dist"] = [0.0, 0.0, 0.0, 0.0]
    bundle = write_bundle(tmp_path, files={"calibration.json": json.dumps(bad).encode()})
    with pytest.raises(InputError, match=_err("calibration.json: left.dist:", "at least 5")):
        load_capture(bundle)


def test_inline_calibration_errors_name_the_field(tmp_path):
    bundle = write_bundle(
        tmp_path,
        inline_calibration=True,
        mutate=_set(["calibration", "R"], [[1, 0, 0], [0, 1, 0], [0, 0, -1]]),
    )
    with pytest.raises(InputError, match=_err("capture.json: calibration.R:", "rotation")):
        load_capture(bundle)
    bundle = write_bundle(
        tmp_path, name="b2", inline_calibration=True, mutate=_set(["calibration", "format"], "x/1")
    )
    with pytest.raises(
        InputError,
        match=_err("capture.json: calibration.format:", "expected 'stereo-calibration/1'"),
    ):
        load_capture(bundle)


def test_calibration_of_wrong_type(tmp_path):
    with pytest.raises(
        InputError, match=_err("capture.json: calibration: expected a file name", "got a number")
    ):
        load_capture(write_bundle(tmp_path, calibration=3))


def test_calibration_path_leaving_the_bundle(tmp_path):
    with pytest.raises(InputError, match=_err("capture.json: calibration:", "leaves the bundle")):
        load_capture(write_bundle(tmp_path, calibration="../calibration.json"))


def test_calibration_image_size_must_match_images(tmp_path):
    cal = calibration_doc(WIDTH, HEIGHT + 8)
    bundle = write_bundle(tmp_path, files={"calibration.json": json.dumps(cal).encode()})
    with pytest.raises(
        InputError,
        match=_err("photometric.images[0]: 'ps_00.png'", f"expected {WIDTH}x{HEIGHT + 8}"),
    ):
        load_capture(bundle)


# --------------------------------------------------------------------------- zips


def _zip_with(tmp_path, extra: zipfile.ZipInfo, content: bytes = b"x") -> Path:
    """A valid bundle zip plus one hostile member appended last."""
    zpath = zip_folder(write_bundle(tmp_path, name="z"), tmp_path / "evil.zip")
    with zipfile.ZipFile(zpath, "a") as zf:
        zf.writestr(extra, content)
    return zpath


@pytest.fixture
def no_member_read(monkeypatch):
    """Call the returned function to fail the test if any zip member is opened from then on."""

    def refuse(self, *args, **kwargs):
        raise AssertionError("a zip member was read before the checks refused the zip")

    return lambda: monkeypatch.setattr(zipfile.ZipFile, "open", refuse)


@pytest.mark.parametrize(
    ("name", "problem"),
    [
        ("../../evil.png", "leaves the bundle"),
        ("ok/../../evil.png", "leaves the bundle"),
        ("..\\evil.png", "leaves the bundle"),
        ("/etc/evil.png", "absolute"),
        ("C:/evil.png", "absolute"),
    ],
)
def test_zip_slip_member_refused_before_reading(tmp_path, no_member_read, name, problem):
    zpath = _zip_with(tmp_path, zipfile.ZipInfo(name))
    no_member_read()
    with pytest.raises(InputError, match=_err("evil.zip: member", repr(name), problem)):
        load_capture(zpath)


def test_zip_symlink_member_refused(tmp_path, no_member_read):
    info = zipfile.ZipInfo("link.png")
    info.create_system = 3
    info.external_attr = (stat.S_IFLNK | 0o777) << 16
    zpath = _zip_with(tmp_path, info, b"/etc/passwd")
    no_member_read()
    with pytest.raises(
        InputError, match=_err("evil.zip: member 'link.png': refused: symbolic link")
    ):
        load_capture(zpath)


def test_zip_total_size_limit(tmp_path, no_member_read):
    zpath = write_bundle(tmp_path, as_zip=True)
    total = sum(i.file_size for i in zipfile.ZipFile(zpath).infolist())
    no_member_read()
    with pytest.raises(
        InputError, match=_err("bundle.zip: refused: uncompressed size exceeds", str(total - 1))
    ):
        load_capture(zpath, max_total_bytes=total - 1)


def test_zip_compression_ratio_limit(tmp_path):
    info = zipfile.ZipInfo("padding.bin")
    info.compress_type = zipfile.ZIP_DEFLATED
    zpath = _zip_with(tmp_path, info, bytes(4 * 1024**2))  # 4 MiB of zeros deflate ~1000:1
    with pytest.raises(
        InputError,
        match=_err("evil.zip: member 'padding.bin': refused: compression ratio", "200:1"),
    ):
        load_capture(zpath)
    # The same bundle is fine when the caller trusts it with a higher ratio.
    assert load_capture(zpath, max_ratio=5000).n_lights == 4


def test_zip_without_capture_json(tmp_path):
    folder = write_bundle(tmp_path)
    (folder / "capture.json").rename(folder / "other.json")
    zpath = zip_folder(folder, tmp_path / "b.zip")
    with pytest.raises(InputError, match=_err("b.zip: capture.json: missing")):
        load_capture(zpath)


def test_zip_with_two_top_folders(tmp_path):
    zpath = zip_folder(write_bundle(tmp_path), tmp_path / "b.zip", top_folder="one")
    with zipfile.ZipFile(zpath, "a") as zf:
        zf.writestr("two/readme.txt", "x")
    with pytest.raises(InputError, match=_err("b.zip: capture.json: missing")):
        load_capture(zpath)


def test_zip_errors_name_the_member(tmp_path):
    zpath = write_bundle(tmp_path, as_zip=True, top_folder="p", omit=["ps_01.png"])
    with pytest.raises(
        InputError,
        match=_err("bundle.zip:p/capture.json: photometric.images[1]: 'ps_01.png'", "not found"),
    ):
        load_capture(zpath)


def test_zip_duplicate_member_refused(tmp_path):
    zpath = write_bundle(tmp_path, as_zip=True)
    with pytest.warns(UserWarning, match="Duplicate name"), zipfile.ZipFile(zpath, "a") as zf:
        zf.writestr("ps_00.png", b"other")
    with pytest.raises(
        InputError, match=_err("bundle.zip: member 'ps_00.png': refused: duplicate")
    ):
        load_capture(zpath)


def test_loader_argument_checks(tmp_path):
    with pytest.raises(ValueError, match=r"max_ratio: expected a ratio >= 1, got 0.5"):
        load_capture(tmp_path, max_ratio=0.5)
    with pytest.raises(ValueError, match="max_total_bytes: expected a positive"):
        load_capture(tmp_path, max_total_bytes=0)
    with pytest.raises(TypeError, match="path: expected a path, got int"):
        load_capture(3)


# --------------------------------------------------------------------------- calibration


def test_calibration_round_trip(tmp_path):
    doc = calibration_doc()
    rig = load_calibration(doc)
    assert calibration_document(rig) == doc
    path = tmp_path / "cal.json"
    path.write_text(json.dumps(calibration_document(rig)))
    again = load_calibration(path)
    np.testing.assert_array_equal(again.left.K, rig.left.K)
    np.testing.assert_array_equal(again.left.dist, rig.left.dist)
    assert again.rms_px == rig.rms_px and again.board == rig.board


def test_calibration_document_without_optional_parts():
    doc = calibration_doc()
    del doc["rms_px"], doc["board"]
    rig = load_calibration(doc)
    assert rig.rms_px is None and rig.board is None
    assert calibration_document(rig) == doc


@pytest.mark.parametrize(
    ("mutate", "field", "problem"),
    [
        (_set(["image_size"], [0, 48]), "image_size", "positive"),
        (_set(["T"], [1.0, 2.0]), "T", "at least 3"),
        (_set(["left", "K", 0, 0], -5.0), "left.K", "fx, fy > 0"),
        (_set(["right", "dist", 4], float("nan")), "right.dist[4]", "finite"),
        (_set(["R"], [[0, 1, 0], [1, 0, 0], [0, 0, 1]]), "R", "rotation"),
        (_set(["board", "square_mm"], 0), "board.square_mm", "greater than 0"),
        (_set(["extra"], 1), "extra", "unknown key"),
        (lambda d: d.pop("right"), "right", "missing required key"),
        (_set(["format"], "stereo-calibration/2"), "format", "expected 'stereo-calibration/1'"),
    ],
)
def test_bad_calibration(tmp_path, mutate, field, problem):
    doc = calibration_doc()
    mutate(doc)
    with pytest.raises(InputError, match=_err(f"my_cal.json: {field}:", problem)):
        load_calibration(doc, file_label="my_cal.json")
    path = tmp_path / "c.json"
    path.write_text(json.dumps(doc))
    with pytest.raises(InputError, match=_err(f"c.json: {field}:", problem)):
        load_calibration(path)
    with pytest.raises(InputError, match=_err(f"upload.json: {field}:", problem)):
        load_calibration(path, file_label="upload.json")


# --------------------------------------------------------------------------- read_json


@pytest.mark.parametrize(
    ("content", "problem"),
    [
        (b"", "file is empty"),
        (b'{"a": }', "not valid JSON"),
        (b"3", "got a number"),
        (b"\xff\xfe{}", "not UTF-8"),
    ],
)
def test_read_json_bad_files(tmp_path, content, problem):
    path = tmp_path / "x.json"
    path.write_bytes(content)
    with pytest.raises(InputError, match=_err("the x file:", problem)):
        read_json(path, label="the x file")


def test_read_json_missing_file(tmp_path):
    with pytest.raises(InputError, match=_err("missing.json: file not found")):
        read_json(tmp_path / "missing.json")


# --------------------------------------------------------------------------- targets


def test_target_shapes(tmp_path):
    cyl = load_target(target_doc())
    assert cyl == Target(
        shape="cylinder", radius_mm=5000.0, size_mm=(3000.0, 3000.0), tolerance_mm=2.0
    )
    plane = load_target(target_doc(shape={"type": "plane"}))
    assert plane.shape == "plane" and plane.radius_mm is None
    path = tmp_path / "t.json"
    path.write_text(json.dumps(target_doc(shape={"type": "sphere", "radius_mm": 8000.0})))
    sph = load_target(path)
    assert sph.shape == "sphere" and sph.radius_mm == 8000.0 and sph.source == path


@pytest.mark.parametrize("suffix", ["stl", "ply", "obj"])
def test_mesh_target(tmp_path, suffix):
    import trimesh

    box = trimesh.creation.box(extents=(3000.0, 2000.0, 10.0))
    box.export(tmp_path / f"plate.{suffix}")
    path = tmp_path / "target.json"
    path.write_text(json.dumps(target_doc(shape={"type": "mesh", "file": f"plate.{suffix}"})))
    tgt = load_target(path)
    assert tgt.shape == "mesh" and tgt.radius_mm is None and tgt.mesh_faces.shape == (12, 3)
    # STL stores one vertex per face corner: compare the coordinate extents, not counts.
    np.testing.assert_allclose(tgt.mesh_vertices_mm.min(axis=0), [-1500.0, -1000.0, -5.0])
    np.testing.assert_allclose(tgt.mesh_vertices_mm.max(axis=0), [1500.0, 1000.0, 5.0])
    as_dict = load_target(json.loads(path.read_text()), base_dir=tmp_path)
    np.testing.assert_array_equal(as_dict.mesh_faces, tgt.mesh_faces)


@pytest.mark.parametrize(
    ("shape", "files", "problem"),
    [
        ({"type": "mesh", "file": "gone.stl"}, {}, "'gone.stl': file not found"),
        ({"type": "mesh", "file": "../plate.stl"}, {}, "leaves the bundle"),
        (
            {"type": "mesh", "file": "plate.step"},
            {"plate.step": b"x"},
            "expected an STL, PLY or OBJ",
        ),
        (
            {"type": "mesh", "file": "plate.stl"},
            {"plate.stl": b"solid x\nendsolid x\n"},
            "plate.stl",
        ),
    ],
)
def test_bad_mesh_target(tmp_path, shape, files, problem):
    for name, content in files.items():
        (tmp_path / name).write_bytes(content)
    path = tmp_path / "target.json"
    path.write_text(json.dumps(target_doc(shape=shape)))
    with pytest.raises(InputError, match=_err("target.json: shape.file:", problem)):
        load_target(path)


def test_target_traceability_is_optional_and_kept():
    """plate-target/1's optional drawing, hull and block (printed on the report)."""
    trace = {"drawing": {"number": "DWG-H77-B21-0042", "revision": "C"}, "hull": "H77"}
    target = load_target(target_doc(**trace, block="B" * 64))
    assert target.shape == "cylinder"
    assert TargetFile.model_validate(target_doc(**trace)).drawing.revision == "C"


def test_mesh_target_as_dict_needs_base_dir():
    with pytest.raises(InputError, match=_err("target.json: shape.file:", "needs base_dir")):
        load_target(target_doc(shape={"type": "mesh", "file": "plate.stl"}))


@pytest.mark.parametrize(
    ("overrides", "field", "problem"),
    [
        ({"shape": {"type": "cone"}}, "shape", "unknown 'type' 'cone'"),
        ({"shape": {"type": "cylinder", "radius_mm": -5.0}}, "shape.radius_mm", "greater than 0"),
        ({"shape": {"type": "cylinder"}}, "shape.radius_mm", "missing required key"),
        ({"shape": {"type": "plane", "radius_mm": 5.0}}, "shape.radius_mm", "unknown key"),
        ({"size_mm": [3000.0, -1.0]}, "size_mm", "positive"),
        ({"tolerance_mm": float("inf")}, "tolerance_mm", "finite"),
        ({"tolerance_mm": DELETE}, "tolerance_mm", "missing required key"),
        ({"format": "plate-target/0"}, "format", "expected 'plate-target/1'"),
        ({"hull": "H" * 65}, "hull", "at most 64 characters"),
        ({"block": " "}, "block", "printable text, not blank"),
        ({"drawing": {"number": "D-1"}}, "drawing.revision", "missing required key"),
        ({"drawing": {"number": "D\n1", "revision": "C"}}, "drawing.number", "printable"),
        ({"drawing": {"number": "D", "revision": "C", "sheet": 2}}, "drawing.sheet", "unknown key"),
        ({"drawing": "DWG-1"}, "drawing", "valid dictionary"),
    ],
)
def test_bad_target(overrides, field, problem):
    with pytest.raises(InputError, match=_err(f"target.json: {field}:", problem)):
        load_target(target_doc(**overrides))
