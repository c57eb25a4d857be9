"""The inspection's own uncertainty in the forming model: read from result.json, weighed per pass, a
not-capable inspection named; older results keep the model's constant."""

from __future__ import annotations

import dataclasses
import math

import pytest

from pipeline.formats import InputError
from pipeline.forming import PlateRecord, RollPass, advise, curvature_band, fit
from pipeline.forming.learning import Priors, inspection_variance
from pipeline.forming.records import inspection_quality
from tests.pipeline.forming_cases import MACHINES, rolled, target


def test_result_uncertainty_and_capability_are_read():
    assert inspection_quality({}) == (None, True)  # an older result: the model's constant
    assert inspection_quality({"uncertainty": {"k": 2, "radius_mm": 10.0}}) == (5.0, True)
    assert inspection_quality({"uncertainty": {"k": 2, "radius_mm": None}}) == (None, True)
    warned = {"warnings": ["measurement Not Capable for the tolerance: TUR 2.1 < 4"]}
    assert inspection_quality(warned) == (None, False)
    with pytest.raises(InputError, match="radius_mm"):
        inspection_quality({"uncertainty": {"k": 2, "radius_mm": -1.0}})
    with pytest.raises(InputError, match="k"):
        inspection_quality({"uncertainty": {"k": 0, "radius_mm": 1.0}})
    process = {"method": "roll-bending", "machine_id": "R3-01", "top_roll_displacement_mm": 90.0}
    q = RollPass.from_dict(
        process,
        measured_radius_mm=5100.0,
        verdict="fail",
        result={"uncertainty": {"k": 2, "radius_mm": 25.5}, **warned},
    )
    assert q.radius_uncertainty_mm == 12.75 and q.capable is False and q.flipped is False


def test_a_flipped_pass_alone_may_have_a_negative_displacement():
    assert RollPass("R3-01", -12.0, flipped=True).top_roll_displacement_mm == -12.0
    with pytest.raises(InputError, match="top_roll_displacement_mm"):
        RollPass("R3-01", -12.0)
    with pytest.raises(InputError, match="flipped"):
        RollPass("R3-01", 12.0, flipped="yes")  # type: ignore[arg-type]


def _probe(u_mm: float | None, capable: bool = True) -> PlateRecord:
    """A 5 m plate after an under-bent first pass, its inspection with uncertainty ``u_mm`` (k=1)."""
    plate = rolled(PlateRecord("p", target(5000.0, 20.0)), 105.0, factor=1.2, compliance=2.0)
    q = plate.passes[-1]
    q = dataclasses.replace(q, radius_uncertainty_mm=u_mm, capable=capable)
    return PlateRecord("p", plate.target, (q,))


def test_the_inspections_uncertainty_sets_its_weight():
    priors = Priors()
    older, fine, coarse = _probe(None), _probe(0.5), _probe(0.0025 * 6450.0)
    k = 1.0 / older.target.mid_radius_mm(older.passes[0].measured_radius_mm)
    # no uncertainty: today's constant (0.05 % and 0.1 mm of sagitta)
    w = older.target.width_mm
    const = (priors.radius_noise * k) ** 2 + (8 * priors.sagitta_noise_mm / w**2) ** 2
    assert inspection_variance(older, 0, priors) == pytest.approx(const)
    # with it: U/k of the radius, relative to the mid-surface radius (dk = u k^2)
    r_mid = coarse.target.mid_radius_mm(coarse.passes[0].measured_radius_mm)
    assert math.sqrt(inspection_variance(coarse, 0, priors)) == pytest.approx(
        0.0025 * 6450.0 / r_mid**2
    )
    assert inspection_variance(fine, 0, priors) < const < inspection_variance(coarse, 0, priors)
    # a coarse inspection (0.25 % sd, as at 320x256 with 6 lights) widens the next pass's prediction
    # and moves the aim to the open side; its own fit is the same plate
    a_fine, a_coarse = advise(fine, MACHINES), advise(coarse, MACHINES)
    span = [
        a.expected_radius_range_mm[1] - a.expected_radius_range_mm[0] for a in (a_fine, a_coarse)
    ]
    assert span[1] > span[0]
    assert a_coarse.top_roll_displacement_mm < a_fine.top_roll_displacement_mm
    assert a_coarse.basis["aim"]["probability_over_band"] <= 0.005 + 1e-9
    entry = a_coarse.basis["inspections"][0]
    assert entry["radius_uncertainty_mm"] == 0.0025 * 6450.0 and entry["capable"] is True


def test_the_fit_weighs_each_inspection_by_its_uncertainty():
    # two passes of one plate, the second's inspection 3 % off: taken at the model's constant the fit
    # splits the difference; reported as coarse (3 % sd), the fit follows the first
    plate = rolled(PlateRecord("h", target(5000.0, 20.0)), 100.0, factor=1.2, compliance=2.0)
    plate = rolled(plate, 105.0, factor=1.2, compliance=2.0)
    first, second = plate.passes
    misfit = []
    for u in (None, 0.03 * second.measured_radius_mm):
        wrong = dataclasses.replace(
            second, measured_radius_mm=1.03 * second.measured_radius_mm, radius_uncertainty_mm=u
        )
        record = PlateRecord("h", plate.target, (first, wrong))
        k_fit = fit([record], MACHINES).curvatures(record)[1][0]
        misfit.append(abs(k_fit * plate.target.mid_radius_mm(first.measured_radius_mm) - 1.0))
    assert misfit[0] > 0.01 and misfit[1] < 0.1 * misfit[0]


def test_a_not_capable_inspection_is_weighed_and_named():
    priors = Priors()
    plate = _probe(None, capable=False)
    band = curvature_band(plate.target)
    assert math.sqrt(inspection_variance(plate, 0, priors)) >= band / 8 * (1 - 1e-12)
    advice = advise(plate, MACHINES)
    assert advice.action == "bend"
    assert any("not capable" in w and "pass 1" in w for w in advice.basis["warnings"])
    assert advice.basis["inspections"][0]["capable"] is False
    assert advice.basis["enough_data"] is False
