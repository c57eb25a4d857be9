"""Virtual templates: sections of analytic cylinders."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from pipeline.judge.sections import cut_sections, plate_frame, section_positions
from tests.web.plates import cylinder_grid


def _sag(radius_mm, x):
    return radius_mm - np.sqrt(radius_mm**2 - x**2)


def _pose(vertices, rotation, shift):
    return (vertices - [0, 0, 3000.0]) @ rotation.T + [0, 0, 3000.0] + shift


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_gap_matches_two_cylinders(seed):
    # Target R 5000, plate R 5050 touching at the apex, both posed by the same random
    # rigid motion (tilt up to 10 deg): the gap is the difference of sagittas, whatever
    # the pose. Grid 50 mm -> chord error 50^2/(8 R) ~ 0.06 mm per surface, nearly the
    # same on both (radii 1 % apart) and the plane's tilt adds a cos(slope) factor on
    # gaps of <= 2.3 mm: 0.02 mm covers both.
    rng = np.random.default_rng(seed)
    rot = Rotation.from_rotvec(rng.uniform(-1, 1, 3) * np.deg2rad(10) / np.sqrt(3)).as_matrix()
    shift = rng.uniform(-200, 200, 3)
    tv, tf, _ = cylinder_grid(radius_mm=5000.0, size_mm=(3000.0, 2000.0), n=(61, 41))
    mv, mf, _ = cylinder_grid(radius_mm=5050.0, size_mm=(3000.0, 2000.0), n=(61, 41))
    frame, sections = cut_sections(
        _pose(mv, rot, shift), mf, _pose(tv, rot, shift), tf, spacing_mm=500.0
    )
    # Frames are stacked along the cylinder axis (camera y before the pose).
    assert abs(frame.along @ (rot @ [0, 1, 0])) > 0.999
    assert frame.normal @ (rot @ [0, 0, -1]) > 0.999  # towards the cameras
    np.testing.assert_allclose([s.position_mm for s in sections], [500.0, 1000.0, 1500.0], atol=1.0)
    for s in sections:
        x = s.u_mm - 1500.0
        expected = _sag(5000.0, x) - _sag(5050.0, x)
        ok = np.isfinite(s.gap_mm)
        assert ok.mean() > 0.97
        np.testing.assert_allclose(s.gap_mm[ok], expected[ok], atol=0.02)


def test_positions_are_centred_and_spaced():
    tv, _, _ = cylinder_grid(radius_mm=5000.0, size_mm=(3000.0, 2000.0), n=(31, 21))
    frame = plate_frame(tv)
    positions = section_positions(frame, 600.0)
    np.testing.assert_allclose(positions, [400.0, 1000.0, 1600.0], atol=1e-6)
    with pytest.raises(ValueError, match="spacing_mm: expected a positive number"):
        section_positions(frame, 0.0)
    with pytest.raises(ValueError, match="spacing_mm: expected at most 200 sections"):
        section_positions(frame, 5.0)


def test_holes_are_nan_not_bridged():
    tv, tf, _ = cylinder_grid(radius_mm=5000.0, size_mm=(3000.0, 2000.0), n=(61, 41))
    # Remove the measured faces over x in (-400, 400): the section must show NaN there.
    centres = tv[tf].mean(axis=1)
    mf = tf[np.abs(centres[:, 0]) > 400]
    _, sections = cut_sections(tv, mf, tv, tf, spacing_mm=1000.0)
    s = sections[0]
    x = s.u_mm - 1500.0
    assert np.all(np.isnan(s.gap_mm[np.abs(x) < 350]))
    np.testing.assert_allclose(s.gap_mm[np.abs(x) > 450], 0.0, atol=1e-9)


def test_plate_frame_refuses_bad_input():
    with pytest.raises(
        ValueError, match=r"target_vertices_mm: expected shape \(V, 3\) with V >= 6"
    ):
        plate_frame(np.zeros((4, 3)))
    bad = np.zeros((10, 3))
    bad[0, 0] = np.nan
    with pytest.raises(ValueError, match="expected finite coordinates"):
        plate_frame(bad)


def test_trend_axis_ticks_are_round_numbers():
    from app.axes import nice_ticks
    from web.charts import trend_chart

    assert nice_ticks(0.0, 0.017) == ([0.0, 0.005, 0.01, 0.015, 0.02], 3)
    assert nice_ticks(-0.16, 2.16) == ([-0.5, 0.0, 0.5, 1.0, 1.5, 2.0, 2.5], 1)
    assert nice_ticks(0.0, 130.0) == ([0.0, 50.0, 100.0, 150.0], 0)
    with pytest.raises(ValueError, match="axis range: expected finite lo <= hi"):
        nice_ticks(1.0, 0.0)
    chart = trend_chart([(1, "#1", 0.017, 0.22), (2, "#2", -0.4, 2.6)], tolerance_mm=2.0)
    radius, deviation = chart.series
    assert [label for _, label in radius.ticks] == [
        "-0.5",
        "-0.4",
        "-0.3",
        "-0.2",
        "-0.1",
        "0.0",
        "0.1",
    ]
    assert [label for _, label in deviation.ticks] == ["0", "1", "2", "3"]
    # the tolerance line lies inside the panel; without a radius band, none on the radius panel
    [(y_tol, label)] = deviation.limits
    assert deviation.y0 < y_tol < deviation.y1 and label == "tolerance" and radius.limits == []
    banded = trend_chart(
        [(1, "1", 0.017, 0.22), (2, "2", -0.4, 2.6)], tolerance_mm=2.0, radius_band_pct=0.9
    )
    (y_hi, _), (y_lo, _) = banded.series[0].limits
    panel = banded.series[0]
    assert panel.y0 <= y_hi < y_lo <= panel.y1  # +0.9 % above -0.9 %, both drawn in the panel


def test_template_gap_enlargement_follows_the_tolerance_or_the_gap():
    from pipeline.judge.sections import Section
    from web.charts import section_drawings

    u = np.linspace(0.0, 3000.0, 61)
    target_h = 225.0 - (5000.0 - np.sqrt(5000.0**2 - (u - 1500.0) ** 2))  # a 5 m arc, mm

    def drawing(gap_mm):
        gap = np.full_like(u, gap_mm)
        return section_drawings(
            [Section(100.0, u, target_h, target_h + gap, gap)], tolerance_mm=2.0, width=1100.0
        )[0]

    sx = (1100.0 - 80.0) / 3000.0  # px per mm along the section (40 px pads)
    small = drawing(0.05)  # noise-level gaps: the tolerance sets the scale (2 mm -> <= 24 px)
    assert 2.0 * small.exaggeration * sx <= 24.0 < 2.0 * 2.5 * small.exaggeration * sx
    large = drawing(6.0)  # a gap beyond tolerance sets it instead
    assert 6.0 * large.exaggeration * sx <= 24.0 and large.exaggeration < small.exaggeration
    with pytest.raises(ValueError, match="tolerance_mm: expected a positive number"):
        section_drawings(
            [Section(100.0, u, target_h, target_h, np.zeros_like(u))], tolerance_mm=0.0
        )


def test_a_frame_goes_through_each_defect(tmp_path):
    """Frames at a spacing miss a small dent; the frame through its centroid (details.json, target
    frame moved by the registration) crosses it and shows its depth."""
    import json

    from pipeline.artifacts.ply import write_surface_ply, write_target_ply
    from pipeline.judge.sections import load_sections

    h, w = 60, 80
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    x_mm, y_mm = (xx - (w - 1) / 2) * 25.0, (yy - (h - 1) / 2) * 25.0
    dent = 5.0 * np.exp(-((x_mm - 330.0) ** 2 + (y_mm - 140.0) ** 2) / (2 * 40.0**2))
    z = 3000.0 - dent  # flat plate 3 m from the cameras, a 5 mm bump towards them at (330, 140)
    points = np.dstack([x_mm, y_mm, z])
    write_surface_ply(tmp_path / "surface.ply", points, np.ones((h, w), bool), dent)
    gx, gy = np.meshgrid(np.linspace(-990.0, 990.0, 12), np.linspace(-740.0, 740.0, 9))
    tv = np.column_stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)])
    idx = np.arange(gx.size).reshape(gx.shape)
    a, b, c, d = (
        idx[:-1, :-1].ravel(),
        idx[:-1, 1:].ravel(),
        idx[1:, 1:].ravel(),
        idx[1:, :-1].ravel(),
    )
    tf = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    T = np.eye(4)
    T[2, 3] = 3000.0  # target frame -> camera frame: 3 m along the optical axis
    write_target_ply(tmp_path / "target.ply", tv, tf, T)
    (tmp_path / "result.json").write_text(json.dumps({"tolerance_mm": 2.0, "artifacts": {}}))
    details = {"T_cam_target": T.tolist(), "defects": [{"centroid_mm": [330.0, 140.0]}]}
    (tmp_path / "details.json").write_text(json.dumps(details))

    _frame, sections, _tol = load_sections(tmp_path, spacing_mm=700.0)
    through = [s for s in sections if s.defect == 1]
    assert len(through) == 1
    worst = float(np.nanmax(np.abs(through[0].gap_mm)))
    assert worst == pytest.approx(5.0, abs=0.5)
    others = [float(np.nanmax(np.abs(s.gap_mm))) for s in sections if s.defect is None]
    assert others and max(others) < worst


def _sphere_grid(radius_mm, size_mm, n):
    x = np.linspace(-size_mm[0] / 2, size_mm[0] / 2, n[0])
    y = np.linspace(-size_mm[1] / 2, size_mm[1] / 2, n[1])
    xx, yy = np.meshgrid(x, y)
    z = radius_mm - np.sqrt(radius_mm**2 - xx**2 - yy**2)
    tv = np.column_stack([xx.ravel(), yy.ravel(), z.ravel()])
    idx = np.arange(xx.size).reshape(xx.shape)
    a, b, c, d = (
        idx[:-1, :-1].ravel(),
        idx[:-1, 1:].ravel(),
        idx[1:, 1:].ravel(),
        idx[1:, :-1].ravel(),
    )
    return tv, np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])


@pytest.mark.parametrize("turn_deg", [0.0, 30.0, 45.0])
def test_frames_on_a_sphere_run_square_to_the_plate(turn_deg):
    """A sphere bends alike every way: the frame lines follow the target's x (its first side), not
    a diagonal the curvature fit happens to pick, however the plate lies under the cameras."""
    tv, tf = _sphere_grid(8000.0, (3000.0, 2000.0), (61, 41))
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("xz", [180.0, turn_deg], degrees=True).as_matrix()
    T[:3, 3] = [100.0, -50.0, 3000.0]
    cam = tv @ T[:3, :3].T + T[:3, 3]
    frame, sections = cut_sections(cam, tf, cam, tf, spacing_mm=500.0, target_axes=T[:3, :3])
    assert abs(frame.across @ T[:3, 0]) > 0.999
    np.testing.assert_allclose(np.diff(frame.across_range_mm), [3000.0], atol=30.0)
    for s in sections:
        ok = np.isfinite(s.gap_mm)
        assert ok.mean() > 0.95 and np.abs(s.gap_mm[ok]).max() < 1e-6


def test_frames_follow_the_target_axis_it_bends_along():
    """A cylinder bent along the target's y (a mesh target need not bend along x): the frame lines
    run along y, frames are stacked along x."""
    tv, _tf, _ = cylinder_grid(radius_mm=5000.0, size_mm=(3000.0, 2000.0), n=(61, 41))
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("z", 90.0, degrees=True).as_matrix()  # target y = camera -x
    frame = plate_frame(tv, T[:3, :3])
    assert abs(frame.across @ T[:3, 1]) > 0.999
    with pytest.raises(ValueError, match=r"target_axes: expected a finite \(3, 3\) rotation"):
        plate_frame(tv, np.eye(2))


def test_a_frame_goes_through_a_chosen_point():
    tv, tf, _ = cylinder_grid(radius_mm=5000.0, size_mm=(3000.0, 2000.0), n=(61, 41))
    frame, sections = cut_sections(
        tv,
        tf,
        tv,
        tf,
        spacing_mm=700.0,
        chosen_mm=[np.array([0.0, 333.0, 3000.0]), np.array([0.0, 5000.0, 3000.0])],
    )
    chosen = [s for s in sections if s.chosen]
    assert len(chosen) == 1  # the point off the plate is skipped
    assert chosen[0].defect is None
    line = frame.line_mm(chosen[0].position_mm)
    np.testing.assert_allclose(line[:, 1], [333.0, 333.0], atol=1.0)


def test_gap_labels_never_overlap_and_the_worst_gap_is_labelled():
    """A section measured over only a fifth of its length (a plate partly off the camera) with a
    sharp gap between two evenly spread label places: the labels keep apart, the worst gap has one."""
    from pipeline.judge.sections import Section
    from web.charts import LABEL_SPACING_PX, section_drawings

    u = np.linspace(0.0, 3000.0, 241)
    target_h = np.zeros_like(u)
    gap = np.full_like(u, np.nan)
    part = slice(100, 149)
    gap[part] = 0.1 * np.sin(u[part] / 50.0)
    gap[131] = -3.2
    section = Section(1000.0, u, target_h, target_h + gap, gap)
    [drawing] = section_drawings([section], tolerance_mm=2.0)
    xs = sorted(label.x for label in drawing.labels)
    assert len(xs) >= 2 and np.diff(xs).min() >= LABEL_SPACING_PX
    worst = [label for label in drawing.labels if label.gap_mm == pytest.approx(-3.2)]
    assert len(worst) == 1 and worst[0].out_of_tolerance


def test_templates_are_placed_in_the_targets_frame_with_its_edges_named():
    """Issue 26 (one frame for the operator): a frame line at x = -803 mm of a 3000 mm plate is
    "x = −803 mm, 697 mm from edge D", its drawing runs from edge A (y smallest) to edge C."""
    import numpy as np

    from app.plate_frame import frame_place

    placed = frame_place(np.array([[-803.2, -1500.0], [-802.8, 1500.0]]), 1500.0)
    assert placed.where == "x = \u2212803 mm, 697 mm from edge D"
    assert placed.ends == ("edge A (y \u22121500)", "edge C (y +1500)")
    across = frame_place(np.array([[1500.0, 0.2], [-1500.0, 0.1]]), 1500.0)
    assert across.where == "y = 0 mm, 1500 mm from edge A"
    assert across.ends == ("edge B (x +1500)", "edge D (x \u22121500)")
