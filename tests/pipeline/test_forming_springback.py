"""Springback (Gardiner, plane strain): published values, the elastic and fully plastic limits, the history rule."""

from __future__ import annotations

import math

import numpy as np
import pytest

from pipeline.forming import springback as sb
from pipeline.forming.records import FormingTarget, Machine, Material, PlateRecord, RollPass
from pipeline.forming.rolling import plate_curvatures

MACHINE = Machine("R3-01", 1400.0, 420.0, 500.0)


def test_textbook_example():
    # Kalpakjian & Schmid, Manufacturing Engineering and Technology, sec. 16.5, example "Estimating
    # springback": a 20-gage steel sheet (0.0359 in) bent to R_i = 0.5 in, Y = 42,000 psi,
    # E = 29e6 psi: R_i Y / (E T) = 0.0201, R_i / R_f = 0.94, R_f = 0.53 in; to end at 0.5 in it must be
    # bent to R_i = 0.47 in. (The book's narrow strip: uniaxial Y and E; units cancel.)
    t, Y, E = 0.0359, 42_000.0, 29e6
    assert 0.5 * Y / (E * t) == pytest.approx(0.0201, abs=1e-4)
    ratio = sb.gardiner_ratio(0.5, Y, E, t)
    assert ratio == pytest.approx(0.94, abs=5e-3)
    assert round(0.5 / ratio, 2) == 0.53
    assert 1.0 / sb.unloaded_curvature(1 / 0.5, Y, E, t) == pytest.approx(0.5 / ratio, rel=1e-12)
    assert round(1.0 / sb.loaded_curvature_for(1 / 0.5, Y, E, t), 2) == 0.47


def test_moment_form_is_gardiners_relation():
    # 1/R' = 1/R - M/(E'I) with the elastic-perfectly-plastic moment is R/R' = 1 - 3x + 4x^3
    S, E, t = 410.0, 226_000.0, 20.0
    R = np.array([800.0, 2000.0, 4000.0, 5500.0])
    x = R * S / (E * t)
    assert np.all(x < 0.5)
    np.testing.assert_allclose(
        R * sb.unloaded_curvature(1 / R, S, E, t), 1 - 3 * x + 4 * x**3, rtol=1e-9, atol=1e-12
    )
    np.testing.assert_allclose(sb.gardiner_ratio(R, S, E, t), 1 - 3 * x + 4 * x**3, rtol=1e-12)


def test_plane_strain_constants():
    assert sb.plane_strain_modulus(206_000.0, 0.3) == pytest.approx(206_000.0 / 0.91)
    assert sb.plane_strain_yield(355.0) == pytest.approx(355.0 * 2 / math.sqrt(3))
    assert sb.plane_strain_yield(355.0, "tresca") == 355.0
    with pytest.raises(ValueError, match="criterion"):
        sb.plane_strain_yield(355.0, "rankine")
    with pytest.raises(ValueError, match="poisson"):
        sb.plane_strain_modulus(206_000.0, 0.5)


def test_elastic_no_permanent_set():
    S, E, t = 410.0, 226_000.0, 20.0
    ky = sb.yield_curvature(S, E, t)
    assert ky == pytest.approx(2 * S / (E * t))
    k = np.array([0.0, 0.3 * ky, ky])
    np.testing.assert_array_equal(sb.unloaded_curvature(k, S, E, t), 0.0)
    assert sb.gardiner_ratio(1 / ky, S, E, t) == 0.0  # x = 1/2 exactly: Gardiner's elastic limit
    # just past first yield the set grows from zero, continuously (1.5 e^2 k_y for k = k_y (1 + e))
    e = 1e-3
    assert sb.unloaded_curvature(ky * (1 + e), S, E, t) == pytest.approx(1.5 * e * e * ky, rel=5e-3)
    # the moment is continuous at first yield (2/3 of the fully plastic moment) and elastic below
    Mp = S * t * t / 4
    assert sb.bending_moment(ky, S, E, t) == pytest.approx(2 / 3 * Mp)
    assert sb.bending_moment(0.5 * ky, S, E, t) == pytest.approx(E * t**3 / 12 * 0.5 * ky)


def test_fully_plastic_limit():
    # springback tends to M_p / (E' I) = 3 S / (E' t) = 1.5 k_y (rigid-plastic; Marciniak, Duncan & Hu ch. 6)
    S, E, t = 410.0, 226_000.0, 10.0
    ky = sb.yield_curvature(S, E, t)
    k = 500 * ky
    assert k - sb.unloaded_curvature(k, S, E, t) == pytest.approx(3 * S / (E * t), rel=1e-5)
    assert sb.bending_moment(k, S, E, t) == pytest.approx(S * t * t / 4, rel=1e-5)
    ks = np.linspace(1.01, 40, 200) * ky
    assert np.all(
        np.diff(ks - sb.unloaded_curvature(ks, S, E, t)) > 0
    )  # springback grows to its limit


def test_inverse():
    S, E, t = 410.0, 226_000.0, 20.0
    for ku in (1 / 15000, 1 / 5000, 1 / 1500):
        kl = sb.loaded_curvature_for(ku, S, E, t)
        assert sb.unloaded_curvature(kl, S, E, t) == pytest.approx(ku, rel=1e-10)
    with pytest.raises(ValueError, match="unloaded"):
        sb.loaded_curvature_for(0.0, S, E, t)


def test_history_rule():
    S, E, t = 410.0, 226_000.0, 20.0
    k1, k_less, k2 = 5e-4, 4e-4, 6e-4
    after = sb.curvatures_after_passes([k1, k_less, k1, k2, k_less], S, E, t)
    single = sb.unloaded_curvature(np.array([k1, k2]), S, E, t)
    # a pass that does not load beyond an earlier one leaves the shape; a deeper one acts as if alone
    np.testing.assert_allclose(
        after, [single[0], single[0], single[0], single[1], single[1]], rtol=1e-15
    )
    # a plate that already saw more than a pass loads it to is left unchanged by it
    np.testing.assert_allclose(
        sb.curvatures_after_passes([k_less], S, E, t, initial_loaded=k2), single[1]
    )


def test_history_rule_through_the_bender():
    target = FormingTarget(5000.0, 2.0, 3000.0, 4000.0, Material("AH36", 20.0, 355.0))
    plate = PlateRecord(
        "p", target, (RollPass("R3-01", 100.0), RollPass("R3-01", 90.0), RollPass("R3-01", 104.0))
    )
    loaded, unloaded = plate_curvatures(
        plate, {"R3-01": MACHINE}, yield_factor=1.2, compliance_mm_per_mn={"R3-01": 2.0}
    )
    assert loaded[1] < loaded[0] < loaded[2]
    assert unloaded[1] == unloaded[0]  # the shallower pass changes nothing
    assert unloaded[2] > unloaded[0]
