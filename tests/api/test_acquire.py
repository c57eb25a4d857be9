"""POST /plates/{plate_id}/inspections/acquire end to end: the web app, a real consumer process, real devices.

The cells: the demo cell (simulated cameras and lights, as demo mode writes it, smaller), and the
acceptance cell (left camera Aravis' ``arv-fake-gv-camera-0.8`` over loopback, right camera
Aravis' in-process ``Fake_1``, the tests' TCP light controller). SQLite migrated by Alembic,
the consumer as in tests/api/test_jobs.py.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from app.main import create_app
from app.models import Inspection
from app.services.cell import CELL_DIR, DEMO_CELL_DIR, CellLock
from app.settings import Settings
from pipeline.acquisition import write_demo_cell
from pipeline.io import load_capture
from tests.acquisition.helpers import HEIGHT, WIDTH, tcp_lights, write_cell
from tests.api.helpers import (
    AUTH,
    FAKE_INSPECT,
    TOKEN,
    Consumer,
    invocations,
    pdf_text,
    target_json,
    wait_for,
    wait_until,
)

N = 6
FAKE_1 = {"driver": "aravis", "device_id": "Fake_1"}
#: Configured exposures: no auto-exposure pre-shots.
FIXED_FAKE_1 = {**FAKE_1, "exposure_us": 5000.0}
FIXED_SIMULATED = {"driver": "simulated", "exposure_us": 5000.0}
#: Light by light in image order: on, frame, off.
SEQUENCE = [c for k in range(N) for c in (f"L{k} ON", f"L{k} OFF")]
ALL_ON = [f"L{k} ON" for k in range(N)]
ALL_OFF = [f"L{k} OFF" for k in range(N)]
CYLINDER = json.loads(target_json())
#: A forming pass (the ``process`` of the inspection routes) on machine R3-01.
PASS = {"method": "roll-bending", "machine_id": "R3-01", "top_roll_displacement_mm": 97.0}
MACHINE = {
    "kind": "three-roll-pyramid",
    "bottom_roll_spacing_mm": 1400,
    "bottom_roll_diameter_mm": 420,
    "top_roll_diameter_mm": 500,
}


@pytest.fixture
def service(tmp_path):
    """A factory: ``service(**settings)`` -> TestClient of create_app on ``tmp_path/data`` (token, fake pipeline)."""
    apps = []

    def make(**overrides) -> TestClient:
        settings = Settings(
            **{
                "data_dir": tmp_path / "data",
                "api_token": TOKEN,
                "progress_interval_s": 0.05,
                "inspect_entry": FAKE_INSPECT,
                **overrides,
            }
        )
        app = create_app(settings)
        apps.append(app)
        return TestClient(app)

    yield make
    for app in apps:
        app.state.engine.dispose()


@pytest.fixture
def consumers():
    """A factory of started consumers (tests/api/conftest.py's Consumer), all stopped after the test."""
    started = []

    def start(settings: Settings, **kw) -> Consumer:
        started.append(Consumer(settings, **kw).start())
        return started[-1]

    yield start
    for consumer in started:
        consumer.stop()


def _demo_service(service, tmp_path, **overrides) -> TestClient:
    """Demo mode with a demo cell written first, smaller than the default one (kept by the service)."""
    write_demo_cell(tmp_path / "data" / DEMO_CELL_DIR, n_lights=N, width=WIDTH, height=HEIGHT)
    return service(demo=True, **overrides)


def _acquire(client, plate_id, headers=AUTH, **body):
    return client.post(
        f"/api/v1/plates/{plate_id}/inspections/acquire", json=body or None, headers=headers
    )


def _put_machine(client) -> None:
    r = client.put("/api/v1/machines/R3-01", json=MACHINE, headers=AUTH)
    assert r.status_code in (200, 201), r.text


def _inputs(client, inspection_id) -> Path:
    return client.app.state.storage.inputs_dir(inspection_id)


def _row(client, inspection_id) -> Inspection:
    with client.app.state.session_factory() as session:
        return session.get(Inspection, inspection_id)


# ------------------------------------------------------------------ the demo cell


def test_demo_cell_acquires_then_inspects(service, consumers, tmp_path):
    calls = tmp_path / "invocations.txt"
    client = _demo_service(service, tmp_path)
    health = client.get("/healthz").json()["cell"]
    assert (health["ready"], health["cell_id"], health["demo"]) == (True, "demo", True)
    assert [(c["side"], c["state"], c["model"], c["serial"]) for c in health["cameras"]] == [
        ("left", "connected", "simulated camera", "SIM-LEFT"),
        ("right", "connected", "simulated camera", "SIM-RIGHT"),
    ]
    consumer = consumers(client.app.state.settings, invocations=calls)

    r = _acquire(client, "DEMO-7")  # no body: the plate's target, here the demo cell's
    assert r.status_code == 202, r.text
    body = wait_for(client, r.json()["id"], consumer=consumer)

    assert body["status"] == "done", body
    assert (body["source"], body["cell_id"], body["stage"]) == ("acquired", "demo", "done")
    assert body["result"]["plate_id"] == "DEMO-7" and body["result"]["target_radius_mm"] == 5000.0
    # from the last frame's arrival to the result: beyond the inspection's own time, not before it
    after = body["result"]["timings_s"]["after_last_frame"]
    assert body["result"]["timings_s"]["total"] <= after < 60.0
    assert client.get("/api/v1/plates/DEMO-7/target").json()["radius_mm"] == 5000.0
    # the bundle the cell took is what the pipeline ran on (the test double loads it), once
    capture = load_capture(_inputs(client, body["id"]) / "bundle")
    assert (capture.plate_id, capture.n_lights, capture.images.shape) == (
        "DEMO-7",
        N,
        (N, HEIGHT, WIDTH),
    )
    assert [event for event, *_ in invocations(calls)] == ["start", "end"]
    record = client.get(body["artifacts"]["capture.json"]).json()["acquisition"]
    assert record["cell_id"] == "demo" and record["light_controller"] == {
        "driver": "simulated",
        "n_lights": N,
    }
    assert [f["file"] for f in record["frames"]] == (
        ["stereo_left.png", "stereo_right.png", "dark.png"] + [f"ps_{k:02d}.png" for k in range(N)]
    )
    assert json.loads((_inputs(client, body["id"]) / "acquisition.json").read_text()) == {
        "cell_id": "demo",
        "config": "cell.json",
    }
    # the signed report names the cell and the cameras' serials from the bundle's record
    report = client.get(f"/api/v1/inspections/{body['id']}/report.pdf")
    assert report.status_code == 200, report.text
    flat = " ".join(pdf_text(report.content, tmp_path).split())
    assert "Camera serials L SIM-LEFT, R SIM-RIGHT" in flat and "Cell demo" in flat
    assert f"Inspection #{body['id']} (acquired)" in flat
    # the cameras' last frames, for the Cell page
    for side in ("left", "right"):
        thumb = client.get(f"/cell/cameras/{side}.png")
        assert thumb.status_code == 200 and thumb.content.startswith(b"\x89PNG")
    assert (
        f'src="/cell/cameras/left.png?inspection={body["id"]}"' in client.get("/cell/cameras").text
    )


# ------------------------------------------------------------------ the acceptance cell: Aravis' fake cameras, TCP lights


def test_acceptance_cell_gige_and_fake_cameras_tcp_lights(
    service, consumers, tmp_path, fake_gv, light_server
):
    """Left camera arv-fake-gv-camera (GigE Vision over loopback), right Fake_1, the tests' TCP lights, the real pipeline."""
    seen = []  # the job's stage and status when the first light is switched on
    client_box = []

    def on_command(command: str) -> None:
        if command == "L0 ON" and not seen:
            row = _row(client_box[0], 1)
            seen.append((row.status, row.stage))

    server = light_server(on_command=on_command)
    left = {"driver": "aravis", "device_id": fake_gv.device_id}
    config = write_cell(
        tmp_path / "cell", left=left, right=FAKE_1, lights=tcp_lights(server), n_lights=N
    )
    # the fake GigE camera is a process of its own: on a machine busy with other tests (the suite
    # runs a worker per core) its frames can take seconds; the timeout is the cell's setting
    client = service(cell_config=config, inspect_entry="pipeline.run:inspect", frame_timeout_s=15.0)
    client_box.append(client)

    health = client.get("/healthz").json()["cell"]
    assert (health["ready"], health["cell_id"], health["demo"], health["in_use"]) == (
        True,
        "cell-test",
        False,
        None,
    )
    cams = {c["side"]: c for c in health["cameras"]}
    assert (cams["left"]["state"], cams["left"]["model"], cams["left"]["serial"]) == (
        "connected",
        "Fake",
        fake_gv.serial,
    )
    assert (cams["right"]["state"], cams["right"]["model"], cams["right"]["device_id"]) == (
        "connected",
        "Fake",
        "Fake_1",
    )
    consumer = consumers(client.app.state.settings)

    r = _acquire(client, "ACC-0001", target=CYLINDER)
    assert r.status_code == 202, r.text
    body = wait_for(client, r.json()["id"], timeout_s=180, consumer=consumer)

    assert seen == [("running", "capture")]  # the capture stage while the lights are switched
    # a fake pattern is no plate: measured or refused as not measurable, never a capture or internal failure
    assert body["status"] == "done" or not body["error"].startswith(
        ("acquisition failed", "internal error")
    ), body
    assert body["stage"] not in (None, "capture")  # the pipeline's stages ran after the capture
    capture = load_capture(_inputs(client, body["id"]) / "bundle")
    assert (capture.plate_id, capture.n_lights, capture.bit_depth) == ("ACC-0001", N, 16)
    assert capture.images.shape == (N, HEIGHT, WIDTH) and capture.stereo_right.shape == (
        HEIGHT,
        WIDTH,
    )
    record = json.loads((_inputs(client, body["id"]) / "bundle" / "capture.json").read_text())[
        "acquisition"
    ]
    assert record["cell_id"] == "cell-test" and record["config"] == "cell.json"
    gv, fake = record["cameras"]["left"], record["cameras"]["right"]
    assert (gv["model"], gv["serial"], gv["protocol"]) == ("Fake", fake_gv.serial, "GigE Vision")
    assert (fake["model"], fake["device_id"]) == ("Fake", "Fake_1")
    assert (
        record["light_controller"]["address"] == server.address
        and record["light_controller"]["replies"] is True
    )
    assert len(record["frames"]) == N + 3
    # auto-exposure pre-shots under all lights, then one per light, light by light, the stereo pair
    assert server.commands == ALL_ON + ALL_OFF + SEQUENCE + ALL_ON + ALL_OFF + SEQUENCE
    assert (
        client.get(f"/api/v1/inspections/{body['id']}/artifacts/capture.json").json()["acquisition"]
        == record
    )
    last = json.loads((tmp_path / "data" / CELL_DIR / "state.json").read_text())
    assert (
        last["inspection_id"] == body["id"] and last["cameras"]["left"]["serial"] == fake_gv.serial
    )


def test_controller_refusing_fails_the_job_naming_device_and_step(
    service, consumers, tmp_path, light_server
):
    calls = tmp_path / "invocations.txt"
    server = light_server(refuse="L2 ON")
    # a flood light for the stereo pair: "L2 ON" comes only with photometric image 2
    lights = tcp_lights(server, stereo_on="FLOOD ON\n", stereo_off="FLOOD OFF\n")
    config = write_cell(tmp_path / "cell", left=FIXED_FAKE_1, right=FIXED_SIMULATED, lights=lights)
    client = service(cell_config=config)
    consumer = consumers(client.app.state.settings, invocations=calls)

    r = _acquire(client, "P-REFUSED", target=CYLINDER)
    assert r.status_code == 202, r.text
    body = wait_for(client, r.json()["id"], consumer=consumer)

    assert (body["status"], body["verdict"], body["stage"]) == ("error", None, "capture")
    assert body["error"] == (
        f"acquisition failed: light controller {server.address}: photometric image 2 (ps_02.png): "
        "refused 'L2 ON': answered 'ERR refused'"
    )
    assert server.commands == ["FLOOD ON", "FLOOD OFF", *SEQUENCE[:6]]  # light 2 switched off again
    assert invocations(calls) == []  # nothing to inspect
    inputs = _inputs(client, body["id"])
    assert sorted(p.name for p in inputs.iterdir()) == [
        "acquisition.json",
        "target",
    ]  # kept; no partial bundle


def test_consumer_of_another_cell_fails_the_job(service, tmp_path):
    from app.jobs import execute_inspection

    client = _demo_service(service, tmp_path)
    inspection_id = _acquire(client, "P-OTHER", target=CYLINDER).json()["id"]
    other = write_cell(
        tmp_path / "other",
        left=FIXED_SIMULATED,
        right=FIXED_SIMULATED,
        lights={"driver": "simulated"},
    )
    settings = client.app.state.settings.model_copy(update={"cell_config": other})
    state = client.app.state
    assert (
        execute_inspection(
            inspection_id,
            settings=settings,
            session_factory=state.session_factory,
            storage=state.storage,
        )
        == "error"
    )
    assert client.get(f"/api/v1/inspections/{inspection_id}").json()["error"] == (
        "cell_id: the job was queued for cell 'demo', this consumer's cell (cell.json) is 'cell-test'"
    )


# ------------------------------------------------------------------ refusals


def test_no_cell_outside_demo_is_409_naming_the_setting(service):
    client = service()
    r = _acquire(client, "P-1", target=CYLINDER)
    assert r.status_code == 409, r.text
    assert r.json()["detail"].startswith(
        "PLATE_INSPECT_CELL_CONFIG: no cell is configured on this server"
    )
    assert client.get("/api/v1/inspections").json()["total"] == 0
    assert client.get("/healthz").json()["cell"] is None
    page = client.get("/cell").text
    assert re.search(
        r'<button type="button" id="capture"[^>]* disabled title="PLATE_INSPECT_CELL_CONFIG: no cell',
        page,
    )
    assert "Capture unavailable: PLATE_INSPECT_CELL_CONFIG" in page


def test_a_bad_cell_config_is_409_naming_file_and_field(service, tmp_path):
    config = write_cell(
        tmp_path / "cell",
        left={"driver": "aravis"},
        right=FIXED_SIMULATED,
        lights={"driver": "simulated"},
    )
    client = service(cell_config=config)
    r = _acquire(client, "P-1")
    assert r.status_code == 409, r.text
    assert r.json()["detail"] == (
        "PLATE_INSPECT_CELL_CONFIG: the cell's configuration is not usable: cell.json: cameras.left.device_id: "
        "missing required key (an aravis camera is opened by its device id)"
    )
    health = client.get("/healthz").json()["cell"]
    assert (health["ready"], health["reason"], health["cameras"]) == (False, r.json()["detail"], [])


def test_a_cell_over_the_light_limit_is_409_naming_the_setting(service, tmp_path):
    config = write_cell(
        tmp_path / "cell",
        left=FIXED_SIMULATED,
        right=FIXED_SIMULATED,
        lights={"driver": "simulated"},
    )
    r = _acquire(service(cell_config=config, max_lights=4), "P-1")
    assert r.status_code == 409, r.text
    assert (
        "cell.json: lights.lights: 6 lights, more than the limit of 4 (the server setting PLATE_INSPECT_MAX_LIGHTS"
        in r.json()["detail"]
    )


def test_writes_need_the_token(service, tmp_path):
    client = _demo_service(service, tmp_path)
    assert _acquire(client, "P-1", headers={}).status_code == 401
    assert _acquire(client, "P-1", headers={"Authorization": "Bearer wrong"}).status_code == 401
    assert client.get("/api/v1/inspections").json()["total"] == 0


@pytest.mark.parametrize(
    ("body", "field"),
    [
        (
            {"target": {**CYLINDER, "shape": {"type": "cylinder", "radius_mm": 5.0}}},
            "target: shape.radius_mm",
        ),
        ({"target": {**CYLINDER, "tolerance_mm": -1.0}}, "target: tolerance_mm"),
        ({"process": PASS | {"machine_id": "R9"}}, "process.machine_id"),  # no such machine
        ({"process": PASS | {"top_roll_displacement_mm": 0}}, "process.top_roll_displacement_mm"),
        ({"process": PASS | {"method": "press"}}, "process.method"),
        ({"process": True}, "process"),
        ({"cell": "demo"}, "cell"),  # unknown keys are refused
    ],
)
def test_bad_target_or_process_is_422_and_stores_nothing(service, tmp_path, body, field):
    client = _demo_service(service, tmp_path)
    _put_machine(client)
    r = _acquire(client, "P-1", **body)
    assert r.status_code == 422 and r.json()["field"] == field, r.text
    assert client.get("/api/v1/inspections").json()["total"] == 0
    assert client.get("/api/v1/plates/P-1/target").status_code == 404


def test_target_and_process_are_kept(service, tmp_path):
    client = _demo_service(service, tmp_path)
    _put_machine(client)
    r = _acquire(
        client,
        "P-1",
        target={**CYLINDER, "shape": {"type": "sphere", "radius_mm": 7000.0}},
        process=PASS,
    )
    assert r.status_code == 202, r.text
    assert (
        client.get("/api/v1/plates/P-1/target").json()["shape"] == "sphere"
    )  # the plate's target now
    body = client.get(f"/api/v1/inspections/{r.json()['id']}").json()
    assert (body["process"], body["cell_id"], body["source"]) == (PASS, "demo", "acquired")
    assert (
        json.loads((_inputs(client, body["id"]) / "target" / "target.json").read_text())["shape"][
            "radius_mm"
        ]
        == 7000.0
    )


def test_no_target_outside_demo_is_422(service, tmp_path):
    config = write_cell(
        tmp_path / "cell",
        left=FIXED_SIMULATED,
        right=FIXED_SIMULATED,
        lights={"driver": "simulated"},
    )
    r = _acquire(service(cell_config=config), "P-1")
    assert r.status_code == 422 and r.json()["field"] == "target", r.text


def test_queue_cap_applies(service, tmp_path):
    client = _demo_service(service, tmp_path, max_queued_per_plate=1)
    assert _acquire(client, "P-1").status_code == 202
    r = _acquire(client, "P-1")
    assert r.status_code == 429 and int(r.headers["Retry-After"]) >= 1, r.text
    assert client.get("/api/v1/inspections").json()["total"] == 1


# ------------------------------------------------------------------ the cameras' state


def test_cameras_are_not_checked_while_a_capture_holds_them(service, tmp_path):
    missing = {"driver": "aravis", "device_id": "Nobody-0000"}
    config = write_cell(
        tmp_path / "cell", left=missing, right=FIXED_SIMULATED, lights={"driver": "simulated"}
    )
    client = service(cell_config=config)
    lock = CellLock(tmp_path / "data")
    assert lock.acquire("inspection 41 (acquiring)")  # as the consumer holds it during a capture
    try:
        health = client.get("/healthz").json()["cell"]
    finally:
        lock.release()
    assert health["in_use"] == "inspection 41 (acquiring)"
    assert [(c["side"], c["state"]) for c in health["cameras"]] == [
        ("left", "unknown"),
        ("right", "unknown"),
    ]

    health = client.get("/healthz").json()["cell"]  # free again: checked
    cams = {c["side"]: c for c in health["cameras"]}
    assert health["in_use"] is None
    assert cams["left"]["state"] == "unreachable" and cams["right"]["state"] == "connected"


def test_a_camera_that_does_not_answer_in_time_is_reported_unreachable_without_waiting_for_it(
    tmp_path,
):
    """Aravis looks for a missing camera for about a second; the check is waited for 0.1 s, then not at all."""
    from app.services.camera_monitor import CameraMonitor

    missing = {"driver": "aravis", "device_id": "Nobody-0000"}
    config = write_cell(
        tmp_path / "cell", left=missing, right=FIXED_SIMULATED, lights={"driver": "simulated"}
    )
    monitor = CameraMonitor(Settings(data_dir=tmp_path / "data", cell_config=config), timeout_s=0.1)

    for _ in range(2):  # the first call starts the check, the second finds it still running
        cameras = monitor.state().cameras
        assert [(c.state, c.detail) for c in cameras] == [
            ("unreachable", "no answer within 0.1 s")
        ] * 2
    cameras = wait_until(
        lambda: (c := monitor.state().cameras)[0].detail != "no answer within 0.1 s" and c, 30
    )
    assert (cameras[0].state, cameras[0].detail) == (
        "unreachable",
        "opening: Device 'Nobody-0000' not found",
    )
    assert (cameras[1].state, cameras[1].serial) == ("connected", "SIM-RIGHT")


# ------------------------------------------------------------------ a cell with a conveyor: every station


def test_a_station_that_fails_while_the_next_is_photographed_is_the_jobs_error(
    service, consumers, tmp_path
):
    """Issue 29: each station is reconstructed while the next is photographed; one that fails there
    is the job's error, naming the station's bundle (tests/api/failing_station.py: station 1
    loses its capture.json in the early reconstruction's links only)."""
    write_demo_cell(
        tmp_path / "data" / DEMO_CELL_DIR, n_lights=6, width=320, height=256, stations=3
    )
    client = service(demo=True, inspect_entry="tests.api.failing_station:inspect")
    consumer = consumers(client.app.state.settings)
    r = _acquire(client, "LONG-2")
    assert r.status_code == 202, r.text
    body = wait_for(client, r.json()["id"], consumer=consumer, timeout_s=600)
    assert body["status"] == "error", body
    assert body["error"] == (
        "bundle/station_01/capture.json: file not found (a capture bundle folder must hold capture.json)"
    )
    bundle = _inputs(client, body["id"]) / "bundle"
    # every station was still photographed, and nothing of the early reconstruction is left
    assert sorted(p.name for p in bundle.iterdir()) == ["station_00", "station_01", "station_02"]
    assert sorted(p.name for p in bundle.parent.iterdir()) == sorted(
        ["acquisition.json", "bundle", "target"]
    )


def test_a_conveyor_cell_acquires_every_station_and_measures_one_plate(
    service, consumers, tmp_path
):
    """Issue 29: an acquire job on a cell with a conveyor photographs each station (the simulated
    conveyor's encoder a few mm off, the plate yawing) and the real pipeline measures them as one plate."""
    from pipeline.run import inspect

    write_demo_cell(
        tmp_path / "data" / DEMO_CELL_DIR, n_lights=6, width=640, height=512, stations=3
    )
    client = service(demo=True, inspect_entry=inspect)
    consumer = consumers(client.app.state.settings)
    r = _acquire(client, "LONG-1")  # the demo cell's target: the whole plate
    assert r.status_code == 202, r.text
    body = wait_for(client, r.json()["id"], consumer=consumer, timeout_s=600)
    assert body["status"] == "done", body
    result = body["result"]
    assert result["verdict"] == "pass", result
    assert abs(result["radius_error_pct"]) < 0.1
    bundle = _inputs(client, body["id"]) / "bundle"
    stations = sorted(p.name for p in bundle.iterdir())
    assert stations == ["station_00", "station_01", "station_02"]
    assert [load_capture(bundle / s).station.index for s in stations] == [0, 1, 2]
    details = client.get(body["artifacts"]["details.json"]).json()
    assert [s["index"] for s in details["stations"]["stations"]] == [0, 1, 2]
    # the measured travel against the encoder's: each a few mm off, refined on the overlaps
    for station in details["stations"]["stations"][1:]:
        assert abs(station["travel_mm"] - station["travel_encoder_mm"]) < 10.0
    record = client.get(body["artifacts"]["capture.json"]).json()["acquisition"]
    assert record["conveyor"]["driver"] == "simulated"
    # the report reads the stations' acquisition record and calibration from the acquired bundles
    report = client.get(f"/api/v1/inspections/{body['id']}/report.pdf")
    assert report.status_code == 200, report.text
    flat = " ".join(pdf_text(report.content, tmp_path).split())
    assert "Camera serials L SIM-LEFT, R SIM-RIGHT" in flat
