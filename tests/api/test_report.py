"""The inspection report's route: only a done inspection has one; unknown ids are 404.

The report of a real measured plate (its defect's peak in the PDF, the page rendered) is checked in
``test_jobs.py::test_a_dented_plate_fails_and_the_api_lists_its_defect``; its layout in
``tests/web/test_pages.py``.
"""

from __future__ import annotations

import io
import json
import re
import zipfile

import pytest
from fastapi.testclient import TestClient

from app.main import create_app
from tests.api.helpers import AUTH, pdf_text, target_json


def test_report_of_an_unknown_or_unfinished_inspection(client):
    r = client.get("/api/v1/inspections/999999/report.pdf")
    assert r.status_code == 404 and r.json()["field"] == "inspection_id"
    created = client.post(
        "/api/v1/plates/P-RPT/inspections/simulated",
        json={"width": 160, "height": 128, "n_lights": 3},
        headers=AUTH,
    )
    assert created.status_code == 202, created.text
    r = client.get(f"/api/v1/inspections/{created.json()['id']}/report.pdf")
    assert r.status_code == 409
    assert r.json()["field"] == "inspection_id" and "only a done inspection" in r.json()["detail"]


def test_operator_names_are_checked(client, bundle_zip):
    bad = client.post(
        "/api/v1/plates/P-OP/inspections/simulated",
        json={"width": 160, "height": 128, "n_lights": 3, "operator": "x" * 81},
        headers=AUTH,
    )
    assert bad.status_code == 422 and "operator" in bad.json()["field"], bad.text
    files = {
        "capture": ("bundle.zip", bundle_zip, "application/zip"),
        "target": ("target.json", target_json(), "application/json"),
    }
    r = client.post(
        "/api/v1/plates/P-100/inspections",
        files=files,
        data={"operator": "tab\there"},
        headers=AUTH,
    )
    assert r.status_code == 422 and r.json()["field"] == "operator", r.text
    ok = client.post(
        "/api/v1/plates/P-100/inspections",
        files=files,
        data={"operator": "Kim Ji-woo"},
        headers=AUTH,
    )
    assert ok.status_code == 202, ok.text
    doc = client.get(f"/api/v1/inspections/{ok.json()['id']}").json()
    assert doc["operator"] == "Kim Ji-woo"


# ------------------------------------------------------------------ the signed report's content

TRACE = {"drawing": {"number": "DWG-H77-B21-0042", "revision": "C"}, "hull": "H77", "block": "B21"}
DEFECT = {
    "centroid_px": [30.0, 20.0],
    "centroid_mm": [-600.0, 300.0],
    "area_mm2": 70686.0,
    "peak_deviation_mm": -6.05,
    "mean_deviation_mm": -3.1,
    "uncertainty_mm": 0.41,  # U at its peak (details.json), not the plate's U95
}


def _seed(app, bundle_zip, *, plate_id, acquired, result_extra, trace=TRACE, defects=(DEFECT,)):
    """A done inspection of ``plate_id`` (analytic cylinder artifacts), its bundle folder holding
    the calibration and, when ``acquired``, an acquisition record with camera serials."""
    from app.services import inspections as svc
    from app.services import leases
    from tests.web.helpers import _simulation
    from tests.web.plates import write_artifacts

    with zipfile.ZipFile(io.BytesIO(bundle_zip)) as zf:
        calibration = json.loads(zf.read("capture.json"))["calibration"]
        calibration = (
            json.loads(zf.read(calibration)) if isinstance(calibration, str) else calibration
        )
    calibration["rms_px"] = 0.213
    storage = app.state.storage
    with app.state.session_factory() as session:
        row = svc.create_simulated_inspection(
            session=session, storage=storage, plate_id=plate_id, simulation=_simulation()
        )
        row.operator = "Kim Ji-woo"
        inspection_id, bundle = row.id, storage.absolute(row.capture_path)
        target_path = storage.absolute(row.target_path)
        session.commit()
        assert leases.claim(session=session, inspection_id=inspection_id)
        folder = write_artifacts(
            storage.artifacts_dir(inspection_id), plate_id=plate_id, measured_radius_mm=5050.0
        )
        bundle.mkdir(parents=True, exist_ok=True)
        (bundle / "calibration.json").write_text(json.dumps(calibration))
        capture = {"captured_at": "2026-11-26T08:31:00Z", "calibration": "calibration.json"}
        if acquired:
            capture["acquisition"] = {
                "cell_id": "cell-07",
                "cameras": {
                    "left": {"vendor": "Basler", "model": "a2A2448", "serial": "22334455"},
                    "right": {"vendor": "Basler", "model": "a2A2448", "serial": "22334456"},
                },
            }
        (bundle / "capture.json").write_text(json.dumps(capture))
        target = json.loads(target_json(**trace, size_mm=[3000.0, 2000.0]))
        target_path.parent.mkdir(parents=True, exist_ok=True)
        target_path.write_text(json.dumps(target))
        T = [[1.0, 0, 0, 0], [0, -1.0, 0, 0], [0, 0, -1.0, 3000.0], [0, 0, 0, 1.0]]  # z to cameras
        details = {
            "T_cam_target": T,
            "registration_rms_mm": 0.412,
            "defects": list(defects),
            "reasons": [],
        }
        (folder / "details.json").write_text(json.dumps(details))
        document = json.loads((folder / "result.json").read_text()) | result_extra
        (folder / "result.json").write_text(json.dumps(document))
        leases.mark_done(session=session, inspection_id=inspection_id, document=document)
        session.commit()
    return inspection_id, calibration


@pytest.fixture
def yard_client(settings):
    app = create_app(settings.model_copy(update={"yard": "Okpo yard"}))
    with TestClient(app) as c:
        yield c
    app.state.engine.dispose()


def _report_text(client, inspection_id, tmp_path) -> str:
    r = client.get(f"/api/v1/inspections/{inspection_id}/report.pdf")
    assert r.status_code == 200 and r.headers["content-type"] == "application/pdf", r.text
    return pdf_text(r.content, tmp_path)


def test_a_report_to_sign_carries_its_traceability_calibration_and_judged_items(
    yard_client, bundle_zip, tmp_path
):
    uncertainty = {"k": 2, "radius_mm": 3.1, "deviation_mm": 0.35}
    warning = "a light calibration was applied to nominal lights"
    inspection_id, calibration = _seed(
        yard_client.app,
        bundle_zip,
        plate_id="H77-B21-P07",
        acquired=True,
        result_extra={"uncertainty": uncertainty, "warnings": [warning]},
    )
    files = {"calibration": ("calibration.json", json.dumps(calibration).encode())}
    uploaded = yard_client.post("/api/v1/calibrations", files=files, headers=AUTH)
    assert uploaded.status_code == 201, uploaded.text
    text = _report_text(yard_client, inspection_id, tmp_path)
    flat = " ".join(text.split())
    pages = re.findall(r"Page (\d+) of (\d+)", text)
    assert len(pages) >= 2 and all(total == str(len(pages)) for _, total in pages), pages
    assert [int(p) for p, _ in pages] == list(range(1, len(pages) + 1))
    # the header, on every page
    assert text.count("Okpo yard") == len(pages) and text.count("DWG-H77-B21-0042") >= len(pages)
    for needle in ("Hull H77", "Block B21", "Revision C", "Plate H77-B21-P07", "Cell cell-07"):
        assert flat.count(needle) >= len(pages), needle
    assert f"IR-{inspection_id:06d}" in text and "Camera serials L 22334455, R 22334456" in flat
    assert f"Calibration #{uploaded.json()['id']}" in flat and "Operator Kim Ji-woo" in flat
    assert re.search(r"Calibration RMS \d+\.\d{3} px", flat) and "UTC" in text
    # the alignment, the judged items with tolerance and uncertainty, the decision rule
    assert "Residual 0.41 mm RMS" in flat and "best fit" in flat
    radius = re.search(r"Radius\s+5000\.0 mm\s+5050\.0 mm\s+\+50\.0 mm \(\+1\.00 %\).*", text)
    assert radius and "3.10 mm" in radius.group(0) and "FAIL" in radius.group(0), text
    defect = re.search(r"^\s*1\s+-600\s+300\s+706\.9\s.*$", text, re.MULTILINE)
    assert defect and "-6.05" in defect.group(0) and "±2.00" in defect.group(0), text
    assert "0.41 mm" in defect.group(0) and "FAIL" in defect.group(0)
    assert "1: -6.0 mm (tol. ±2)" in text  # the callout on the map
    assert "ISO 14253-1" in text and "tolerance 2.00 mm / U95 0.35 mm = 5.7" in flat
    assert warning in flat
    for row in ("Minimum (signed)", "Maximum (signed)", "Standard deviation", "p95 of |deviation|"):
        assert row in text
    assert "Virtual templates" in text and "700 mm grid" in text
    # the frames placed in the target's frame, as on the dashboard's map (issue 26)
    assert re.search(r"Frame at\s+Through", text) and "from edge" in text, text
    assert re.search(r"[xy] = [-+]?\d+ mm, \d+ mm from edge [ABCD]", text), text
    assert re.search(r"Within tolerance\s+\d+\.\d\d %\s+the judged area", text)
    # signature blocks
    assert "QA approver" in text and "Disposition" in text
    assert "accept" in text and "rework" in text and "concession" in text
    assert "Target shape —" not in text and "-0.00" not in text and "—" not in text


def test_the_decision_rule_flags_a_measurement_not_capable_for_its_tolerance():
    from app.report.document import decision_rule

    capable = decision_rule({"tolerance_mm": 2.0, "uncertainty": {"k": 2, "deviation_mm": 0.4}})
    assert "= 5.0; the measurement is capable" in capable and "ISO 14253-1" in capable
    poor = decision_rule({"tolerance_mm": 2.0, "uncertainty": {"k": 2, "deviation_mm": 0.8}})
    assert "= 2.5; the measurement is <b>NOT CAPABLE</b> (below 4)" in poor
    assert "not stated" in decision_rule({"tolerance_mm": 2.0})


def test_numbers_never_print_minus_zero_and_always_a_decimal_point():
    from app.report.text import num, signed, when

    assert signed(-0.004, 2, "%") == "0.00 %" and signed(-0.006, 2) == "-0.01"
    assert num(-0.04, 1) == "0.0" and num(None, 1) == "not recorded"
    assert signed(1234.5, 1, "mm") == "+1234.5 mm"
    assert when("2026-11-26T09:01:02") == "2026-11-26 09:01:02 UTC"


def test_what_a_bundle_does_not_record_is_said_not_recorded(client, bundle_zip, tmp_path):
    inspection_id, _ = _seed(
        client.app, bundle_zip, plate_id="P-PLAIN", acquired=False, result_extra={}, trace={}
    )
    flat = " ".join(_report_text(client, inspection_id, tmp_path).split())
    for label in ("Yard", "Hull", "Block", "Drawing", "Revision", "Camera serials", "Cell"):
        assert f"{label} not recorded" in flat, label
    assert "Calibration bundle's own, sha256" in flat and "Calibration date not recorded" in flat
    assert "U95 not recorded" in flat or "not stated" in flat
    assert "Warnings None." in flat and "-0.00" not in flat


def test_a_measured_dented_plate_report_prints_its_drawing_and_every_judged_item(tmp_path):
    """The real pipeline (a consumer process): the plate's target carries its drawing, hull and
    block; the dented plate's report prints them on every page, with the alignment's residual, the
    defect judged against its tolerance and the approval blocks."""
    from app.settings import Settings
    from tests.api.helpers import TOKEN, Consumer, wait_for

    settings = Settings(data_dir=tmp_path / "dent", api_token=TOKEN, yard="Okpo yard")
    app = create_app(settings)
    consumer = Consumer(settings).start()
    trace = {"drawing": {"number": "DWG-H77-B21-0042", "revision": "C"}, "hull": "H77"}
    try:
        with TestClient(app) as client:
            r = client.put(
                "/api/v1/plates/H77-B21-P09/target",
                content=target_json(**trace, block="B21"),
                headers={**AUTH, "Content-Type": "application/json"},
            )
            assert r.status_code == 200, r.text
            r = client.post(
                "/api/v1/plates/H77-B21-P09/inspections/simulated",
                json={
                    "width": 612,
                    "height": 512,
                    "seed": 8,
                    "dents": [
                        {"x_mm": -600.0, "y_mm": 300.0, "radius_mm": 150.0, "depth_mm": -6.0}
                    ],
                },
                headers=AUTH,
            )
            assert r.status_code == 202 and r.headers["location"].endswith(str(r.json()["id"]))
            body = wait_for(client, r.json()["id"], timeout_s=180, consumer=consumer)
            assert body["status"] == "done" and body["verdict"] == "fail", body
            text = _report_text(client, body["id"], tmp_path)
    finally:
        consumer.stop()
        app.state.engine.dispose()
    flat = " ".join(text.split())
    pages = int(re.search(r"Page 1 of (\d+)", text).group(1))
    for needle in ("Okpo yard", "Drawing DWG-H77-B21-0042", "Revision C", "Hull H77", "Block B21"):
        assert flat.count(needle) >= pages, needle
    assert "Camera serials not recorded" in flat  # a simulated bundle records no cameras
    assert re.search(r"Residual \d+\.\d\d mm RMS", flat) and "ISO 14253-1" in flat
    peak = f"{body['defects'][0]['peak_mm']:+.2f}"
    assert re.search(rf"^\s*1\s+-?\d+\s+-?\d+\s.*{re.escape(peak)}.*±2\.00.*FAIL", text, re.M)
    assert "U (k=2)" in text and "QA approver" in text and "Disposition (QA)" in flat
