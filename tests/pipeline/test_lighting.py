"""The lights of a real cell, end to end (issue 10): LEDs 2.8 m above a 3 m plate, bumped lights, glare.

Perfect cylinders (R 5000 mm over 3 x 3 m at 3 m), so the right verdict is PASS; 612 x 512 px keeps
the suite fast (the stereo pair is four times noisier per pixel there than at 1224 x 1024, where
``benchmarks/bench_lights.py`` measures the product figures).
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from pipeline.cli import main as cli_main
from pipeline.run import inspect
from pipeline.simulate import CaptureSpec, Dent, PlateSpec, simulate_capture
from pipeline.surface.normals import NormalField
from pipeline.surface.reconstruct import integrate_and_fuse

NEAR = dict(near_field_mm=2800.0, light_elevation_deg=30.0, led_mu=1.5, width=612, height=512)


def _run(tmp_path, seed=5, **capture):
    bundle = simulate_capture(
        tmp_path / "bundle", plate=PlateSpec(), capture=CaptureSpec(**capture), seed=seed
    )
    seen = []
    doc = inspect(
        bundle,
        bundle / "target.json",
        out_dir=tmp_path / "out",
        progress=lambda stage, fraction: seen.append(fraction),
    ).document
    assert (
        seen == sorted(seen) and seen[-1] == 1.0
    )  # the progress never goes back, whichever light model
    details = json.loads((tmp_path / "out" / "details.json").read_text())
    return doc, details


def test_point_lights_with_positions_measure_the_radius(tmp_path):
    doc, details = _run(tmp_path, **NEAR)
    assert abs(doc["radius_error_pct"]) <= 0.1, doc  # acceptance: <= 0.1 %
    assert doc["verdict"] == "pass"
    assert details["light_model"] == "near-field"
    steps = details["near_field_depth_steps_mm"]
    assert (
        1 <= len(steps) <= 4 and steps[-1] < 1.0
    )  # the alternation stopped because the depth stopped moving
    assert "warnings" not in doc


def test_nominal_directions_of_leds_do_not_bend_the_radius(tmp_path):
    """What used to crash (normals facing away) or give -57 %: the stereo pair governs the bend, and the
    lights are refitted as point lights on its geometry."""
    doc, details = _run(tmp_path, manifest_lights="nominal", **NEAR)
    assert abs(doc["radius_error_pct"]) <= 0.3, doc  # acceptance: <= 0.3 %
    assert details["light_refinement"]["model"] == "point"
    assert details["light_refinement"]["rms_point"] < 0.2 * details["light_refinement"]["rms_given"]
    assert any("did not fit the plate the stereo pair measured" in w for w in doc["warnings"])
    # each LED stays on its given direction from the plate's centre: only its distance was fitted
    assert all(c["turn_deg"] < 0.01 for c in details["light_refinement"]["corrections"])


def test_a_rust_patch_at_the_edge_under_nominal_leds_stays_on_the_plate(tmp_path):
    """Under LEDs given by their directions the plate is first measured on the brightness mask, which
    leaves out a rust patch at the plate's edge (the LEDs light the edge least, and rust is dark). The
    lights do not fit, and the plate is segmented again on the stereo depth: matched over that mask,
    the pair had left the patch a hole, and a notch of the plate went unmeasured (area 0.93 of the
    target; at 1224 x 1024 a deviation of 2.8 mm at the notch's rim on a plate formed exactly). The
    pair is now matched again over every pixel that may be plate (seed 92: a rust patch on the right
    edge, found by ``benchmarks/bench_sweep.py``)."""
    doc, details = _run(
        tmp_path, seed=92, manifest_lights="nominal", **dict(NEAR, near_field_mm=3500.0)
    )
    truth = np.load(tmp_path / "bundle" / "truth.npz")
    measured = np.isfinite(np.load(tmp_path / "out" / "depth.npy"))
    assert details["light_refinement"] is not None  # the path this is about: the lights refitted
    assert not np.any(measured & ~truth["mask"])
    # the plate less its edge band: the band is ~4 px wide (~1.5 % of the plate at this size)
    assert np.count_nonzero(truth["mask"] & ~measured) < 0.03 * np.count_nonzero(truth["mask"])
    assert details["segmentation"]["area_ratio"] > 0.98
    assert doc["verdict"] == "pass"


@pytest.mark.parametrize(("width", "height"), [(612, 512), (1224, 1024)])
def test_a_light_bumped_by_one_degree_does_not_bend_the_radius(tmp_path, width, height):
    """The stereo pair proves the bend; refitted lights are used, and said, only when the plate they
    measure agrees better with it (on this seed they did not, at either size: the given lights stood,
    unsaid)."""
    doc, details = _run(tmp_path, light_error_deg=1.0, width=width, height=height)
    assert abs(doc["radius_error_pct"]) <= 0.2, doc  # acceptance: <= 0.2 %
    assert doc["verdict"] == "pass"
    refit = details["light_refinement"]
    said = any("did not fit the plate" in w for w in doc.get("warnings", []))
    assert said == (refit is not None)
    if refit is not None:
        assert refit["model"] == "distant" and refit["rms_distant"] < refit["rms_given"]
        assert 0.2 < max(c["turn_deg"] for c in refit["corrections"]) < 3.0


@pytest.mark.slow
@pytest.mark.parametrize("manifest", ["nominal", "exact"])
def test_glare_with_18_leds_does_not_crash_or_bend_the_radius(tmp_path, manifest):
    """At 1224 x 1024: at 612 x 512 highlights that move between the two views bias the stereo pair
    itself (-0.7 % radius from the stereo points alone on seed 5)."""
    near = dict(NEAR, width=1224, height=1024)
    doc, _ = _run(tmp_path, manifest_lights=manifest, n_lights=18, specular=0.5, **near)
    assert abs(doc["radius_error_pct"]) <= 0.3, doc  # acceptance: <= 0.3 %, no crash


@pytest.mark.slow
@pytest.mark.parametrize("error_deg", [0.0, 1.0])
def test_leds_given_by_directions_over_a_glossy_plate_are_refitted_with_the_lobe(
    tmp_path, error_deg
):
    """Issue 24's real cell, glossy: 18 LEDs given only by their nominal directions (exact, or written
    a degree off). The lights are refitted jointly with the coating's lobe (as if Lambertian, the
    glare put them at half their distance and the plate read 4-5 mm off at its edges) and the plate
    is measured with the lobe."""
    near = dict(NEAR, width=1224, height=1024, light_error_deg=error_deg)
    doc, details = _run(tmp_path, manifest_lights="nominal", n_lights=18, specular=0.5, **near)
    assert doc["verdict"] == "pass"
    dev = doc["deviation_mm"]
    assert dev["p95"] <= 0.3 and dev["max_abs"] <= 1.2, dev  # acceptance
    assert abs(doc["radius_error_pct"]) <= 0.2, doc
    assert doc["uncertainty"]["deviation_mm"] >= 0.8 * dev["p95"]
    refit = details["light_refinement"]
    assert refit["model"] == "point"
    truth = np.load(tmp_path / "bundle" / "truth.npz")
    fitted = np.array([c["position_mm"] for c in refit["corrections"]])
    err = np.linalg.norm(fitted - truth["light_positions_mm"], axis=1)
    assert err.max() < 60.0, err  # 1.5-1.9 m as if Lambertian


@pytest.mark.slow
def test_a_broad_lobe_under_leds_given_by_directions_is_measured_with_its_own_exponent(tmp_path):
    """The lights refitted with the lobe, the plate measured with the lobe's exponent refined between
    the grid's points: on the grid (15.87 for 15) this plate read p95 0.78 mm, max 1.8 mm."""
    near = dict(NEAR, width=1224, height=1024)
    doc, details = _run(
        tmp_path,
        seed=0,
        manifest_lights="nominal",
        n_lights=18,
        specular=0.5,
        shininess=15.0,
        **near,
    )
    dev = doc["deviation_mm"]
    assert doc["verdict"] == "pass"
    assert dev["p95"] <= 0.3 and dev["max_abs"] <= 1.2, dev  # acceptance on a real cell
    assert details["light_refinement"]["model"] == "point"


DENT = Dent(x_mm=-600.0, y_mm=300.0, radius_mm=150.0, depth_mm=-6.0)


def _dent_fails(tmp_path, **capture):
    """A plate with :data:`DENT` (seed 7): it fails, with one defect at the dent of its depth;
    details.json returned."""
    bundle = simulate_capture(
        tmp_path / "bundle", plate=PlateSpec(dents=(DENT,)), capture=CaptureSpec(**capture), seed=7
    )
    doc = inspect(bundle, bundle / "target.json", out_dir=tmp_path / "out").document
    details = json.loads((tmp_path / "out" / "details.json").read_text())
    assert doc["verdict"] == "fail"
    assert len(details["defects"]) == 1, details["defects"]
    found = details["defects"][0]
    assert found["peak_deviation_mm"] == pytest.approx(-DENT.depth_mm, abs=1.0)
    assert np.hypot(found["centroid_mm"][0] - DENT.x_mm, found["centroid_mm"][1] - DENT.y_mm) < 20.0
    return details


@pytest.mark.slow
def test_a_dent_still_fails_a_glossy_plate_under_nominal_leds(tmp_path):
    details = _dent_fails(
        tmp_path,
        manifest_lights="nominal",
        n_lights=18,
        specular=0.5,
        **dict(NEAR, width=1224, height=1024),
    )
    assert details["light_refinement"]["model"] == "point"


GLOSSY_DISTANT = dict(n_lights=12, specular=0.4, shininess=15.0, width=1224, height=1024)


@pytest.mark.slow
def test_a_broad_lobe_under_distant_lights_is_measured_on_the_stereo_surface(tmp_path):
    """A broad lobe (e 15) lies almost within the Lambertian span: the normals' own specular stage
    read its exponent at 9 and the plate formed exactly failed (p95 0.9 mm, max 2.3-2.8 mm, the
    lights blamed). Measured on the stereo pair's surface, the lobe is told from the diffuse light."""
    doc, details = _run(tmp_path, **GLOSSY_DISTANT)
    dev = doc["deviation_mm"]
    assert doc["verdict"] == "pass"
    assert dev["p95"] <= 0.3 and dev["max_abs"] <= 1.2, dev  # acceptance on a real cell
    assert abs(doc["radius_error_pct"]) <= 0.2, doc
    assert doc["uncertainty"]["deviation_mm"] >= 0.8 * dev["p95"]
    assert details["light_refinement"] is None
    assert not any("lights" in w or "disagreed" in w for w in doc.get("warnings", [])), doc


@pytest.mark.slow
def test_distant_lights_refitted_on_a_glossy_plate_are_measured_with_the_stereo_lobe(tmp_path):
    """18 distant lights written a degree off over a glossy plate: the lights are refitted, and the
    plate measured with them takes the lobe measured on the stereo surface as given lights do (its
    parameters' uncertainty then reaches U: ``lobe_mm``). On the bench (seeds 0, 1) max 0.54 / 0.62
    mm before, 0.28 / 0.34 mm after."""
    doc, details = _run(
        tmp_path, seed=0, n_lights=18, specular=0.5, light_error_deg=1.0, width=1224, height=1024
    )
    dev = doc["deviation_mm"]
    assert doc["verdict"] == "pass" and dev["p95"] <= 0.3 and dev["max_abs"] <= 1.2, dev
    assert details["light_refinement"]["model"] == "distant"
    assert details["uncertainty"]["components"].get("lobe_mm", 0.0) > 0.0, details["uncertainty"]


@pytest.mark.slow
def test_a_broad_lobe_under_distant_lights_a_degree_off_is_refitted_with_distant_lights(tmp_path):
    """Free point lights explain a broad lobe under distant lights written a degree off far better
    than distant Lambertian ones, so the lobe under those was never tested; the plate measured with
    the point lights came out no closer to the stereo pair's, and the given lights stood with a 4 mm
    disagreement (seed 61 of the sweep in docs/figures.md failed at 4.9 mm). The distant lights are
    then refitted with the lobe."""
    doc, details = _run(tmp_path, light_error_deg=1.0, **GLOSSY_DISTANT)
    dev = doc["deviation_mm"]
    assert doc["verdict"] == "pass" and dev["p95"] <= 0.3 and dev["max_abs"] <= 1.2, dev
    assert details["light_refinement"]["model"] == "distant", details["light_refinement"]
    assert not any("disagreed" in w for w in doc.get("warnings", [])), doc["warnings"]


@pytest.mark.slow
def test_a_dent_still_fails_a_glossy_plate_under_distant_lights(tmp_path):
    _dent_fails(tmp_path, **GLOSSY_DISTANT)


def test_the_lstsq_estimator_under_nominal_leds_no_longer_crashes(tmp_path, capsys):
    bundle = simulate_capture(
        tmp_path / "bundle",
        plate=PlateSpec(),
        capture=CaptureSpec(manifest_lights="nominal", **NEAR),
        seed=6,
    )
    code = cli_main(
        [
            "inspect",
            str(bundle),
            "--target",
            str(bundle / "target.json"),
            "--out",
            str(tmp_path / "out"),
            "--normals",
            "lstsq",
            "--no-warm-up",
        ]
    )
    assert code == 0, capsys.readouterr().err
    doc = json.loads((tmp_path / "out" / "result.json").read_text())
    assert abs(doc["radius_error_pct"]) <= 0.3


def test_normals_facing_away_are_filled_and_counted_not_fatal():
    h, w = 120, 160
    K = np.array([[150.0, 0, 80], [0, 150.0, 60], [0, 0, 1]])
    normals = np.zeros((h, w, 3), np.float32)
    normals[..., 2] = -1.0
    normals[50:53, 70:75] = (
        0.0,
        0.0,
        1.0,
    )  # 15 normals facing away, as a light model that does not fit gives
    normals[10, 10] = np.nan
    mask = np.ones((h, w), bool)
    field = NormalField(normals, np.ones((h, w), np.float32), mask, np.zeros((h, w), bool), 0)
    depth, out_mask, out_field, fused, dropped = integrate_and_fuse(
        field, K, prior_mm=None, working_distance_mm=3000.0, stereo_weight=1e-4, tol=1e-6
    )
    assert dropped == 16 and out_field.n_filled == 16 and fused is None
    assert np.all(np.isfinite(depth[out_mask])) and out_mask.all()
    np.testing.assert_allclose(
        depth, 3000.0, rtol=1e-6
    )  # a flat plate facing the camera, filled smoothly


@pytest.mark.slow
def test_lights_calibrated_on_a_flat_plate_measure_a_curved_one(tmp_path):
    """calibrate-lights on a flat reference, then a plate whose bundle gives only nominal directions,
    measured with those lights as the service applies them (same LEDs: the same seed draws the same
    intensities). At 1224 x 1024: at 612 x 512 the calibration's positions are within ~12 mm and the
    radius within ~0.15 %."""
    from pipeline.io import load_capture
    from pipeline.lights.calibration import calibrate_lights

    capture = CaptureSpec(manifest_lights="nominal", **dict(NEAR, width=1224, height=1024))
    ref = simulate_capture(
        tmp_path / "ref",
        plate=PlateSpec(shape="plane", radius_mm=None, tilt_deg=(1.0, -1.0)),
        capture=capture,
        seed=9,
    )
    lights = calibrate_lights([load_capture(ref)]).lights
    bundle = simulate_capture(tmp_path / "plate", plate=PlateSpec(), capture=capture, seed=9)
    doc = inspect(
        bundle, bundle / "target.json", out_dir=tmp_path / "out", light_calibration=lights
    ).document
    assert abs(doc["radius_error_pct"]) <= 0.1, doc  # acceptance: <= 0.1 %, right verdict
    assert doc["verdict"] == "pass"
    assert (
        "a light calibration was applied to the capture's nominal light directions"
        in doc["warnings"]
    )
    details = json.loads((tmp_path / "out" / "details.json").read_text())
    assert details["light_model"] == "near-field" and details["light_refinement"] is None
