"""Reverse passes: an over-bent plate flipped and rolled to open it, and bending again after one.

Mechanics
---------
Curvatures are of the plate's mid-surface in the sense of its bend (positive: the way it was rolled).
Flipped over, the plate arches up on the bottom rolls; the top roll, at a displacement ``d`` measured as
for a bending pass (down from touching a flat plate), presses the arch flatter (``d < 0``: the top roll
stops above that point) or through flat into the other way (``d > 0``). The loaded shape is again an arc
through the three contacts; with the contacts on the other faces the same algebra as
:mod:`.bender` gives, for either sign,

    k_L(d) = -2 d / (a^2 + d^2 - 2 d (r_b + t/2))

(``d < 0``: an arch of mid radius ``(a^2 + d^2) / (2 |d|) + r_b + t/2``). The machine's gain and give act
as in a bending pass (:mod:`.rolling`): the plate sees ``g d - c F``, ``F`` holding the moment.

The section follows Masing's rule on the elastic-perfectly-plastic curve ``M_0`` (:mod:`.springback`):
from the forward peak ``(k_p, M_0(k_p))`` the reverse branch is

    M(k) = M_0(k_p) - 2 M_b((k_p - k) / 2)

and from the reverse point ``(k_r, M_r)`` a forward reload ``M(k) = M_r + 2 M_b((k - k_r) / 2)`` (at most
``M_0(k)``), where ``M_b`` is ``M_0`` with the yield stress times ``beta``, the *reverse factor*: 1 is
Masing's ideal material; real steels yield earlier in reverse (the Bauschinger effect), ``beta < 1``.
Unloading is elastic, ``k' = k - M / (E' I)``. A flipped pass whose arch is not flatter than the plate
(``k_L >= k``) does not touch it, and one that does not go beyond an earlier flipped pass changes
nothing (the memory of Masing's rule), as the history rule of bending passes.

Learning
--------
``beta`` is learned from the yard's own reverse passes (:func:`reverse_factor`): each plate of the history
with an inspected shape before its first flipped pass and after it gives the ``beta`` that makes the
model's opening (its fitted factor, compliance and gain) match the measured one. With none, the prior
``N(0.85, 0.15^2)``: a wide margin for a mechanism the bending passes do not show. With some, a
hierarchical estimate: the yard's mean ``beta`` (that prior, updated by the ``n`` plates) and the spread
of plates about it (prior 0.05 worth 2 plates, updated from the plates' values); a plate's ``beta`` is
predicted with both. The plate's own reverse passes, when it has some, give its own ``beta``.

Aim
---
The prediction starts from the plate's measured shape (the model's increment from it, as
:meth:`.learning.Fit.predict`) and its spread is sampled (:data:`SAMPLES` draws of the plate's factor, the
machine's compliance and gain from the fit's covariance, ``beta`` and the new pass's displacement
scatter). A reverse pass aims its median at the target and opens beyond the band's open edge
(``target - over_band * band``) with at most ``AimSettings.reverse_open_probability``; a bending pass after
a reverse keeps the bending aim's ``over_probability`` on the tight side.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from . import springback
from .learning import Fit, inspection_variance, measured_curvature
from .records import Machine, PlateRecord, RollPass
from .rolling import PassSetup

Floats = npt.NDArray[np.float64]

#: Draws of the parameters a reverse prediction is sampled with (a fixed seed: the advice is repeatable).
SAMPLES = 4000
#: Prior mean and sd of the reverse factor ``beta`` without reverse passes in the history.
BETA_PRIOR = (0.85, 0.15)
#: Prior sd of ``beta`` between plates of the yard about its mean (the plates' mean is what the
#: prior's sd above leaves open), and the pseudo-observations that guess is worth.
BETA_SPREAD = 0.05
BETA_PRIOR_WEIGHT = 2.0
#: Bounds of ``beta`` (a draw is clipped to them).
BETA_BOUNDS = (0.3, 1.5)
_ITER = 30
#: Displacement step of a numerical derivative, mm.
_H_D = 1e-2


@dataclass(frozen=True)
class ReverseFactor:
    """The reverse factor ``beta``'s predictive distribution and how many reverse passes it rests on."""

    mean: float
    sd: float
    passes: int


@dataclass(frozen=True)
class Section:
    """Constants of one plate on one machine for the reverse mechanics, vectorised over samples."""

    setup: PassSetup
    stiffness: float  # E' I per unit width, N mm

    @classmethod
    def of(cls, machine: Machine, plate: PlateRecord) -> Section:
        setup = PassSetup.of([machine], [plate])
        t = float(setup.thickness_mm[0])
        return cls(setup, float(setup.modulus_mpa[0]) * t**3 / 12.0)

    def moment(self, curvature: Floats, factor: Floats) -> Floats:
        """``M_0`` per unit width at ``|curvature|`` with the yield times ``factor``, N mm / mm (signed)."""
        s = self.setup
        m = springback.bending_moment(
            np.abs(curvature), s.yield_mpa[0] * factor, s.modulus_mpa[0], s.thickness_mm[0]
        )
        return np.sign(curvature) * np.asarray(m, dtype=np.float64)

    def flipped_curvature(self, displacement_mm: Floats) -> Floats:
        """Loaded curvature of a flipped pass at an effective displacement (module docstring), 1/mm."""
        s = self.setup
        d = np.asarray(displacement_mm, dtype=np.float64)
        k = -2.0 * d / (float(s.half_span_mm[0]) ** 2 + d * d - 2.0 * d * self._offset())
        return np.asarray(k, dtype=np.float64)

    def _offset(self) -> float:
        s = self.setup
        return float(s.bottom_roll_radius_mm[0] + 0.5 * s.thickness_mm[0])

    def force(self, curvature: Floats, moment: Floats) -> Floats:
        """Top-roll force holding ``|moment|`` at ``curvature`` (:meth:`.rolling.PassSetup.force_n`), N."""
        s = self.setup
        a = float(s.half_span_mm[0])
        k = np.abs(curvature)
        root = np.sqrt(np.maximum((1.0 + k * self._offset()) ** 2 - (k * a) ** 2, 0.0))
        return 2.0 * np.abs(moment) * float(s.length_mm[0]) * root / a


@dataclass(frozen=True)
class Draws:
    """Parameter samples: the plate's factor, the machine's compliance (mm/MN) and gain, ``beta``."""

    factor: Floats
    compliance: Floats
    gain: Floats
    beta: Floats


def draws(fitted: Fit, plate_id: str, machine_id: str, beta: ReverseFactor, n: int) -> Draws:
    """``n`` joint draws from the fit's posterior (``n == 1``: its mean) and ``beta``'s distribution."""
    idx = [
        fitted._index("plate", plate_id),
        fitted._index("machine", machine_id),
        fitted._index("gain", machine_id),
    ]
    mean = fitted.mean[idx]
    if n == 1:
        x = mean[None, :]
        b = np.array([beta.mean])
    else:
        rng = np.random.default_rng(0)
        x = rng.multivariate_normal(mean, fitted.cov[np.ix_(idx, idx)], size=n)
        b = beta.mean + beta.sd * rng.standard_normal(n)
    return Draws(
        np.clip(x[:, 0], 0.3, 3.0),
        np.maximum(x[:, 1], fitted.priors.compliance_floor_mm_per_mn),
        x[:, 2],
        np.clip(b, *BETA_BOUNDS),
    )


class ReversalError(ValueError):
    """A load path the reverse mechanics does not describe (a second reversal)."""


@dataclass
class _Path:
    """A plate's load path, per sample: forward peak, reverse point, reload peak (loaded, 1/mm)."""

    peak: Floats
    reverse: Floats | None = None
    reload: Floats | None = None


def _walk(
    section: Section, passes: tuple[RollPass, ...], x: Draws, machine_id: str, shift_mm: Floats
) -> _Path:
    """The load path of ``passes`` (all on ``machine_id``); ``shift_mm`` is added to the last pass's
    displacement (its scatter)."""
    path = _Path(np.zeros_like(x.factor))
    for j, q in enumerate(passes):
        if q.machine_id != machine_id:
            raise ReversalError(
                f"passes[{j}]: a reverse cycle on one machine only, got {q.machine_id!r}"
            )
        d = q.top_roll_displacement_mm + (shift_mm if j == len(passes) - 1 else 0.0)
        if not q.flipped:
            kl = section.setup.loaded_curvature(d, x.factor, x.compliance, x.gain)
            if path.reverse is None:
                path.peak = np.maximum(path.peak, kl)
            else:
                path.reload = kl if path.reload is None else np.maximum(path.reload, kl)
            continue
        if path.reload is not None:
            raise ReversalError("a second reversal (flipped after bending again) is not modelled")
        kl = _flipped_loaded(section, path, x, np.asarray(d, dtype=np.float64))
        path.reverse = kl if path.reverse is None else np.minimum(path.reverse, kl)
    return path


def _reverse_moment(section: Section, path: _Path, k: Floats, x: Draws) -> Floats:
    """Masing's reverse branch from the forward peak (module docstring), N mm / mm."""
    m_peak = section.moment(path.peak, x.factor)
    return m_peak - 2.0 * section.moment(0.5 * (path.peak - k), x.factor * x.beta)


def _flipped_loaded(section: Section, path: _Path, x: Draws, d: Floats) -> Floats:
    """Loaded curvature of a flipped pass with the machine's gain and give (fixed point)."""
    current = _unloaded(section, path, x)
    k = section.flipped_curvature(x.gain * d)
    for _ in range(_ITER):
        m = np.where(k < current, _reverse_moment(section, path, k, x), 0.0)
        k = section.flipped_curvature(x.gain * d - 1e-6 * x.compliance * section.force(k, m))
    return np.asarray(k, dtype=np.float64)


def _unloaded(section: Section, path: _Path, x: Draws) -> Floats:
    """The curvature after unloading at the end of ``path`` (module docstring), 1/mm."""
    ei = section.stiffness
    k = path.peak - section.moment(path.peak, x.factor) / ei
    if path.reverse is None:
        return np.asarray(k, dtype=np.float64)
    touched = path.reverse < k
    k_r = np.where(touched, path.reverse, k)
    m_r = np.where(touched, _reverse_moment(section, path, k_r, x), 0.0)
    k = np.where(touched, k_r - m_r / ei, k)
    if path.reload is None:
        return np.asarray(k, dtype=np.float64)
    k_q = path.reload
    m_q = np.minimum(
        m_r + 2.0 * section.moment(0.5 * np.maximum(k_q - k_r, 0.0), x.factor * x.beta),
        section.moment(k_q, x.factor),
    )
    return np.asarray(np.where(k_q > k, k_q - m_q / ei, k), dtype=np.float64)


def model_curvature(
    section: Section, plate: PlateRecord, x: Draws, machine_id: str, shift_mm: Floats | float = 0.0
) -> Floats:
    """The model's curvature after the plate's passes, per draw (``shift_mm``: the last pass's error)."""
    shift = np.broadcast_to(np.asarray(shift_mm, dtype=np.float64), x.factor.shape)
    return _unloaded(section, _walk(section, plate.passes, x, machine_id, shift), x)


def reverse_factor(
    fitted: Fit,
    plates: list[PlateRecord],
    machine: Machine,
    *,
    own: str | None = None,
    prior: tuple[float, float] = BETA_PRIOR,
) -> ReverseFactor:
    """``beta`` from the plates' reverse passes on ``machine`` (module docstring, "Learning").

    Parameters
    ----------
    fitted : Fit
        A fit whose plates include ``plates`` (their forward passes).
    plates : list of PlateRecord
        Plates of the history, and the plate advised; those without an inspected shape before and after
        their first block of flipped passes on ``machine`` are skipped, and so are those whose reverse
        did not move them (the opening is then only a bound on ``beta``).
    machine : Machine
    own : str, optional
        The advised plate's id: when its own reverse passes give ``beta``, that estimate is used with
        its own sd (its inspections' noise and its pass's scatter), not the spread between plates.
    prior : (float, float)
        Mean and sd of ``beta`` without data.

    Returns
    -------
    ReverseFactor
        The predictive mean and sd of the plate's ``beta`` and the reverse passes it rests on.
    """
    found = {p.plate_id: e for p in plates if (e := _beta_of(fitted, p, machine)) is not None}
    if own is not None and own in found:
        mean, sd = found[own]
        return ReverseFactor(mean, sd, len(found))
    if not found:
        return ReverseFactor(prior[0], prior[1], 0)
    values = np.asarray([m for m, _ in found.values()])
    n = len(values)
    tau2 = (BETA_PRIOR_WEIGHT * BETA_SPREAD**2 + float(np.sum((values - values.mean()) ** 2))) / (
        BETA_PRIOR_WEIGHT + n - 1
    )
    precision = 1.0 / prior[1] ** 2 + n / tau2
    mean = (prior[0] / prior[1] ** 2 + float(values.sum()) / tau2) / precision
    return ReverseFactor(float(mean), math.sqrt(tau2 + 1.0 / precision), n)


def _reverse_span(plate: PlateRecord, machine_id: str) -> tuple[int, int] | None:
    """The last inspected pass before the plate's first flipped pass and the last inspected pass of
    that block of flipped passes, all on ``machine_id``; None without both."""
    flips = [j for j, q in enumerate(plate.passes) if q.flipped]
    if not flips:
        return None
    j0 = flips[0]
    j1 = j0
    while j1 + 1 < len(plate.passes) and plate.passes[j1 + 1].flipped:
        j1 += 1
    before = [j for j in range(j0) if plate.passes[j].inspected]
    after = [j for j in range(j0, j1 + 1) if plate.passes[j].inspected]
    if not before or not after:
        return None
    if any(q.machine_id != machine_id for q in plate.passes[: after[-1] + 1]):
        return None
    return before[-1], after[-1]


def _beta_of(fitted: Fit, plate: PlateRecord, machine: Machine) -> tuple[float, float] | None:
    """The ``beta`` that makes the model open ``plate`` as its first reverse passes did, and its sd
    from the two inspections' noise and the reverse pass's scatter; None when it cannot be told."""
    span = _reverse_span(plate, machine.machine_id)
    if span is None or plate.plate_id not in fitted.plate_ids:
        return None
    i0, i1 = span
    k0, k1 = (
        measured_curvature(plate, plate.passes[j].measured_radius_mm or math.inf) for j in span
    )
    noise = inspection_variance(plate, i0, fitted.priors) + inspection_variance(
        plate, i1, fitted.priors
    )
    if k0 - k1 < 3.0 * math.sqrt(noise):
        return None  # the reverse did not move the plate: a bound, not a value
    head = PlateRecord(plate.plate_id, plate.target, plate.passes[: i0 + 1])
    upto = PlateRecord(plate.plate_id, plate.target, plate.passes[: i1 + 1])
    section = Section.of(machine, plate)
    x = draws(fitted, plate.plate_id, machine.machine_id, ReverseFactor(1.0, 0.0, 0), 1)

    def opened(beta: float, shift_mm: float = 0.0) -> float:
        xb = Draws(x.factor, x.compliance, x.gain, np.array([beta]))
        m0 = model_curvature(section, head, xb, machine.machine_id)[0]
        m1 = model_curvature(section, upto, xb, machine.machine_id, shift_mm)[0]
        return float(m1 - m0)

    beta = _root(lambda b: opened(b) - (k1 - k0), *BETA_BOUNDS)
    slope = (opened(beta + 1e-3) - opened(beta)) / 1e-3
    g_d = opened(beta, _H_D) - opened(beta)
    if not (BETA_BOUNDS[0] < beta < BETA_BOUNDS[1]) or slope == 0:
        return None
    sd = math.sqrt(noise + (g_d / _H_D * fitted.scatter_mm) ** 2) / abs(slope)
    return beta, sd


class Predictor:
    """Sampled predictions of a plate's curvature after one more pass on ``machine`` (module docstring,
    "Aim"): the draws and the model's current curvature are computed once.

    Raises
    ------
    ReversalError
        A load path the mechanics does not describe (:func:`model_curvature`).
    """

    def __init__(self, fitted: Fit, plate: PlateRecord, machine: Machine, beta: ReverseFactor):
        self.plate, self.machine_id = plate, machine.machine_id
        self.section = Section.of(machine, plate)
        self.x = draws(fitted, plate.plate_id, machine.machine_id, beta, SAMPLES)
        rng = np.random.default_rng(1)
        self.error_mm = fitted.scatter_mm * rng.standard_normal(SAMPLES)
        last = len(plate.passes) - 1
        k_meas = measured_curvature(plate, plate.passes[last].measured_radius_mm or math.inf)
        noise = math.sqrt(inspection_variance(plate, last, fitted.priors))
        self.start = k_meas + noise * rng.standard_normal(SAMPLES)
        self.k_measured = k_meas
        self.k_model = model_curvature(self.section, plate, self.x, self.machine_id)

    def samples(self, displacement_mm: float, *, flipped: bool) -> Floats:
        """The plate's curvature after a pass at this displacement, one value per draw, 1/mm."""
        trial = self.plate.with_pass(RollPass(self.machine_id, displacement_mm, flipped=flipped))
        k_new = model_curvature(self.section, trial, self.x, self.machine_id, self.error_mm)
        return np.asarray(self.start + (k_new - self.k_model), dtype=np.float64)

    def contact_mm(self) -> float:
        """The flipped pass's displacement (nominal machine) whose arch is the plate's measured shape."""
        lo, hi = -0.999 * float(self.section.setup.half_span_mm[0]), 0.0
        k = self.k_measured
        for _ in range(60):
            mid = 0.5 * (lo + hi)
            if float(self.section.flipped_curvature(np.array([mid]))[0]) > k:
                lo = mid
            else:
                hi = mid
        return lo


def _root(g: Callable[[float], float], lo: float, hi: float) -> float:
    """Where the non-increasing or non-decreasing ``g`` changes sign in ``[lo, hi]`` (bisection; an end
    when it does not)."""
    g_lo, g_hi = g(lo), g(hi)
    if g_lo * g_hi > 0:
        return lo if abs(g_lo) < abs(g_hi) else hi
    for _ in range(_ITER + 10):
        mid = 0.5 * (lo + hi)
        g_mid = g(mid)
        if g_mid * g_lo > 0:
            lo, g_lo = mid, g_mid
        else:
            hi = mid
    return 0.5 * (lo + hi)


def aim_reverse(
    predictor: Predictor, target_k: float, open_k: float, open_probability: float, d_max: float
) -> float:
    """The flipped pass's displacement: the median at ``target_k`` unless that opens the plate beyond
    ``open_k`` with more than ``open_probability``; at least beyond the plate's earlier flipped passes
    (which a setting not beyond them repeats: it does not move the plate), mm."""
    earlier = [q.top_roll_displacement_mm for q in predictor.plate.passes if q.flipped]
    d_lo = max([predictor.contact_mm(), *earlier])

    def median(d: float) -> float:
        return float(np.median(predictor.samples(d, flipped=True))) - target_k

    def opened(d: float) -> float:
        return float(np.quantile(predictor.samples(d, flipped=True), open_probability)) - open_k

    return min(_root(median, d_lo, d_max), _root(opened, d_lo, d_max))


def aim_after_reverse(
    predictor: Predictor, target_k: float, tight_k: float, over_probability: float, d_max: float
) -> float:
    """A bending pass after a reverse: the median at ``target_k`` unless that ends tighter than
    ``tight_k`` with more than ``over_probability``, mm."""
    d_lo = 1e-3

    def median(d: float) -> float:
        return float(np.median(predictor.samples(d, flipped=False))) - target_k

    def tight(d: float) -> float:
        return (
            float(np.quantile(predictor.samples(d, flipped=False), 1 - over_probability)) - tight_k
        )

    return min(_root(median, d_lo, d_max), _root(tight, d_lo, d_max))
