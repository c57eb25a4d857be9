"""End to end: simulated plates through pipeline.run.inspect, against the simulator's truth.

The product's accuracy figures (issue 3/4) are checked at the issue's settings:
1224x1024, 16-bit, 0.4 % noise. Each case renders its own bundle (seeded) so the
tests do not share state; the seeds differ from the benchmark's.
"""

from __future__ import annotations

import json
import zipfile
from pathlib import Path

import numpy as np
import pytest

from pipeline.cli import main as cli_main
from pipeline.formats import CaptureError, ResultFile
from pipeline.run import STAGES, InspectOptions, inspect, warm_up
from pipeline.simulate import CaptureSpec, Dent, PlateSpec, simulate_capture

FULL = dict(width=1224, height=1024)


def run_case(tmp_path: Path, *, plate: PlateSpec, capture: CaptureSpec, seed: int, **kwargs):
    bundle = simulate_capture(
        tmp_path / "bundle", plate=plate, capture=capture, seed=seed, **kwargs
    )
    result = inspect(bundle, bundle / "target.json", out_dir=tmp_path / "out")
    return bundle, result.document


@pytest.mark.parametrize(
    "radius_mm, convex, n_lights, limit_pct",
    [
        (5000.0, True, 12, 0.2),  # issue 3: <= 0.2 % at 12 lights
        (3500.0, False, 12, 0.2),  # concave bends alike
        (8000.0, True, 3, 0.5),  # issue 3: <= 0.5 % with 3 lights
    ],
)
def test_cylinder_radius_within_the_product_figures(
    tmp_path, radius_mm, convex, n_lights, limit_pct
):
    plate = PlateSpec(shape="cylinder", radius_mm=radius_mm, convex=convex, tilt_deg=(2.5, -1.5))
    capture = CaptureSpec(n_lights=n_lights, noise=0.004, bit_depth=16, **FULL)
    _, doc = run_case(tmp_path, plate=plate, capture=capture, seed=11)
    ResultFile.model_validate(doc)
    assert doc["target_radius_mm"] == radius_mm
    assert abs(doc["radius_error_pct"]) <= limit_pct, doc
    assert doc["verdict"] == "pass", doc


@pytest.mark.slow
def test_specular_highlights_do_not_spoil_the_radius(tmp_path):
    # issue 3: a specular lobe must not push the radius error past 0.3 % (robust normals)
    plate = PlateSpec(shape="cylinder", radius_mm=5000.0, tilt_deg=(1.0, 2.0))
    capture = CaptureSpec(n_lights=12, noise=0.004, specular=0.4, **FULL)
    _, doc = run_case(tmp_path, plate=plate, capture=capture, seed=5)
    assert abs(doc["radius_error_pct"]) <= 0.3, doc


def test_a_local_dent_fails_an_otherwise_good_plate(tmp_path):
    plate = PlateSpec(
        shape="cylinder",
        radius_mm=6000.0,
        dents=(Dent(x_mm=400.0, y_mm=-300.0, radius_mm=150.0, depth_mm=6.0),),
    )
    capture = CaptureSpec(n_lights=12, noise=0.004, **FULL)
    bundle, doc = run_case(tmp_path, plate=plate, capture=capture, seed=21)
    assert doc["verdict"] == "fail", doc
    assert (
        doc["deviation_mm"]["max_abs"] > 4.0
    )  # the dent is 6 mm deep; the fit spreads a little of it
    assert abs(doc["radius_error_pct"]) <= 0.2  # robust fits: one dent does not move the radius
    details = json.loads((tmp_path / "out" / "details.json").read_text())
    assert details["defects"], "the dent is reported as a defect region"
    # the defect sits where the dent was rendered: compare with the truth depth change
    truth = np.load(bundle / "truth.npz")
    u, v = details["defects"][0]["centroid_px"]
    xy = truth["plate_xy_mm"][int(round(v)), int(round(u))]
    assert np.hypot(xy[0] - 400.0, xy[1] + 300.0) < 60.0


def test_a_dent_is_measured_on_a_binned_working_grid(tmp_path):
    # a working cell of 7 mm bins the 1224x1024 capture (3.3 mm per pixel at 3 m) by 2: the dent and
    # the radius are measured as on the capture's own pixels, the depth map comes on the working grid
    plate = PlateSpec(
        shape="cylinder",
        radius_mm=6000.0,
        dents=(Dent(x_mm=400.0, y_mm=-300.0, radius_mm=150.0, depth_mm=6.0),),
    )
    capture = CaptureSpec(n_lights=12, noise=0.004, **FULL)
    bundle = simulate_capture(tmp_path / "bundle", plate=plate, capture=capture, seed=21)
    out = tmp_path / "out"
    options = InspectOptions(working_cell_mm=7.0)
    doc = inspect(bundle, bundle / "target.json", out_dir=out, options=options).document
    assert doc["verdict"] == "fail", doc
    assert doc["deviation_mm"]["max_abs"] > 4.0
    assert abs(doc["radius_error_pct"]) <= 0.2
    assert np.load(out / "depth.npy").shape == (512, 612)
    details = json.loads((out / "details.json").read_text())
    truth = np.load(bundle / "truth.npz")
    u, v = details["defects"][0]["centroid_px"]  # on the working grid: twice as coarse
    xy = truth["plate_xy_mm"][int(round(2 * v + 0.5)), int(round(2 * u + 0.5))]
    assert np.hypot(xy[0] - 400.0, xy[1] + 300.0) < 60.0


def test_a_plate_bent_to_the_wrong_radius_fails(tmp_path):
    # formed to 4600 mm against a 5000 mm target: the sagitta differs by ~20 mm over 3 m
    plate = PlateSpec(shape="cylinder", radius_mm=4600.0)
    capture = CaptureSpec(n_lights=12, noise=0.004, **FULL)
    bundle = simulate_capture(tmp_path / "bundle", plate=plate, capture=capture, seed=3)
    target = json.loads((bundle / "target.json").read_text())
    target["shape"]["radius_mm"] = 5000.0
    result = inspect(bundle, target, out_dir=tmp_path / "out")
    doc = result.document
    assert doc["verdict"] == "fail"
    assert doc["radius_error_pct"] == pytest.approx(-8.0, abs=0.2)


def test_stereo_makes_the_working_distance_hint_irrelevant(tmp_path):
    # issue 4: with a stereo pair, a wrong working-distance hint no longer changes the radius
    plate = PlateSpec(shape="cylinder", radius_mm=5000.0)
    capture = CaptureSpec(n_lights=12, noise=0.004, **FULL)
    bundle = simulate_capture(tmp_path / "bundle", plate=plate, capture=capture, seed=8)
    radii = []
    for hint in (3000.0, 2600.0):
        doc = json.loads((bundle / "capture.json").read_text())
        doc["working_distance_mm"] = hint
        (bundle / "capture.json").write_text(json.dumps(doc))
        radii.append(
            inspect(bundle, bundle / "target.json", out_dir=tmp_path / f"out{hint:.0f}").document[
                "radius_mm"
            ]
        )
    assert abs(radii[0] - radii[1]) / 5000.0 < 1e-4
    assert abs(radii[0] - 5000.0) / 5000.0 < 2e-3


def test_without_stereo_the_working_distance_sets_the_scale(tmp_path):
    plate = PlateSpec(shape="sphere", radius_mm=9000.0)
    capture = CaptureSpec(n_lights=12, noise=0.004, stereo=False, width=612, height=512)
    _, doc = run_case(tmp_path, plate=plate, capture=capture, seed=4)
    assert abs(doc["radius_error_pct"]) <= 0.5, doc
    assert all(
        r is not None and r == pytest.approx(9000.0, rel=0.01) for r in doc["principal_radii_mm"]
    )


def test_progress_reports_every_stage_and_artifacts_exist(tmp_path):
    plate = PlateSpec(shape="plane", radius_mm=None)
    capture = CaptureSpec(n_lights=6, width=320, height=256)
    bundle = simulate_capture(tmp_path / "bundle", plate=plate, capture=capture, seed=2)
    seen = []
    result = inspect(
        bundle,
        bundle / "target.json",
        out_dir=tmp_path / "out",
        progress=lambda s, f: seen.append((s, f)),
    )
    assert [s for s, _ in seen] == [*STAGES, "done"]
    assert [f for _, f in seen] == sorted(f for _, f in seen)
    doc = result.document
    assert doc["radius_mm"] is None and doc["principal_radii_mm"] == [None, None]
    for name in doc["artifacts"].values():
        assert (tmp_path / "out" / name).stat().st_size > 0
    assert set(doc["timings_s"]) >= {"load", "normals", "depth", "curvature", "deviation", "total"}


def test_an_unmeasurable_capture_leaves_an_error_result(tmp_path):
    capture = CaptureSpec(n_lights=4, width=320, height=256, stereo=False, working_distance_mm=None)
    bundle = simulate_capture(tmp_path / "bundle", capture=capture, seed=1)
    with pytest.raises(CaptureError, match="working_distance_mm"):
        inspect(bundle, bundle / "target.json", out_dir=tmp_path / "out")
    doc = json.loads((tmp_path / "out" / "result.json").read_text())
    assert doc["verdict"] == "error" and "working_distance_mm" in doc["error"]
    assert "warnings" not in doc
    # the CLI: exit 3 (not measurable), result.json written all the same
    code = cli_main(
        [
            "inspect",
            str(bundle),
            "--target",
            str(bundle / "target.json"),
            "--out",
            str(tmp_path / "o3"),
            "--no-warm-up",
        ]
    )
    assert code == 3
    assert json.loads((tmp_path / "o3" / "result.json").read_text())["verdict"] == "error"


def test_cli_inspect_exit_codes(tmp_path, capsys):
    bundle = simulate_capture(
        tmp_path / "bundle", capture=CaptureSpec(n_lights=4, width=320, height=256), seed=6
    )
    archive = tmp_path / "bundle.zip"
    with zipfile.ZipFile(archive, "w") as zf:
        for f in bundle.iterdir():
            zf.write(f, f.name)
    assert (
        cli_main(
            [
                "inspect",
                str(archive),
                "--target",
                str(bundle / "target.json"),
                "--out",
                str(tmp_path / "o"),
            ]
        )
        == 0
    )
    assert json.loads((tmp_path / "o" / "result.json").read_text())["verdict"] in ("pass", "fail")
    capsys.readouterr()
    # bad input: exit 2 and one line naming the file and the field
    doc = json.loads((bundle / "capture.json").read_text())
    doc["photometric"]["lights"][1]["direction"] = [0.0, 0.0, 0.0]
    (bundle / "capture.json").write_text(json.dumps(doc))
    code = cli_main(
        [
            "inspect",
            str(bundle),
            "--target",
            str(bundle / "target.json"),
            "--out",
            str(tmp_path / "o2"),
            "--no-warm-up",
        ]
    )
    err = capsys.readouterr().err.strip()
    assert code == 2
    assert len(err.splitlines()) == 1 and "capture.json" in err and "lights[1].direction" in err
    assert cli_main(["calibrate", str(tmp_path), "--board", "9by6", "--square", "25"]) == 2


def test_warm_up_runs_a_small_inspection_and_leaves_nothing(tmp_path, monkeypatch):
    import tempfile

    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    seconds = warm_up()
    assert seconds > 0
    assert list(tmp_path.iterdir()) == []  # its temporary folder is gone
