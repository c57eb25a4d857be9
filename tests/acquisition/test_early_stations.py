"""Stations reconstructed as they arrive (issue 29): ``plate-inspect acquire --target --result`` on a
conveyor cell reconstructs each station while the next is photographed; the result is the one of
inspecting the written bundles afterwards, and a station that fails in the background is the
inspection's error, naming it."""

from __future__ import annotations

import json

import numpy as np
import pytest

from pipeline.acquisition import acquire_stations, write_demo_cell
from pipeline.cli import EXIT_NOT_MEASURABLE, EXIT_OK, main
from pipeline.formats import CaptureError
from pipeline.run import EarlyStations, inspect
from pipeline.stations import early

#: Every artifact whose numbers the two ways must share.
ARRAYS = ("depth.npy", "uncertainty.npy")


@pytest.fixture(scope="module")
def acquired(tmp_path_factory):
    """The demo cell's conveyor at 3 stations, 640 x 512: acquired and inspected as the stations
    arrive (the CLI), then the written bundles inspected afterwards."""
    root = tmp_path_factory.mktemp("early-stations")
    config = write_demo_cell(root / "cell", n_lights=6, width=640, height=512, stations=3)
    target = root / "cell" / "target.json"
    code = main(
        [
            "acquire",
            str(config),
            "--plate-id",
            "LONG-1",
            "--out",
            str(root / "stations"),
            "--target",
            str(target),
            "--result",
            str(root / "early"),
        ]
    )
    bundles = sorted((root / "stations").iterdir())
    after = main(
        ["inspect", *map(str, bundles), "--target", str(target), "--out", str(root / "after")]
    )
    return root, code, after


def test_stations_reconstructed_as_they_arrive_give_the_result_of_the_written_bundles(acquired):
    root, code, after = acquired
    assert code == EXIT_OK and after == EXIT_OK
    early_doc = json.loads((root / "early" / "result.json").read_text())
    after_doc = json.loads((root / "after" / "result.json").read_text())
    assert early_doc["verdict"] == "pass"
    for key in ("verdict", "radius_mm", "principal_radii_mm", "deviation_mm", "uncertainty"):
        assert early_doc[key] == after_doc[key], key
    for name in ARRAYS:
        np.testing.assert_array_equal(
            np.load(root / "early" / name), np.load(root / "after" / name)
        )
    early_details = json.loads((root / "early" / "details.json").read_text())
    after_details = json.loads((root / "after" / "details.json").read_text())
    assert early_details == after_details  # the stations named by their written bundles too
    assert early_details["stations"]["stations"][1]["bundle"] == str(
        root / "stations" / "station_01" / "capture.json"
    )


def test_an_acquired_plate_of_stations_reports_the_time_after_its_last_frame(acquired):
    root, _, _ = acquired
    timings = json.loads((root / "early" / "result.json").read_text())["timings_s"]
    assert timings["after_last_frame"] > 0.0
    # nothing of the stations is left beside them (the links of the early reconstruction)
    assert sorted(p.name for p in root.iterdir()) == ["after", "cell", "early", "stations"]


def _failing_at(index, error):
    """reconstruct_station that raises ``error(label)`` at station ``index``."""
    real = early.reconstruct_station

    def reconstruct(ref, *args, **kwargs):
        if ref.station.index == index:
            raise error(ref.label)
        return real(ref, *args, **kwargs)

    return reconstruct


@pytest.fixture(scope="module")
def small_cell(tmp_path_factory):
    root = tmp_path_factory.mktemp("early-small")
    return write_demo_cell(root / "cell", n_lights=6, width=320, height=256, stations=3)


def test_a_station_that_cannot_be_measured_in_the_background_is_the_inspections_error(
    tmp_path, small_cell, monkeypatch, capsys
):
    monkeypatch.setattr(
        early,
        "reconstruct_station",
        _failing_at(1, lambda label: CaptureError(f"{label}: stereo: no plate found")),
    )
    target = small_cell.parent / "target.json"
    argv = ["acquire", str(small_cell), "--plate-id", "P", "--out", str(tmp_path / "stations")]
    code = main([*argv, "--target", str(target), "--result", str(tmp_path / "result")])
    assert code == EXIT_NOT_MEASURABLE
    station = tmp_path / "stations" / "station_01" / "capture.json"
    err = capsys.readouterr().err
    assert f"{station}: stereo: no plate found" in err  # its bundle where it was written
    doc = json.loads((tmp_path / "result" / "result.json").read_text())
    assert doc["verdict"] == "error" and doc["error"] == f"{station}: stereo: no plate found"
    assert sorted(p.name for p in (tmp_path / "stations").iterdir()) == [
        "station_00",
        "station_01",
        "station_02",
    ]


def test_any_other_failure_of_a_station_in_the_background_names_the_station(
    tmp_path, small_cell, monkeypatch
):
    monkeypatch.setattr(
        early, "reconstruct_station", _failing_at(2, lambda label: MemoryError("out of memory"))
    )
    target = small_cell.parent / "target.json"
    stations = tmp_path / "stations"
    with EarlyStations(target, stations) as early_stations:
        bundles = acquire_stations(
            small_cell, "P", stations, station_done=early_stations.station_done
        )
        with pytest.raises(RuntimeError) as caught:
            inspect(bundles, target, out_dir=tmp_path / "result", early=early_stations)
    assert str(caught.value) == (
        f"{stations / 'station_02' / 'capture.json'}: station 2: the station's reconstruction "
        "failed: MemoryError: out of memory"
    )


def test_early_stations_of_another_target_are_refused(tmp_path, small_cell):
    target = small_cell.parent / "target.json"
    other = json.loads(target.read_text())
    refused = pytest.raises(ValueError, match="another target, options or light calibration")
    with EarlyStations(target, tmp_path / "stations") as early_stations, refused:
        inspect(
            [tmp_path / "a", tmp_path / "b"], other, out_dir=tmp_path / "r", early=early_stations
        )


def test_the_cli_wants_target_and_result_together(tmp_path, small_cell, capsys):
    argv = ["acquire", str(small_cell), "--plate-id", "P", "--out", str(tmp_path / "s")]
    assert main([*argv, "--target", "t.json"]) != EXIT_OK
    assert "--target, --result: expected both" in capsys.readouterr().err


def test_stations_the_early_reconstruction_missed_are_reconstructed_by_the_inspection(
    acquired, tmp_path
):
    root, _, _ = acquired
    bundles = sorted((root / "stations").iterdir())
    target = root / "cell" / "target.json"
    with EarlyStations(target, root / "stations") as early_stations:
        for k in (0, 2):  # station 1 never reported (its bundle could not be linked, say)
            early_stations.station_done(k, bundles[k])
        doc = inspect(bundles, target, out_dir=tmp_path / "mixed", early=early_stations).document
    after = json.loads((root / "after" / "result.json").read_text())
    for key in ("verdict", "radius_mm", "principal_radii_mm", "deviation_mm", "uncertainty"):
        assert doc[key] == after[key], key
    np.testing.assert_array_equal(
        np.load(tmp_path / "mixed" / "depth.npy"), np.load(root / "after" / "depth.npy")
    )
