"""Conveyor stations as input (issue 29): the ``station`` field of plate-capture/1 and the set of stations.

Every bad bundle or bad set is an InputError naming the bundle and the field (the CLI's exit 2), found
before any image is decoded. Bundles are simulated at 64 x 64 px: only their capture.json matters here.
"""

import json
from pathlib import Path

import pytest

from pipeline.cli import EXIT_BAD_INPUT, main
from pipeline.formats import InputError
from pipeline.io import load_capture, read_capture_header
from pipeline.simulate import CaptureSpec, PlateSpec, simulate_stations
from pipeline.stations import MIN_OVERLAP, plan_stations, view_length_mm

SMALL = CaptureSpec(width=64, height=64, n_lights=3, stereo=False)
LONG = PlateSpec(size_mm=(3000.0, 7000.0))


@pytest.fixture(scope="module")
def stations(tmp_path_factory) -> list[Path]:
    return simulate_stations(
        tmp_path_factory.mktemp("stations"),
        n_stations=3,
        spacing_mm=2000.0,
        plate=LONG,
        capture=SMALL,
        seed=3,
    )


def _edit(bundle: Path, change) -> Path:
    path = bundle / "capture.json"
    doc = json.loads(path.read_text())
    change(doc)
    path.write_text(json.dumps(doc))
    return bundle


def _copy(src: Path, dst: Path) -> Path:
    dst.mkdir()
    for f in src.iterdir():
        (dst / f.name).write_bytes(f.read_bytes())
    return dst


def test_station_field_is_read(stations):
    cap = load_capture(stations[1])
    header = read_capture_header(stations[1])
    assert cap.station is not None and header.station == cap.station
    assert cap.station.index == 1
    assert abs(cap.station.travel_mm - 2000.0) <= 4.0  # the encoder, a few mm off
    truth = json.loads((stations[0].parent / "stations_truth.json").read_text())
    assert cap.station.direction == pytest.approx(truth["direction"])


@pytest.mark.parametrize(
    ("field", "value", "words"),
    [
        ("direction", [0.0, 2.0, 0.0], "unit vector"),
        ("direction", [0.0, 1.0], "at least 3"),
        ("index", -1, "greater than or equal"),
        ("index", 1.5, "integer"),
        ("travel_mm", "far", "number"),
    ],
)
def test_bad_station_field_names_file_and_field(stations, tmp_path, field, value, words):
    bundle = _copy(stations[1], tmp_path / "bad")

    def change(doc):
        doc["station"][field] = value

    _edit(bundle, change)
    with pytest.raises(InputError) as err:
        load_capture(bundle)
    assert "capture.json" in err.value.file
    assert err.value.field == f"station.{field}"
    assert words in err.value.reason


def test_unknown_station_key_is_refused(stations, tmp_path):
    bundle = _edit(_copy(stations[0], tmp_path / "b"), lambda d: d["station"].update(speed=1))
    with pytest.raises(InputError) as err:
        load_capture(bundle)
    assert err.value.field.startswith("station")


def test_plan_sorts_stations(stations):
    refs = plan_stations([stations[2], stations[0], stations[1]])
    assert [r.station.index for r in refs] == [0, 1, 2]


def test_duplicate_index(stations, tmp_path):
    dup = _edit(_copy(stations[2], tmp_path / "dup"), lambda d: d["station"].update(index=1))
    with pytest.raises(InputError) as err:
        plan_stations([stations[0], stations[1], dup])
    assert err.value.field == "station.index" and "duplicate" in err.value.reason
    assert "dup" in err.value.file


def test_missing_index(stations):
    with pytest.raises(InputError) as err:
        plan_stations([stations[0], stations[2]])
    assert err.value.field == "station.index" and "missing" in err.value.reason
    assert "station_02" in err.value.file


def test_mixed_plate_ids(stations, tmp_path):
    other = _edit(_copy(stations[1], tmp_path / "other"), lambda d: d.update(plate_id="X-2"))
    with pytest.raises(InputError) as err:
        plan_stations([stations[0], other, stations[2]])
    assert err.value.field == "plate_id" and "other" in err.value.file


def test_bundle_without_station(stations, tmp_path):
    plain = _edit(_copy(stations[1], tmp_path / "plain"), lambda d: d.pop("station"))
    with pytest.raises(InputError) as err:
        plan_stations([stations[0], plain])
    assert err.value.field == "station" and "plain" in err.value.file


def test_stations_without_overlap(stations, tmp_path):
    ref = plan_stations(stations)[1]
    too_far = (1.0 - MIN_OVERLAP) * view_length_mm(ref) + 50.0
    far = _edit(
        _copy(stations[1], tmp_path / "far"), lambda d: d["station"].update(travel_mm=too_far)
    )
    with pytest.raises(InputError) as err:
        plan_stations([stations[0], far])
    assert err.value.field == "station.travel_mm" and "no overlap" in err.value.reason


def test_travel_must_increase_and_directions_agree(stations, tmp_path):
    back = _edit(_copy(stations[1], tmp_path / "back"), lambda d: d["station"].update(travel_mm=-5))
    with pytest.raises(InputError) as err:
        plan_stations([stations[0], back])
    assert err.value.field == "station.travel_mm"
    turned = _edit(
        _copy(stations[1], tmp_path / "turned"),
        lambda d: d["station"].update(direction=[1.0, 0.0, 0.0]),
    )
    with pytest.raises(InputError) as err:
        plan_stations([stations[0], turned])
    assert err.value.field == "station.direction"


def test_cli_bad_set_exits_2(stations, tmp_path, capsys):
    code = main(
        [
            "inspect",
            str(stations[0]),
            str(stations[2]),
            "--target",
            str(stations[0] / "target.json"),
            "--out",
            str(tmp_path / "out"),
            "--no-warm-up",
        ]
    )
    assert code == EXIT_BAD_INPUT
    err = capsys.readouterr().err
    assert "station.index" in err and "station_02" in err


def test_cli_simulates_stations(tmp_path, capsys):
    out = tmp_path / "sim"
    code = main(
        [
            "simulate",
            "capture",
            str(out),
            "--stations",
            "3",
            "--station-spacing",
            "2000",
            "--plate-size",
            "3000x7000",
            "--size",
            "64x64",
            "--lights",
            "3",
            "--no-stereo",
        ]
    )
    assert code == 0
    refs = plan_stations(sorted(out.glob("station_*")))
    assert [r.station.index for r in refs] == [0, 1, 2]
    target = json.loads((out / "target.json").read_text())
    assert target["size_mm"] == [3000.0, 7000.0]
    truth = json.loads((out / "stations_truth.json").read_text())
    assert truth["travel_mm"] == [0.0, 2000.0, 4000.0]
    assert all(
        abs(e - t) <= 4.0 for e, t in zip(truth["encoder_mm"], truth["travel_mm"], strict=True)
    )
    assert all(abs(y) <= 0.3 for y in truth["yaw_deg"])


@pytest.mark.parametrize(
    "extra",
    [["--stations", "1", "--station-spacing", "2000"], ["--stations", "3"], ["--plate-size", "3x"]],
)
def test_cli_simulate_bad_station_arguments_exit_2(tmp_path, extra):
    code = main(["simulate", "capture", str(tmp_path / "sim"), "--size", "64x64", *extra])
    assert code == EXIT_BAD_INPUT
