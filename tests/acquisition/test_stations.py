"""plate-inspect acquire with a conveyor (issue 29): one bundle per station, measured as one plate;
the tcp conveyor against the tests' own controller on loopback; its failures named by step."""

from __future__ import annotations

import json
import re
import time

import numpy as np
import pytest

from pipeline.acquisition import acquire, acquire_stations, write_demo_cell
from pipeline.acquisition.conveyor import SIMULATED_ENCODER_ERROR_MM
from pipeline.cli import EXIT_BAD_INPUT, EXIT_HARDWARE, EXIT_OK, main
from pipeline.formats import AcquisitionError, InputError
from pipeline.io import load_capture
from tests.acquisition.helpers import tcp_lights, write_cell

N = 6
SPACING_MM = 2100.0
#: The simulated plate's travel axis in the left camera frame (its tilt: 3 deg about x).
DIRECTION = [0.0, -0.99863, -0.05234]
FIXED_FAKE_1 = {"driver": "aravis", "device_id": "Fake_1", "exposure_us": 5000.0}
FIXED_SIMULATED = {"driver": "simulated", "exposure_us": 5000.0}


def _conveyor(server=None, **extra) -> dict:
    tcp = {"driver": "tcp", "address": server.address} if server else {"driver": "simulated"}
    return {
        **tcp,
        "direction": DIRECTION,
        "stations_mm": [0.0, SPACING_MM, 2 * SPACING_MM],
        **extra,
    }


def _nothing_left(tmp_path) -> bool:
    return not (tmp_path / "stations").exists()


@pytest.fixture(scope="module")
def demo_stations(tmp_path_factory):
    """The demo cell with a simulated conveyor at 3 stations, 640 x 512, acquired, then measured as one
    plate through the CLI. (At 480 x 384 the demo cell's 6 LEDs give an expanded uncertainty of 0.75
    mm, tolerance / U = 2.7: a plate formed exactly read a largest deviation of 1.7-2.2 mm against the
    2 mm tolerance, pass or fail by chance; at 640 x 512, 1.0 mm.)"""
    root = tmp_path_factory.mktemp("demo-stations")
    config = write_demo_cell(root / "cell", n_lights=N, width=640, height=512, stations=3)
    events = []
    bundles = acquire_stations(
        config,
        "LONG-1",
        root / "stations",
        progress=lambda stage, fraction: events.append(("progress", stage, fraction)),
        station_done=lambda index, bundle: events.append(("done", index, bundle)),
    )
    code = main(
        [
            "inspect",
            *map(str, bundles),
            "--target",
            str(root / "cell" / "target.json"),
            "--out",
            str(root / "result"),
            "--no-warm-up",
        ]
    )
    return root, config, bundles, events, code


def test_simulated_conveyor_plate_formed_exactly_passes_as_one_plate(demo_stations):
    root, _, _, _, code = demo_stations
    assert code == EXIT_OK
    doc = json.loads((root / "result" / "result.json").read_text())
    target = json.loads((root / "cell" / "target.json").read_text())
    assert target["size_mm"] == [3000.0, 3000.0 + 2 * SPACING_MM]  # the whole plate
    assert doc["verdict"] == "pass"
    assert abs(doc["radius_mm"] / 5000.0 - 1) < 0.001  # within 0.1 %
    details = json.loads((root / "result" / "details.json").read_text())["stations"]
    # the registration found the true travels (the simulated plate goes exactly where it is sent)
    for station, true in zip(details["stations"], [0.0, SPACING_MM, 2 * SPACING_MM], strict=True):
        assert station["travel_mm"] == pytest.approx(true, abs=2.0)


def test_each_station_is_a_bundle_with_its_station_field(demo_stations):
    root, config, bundles, _, _ = demo_stations
    assert bundles == [root / "stations" / f"station_{k:02d}" for k in range(3)]
    assert sorted(p.name for p in (root / "stations").iterdir()) == [b.name for b in bundles]
    direction = json.loads(config.read_text())["conveyor"]["direction"]
    encoder = []
    for k, bundle in enumerate(bundles):
        capture = load_capture(bundle)
        assert capture.plate_id == "LONG-1" and capture.n_lights == N
        doc = json.loads((bundle / "capture.json").read_text())
        assert doc["station"]["index"] == k
        np.testing.assert_allclose(doc["station"]["direction"], direction, rtol=0, atol=1e-12)
        travel = doc["station"]["travel_mm"]
        assert abs(travel - k * SPACING_MM) <= 2 * SIMULATED_ENCODER_ERROR_MM
        conveyor = doc["acquisition"]["conveyor"]
        assert conveyor["driver"] == "simulated" and conveyor["target_mm"] == k * SPACING_MM
        encoder.append(conveyor["encoder_mm"])
        assert travel == pytest.approx(encoder[-1] - encoder[0], abs=1e-3)
    # every station sees another part of the plate (the plate moved under the head)
    first, second = (load_capture(b).stereo_left.astype(float) for b in bundles[:2])
    assert np.abs(first - second).mean() > 0.05 * first.mean()


def test_progress_names_the_station_and_each_bundle_is_reported_when_complete(demo_stations):
    _, _, bundles, events, _ = demo_stations
    done = [e for e in events if e[0] == "done"]
    # each reported in the partial folder the stations are written into (renamed with the last)
    partial = bundles[0].parent.with_name(bundles[0].parent.name + ".partial")
    assert done == [("done", k, partial / bundle.name) for k, bundle in enumerate(bundles)]
    stages = [e for e in events if e[0] == "progress"]
    fractions = [f for _, _, f in stages]
    assert fractions == sorted(fractions) and fractions[0] >= 0.0 and fractions[-1] <= 1.0
    assert ("progress", "station 2/3: moving to 2100 mm", pytest.approx(1 / 3)) in stages
    assert any(stage == f"station 3/3: ps_{N - 1:02d}.png taken" for _, stage, _ in stages)
    # station k's bundle is reported before the conveyor moves on to station k + 1
    order = [e[1] if e[0] == "done" else e[1].split(":")[0] for e in events]
    assert order.index(0) < order.index("station 2/3") and order.index(1) < order.index(
        "station 3/3"
    )


def test_tcp_conveyor_lights_and_fake_gige_camera_in_step_order(
    tmp_path, fake_gv, light_server, conveyor_server, capsys
):
    """The conveyor moves, then the station's frames; each move is commanded from the encoder's last
    reading (a positioning error does not carry over); ``travel_mm`` is the encoder's reading less
    station 0's. The fake cameras show their own pattern: no measurement here."""
    log: list[str] = []
    lights = light_server(on_command=log.append)
    conveyor = conveyor_server(start_mm=512.5, errors_mm=[0.0, 3.25, -1.5], on_command=log.append)
    left = {"driver": "aravis", "device_id": fake_gv.device_id, "exposure_us": 5000.0}
    config = write_cell(
        tmp_path / "cell",
        left=left,
        right=FIXED_FAKE_1,
        lights=tcp_lights(lights),
        n_lights=N,
        conveyor=_conveyor(conveyor),
    )
    out = tmp_path / "stations"
    assert main(["acquire", str(config), "--plate-id", "TCP-1", "--out", str(out)]) == EXIT_OK
    printed = capsys.readouterr().out
    assert "TCP-1 station 1: travel 2103.2 mm" in printed
    assert "wrote 3 station bundles" in printed

    assert conveyor.commands == ["MOVE 0.000", "MOVE 2100.000", "MOVE 2096.750"]
    frames = [
        *(f"L{k} ON" for k in range(N)),
        *(f"L{k} OFF" for k in range(N)),
    ] + [c for k in range(N) for c in (f"L{k} ON", f"L{k} OFF")]
    assert log == [
        "MOVE 0.000",
        *frames,
        "MOVE 2100.000",
        *frames,
        "MOVE 2096.750",
        *frames,
    ]
    travels = []
    for k in range(3):
        doc = json.loads((out / f"station_{k:02d}" / "capture.json").read_text())
        assert doc["plate_id"] == "TCP-1" and doc["station"]["index"] == k
        np.testing.assert_allclose(
            doc["station"]["direction"], np.array(DIRECTION) / np.linalg.norm(DIRECTION)
        )
        travels.append(doc["station"]["travel_mm"])
        record = doc["acquisition"]["conveyor"]
        assert record["driver"] == "tcp" and record["address"] == conveyor.address
        assert [f["file"] for f in doc["acquisition"]["frames"]][-1] == f"ps_{N - 1:02d}.png"
        assert load_capture(out / f"station_{k:02d}").images.shape[0] == N
    assert travels == [0.0, 2103.25, 4198.5]


# --------------------------------------------------------------------------- failures


def test_conveyor_refusing_a_move_exits_4_naming_conveyor_and_station(
    tmp_path, light_server, conveyor_server, capsys
):
    lights = light_server()
    conveyor = conveyor_server(refuse=1)
    config = write_cell(
        tmp_path / "cell",
        left=FIXED_FAKE_1,
        right=FIXED_SIMULATED,
        lights=tcp_lights(lights),
        n_lights=N,
        conveyor=_conveyor(conveyor),
    )
    code = main(["acquire", str(config), "--plate-id", "P", "--out", str(tmp_path / "stations")])
    assert code == EXIT_HARDWARE
    assert (
        f"conveyor {conveyor.address}: station 1 (moving to 2100 mm): refused 'MOVE 2100.000': "
        "answered 'ERR blocked'" in capsys.readouterr().err
    )
    assert conveyor.commands == ["MOVE 0.000", "MOVE 2100.000"]
    assert _nothing_left(tmp_path)  # station 0's bundle too: the plate is not complete
    assert lights.commands[-1] == f"L{N - 1} OFF"  # every light off


def test_conveyor_that_stops_answering_exits_4_within_its_timeout(
    tmp_path, conveyor_server, capsys
):
    conveyor = conveyor_server(stall=2)
    config = write_cell(
        tmp_path / "cell",
        left=FIXED_FAKE_1,
        right=FIXED_SIMULATED,
        lights={"driver": "simulated"},
        conveyor=_conveyor(conveyor, move_timeout_s=1.0),
    )
    t0 = time.monotonic()
    code = main(["acquire", str(config), "--plate-id", "P", "--out", str(tmp_path / "stations")])
    assert code == EXIT_HARDWARE
    assert (
        f"conveyor {conveyor.address}: station 2 (moving to 4200 mm): no answer to 'MOVE 2100.000' "
        "within 1 s" in capsys.readouterr().err
    )
    assert time.monotonic() - t0 < 30  # two stations photographed, then 1 s for the stalled move
    assert _nothing_left(tmp_path)


@pytest.mark.parametrize(
    ("server", "match"),
    [
        (
            {"reply": "OK"},
            "station 0 (moving to 0 mm): answered 'OK' to 'MOVE 0.000': expected 'OK <encoder_mm>'",
        ),
        (
            {"errors_mm": [0.0, -1200.0]},
            "station 1 (moving to 2100 mm): the encoder reads 900.0 mm of travel after the move",
        ),
        (
            {"echo": True, "errors_mm": [0.0, 0.0, 5000.0]},
            "station 2 (moving to 4200 mm): the encoder reads 9200.0",
        ),
    ],
)
def test_conveyor_answers_that_are_not_a_station(tmp_path, conveyor_server, server, match):
    conveyor = conveyor_server(**server)
    config = write_cell(
        tmp_path / "cell",
        left=FIXED_FAKE_1,
        right=FIXED_SIMULATED,
        lights={"driver": "simulated"},
        conveyor=_conveyor(conveyor),
    )
    with pytest.raises(AcquisitionError, match=re.escape(f"conveyor {conveyor.address}: {match}")):
        acquire_stations(config, "P", tmp_path / "stations")
    assert _nothing_left(tmp_path)


def test_conveyor_not_listening_is_a_hardware_failure(tmp_path, conveyor_server, capsys):
    conveyor = conveyor_server()
    conveyor.close()
    config = write_cell(
        tmp_path / "cell",
        left=FIXED_SIMULATED,
        right=FIXED_SIMULATED,
        lights={"driver": "simulated"},
        conveyor=_conveyor(conveyor),
    )
    code = main(["acquire", str(config), "--plate-id", "P", "--out", str(tmp_path / "stations")])
    assert code == EXIT_HARDWARE
    assert f"conveyor {conveyor.address}: connecting: Connection refused" in capsys.readouterr().err
    assert _nothing_left(tmp_path)


def test_bad_conveyor_config_exits_2_naming_the_field(tmp_path, capsys):
    config = write_cell(
        tmp_path / "cell",
        left=FIXED_SIMULATED,
        right=FIXED_SIMULATED,
        lights={"driver": "simulated"},
        conveyor=_conveyor(stations_mm=[0.0, 2100.0, 2100.0]),
    )
    code = main(["acquire", str(config), "--plate-id", "P", "--out", str(tmp_path / "stations")])
    assert code == EXIT_BAD_INPUT
    assert (
        "cell.json: conveyor.stations_mm: expected strictly increasing positions, got 2100 mm at "
        "station 2 after 2100 mm" in capsys.readouterr().err
    )
    assert _nothing_left(tmp_path)


def test_one_view_and_stations_are_not_mixed_up(tmp_path):
    stations = write_demo_cell(tmp_path / "long", width=160, height=128, stations=2)
    with pytest.raises(InputError, match=r"cell\.json: conveyor: this cell carries the plate"):
        acquire(stations, "P", tmp_path / "bundle")
    one = write_demo_cell(tmp_path / "one", width=160, height=128)
    with pytest.raises(InputError, match=r"cell\.json: conveyor: missing"):
        acquire_stations(one, "P", tmp_path / "stations")
    assert not (tmp_path / "bundle").exists() and _nothing_left(tmp_path)
    assert "conveyor" not in json.loads(one.read_text())  # the default demo cell is as it was


def test_a_killed_acquisitions_stations_are_never_taken_for_a_plate(tmp_path):
    """Stations are written into ``OUT.partial`` and renamed to ``OUT`` with the last one: a killed
    acquisition leaves no ``OUT`` (so a job run again photographs the plate anew, never measuring the
    stations it had), and its partial folder is removed by the next acquisition."""
    config = write_demo_cell(tmp_path / "cell", n_lights=N, width=160, height=128, stations=3)
    stale = tmp_path / "stations.partial" / "station_00"
    stale.mkdir(parents=True)
    (stale / "capture.json").write_text("{}")
    seen = []
    bundles = acquire_stations(
        config,
        "LONG-2",
        tmp_path / "stations",
        station_done=lambda k, bundle: seen.append(
            (bundle.parent.name, (tmp_path / "stations").exists())
        ),
    )
    # while stations are taken they sit in the partial folder, and OUT does not exist
    assert seen == [("stations.partial", False)] * 3
    assert [b.name for b in bundles] == ["station_00", "station_01", "station_02"]
    assert all((b / "capture.json").is_file() for b in bundles)
    assert not (tmp_path / "stations.partial").exists()
