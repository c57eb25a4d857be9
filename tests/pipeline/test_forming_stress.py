"""Issue 27's stress cases on campaigns of the simulator (synthetic ground truth): no plate over-bent,
none left without a setting, and never again a setting shown not to move the plate.

Seeds differ from ``benchmarks/bench_forming.py``'s (0-11) and were not chosen by their outcome.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from pipeline.forming import AimSettings, Priors, advise, curvature_band
from pipeline.forming.advice import target_curvature
from pipeline.forming.campaign import (
    STRESS,
    TruePhysics,
    TruePlate,
    inspect,
    run_campaign,
    stress_plates,
    summary,
)
from pipeline.forming.learning import inspection_variance, measured_curvature
from pipeline.forming.records import Machine, RollPass

MACHINE = Machine("R3-01", 1400.0, 420.0, 500.0)
CASES = [name for name in STRESS if name != "model"]


@pytest.fixture(scope="module")
def campaigns():
    out = {}
    for k, name in enumerate(CASES):
        over, kind = STRESS[name]
        seed = 4100 + k
        out[name] = run_campaign(
            stress_plates(kind, 12, seed),
            MACHINE,
            TruePhysics(**{"compliance_mm_per_mn": 2.0, **over}),
            np.random.default_rng(seed + 1),
        )
    return out


@pytest.mark.parametrize("name", CASES)
def test_no_plate_over_bent_under_the_stress_cases(campaigns, name):
    # judged on the plates' true curvature against the inspection's band; each plate is done, or
    # (its inspection's noise at the band's tight edge) told to reverse; none is left without a
    # setting or stopped after six passes
    outcomes = campaigns[name]
    assert summary(outcomes)["over_bent"] == 0
    assert all(o.final in ("done", "reverse") for o in outcomes)


def test_a_setting_that_did_not_move_the_plate_is_never_repeated(campaigns):
    """A pass whose inspection found the plate as the one before it (within 3 sd of the two
    inspections' noise) is never followed by a setting less than ``setting_step_mm`` deeper."""
    step = AimSettings().setting_step_mm
    stalls = 0
    for outcomes in campaigns.values():
        for o in outcomes:
            plate, passes = o.record, o.record.passes
            for j in range(1, len(passes)):
                k0 = measured_curvature(plate, passes[j - 1].measured_radius_mm)
                k1 = measured_curvature(plate, passes[j].measured_radius_mm)
                noise = math.sqrt(
                    inspection_variance(plate, j - 1, Priors())
                    + inspection_variance(plate, j, Priors())
                )
                if abs(k1 - k0) > 3 * noise:
                    continue
                stalls += 1
                stalled = passes[j].top_roll_displacement_mm
                assert all(
                    q.top_roll_displacement_mm >= stalled + step - 1e-9 for q in passes[j + 1 :]
                )
    assert stalls > 0  # the campaigns do stall (a 0.2 mm scatter), so the rule was exercised


def test_an_over_bent_campaign_plate_is_told_reverse_with_a_setting(campaigns):
    # a plate of the scatter case rolled again through its advised passes, then on purpose 12 mm
    # past its last setting: reverse, with the top roll's setting to open it and the words for it
    name = "scatter 0.2 mm"
    outcomes = campaigns[name]
    over, kind = STRESS[name]
    physics = TruePhysics(**{"compliance_mm_per_mn": 2.0, **over})
    sim = stress_plates(kind, 12, 4100 + CASES.index(name))[3]
    truth, rng, record = TruePlate(sim, MACHINE, physics), np.random.default_rng(7), sim.record
    settings = [q.top_roll_displacement_mm for q in outcomes[3].record.passes]
    for d in [*settings, settings[-1] + 12.0]:
        k = truth.roll(d, rng)
        record = record.with_pass(RollPass("R3-01", d, *inspect(record, k, physics, rng)))
    target = record.target
    assert k > target_curvature(target) + curvature_band(target)  # truly over-bent
    advice = advise(record, {"R3-01": MACHINE}, history=[o.record for o in outcomes[:3]])
    assert advice.action == "reverse" and advice.top_roll_displacement_mm is not None
    assert "turn the plate over" in advice.basis["reason"]
    assert advice.expected_radius_mm > record.passes[-1].measured_radius_mm


def test_the_campaign_keeps_each_passs_true_curvature(campaigns):
    # the simulator keeps the hidden truth after each pass (bench_forming.py --stress --diagnose
    # judges the advice's predictions against it): one a pass, each what its inspection measured
    # within the inspection's noise (0.05 % of the radius, 5 sd here), and a plate is over-bent
    # exactly when its truth passed the verdict's band on the tight side at some pass
    for outcomes in campaigns.values():
        for o in outcomes:
            target = o.record.target
            edge = target_curvature(target) + 0.95 * curvature_band(target)
            assert len(o.true_curvatures) == o.passes
            assert o.over_bent == any(k > edge for k in o.true_curvatures)
            for q, k in zip(o.record.passes, o.true_curvatures):
                measured = measured_curvature(o.record, q.measured_radius_mm)
                assert measured == pytest.approx(k, rel=5 * 5e-4)


@pytest.mark.xfail(
    strict=True,
    reason="issue 27, not fixed: a first correction early in a campaign whose scatter is twice the "
    "prior's rests on a scatter estimate far below the truth (docs/forming.md, fourth and fifth "
    "rounds: its six plates' rows said 0.08 mm and its correction drew 3 sd of the true scatter; "
    "eighth round: with the scatter known it does not, but 7 of 1200 other plates at 0.2 mm do)",
)
def test_an_early_correction_at_twice_the_prior_scatter_does_not_over_bend():
    # bench_forming.py's seed 7 at a 0.2 mm scatter: the seventh plate's first correction was
    # predicted with the scatter estimated at 0.088 mm from the six plates before it, and over-bent
    # (1.31 bands, the verdict's edge at 0.95); with the true scatter known it would have been aimed
    # 0.32 mm shallower
    over, kind = STRESS["scatter 0.2 mm"]
    outcomes = run_campaign(
        stress_plates(kind, 20, 7)[:7],
        MACHINE,
        TruePhysics(**{"compliance_mm_per_mn": 2.0, **over}),
        np.random.default_rng(107),
    )
    assert outcomes[6].advice[1]["basis"]["parameters"]["scatter_mm"] < 0.1
    assert not outcomes[6].over_bent
