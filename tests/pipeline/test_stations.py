"""A plate longer than the view measured from its conveyor stations (issue 29), against simulated truth.

Three stations of a 7.5 m plate at 480 x 384 px (small images keep the tests fast; the acceptance
figures at 1224 x 1024 are benchmarks/bench_stations.py's). The stations' encoder is a few mm off and
each station yaws by up to 0.3 deg (the simulator's defaults).
"""

import itertools
import json
from pathlib import Path

import numpy as np
import pytest
from pydantic import TypeAdapter

from pipeline.cli import EXIT_NOT_MEASURABLE, main
from pipeline.formats import CaptureError
from pipeline.judge.details import Details
from pipeline.run import inspect
from pipeline.simulate import CaptureSpec, Dent, PlateSpec, simulate_stations

SIZE = CaptureSpec(width=480, height=384)
SPACING_MM = 2400.0
LENGTH_MM = 7500.0
#: The overlap between stations 0 and 1 is centred at this plate y (mm).
SEAM_Y_MM = -SPACING_MM / 2


def _plate(**kwargs) -> PlateSpec:
    return PlateSpec(size_mm=(3000.0, LENGTH_MM), **kwargs)


def _stations(root: Path, plate: PlateSpec, capture: CaptureSpec = SIZE) -> list[Path]:
    return simulate_stations(
        root, n_stations=3, spacing_mm=SPACING_MM, plate=plate, capture=capture, seed=5
    )


@pytest.fixture(scope="module")
def perfect(tmp_path_factory):
    root = tmp_path_factory.mktemp("perfect")
    bundles = _stations(root / "in", _plate())
    reported: list[tuple[str, float]] = []
    result = inspect(
        bundles,
        root / "in" / "target.json",
        out_dir=root / "out",
        progress=lambda stage, fraction: reported.append((stage, fraction)),
    )
    details = json.loads((root / "out" / "details.json").read_text())
    (root / "progress.json").write_text(json.dumps(reported))
    return bundles, result.document, details, root


def test_perfect_plate_passes_with_its_radius(perfect):
    _, doc, _, _ = perfect
    assert doc["verdict"] == "pass"
    assert abs(doc["radius_error_pct"]) < 0.2
    assert doc["deviation_mm"]["p95"] < 0.6
    assert doc["uncertainty"]["deviation_mm"] > 0 and doc["uncertainty"]["radius_mm"] > 0


def test_details_give_each_station_pose_travel_and_overlap(perfect):
    _, _, details, root = perfect
    truth = json.loads((root / "in" / "stations_truth.json").read_text())
    st = details["stations"]
    assert [s["index"] for s in st["stations"]] == [0, 1, 2]
    for s, true, enc in zip(st["stations"], truth["travel_mm"], truth["encoder_mm"], strict=True):
        assert s["travel_encoder_mm"] == pytest.approx(enc, abs=1e-3)
        assert abs(s["travel_mm"] - true) < 1.5  # the encoder is up to 4 mm off
        assert np.asarray(s["T_plate_station"]).shape == (4, 4)
    seams = [o for o in st["overlaps"] if o["stations"][1] == o["stations"][0] + 1]
    assert len(seams) == 2
    for o in seams:
        assert o["rms_mm"] < 0.5 and o["max_mm"] >= o["rms_mm"] and o["matches"] >= 12
    assert "stations_registration_mm" in details["uncertainty"]["components"]


def test_each_station_footprint_covers_its_part_of_the_plate(perfect):
    """The outline the map draws: each station's image frame on the target, consecutive ones overlapping
    along the plate (its y) by the view's length less the spacing, together spanning its length."""
    _, _, details, _ = perfect
    spans = []
    for s in details["stations"]["stations"]:
        corners = np.asarray(s["footprint_mm"])
        assert corners.shape == (4, 2)
        spans.append((corners[:, 1].min(), corners[:, 1].max()))
    assert spans[0][0] < -LENGTH_MM / 2 and spans[-1][1] > LENGTH_MM / 2
    for (lo0, hi0), (lo1, hi1) in itertools.pairwise(spans):
        assert lo0 < lo1 < hi0 < hi1
        assert lo1 - lo0 == pytest.approx(
            SPACING_MM, abs=20.0
        )  # the travel, up to the yaw at the corners


def test_progress_is_reported_per_station_then_for_the_plate(perfect):
    _, _, _, root = perfect
    reported = json.loads((root / "progress.json").read_text())
    stages = [stage for stage, _ in reported]
    for k in (1, 2, 3):
        assert f"station {k}/3: normals" in stages
    assert stages.index("station 1/3: depth") < stages.index("station 2/3: load")
    assert stages.index("station 3/3: depth") < stages.index("curvature")
    fractions = [f for _, f in reported]
    assert fractions == sorted(fractions) and fractions[-1] == 1.0


def test_all_artifacts_written(perfect):
    _, doc, _, root = perfect
    for name in doc["artifacts"].values():
        assert (root / "out" / name).is_file(), name


def test_dent_across_two_stations_fails_with_its_depth(tmp_path):
    dent = Dent(x_mm=300.0, y_mm=SEAM_Y_MM, radius_mm=250.0, depth_mm=5.0)
    bundles = _stations(tmp_path / "in", _plate(dents=(dent,)))
    result = inspect(bundles, tmp_path / "in" / "target.json", out_dir=tmp_path / "out")
    doc = result.document
    details = json.loads((tmp_path / "out" / "details.json").read_text())
    assert doc["verdict"] == "fail"
    assert 4.0 < doc["deviation_mm"]["max_abs"] < 5.6
    worst = details["defects"][0]
    assert abs(worst["peak_deviation_mm"]) == pytest.approx(
        doc["deviation_mm"]["max_abs"], abs=0.01
    )
    x, y = worst["centroid_mm"]
    assert np.hypot(x - dent.x_mm, y - dent.y_mm) < 60.0


def test_under_bent_plate_fails_with_its_radius(tmp_path):
    bundles = _stations(tmp_path / "in", _plate(radius_mm=5300.0))
    target = json.loads((tmp_path / "in" / "target.json").read_text())
    target["shape"]["radius_mm"] = 5000.0
    result = inspect(bundles, target, out_dir=tmp_path / "out")
    doc = result.document
    assert doc["verdict"] == "fail"
    assert abs(doc["radius_mm"] - 5300.0) / 5300.0 < 0.002


def test_untextured_plate_cannot_be_stitched(tmp_path, capsys):
    """A plate with no texture gives its overlaps nothing to register on: error naming the station."""
    bundles = _stations(
        tmp_path / "in", _plate(), capture=CaptureSpec(width=480, height=384, texture="uniform")
    )
    with pytest.raises(CaptureError, match=r"station_01.*registered"):
        inspect(bundles, tmp_path / "in" / "target.json", out_dir=tmp_path / "out")
    result = json.loads((tmp_path / "out" / "result.json").read_text())
    assert result["verdict"] == "error" and "station 1" in result["error"]
    code = main(
        [
            "inspect",
            *map(str, bundles),
            "--target",
            str(tmp_path / "in" / "target.json"),
            "--out",
            str(tmp_path / "cli"),
            "--no-warm-up",
        ]
    )
    assert code == EXIT_NOT_MEASURABLE
    assert "station_01" in capsys.readouterr().err


def test_encoder_far_off_is_not_stitched(tmp_path):
    """An encoder reading 150 mm off (a slipping plate) puts the overlap's search elsewhere: error, not a
    wrong stitch."""
    bundles = _stations(tmp_path / "in", _plate())
    path = bundles[2] / "capture.json"
    doc = json.loads(path.read_text())
    doc["station"]["travel_mm"] += 150.0
    path.write_text(json.dumps(doc))
    with pytest.raises(CaptureError, match="station_02"):
        inspect(bundles, tmp_path / "in" / "target.json", out_dir=tmp_path / "out")


def test_one_bundle_in_a_list_is_the_single_view(perfect, tmp_path):
    bundles, _, _, root = perfect
    one = inspect([bundles[1]], root / "in" / "target.json", out_dir=tmp_path / "list")
    alone = inspect(bundles[1], root / "in" / "target.json", out_dir=tmp_path / "alone")
    a, b = dict(one.document), dict(alone.document)
    a.pop("timings_s")
    b.pop("timings_s")
    assert a == b
    assert "stations" not in json.loads((tmp_path / "list" / "details.json").read_text())


def test_uncertainty_includes_the_registration(perfect):
    _, doc, details, _ = perfect
    u = details["uncertainty"]
    reg = u["components"]["stations_registration_mm"]
    assert reg > 0
    assert doc["uncertainty"]["deviation_mm"] >= 2 * reg  # U (k = 2) holds the registration's part
    per_station = [s["registration_sd_mm"] for s in details["stations"]["stations"]]
    assert max(per_station) == pytest.approx(reg, abs=1e-4)


def test_details_match_their_model(perfect):
    """details.json of a stitched plate reads back into its model (the schema's source)."""
    _, _, details, _ = perfect
    model = TypeAdapter(Details).validate_python(details)
    assert model.stations is not None and len(model.stations.stations) == 3
