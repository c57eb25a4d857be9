"""Whole inspections through the API with a real consumer process (huey on SQLite)."""

from __future__ import annotations

import io
import json
import re
import time
import zipfile

import numpy as np
import pytest

from tests.api.helpers import (
    AUTH,
    capture_json_with_plate,
    invocations,
    pdf_text,
    rendered_page_ink,
    rezip,
    target_json,
    wait_for,
)


def _post_bundle(client, plate_id, bundle, *, target=True, headers=None):
    files = {"capture": ("bundle.zip", bundle, "application/zip")}
    if target:
        files["target"] = ("target.json", target_json(), "application/json")
    return client.post(
        f"/api/v1/plates/{plate_id}/inspections", files=files, headers=headers or AUTH
    )


def test_whole_inspection_through_the_api(client, settings, consumer_factory, bundle_zip):
    consumer = consumer_factory().start()
    r = _post_bundle(client, "P-100", bundle_zip)
    assert r.status_code == 202, r.text
    assert r.json()["status"] == "queued"
    inspection_id = r.json()["id"]

    body = wait_for(client, inspection_id, consumer=consumer)
    assert body["status"] == "done", body
    assert body["plate_id"] == "P-100"
    assert body["progress"] == 1.0
    assert body["error"] is None
    assert body["result"]["format"] == "plate-result/1"
    assert body["result"]["verdict"] == "pass"
    assert body["verdict"] == "pass"
    assert set(body["artifacts"]) >= {"result.json", "deviation.png"}
    art = client.get(body["artifacts"]["result.json"])
    assert art.status_code == 200 and art.json()["plate_id"] == "P-100"
    assert (
        client.get(f"/api/v1/inspections/{inspection_id}/artifacts/nothing.png").status_code == 404
    )
    assert client.get(
        f"/api/v1/inspections/{inspection_id}/artifacts/..%2Fresult.json"
    ).status_code in (404, 422)

    plates = client.get("/api/v1/plates").json()
    assert plates["total"] == 1
    assert plates["items"][0]["latest_verdict"] == "pass"
    assert plates["items"][0]["target"]["radius_mm"] == 5000.0
    # the inputs are kept on disk
    inputs = settings.data_dir / "inspections" / str(inspection_id) / "inputs"
    assert (inputs / "capture.zip").is_file() and (inputs / "target" / "target.json").is_file()


def test_simulated_inspection_is_rendered_in_the_consumer(client, settings, consumer_factory):
    consumer = consumer_factory().start()
    spec = {
        "shape": "sphere",
        "radius_mm": 8000.0,
        "n_lights": 4,
        "width": 160,
        "height": 128,
        "dents": [{"x_mm": 100.0, "y_mm": -50.0, "radius_mm": 150.0, "depth_mm": 3.0}],
        "seed": 3,
    }
    r = client.post("/api/v1/plates/SIM-1/inspections/simulated", json=spec, headers=AUTH)
    assert r.status_code == 202, r.text
    body = wait_for(client, r.json()["id"], consumer=consumer)
    assert body["status"] == "done", body
    assert body["source"] == "simulated"
    bundle = settings.data_dir / "inspections" / str(body["id"]) / "inputs" / "bundle"
    assert (bundle / "capture.json").is_file() and (bundle / "target.json").is_file()
    assert body["result"]["target_radius_mm"] == 8000.0


def test_consumer_killed_mid_job_is_requeued_and_completes(
    client, consumer_factory, bundle_zip, tmp_path
):
    # 0.4 s per stage: the job runs ~2.4 s, so the kill lands mid-job.
    calls = tmp_path / "invocations.txt"
    first = consumer_factory(stage_delay_s=0.4, invocations=calls).start()
    inspection_id = _post_bundle(client, "P-100", bundle_zip).json()["id"]
    deadline = time.monotonic() + 30
    while True:
        body = client.get(f"/api/v1/inspections/{inspection_id}").json()
        if body["status"] == "running" and body["stage"] not in (None, "load"):
            break
        assert time.monotonic() < deadline, f"job never ran: {body}\n{first.output()}"
        time.sleep(0.05)
    first.kill()
    time.sleep(0.5)
    body = client.get(f"/api/v1/inspections/{inspection_id}").json()
    assert body["status"] == "running"  # the row still says so: its consumer is gone

    second = consumer_factory(
        stage_delay_s=0.0, invocations=calls, log_name="consumer-2.log"
    ).start()
    body = wait_for(client, inspection_id, consumer=second)
    assert body["status"] == "done", body
    assert body["result"]["verdict"] == "pass" and body["error"] is None
    # Run again once (one worker death, below the limit) and completed once.
    events = [(event, i, pid) for event, i, pid in invocations(calls)]
    assert events == [
        ("start", inspection_id, first.proc.pid),
        ("start", inspection_id, second.proc.pid),
        ("end", inspection_id, second.proc.pid),
    ]
    from app.models import Inspection

    with client.app.state.session_factory() as s:
        row = s.get(Inspection, inspection_id)
        assert (row.attempts, row.deaths, row.lease_owner) == (2, 1, None)


@pytest.mark.parametrize(
    ("plate_id", "message"),
    [
        ("P-UNMEASURABLE", "P-UNMEASURABLE: no plate found in the photometric images"),
        ("P-CRASH", "internal error: RuntimeError: simulated bug"),
        # the server path of the file is not given away: named relative to the inspection's inputs
        (
            "P-PATHERROR",
            "internal error: FileExistsError: [Errno 17] File exists: 'bundle.partial'",
        ),
    ],
)
def test_failed_job_keeps_inputs_and_error(
    client, settings, consumer_factory, bundle_zip, plate_id, message
):
    consumer = consumer_factory().start()
    capture_json = capture_json_with_plate(bundle_zip, plate_id)
    bundle = rezip(bundle_zip, replace={"capture.json": capture_json})
    r = _post_bundle(client, plate_id, bundle)
    assert r.status_code == 202, r.text
    body = wait_for(client, r.json()["id"], consumer=consumer)
    assert body["status"] == "error"
    assert body["error"] == message
    assert body["verdict"] is None
    assert body["result"] is None
    inputs = settings.data_dir / "inspections" / str(body["id"]) / "inputs"
    assert (inputs / "capture.zip").is_file()
    assert client.get("/api/v1/plates").json()["items"][0]["latest_verdict"] is None


def test_a_job_delivered_twice_runs_once(client, settings):
    from app.jobs import execute_inspection

    r = client.post(
        "/api/v1/plates/SIM-2/inspections/simulated",
        json={"n_lights": 3, "width": 160, "height": 128},
        headers=AUTH,
    )
    inspection_id = r.json()["id"]
    state = client.app.state
    kw = dict(settings=settings, session_factory=state.session_factory, storage=state.storage)
    assert execute_inspection(inspection_id, **kw) == "done"
    assert execute_inspection(inspection_id, **kw) == "skipped"
    assert client.get(f"/api/v1/inspections/{inspection_id}").json()["status"] == "done"


def test_simulated_bundle_rendered_over_leftovers_of_dead_runs(client, settings):
    from app.jobs import execute_inspection

    r = client.post(
        "/api/v1/plates/SIM-3/inspections/simulated",
        json={"n_lights": 3, "width": 160, "height": 128},
        headers=AUTH,
    )
    inspection_id = r.json()["id"]
    inputs = settings.data_dir / "inspections" / str(inspection_id) / "inputs"
    # A run killed while rendering (the old fixed name, and a newer random one), and a bundle
    # folder without its capture.json.
    for leftover in ("bundle.partial", "bundle.partial-k2j4x9"):
        (inputs / leftover).mkdir()
        (inputs / leftover / "ps_00.png").write_bytes(b"half an image")
    (inputs / "bundle").mkdir()
    (inputs / "bundle" / "ps_00.png").write_bytes(b"half an image")
    state = client.app.state
    status = execute_inspection(
        inspection_id,
        settings=settings,
        session_factory=state.session_factory,
        storage=state.storage,
    )
    assert status == "done", client.get(f"/api/v1/inspections/{inspection_id}").json()
    assert sorted(p.name for p in inputs.iterdir()) == ["bundle", "simulation.json"]
    assert (inputs / "bundle" / "capture.json").is_file()


def test_real_pipeline_inspection(tmp_path, consumer_factory, bundle_zip):
    """The production entry point (pipeline.run:inspect): a simulated plate is measured; a valid
    bundle with neither a stereo pair nor a working distance is accepted, then fails saying why."""
    from fastapi.testclient import TestClient

    from app.main import create_app
    from app.settings import Settings
    from tests.api.helpers import TOKEN, Consumer

    settings = Settings(data_dir=tmp_path / "real", api_token=TOKEN, progress_interval_s=0.05)
    app = create_app(settings)
    consumer = Consumer(settings).start()
    try:
        with TestClient(app) as client:
            r = client.post(
                "/api/v1/plates/SIM-R/inspections/simulated",
                json={"width": 320, "height": 256, "n_lights": 8, "seed": 5},
                headers=AUTH,
            )
            body = wait_for(client, r.json()["id"], timeout_s=120, consumer=consumer)
            assert body["status"] == "done", body
            assert body["result"]["verdict"] in ("pass", "fail")
            assert "result.json" in body["artifacts"]

            doc = json.loads(zipfile.ZipFile(io.BytesIO(bundle_zip)).read("capture.json"))
            del doc["stereo"]
            doc.pop("working_distance_mm", None)
            no_scale = rezip(
                bundle_zip,
                replace={"capture.json": json.dumps(doc).encode()},
                drop=("stereo_left.png", "stereo_right.png"),
            )
            r = _post_bundle(client, "P-100", no_scale)
            assert r.status_code == 202, r.text  # a valid bundle: refused only when measured
            body = wait_for(client, r.json()["id"], timeout_s=120, consumer=consumer)
            assert body["status"] == "error" and body["verdict"] is None
            assert body["error"] == (
                "capture.zip: stereo, working_distance_mm: a metric result needs a stereo pair or a working distance"
            )
            inputs = settings.data_dir / "inspections" / str(body["id"]) / "inputs"
            assert (inputs / "capture.zip").is_file() and (
                inputs / "target" / "target.json"
            ).is_file()
    finally:
        consumer.stop()
        app.state.engine.dispose()


def test_a_dented_plate_fails_and_the_api_lists_its_defect(tmp_path):
    """The real pipeline: the inspection document names the dent's place (target frame) and depth."""
    from fastapi.testclient import TestClient

    from app.main import create_app
    from app.settings import Settings
    from tests.api.helpers import TOKEN, Consumer

    settings = Settings(data_dir=tmp_path / "dent", api_token=TOKEN)
    app = create_app(settings)
    consumer = Consumer(settings).start()
    dent = {"x_mm": -600.0, "y_mm": 300.0, "radius_mm": 150.0, "depth_mm": -6.0}
    try:
        with TestClient(app) as client:
            r = client.post(
                "/api/v1/plates/DENT-1/inspections/simulated",
                json={
                    "width": 612,
                    "height": 512,
                    "dents": [dent],
                    "seed": 8,
                    "operator": "  A. Welder ",
                },
                headers=AUTH,
            )
            assert r.status_code == 202, r.text
            body = wait_for(client, r.json()["id"], timeout_s=180, consumer=consumer)
            page = client.get(f"/inspections/{body['id']}").text
            report = client.get(f"/api/v1/inspections/{body['id']}/report.pdf")
            plate_map = client.get(f"/api/v1/inspections/{body['id']}/plate-map")
            map_png = client.get(f"/api/v1/inspections/{body['id']}/plate-map.png")
            chosen = client.get(f"/inspections/{body['id']}?at_x=200&at_y=-450").text
            missing = client.get("/api/v1/inspections/999/plate-map")
    finally:
        consumer.stop()
        app.state.engine.dispose()
    assert body["status"] == "done" and body["verdict"] == "fail", body
    # the result page and the signed report show the defect's peak as the table prints it
    peak = f"{body['defects'][0]['peak_mm']:+.1f}"
    assert f">{peak}</td>" in page
    assert 'data-defect="1"' in page and "through defect 1" in page  # a template crosses the dent
    # the plate map (target frame, mm) is reddest at the dent, and beyond tolerance there
    assert plate_map.status_code == 200, plate_map.text
    m = plate_map.json()
    grid = np.array([[np.nan if v is None else v for v in row] for row in m["deviation_mm"]])
    assert grid.shape == (m["ny"], m["nx"]) and np.isfinite(grid).mean() > 0.5
    j, i = np.unravel_index(np.nanargmax(grid), grid.shape)
    x_peak = m["x0_mm"] + (i + 0.5) * m["cell_mm"]
    y_peak = m["y0_mm"] + (j + 0.5) * m["cell_mm"]
    assert abs(x_peak - dent["x_mm"]) < 40.0 and abs(y_peak - dent["y_mm"]) < 40.0
    assert grid[j, i] == pytest.approx(6.0, abs=1.0)
    assert [d["id"] for d in m["defects"]] == [1]
    from PIL import Image

    with Image.open(io.BytesIO(map_png.content)) as image:
        assert image.size == (m["nx"], m["ny"]) and image.mode == "RGBA"
        # y up: the dent's cell is drawn at row ny - 1 - j, saturated red beyond tolerance
        r, g, b, a = image.getpixel((int(i), int(m["ny"] - 1 - j)))
    assert a == 255 and r > 150 and g < 80 and b < 80
    assert missing.status_code == 404 and missing.json()["field"] == "inspection_id"
    # a template through the chosen point: its frame line on the map crosses it
    assert "through the point you chose" in chosen
    line = re.search(r'class="template chosen" data-line="([-\d. ]+)"', chosen).group(1)
    x1, y1, x2, y2 = (float(v) for v in line.split())
    t = (200.0 - x1) / (x2 - x1)
    assert abs(y1 + t * (y2 - y1) - -450.0) < 15.0
    assert report.status_code == 200 and report.headers["content-type"] == "application/pdf"
    text = pdf_text(report.content, tmp_path)
    assert "DENT-1" in text and "FAIL" in text and peak in text and "Signature" in text
    assert body["operator"] == "A. Welder" and "A. Welder" in text  # who started it signs
    assert "x, mm" in text and "y, mm" in text and "target's frame" in text  # the map in mm
    assert "through defect 1" in text  # the template through the defect, drawn with its gap
    assert rendered_page_ink(report.content, tmp_path) > 0.02
    assert body["reasons"] and "tolerance" in body["reasons"][0]
    [defect] = body["defects"]
    assert defect["id"] == 1
    assert defect["peak_mm"] == pytest.approx(6.0, abs=1.0)  # a bump: towards the cameras
    assert 0 < defect["mean_mm"] < defect["peak_mm"]
    x, y = defect["centroid_mm"]
    assert abs(x - dent["x_mm"]) < 30.0 and abs(y - dent["y_mm"]) < 30.0


def test_an_upload_error_names_the_bundle_as_sent_and_the_plate_mismatch_plainly(client):
    files = {
        "capture": ("bad.zip", b"this is not a zip archive", "application/zip"),
        "target": ("target.json", target_json(), "application/json"),
    }
    r = client.post("/api/v1/plates/P-NAMED/inspections", files=files, headers=AUTH)
    assert r.status_code == 422, r.text
    assert r.json()["file"].startswith("bad.zip") and "capture.zip" not in r.text


def test_a_bundle_of_another_plate_is_refused_in_plain_words(client, bundle_zip):
    r = _post_bundle(client, "HULL-UP1", bundle_zip)  # the bundle is of plate P-100
    assert r.status_code == 422
    detail = r.json()["detail"]
    assert "the bundle is of plate 'P-100', not of 'HULL-UP1'" in detail and "URL" not in detail
