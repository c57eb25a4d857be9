"""Hostile inputs answer 404 or 422 with the project's error body naming the field, never 5xx.

Each case is one a prober (schemathesis) found answering 500 or dropping the connection:
ids and offsets past 64 bits, plate ids with '..', JSON nested 10 000 levels deep or holding a
5 000-digit number, non-finite numbers, physically impossible sizes, booleans taken for integers.
"""

from __future__ import annotations

import json
import math
import re

import pytest
from sqlalchemy import func, select

from app.models import Inspection, LightCalibration, Plate, Target
from app.routes.common import MAX_ROW_ID
from app.schemas import PLATE_ID_MAX_LENGTH, PLATE_ID_REGEX
from app.storage import check_plate_id
from tests.api.helpers import AUTH, rezip, stored_files, target_json

JSON = {**AUTH, "Content-Type": "application/json"}
PAST_64_BITS = str(2**63)
DEEP = "[" * 10_000 + "]" * 10_000
LONG_NUMBER = "1" * 5_000


def _count(client, model) -> int:
    with client.app.state.session_factory() as s:
        return s.scalar(select(func.count()).select_from(model))


def _refused(r, field: str, *, status: int = 422) -> dict:
    """Assert the project's error body naming ``field``; return it."""
    assert r.status_code == status, r.text
    body = r.json()
    assert body["field"] == field, body
    assert isinstance(body["detail"], str) and body["detail"], body
    return body


# ------------------------------------------------------------------ ids and offsets past 64 bits


@pytest.mark.parametrize(
    ("url", "field"),
    [
        (f"/api/v1/inspections/{PAST_64_BITS}", "inspection_id"),
        (f"/api/v1/inspections/{PAST_64_BITS}/artifacts/result.json", "inspection_id"),
        (f"/api/v1/light-calibrations/{PAST_64_BITS}", "light_calibration_id"),
        ("/inspections/99999999999999999999", "inspection_id"),  # dashboard pages
        ("/inspections/99999999999999999999/templates", "inspection_id"),
        ("/api/v1/inspections/0", "inspection_id"),
        ("/api/v1/light-calibrations/-1", "light_calibration_id"),
    ],
)
def test_ids_out_of_range_are_422_naming_the_id(client, url, field):
    body = _refused(client.get(url), field)
    assert field in body["detail"]


@pytest.mark.parametrize(
    "url",
    [
        f"/api/v1/inspections/{MAX_ROW_ID}",
        f"/api/v1/light-calibrations/{MAX_ROW_ID}",
        f"/inspections/{MAX_ROW_ID}",
    ],
)
def test_the_largest_id_is_simply_not_found(client, url):
    assert client.get(url).status_code == 404


@pytest.mark.parametrize(
    "url", ["/api/v1/inspections", "/api/v1/plates", "/api/v1/plates/P-1/inspections"]
)
def test_offsets_past_64_bits_are_422(client, url):
    _refused(client.get(url, params={"offset": PAST_64_BITS}), "offset")
    made = client.post("/api/v1/plates/P-1/inspections/simulated", json={}, headers=AUTH)
    assert made.status_code == 202, made.text  # the plate is known: its list is 200
    r = client.get(url, params={"offset": str(MAX_ROW_ID)})
    assert r.status_code == 200 and r.json()["items"] == [], r.text


# ------------------------------------------------------------------ plate ids


@pytest.mark.parametrize(
    ("method", "path", "kwargs"),
    [
        ("POST", "/inspections/simulated", {"json": {}}),
        ("PUT", "/target", {"content": target_json(), "headers": JSON}),
        ("POST", "/inspections", {"files": {"capture": ("b.zip", b"PK")}}),
        ("GET", "", {}),
        ("GET", "/target", {}),
        ("GET", "/inspections", {}),
    ],
)
@pytest.mark.parametrize(
    "plate_id", ["a..b", "..a", "a" * (PLATE_ID_MAX_LENGTH + 1), "-a", "a b", "a:b"]
)
def test_bad_plate_ids_are_422_everywhere_and_store_nothing(
    client, settings, method, path, kwargs, plate_id
):
    kwargs = {"headers": AUTH, **kwargs}
    r = client.request(method, f"/api/v1/plates/{plate_id}{path}", **kwargs)
    body = _refused(r, "plate_id")
    assert body["detail"].startswith("plate_id: ")
    assert _count(client, Plate) == 0 and stored_files(settings.data_dir) == []


@pytest.mark.parametrize(
    "plate_id",
    [
        "H1234-P07",
        "a",
        "A.b_c-d",
        "a.",
        "a.b.c",
        "a" * 64,
        "a..b",
        "a...",
        "..",
        ".a",
        "_a",
        "a" * 65,
        "a/b",
        "a\\b",
        "",
        "é",
        "a\nb",
        "a.-.b",
        "a-.b",
        "a._b",
    ],
)
def test_the_published_pattern_is_the_storage_rule(plate_id):
    try:
        check_plate_id(plate_id)
        valid = True
    except ValueError:
        valid = False
    published = (
        bool(re.fullmatch(PLATE_ID_REGEX, plate_id)) and len(plate_id) <= PLATE_ID_MAX_LENGTH
    )
    assert published == valid, plate_id


def test_openapi_publishes_the_plate_id_pattern(client):
    spec = client.get("/openapi.json").json()
    params = spec["paths"]["/api/v1/plates/{plate_id}/inspections/simulated"]["post"]["parameters"]
    schema = next(p["schema"] for p in params if p["name"] == "plate_id")
    assert schema["pattern"] == PLATE_ID_REGEX and schema["maxLength"] == PLATE_ID_MAX_LENGTH


# ------------------------------------------------------------------ JSON that breaks parsers


def test_target_nested_10000_levels_is_422(client, settings):
    body = _refused(
        client.put("/api/v1/plates/P-1/target", content=f'{{"format": {DEEP}}}', headers=JSON),
        "target",
    )
    assert "nested deeper" in body["detail"]
    assert str(settings.data_dir) not in body["detail"]
    assert _count(client, Target) == 0 and stored_files(settings.data_dir) == []


def test_target_nested_past_the_depth_limit_names_the_field(client):
    nested = "[" * 100 + "]" * 100
    r = client.put(
        "/api/v1/plates/P-1/target",
        content=f'{{"format": "plate-target/1", "size_mm": {nested}}}',
        headers=JSON,
    )
    assert r.status_code == 422, r.text
    body = r.json()
    assert (
        body["field"].startswith("target: size_mm[0][0]")
        and "nested deeper than 32" in body["detail"]
    )


def test_target_with_a_5000_digit_number_is_422_naming_it(client):
    doc = target_json().decode().replace('"tolerance_mm": 2.0', f'"tolerance_mm": {LONG_NUMBER}')
    body = _refused(
        client.put("/api/v1/plates/P-1/target", content=doc, headers=JSON), "target: tolerance_mm"
    )
    assert "5000" in body["detail"]


def test_deep_and_long_json_in_uploaded_files_are_422(client, settings, bundle_zip):
    files = {
        "capture": ("b.zip", bundle_zip),
        "target": ("t.json", f'{{"format": {DEEP}}}'.encode()),
    }
    body = _refused(
        client.post("/api/v1/plates/P-100/inspections", files=files, headers=AUTH), "target"
    )
    assert body["file"] == "target/target.json" and str(settings.data_dir) not in body["detail"]
    long_tolerance = target_json().replace(
        b'"tolerance_mm": 2.0', f'"tolerance_mm": {LONG_NUMBER}'.encode()
    )
    files["target"] = ("t.json", long_tolerance)
    body = _refused(
        client.post("/api/v1/plates/P-100/inspections", files=files, headers=AUTH),
        "target: tolerance_mm",
    )
    assert "digits" in body["detail"] and str(settings.data_dir) not in body["detail"]
    deep_capture = rezip(bundle_zip, replace={"capture.json": f'{{"format": {DEEP}}}'.encode()})
    body = _refused(
        client.post(
            "/api/v1/plates/P-100/inspections",
            files={"capture": ("b.zip", deep_capture)},
            headers=AUTH,
        ),
        "capture",
    )
    assert "nested deeper" in body["detail"]
    r = client.post(
        "/api/v1/light-calibrations", content=f'{{"lights": {LONG_NUMBER}}}', headers=JSON
    )
    assert "digits" in _refused(r, "lights")["detail"]
    _refused(
        client.post("/api/v1/light-calibrations", content=f'{{"lights": {DEEP}}}', headers=JSON),
        None,
    )
    stl = b"solid x\nendsolid x\n"
    r = client.put(
        "/api/v1/plates/P-1/target",
        files={"mesh": ("p.stl", stl), "target": ("t.json", DEEP)},
        headers=AUTH,
    )
    _refused(r, "target")
    assert _count(client, Inspection) == 0 and _count(client, LightCalibration) == 0


@pytest.mark.parametrize("value", [DEEP, LONG_NUMBER])
def test_simulated_body_that_json_cannot_parse_is_400(client, value):
    r = client.post(
        "/api/v1/plates/P-1/inspections/simulated", content=f'{{"seed": {value}}}', headers=JSON
    )
    body = _refused(r, "body", status=400)
    assert body["detail"].startswith("body: not usable JSON")
    assert _count(client, Inspection) == 0


# ------------------------------------------------------------------ numbers: finite, physical, strict


@pytest.mark.parametrize(
    ("raw", "field"),
    [
        ('{"tolerance_mm": Infinity}', "tolerance_mm"),
        ('{"tolerance_mm": NaN}', "tolerance_mm"),
        ('{"radius_mm": -Infinity}', "radius_mm"),
        ('{"dents": [{"x_mm": NaN, "y_mm": 0, "radius_mm": 100, "depth_mm": 2}]}', "dents.0.x_mm"),
        ('{"seed": false}', "seed"),
        ('{"seed": 1.0}', "seed"),
        ('{"n_lights": "6"}', "n_lights"),
        ('{"width": true}', "width"),
        ('{"convex": 1}', "convex"),
        ('{"noise": "0.1"}', "noise"),
        ('{"radius_mm": 1e308}', "radius_mm"),
        ('{"radius_mm": 10}', "radius_mm"),
        ('{"tolerance_mm": 1e6}', "tolerance_mm"),
        (
            '{"dents": [{"x_mm": 1e300, "y_mm": 0, "radius_mm": 100, "depth_mm": 2}]}',
            "dents.0.x_mm",
        ),
        (
            '{"dents": [{"x_mm": 0, "y_mm": 0, "radius_mm": 100, "depth_mm": 1e12}]}',
            "dents.0.depth_mm",
        ),
    ],
)
def test_simulated_numbers_are_finite_physical_and_strict(client, raw, field):
    r = client.post("/api/v1/plates/P-1/inspections/simulated", content=raw, headers=JSON)
    _refused(r, field)
    assert _count(client, Inspection) == 0


def test_simulated_radius_refusal_says_hull_plate(client):
    r = client.post(
        "/api/v1/plates/P-1/inspections/simulated", json={"radius_mm": 1e308}, headers=AUTH
    )
    assert "hull plate" in _refused(r, "radius_mm")["detail"]
    r = client.post(
        "/api/v1/plates/P-1/inspections/simulated",
        json={"seed": 1, "convex": False, "radius_mm": 2000},
        headers=AUTH,
    )
    assert r.status_code == 202, r.text


@pytest.mark.parametrize(
    ("over", "field", "words"),
    [
        (
            {"shape": {"type": "cylinder", "radius_mm": 1e308}},
            "target: shape.radius_mm",
            "hull plate",
        ),
        ({"shape": {"type": "sphere", "radius_mm": 1.0}}, "target: shape.radius_mm", "hull plate"),
        ({"size_mm": [3000.0, 1e300]}, "target: size_mm[1]", "hull plate"),
        ({"size_mm": [0.001, 3000.0]}, "target: size_mm[0]", "hull plate"),
        ({"tolerance_mm": 1e9}, "target: tolerance_mm", "hull plate"),
        ({"tolerance_mm": math.inf}, "target: tolerance_mm", "finite"),
    ],
)
def test_targets_no_hull_plate_can_be_are_422(client, over, field, words):
    doc = json.dumps(json.loads(target_json()) | over)
    body = _refused(client.put("/api/v1/plates/P-1/target", content=doc, headers=JSON), field)
    assert words in body["detail"]
    assert _count(client, Target) == 0 and _count(client, Plate) == 0


def test_mesh_target_fields_must_be_finite(client):
    import trimesh

    stl = trimesh.exchange.stl.export_stl(trimesh.creation.box(extents=(3000.0, 2000.0, 10.0)))
    for value in ("inf", "nan", "-Infinity", LONG_NUMBER):
        r = client.put(
            "/api/v1/plates/P-1/target",
            files={"mesh": ("plate.stl", stl)},
            data={"size_x_mm": value, "size_y_mm": "2000", "tolerance_mm": "1.5"},
            headers=AUTH,
        )
        assert "finite" in _refused(r, "size_x_mm")["detail"]
    far = trimesh.exchange.stl.export_stl(trimesh.creation.box(extents=(3e9, 2000.0, 10.0)))
    r = client.put(
        "/api/v1/plates/P-1/target",
        files={"mesh": ("plate.stl", far)},
        data={"size_x_mm": "3000", "size_y_mm": "2000", "tolerance_mm": "1.5"},
        headers=AUTH,
    )
    assert "hull plate" in _refused(r, "target: shape.file")["detail"]
    assert _count(client, Target) == 0


def test_light_calibration_lights_out_of_the_cell_are_422(client):
    lights = [
        {
            "position_mm": [1500.0 * math.cos(a), 1500.0 * math.sin(a), 200.0],
            "axis": [0.0, 0.0, 1.0],
            "mu": 1.0,
            "intensity": 1.0,
        }
        for a in (0.0, 2.0, 4.0)
    ]
    lights[1]["position_mm"] = [1e300, 0.0, 0.0]
    r = client.post(
        "/api/v1/light-calibrations",
        json={"format": "light-calibration/1", "lights": lights},
        headers=AUTH,
    )
    body = _refused(r, "lights[1].position_mm")
    assert "within 50000 mm" in body["detail"]
    assert _count(client, LightCalibration) == 0


def test_the_dashboard_cell_form_body_is_still_accepted(client):
    """What web/static/js/cell.js sends (numbers from number inputs, booleans from the select)."""
    body = {
        "shape": "cylinder",
        "radius_mm": 5000,
        "convex": True,
        "n_lights": 12,
        "lights": "near-field",
        "light_manifest": "exact",
        "noise": 0.004,
        "tolerance_mm": 2,
        "width": 1224,
        "height": 1024,
        "seed": 0,
        "dents": [{"x_mm": 300, "y_mm": -200, "radius_mm": 150, "depth_mm": 4}],
        "floor_mm": 600,
        "cutout_radius_mm": 250,
    }
    r = client.post("/api/v1/plates/H7-P11/inspections/simulated", json=body, headers=AUTH)
    assert r.status_code == 202, r.text


def test_a_json_body_json_cannot_parse_is_400_on_every_route(client):
    # The session route has no special handling: the error handler names the body.
    r = client.post("/api/v1/session", content=f'{{"token": {DEEP}}}', headers=JSON)
    body = _refused(r, "body", status=400)
    assert "nested too deeply" in body["detail"]
