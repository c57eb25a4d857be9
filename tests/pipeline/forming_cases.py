"""A machine, a target and a plate rolled on the true physics: shared by the forming tests."""

from __future__ import annotations

import math

from pipeline.forming import (
    FormingTarget,
    Machine,
    Material,
    PlateRecord,
    RollPass,
    curvature_band,
)
from pipeline.forming.advice import target_curvature
from pipeline.forming.rolling import plate_curvatures

MACHINE = Machine("R3-01", 1400.0, 420.0, 500.0)


MACHINES = {"R3-01": MACHINE}


def target(radius=5000.0, t=20.0, width=3000.0):
    return FormingTarget(radius, 2.0, width, 4000.0, Material("AH36", t, 355.0))


def rolled(
    plate: PlateRecord, d: float, *, factor: float, compliance: float, verdict: bool = True
) -> PlateRecord:
    """The plate after one more pass on the true physics (no scatter), inspected exactly."""
    trial = plate.with_pass(RollPass("R3-01", d))
    k = plate_curvatures(
        trial, MACHINES, yield_factor=factor, compliance_mm_per_mn={"R3-01": compliance}
    )[1][-1]
    radius = math.inf if k <= 0 else plate.target.surface_radius_mm(1 / k)
    ok = abs(k - target_curvature(plate.target)) <= 0.95 * curvature_band(plate.target)
    return plate.with_pass(
        RollPass("R3-01", d, radius, ("pass" if ok else "fail") if verdict else None)
    )
