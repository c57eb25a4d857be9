"""The demo cell's simulated cameras: the simulator's rendering, exposure and auto-exposure."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from pipeline.acquisition import (
    SimulatedCamera,
    SimulatedCell,
    SimulatedLightController,
    auto_exposure,
)
from pipeline.acquisition.acquire import EXPOSURE_FLOOR, EXPOSURE_LIMIT, brightest_fraction
from pipeline.formats import CellCamera
from pipeline.io import load_capture
from pipeline.simulate import CaptureSpec, PlateSpec, default_rig, render_radiance, simulate_capture


def test_render_radiance_is_what_simulate_capture_renders(tmp_path):
    rig = default_rig(width=160, height=128)
    spec = CaptureSpec(n_lights=4, noise=0.0, dark_level=0.0, width=160, height=128)
    bundle = simulate_capture(tmp_path, capture=spec, rig=rig, seed=3)
    capture = load_capture(bundle)
    left = render_radiance(PlateSpec(), rig, capture.lights, side="left", capture=spec, seed=3)
    np.testing.assert_array_equal(np.rint(left * 65535), capture.images)
    right = render_radiance(PlateSpec(), rig, capture.lights, side="right", capture=spec, seed=3)
    np.testing.assert_allclose(np.rint(right.mean(axis=0) * 65535), capture.stereo_right, atol=1)


@pytest.fixture
def cell():
    rig = default_rig(width=200, height=160)
    lights = CaptureSpec(n_lights=4, near_field_mm=2000.0).lights(
        np.array([0.0, 0.0, 3000.0]), np.ones(4)
    )
    controller = SimulatedLightController(4, False)
    return SimulatedCell(rig, lights, 3000.0, controller, "PLATE-7")


def _camera(cell, side="left"):
    camera = SimulatedCamera(side, CellCamera(driver="simulated"), cell)
    camera.configure(pixel_format="Mono16", width=200, height=160)
    return camera


def test_a_frame_shows_the_lights_the_controller_switched_on(cell):
    camera = _camera(cell)
    camera.set_exposure(5000.0, step="test")

    def signal() -> np.ndarray:  # local means: the sensor noise averaged out
        return cv2.blur(camera.grab(step="test", timeout_s=1).image.astype(float), (15, 15))

    dark = signal()
    cell.controller.on(1, step="test")
    one = signal() - dark
    cell.controller.on(2, step="test")
    both = signal() - dark
    cell.controller.off(1, step="test")
    two = signal() - dark
    assert one.mean() > 1000 and two.mean() > 1000 and not np.allclose(one, two, atol=500)
    np.testing.assert_allclose(both, one + two, atol=300)  # light adds up


def test_exposure_scales_the_signal(cell):
    camera = _camera(cell)
    cell.controller.on(0, step="test")
    frames = {}
    for exposure in (2000.0, 4000.0):
        camera.set_exposure(exposure, step="test")
        frames[exposure] = camera.grab(step="test", timeout_s=1).image.astype(float).mean()
    dark_level = CaptureSpec().dark_level * 65535
    assert (frames[4000.0] - dark_level) / (frames[2000.0] - dark_level) == pytest.approx(
        2.0, rel=0.02
    )


def test_auto_exposure_brings_both_cameras_between_floor_and_limit(cell):
    cameras = [_camera(cell, "left"), _camera(cell, "right")]
    for k in range(4):
        cell.controller.on(k, step="test")
    exposures, shots = auto_exposure(cameras, bit_depth=16, timeout_s=1.0, step="test")
    assert shots >= 2
    for camera in cameras:
        assert exposures[camera.side] == pytest.approx(
            camera.set_exposure(exposures[camera.side], step="test")
        )
        p = brightest_fraction(camera.grab(step="check", timeout_s=1).image, 16)
        assert EXPOSURE_FLOOR <= p <= EXPOSURE_LIMIT


def test_photometric_frames_are_exposed_for_one_light_not_all(tmp_path):
    """Auto-exposure meters all lights together, then the brightest single-light frame: each
    photometric frame uses most of the sensor's range (issue 24: the demo cell's plate)."""
    from pipeline.acquisition import acquire, write_demo_cell

    cell = write_demo_cell(tmp_path / "cell", width=320, height=256)
    bundle = acquire(cell, plate_id="EXPOSED", out_dir=tmp_path / "bundle")
    record = json.loads((bundle / "capture.json").read_text())["acquisition"]
    exposure = record["cameras"]["left"]["exposure_us"]
    assert exposure["photometric"] > 3 * exposure["stereo"]
    brightest = max(
        float(np.percentile(cv2.imread(str(bundle / f"ps_{k:02d}.png"), -1), 99.9))
        for k in range(8)
    )
    assert 0.5 < brightest / 65535 < 0.95


def test_a_conveyor_along_the_plate_carries_it_to_the_stations_pose():
    """carried_pose (the simulated cell's conveyor) and station_pose (simulate capture --stations)
    put a plate carried along its own length at the same place, yaw included."""
    from pipeline.simulate import carried_pose, plate_pose, station_pose

    plate = PlateSpec(size_mm=(3000.0, 7200.0))
    direction = -plate_pose(plate)[:3, 1]
    for travel, yaw in ((0.0, 0.0), (2100.0, 0.25), (4200.0, -0.3)):
        np.testing.assert_allclose(
            carried_pose(
                plate,
                first_centre_y_mm=-2100.0,
                travel_mm=travel,
                direction=direction,
                yaw_deg=yaw,
            ),
            station_pose(plate, -2100.0 + travel, yaw),
            atol=1e-9,
        )
