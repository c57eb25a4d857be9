"""Request and queue limits: image pixels, lights, simulated size (422); queued jobs (429, Retry-After)."""

from __future__ import annotations

import io
import json
import math
import struct
import zipfile
import zlib

import pytest
from sqlalchemy import func, select

from app.limits import Limits
from app.limits.work import read_capture_header
from app.models import Inspection, Target
from app.settings import Settings
from tests.api.helpers import AUTH, stored_files, target_json, wait_for

SIMULATED_SMALL = {"n_lights": 3, "width": 64, "height": 64}


def _count(client, model, *where) -> int:
    with client.app.state.session_factory() as s:
        return s.scalar(select(func.count()).select_from(model).where(*where))


def _simulated(client, plate_id="P-1", headers=AUTH, **spec):
    return client.post(
        f"/api/v1/plates/{plate_id}/inspections/simulated", json=spec, headers=headers
    )


# ------------------------------------------------------------------ capture bundles built from headers


def _chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))


def png_header_only(width: int, height: int) -> bytes:
    """A 16-bit grey PNG whose header declares ``width`` x ``height`` and whose pixel data is cut short.

    Enough for a header check; decoding it fails.
    """
    ihdr = struct.pack(">IIBBBBB", width, height, 16, 0, 0, 0, 0)
    idat = zlib.compress(b"\0" * 64)
    return (
        b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", ihdr) + _chunk(b"IDAT", idat) + _chunk(b"IEND", b"")
    )


def png_zeros(width: int, height: int) -> bytes:
    """A complete, valid 16-bit grey PNG of zeros: a few kB for millions of pixels."""
    row = b"\0" * (1 + 2 * width)
    packer = zlib.compressobj(9)
    data = b"".join(packer.compress(row) for _ in range(height)) + packer.flush()
    ihdr = struct.pack(">IIBBBBB", width, height, 16, 0, 0, 0, 0)
    return (
        b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", ihdr) + _chunk(b"IDAT", data) + _chunk(b"IEND", b"")
    )


def calibration_doc(width: int, height: int) -> dict:
    """A plausible stereo-calibration/1 for a camera of ``width`` x ``height`` px."""
    f = 1.2 * width
    K = [[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]]
    return {
        "format": "stereo-calibration/1",
        "image_size": [width, height],
        "left": {"K": K, "dist": [0.0] * 5},
        "right": {"K": K, "dist": [0.0] * 5},
        "R": [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
        "T": [-400.0, 0.0, 0.0],
    }


def capture_zip(
    *,
    plate_id: str,
    width: int,
    height: int,
    n_lights: int,
    stereo: bool = True,
    image: bytes | None = None,
) -> bytes:
    """A capture bundle (zip) of ``n_lights`` photometric images (+ a stereo pair) of one size.

    Every image is ``image`` (default: a header-only PNG of that size).
    """
    image = png_header_only(width, height) if image is None else image
    names = [f"img_{k:02d}.png" for k in range(n_lights)]
    tilt = math.radians(45.0)
    lights = [
        {"direction": [math.sin(tilt) * math.cos(a), math.sin(tilt) * math.sin(a), -math.cos(tilt)]}
        for a in (2 * math.pi * k / n_lights for k in range(n_lights))
    ]
    doc = {
        "format": "plate-capture/1",
        "plate_id": plate_id,
        "calibration": calibration_doc(width, height),
        "bit_depth": 16,
        "photometric": {"lights": lights, "images": names},
        "working_distance_mm": 3000.0,
    }
    if stereo:
        doc["stereo"] = {"left": "left.png", "right": "right.png"}
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as zf:
        zf.writestr("capture.json", json.dumps(doc))
        for name in names + (["left.png", "right.png"] if stereo else []):
            zf.writestr(name, image)
    return buf.getvalue()


def _upload(client, plate_id: str, bundle: bytes, *, target: bool = True, headers=AUTH):
    files = {"capture": ("bundle.zip", bundle, "application/zip")}
    if target:
        files["target"] = ("target.json", target_json(), "application/json")
    return client.post(f"/api/v1/plates/{plate_id}/inspections", files=files, headers=headers)


# ------------------------------------------------------------------ defaults


def test_defaults_admit_the_cell_and_name_their_settings():
    limits = Limits.from_settings(Settings(api_token="t"))
    assert limits.max_image_pixels >= 2448 * 2048
    assert limits.max_lights >= 38
    assert limits.max_queued_per_plate >= 8
    assert limits.max_queued >= limits.max_queued_per_plate


def test_defaults_admit_40_images_of_2448x2048_and_38_lights(tmp_path):
    path = tmp_path / "capture.zip"
    path.write_bytes(capture_zip(plate_id="P-CELL", width=2448, height=2048, n_lights=38))
    header = read_capture_header(path, Limits.from_settings(Settings(api_token="t")))
    assert header.n_lights == 38 and len(header.images) == 40
    assert {(im.width, im.height) for im in header.images} == {(2448, 2048)}
    assert [im.field for im in header.images[-2:]] == ["stereo.left", "stereo.right"]


def test_the_cell_capture_is_accepted_from_its_headers(client, settings):
    """The web process checks headers only: images whose pixel data is cut short are accepted here
    (the job decodes them and fails with the reason, see test_image_corrupt_past_its_header_fails_the_job)."""
    r = _upload(
        client, "P-CELL", capture_zip(plate_id="P-CELL", width=2448, height=2048, n_lights=38)
    )
    assert r.status_code == 202, r.text


# ------------------------------------------------------------------ uploads over the limits


def test_huge_declared_images_are_refused_from_their_header(client, settings):
    """The prober's upload: 12 images declaring 4000x4000, a few hundred kB in all (valid PNGs of zeros)."""
    bundle = capture_zip(
        plate_id="P-BIG", width=4000, height=4000, n_lights=12, image=png_zeros(4000, 4000)
    )
    assert len(bundle) < 1_000_000
    before = stored_files(settings.data_dir)
    r = _upload(client, "P-BIG", bundle)
    assert r.status_code == 422, r.text
    body = r.json()
    assert "'img_00.png'" in body["detail"]  # names the image file
    assert "4000x4000 px" in body["detail"]
    assert f"limit of {settings.max_image_pixels} px" in body["detail"]
    assert "PLATE_INSPECT_MAX_IMAGE_PIXELS" in body["detail"]
    assert body["field"] == "capture: photometric.images[0]"
    assert body["file"] == "bundle.zip:capture.json"  # the bundle as the client named it
    assert str(settings.data_dir) not in body["detail"]
    assert _count(client, Inspection) == 0 and stored_files(settings.data_dir) == before


def test_decompression_bomb_header_is_refused_without_decoding(client):
    bomb = png_header_only(100_000, 100_000)  # 10 Gpx declared in 100 bytes
    r = _upload(
        client,
        "P-BOMB",
        capture_zip(plate_id="P-BOMB", width=2448, height=2048, n_lights=3, image=bomb),
    )
    assert r.status_code == 422, r.text
    assert "'img_00.png'" in r.json()["detail"] and "decompression bomb" in r.json()["detail"]
    assert r.json()["field"] == "capture: photometric.images[0]"


def test_image_pixel_limit_is_a_setting(tmp_path):
    path = tmp_path / "capture.zip"
    path.write_bytes(capture_zip(plate_id="P", width=640, height=480, n_lights=3))
    limits = Limits.from_settings(Settings(api_token="t", max_image_pixels=640 * 480))
    assert read_capture_header(path, limits).images[0].width == 640
    tighter = Limits.from_settings(Settings(api_token="t", max_image_pixels=640 * 480 - 1))
    with pytest.raises(ValueError, match="PLATE_INSPECT_MAX_IMAGE_PIXELS"):
        read_capture_header(path, tighter)


def test_too_many_lights_are_refused_before_any_image(tmp_path, client, settings):
    limits = Limits.from_settings(settings)
    n = settings.max_lights + 1
    r = _upload(
        client, "P-LIGHTS", capture_zip(plate_id="P-LIGHTS", width=640, height=480, n_lights=n)
    )
    assert r.status_code == 422, r.text
    body = r.json()
    assert body["field"] == "capture: photometric.lights"
    assert f"{n} lights" in body["detail"] and f"limit of {limits.max_lights}" in body["detail"]
    assert "PLATE_INSPECT_MAX_LIGHTS" in body["detail"]
    # the images are never opened: the same bundle with unreadable images gives the same refusal
    path = tmp_path / "capture.zip"
    path.write_bytes(
        capture_zip(plate_id="P", width=640, height=480, n_lights=n, image=b"not an image")
    )
    with pytest.raises(ValueError, match=r"photometric.lights"):
        read_capture_header(path, limits)


def test_image_corrupt_past_its_header_fails_the_job_with_its_inputs(
    client, settings, consumer_factory
):
    """Accepted from its headers, the bundle is decoded by the job, which fails naming the image."""
    consumer = consumer_factory().start()
    r = _upload(client, "P-CUT", capture_zip(plate_id="P-CUT", width=320, height=256, n_lights=3))
    assert r.status_code == 202, r.text
    body = wait_for(client, r.json()["id"], consumer=consumer)
    assert body["status"] == "error" and body["verdict"] is None
    assert "'img_00.png'" in body["error"] and "cannot decode" in body["error"], body["error"]
    assert not body["error"].startswith("internal error")
    inputs = settings.data_dir / "inspections" / str(body["id"]) / "inputs"
    assert (inputs / "capture.zip").is_file()


def test_calibration_image_size_over_the_limit_is_refused(client, settings):
    doc = calibration_doc(20_000, 20_000)
    r = client.post(
        "/api/v1/calibrations",
        files={"calibration": ("c.json", json.dumps(doc).encode())},
        headers=AUTH,
    )
    assert r.status_code == 422, r.text
    assert r.json()["field"] == "calibration: image_size"
    assert (
        "20000x20000 px" in r.json()["detail"]
        and "PLATE_INSPECT_MAX_IMAGE_PIXELS" in r.json()["detail"]
    )
    ok = calibration_doc(2448, 2048)
    r = client.post(
        "/api/v1/calibrations",
        files={"calibration": ("c.json", json.dumps(ok).encode())},
        headers=AUTH,
    )
    assert r.status_code == 201, r.text


def test_light_calibration_over_the_light_limit_is_refused(client, settings):
    n = settings.max_lights + 1
    lights = [
        {
            "position_mm": [1500.0 * math.cos(a), 1500.0 * math.sin(a), 200.0],
            "axis": [0.0, 0.0, 1.0],
            "mu": 1.0,
            "intensity": 1.0,
        }
        for a in (2 * math.pi * k / n for k in range(n))
    ]
    doc = {"format": "light-calibration/1", "lights": lights}
    r = client.post("/api/v1/light-calibrations", json=doc, headers=AUTH)
    assert r.status_code == 422, r.text
    assert r.json()["field"] == "lights" and "PLATE_INSPECT_MAX_LIGHTS" in r.json()["detail"]
    doc["lights"] = lights[:38]
    assert client.post("/api/v1/light-calibrations", json=doc, headers=AUTH).status_code == 201


# ------------------------------------------------------------------ simulated inspections


def test_simulated_size_and_lights_over_the_limits_are_refused(client, settings):
    r = _simulated(client, width=4096, height=4096, n_lights=64)  # the prober's 10.7 GB render
    assert r.status_code == 422, r.text
    assert r.json()["field"] == "n_lights" and "PLATE_INSPECT_MAX_LIGHTS" in r.json()["detail"]
    r = _simulated(client, width=4096, height=4096)
    assert r.status_code == 422, r.text
    body = r.json()
    assert body["field"] == "width"
    assert (
        "4096x4096 px" in body["detail"]
        and f"limit of {settings.max_simulated_pixels} px" in body["detail"]
    )
    assert "PLATE_INSPECT_MAX_SIMULATED_PIXELS" in body["detail"]
    assert _count(client, Inspection) == 0
    assert _simulated(client, n_lights=38).status_code == 202  # the default size, the cell's lights


# ------------------------------------------------------------------ the queue


def test_a_plate_gets_8_queued_jobs_then_429(client, settings):
    assert settings.max_queued_per_plate == 8
    ids = []
    for seed in range(8):
        r = _simulated(client, "P-Q", seed=seed, **SIMULATED_SMALL)
        assert r.status_code == 202, r.text
        ids.append(r.json()["id"])
    r = _simulated(client, "P-Q", seed=8, **SIMULATED_SMALL)
    assert r.status_code == 429, r.text
    body = r.json()
    assert body["field"] == "plate_id"
    assert (
        "8 inspections waiting" in body["detail"]
        and "PLATE_INSPECT_MAX_QUEUED_PER_PLATE" in body["detail"]
    )
    retry_after = int(r.headers["Retry-After"])
    assert retry_after >= 1
    assert _count(client, Inspection, Inspection.plate_id == "P-Q") == 8
    # another plate is still admitted
    assert _simulated(client, "P-OTHER", **SIMULATED_SMALL).status_code == 202


def test_full_plate_queue_refuses_an_upload_and_stores_nothing(client, settings, bundle_zip):
    for seed in range(settings.max_queued_per_plate):
        assert _simulated(client, "P-100", seed=seed, **SIMULATED_SMALL).status_code == 202
    targets = _count(client, Target)
    before = stored_files(settings.data_dir)
    r = _upload(client, "P-100", bundle_zip)  # with a new target: its files must not stay
    assert r.status_code == 429, r.text
    assert "Retry-After" in r.headers
    assert _count(client, Target) == targets
    assert stored_files(settings.data_dir) == before


def test_whole_queue_cap_is_429_with_retry_after(tmp_path, settings):
    from fastapi.testclient import TestClient

    from app.main import create_app

    capped = settings.model_copy(update={"max_queued": 3})
    app = create_app(capped)
    with TestClient(app) as client:
        for k in range(3):
            assert _simulated(client, f"P-{k}", **SIMULATED_SMALL).status_code == 202
        r = _simulated(client, "P-3", **SIMULATED_SMALL)
        assert r.status_code == 429, r.text
        assert r.json()["field"] is None
        assert (
            "3 inspections are waiting" in r.json()["detail"]
            and "PLATE_INSPECT_MAX_QUEUED" in r.json()["detail"]
        )
        assert int(r.headers["Retry-After"]) >= 1
        assert _count(client, Inspection) == 3
    app.state.engine.dispose()


def test_a_refused_retry_is_admitted_once_the_queue_moves(client, settings, consumer_factory):
    """A 429 is not remembered under the Idempotency-Key: the same request is admitted later."""
    for seed in range(settings.max_queued_per_plate):
        assert _simulated(client, "P-R", seed=seed, **SIMULATED_SMALL).status_code == 202
    headers = {**AUTH, "Idempotency-Key": "mes-retry-1"}
    r = _simulated(client, "P-R", headers=headers, seed=99, **SIMULATED_SMALL)
    assert r.status_code == 429, r.text
    consumer = consumer_factory().start()
    first = client.get("/api/v1/plates/P-R/inspections", params={"limit": 200}).json()["items"][-1][
        "id"
    ]
    wait_for(client, first, statuses=("running", "done", "error"), consumer=consumer)
    r = _simulated(client, "P-R", headers=headers, seed=99, **SIMULATED_SMALL)
    assert r.status_code == 202, r.text
    again = _simulated(client, "P-R", headers=headers, seed=99, **SIMULATED_SMALL)
    assert again.status_code == 202 and again.json() == r.json()
    assert again.headers.get("idempotent-replayed") == "true"
