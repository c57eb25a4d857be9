"""Forming inputs: issue 14's JSON shapes read, bad values refused with the field named."""

from __future__ import annotations

import math

import pytest

from pipeline.formats import InputError
from pipeline.forming import (
    AimSettings,
    FormingTarget,
    Machine,
    Material,
    PlateRecord,
    Priors,
    RollPass,
    advise,
)
from pipeline.io import Target

MACHINE_JSON = {
    "kind": "three-roll-pyramid",
    "bottom_roll_spacing_mm": 1400,
    "bottom_roll_diameter_mm": 420,
    "top_roll_diameter_mm": 500,
}
MATERIAL_JSON = {
    "grade": "AH36",
    "thickness_mm": 20,
    "yield_mpa": 355,
    "youngs_mpa": 206000,
    "poisson": 0.3,
}
PASS_JSON = {"method": "roll-bending", "machine_id": "R3-01", "top_roll_displacement_mm": 97.0}


def test_issue_shapes_read():
    m = Machine.from_dict("R3-01", MACHINE_JSON)
    assert (m.half_span_mm, m.bottom_roll_radius_mm, m.top_roll_radius_mm) == (700.0, 210.0, 250.0)
    mat = Material.from_dict(MATERIAL_JSON)
    assert mat == Material("AH36", 20.0, 355.0)
    assert (
        Material.from_dict({"grade": "DH36", "thickness_mm": 15, "yield_mpa": 355}).youngs_mpa
        == 206000.0
    )
    p = RollPass.from_dict(PASS_JSON, measured_radius_mm=5100.0, verdict="fail")
    assert (p.machine_id, p.top_roll_displacement_mm, p.inspected) == ("R3-01", 97.0, True)
    target = FormingTarget.from_target(
        Target("cylinder", 5000.0, (3000.0, 4000.0), 2.0), MATERIAL_JSON
    )
    assert (target.width_mm, target.length_mm, target.material.grade) == (3000.0, 4000.0, "AH36")
    # radii of the convex (camera) side <-> mid-surface
    assert target.mid_radius_mm(5000.0) == 4990.0 and target.surface_radius_mm(4990.0) == 5000.0
    assert target.mid_radius_mm(math.inf) == math.inf


@pytest.mark.parametrize(
    "make, field",
    [
        (lambda: Machine("R3-01", -1400.0, 420.0, 500.0), "bottom_roll_spacing_mm"),
        (lambda: Machine("R3-01", 1400.0, float("nan"), 500.0), "bottom_roll_diameter_mm"),
        (lambda: Machine("R3-01", 1400.0, 420.0, float("inf")), "top_roll_diameter_mm"),
        (lambda: Machine("R3-01", 400.0, 420.0, 500.0), "bottom_roll_spacing_mm"),
        (lambda: Machine("", 1400.0, 420.0, 500.0), "machine_id"),
        (lambda: Machine.from_dict("R3-01", {**MACHINE_JSON, "kind": "four-roll"}), "kind"),
        (lambda: Machine.from_dict("R3-01", {**MACHINE_JSON, "speed": 3}), "speed"),
        (
            lambda: Machine.from_dict(
                "R3-01", {k: v for k, v in MACHINE_JSON.items() if k != "top_roll_diameter_mm"}
            ),
            "top_roll_diameter_mm",
        ),
        (lambda: Material("AH36", 0.0, 355.0), "thickness_mm"),
        (lambda: Material("AH36", 20.0, "355"), "yield_mpa"),
        (lambda: Material("AH36", 20.0, 355.0, youngs_mpa=-1.0), "youngs_mpa"),
        (lambda: Material("AH36", 20.0, 355.0, poisson=0.6), "poisson"),
        (lambda: Material("AH36", 20.0, 300_000.0), "yield_mpa"),
        (lambda: Material(" ", 20.0, 355.0), "grade"),
        (
            lambda: FormingTarget(0.0, 2.0, 3000.0, 3000.0, Material("AH36", 20.0, 355.0)),
            "radius_mm",
        ),
        (
            lambda: FormingTarget(15.0, 2.0, 3000.0, 3000.0, Material("AH36", 20.0, 355.0)),
            "radius_mm",
        ),
        (
            lambda: FormingTarget(5000.0, -2.0, 3000.0, 3000.0, Material("AH36", 20.0, 355.0)),
            "tolerance_mm",
        ),
        (
            lambda: FormingTarget(
                5000.0, 2.0, 3000.0, 3000.0, Material("AH36", 20.0, 355.0), "outer"
            ),
            "surface",
        ),
        (lambda: FormingTarget(5000.0, 2.0, 3000.0, 3000.0, MATERIAL_JSON), "material"),
        (
            lambda: FormingTarget.from_target(
                Target("sphere", 5000.0, (3000.0, 3000.0), 2.0), MATERIAL_JSON
            ),
            "shape",
        ),
        (
            lambda: FormingTarget.from_target(
                Target("cylinder", 5000.0, (3000.0, 3000.0), 2.0), None
            ),
            "material",
        ),
        (lambda: RollPass("R3-01", float("nan")), "top_roll_displacement_mm"),
        (lambda: RollPass("R3-01", 97.0, measured_radius_mm=-5.0), "measured_radius_mm"),
        (lambda: RollPass("R3-01", 97.0, measured_radius_mm=5000.0, verdict="ok"), "verdict"),
        (lambda: RollPass("R3-01", 97.0, verdict="pass"), "measured_radius_mm"),
        (lambda: RollPass.from_dict({**PASS_JSON, "method": "press-brake"}), "method"),
        (
            lambda: RollPass.from_dict({k: v for k, v in PASS_JSON.items() if k != "machine_id"}),
            "machine_id",
        ),
        (
            lambda: PlateRecord(
                "p",
                FormingTarget(5000.0, 2.0, 3000.0, 3000.0, Material("AH36", 20.0, 355.0)),
                (PASS_JSON,),
            ),
            "passes[0]",
        ),
    ],
)
def test_bad_inputs_name_the_field(make, field):
    with pytest.raises(InputError) as err:
        make()
    assert err.value.field == field
    assert field in str(err.value)


def test_advice_inputs_name_the_field():
    machines = {"R3-01": Machine.from_dict("R3-01", MACHINE_JSON)}
    target = FormingTarget(5000.0, 2.0, 3000.0, 3000.0, Material("AH36", 20.0, 355.0))
    with pytest.raises(InputError, match="machine_id"):
        advise(PlateRecord("p", target), machines)  # a first pass needs its machine
    with pytest.raises(InputError, match="R9-99"):
        advise(PlateRecord("p", target), machines, machine_id="R9-99")
    not_inspected = PlateRecord("p", target, (RollPass("R3-01", 97.0),))
    with pytest.raises(InputError) as err:
        advise(not_inspected, machines)
    assert err.value.field == "passes[0].measured_radius_mm"
    with pytest.raises(ValueError, match="over_probability"):
        AimSettings(over_probability=0.7)
    with pytest.raises(ValueError, match="scatter_mm"):
        Priors(scatter_mm=0.0)
