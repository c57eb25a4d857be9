"""The deviation map in the target's frame (pipeline.judge.plate_map) and the tolerance-band colours."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from pipeline.artifacts.colours import (
    ABOVE_RGB,
    BELOW_RGB,
    IN_TOLERANCE_RGB,
    NO_DATA_RGB,
    tolerance_band_colormap,
)
from pipeline.judge.plate_map import load_plate_map, plate_map, to_camera_frame, to_target_frame


def _pose(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rng.uniform(-0.4, 0.4, 3)).as_matrix()
    T[:3, 3] = rng.uniform(-300, 300, 3) + np.array([0.0, 0.0, 3000.0])
    return T


def _field(x, y):
    """A deviation known everywhere in the target frame: a tilt and a 6 mm dent at (-600, 300)."""
    return (
        0.0004 * x - 0.0002 * y + 6.0 * np.exp(-((x + 600) ** 2 + (y - 300) ** 2) / (2 * 80.0**2))
    )


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_cells_hold_the_deviation_at_their_place_in_the_target_frame(seed):
    # vertices every 5 mm (as surface.ply's grid), centred in the 20 mm cells: a cell's mean is then
    # the field's mean over the cell, whatever the pose
    gx, gy = np.meshgrid(np.arange(-1500, 1500, 5.0) + 2.5, np.arange(-1000, 1000, 5.0) + 2.5)
    x, y = gx.ravel(), gy.ravel()
    z = (x**2) / (2 * 8000.0)  # any height: the map is of x and y
    T = _pose(seed)
    cam = to_camera_frame(np.column_stack([x, y, z]), T)
    m = plate_map(cam, _field(x, y), T, cells=150)
    assert m.cell_mm == 20.0  # 3000 / 150, a round size
    x0, x1, y0, y1 = m.extent_mm
    assert x0 <= x.min() < x0 + m.cell_mm and x1 - m.cell_mm <= x.max() <= x1
    assert y0 <= -1000 and y1 >= 1000
    ny, nx = m.deviation_mm.shape
    xc = m.x0_mm + (np.arange(nx) + 0.5) * m.cell_mm
    yc = m.y0_mm + (np.arange(ny) + 0.5) * m.cell_mm
    expected = _field(*np.meshgrid(xc, yc))
    ok = np.isfinite(m.deviation_mm)
    assert ok.mean() > 0.95
    # a cell's mean vs the field at its centre: the dent's curvature over 20 mm cells, ~0.03 mm
    np.testing.assert_allclose(m.deviation_mm[ok], expected[ok], atol=0.05)
    # the cell [-600, -580) x [300, 320) holds the dent's peak at its corner
    assert m.value_at(-600.0, 300.0) == pytest.approx(_field(-590.0, 310.0), abs=0.05)
    assert math.isnan(m.value_at(5000.0, 0.0))


def test_frames_round_trip_and_bad_inputs_are_named(tmp_path):
    T = _pose(3)
    p = np.array([[10.0, -20.0, 5.0], [300.0, 40.0, -2.0]])
    np.testing.assert_allclose(to_target_frame(to_camera_frame(p, T), T), p, atol=1e-9)
    with pytest.raises(ValueError, match=r"T_cam_target: expected a finite \(4, 4\) matrix"):
        to_target_frame(p, np.eye(3))
    with pytest.raises(ValueError, match="deviation_mm: expected one value per vertex"):
        plate_map(p, [1.0], T)
    with pytest.raises(ValueError, match="at least one vertex with a finite deviation"):
        plate_map(p, [np.nan, np.nan], T)
    with pytest.raises(ValueError, match="cells: expected >= 2"):
        plate_map(p, [1.0, 2.0], T, cells=1)
    with pytest.raises(ValueError, match=r"details\.json: not found"):
        load_plate_map(tmp_path)
    (tmp_path / "details.json").write_text(json.dumps({"defects": []}))
    (tmp_path / "surface.ply").write_bytes(b"ply\n")
    with pytest.raises(ValueError, match=r"details\.json: T_cam_target"):
        load_plate_map(tmp_path)


def test_tolerance_bands_are_calm_within_and_saturated_beyond():
    dev = np.array([0.0, 1.99, -1.99, 2.0001, 4.0, 9.0, -2.0001, -4.0, -9.0, np.nan])
    rgb = tolerance_band_colormap(dev, tolerance_mm=2.0, limit_mm=4.0)
    assert rgb.shape == (10, 3) and rgb.dtype == np.uint8
    for k in range(3):
        assert tuple(rgb[k]) == IN_TOLERANCE_RGB
    assert np.abs(rgb[3].astype(int) - ABOVE_RGB[0]).max() <= 1
    assert tuple(rgb[4]) == ABOVE_RGB[1] and tuple(rgb[5]) == ABOVE_RGB[1]
    assert np.abs(rgb[6].astype(int) - BELOW_RGB[0]).max() <= 1
    assert tuple(rgb[7]) == BELOW_RGB[1] and tuple(rgb[8]) == BELOW_RGB[1]
    assert tuple(rgb[9]) == NO_DATA_RGB
    with pytest.raises(ValueError, match="limit_mm: expected a finite number above tolerance_mm"):
        tolerance_band_colormap(dev, tolerance_mm=2.0, limit_mm=2.0)
    with pytest.raises(ValueError, match="tolerance_mm: expected a positive"):
        tolerance_band_colormap(dev, tolerance_mm=0.0, limit_mm=2.0)
