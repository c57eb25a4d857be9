"""A plate longer than the view uploaded as its conveyor stations (issue 29): several multipart parts
``capture`` or one zip of station folders, checked as a set before anything is queued, measured as one
plate by the real pipeline in a real consumer (helpers.render_stations: 3 stations at 320 x 256 px).
"""

from __future__ import annotations

import io
import re
import time
import zipfile

import pytest
from sqlalchemy import func, select

from app.models import Inspection, Plate
from tests.api.helpers import (
    AUTH,
    STATIONS_PLATE,
    TOKEN,
    Consumer,
    edit_capture_json,
    pdf_text,
    rezip,
    stored_files,
)

URL = f"/api/v1/plates/{STATIONS_PLATE}/inspections"


def _count(client, model) -> int:
    with client.app.state.session_factory() as s:
        return s.scalar(select(func.count()).select_from(model))


def _as_parts(bundles: list[bytes], names=None) -> list[tuple[str, tuple[str, bytes, str]]]:
    names = names or [f"s{i}.zip" for i in range(len(bundles))]
    return [("capture", (n, b, "application/zip")) for n, b in zip(names, bundles, strict=True)]


def _post(client, files, target: bytes):
    return client.post(
        URL, files=[*files, ("target", ("target.json", target, "application/json"))], headers=AUTH
    )


@pytest.fixture
def real_service(tmp_path):
    """The app and a consumer running the production entry point (pipeline.run:inspect)."""
    from fastapi.testclient import TestClient

    from app.main import create_app
    from app.settings import Settings

    settings = Settings(data_dir=tmp_path / "real", api_token=TOKEN, progress_interval_s=0.05)
    app = create_app(settings)
    consumer = Consumer(settings).start()
    try:
        with TestClient(app) as client:
            yield client, settings, consumer
    finally:
        consumer.stop()
        app.state.engine.dispose()


def _follow(client, inspection_id: int, consumer, timeout_s: float = 180.0) -> tuple[dict, set]:
    """Poll the inspection until it is done or failed; its last body and every stage seen."""
    stages, deadline = set(), time.monotonic() + timeout_s
    while True:
        body = client.get(f"/api/v1/inspections/{inspection_id}").json()
        stages.add(body.get("stage"))
        if body["status"] in ("done", "error"):
            return body, stages
        assert time.monotonic() < deadline, consumer.output()
        time.sleep(0.03)


def test_stations_as_parts_and_as_one_zip_are_measured_as_one_plate(real_service, station_bundles):
    client, settings, consumer = real_service
    target = station_bundles["target"]
    # sent out of order: the station field orders them
    parts = _as_parts(station_bundles["parts"][::-1], ["c.zip", "b.zip", "a.zip"])
    ids = [
        _post(client, parts, target).json()["id"],
        _post(client, [("capture", ("plate.zip", station_bundles["folders"]))], target).json()[
            "id"
        ],
    ]
    for inspection_id in ids:
        body, stages = _follow(client, inspection_id, consumer)
        assert body["status"] == "done", body
        assert body["result"]["verdict"] == "pass", body["result"]
        assert body["result"]["plate_id"] == STATIONS_PLATE
        assert any(
            s and s.startswith("station ") and s[8:12] in ("1/3:", "2/3:", "3/3:") for s in stages
        ), stages
        details = client.get(f"/api/v1/inspections/{inspection_id}/artifacts/details.json").json()
        stations = details["stations"]["stations"]
        assert [s["index"] for s in stations] == [0, 1, 2]
        assert all(len(s["footprint_mm"]) == 4 for s in stations)
        inputs = settings.data_dir / "inspections" / str(inspection_id) / "inputs"
        kept = sorted(p.name for p in (inputs / "stations").iterdir())
        assert kept == ["station_00.zip", "station_01.zip", "station_02.zip"]
        plate_map = client.get(f"/api/v1/inspections/{inspection_id}/plate-map").json()
        assert [s["index"] for s in plate_map["stations"]] == [0, 1, 2]
        # the map spans the whole plate (7.5 m along y), not one view
        x0, x1, y0, y1 = plate_map["extent_mm"]
        assert y1 - y0 > 7000.0 and x1 - x0 < 3500.0
    _report_lists_the_stations(client, ids[0], settings.data_dir)


def _report_lists_the_stations(client, inspection_id: int, folder) -> None:
    """The PDF report of a plate at stations: a stations table, a row per station, beside the map."""
    r = client.get(f"/api/v1/inspections/{inspection_id}/report.pdf")
    assert r.status_code == 200, r.text
    text = pdf_text(r.content, folder)
    assert "Stations" in text and "Travel registered" in text and "Overlap RMS" in text, text
    details = client.get(f"/api/v1/inspections/{inspection_id}/artifacts/details.json").json()
    for s in details["stations"]["stations"]:
        travel = f"{s['travel_mm']:.1f} mm"
        assert re.search(rf"^\s*{s['index']}\s+{re.escape(travel)}", text, re.M), (travel, text)
    assert "The plate was measured at 3 conveyor stations" in " ".join(text.split())


def test_a_job_that_fails_keeps_every_station_and_says_why(real_service, station_bundles):
    client, settings, consumer = real_service
    bundles = list(station_bundles["parts"])
    # a station whose image is cut short after its header: accepted (headers only), refused when decoded
    with zipfile.ZipFile(io.BytesIO(bundles[1])) as zf:
        png = zf.read("ps_02.png")
    bundles[1] = rezip(bundles[1], replace={"ps_02.png": png[: len(png) // 3]})
    r = _post(client, _as_parts(bundles), station_bundles["target"])
    assert r.status_code == 202, r.text
    body, _ = _follow(client, r.json()["id"], consumer)
    assert body["status"] == "error", body
    assert "stations/station_01.zip" in body["error"] and "ps_02.png" in body["error"], body
    inputs = settings.data_dir / "inspections" / str(body["id"]) / "inputs"
    assert sorted(p.name for p in (inputs / "stations").iterdir()) == [
        "station_00.zip",
        "station_01.zip",
        "station_02.zip",
    ]


def _duplicate(parts: list[bytes]) -> list[bytes]:
    return [parts[0], parts[1], parts[1]]


def _mixed_plates(parts: list[bytes]) -> list[bytes]:
    return [parts[0], edit_capture_json(parts[1], lambda d: d.update(plate_id="OTHER")), parts[2]]


def _without_station(parts: list[bytes]) -> list[bytes]:
    return [parts[0], parts[1], edit_capture_json(parts[2], lambda d: d.pop("station"))]


BAD_SETS = [
    (_duplicate, 2, "capture: station.index", "duplicate station index 1"),
    (_mixed_plates, 1, "capture: plate_id", "'OTHER'"),
    (_without_station, 2, "capture: station", "expected a station"),
]


@pytest.mark.parametrize(("bad", "culprit", "field", "words"), BAD_SETS)
def test_a_bad_set_of_parts_is_refused_naming_the_part_and_nothing_is_queued(
    client, settings, station_bundles, bad, culprit, field, words
):
    before = stored_files(settings.data_dir)
    r = _post(client, _as_parts(bad(station_bundles["parts"])), station_bundles["target"])
    assert r.status_code == 422, r.text
    body = r.json()
    assert body["field"] == field, body
    assert body["file"] == f"s{culprit}.zip:capture.json", body
    assert body["detail"].startswith(f"s{culprit}.zip:capture.json: ") and words in body["detail"]
    assert str(settings.data_dir) not in body["detail"]
    assert _count(client, Inspection) == 0 and _count(client, Plate) == 0
    assert stored_files(settings.data_dir) == before


@pytest.mark.parametrize(("bad", "culprit", "field", "words"), BAD_SETS)
def test_a_bad_zip_of_station_folders_is_refused_naming_the_folder(
    client, settings, station_bundles, bad, culprit, field, words
):
    """The folders of the zip are station_00/ .. station_02/ in one top folder; the bad set puts the
    culprit's bundle in its folder (a duplicate: station 1's bundle in station_02/)."""
    members = {}
    for i, bundle in enumerate(bad(station_bundles["parts"])):
        with zipfile.ZipFile(io.BytesIO(bundle)) as zf:
            for name in zf.namelist():
                members[f"LONG-1/station_{i:02d}/{name}"] = zf.read(name)
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        for name, data in members.items():
            zf.writestr(name, data)
    before = stored_files(settings.data_dir)
    r = _post(client, [("capture", ("plate.zip", buf.getvalue()))], station_bundles["target"])
    assert r.status_code == 422, r.text
    body = r.json()
    assert body["field"] == field, body
    assert body["file"] == f"plate.zip:LONG-1/station_{culprit:02d}/capture.json", body
    assert words in body["detail"]
    assert _count(client, Inspection) == 0 and stored_files(settings.data_dir) == before


def test_stations_of_another_plate_and_parts_without_names(client, settings, station_bundles):
    r = client.post(
        "/api/v1/plates/OTHER/inspections",
        files=[
            *_as_parts(station_bundles["parts"]),
            ("target", ("target.json", station_bundles["target"])),
        ],
        headers=AUTH,
    )
    assert r.status_code == 422 and r.json()["field"] == "capture: plate_id", r.text
    assert r.json()["file"] == "s0.zip:capture.json"
    # parts that share a name are named by their place among the parts
    parts = _as_parts(_duplicate(station_bundles["parts"]), ["b.zip"] * 3)
    r = _post(client, parts, station_bundles["target"])
    assert r.status_code == 422 and r.json()["file"] == "capture[2]:capture.json", r.text
    assert _count(client, Inspection) == 0 and stored_files(settings.data_dir) == []


def test_the_zip_of_station_folders_may_hold_them_in_one_top_folder(client, station_bundles):
    r = _post(
        client, [("capture", ("plate.zip", station_bundles["nested"]))], station_bundles["target"]
    )
    assert r.status_code == 202, r.text
    with client.app.state.session_factory() as s:
        row = s.get(Inspection, r.json()["id"])
        assert row.capture_path.endswith("/inputs/stations")


def test_one_bundle_a_folder_too_deep_is_refused_as_before(client, station_bundles):
    """A zip with a single bundle two folders down is no set of stations: the bundle's own error."""
    buf = io.BytesIO()
    with (
        zipfile.ZipFile(io.BytesIO(station_bundles["parts"][0])) as src,
        zipfile.ZipFile(buf, "w") as dst,
    ):
        for name in src.namelist():
            dst.writestr(f"LONG-1/station_00/{name}", src.read(name))
    r = _post(client, [("capture", ("plate.zip", buf.getvalue()))], station_bundles["target"])
    assert r.status_code == 422, r.text
    assert r.json()["field"] == "capture: capture.json", r.text
    assert "at the root of the zip or in its one top folder" in r.json()["detail"]
