"""Bender geometry: the loaded radius from the top-roll displacement, its inverse, limits and the rolls' force."""

from __future__ import annotations

import math

import numpy as np
import pytest

from pipeline.forming import bender, springback
from pipeline.forming.records import FormingTarget, Machine, Material, PlateRecord
from pipeline.forming.rolling import PassSetup

MACHINE = Machine(
    "R3-01",
    bottom_roll_spacing_mm=1400.0,
    bottom_roll_diameter_mm=420.0,
    top_roll_diameter_mm=500.0,
)


def test_hand_checked_case():
    # Issue 14's machine and pass, 20 mm plate. By hand: a = 700, r_b = 210;
    # rho = (700^2 + 97^2) / (2 * 97) = 499409 / 194 = 2574.2732 mm; R = rho - r_b - t/2 = 2354.2732 mm.
    R = bender.loaded_radius_mm(97.0, MACHINE, 20.0)
    assert pytest.approx(2354.2732, abs=1e-3) == R
    assert bender.displacement_for_radius_mm(R, MACHINE, 20.0) == pytest.approx(97.0, abs=1e-9)


def test_circle_touches_the_three_rolls():
    # Build the configuration from the returned radius and check every tangency independently.
    t, d = 20.0, 97.0
    R = bender.loaded_radius_mm(d, MACHINE, t)
    a, rb, rt = 700.0, 210.0, 250.0
    top_centre_y = (
        rb + t + rt - d
    )  # the top roll just touching the flat plate, then moved down by d
    c = math.sqrt(
        (R + t / 2 + rb) ** 2 - a * a
    )  # centre of the plate's circle, from the bottom-roll tangency
    # bottom rolls: outer surface (R + t/2) externally tangent to the roll circle at (+-a, 0)
    assert math.hypot(a, c) == pytest.approx(R + t / 2 + rb, rel=1e-12)
    # top roll on the axis, inside the inner surface (R - t/2), internally tangent
    assert c - top_centre_y == pytest.approx(R - t / 2 - rt, abs=1e-9)


def test_top_roll_radius_cancels():
    other = Machine("R3-02", 1400.0, 420.0, 300.0)
    d = np.array([20.0, 60.0, 140.0])
    np.testing.assert_allclose(
        bender.loaded_radius_mm(d, other, 15.0), bender.loaded_radius_mm(d, MACHINE, 15.0)
    )


def test_small_displacement_approximation():
    # R = L^2 / (8 d) + d/2 - r_b - t/2 exactly; the shop formula L^2 / (8 d) is its leading term.
    t = 12.0
    for d in (0.5, 5.0, 50.0):
        R = bender.loaded_radius_mm(d, MACHINE, t)
        assert R - 1400.0**2 / (8 * d) == pytest.approx(d / 2 - 210.0 - t / 2, abs=1e-9)
    d = 0.2
    assert bender.loaded_radius_mm(d, MACHINE, t) / (1400.0**2 / (8 * d)) == pytest.approx(
        1.0, abs=2e-4
    )


def test_inverse_round_trip_and_flat():
    R = np.array([1200.0, 2500.0, 8000.0, 40000.0])
    d = bender.displacement_for_radius_mm(R, MACHINE, 25.0)
    assert np.all(np.diff(d) < 0)  # a larger radius needs less displacement
    np.testing.assert_allclose(bender.loaded_radius_mm(d, MACHINE, 25.0), R, rtol=1e-12)
    assert bender.displacement_for_radius_mm(math.inf, MACHINE, 25.0) == 0.0


def test_limits_name_the_field():
    d_max = bender.max_displacement_mm(MACHINE, 20.0)
    assert d_max == pytest.approx(700.0)  # these rolls never wrap a 20 mm plate before d = a
    tight = Machine("R3-03", 1400.0, 420.0, 1300.0)  # a big top roll: the plate wraps it first
    r_min = bender.min_loaded_radius_mm(tight, 20.0)
    assert r_min == pytest.approx(650.0 + 10.0)  # inner surface on the top roll: R - t/2 = r_t
    with pytest.raises(ValueError, match="displacement_mm"):
        bender.loaded_radius_mm(d_max + 1.0, MACHINE, 20.0)
    with pytest.raises(ValueError, match="displacement_mm"):
        bender.loaded_radius_mm(0.0, MACHINE, 20.0)
    with pytest.raises(ValueError, match="radius_mm"):
        bender.displacement_for_radius_mm(r_min - 1.0, tight, 20.0)
    with pytest.raises(ValueError, match="thickness_mm"):
        bender.loaded_radius_mm(50.0, MACHINE, -1.0)


def test_roll_force_three_point_limit_and_free_body():
    M = 1.0e8  # N mm over the plate's length
    # gentle bend: F -> 4 M / L (three-point bending)
    assert bender.roll_force_n(M, 1e7, MACHINE, 20.0) == pytest.approx(4 * M / 1400.0, rel=1e-4)
    # tight bend: the free body of one half, N along the normal at phi, sin(phi) = a / rho
    R, t = 1500.0, 20.0
    phi = math.asin(700.0 / (R + t / 2 + 210.0))
    N = M / (R * math.sin(phi))  # moment of N about the mid-surface under the top roll
    assert bender.roll_force_n(M, R, MACHINE, t) == pytest.approx(2 * N * math.cos(phi), rel=1e-12)
    assert bender.roll_force_n(M, math.inf, MACHINE, t) == 0.0


def test_vectorised_pass_model_agrees():
    # rolling.PassSetup writes the geometry and the force in curvature form for whole campaigns
    plate = PlateRecord(
        "p", FormingTarget(5000.0, 2.0, 3000.0, 4000.0, Material("AH36", 20.0, 355.0))
    )
    setup = PassSetup.of([MACHINE, MACHINE], [plate, plate])
    d = np.array([40.0, 120.0])
    R = bender.loaded_radius_mm(d, MACHINE, 20.0)
    np.testing.assert_allclose(setup.geometric_curvature(d), 1 / R, rtol=1e-12)
    S = springback.plane_strain_yield(355.0) * 1.2
    E = springback.plane_strain_modulus(206000.0, 0.3)
    moment = springback.bending_moment(1 / R, S, E, 20.0) * 4000.0
    np.testing.assert_allclose(
        setup.force_n(1 / R, 1.2), bender.roll_force_n(moment, R, MACHINE, 20.0), rtol=1e-12
    )
    # a rigid machine loads to the geometric curvature; a compliant one less
    np.testing.assert_allclose(setup.loaded_curvature(d, 1.2, 0.0), 1 / R, rtol=1e-12)
    assert np.all(setup.loaded_curvature(d, 1.2, 2.0) < 1 / R)
