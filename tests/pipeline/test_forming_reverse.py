"""Reverse passes: Masing's rule on the elastic-plastic section, the flipped pass's geometry, an over-bent
plate opened by the advice (the model's physics with a hidden reverse factor), learning from the yard."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.forming import PlateRecord, RollPass, advise, curvature_band
from pipeline.forming.advice import target_curvature
from pipeline.forming.reverse import Draws, Section, model_curvature
from tests.pipeline.forming_cases import MACHINE, MACHINES, rolled, target

FACTOR, COMPLIANCE = 1.2, 1.0


def truth(plate: PlateRecord, beta: float) -> float:
    """The plate's curvature after its passes on the model's physics with reverse factor ``beta``."""
    x = Draws(np.array([FACTOR]), np.array([COMPLIANCE]), np.array([1.0]), np.array([beta]))
    return float(model_curvature(Section.of(MACHINE, plate), plate, x, "R3-01")[0])


def next_pass(plate: PlateRecord, d: float, flipped: bool, beta: float) -> PlateRecord:
    """The plate after one more pass on the true physics, inspected exactly."""
    k = truth(plate.with_pass(RollPass("R3-01", d, flipped=flipped)), beta)
    ok = abs(k - target_curvature(plate.target)) <= 0.95 * curvature_band(plate.target)
    radius = plate.target.surface_radius_mm(1 / k)
    return plate.with_pass(RollPass("R3-01", d, radius, "pass" if ok else "fail", flipped=flipped))


def test_flipped_geometry_and_masing_memory():
    plate = rolled(PlateRecord("p", target(5000.0, 20.0)), 130.0, factor=FACTOR, compliance=0.0)
    section = Section.of(MACHINE, plate)
    # the arch: mid radius (a^2 + d^2) / (2 |d|) + r_b + t/2 for d < 0; through flat for d > 0
    a, rb, t = 700.0, 210.0, 20.0
    k = section.flipped_curvature(np.array([-40.0, 0.0, 40.0]))
    assert k[0] == pytest.approx(1 / ((a * a + 1600) / 80 + rb + t / 2))
    assert k[1] == 0.0 and k[2] < 0
    k0 = truth(plate, 1.0)
    # an arch not flatter than the plate does not touch it; a flipped pass opens it; one not beyond
    # an earlier flipped pass changes nothing (Masing's memory)
    assert truth(plate.with_pass(RollPass("R3-01", -200.0, flipped=True)), 0.8) == pytest.approx(k0)
    opened = plate.with_pass(RollPass("R3-01", -10.0, flipped=True))
    assert truth(opened, 0.8) < k0
    again = opened.with_pass(RollPass("R3-01", -30.0, flipped=True))
    assert truth(again, 0.8) == pytest.approx(truth(opened, 0.8))
    # a lower reverse factor (Bauschinger) opens more at the same setting
    assert truth(opened, 0.6) < truth(opened, 1.0)


@pytest.mark.parametrize("beta", [0.6, 0.85, 1.0])
def test_an_over_bent_plate_is_opened_and_finished(beta):
    plate = rolled(
        PlateRecord("p", target(5000.0, 20.0)), 130.0, factor=FACTOR, compliance=COMPLIANCE
    )
    kt, band = target_curvature(plate.target), curvature_band(plate.target)
    actions = []
    for _ in range(6):
        advice = advise(plate, MACHINES)
        actions.append(advice.action)
        if advice.action == "done":
            break
        assert advice.top_roll_displacement_mm is not None and advice.expected_radius_mm is not None
        plate = next_pass(plate, advice.top_roll_displacement_mm, advice.action == "reverse", beta)
        k = 1 / plate.target.mid_radius_mm(plate.passes[-1].measured_radius_mm)
        # a reverse never throws the plate far beyond the open side (beta 0.6 is the prior's 5 % tail)
        assert k > kt - 3 * band
    assert actions[0] == "reverse" and actions[-1] == "done" and len(actions) <= 5


def test_the_yards_reverse_passes_teach_the_next():
    beta = 0.7
    earlier = rolled(
        PlateRecord("e", target(5000.0, 20.0)), 130.0, factor=FACTOR, compliance=COMPLIANCE
    )
    advice = advise(earlier, MACHINES)
    earlier = next_pass(earlier, advice.top_roll_displacement_mm, True, beta)
    plate = rolled(
        PlateRecord("p", target(5000.0, 20.0)), 128.0, factor=FACTOR, compliance=COMPLIANCE
    )
    told = advise(plate, MACHINES, history=[earlier])
    assert told.basis["reverse"]["reverse_factor"]["reverse_passes"] == 1
    assert told.basis["reverse"]["reverse_factor"]["mean"] == pytest.approx(beta, abs=0.03)
    assert "learned from 1 reverse passes" in told.basis["reverse"]["rests_on"]
    alone = advise(plate, MACHINES)  # the same plate without the yard's reverse pass
    assert alone.basis["reverse"]["reverse_factor"]["reverse_passes"] == 0
    assert (
        told.basis["reverse"]["reverse_factor"]["sd"]
        < alone.basis["reverse"]["reverse_factor"]["sd"]
    )
    kt, band = target_curvature(plate.target), curvature_band(plate.target)
    misses = []
    for advice in (told, alone):
        after = next_pass(plate, advice.top_roll_displacement_mm, True, beta)
        radius = after.passes[-1].measured_radius_mm
        assert 1 / after.target.mid_radius_mm(radius) > kt - band  # not opened beyond the band
        misses.append(abs(radius / advice.expected_radius_mm - 1))
    # the learned reverse predicts its outcome better
    assert misses[0] < 0.5 * misses[1]
