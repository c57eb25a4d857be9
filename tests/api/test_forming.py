"""Forming (issue 14) in the service: machines, the pass stored with each inspection, the advice, the export,
and simulated inspections judged against the plate's target."""

from __future__ import annotations

import csv
import io
import json

import pytest

from tests.api.helpers import AUTH, MACHINE, MATERIAL, process, target_json

SMALL = {"n_lights": 3, "width": 160, "height": 128}


def put_target(client, plate_id: str, **over) -> None:
    body = json.loads(target_json(material=MATERIAL))
    body.update(over)
    r = client.put(
        f"/api/v1/plates/{plate_id}/target",
        content=json.dumps(body),
        headers={**AUTH, "Content-Type": "application/json"},
    )
    assert r.status_code == 200, r.text


def inspected_pass(
    client,
    plate_id: str,
    displacement_mm: float,
    radius_mm: float,
    verdict: str,
    *,
    flipped: bool = False,
    **result,
) -> int:
    """A simulated inspection with a process, finished by the service as a job would finish it;
    ``result`` adds keys to its result document (``uncertainty``, ``warnings``)."""
    from app.services import leases as svc

    r = client.post(
        f"/api/v1/plates/{plate_id}/inspections/simulated",
        json={**SMALL, "process": process(displacement_mm, flipped=flipped)},
        headers=AUTH,
    )
    assert r.status_code == 202, r.text
    inspection_id = r.json()["id"]
    document = {
        "format": "plate-result/1",
        "plate_id": plate_id,
        "radius_mm": radius_mm,
        "target_radius_mm": 5000.0,
        "radius_error_pct": 100 * (radius_mm - 5000) / 5000,
        "deviation_mm": {"rms": 1, "max_abs": 3, "p95": 2},
        "tolerance_mm": 2.0,
        "within_tolerance_pct": 90.0,
        "verdict": verdict,
        **result,
    }
    with client.app.state.session_factory() as session:
        assert svc.claim(session=session, inspection_id=inspection_id)
        assert svc.mark_done(session=session, inspection_id=inspection_id, document=document)
        session.commit()
    return inspection_id


@pytest.fixture
def machine(client):
    r = client.put("/api/v1/machines/R3-01", json=MACHINE, headers=AUTH)
    assert r.status_code == 201, r.text
    return r.json()


def test_machines_crud_and_auth(client, machine):
    assert machine["id"] == "R3-01" and machine["bottom_roll_spacing_mm"] == 1400
    assert client.put("/api/v1/machines/R3-02", json=MACHINE).status_code == 401
    r = client.put(
        "/api/v1/machines/R3-01", json={**MACHINE, "top_roll_diameter_mm": 520}, headers=AUTH
    )
    assert r.status_code == 200 and r.json()["top_roll_diameter_mm"] == 520
    assert [m["id"] for m in client.get("/api/v1/machines").json()] == ["R3-01"]
    assert client.get("/api/v1/machines/R3-01").json()["top_roll_diameter_mm"] == 520
    r = client.get("/api/v1/machines/R9")
    assert r.status_code == 404 and r.json()["field"] == "machine_id"


@pytest.mark.parametrize(
    "change, field",
    [
        ({"bottom_roll_spacing_mm": -1}, "bottom_roll_spacing_mm"),
        ({"top_roll_diameter_mm": 0}, "top_roll_diameter_mm"),
        ({"bottom_roll_diameter_mm": "420"}, "bottom_roll_diameter_mm"),
        ({"kind": "four-roll"}, "kind"),
        (
            {"bottom_roll_spacing_mm": 400},
            "bottom_roll_spacing_mm",
        ),  # narrower than the bottom rolls
        ({"extra": 1}, "extra"),
    ],
)
def test_bad_machine_is_422_naming_the_field(client, change, field):
    r = client.put("/api/v1/machines/R3-01", json={**MACHINE, **change}, headers=AUTH)
    assert r.status_code == 422, r.text
    assert r.json()["field"] == field
    assert client.get("/api/v1/machines").json() == []


def test_non_finite_machine_number_is_422(client):
    body = json.dumps(MACHINE).replace("1400", "Infinity")
    r = client.put(
        "/api/v1/machines/R3-01", content=body, headers={**AUTH, "Content-Type": "application/json"}
    )
    assert r.status_code == 422 and r.json()["field"] == "bottom_roll_spacing_mm"


def test_target_material_is_validated(client):
    put_target(client, "P-M1")
    assert (
        client.get("/api/v1/plates/P-M1/target").json()["document"]["material"]["grade"] == "AH36"
    )
    body = json.loads(target_json(material={**MATERIAL, "thickness_mm": -20}))
    r = client.put(
        "/api/v1/plates/P-M1/target",
        content=json.dumps(body),
        headers={**AUTH, "Content-Type": "application/json"},
    )
    assert r.status_code == 422 and "material.thickness_mm" in r.json()["field"], r.text


def test_process_is_stored_and_returned(client, machine, bundle_zip):
    r = client.post(
        "/api/v1/plates/P-100/inspections",
        headers=AUTH,
        files={
            "capture": ("c.zip", bundle_zip),
            "target": ("t.json", target_json(material=MATERIAL)),
        },
        data={"process": json.dumps(process(97.0))},
    )
    assert r.status_code == 202, r.text
    inspection_id = r.json()["id"]
    assert client.get(f"/api/v1/inspections/{inspection_id}").json()["process"] == process(97.0)
    history = client.get("/api/v1/plates/P-100/inspections").json()["items"]
    assert history[0]["process"] == process(97.0)

    r = client.post(
        "/api/v1/plates/P-S1/inspections/simulated",
        json={**SMALL, "process": process(90.0)},
        headers=AUTH,
    )
    assert r.status_code == 202
    assert client.get(f"/api/v1/inspections/{r.json()['id']}").json()["process"] == process(90.0)


@pytest.mark.parametrize(
    "bad, field",
    [
        (process(machine_id="R9"), "process.machine_id"),
        ({**process(), "top_roll_displacement_mm": -3}, "process.top_roll_displacement_mm"),
        ({**process(), "method": "press"}, "process.method"),
    ],
)
def test_bad_process_is_422(client, machine, bundle_zip, bad, field):
    r = client.post(
        "/api/v1/plates/P-S2/inspections/simulated", json={**SMALL, "process": bad}, headers=AUTH
    )
    assert r.status_code == 422 and r.json()["field"] == field, r.text
    r = client.post(
        "/api/v1/plates/P-100/inspections",
        headers=AUTH,
        files={"capture": ("c.zip", bundle_zip), "target": ("t.json", target_json())},
        data={"process": json.dumps(bad)},
    )
    assert r.status_code == 422 and r.json()["field"] == field, r.text
    r = client.post(
        "/api/v1/plates/P-100/inspections",
        headers=AUTH,
        files={"capture": ("c.zip", bundle_zip), "target": ("t.json", target_json())},
        data={"process": "{not json"},
    )
    assert r.status_code == 422 and r.json()["field"] == "process", r.text
    assert client.get("/api/v1/inspections").json()["total"] == 0


def test_advice_nominal_bend_done_reverse(client, machine):
    r = client.get("/api/v1/plates/P-A/advice", params={"machine_id": "R3-01"})
    assert r.status_code == 404

    put_target(client, "P-A")
    r = client.get("/api/v1/plates/P-A/advice")
    assert r.status_code == 422 and r.json()["field"] == "machine_id", r.text
    first = client.get("/api/v1/plates/P-A/advice", params={"machine_id": "R3-01"}).json()
    assert first["action"] == "bend" and first["basis"]["data"] == "nominal only: no history"
    lo, hi = first["expected_radius_range_mm"]
    assert (
        lo < first["expected_radius_mm"] < hi and first["expected_radius_mm"] > 5000
    )  # aimed on the open side

    inspected_pass(client, "P-A", first["top_roll_displacement_mm"], 6200.0, "fail")  # under-bent
    second = client.get("/api/v1/plates/P-A/advice").json()
    assert second["action"] == "bend" and second["machine_id"] == "R3-01"
    assert second["top_roll_displacement_mm"] > first["top_roll_displacement_mm"]
    assert second["basis"]["plate_passes_inspected"] == 1

    inspected_pass(client, "P-A", second["top_roll_displacement_mm"], 5010.0, "pass")
    assert client.get("/api/v1/plates/P-A/advice").json()["action"] == "done"

    put_target(client, "P-B")
    inspected_pass(client, "P-B", 140.0, 4500.0, "fail")  # over-bent
    over = client.get("/api/v1/plates/P-B/advice").json()
    assert over["action"] == "reverse" and over["top_roll_displacement_mm"] is not None
    assert 4500.0 < over["expected_radius_mm"] < 5100.0 and over["basis"]["reverse"]["flipped"]
    # the reverse pass, flipped (its displacement may be negative), and the advice after it
    inspected_pass(client, "P-B", over["top_roll_displacement_mm"], 4800.0, "fail", flipped=True)
    passes = client.get("/api/v1/plates/P-B/inspections").json()
    assert any((i.get("process") or {}).get("flipped") is True for i in passes["items"])
    again = client.get("/api/v1/plates/P-B/advice").json()
    assert (
        again["action"] == "reverse"
        and again["basis"]["reverse"]["reverse_factor"]["reverse_passes"] == 1
    )

    put_target(client, "P-C")  # a new plate: P-A's passes are its history on this machine
    third = client.get("/api/v1/plates/P-C/advice", params={"machine_id": "R3-01"}).json()
    assert third["action"] == "bend" and third["basis"]["machine_plates"] == 2


def test_advice_needs_a_cylinder_with_material(client, machine):
    put_target(client, "P-N", material=None)
    r = client.get("/api/v1/plates/P-N/advice", params={"machine_id": "R3-01"})
    assert r.status_code == 409 and "material" in r.json()["detail"]
    put_target(client, "P-N", shape={"type": "sphere", "radius_mm": 5000.0})
    r = client.get("/api/v1/plates/P-N/advice", params={"machine_id": "R3-01"})
    assert r.status_code == 409 and "cylinder" in r.json()["detail"]
    client.post("/api/v1/plates/P-T/inspections/simulated", json=SMALL, headers=AUTH)
    r = client.get("/api/v1/plates/P-T/advice", params={"machine_id": "R3-01"})
    assert r.status_code == 409 and "no target" in r.json()["detail"]
    put_target(client, "P-N")
    r = client.get("/api/v1/plates/P-N/advice", params={"machine_id": "R9"})
    assert r.status_code == 422 and r.json()["field"] == "machine_id"


def test_forming_history_csv(client, machine):
    put_target(client, "P-H")
    inspected_pass(client, "P-H", 95.0, 6100.0, "fail")
    inspected_pass(client, "P-H", 101.5, 5005.0, "pass")
    client.post(
        "/api/v1/plates/P-H/inspections/simulated", json=SMALL, headers=AUTH
    )  # no process: not a pass
    r = client.get("/api/v1/forming-history.csv")
    assert r.status_code == 200 and r.headers["content-type"].startswith("text/csv")
    rows = list(csv.DictReader(io.StringIO(r.text)))
    assert [
        (
            row["plate_id"],
            row["machine_id"],
            row["grade"],
            row["thickness_mm"],
            row["top_roll_displacement_mm"],
            row["measured_radius_mm"],
            row["verdict"],
        )
        for row in rows
    ] == [
        ("P-H", "R3-01", "AH36", "20", "95.0", "6100.0", "fail"),
        ("P-H", "R3-01", "AH36", "20", "101.5", "5005.0", "pass"),
    ]


def test_simulated_inspection_uses_the_plates_target(client, settings):
    put_target(client, "P-G", tolerance_mm=3.0)
    r = client.post(
        "/api/v1/plates/P-G/inspections/simulated",
        json={**SMALL, "radius_mm": 7000.0},
        headers=AUTH,
    )
    inspection_id = r.json()["id"]
    used = (
        settings.data_dir / "inspections" / str(inspection_id) / "inputs" / "target" / "target.json"
    )
    assert json.loads(used.read_text())["shape"]["radius_mm"] == 5000.0
    summary = client.get("/api/v1/plates/P-G/inspections").json()["items"][0]
    assert summary["target_radius_mm"] == 5000.0 and summary["tolerance_mm"] == 3.0


@pytest.mark.parametrize(
    ("size", "rendered"),
    [([2000.0, 1500.0], [2000.0, 1500.0]), ([6000.0, 2500.0], [3000.0, 2500.0])],
)
def test_a_simulated_plate_has_its_targets_size(client, settings, size, rendered):
    """The demo cell renders the plate at its target's size (so that outline and target agree), each
    side at most the 3 m its cameras see."""
    from app.services.inspections import simulation_specs

    put_target(client, "P-SIZE", size_mm=size)
    r = client.post("/api/v1/plates/P-SIZE/inspections/simulated", json=SMALL, headers=AUTH)
    assert r.status_code == 202, r.text
    folder = settings.data_dir / "inspections" / str(r.json()["id"]) / "inputs"
    simulation = json.loads((folder / "simulation.json").read_text())
    assert simulation["size_mm"] == rendered
    plate, _capture = simulation_specs(simulation)
    assert plate.size_mm == tuple(rendered)


def test_under_bent_simulated_plate_fails(tmp_path):
    """The real pipeline: a plate rendered at 7 m against its 5 m target fails."""
    from fastapi.testclient import TestClient

    from app.jobs import execute_inspection
    from app.main import create_app
    from app.settings import Settings
    from tests.api.helpers import TOKEN

    settings = Settings(data_dir=tmp_path / "real", api_token=TOKEN, progress_interval_s=0.05)
    app = create_app(settings)
    try:
        with TestClient(app) as client:
            put_target(client, "P-U")
            r = client.post(
                "/api/v1/plates/P-U/inspections/simulated",
                json={"width": 320, "height": 256, "n_lights": 8, "seed": 5, "radius_mm": 7000.0},
                headers=AUTH,
            )
            inspection_id = r.json()["id"]
            state = client.app.state
            assert (
                execute_inspection(
                    inspection_id,
                    settings=settings,
                    session_factory=state.session_factory,
                    storage=state.storage,
                )
                == "done"
            )
            body = client.get(f"/api/v1/inspections/{inspection_id}").json()
            assert body["result"]["target_radius_mm"] == 5000.0
            assert body["verdict"] == "fail", body["result"]
            assert body["result"]["radius_mm"] > 6000
    finally:
        app.state.engine.dispose()


def test_advice_takes_each_inspections_uncertainty(client, machine):
    put_target(client, "P-U")
    first = client.get("/api/v1/plates/P-U/advice", params={"machine_id": "R3-01"}).json()
    inspected_pass(
        client,
        "P-U",
        first["top_roll_displacement_mm"],
        6200.0,
        "fail",
        uncertainty={"k": 2, "radius_mm": 31.0, "deviation_mm": 0.4},
        warnings=["the measurement is not capable for the tolerance (TUR 2.6 < 4)"],
    )
    advice = client.get("/api/v1/plates/P-U/advice").json()
    assert advice["action"] == "bend"
    entry = advice["basis"]["inspections"][0]
    assert entry["radius_uncertainty_mm"] == 15.5 and entry["capable"] is False
    assert any("not capable" in w and "pass 1" in w for w in advice["basis"]["warnings"])
    # an older result without uncertainty keeps the model's constant
    put_target(client, "P-O")
    inspected_pass(client, "P-O", first["top_roll_displacement_mm"], 6200.0, "fail")
    older = client.get("/api/v1/plates/P-O/advice").json()
    assert older["basis"]["inspections"][0]["radius_uncertainty_mm"] is None
    assert older["basis"]["inspections"][0]["capable"] is True
