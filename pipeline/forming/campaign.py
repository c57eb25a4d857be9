"""A simulated forming campaign: plates rolled on one machine by the advice, against a hidden "true" physics.

The truth is the model's physics (:mod:`.rolling`) with values the advice does not see:

- each plate's yield factor (drawn by :func:`random_batch`, 1.05-1.35 times the nominal yield);
- the machine's compliance and displacement gain (how far the plate is really pushed per mm of the
  reading: a bender geometry a few per cent off the model's);
- the material's hardening (a factor on the permanent curvature);
- per pass: a displacement scatter (the roll's repeatability, the plate's feed) and a scatter of the
  yield factor of the material that pass yields (local variation);
- per inspection: relative radius noise; the inspection's verdict passes a curvature error up to
  ``verdict_band`` times :func:`.advice.curvature_band` (what :func:`pipeline.judge.verdict.judge` does).

Used by the tests and by ``benchmarks/bench_forming.py``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np

from .advice import AimSettings, advise, curvature_band, target_curvature
from .learning import Priors
from .records import FormingTarget, Machine, Material, PlateRecord, RollPass
from .rolling import PassSetup

GRADES = (("AH36", 355.0), ("DH36", 355.0))
THICKNESSES_MM = (10.0, 15.0, 20.0, 25.0, 30.0)


@dataclass(frozen=True)
class TruePhysics:
    """The hidden part of the simulated world.

    Attributes
    ----------
    compliance_mm_per_mn : float
        The machine's real compliance.
    displacement_gain : float
        The machine's real displacement gain (1: the model's geometry).
    displacement_scatter_mm : float
        Sd of a pass's effective displacement.
    yield_scatter : float
        Relative sd of the yield factor of the material a pass yields.
    hardening : float
        Factor on the permanent curvature the model's elastic-perfectly-plastic section leaves (0.98:
        2 % less, as a hardening section springs back more).
    radius_noise : float
        Relative sd of an inspected radius.
    verdict_band : float
        The inspection passes ``|k - k_target| <= verdict_band * curvature_band``.
    """

    compliance_mm_per_mn: float = 2.0
    displacement_gain: float = 1.0
    displacement_scatter_mm: float = 0.1
    yield_scatter: float = 0.0
    hardening: float = 1.0
    radius_noise: float = 5e-4
    verdict_band: float = 0.95


@dataclass(frozen=True)
class SimPlate:
    """A plate to roll and its hidden yield factor."""

    record: PlateRecord
    yield_factor: float


@dataclass
class PlateOutcome:
    """What happened to one plate.

    Attributes
    ----------
    plate_id : str
    passes : int
        Passes rolled.
    final : str
        The last advice's action (``done``, ``reverse``) or ``"stopped"`` after ``max_passes``.
    over_bent : bool
        Its true curvature left the verdict's band on the tight side at some point.
    record : PlateRecord
        Its passes and inspections.
    advice : list of dict
        Every advice it was given.
    true_curvatures : list of float
        Its true mid-surface curvature after each pass, 1/mm (the hidden truth the inspections
        measured with their noise).
    """

    plate_id: str
    passes: int
    final: str
    over_bent: bool
    record: PlateRecord
    advice: list[dict[str, Any]] = field(default_factory=list)
    true_curvatures: list[float] = field(default_factory=list)


def random_batch(
    n: int,
    rng: np.random.Generator,
    *,
    radii_mm: tuple[float, float] = (3000.0, 15000.0),
    thicknesses_mm: Sequence[float] = THICKNESSES_MM,
    grades: Sequence[tuple[str, float]] = GRADES,
    yield_factors: tuple[float, float] = (1.05, 1.35),
    prefix: str = "P",
) -> list[SimPlate]:
    """``n`` plates of random radius (log-uniform), thickness, grade, size and hidden yield factor.

    Sizes: width across the bend 2.5-3.5 m, length along the rolls 2-10 m; tolerance 2 mm.
    """
    out = []
    for i in range(n):
        grade, yield_mpa = grades[int(rng.integers(len(grades)))]
        t = float(thicknesses_mm[int(rng.integers(len(thicknesses_mm)))])
        radius = float(math.exp(rng.uniform(math.log(radii_mm[0]), math.log(radii_mm[1]))))
        target = FormingTarget(
            round(radius, -1),
            2.0,
            float(rng.uniform(2500, 3500)),
            float(rng.uniform(2000, 10000)),
            Material(grade, t, yield_mpa),
        )
        out.append(
            SimPlate(
                PlateRecord(f"{prefix}{i + 1:03d}", target), float(rng.uniform(*yield_factors))
            )
        )
    return out


class TruePlate:
    """A plate's hidden state: the largest loaded curvature so far and the yield of the pass that set it."""

    def __init__(self, plate: SimPlate, machine: Machine, physics: TruePhysics) -> None:
        self.plate, self.physics = plate, physics
        self.setup = PassSetup.of([machine], [plate.record])
        self.peak, self.peak_factor = 0.0, plate.yield_factor

    def roll(self, displacement_mm: float, rng: np.random.Generator) -> float:
        """Roll one pass; returns the true mid-surface curvature after it."""
        f = self.plate.yield_factor * (1.0 + self.physics.yield_scatter * rng.standard_normal())
        d = displacement_mm + self.physics.displacement_scatter_mm * rng.standard_normal()
        k = float(
            self.setup.loaded_curvature(
                np.array([d]),
                f,
                self.physics.compliance_mm_per_mn,
                self.physics.displacement_gain,
            )[0]
        )
        if k > self.peak:
            self.peak, self.peak_factor = k, f
        return self.curvature()

    def curvature(self) -> float:
        unloaded = self.setup.unloaded_curvature(np.array([self.peak]), self.peak_factor)[0]
        return float(self.physics.hardening * unloaded)


def inspect(
    plate: PlateRecord, curvature: float, physics: TruePhysics, rng: np.random.Generator
) -> tuple[float, Literal["pass", "fail"]]:
    """A simulated inspection of a plate of true mid-surface curvature: (measured radius, verdict)."""
    target = plate.target
    if curvature <= 0:
        radius = math.inf
    else:
        radius = target.surface_radius_mm(1.0 / curvature) * (
            1.0 + physics.radius_noise * rng.standard_normal()
        )
    k_meas = 0.0 if math.isinf(radius) else 1.0 / target.mid_radius_mm(radius)
    ok = abs(k_meas - target_curvature(target)) <= physics.verdict_band * curvature_band(target)
    return radius, "pass" if ok else "fail"


def run_campaign(
    plates: Sequence[SimPlate],
    machine: Machine,
    physics: TruePhysics,
    rng: np.random.Generator,
    *,
    learning: bool = True,
    max_passes: int = 6,
    priors: Priors = Priors(),
    settings: AimSettings = AimSettings(),
) -> list[PlateOutcome]:
    """Roll the plates one after the other on ``machine``, each pass as advised, until done or reverse.

    Parameters
    ----------
    plates : sequence of SimPlate
    machine : Machine
    physics : TruePhysics
    rng : numpy Generator
        Draws the passes' scatter and the inspections' noise.
    learning : bool
        Give the advice the finished plates as history; False: each plate on its own (the nominal model
        and the priors, then its own passes).
    max_passes : int
        Stop a plate after this many passes.
    priors, settings
        Passed to :func:`.advice.advise`.

    Returns
    -------
    list of PlateOutcome
    """
    machines = {machine.machine_id: machine}
    finished: list[PlateRecord] = []
    out = []
    for sim in plates:
        record, truth = sim.record, TruePlate(sim, machine, physics)
        band_hi = target_curvature(record.target) + physics.verdict_band * curvature_band(
            record.target
        )
        over, final, given, truths = False, "stopped", [], []
        while True:
            advice = advise(
                record,
                machines,
                history=finished if learning else (),
                machine_id=machine.machine_id,
                priors=priors,
                settings=settings,
            )
            given.append(advice.to_dict())
            if advice.action != "bend":
                final = advice.action
                break
            if len(record.passes) >= max_passes or advice.top_roll_displacement_mm is None:
                break
            k = truth.roll(advice.top_roll_displacement_mm, rng)
            truths.append(k)
            over |= k > band_hi
            radius, verdict = inspect(record, k, physics, rng)
            record = record.with_pass(
                RollPass(machine.machine_id, advice.top_roll_displacement_mm, radius, verdict)
            )
        finished.append(record)
        out.append(
            PlateOutcome(record.plate_id, len(record.passes), final, over, record, given, truths)
        )
    return out


def summary(outcomes: Sequence[PlateOutcome]) -> dict[str, Any]:
    """Counts of a campaign: plates, done, over-bent, passes (all, mean, mean after the first plate, max)."""
    passes = np.array([o.passes for o in outcomes], dtype=float)
    return {
        "plates": len(outcomes),
        "done": sum(o.final == "done" for o in outcomes),
        "over_bent": sum(o.over_bent for o in outcomes),
        "reverse": sum(o.final == "reverse" for o in outcomes),
        "mean_passes": float(passes.mean()) if passes.size else math.nan,
        "mean_passes_after_first": float(passes[1:].mean()) if passes.size > 1 else math.nan,
        "max_passes": int(passes.max()) if passes.size else 0,
    }


#: Issue 27's stress cases: name -> (the hidden physics' departures from :class:`TruePhysics`'s
#: defaults, the kind of plates for :func:`stress_plates`).
STRESS: dict[str, tuple[dict[str, float], str]] = {
    "model": ({}, "mixed"),
    "scatter 0.2 mm": ({"displacement_scatter_mm": 0.2}, "mixed"),
    "work hardening 2 %": ({"hardening": 0.98}, "mixed"),
    "geometry 3 % short": ({"displacement_gain": 0.97}, "mixed"),
    "geometry 3 % long": ({"displacement_gain": 1.03}, "mixed"),
    "batch yield 1.40-1.50": ({}, "high-yield"),
    "new grade after 2 plates": ({}, "new-grade"),
}


def stress_plates(kind: str, n: int, seed: int) -> list[SimPlate]:
    """A stress case's ``n`` plates, drawn from ``seed``.

    Parameters
    ----------
    kind : {"mixed", "high-yield", "new-grade"}
        ``mixed``: :func:`random_batch`; ``high-yield``: one heat of one grade and thickness whose
        yield lies 1.40-1.50 x its nominal grade's (far above the prior's 1.17 +- 0.06);
        ``new-grade``: mixed plates, then from the middle of the campaign a grade and thickness
        never seen (EH40, 390 MPa), 1.25-1.45 x nominal, so that its third plate is advised after two.
    n : int
    seed : int

    Returns
    -------
    list of SimPlate
    """
    rng = np.random.default_rng(seed)
    if kind == "mixed":
        return random_batch(n, rng)
    if kind == "high-yield":
        thickness = float(rng.choice([15.0, 20.0, 25.0]))
        return random_batch(
            n, rng, thicknesses_mm=[thickness], grades=[GRADES[0]], yield_factors=(1.40, 1.50)
        )
    if kind != "new-grade":
        raise ValueError(f"kind: expected mixed, high-yield or new-grade, got {kind!r}")
    old = random_batch(n // 2, rng)
    thickness = float(rng.choice([12.0, 18.0, 22.0]))
    new = random_batch(
        n - n // 2,
        rng,
        thicknesses_mm=[thickness],
        grades=[("EH40", 390.0)],
        yield_factors=(1.25, 1.45),
        prefix="N",
    )
    return old + new
