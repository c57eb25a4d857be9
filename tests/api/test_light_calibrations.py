"""Light calibrations through the API: upload, refusal, list, current; inspections run with the current one."""

from __future__ import annotations

import io
import json
import zipfile

import numpy as np
import pytest
from sqlalchemy import func, select

from app.models import LightCalibration
from tests.api.helpers import (
    AUTH,
    TOKEN,
    Consumer,
    rezip,
    stored_files,
    target_json,
    wait_for,
    zip_folder,
)

URL = "/api/v1/light-calibrations"
APPLIED = "a light calibration was applied to the capture's nominal light directions"


@pytest.fixture(scope="session")
def near_field(tmp_path_factory):
    """A near-field capture whose manifest gives only nominal light directions (plate NF-1, 12 LEDs
    2.8 m above the plate), zipped; its target; and the true lights as a light-calibration/1 document."""
    from pipeline.io import light_calibration_document
    from pipeline.lights.model import Lights
    from pipeline.simulate import CaptureSpec, PlateSpec, simulate_capture

    folder = tmp_path_factory.mktemp("near-field") / "NF-1"
    simulate_capture(
        folder,
        plate=PlateSpec(),
        capture=CaptureSpec(
            near_field_mm=2800,
            light_elevation_deg=30,
            led_mu=1.5,
            manifest_lights="nominal",
            width=320,
            height=256,
        ),
        plate_id="NF-1",
        seed=0,
    )
    truth = np.load(folder / "truth.npz")
    lights = Lights.points(
        truth["light_positions_mm"],
        truth["light_intensity"],
        axes=truth["light_axes"],
        mu=truth["light_mu"],
    )
    return {
        "zip": zip_folder(folder),
        "target": (folder / "target.json").read_bytes(),
        "lights": light_calibration_document(lights, 0.004),
    }


def _first(document: dict, n: int) -> dict:
    """The document with its first ``n`` lights only (a calibration of another cell)."""
    return dict(document, lights=document["lights"][:n])


def _upload(client, document, *, name="cell-lights.json", headers=AUTH):
    return client.post(URL, files={"calibration": (name, json.dumps(document))}, headers=headers)


def _count(client, model) -> int:
    with client.app.state.session_factory() as s:
        return s.scalar(select(func.count()).select_from(model))


def _post_bundle(client, plate_id, bundle, target=None):
    files = {
        "capture": ("bundle.zip", bundle, "application/zip"),
        "target": ("target.json", target or target_json(), "application/json"),
    }
    return client.post(f"/api/v1/plates/{plate_id}/inspections", files=files, headers=AUTH)


# ------------------------------------------------------------------ upload, list, current


def test_upload_list_and_current(client, settings, near_field):
    assert client.get(f"{URL}/current").status_code == 404
    assert client.get(URL).json() == []

    r = _upload(client, near_field["lights"], name="C:\\cell\\cell-lights.json")
    assert r.status_code == 201, r.text
    first = r.json()
    assert first["file_name"] == "cell-lights.json"  # the client's folders are not kept
    assert first["n_lights"] == 12 and first["rms"] == 0.004
    assert first["document"] == near_field["lights"]
    stored = settings.data_dir / "light-calibrations" / str(first["id"]) / "lights.json"
    assert json.loads(stored.read_text()) == near_field["lights"]
    assert client.get(f"{URL}/current").json()["id"] == first["id"]

    # A JSON body works too, and the newest upload becomes the current one.
    r = client.post(
        URL,
        content=json.dumps(_first(near_field["lights"], 6)),
        headers={**AUTH, "Content-Type": "application/json"},
    )
    assert r.status_code == 201, r.text
    second = r.json()
    assert second["file_name"] is None and second["n_lights"] == 6
    assert client.get(f"{URL}/current").json()["id"] == second["id"]
    assert [c["id"] for c in client.get(URL).json()] == [second["id"], first["id"]]
    assert client.get(f"{URL}/{first['id']}").json()["document"] == near_field["lights"]
    r = client.get(f"{URL}/999")
    assert r.status_code == 404 and r.json()["field"] == "light_calibration_id"

    # A retry with the same Idempotency-Key stores nothing more.
    headers = {**AUTH, "Idempotency-Key": "lights-1"}
    r1 = _upload(client, near_field["lights"], headers=headers)
    r2 = _upload(client, near_field["lights"], headers=headers)
    assert r1.status_code == r2.status_code == 201 and r2.headers["Idempotent-Replayed"] == "true"
    assert r1.json() == r2.json() and _count(client, LightCalibration) == 3


@pytest.mark.parametrize(
    ("mutate", "field"),
    [
        (lambda d: d["lights"][2].update(axis=[0.0, 0.0, 2.0]), "lights[2].axis"),
        (lambda d: d["lights"][0].update(mu=-1.0), "lights[0].mu"),
        (lambda d: d.update(lights=d["lights"][:2]), "lights"),
        (lambda d: d.update(format="stereo-calibration/1"), "format"),
        (lambda d: d.update(extra=1), "extra"),
    ],
)
def test_bad_light_calibration_is_refused_naming_file_and_field(
    client, settings, near_field, mutate, field
):
    document = json.loads(json.dumps(near_field["lights"]))
    mutate(document)
    before = stored_files(settings.data_dir)
    r = _upload(client, document, name="bad-lights.json")
    assert r.status_code == 422, r.text
    body = r.json()
    assert body["file"] == "bad-lights.json" and body["field"] == f"calibration: {field}", body
    assert body["detail"].startswith(f"bad-lights.json: {field}: "), body
    assert str(settings.data_dir) not in body["detail"]
    # the same document as a JSON body: the message names the body
    r = client.post(
        URL, content=json.dumps(document), headers={**AUTH, "Content-Type": "application/json"}
    )
    assert r.status_code == 422 and r.json()["file"] == "body" and r.json()["field"] == field, (
        r.text
    )
    assert _count(client, LightCalibration) == 0 and stored_files(settings.data_dir) == before
    assert client.get(f"{URL}/current").status_code == 404


def test_light_calibration_upload_refusals(client, settings):
    r = client.post(URL, files={"calibration": ("lights.json", b"{not json")}, headers=AUTH)
    assert r.status_code == 422 and r.json()["file"] == "lights.json", r.text
    r = client.post(URL, files={"other": ("lights.json", b"{}")}, headers=AUTH)
    assert r.status_code == 422 and r.json()["field"] == "calibration", r.text
    r = client.post(URL, content=b"format: yaml", headers={**AUTH, "Content-Type": "text/yaml"})
    assert r.status_code == 415 and r.json()["field"] == "Content-Type"
    r = client.post(URL, files={"calibration": ("lights.json", b"{}")})
    assert r.status_code == 401
    assert _count(client, LightCalibration) == 0 and stored_files(settings.data_dir) == []


# ------------------------------------------------------------------ inspections


def _point_light_bundle(bundle: bytes, lights: dict) -> bytes:
    """The bundle with point lights in its manifest (from a light calibration's first lights)."""
    doc = json.loads(zipfile.ZipFile(io.BytesIO(bundle)).read("capture.json"))
    n = len(doc["photometric"]["lights"])
    doc["photometric"]["lights"] = lights["lights"][:n]
    return rezip(bundle, replace={"capture.json": json.dumps(doc).encode()})


def test_inspection_records_the_current_light_calibration_for_nominal_lights(
    client, bundle_zip, near_field
):
    r = _post_bundle(client, "P-100", bundle_zip)
    assert r.status_code == 202, r.text
    assert (
        client.get(f"/api/v1/inspections/{r.json()['id']}").json()["light_calibration_id"] is None
    )

    calibration_id = _upload(client, _first(near_field["lights"], 6)).json()["id"]
    r = _post_bundle(client, "P-100", bundle_zip)  # 6 nominal directions
    assert (
        client.get(f"/api/v1/inspections/{r.json()['id']}").json()["light_calibration_id"]
        == calibration_id
    )

    # A capture that gives point lights keeps them: no calibration is passed.
    r = _post_bundle(client, "P-100", _point_light_bundle(bundle_zip, near_field["lights"]))
    assert r.status_code == 202, r.text
    assert (
        client.get(f"/api/v1/inspections/{r.json()['id']}").json()["light_calibration_id"] is None
    )
    # The simulated cell renders with the lights it writes: no calibration either.
    r = client.post("/api/v1/plates/SIM-1/inspections/simulated", json={}, headers=AUTH)
    assert (
        client.get(f"/api/v1/inspections/{r.json()['id']}").json()["light_calibration_id"] is None
    )


def test_job_uses_the_light_calibration_recorded_at_submission(
    client, settings, consumer_factory, bundle_zip, near_field
):
    """Fake pipeline (records the count of lights it was given): a calibration uploaded after an
    inspection was submitted does not change that inspection's lights."""
    six = _upload(client, _first(near_field["lights"], 6)).json()["id"]
    before = _post_bundle(client, "P-100", bundle_zip).json()["id"]
    twelve = _upload(client, near_field["lights"]).json()["id"]
    after = _post_bundle(client, "P-100", bundle_zip).json()["id"]

    consumer = consumer_factory().start()
    first, second = (wait_for(client, i, consumer=consumer) for i in (before, after))
    assert first["status"] == second["status"] == "done", (first, second)
    assert first["light_calibration_id"] == six and second["light_calibration_id"] == twelve
    assert first["result"]["warnings"] == [APPLIED]
    assert second["result"]["warnings"][0].startswith(
        "the light calibration was not applied: it has 12 lights"
    )
    for body, n in ((first, 6), (second, 12)):
        assert (
            client.get(body["artifacts"]["details.json"]).json()["light_calibration_n_lights"] == n
        )


def test_real_pipeline_applies_the_light_calibration_to_a_nominal_near_field_capture(
    tmp_path, near_field
):
    """pipeline.run:inspect in a real consumer: the current light calibration (the simulator's true
    lights) is applied to nominal directions and the result says so. Only the service's part is
    asserted (stored, passed, applied, warning kept), not the measured radius."""
    from fastapi.testclient import TestClient

    from app.main import create_app
    from app.settings import Settings

    settings = Settings(data_dir=tmp_path / "real", api_token=TOKEN, progress_interval_s=0.05)
    app = create_app(settings)
    consumer = Consumer(settings).start()
    try:
        with TestClient(app) as client:
            calibration_id = _upload(client, near_field["lights"]).json()["id"]
            r = _post_bundle(client, "NF-1", near_field["zip"], target=near_field["target"])
            assert r.status_code == 202, r.text
            body = wait_for(client, r.json()["id"], timeout_s=240, consumer=consumer)
            assert body["light_calibration_id"] == calibration_id
            assert body["status"] == "done", body
            assert APPLIED in body["result"]["warnings"]
            assert APPLIED in client.get(body["artifacts"]["result.json"]).json()["warnings"]
    finally:
        consumer.stop()
        app.state.engine.dispose()
