"""The inspection report's route: only a done inspection has one; unknown ids are 404.

The report of a real measured plate (its defect's peak in the PDF, the page rendered) is checked in
``test_jobs.py::test_a_dented_plate_fails_and_the_api_lists_its_defect``; its layout in
``tests/web/test_pages.py``.
"""

from __future__ import annotations

from tests.api.helpers import AUTH, target_json


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
