"""The REST API without a consumer: validation, auth, idempotency, limits, paging, targets, calibrations."""

from __future__ import annotations

import io
import json
import re
import zipfile

import pytest
from sqlalchemy import func, select

from app.models import Inspection, Plate
from tests.api.helpers import AUTH, rezip, stored_files, target_json


def _count(client, model) -> int:
    with client.app.state.session_factory() as s:
        return s.scalar(select(func.count()).select_from(model))


def _simulated(client, plate_id="P-1", headers=AUTH, **spec):
    return client.post(
        f"/api/v1/plates/{plate_id}/inspections/simulated", json=spec, headers=headers
    )


# ------------------------------------------------------------------ bad bundles


def _capture_doc(bundle: bytes) -> dict:
    with zipfile.ZipFile(io.BytesIO(bundle)) as zf:
        return json.loads(zf.read("capture.json"))


@pytest.mark.parametrize(
    ("mutate", "field_part"),
    [
        (lambda d: d["photometric"]["lights"][0].update(direction=[0.0, 0.0, -2.0]), "lights"),
        (lambda d: d.pop("bit_depth"), "bit_depth"),
        (lambda d: d["photometric"]["images"].__setitem__(1, "missing.png"), "images"),
    ],
)
def test_bad_bundle_is_refused_and_nothing_is_stored(
    client, settings, bundle_zip, mutate, field_part
):
    doc = _capture_doc(bundle_zip)
    mutate(doc)
    bad = rezip(bundle_zip, replace={"capture.json": json.dumps(doc).encode()})
    before = stored_files(settings.data_dir)
    r = client.post(
        "/api/v1/plates/P-100/inspections",
        files={"capture": ("b.zip", bad), "target": ("target.json", target_json())},
        headers=AUTH,
    )
    assert r.status_code == 422, r.text
    body = r.json()
    assert body["file"].endswith(("capture.json", "missing.png")), body
    assert field_part in (body["field"] or "") or field_part in body["detail"], body
    assert str(settings.data_dir) not in body["detail"]  # no server paths in messages
    assert _count(client, Plate) == 0 and _count(client, Inspection) == 0
    assert stored_files(settings.data_dir) == before


def test_not_a_zip_and_missing_capture_are_refused(client, settings):
    r = client.post(
        "/api/v1/plates/P-100/inspections", files={"capture": ("b.zip", b"not a zip")}, headers=AUTH
    )
    assert r.status_code == 422 and r.json()["field"] == "capture", r.text
    r = client.post(
        "/api/v1/plates/P-100/inspections",
        files={"target": ("t.json", target_json())},
        headers=AUTH,
    )
    assert r.status_code == 422 and r.json()["field"] == "capture", r.text
    assert _count(client, Plate) == 0 and stored_files(settings.data_dir) == []


def test_bundle_of_another_plate_and_missing_target_are_refused(client, settings, bundle_zip):
    r = client.post(
        "/api/v1/plates/P-999/inspections",
        files={"capture": ("b.zip", bundle_zip), "target": ("t.json", target_json())},
        headers=AUTH,
    )
    assert r.status_code == 422 and r.json()["field"] == "capture: plate_id", r.text
    r = client.post(
        "/api/v1/plates/P-100/inspections", files={"capture": ("b.zip", bundle_zip)}, headers=AUTH
    )
    assert r.status_code == 422 and r.json()["field"] == "target", r.text
    bad_target = target_json(tolerance_mm=-1)
    r = client.post(
        "/api/v1/plates/P-100/inspections",
        files={"capture": ("b.zip", bundle_zip), "target": ("t.json", bad_target)},
        headers=AUTH,
    )
    assert r.status_code == 422 and "tolerance_mm" in r.json()["detail"], r.text
    assert _count(client, Plate) == 0 and stored_files(settings.data_dir) == []


def test_target_of_the_plate_is_used_when_none_is_sent(client, bundle_zip):
    assert (
        client.put(
            "/api/v1/plates/P-100/target",
            content=target_json(),
            headers={**AUTH, "Content-Type": "application/json"},
        ).status_code
        == 200
    )
    r = client.post(
        "/api/v1/plates/P-100/inspections", files={"capture": ("b.zip", bundle_zip)}, headers=AUTH
    )
    assert r.status_code == 202, r.text


# ------------------------------------------------------------------ auth, idempotency, limits


@pytest.mark.parametrize(
    "headers",
    [
        {},
        {"Authorization": "Bearer wrong-token"},
        {"Authorization": "Basic dGVzdA=="},
        {"Authorization": "Bearer "},
    ],
)
def test_writes_need_the_token(client, headers):
    r = _simulated(client, headers=headers)
    assert r.status_code == 401, r.text
    assert r.json()["field"] == "Authorization"
    assert r.headers["www-authenticate"] == "Bearer"
    r = client.put(
        "/api/v1/plates/P-1/target",
        content=target_json(),
        headers={**headers, "Content-Type": "application/json"},
    )
    assert r.status_code == 401
    r = client.post(
        "/api/v1/calibrations", files={"calibration": ("c.json", b"{}")}, headers=headers
    )
    assert r.status_code == 401
    assert _count(client, Plate) == 0


def test_dashboard_session_cookie_allows_writes(client):
    assert client.post("/api/v1/session", json={"token": "wrong"}).status_code == 401
    r = client.post("/api/v1/session", json={"token": AUTH["Authorization"].split()[1]})
    assert r.status_code == 204
    assert (
        "httponly" in r.headers["set-cookie"].lower()
        and "samesite=strict" in r.headers["set-cookie"].lower()
    )
    assert _simulated(client, headers={}).status_code == 202
    r = _simulated(client, headers={"Origin": "http://evil.example"})
    assert r.status_code == 403 and r.json()["field"] == "Origin"
    client.delete("/api/v1/session")
    assert _simulated(client, headers={}).status_code == 401


def test_idempotent_retry_returns_the_first_answer(client, bundle_zip):
    headers = {**AUTH, "Idempotency-Key": "mes-42"}
    files = {"capture": ("b.zip", bundle_zip), "target": ("t.json", target_json())}
    first = client.post("/api/v1/plates/P-100/inspections", files=files, headers=headers)
    again = client.post("/api/v1/plates/P-100/inspections", files=files, headers=headers)
    assert first.status_code == again.status_code == 202
    assert first.json() == again.json()
    assert again.headers.get("idempotent-replayed") == "true"
    assert _count(client, Inspection) == 1
    # the same key on another route is another request
    r1 = _simulated(client, "P-100", headers=headers)
    r2 = _simulated(client, "P-100", headers=headers)
    assert (
        r1.status_code == 202 and r2.json() == r1.json() and r1.json()["id"] != first.json()["id"]
    )
    assert _count(client, Inspection) == 2
    # a refusal is remembered too
    bad = {**AUTH, "Idempotency-Key": "mes-43"}
    b1 = client.post(
        "/api/v1/plates/P-100/inspections", files={"capture": ("b.zip", b"x")}, headers=bad
    )
    b2 = client.post(
        "/api/v1/plates/P-100/inspections", files={"capture": ("b.zip", b"x")}, headers=bad
    )
    assert b1.status_code == b2.status_code == 422 and b1.json() == b2.json()
    # a new key is a new inspection
    assert (
        _simulated(client, "P-100", headers={**AUTH, "Idempotency-Key": "mes-44"}).json()["id"]
        != r1.json()["id"]
    )
    assert _count(client, Inspection) == 3


def test_a_key_sent_again_with_another_body_is_422_naming_the_header(client, bundle_zip):
    headers = {**AUTH, "Idempotency-Key": "mes-50"}
    url = "/api/v1/plates/P-100/inspections"
    first = client.post(
        url,
        files={"capture": ("b.zip", bundle_zip), "target": ("t.json", target_json())},
        data={"operator": "Kim"},
        headers=headers,
    )
    assert first.status_code == 202, first.text
    # the same fields and contents: another part order, boundary and file name replay the first
    again = client.post(
        url,
        files=[("target", ("other.json", target_json())), ("capture", ("c.zip", bundle_zip))],
        data={"operator": "Kim"},
        headers=headers,
    )
    assert again.status_code == 202 and again.json() == first.json()
    assert again.headers["idempotent-replayed"] == "true"
    assert again.headers["location"] == f"/api/v1/inspections/{first.json()['id']}"
    # another operator, another file: refused, nothing created
    for data, target in (({"operator": "Lee"}, target_json()), ({"operator": "Kim"}, b"{}")):
        other = client.post(
            url,
            files={"capture": ("b.zip", bundle_zip), "target": ("t.json", target)},
            data=data,
            headers=headers,
        )
        assert other.status_code == 422 and other.json()["field"] == "Idempotency-Key", other.text
        assert "another body" in other.json()["detail"]
    assert _count(client, Inspection) == 1
    # JSON bodies: key order and spacing do not count, contents do
    key = {**AUTH, "Idempotency-Key": "mes-51", "Content-Type": "application/json"}
    sim = "/api/v1/plates/P-100/inspections/simulated"
    one = client.post(sim, content=b'{"seed": 1, "n_lights": 4}', headers=key)
    two = client.post(sim, content=b'{"n_lights":4,"seed":1}', headers=key)
    assert one.status_code == two.status_code == 202 and one.json() == two.json()
    three = client.post(sim, content=b'{"n_lights": 4, "seed": 2}', headers=key)
    assert three.status_code == 422 and three.json()["field"] == "Idempotency-Key"
    assert _count(client, Inspection) == 2


def test_a_target_put_again_under_its_key_replays_only_the_same_document(client):
    """PUT /target reads its body itself (JSON or multipart): the key's fingerprint still sees it."""
    url = "/api/v1/plates/P-IK/target"
    headers = {**AUTH, "Idempotency-Key": "mes-60", "Content-Type": "application/json"}
    doc = json.loads(target_json())
    first = client.put(url, content=json.dumps(doc), headers=headers)
    reordered = json.dumps(dict(reversed(list(doc.items()))), indent=2)
    again = client.put(url, content=reordered, headers=headers)
    assert first.status_code == again.status_code == 200 and again.json() == first.json()
    assert again.headers["idempotent-replayed"] == "true"
    other = client.put(url, content=target_json(tolerance_mm=3.0), headers=headers)
    assert other.status_code == 422 and other.json()["field"] == "Idempotency-Key", other.text
    assert client.get(url).json()["tolerance_mm"] == 2.0


def test_202_and_201_say_where_the_new_thing_is(client):
    r = _simulated(client, "P-LOC")
    assert r.status_code == 202
    assert r.headers["location"] == f"/api/v1/inspections/{r.json()['id']}"
    assert client.get(r.headers["location"]).json()["plate_id"] == "P-LOC"
    machine = {
        "kind": "three-roll-pyramid",
        "bottom_roll_spacing_mm": 1400,
        "bottom_roll_diameter_mm": 420,
        "top_roll_diameter_mm": 500,
    }
    r = client.put("/api/v1/machines/R3-01", json=machine, headers=AUTH)
    assert r.status_code == 201 and r.headers["location"] == "/api/v1/machines/R3-01"
    r = client.put("/api/v1/machines/R3-01", json=machine, headers=AUTH)
    assert r.status_code == 200 and "location" not in r.headers


def test_a_body_that_is_not_json_is_400_naming_the_problem(client):
    r = client.post(
        "/api/v1/plates/P-1/inspections/simulated",
        content=b'{"width": 160,, }',
        headers={**AUTH, "Content-Type": "application/json"},
    )
    assert r.status_code == 400 and r.json()["field"] == "body", r.text
    assert r.json()["detail"].startswith("body: not JSON (expecting")
    assert _count(client, Inspection) == 0


def test_the_inspections_of_an_unknown_plate_are_404(client):
    r = client.get("/api/v1/plates/NOPE/inspections")
    assert r.status_code == 404 and r.json()["field"] == "plate_id"
    assert client.get("/api/v1/plates/NOPE").status_code == 404


def test_an_unknown_machine_says_how_to_add_it(client):
    r = _simulated(
        client,
        "P-M",
        process={"method": "roll-bending", "machine_id": "R9", "top_roll_displacement_mm": 90.0},
    )
    assert r.status_code == 422 and r.json()["field"] == "process.machine_id", r.text
    assert "PUT /api/v1/machines/R9" in r.json()["detail"] and "{" not in r.json()["detail"]


def test_a_target_carries_its_drawing_hull_and_block(client):
    url = "/api/v1/plates/P-TR/target"
    json_body = {**AUTH, "Content-Type": "application/json"}
    trace = {"drawing": {"number": "DWG-H77-B21-0042", "revision": "C"}, "hull": "H77"}
    r = client.put(url, content=target_json(**trace, block="B21"), headers=json_body)
    assert r.status_code == 200, r.text
    stored = client.get(url).json()["document"]
    assert stored["drawing"] == trace["drawing"] and (stored["hull"], stored["block"]) == (
        "H77",
        "B21",
    )
    r = client.put(url, content=target_json(hull="H" * 65), headers=json_body)
    assert r.status_code == 422 and r.json()["field"] == "target: hull", r.text
    assert r.json()["file"] == "target.json" and "64 characters" in r.json()["detail"]
    r = client.put(url, content=target_json(drawing={"number": "D-1"}), headers=json_body)
    assert r.status_code == 422 and r.json()["field"] == "target: drawing.revision", r.text
    r = client.put(url, content=target_json(yard="Okpo"), headers=json_body)
    assert r.status_code == 422 and r.json()["field"] == "target: yard", r.text


def test_upload_over_the_limit_is_413(client, settings):
    big = b"0" * (settings.max_upload_bytes + 1)
    r = client.post(
        "/api/v1/plates/P-100/inspections", files={"capture": ("b.zip", big)}, headers=AUTH
    )
    assert r.status_code == 413
    assert r.json()["field"] == "body" and "bytes" in r.json()["detail"]

    def chunks():  # no Content-Length: counted while streaming
        for _ in range(9):
            yield b"0" * (1 << 20)

    r = client.put(
        "/api/v1/plates/P-100/target",
        content=chunks(),
        headers={**AUTH, "Content-Type": "application/json"},
    )
    assert r.status_code == 413 and r.json()["field"] == "body"
    assert _count(client, Plate) == 0 and stored_files(settings.data_dir) == []


def test_validation_errors_name_the_field(client):
    r = _simulated(client, n_lights=2)
    assert r.status_code == 422 and r.json()["field"] == "n_lights", r.text
    r = _simulated(client, shape="torus")
    assert r.status_code == 422 and r.json()["field"] == "shape"
    r = _simulated(client, plate_id="bad plate!")
    assert r.status_code == 422 and r.json()["field"] == "plate_id"
    r = _simulated(client, dents=[{"x_mm": 0, "y_mm": 0, "radius_mm": -5, "depth_mm": 1}])
    assert r.status_code == 422 and r.json()["field"] == "dents.0.radius_mm"
    r = client.get("/api/v1/inspections/999")
    assert r.status_code == 404 and r.json()["field"] == "inspection_id"


# ------------------------------------------------------------------ lists


def test_plates_list_and_history_paging(client):
    ids = [_simulated(client, "P-A", seed=i).json()["id"] for i in range(5)]
    _simulated(client, "P-B")
    page = client.get("/api/v1/plates/P-A/inspections", params={"limit": 2}).json()
    assert page["total"] == 5 and [i["id"] for i in page["items"]] == ids[::-1][:2]
    page = client.get("/api/v1/plates/P-A/inspections", params={"limit": 2, "offset": 4}).json()
    assert [i["id"] for i in page["items"]] == [ids[0]]
    assert client.get("/api/v1/plates/P-A/inspections", params={"limit": 0}).status_code == 422
    plates = client.get("/api/v1/plates").json()
    assert [p["id"] for p in plates["items"]] == ["P-B", "P-A"]  # most recently inspected first
    assert plates["items"][1]["inspection_count"] == 5
    assert plates["items"][1]["latest_inspection"]["id"] == ids[-1]
    queued = client.get("/api/v1/inspections", params={"status": "queued", "limit": 50}).json()
    assert queued["total"] == 6
    assert client.get("/api/v1/plates/P-A").json()["inspection_count"] == 5
    assert client.get("/api/v1/plates/NOPE").status_code == 404


def test_healthz_and_openapi(client):
    assert client.get("/healthz").json()["status"] == "ok"
    paths = client.get("/openapi.json").json()["paths"]
    for path in (
        "/api/v1/plates/{plate_id}/inspections",
        "/api/v1/plates/{plate_id}/inspections/simulated",
        "/api/v1/inspections/{inspection_id}",
        "/api/v1/inspections/{inspection_id}/artifacts/{name}",
        "/api/v1/plates",
        "/api/v1/plates/{plate_id}/target",
        "/api/v1/calibrations",
        "/api/v1/calibrations/current",
    ):
        assert path in paths, path
    docs = client.get("/docs")
    assert docs.status_code == 200
    # The cell's network is closed: Swagger UI's files come from this server, not a CDN.
    assets = re.findall(r'(?:src|href)="([^"]+)"', docs.text)
    assert assets and not re.search(r"https?://", docs.text), assets
    for asset in assets:
        assert client.get(asset).status_code == 200, asset


# ------------------------------------------------------------------ targets and calibrations


def test_put_target_json_then_mesh_upload(client, settings):
    r = client.put(
        "/api/v1/plates/P-7/target",
        content=target_json(shape={"type": "sphere", "radius_mm": 9000.0}),
        headers={**AUTH, "Content-Type": "application/json"},
    )
    assert r.status_code == 200, r.text
    assert r.json()["shape"] == "sphere" and r.json()["radius_mm"] == 9000.0

    import trimesh

    mesh = trimesh.creation.box(extents=(3000.0, 2000.0, 10.0))
    stl = trimesh.exchange.stl.export_stl(mesh)
    r = client.put(
        "/api/v1/plates/P-7/target",
        files={"mesh": ("plate.stl", stl)},
        data={"size_x_mm": "3000", "size_y_mm": "2000", "tolerance_mm": "1.5"},
        headers=AUTH,
    )
    assert r.status_code == 200, r.text
    assert r.json()["shape"] == "mesh" and r.json()["tolerance_mm"] == 1.5
    current = client.get("/api/v1/plates/P-7/target").json()
    assert current["id"] == r.json()["id"] and current["document"]["shape"] == {
        "type": "mesh",
        "file": "plate.stl",
    }
    assert (
        settings.data_dir / "plates" / "P-7" / "targets" / str(current["id"]) / "plate.stl"
    ).is_file()

    doc = json.loads(target_json(shape={"type": "mesh", "file": "hull.stl"}))
    r = client.put(
        "/api/v1/plates/P-7/target",
        files={"mesh": ("x.stl", stl), "target": ("t.json", json.dumps(doc))},
        headers=AUTH,
    )
    assert r.status_code == 200, r.text

    r = client.put(
        "/api/v1/plates/P-7/target",
        files={"mesh": ("plate.stl", stl)},
        data={"size_x_mm": "3000"},
        headers=AUTH,
    )
    assert r.status_code == 422 and r.json()["field"] == "size_y_mm"
    r = client.put(
        "/api/v1/plates/P-7/target",
        files={"mesh": ("plate.stl", b"solid nothing")},
        data={"size_x_mm": "3000", "size_y_mm": "2000", "tolerance_mm": "1.5"},
        headers=AUTH,
    )
    assert r.status_code == 422, r.text
    r = client.put(
        "/api/v1/plates/P-7/target",
        content=b"format: yaml",
        headers={**AUTH, "Content-Type": "text/yaml"},
    )
    assert r.status_code == 415
    assert client.get("/api/v1/plates/P-7/target").json()["id"] == current["id"] + 1
    assert client.get("/api/v1/plates/NONE/target").status_code == 404


def test_calibration_upload_and_current(client, bundle_zip):
    assert client.get("/api/v1/calibrations/current").status_code == 404
    with zipfile.ZipFile(io.BytesIO(bundle_zip)) as zf:
        calibration = zf.read("calibration.json")
    r = client.post(
        "/api/v1/calibrations",
        files={"calibration": ("calibration.json", calibration)},
        headers=AUTH,
    )
    assert r.status_code == 201, r.text
    doc = json.loads(calibration)
    current = client.get("/api/v1/calibrations/current").json()
    assert current["id"] == r.json()["id"]
    assert current["image_size"] == doc["image_size"] and current["rms_px"] == doc.get("rms_px")
    bad = dict(doc, R=[[1, 0], [0, 1]])
    r = client.post(
        "/api/v1/calibrations", files={"calibration": ("c.json", json.dumps(bad))}, headers=AUTH
    )
    assert r.status_code == 422 and "R" in r.json()["field"], r.text
    assert client.get("/api/v1/calibrations/current").json()["id"] == current["id"]
    assert len(client.get("/api/v1/calibrations").json()) == 1
