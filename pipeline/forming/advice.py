"""The advice after an inspection: done, reverse, or bend with the next top-roll displacement.

Tolerance band
--------------
The inspection registers the target (its radius fixed) on the measured plate with a robust fit that
lays the plate's middle on the target; a curvature error ``dk`` then shows at the plate's edges as the
difference of the two sagittas over the width ``w``: ``|dk| w^2 / 8``. The plate passes while that is
within the tolerance::

    |k - k_target| <= band = 8 tol / w^2

(for a 3 m plate and 2 mm: 1.8e-6 / mm, i.e. 0.9 % of a 5 m radius, 2.7 % of a 15 m one). Checked
against :func:`pipeline.judge.verdict.judge` on ray-cast cylinders in the tests: it passes up to about 0.95
of that band.

Actions
-------
- ``done``: the latest inspection passes (its verdict; without a verdict, the measured radius within the band).
- ``reverse``: the latest inspection fails with the plate bent tighter than its target (without a verdict,
  tighter than the band): rolling further cannot open it.
- ``bend`` otherwise, also for a plate without passes, with the displacement from :func:`aim`.

Aim
---
Over-bending costs a reverse pass or the plate; under-bending one more pass. The next displacement is
the smallest of

- the one whose predicted curvature (median) is the target's,
- the one whose probability of ending tighter than ``target + over_band * band`` is ``over_probability``,

(:class:`AimSettings`): with a sharp prediction the plate is aimed at the target, with a wide one at the
open side of the band, by as much as the uncertainty asks. For a plate without inspected passes of its
own the second rule is applied to the plate at a low yield factor: the ``first_pass_quantile`` of its
group's distribution, or the nominal minimum if that is higher (a plate's factor is never below 1). How
much plates differ is the least known part of the model, and the first pass is then a probe that ends
under-bent; the second pass has the plate's own measurement. The machine's compliance is bounded the
same way: the first pass takes the less cautious of that prediction and the one with the compliance
also fixed at its ``over_probability`` quantile or at its floor (0: a machine gives, it never pushes
further), whichever is higher. A fresh machine's compliance prior (1 +- 2 mm/MN) would otherwise be
taken down to -4 mm/MN, a probe ~15 mm shallow on a 30 mm plate, and the step after it so long that
the gain's 2 % alone spreads it over several bands.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass, field
from typing import Any, Literal

import numpy as np
from scipy import optimize, stats

from ..formats import InputError, PipelineError
from . import bender, reverse
from .learning import (
    Fit,
    Prediction,
    Priors,
    fit,
    inspection_variance,
    latest_state,
    measured_curvature,
)
from .records import FormingTarget, Machine, PlateRecord

Action = Literal["bend", "done", "reverse"]


class FormingError(PipelineError):
    """Valid input the bender cannot serve (a target tighter than the machine can roll)."""


@dataclass(frozen=True)
class AimSettings:
    """How cautiously the advice aims.

    Attributes
    ----------
    over_probability : float
        Allowed probability that the plate ends tighter than ``target + over_band * band``: each
        bending pass may take ``pass_probability``, this over ``planned_passes``.
    planned_passes : int
        The passes ``over_probability`` is split over (the union bound: a plate's risk is at most the
        sum of its passes'). 1 (default): each advice keeps its own pass within it; 4 (a plate done
        within 4 passes, each within a quarter) cost 0.2 passes a plate on the model's own physics
        (docs/forming.md).
    over_band : float
        The share of the band the aim may use on the tight side (0.8: the inspection's pass limit sits at
        ~0.95 of the band, and the band's derivation is approximate).
    first_pass_quantile : float
        A plate without inspected passes of its own is aimed for its yield factor at this quantile of its
        group's distribution, or at the nominal minimum (``Priors.yield_factor_floor``) if that is higher:
        the spread of plates is the least known part of the model.
    min_rows : int
        Inspected states of the plate, its group (same machine, grade, thickness) and its machine below
        which the advice says it has little data.
    verdict_band : float
        The share of the band the inspection's verdict passes (0.95 on ray-cast cylinders): a plate
        past ``target + verdict_band * band`` is over-bent. A plate whose least move (a repeat of the
        deepest setting, or ``setting_step_mm`` beyond one shown not to move it) is past the aim's
        margin (``over_band``) gets the deepest setting from there whose risk of ending past this
        edge is ``over_probability`` (not beyond the one whose median is the target); when even the
        least move's risk exceeds it, no setting.
    setting_step_mm : float
        The least difference of two settings the machine tells apart, mm: the next setting after one
        shown not to move the plate is at least this much deeper (never the same setting again).
    two_pass_fraction : float
        When one pass would land within the band with less than even odds, its spread mostly the
        model's parameters (which a shorter step shrinks), the approach takes two passes, the first
        to this fraction of the remaining bend (:func:`_two_pass`).
    scatter_confidence : float or None
        The over-bending risk past the verdict's edge (``verdict_band``) is also kept within
        ``pass_probability`` with the passes' scatter at this upper credible bound of its posterior
        (:meth:`.learning.Fit.scatter_upper_scale`, normal tails): a tolerance bound, the risk kept
        whatever the scatter within that credibility, besides the predictive Student-t (which keeps it
        on average over the scatter's posterior). None: the Student-t alone (issue 27, sixth round).
    adaptive_split : bool
        Keep ``over_probability`` per plate, split adaptively over its passes (issue 27, seventh
        round): a correction pass (the plate inspected) may take the plate's remaining budget (the
        risks its earlier bending passes took, as the advice then predicted them, subtracted) times
        the probability that it lands within the band, i.e. over the passes the plate is still
        expected to need (:func:`_split_risk`); ``planned_passes`` is then not used. A first pass
        keeps ``pass_probability`` (it is aimed for a low yield factor, a probe). False: each pass
        ``pass_probability``.
    scatter_two_pass : bool
        A plate's first correction whose spread is mostly the passes' scatter and which, with that
        scatter's sd twice its estimate, would end past the verdict's edge with more than the allowed
        risk, approaches in two passes: this one to the deepest setting that keeps that risk at twice
        the scatter (its median at most ``two_pass_fraction`` of the remaining bend), the next from
        its inspection (:func:`_scatter_two_pass`; issue 27, eighth round: a trial, off).
    verdict_probability : float or None
        The over-bending risk each bending pass may take past the verdict's edge (``verdict_band``),
        besides the aim's ``pass_probability`` past ``over_band``: the least move given when the
        scatter fills the band keeps this one too. None (default): only the aim's risk, whose share
        past the verdict's edge is what the spread leaves (issue 27, eighth round: a trial, off).
    reverse_open_probability : float
        Allowed probability that a reverse pass opens the plate beyond ``target - over_band * band`` (it
        then needs one more bending pass, not a reverse or the scrap heap: a milder risk).
    """

    over_probability: float = 0.005
    over_band: float = 0.8
    first_pass_quantile: float = 0.01
    min_rows: int = 3
    reverse_open_probability: float = 0.05
    two_pass_fraction: float = 0.6
    verdict_band: float = 0.95
    setting_step_mm: float = 0.1
    planned_passes: int = 1
    scatter_confidence: float | None = None
    adaptive_split: bool = False
    verdict_probability: float | None = None
    scatter_two_pass: bool = False

    @property
    def pass_probability(self) -> float:
        """The over-bending risk one bending pass may take: ``over_probability / planned_passes``."""
        return self.over_probability / self.planned_passes

    def verdict_risk(self, alpha: float) -> float:
        """The risk a pass allowed ``alpha`` at the aim's margin may take past the verdict's edge:
        ``alpha``, or ``verdict_probability`` when that is set and smaller."""
        return alpha if self.verdict_probability is None else min(alpha, self.verdict_probability)

    def __post_init__(self) -> None:
        if not 0 < self.over_probability < 0.5:
            raise ValueError(
                f"over_probability: expected a number in (0, 0.5), got {self.over_probability!r}"
            )
        if not 0 < self.first_pass_quantile < 0.5:
            raise ValueError(
                f"first_pass_quantile: expected a number in (0, 0.5), got {self.first_pass_quantile!r}"
            )
        if not 0 < self.reverse_open_probability < 0.5:
            raise ValueError(
                "reverse_open_probability: expected a number in (0, 0.5), "
                f"got {self.reverse_open_probability!r}"
            )
        if not 0 < self.two_pass_fraction < 1:
            raise ValueError(
                f"two_pass_fraction: expected a number in (0, 1), got {self.two_pass_fraction!r}"
            )
        if not self.over_band <= self.verdict_band <= 1:
            raise ValueError(
                f"verdict_band: expected a number in [over_band, 1], got {self.verdict_band!r}"
            )
        if not 0 < self.over_band <= 1:
            raise ValueError(f"over_band: expected a number in (0, 1], got {self.over_band!r}")
        if not (math.isfinite(self.setting_step_mm) and self.setting_step_mm > 0):
            raise ValueError(
                f"setting_step_mm: expected a positive number, got {self.setting_step_mm!r}"
            )
        if not (isinstance(self.planned_passes, int) and self.planned_passes >= 1):
            raise ValueError(
                f"planned_passes: expected a positive integer, got {self.planned_passes!r}"
            )
        if self.scatter_confidence is not None and not 0 < self.scatter_confidence < 1:
            raise ValueError(
                f"scatter_confidence: expected a number in (0, 1) or None, "
                f"got {self.scatter_confidence!r}"
            )
        if self.verdict_probability is not None and not 0 < self.verdict_probability < 0.5:
            raise ValueError(
                f"verdict_probability: expected a number in (0, 0.5) or None, "
                f"got {self.verdict_probability!r}"
            )
        if not (isinstance(self.min_rows, int) and self.min_rows >= 0):
            raise ValueError(f"min_rows: expected a non-negative integer, got {self.min_rows!r}")


@dataclass(frozen=True)
class Advice:
    """What to do with the plate next.

    Attributes
    ----------
    action : {"bend", "done", "reverse"}
    machine_id : str
    top_roll_displacement_mm : float or None
        The next pass's setting (``bend`` only).
    expected_radius_mm : float or None
        Predicted radius (median) of the target's surface after that pass (``bend`` only).
    expected_radius_range_mm : (float, float) or None
        Central 95 % interval of that radius (``inf``: the plate may stay flat).
    basis : dict
        What the advice rests on (JSON-ready): data used, parameters with their sd, the aim, warnings.
    """

    action: Action
    machine_id: str
    top_roll_displacement_mm: float | None
    expected_radius_mm: float | None
    expected_radius_range_mm: tuple[float, float] | None
    basis: dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready: tuples become lists, an infinite radius (a flat plate) None."""
        document: dict[str, Any] = _jsonable(asdict(self))
        return document


def _jsonable(value: Any) -> Any:
    if isinstance(value, dict):
        return {k: _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def curvature_band(target: FormingTarget) -> float:
    """Half-width of the curvature band the inspection passes, ``8 tol / w^2``, 1/mm (module docstring)."""
    return 8.0 * target.tolerance_mm / target.width_mm**2


def target_curvature(target: FormingTarget) -> float:
    """The target's mid-surface curvature, 1/mm."""
    return 1.0 / target.mid_radius_mm(target.radius_mm)


def _surface_radius(target: FormingTarget, curvature: float) -> float:
    return math.inf if curvature <= 0 else target.surface_radius_mm(1.0 / curvature)


def state_action(plate: PlateRecord) -> tuple[Action, str] | None:
    """``done`` or ``reverse`` with the reason, from the latest inspection; None when the plate needs bending.

    Raises
    ------
    InputError
        The latest pass was not inspected.
    """
    if not plate.passes:
        return None
    last = plate.passes[-1]
    if last.measured_radius_mm is None:
        raise InputError(
            "plate",
            f"passes[{len(plate.passes) - 1}].measured_radius_mm",
            "missing: inspect the plate after its latest pass before asking for the next",
        )
    k, kt, band = (
        measured_curvature(plate, last.measured_radius_mm),
        target_curvature(plate.target),
        curvature_band(plate.target),
    )
    if last.verdict == "pass":
        return "done", "the latest inspection passes"
    if last.verdict == "fail" and k > kt:
        return "reverse", "the latest inspection fails with the plate bent tighter than its target"
    if last.verdict is None and k > kt + band:
        return "reverse", "the measured radius is tighter than the tolerance band"
    if last.verdict is None and abs(k - kt) <= band:
        return "done", "the measured radius is within the tolerance band (no verdict given)"
    return None


def aim(
    fitted: Fit,
    plate: PlateRecord,
    machine: Machine,
    settings: AimSettings = AimSettings(),
    *,
    spent: float = 0.0,
) -> dict[str, Any]:
    """The next displacement of a plate that needs bending (module docstring), with its prediction.

    Returns
    -------
    dict
        ``displacement_mm``; ``prediction`` there (:class:`~.learning.Prediction`); ``yield_factor``: the
        factor the safe side was aimed for (None: its whole distribution, the plate has passes of its
        own) and ``safe_prediction`` for it; ``warnings`` (list of str).

    Raises
    ------
    FormingError
        The target cannot be reached on this machine even at its deepest setting.
    """
    target = plate.target
    t = target.material.thickness_mm
    kt, band = target_curvature(target), curvature_band(target)
    limit = kt + settings.over_band * band
    p_hi = 1.0 - settings.pass_probability
    d_max = bender.max_displacement_mm(machine, t)
    factor, c_floor = _first_pass_bounds(fitted, plate, machine, settings)

    def predict(d: float) -> Prediction:
        return fitted.predict(plate, machine.machine_id, d)

    def predict_safe(d: float) -> Prediction:
        """The prediction the safe side is aimed for (the first pass: the less cautious of the plate at
        the low yield factor, and that with the machine's compliance also at its floor)."""
        safe = fitted.predict(plate, machine.machine_id, d, yield_factor=factor)
        if factor is None or c_floor is None:
            return safe
        bounded = fitted.predict(
            plate, machine.machine_id, d, yield_factor=factor, compliance_mm_per_mn=c_floor
        )
        return min(safe, bounded, key=lambda pred: pred.quantile(p_hi))

    warnings: list[str] = []
    d_lo, stalled = _least_setting(fitted, plate, machine, predict, d_max, settings)
    if predict_safe(d_max).quantile(p_hi) < limit and predict(d_max).median < kt:
        raise FormingError(
            f"radius {target.radius_mm:g} mm needs more than {machine.machine_id}'s deepest setting "
            f"({d_max:.1f} mm, loaded radius {bender.min_loaded_radius_mm(machine, t):.0f} mm)"
        )

    over_edge = kt + settings.verdict_band * band
    upper = (
        None
        if settings.scatter_confidence is None
        else fitted.scatter_upper_scale(settings.scatter_confidence)
    )

    place = _placer(
        predict,
        predict_safe,
        (kt, limit, over_edge),
        (upper, settings.verdict_probability),
        (d_lo, d_max),
    )

    alpha, passes_left = settings.pass_probability, None
    if settings.adaptive_split and factor is None:
        alpha, passes_left = _split_risk(place, predict, kt, band, settings, spent)
    placed = place(alpha)
    d = placed.displacement_mm
    allowed = settings.verdict_risk(alpha)
    split = None if placed.least else _two_pass(plate, predict, d_lo, d, settings)
    if split is None and settings.scatter_two_pass and not placed.least and stalled is None:
        split = _scatter_two_pass(plate, predict_safe, (d_lo, d), over_edge, allowed, settings)
    if split is not None:
        d = split[0]
        warnings.append(split[1])
    if placed.least:
        words = _scatter_fills_band(stalled, d, placed.risk, allowed, given=not placed.blocked)
        warnings.append(words)
    return {
        "blocked": placed.blocked,
        "displacement_mm": float(d),
        "prediction": predict(d),
        "safe_prediction": predict_safe(d),
        "yield_factor": factor,
        "warnings": warnings,
        "pass_probability": alpha,
        "plate_risk_spent": spent,
        "expected_passes": passes_left,
    }


def _placer(
    predict: Callable[[float], Prediction],
    predict_safe: Callable[[float], Prediction],
    levels: tuple[float, float, float],
    bounds: tuple[float | None, float | None],
    span: tuple[float, float],
) -> Callable[[float], _Placed]:
    """The aim's rule as a function of the over-bending risk the pass may take: the setting (the
    smallest of the one whose median is the target, the one at the aim's margin, the least move's
    rule; module docstring). ``levels``: the target's curvature, the aim's margin, the verdict's
    edge; ``bounds``: the scatter's upper credible scale (``AimSettings.scatter_confidence``) and
    the risk allowed past the verdict's edge (``AimSettings.verdict_probability``), each None when
    off; ``span``: the least and the deepest setting."""
    kt, limit, over_edge = levels
    upper, edge_cap = bounds
    d_lo, d_max = span

    def centre(d: float) -> float:
        return predict(d).median - kt

    def root(g: Callable[[float], float]) -> float:
        """The least displacement from ``d_lo`` where ``g`` reaches 0 (``d_max`` if it never does)."""
        if g(d_lo) >= 0:
            return d_lo
        return d_max if g(d_max) <= 0 else optimize.brentq(g, d_lo, d_max, xtol=1e-3)

    d_centre = root(centre)

    def place(alpha: float) -> _Placed:
        """The pass's setting when it may take the over-bending risk ``alpha``."""
        margin, risk = _over_risks(predict_safe, limit, over_edge, 1.0 - alpha, upper)
        allowed = alpha if edge_cap is None else min(alpha, edge_cap)

        def safe(x: float) -> float:
            """At least 0 where either limit is reached (the aim's margin, or the verdict's edge
            at its own risk): its first root is the shallower of the two."""
            return margin(x) if edge_cap is None else max(margin(x), risk(x) - allowed)

        d = min(root(safe), d_centre)
        # the least move already past the aim's margin: given when it keeps the risk of ending past
        # the band as the inspection judges it within the allowed probability, else no setting
        least = safe(d_lo) >= 0
        blocked = least and risk(d_lo) > allowed
        if least and not blocked:
            # the deepest setting whose risk of ending past the verdict's edge is the allowed one
            d = min(root(lambda x: risk(x) - allowed), d_centre)
        return _Placed(float(d), least, blocked, risk(d))

    return place


@dataclass(frozen=True)
class _Placed:
    """A pass placed at an allowed risk: its setting, whether it is the least move (already past the
    aim's margin), whether even that is past the allowed risk (no setting), its risk past the
    verdict's edge."""

    displacement_mm: float
    least: bool
    blocked: bool
    risk: float


def _split_risk(
    place: Callable[[float], _Placed],
    predict: Callable[[float], Prediction],
    kt: float,
    band: float,
    settings: AimSettings,
    spent: float,
) -> tuple[float, float]:
    """The over-bending risk this pass may take, and the passes the plate is expected to need from
    here (``AimSettings.adaptive_split``): ``(alpha, n)``.

    A plate over-bends at most once, on a pass it reaches, so its risk is at most the sum over its
    passes of the probability of reaching the pass times the pass's risk. The passes already rolled
    were reached: their risks (``spent``, :func:`_spent_risk`) are taken from the plate's budget
    ``over_probability``; what remains, ``R``, is shared by the passes to come, each taking ``alpha``:
    the plate's remaining risk is ``alpha n``, ``n`` the passes it is expected to need from here.

    ``n = 1 + (1 - p) / q``: this pass, aimed at ``alpha``, lands within the band
    (``|k - k_target| <= band``, the advice's own predictive distribution) with ``p``; should it not,
    each later pass lands with ``q``, the probability of a pass whose spread is only this one's
    scatter share (the new pass's and the old peak's, plus the inspection's noise: the part a later,
    shorter step does not shrink; Student-t of this prediction's degrees of freedom), aimed by the
    same rule (median at the target, or short of it by the ``1 - alpha`` quantile of that spread
    below ``target + over_band * band``): geometric, ``1 / q`` passes. Then ``alpha = R / n(alpha)``,
    the largest fixed point (``n`` falls as ``alpha`` grows: a deeper aim lands closer to the target),
    searched down from ``R`` by halves, then refined between the last two. A sharp prediction well
    inside the band (``p``, ``q`` near 1) takes the whole remaining budget; a pass whose scatter fills
    the band (``q`` about a half) about a third of it, the next what is left. A pass given no setting
    lands nowhere (``p = 0``); when the fixed point leaves the pass no setting (its least move past
    ``alpha``), the least move is given if its risk is within ``R``, and takes that risk. ``R`` is kept at least ``over_probability / 1000`` should the earlier
    passes' risks, recomputed on a history that has since grown, add up to the budget.
    """
    remaining = max(settings.over_probability - spent, settings.over_probability * 1e-3)
    limit = kt + settings.over_band * band

    def passes_left(alpha: float) -> float:
        placed = place(alpha)
        pred = predict(placed.displacement_mm)
        p = 0.0 if placed.blocked else _within(pred, kt, band)
        truth_sd = pred.scatter_sd
        later = Prediction(
            0.0, 0.0, math.sqrt(truth_sd**2 + pred.inspection_var), pred.dof, truth_sd
        )
        median = min(kt, limit - truth_sd * float(stats.t.ppf(1.0 - alpha, pred.dof)))
        q = _within(dataclasses.replace(later, mean=median), kt, band)
        return 1.0 + (1.0 - p) / max(q, 1e-12)

    def excess(log_alpha: float) -> float:
        alpha = math.exp(log_alpha)
        return remaining / passes_left(alpha) - alpha

    hi, alpha = math.log(remaining), None
    for _ in range(12):
        lo = hi - math.log(2.0)
        if excess(lo) >= 0:
            alpha = math.exp(optimize.brentq(excess, lo, hi, xtol=0.05))
            break
        hi = lo
    alpha = math.exp(hi) if alpha is None else alpha
    least = place(alpha)
    if least.blocked and least.risk <= remaining:
        # the least move within what the plate has left: given (its risk spent), not refused
        alpha = least.risk * (1.0 + 1e-9)
    return alpha, passes_left(alpha)


def _within(pred: Prediction, kt: float, band: float) -> float:
    """The probability that the prediction lands within the band, ``|k - kt| <= band``."""
    return max(pred.probability_above(kt - band) - pred.probability_above(kt + band), 0.0)


def _over_risks(
    predict_safe: Callable[[float], Prediction],
    limit: float,
    over_edge: float,
    p_hi: float,
    upper: float | None,
) -> tuple[Callable[[float], float], Callable[[float], float]]:
    """The aim's over-bending constraints as functions of the displacement, judged on the plate's
    true curvature (the next inspection's noise is no risk of over-bending).

    ``safe(d)``: how far the ``p_hi`` quantile is past ``limit`` (the aim's margin); ``risk(d)``: the
    probability of ending past ``over_edge`` (the verdict's). With ``upper`` (the scatter's variance
    at an upper credible bound over its estimate, ``AimSettings.scatter_confidence``) each is also
    taken with the scatter's share at that bound, normal tails, against ``over_edge``, and the larger
    counts.
    """

    def risk(d: float) -> float:
        truth = predict_safe(d).truth()
        p = truth.probability_above(over_edge)
        if upper is None:
            return p
        return max(p, truth.with_scatter_variance(upper).probability_above(over_edge))

    def safe(d: float) -> float:
        truth = predict_safe(d).truth()
        margin = truth.quantile(p_hi) - limit
        if upper is None:
            return margin
        return max(margin, truth.with_scatter_variance(upper).quantile(p_hi) - over_edge)

    return safe, risk


def _least_setting(
    fitted: Fit,
    plate: PlateRecord,
    machine: Machine,
    predict: Callable[[float], Prediction],
    d_max: float,
    settings: AimSettings,
) -> tuple[float, float | None]:
    """The least displacement the next pass may take, mm, and the deepest setting shown not to move
    the plate (None: none): the one that loads the plate to its earlier passes' peak, and at least
    ``settings.setting_step_mm`` beyond a setting shown not to move it (never that setting again).

    Raises
    ------
    FormingError
        The plate was loaded beyond what the machine reaches.
    """
    peak = float(np.max(fitted.curvatures(plate)[0], initial=0.0))
    d_lo = 1e-3
    if peak > 0:
        if predict(d_max).loaded_curvature <= peak:
            raise FormingError(
                f"the plate was loaded beyond what {machine.machine_id} reaches at its deepest "
                f"setting ({d_max:.1f} mm)"
            )
        d_lo = optimize.brentq(lambda d: predict(d).loaded_curvature - peak, 1e-3, d_max, xtol=1e-4)
    stalled = _stalled(fitted, plate, machine.machine_id)
    if stalled is not None:
        d_lo = min(max(d_lo, stalled + settings.setting_step_mm), d_max)
    return d_lo, stalled


def _first_pass_bounds(
    fitted: Fit, plate: PlateRecord, machine: Machine, settings: AimSettings
) -> tuple[float | None, float | None]:
    """For a plate without passes of its own: the low yield factor its first pass is aimed for, and the
    machine's compliance at its floor (None where the fit's own distribution is used)."""
    if fitted.rows_per_plate.get(plate.plate_id, 0) != 0:
        return None, None
    factor = max(
        fitted.priors.yield_factor_floor,
        fitted.yield_factor_quantile(plate.plate_id, settings.first_pass_quantile),
    )
    c_floor = None
    c_mean, c_sd = fitted.parameter("machine", machine.machine_id)
    if c_mean > fitted.priors.compliance_floor_mm_per_mn:
        c_floor = max(
            fitted.priors.compliance_floor_mm_per_mn,
            c_mean + c_sd * float(stats.norm.ppf(settings.pass_probability)),
        )
    return factor, c_floor


def _next_machine(
    plate: PlateRecord, machines: Mapping[str, Machine], machine_id: str | None
) -> str:
    """The next pass's machine (default the latest pass's), every machine named known; else InputError."""
    if machine_id is None:
        if not plate.passes:
            raise InputError(
                "advice",
                "machine_id",
                "missing: a plate without passes needs the machine of its first pass",
            )
        machine_id = plate.passes[-1].machine_id
    for name in {machine_id} | {q.machine_id for q in plate.passes}:
        if name not in machines:
            raise InputError(
                "advice",
                "machine_id",
                f"unknown machine {name!r} (known: {', '.join(sorted(machines))})",
            )
    return machine_id


def _spent_risk(
    plate: PlateRecord,
    machines: Mapping[str, Machine],
    history: Sequence[PlateRecord],
    priors: Priors,
    settings: AimSettings,
) -> float:
    """The over-bending risk the plate's corrections so far took (``AimSettings.adaptive_split``):
    for each, the probability that its true curvature ends past the verdict's edge, as the advice
    before it predicted (fitted on the plate's passes before it and the history), with the scatter
    also at its upper credible bound when ``scatter_confidence`` is set.

    The first pass, a probe aimed for the plate's yield at a low quantile or at the nominal minimum
    (a hard bound: a plate's factor is never below 1), is not counted: the predictive Student-t of a
    plate without passes of its own knows no such bound, and on a fresh machine puts 3-5 % past the
    verdict's edge at the probe's setting (seed 0 of the 0.2 mm stress case), more than the plate's
    whole budget, while no probe of the stress campaigns has over-bent a plate."""
    edge = target_curvature(plate.target) + settings.verdict_band * curvature_band(plate.target)
    total = 0.0
    passes = plate.forward.passes
    for j, q in enumerate(passes):
        if j == 0:
            continue  # the probe: its own rule, outside the split (docstring)
        before = PlateRecord(plate.plate_id, plate.target, passes[:j])
        others = _history_for(plate, q.machine_id, history, priors.max_plates)
        known = [h for h in others if all(p.machine_id in machines for p in h.passes)]
        fitted = fit(
            [before, *(h.forward for h in known)], machines, priors, also_machines=[q.machine_id]
        )
        truth = fitted.predict(before, q.machine_id, q.top_roll_displacement_mm).truth()
        risk = truth.probability_above(edge)
        if settings.scatter_confidence is not None:
            upper = fitted.scatter_upper_scale(settings.scatter_confidence)
            risk = max(risk, truth.with_scatter_variance(upper).probability_above(edge))
        total += risk
    return total


def _history_for(
    plate: PlateRecord, machine_id: str, history: Sequence[PlateRecord], limit: int
) -> list[PlateRecord]:
    used = [
        h
        for h in history
        if h.plate_id != plate.plate_id
        and any(q.inspected and q.machine_id == machine_id for q in h.passes)
    ]
    return used[-limit:] if limit else []


def advise(
    plate: PlateRecord,
    machines: Mapping[str, Machine],
    *,
    history: Sequence[PlateRecord] = (),
    machine_id: str | None = None,
    priors: Priors = Priors(),
    settings: AimSettings = AimSettings(),
) -> Advice:
    """Advice for a plate's next step: done, reverse, or bend with the next top-roll displacement.

    Parameters
    ----------
    plate : PlateRecord
        The plate, its target and its passes so far (the latest inspected).
    machines : mapping of machine id to Machine
        The machine of the next pass and every machine the passes name.
    history : sequence of PlateRecord
        Other plates, oldest first. Those with inspected passes on the next pass's machine are fitted
        with this plate (the ``priors.max_plates`` most recent); a plate of the same id is ignored.
    machine_id : str, optional
        The next pass's machine; default the latest pass's. Required for a plate without passes.
    priors : Priors
    settings : AimSettings

    Returns
    -------
    Advice

    Raises
    ------
    InputError
        No machine for the next pass, an unknown machine, the latest pass not inspected.
    FormingError
        The target cannot be rolled on the machine.
    """
    machine_id = _next_machine(plate, machines, machine_id)
    target = plate.target
    kt, band = target_curvature(target), curvature_band(target)
    basis: dict[str, Any] = {
        "target_radius_mm": target.radius_mm,
        "tolerance_band_radius_mm": [
            _surface_radius(target, kt + band),
            _surface_radius(target, kt - band),
        ],
        "measured_radius_mm": plate.passes[-1].measured_radius_mm if plate.passes else None,
    }
    decided = state_action(plate)
    if decided is not None and decided[0] == "done":
        basis["reason"] = decided[1]
        basis["warnings"] = _inspection_warnings(plate, priors)
        return Advice(decided[0], machine_id, None, None, None, basis)

    others = _history_for(plate, machine_id, history, priors.max_plates)
    known = [h for h in others if all(q.machine_id in machines for q in h.passes)]
    fitted = fit(
        [plate.forward, *(h.forward for h in known)], machines, priors, also_machines=[machine_id]
    )
    if decided is not None or any(q.flipped for q in plate.passes):
        basis.update(_data_basis(plate, known, machine_id, fitted, settings))
        basis["reason"] = decided[1] if decided else "the latest inspection is under-bent"
        return _reverse_advice(
            "reverse" if decided else "bend",
            plate,
            known,
            fitted,
            machines[machine_id],
            settings,
            basis,
        )
    spent = (
        _spent_risk(plate, machines, history, priors, settings)
        if settings.adaptive_split and plate.passes
        else 0.0
    )
    aimed = aim(fitted, plate, machines[machine_id], settings, spent=spent)
    if aimed["blocked"]:
        basis.update(_data_basis(plate, known, machine_id, fitted, settings))
        basis["warnings"] += aimed["warnings"]
        basis["reason"] = "the latest inspection is under-bent, and no setting moves it safely"
        return Advice("bend", machine_id, None, None, None, basis)
    pred = aimed["prediction"]
    k_lo, k_hi = pred.quantile(0.025), pred.quantile(0.975)
    basis.update(_data_basis(plate, known, machine_id, fitted, settings))
    if len(known) < len(others):
        basis["warnings"].append(
            f"{len(others) - len(known)} plates of the history left out: they passed through "
            "machines not given"
        )
    basis["aim"] = _aim_basis(target, aimed, settings)
    basis["warnings"] = basis["warnings"] + aimed["warnings"]
    basis["reason"] = "first pass" if not plate.passes else "the latest inspection is under-bent"
    return Advice(
        "bend",
        machine_id,
        aimed["displacement_mm"],
        _surface_radius(target, pred.median),
        (_surface_radius(target, k_hi), _surface_radius(target, k_lo)),
        basis,
    )


def _aim_basis(
    target: FormingTarget, aimed: dict[str, Any], settings: AimSettings
) -> dict[str, Any]:
    """The aim's part of the basis: loaded radius, the probabilities over and within the band."""
    kt, band = target_curvature(target), curvature_band(target)
    pred = aimed["prediction"]
    return {
        "loaded_radius_mm": _surface_radius(target, pred.loaded_curvature),
        "probability_over_band": aimed["safe_prediction"].truth().probability_above(kt + band),
        "probability_within_band": _within(pred, kt, band),
        "over_probability": settings.over_probability,
        "pass_probability": aimed["pass_probability"],
        "plate_risk_spent": aimed["plate_risk_spent"],
        "expected_passes": aimed["expected_passes"],
        "over_band": settings.over_band,
        "yield_factor_aimed": aimed["yield_factor"],
    }


def _data_basis(
    plate: PlateRecord,
    others: Sequence[PlateRecord],
    machine_id: str,
    fitted: Fit,
    settings: AimSettings,
) -> dict[str, Any]:
    rows = fitted.rows_per_plate
    own = rows.get(plate.plate_id, 0)
    same = [h for h in others if h.group == plate.group]
    group_rows = sum(rows.get(h.plate_id, 0) for h in same)
    machine_rows = sum(rows.get(h.plate_id, 0) for h in others)
    warnings = []
    if own == 0 and machine_rows == 0:
        data = "nominal only: no history"
        warnings.append(
            "no inspected pass of this plate or of this machine: the advice rests on the nominal "
            "model and its priors; expect an under-bent plate and a correction pass"
        )
    elif own == 0 and group_rows < settings.min_rows:
        data = (
            "machine history only"
            if group_rows == 0
            else "little history of this grade and thickness"
        )
        warnings.append(
            f"{group_rows} inspected passes of {plate.group[0]} {plate.group[1]:g} mm on {machine_id}: "
            "its yield is mostly the prior's; expect a correction pass"
        )
    elif own == 0:
        data = "history of this machine, grade and thickness"
    else:
        data = "this plate's passes" + (" and history of this machine" if machine_rows else "")
        if machine_rows == 0 and own < settings.min_rows:
            warnings.append("no history of this machine: its compliance and gain are the prior's")
    warnings.extend(_inspection_warnings(plate, fitted.priors))
    c, c_sd = fitted.parameter("machine", machine_id)
    gain, gain_sd = fitted.parameter("gain", machine_id)
    f, f_sd = fitted.parameter("plate", plate.plate_id)
    g, g_sd = fitted.parameter("group", plate.group)
    return {
        "data": data,
        "enough_data": not warnings,
        "plate_passes_inspected": own,
        "group_plates": len(same),
        "group_passes_inspected": group_rows,
        "machine_plates": len(others),
        "machine_passes_inspected": machine_rows,
        "inspections": _inspections_basis(plate, fitted.priors),
        "parameters": {
            "yield_factor": {"mean": f, "sd": f_sd},
            "group_yield_factor": {"mean": g, "sd": g_sd, "plate_spread": fitted.plate_spread},
            "compliance_mm_per_mn": {"mean": c, "sd": c_sd},
            "displacement_gain": {"mean": gain, "sd": gain_sd},
            "scatter_mm": fitted.scatter_mm,
        },
        "warnings": warnings,
    }


def _inspections_basis(plate: PlateRecord, priors: Priors) -> list[dict[str, Any]]:
    """Each inspected pass of the plate as the fit takes it: the radius, its standard uncertainty
    (reported, or None: the model's constant), whether capable, and the curvature sd it enters with."""
    out = []
    for j, q in enumerate(plate.passes):
        if q.measured_radius_mm is None:
            continue
        out.append(
            {
                "pass": j,
                "measured_radius_mm": q.measured_radius_mm,
                "radius_uncertainty_mm": q.radius_uncertainty_mm,
                "capable": q.capable,
                "curvature_sd_per_mm": math.sqrt(inspection_variance(plate, j, priors)),
            }
        )
    return out


def _inspection_warnings(plate: PlateRecord, priors: Priors) -> list[str]:
    """One warning per inspection of the plate that is not capable for its tolerance."""
    out = []
    for j, q in enumerate(plate.passes):
        if q.measured_radius_mm is None or q.capable:
            continue
        u = (
            "no uncertainty reported"
            if q.radius_uncertainty_mm is None
            else (f"radius uncertainty {2 * q.radius_uncertainty_mm:.1f} mm (k=2)")
        )
        out.append(
            f"the inspection after pass {j + 1} is not capable for the tolerance ({u}): the advice "
            "weighs it as no better than a measurement at the capability limit"
        )
    return out


def _reverse_advice(
    action: Literal["bend", "reverse"],
    plate: PlateRecord,
    known: Sequence[PlateRecord],
    fitted: Fit,
    machine: Machine,
    settings: AimSettings,
    basis: dict[str, Any],
) -> Advice:
    """A reverse pass for an over-bent plate, or a bending pass after one (:mod:`.reverse`)."""
    target = plate.target
    kt, band = target_curvature(target), curvature_band(target)
    d_max = bender.max_displacement_mm(machine, target.material.thickness_mm)
    beta = reverse.reverse_factor(fitted, [*known, plate], machine, own=plate.plate_id)
    flipped = action == "reverse"
    try:
        predictor = reverse.Predictor(fitted, plate, machine, beta)
    except reverse.ReversalError as err:
        basis["warnings"].append(f"no setting: {err}; roll it by hand and inspect")
        return Advice(action, machine.machine_id, None, None, None, basis)
    if flipped:
        d = reverse.aim_reverse(
            predictor, kt, kt - settings.over_band * band, settings.reverse_open_probability, d_max
        )
    else:
        d = reverse.aim_after_reverse(
            predictor, kt, kt + settings.over_band * band, settings.pass_probability, d_max
        )
    ks = predictor.samples(d, flipped=flipped)
    k_mid, k_lo, k_hi = (float(np.quantile(ks, p)) for p in (0.5, 0.025, 0.975))
    learned = (
        f"the reverse factor learned from {beta.passes} reverse passes of the yard"
        if beta.passes
        else "the model with a wide margin: no reverse pass in the history (reverse factor "
        f"{beta.mean:g} +- {beta.sd:g}, the Bauschinger effect unknown)"
    )
    basis["reverse"] = {
        "flipped": flipped,
        "rests_on": learned,
        "reverse_factor": {"mean": beta.mean, "sd": beta.sd, "reverse_passes": beta.passes},
        "probability_over_band": float(np.mean(ks > kt + band)),
        "probability_open_beyond_band": float(np.mean(ks < kt - band)),
        "open_probability": settings.reverse_open_probability,
    }
    if flipped:
        basis["reason"] += (
            f": turn the plate over and roll it with the top roll at {d:.1f} mm "
            "(from touching a flat plate; negative: above that point)"
        )
    else:
        basis["warnings"].append("bending after a reverse pass: the advice rests on " + learned)
    return Advice(
        action,
        machine.machine_id,
        d,
        _surface_radius(target, k_mid),
        (_surface_radius(target, k_hi), _surface_radius(target, k_lo)),
        basis,
    )


def _two_pass(
    plate: PlateRecord,
    predict: Callable[[float], Prediction],
    d_lo: float,
    d: float,
    settings: AimSettings,
) -> tuple[float, str] | None:
    """The first of two passes, ``(displacement_mm, words)``, when the spread fills the band; else None.

    The rule applies to a plate with an inspected shape whose next pass at ``d`` lands within the band
    with less than even odds while the passes' scatter is under half its sd: the rest is the
    parameters' share, propagated through the increment, which a shorter step shrinks. The first pass
    is then aimed (median) at ``two_pass_fraction`` of the remaining bend; the second starts from its
    inspection. When the scatter itself fills the band a shorter step does not help, and the rule does
    not apply.
    """
    if not plate.passes or plate.passes[-1].measured_radius_mm is None:
        return None
    target = plate.target
    kt, band = target_curvature(target), curvature_band(target)
    pred = predict(d)
    p_in = pred.probability_above(kt - band) - pred.probability_above(kt + band)
    if p_in >= 0.5 or pred.scatter_sd >= 0.5 * pred.sd:
        return None
    k_now = measured_curvature(plate, plate.passes[-1].measured_radius_mm)
    goal = k_now + settings.two_pass_fraction * (kt - k_now)
    if goal <= k_now or predict(d_lo).median >= goal or predict(d).median <= goal:
        return None
    d_first = float(optimize.brentq(lambda x: predict(x).median - goal, d_lo, d, xtol=1e-3))
    words = (
        f"the predicted spread fills the tolerance band (one pass would land within it with "
        f"{p_in:.0%}): approach in two passes, this one to {settings.two_pass_fraction:.0%} of the "
        "remaining bend, the next from its inspection"
    )
    return d_first, words


def _scatter_two_pass(
    plate: PlateRecord,
    predict: Callable[[float], Prediction],
    span: tuple[float, float],
    over_edge: float,
    allowed: float,
    settings: AimSettings,
) -> tuple[float, str] | None:
    """The first of two passes when the scatter fills the band (``AimSettings.scatter_two_pass``),
    ``(displacement_mm, words)``; else None.

    For a plate's first correction (one pass rolled, inspected) whose prediction at the aim's setting
    ``d`` (``span``: the least setting and ``d``) is mostly the passes' scatter (its share at least half
    the sd), and which, with that share's sd twice its estimate (normal tails: the estimate from a few
    plates may be half the truth), ends past the verdict's edge ``over_edge`` with more than
    ``allowed``: this pass goes to the deepest setting whose risk at twice the scatter is ``allowed``,
    its median at most ``two_pass_fraction`` of the remaining bend; the next starts from its
    inspection, with the plate's own last pass known. The words state the share of the remaining bend
    the median reaches.
    """
    d_lo, d = span
    if len(plate.passes) != 1 or plate.passes[-1].measured_radius_mm is None:
        return None
    pred = predict(d).truth()
    if pred.scatter_sd < 0.5 * pred.sd:
        return None

    def doubled_risk(x: float) -> float:
        return predict(x).truth().with_scatter_variance(4.0).probability_above(over_edge)

    if doubled_risk(d) <= allowed or doubled_risk(d_lo) > allowed:
        return None
    kt = target_curvature(plate.target)
    k_now = measured_curvature(plate, plate.passes[-1].measured_radius_mm)
    if kt <= k_now:
        return None
    d_first = float(optimize.brentq(lambda x: doubled_risk(x) - allowed, d_lo, d, xtol=1e-3))
    goal = k_now + settings.two_pass_fraction * (kt - k_now)
    if predict(d_first).median > goal and predict(d_lo).median < goal:
        d_first = float(
            optimize.brentq(lambda x: predict(x).median - goal, d_lo, d_first, xtol=1e-3)
        )
    share = (predict(d_first).median - k_now) / (kt - k_now)
    words = (
        "the pass's scatter fills the tolerance band (a scatter twice its estimate would put this "
        f"pass past the band with more than {allowed:.2%}): approach in two passes, this one to "
        f"{share:.0%} of the remaining bend, the next from its inspection"
    )
    return d_first, words


def _stalled(fitted: Fit, plate: PlateRecord, machine_id: str) -> float | None:
    """The deepest setting on ``machine_id`` shown not to move the plate: of the passes after the one
    that made its latest inspected shape (:func:`.learning.plate_states`); None when there are none."""
    state = latest_state(plate, fitted.curvatures(plate)[0], fitted.priors)
    if state is None:
        return None
    stalled = [
        q.top_roll_displacement_mm
        for q in plate.passes[state.peak_pass + 1 :]
        if q.machine_id == machine_id and not q.flipped
    ]
    return max(stalled, default=None)


def _scatter_fills_band(
    stalled: float | None,
    d: float,
    probability: float,
    allowed: float,
    *,
    given: bool,
) -> str:
    """The words for a plate whose least move is already past the aim's margin: given (its risk of
    ending past the band's tight edge within the allowed level) or not."""
    move = (
        "the deepest setting so far, repeated,"
        if stalled is None
        else f"the pass at {stalled:.2f} mm did not move the plate: the next setting, "
        f"{d - stalled:.2f} mm beyond it,"
    )
    risk = f"would end past the band with {probability:.2%} (allowed: {allowed:.2%})"
    if given:
        return (
            f"the pass's scatter fills the tolerance band: {move} is the least move, and {risk}; "
            "inspect again"
        )
    return (
        f"no setting: the pass's scatter fills the tolerance band; {move} {risk}. Accept the plate as "
        "it is or roll it on a machine that repeats its setting more closely"
    )
