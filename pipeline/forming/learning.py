"""The model's uncertain parameters fitted to the forming history, with their uncertainty.

Parameters
----------
- ``c_m``: each machine's compliance, mm/MN (:mod:`.rolling`); prior ``N(c0, sc^2)``.
- ``g_m``: each machine's displacement gain (:mod:`.rolling`); prior ``N(1, sg^2)``. Where the compliance
  takes up a shortfall that grows with the force (thick plates), the gain takes one that grows with the
  displacement (the geometry): a model a few per cent off in either way is learned from the machine's
  history instead of being taken for pass scatter (which makes every aim timid).
- ``mu_g``: the mean yield factor of a group of plates of one grade and thickness (plates of a heat, of a
  mill, of a thickness behave alike); prior ``N(f0, sf^2)``. ``f0 - 2 sf`` lies near 1 (nominal yield is a
  minimum) and ``f0`` near mill plates' typical 15 % above it.
- ``f_p``: each plate's yield factor, ``N(mu_g, tau^2)`` about its group's mean: real plates differ.

Data
----
Each inspected pass gives the plate's mid-surface curvature. Passes that do not load the plate beyond an
earlier one do not change it (the history rule), so inspections of one state are averaged into one row.
A row's variance is the inspection's noise, plus the pass's own scatter: a displacement scatter
``sigma_d`` (mm; repeatability of the roll, the plate's feed) times the row's sensitivity ``g = d k / d d``.
The inspection's noise is its own reported radius uncertainty where it has one, else the model's
constant (relative radius noise and an absolute sagitta noise over the plate's width), at least the
capability limit's for an inspection not capable for the tolerance (:func:`inspection_variance`);
inspections of one state are averaged with inverse-variance weights.

Fit
---
Weighted non-linear least squares on the data rows and the priors together (the maximum a posteriori
estimate of the hierarchical model), with ``scipy.optimize.least_squares``; the covariance is the
inverse of ``J^T J`` at the optimum (Laplace). ``sigma_d`` and ``tau`` are then updated as conjugate
variance estimates, each weighted with its prior as pseudo-observations::

    sigma_d^2 = (nu0 sigma0^2 + max(sum_rows w (r^2 - (1 - h) v_inspection) / g^2, 0)) / (nu0 + n)
    tau^2     = (nu_t tau0^2 + sum_plates [(f_p - mu_g)^2 + var(f_p - mu_g)]) / (nu_t + n_plates)

and the fit repeated (three rounds). ``h`` is a row's leverage, its diagonal element of the hat
matrix (a plate's factor takes its first row whole, the machines' and groups' parameters a share of
every row), ``w = (g^2 sigma_d^2 / (v_inspection + g^2 sigma_d^2))^2`` the row's information about
the scatter, and ``n = sum w (1 - h)`` the estimate's degrees of freedom (:func:`_scatter_estimate`).
The last round weighs the rows with the scatter's posterior mean
variance ``nu s^2 / (nu - 2)`` (``nu`` its degrees of freedom, at least 3), so that with few rows the
parameters' covariance carries the doubt about the scatter it was weighed with. Predictions use Student's t with the corresponding degrees of freedom
(:meth:`Fit.predict`): with little data the tails are wide, and the advice aims further to the safe side.
The parameters the rows pinned (a machine's gain and compliance from its plates, a plate's factor from
its own passes) are as uncertain as the scatter those rows were weighed with: the covariance's share
that scales with the scatter's variance, ``d cov / d log sigma_d^2`` (:func:`_scatter_share`), takes
the scatter's degrees of freedom in a prediction, the rest (priors, inspection noise) none.

A plate's next pass is predicted from its latest measured shape plus the model's increment to the new
pass (:meth:`Fit.predict`, :func:`latest_state`), the increment starting where the pass that made that
shape really loaded the plate. Its setting is not that place: the pass scattered by ``x`` mm, and the
shape it left is what the parameters need ``x`` to be (``u(theta, d_p + x) = k_a``, ``u`` the curvature
after one pass). So ``x`` is the fitted parameters' (the scatter the fit attributes to that pass), with
their uncertainty; passes that by the model loaded the plate beyond it but left the shape unchanged
bound it from below, each with its own error (:func:`_stalled_peak`). A plate that ended short of its prediction had its peak
pass scatter short, and its next pass moves it further than from the setting (taking ``x ~ N(0, s^2)``
whatever the shape said made the aim under-predict that move and over-bend at a 0.2 mm scatter). A
pass that does not load the plate beyond that peak leaves the shape: the prediction is
``max(k_a, T)`` (:class:`Prediction`).

A plate's own passes pin its factor; passes of other plates on the same machine pin the machine's
compliance, and those of the same grade and thickness the group's mean factor and spread. A plate with
no history of its own gets its group's distribution; a group with no plates gets the prior.

Kept as one module (~700 lines, a third of them this derivation and the numpydoc): the rows, the
rounds of the fit and the variance updates are one estimator and change together.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from itertools import pairwise

import numpy as np
from scipy import optimize, stats

from .records import Machine, PlateRecord, RollPass
from .rolling import PassSetup, plate_curvatures

#: Rounds of (least squares, variance update).
_ROUNDS = 3
#: Finite-difference steps: compliance (mm/MN), yield factor, displacement (mm).
_H_C, _H_F, _H_D = 1e-3, 1e-5, 1e-3


@dataclass(frozen=True)
class Priors:
    """What the model assumes before any history (all documented in docs/forming.md).

    Attributes
    ----------
    yield_factor, yield_factor_sd : float
        Prior mean and sd of a grade/thickness group's mean yield factor.
    yield_factor_floor : float
        The least factor a plate can have: the nominal yield is a guaranteed minimum (1). The first pass
        of a plate is never aimed for a factor below it (:func:`.advice.aim`).
    plate_spread : float
        Prior guess of the sd of plates' factors about their group's mean (``tau0``).
    plate_spread_weight : float
        How many plates that guess is worth (``nu_t``).
    compliance_mm_per_mn, compliance_sd_mm_per_mn : float
        Prior mean and sd of a machine's compliance.
    compliance_floor_mm_per_mn : float
        The least compliance a machine can have: its frame and rolls give under the force, they never
        push further (0). The first pass of a plate is never aimed for a compliance below it
        (:func:`.advice.aim`); the Gaussian prior alone would put a fresh machine's 0.5 % quantile
        at -4 mm/MN.
    gain_sd : float
        Prior sd of a machine's displacement gain about 1.
    scatter_mm : float
        Prior guess of a pass's displacement scatter (``sigma0``).
    scatter_weight : float
        How many rows that guess is worth (``nu0``): rows all scatter, where an inspected row counts by
        its information about the scatter (:func:`_scatter_estimate`, ~0.3-0.8 of a row). 4 (issue
        14's); 2 with every row counted whole left a fresh machine's first plates with t tails of
        2-3 degrees of freedom once rows counted by their information, and 3 of 24 first plates
        without a setting.
    radius_noise : float
        The inspection's relative radius noise (sd), for an inspection that reports no uncertainty.
    sagitta_noise_mm : float
        The inspection's absolute noise, as a sagitta over the plate's width (mm; ``k w^2 / 8``), for an
        inspection that reports no uncertainty.
    max_plates : int
        Most recent plates of the machine a fit uses besides the plate itself.
    scatter_share_dof : bool
        Give the share of the parameters' covariance that the scatter drives (:attr:`Fit.cov_scatter`:
        a machine's gain and compliance, a plate's factor, pinned by rows weighed with the estimated
        scatter) the scatter's degrees of freedom in a prediction, instead of counting it known
        (issue 27, a trial: off by default, docs/forming.md, fifth round).
    """

    yield_factor: float = 1.17
    yield_factor_sd: float = 0.06
    yield_factor_floor: float = 1.0
    plate_spread: float = 0.09
    plate_spread_weight: float = 4.0
    compliance_mm_per_mn: float = 1.0
    compliance_sd_mm_per_mn: float = 2.0
    compliance_floor_mm_per_mn: float = 0.0
    gain_sd: float = 0.02
    scatter_mm: float = 0.1
    scatter_weight: float = 4.0
    radius_noise: float = 5e-4
    sagitta_noise_mm: float = 0.1
    max_plates: int = 40
    scatter_share_dof: bool = False

    def __post_init__(self) -> None:
        for name in (
            "yield_factor",
            "yield_factor_sd",
            "yield_factor_floor",
            "plate_spread",
            "plate_spread_weight",
            "compliance_sd_mm_per_mn",
            "gain_sd",
            "scatter_mm",
            "scatter_weight",
            "radius_noise",
            "sagitta_noise_mm",
        ):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f"{name}: expected a positive finite number, got {v!r}")
        for name in ("compliance_mm_per_mn", "compliance_floor_mm_per_mn"):
            if not np.isfinite(getattr(self, name)):
                raise ValueError(f"{name}: expected a finite number, got {getattr(self, name)!r}")
        if not (isinstance(self.max_plates, int) and self.max_plates >= 0):
            raise ValueError(
                f"max_plates: expected a non-negative integer, got {self.max_plates!r}"
            )


@dataclass(frozen=True)
class Prediction:
    """The plate's mid-surface curvature after a next pass: ``max(floor, T)``, ``T`` a Student-t.

    Attributes
    ----------
    loaded_curvature : float
        The pass's loaded mid-surface curvature at the fitted parameters, 1/mm.
    mean, sd : float
        Location and scale of ``T``, the curvature after springback should the pass load the plate
        beyond its peak, 1/mm.
    dof : float
        Degrees of freedom.
    scatter_sd : float
        The share of ``sd`` from the passes' displacement scatter (the new pass's and the old peak's),
        1/mm: the part a shorter step does not shrink.
    floor : float
        The plate's present curvature, 1/mm: a pass that does not load it beyond its peak leaves it
        (``-inf``: no floor, a plate without an inspected shape).
    inspection_var : float
        The next inspection's noise in ``sd``, 1/mm^2: a prediction of what it will measure. The
        plate's true curvature after the pass is :meth:`truth`.
    """

    loaded_curvature: float
    mean: float
    sd: float
    dof: float
    scatter_sd: float = 0.0
    floor: float = -np.inf
    inspection_var: float = 0.0

    def truth(self) -> Prediction:
        """The plate's true curvature after the pass: without the next inspection's noise (a known
        variance, so the Welch-Satterthwaite degrees of freedom shrink with the total's square).
        Over-bending is judged on the true radius; the inspection's noise is no risk of it."""
        var = self.sd * self.sd
        rest = max(var - self.inspection_var, 1e-6 * var)
        if self.inspection_var <= 0 or var <= 0:
            return self
        return Prediction(
            self.loaded_curvature,
            self.mean,
            float(np.sqrt(rest)),
            max(self.dof * (rest / var) ** 2, 1.0),
            self.scatter_sd,
            self.floor,
            0.0,
        )

    def with_scatter_variance(self, scale: float) -> Prediction:
        """The same prediction with the passes' scatter share's variance times ``scale`` and taken
        as known (normal tails): the spread should the scatter be ``sqrt(scale)`` times its estimate
        (:meth:`.Fit.scatter_upper_scale`)."""
        var = self.sd * self.sd + (scale - 1.0) * self.scatter_sd * self.scatter_sd
        return Prediction(
            self.loaded_curvature,
            self.mean,
            float(np.sqrt(max(var, 0.0))),
            _KNOWN_DOF,
            float(self.scatter_sd * np.sqrt(scale)),
            self.floor,
            self.inspection_var,
        )

    @property
    def median(self) -> float:
        """The median curvature after the pass, 1/mm."""
        return max(self.floor, self.mean)

    def quantile(self, p: float) -> float:
        return max(self.floor, float(self.mean + self.sd * stats.t.ppf(p, self.dof)))

    def probability_above(self, curvature: float) -> float:
        if curvature < self.floor:
            return 1.0
        return float(stats.t.sf((curvature - self.mean) / self.sd, self.dof))


@dataclass(frozen=True)
class _Peak:
    """Where the pass that made a plate's latest shape really loaded it (:meth:`Fit._anchor_peak`).

    Attributes
    ----------
    machine_id : str
        That pass's machine.
    displacement_mm : float
        Its setting, mm.
    x_fit : float
        Its displacement error at the fitted parameters, mm.
    mean_x : float
        That error's mean given the passes that left the shape unchanged, mm (``x_fit`` without).
    var_fit, var_x : float
        Its variance from the parameters', and given those passes, mm^2.
    g_peak : float
        The shape's curvature per mm of that pass's displacement, 1/mm^2.
    var_fit_scatter : float
        The share of ``var_fit`` that scales with the scatter's variance (:attr:`Fit.cov_scatter`),
        mm^2.
    """

    machine_id: str
    displacement_mm: float
    x_fit: float
    mean_x: float
    var_fit: float
    var_x: float
    g_peak: float
    var_fit_scatter: float = 0.0


@dataclass(frozen=True)
class Fit:
    """Fitted parameters and their covariance (module docstring).

    Attributes
    ----------
    machine_ids, groups, plate_ids : tuple
        The parameters' order: compliances, gains (one per machine each), group means, plate factors.
    mean : (n,) ndarray
    cov : (n, n) ndarray
    scatter_mm : float
        Fitted displacement scatter of a pass, mm.
    plate_spread : float
        Fitted sd of plates' factors about their group's mean.
    n_rows : int
        Inspected states used.
    rows_per_plate : dict
        Inspected states per plate id.
    scatter_dof, spread_dof : float
        Degrees of freedom of the two variance estimates (prior weight included).
    machines : dict
        The machines of the fitted passes.
    priors : Priors
    cov_scatter : (n, n) ndarray or None
        The share of ``cov`` that scales with the pass scatter's variance, ``d cov / d log sigma_d^2``
        (:func:`_scatter_share`): the parameters the rows pinned, each row weighed with a variance
        that is mostly the estimated scatter. A prediction gives it the scatter's degrees of freedom
        (:meth:`_prediction`). None: not computed (``Priors.scatter_share_dof`` off), the whole
        parameters' share counted known as before.
    """

    machine_ids: tuple[str, ...]
    groups: tuple[tuple[str, float], ...]
    plate_ids: tuple[str, ...]
    mean: np.ndarray
    cov: np.ndarray
    scatter_mm: float
    plate_spread: float
    n_rows: int
    rows_per_plate: dict[str, int]
    scatter_dof: float
    spread_dof: float
    machines: dict[str, Machine]
    priors: Priors
    cov_scatter: np.ndarray | None = None

    def _index(self, kind: str, key: str | tuple[str, float]) -> int:
        m = len(self.machine_ids)
        if kind == "machine" and isinstance(key, str):
            return self.machine_ids.index(key)
        if kind == "gain" and isinstance(key, str):
            return m + self.machine_ids.index(key)
        if kind == "group" and isinstance(key, tuple):
            return 2 * m + self.groups.index(key)
        if kind == "plate" and isinstance(key, str):
            return 2 * m + len(self.groups) + self.plate_ids.index(key)
        raise ValueError(f"kind: no {kind!r} parameter for {key!r}")

    def parameter(self, kind: str, key: str | tuple[str, float]) -> tuple[float, float]:
        """(mean, sd) of a machine's compliance or gain, a group's mean factor, or a plate's factor.

        Parameters
        ----------
        kind : {"machine", "gain", "group", "plate"}
        key : machine id, (grade, thickness) or plate id
        """
        i = self._index(kind, key)
        return float(self.mean[i]), float(np.sqrt(max(self.cov[i, i], 0.0)))

    def curvatures(
        self, plate: PlateRecord, theta: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """Loaded and unloaded curvature after each of the plate's passes at the fitted parameters (or ``theta``).

        ``plate`` (its id) must be in the fit, and its passes' machines.
        """
        th = self.mean if theta is None else theta
        used = {p.machine_id for p in plate.passes}
        return plate_curvatures(
            plate,
            self.machines,
            yield_factor=float(th[self._index("plate", plate.plate_id)]),
            compliance_mm_per_mn={m: float(th[self._index("machine", m)]) for m in used},
            gain={m: float(th[self._index("gain", m)]) for m in used},
        )

    def predict(
        self,
        plate: PlateRecord,
        machine_id: str,
        displacement_mm: float,
        *,
        yield_factor: float | None = None,
        compliance_mm_per_mn: float | None = None,
    ) -> Prediction:
        """Distribution of the plate's curvature after one more pass (``plate`` must be in the fit).

        A plate with an inspected shape starts from it (:func:`latest_state`): the latest measured
        curvature plus the model's increment from where the pass that made it really loaded the plate
        (:meth:`_anchor_peak`, :meth:`_beyond_anchor`) to the new pass, floored at that shape. The
        parameters' uncertainty is propagated to first order (numerical gradient) through that
        increment (through the curvature itself for a plate never inspected), the new pass adds its
        scatter, and the next inspection its noise. A shape the model cannot place (flat, or no
        permanent set) is started from with the old peak's scatter ``N(0, s^2)``. Degrees of freedom
        (:func:`_effective_dof`): the scatter's for the scatter's share of the variance (the new
        pass's and the old peak's); the parameters' share is known, or as well as the plates' spread
        when the plate has no inspected passes of its own and its factor is not given.

        Parameters
        ----------
        plate : PlateRecord
        machine_id : str
        displacement_mm : float
        yield_factor : float, optional
            Predict for the plate's factor fixed at this value (the other parameters conditioned on it).
        compliance_mm_per_mn : float, optional
            Likewise for the compliance of ``machine_id``.
        """
        machines_used = sorted({p.machine_id for p in plate.passes} | {machine_id})
        i_plate = self._index("plate", plate.plate_id)
        idx = [self._index(kind, m) for kind in ("machine", "gain") for m in machines_used]
        idx.append(i_plate)
        fixed = {i_plate: yield_factor, self._index("machine", machine_id): compliance_mm_per_mn}
        given = {i: v for i, v in fixed.items() if v is not None}
        theta, cov = _conditioned(self.mean, self.cov, given)
        # no scatter share (Priors.scatter_share_dof off): nothing to condition
        share = (
            np.zeros_like(self.cov)
            if self.cov_scatter is None
            else _conditioned_share(self.cov, self.cov_scatter, given)
        )
        anchor = latest_state(plate, self.curvatures(plate, theta)[0], self.priors)
        sub = cov[np.ix_(idx, idx)]
        sub_s = share[np.ix_(idx, idx)]
        peak = None if anchor is None else self._anchor_peak(plate, theta, idx, sub, anchor, sub_s)
        if peak is not None and anchor is not None:
            return self._beyond_anchor(
                plate, machine_id, displacement_mm, theta, idx, (sub, sub_s), anchor, peak
            )

        def model(th: np.ndarray, d_shift: float = 0.0) -> tuple[float, float]:
            """Loaded curvature of the new pass and the predicted curvature after it (anchored)."""
            trial = plate.with_pass(RollPass(machine_id, displacement_mm + d_shift))
            kl, ku = self.curvatures(trial, th)
            if anchor is None:
                return float(kl[-1]), float(ku[-1])
            return float(kl[-1]), float(ku[-1] - ku[anchor.peak_pass])

        k_loaded, mean = model(theta)
        grad = self._gradient(lambda th: model(th)[1], theta, idx, mean)
        var_par = max(float(grad @ sub @ grad), 0.0)
        # the share the rows pinned with the scatter's weight takes the scatter's degrees of freedom
        # and, with them, the t's scale (the last round weighed the rows with nu s^2 / (nu - 2))
        tied = self._untied(min(max(float(grad @ sub_s @ grad), 0.0), var_par))
        var_par += tied[1] - tied[0]
        g_d = (model(theta, _H_D)[1] - mean) / _H_D
        var_scatter = (g_d * self.scatter_mm) ** 2
        var = 0.0
        if anchor is not None:
            # a shape the model cannot place (flat, or within the elastic range): the increment
            # starts from it with the peak pass's own scatter
            mean += anchor.curvature
            var += anchor.variance
            if k_loaded > anchor.peak_loaded:
                q = plate.passes[anchor.peak_pass]
                g_peak = (
                    self._single(plate, q.machine_id, q.top_roll_displacement_mm + _H_D, theta)[1]
                    - self._single(plate, q.machine_id, q.top_roll_displacement_mm, theta)[1]
                ) / _H_D
                var_scatter += (g_peak * self.scatter_mm) ** 2
        noise = _inspection_variance(mean, plate, self.priors)
        var += var_par + var_scatter + noise
        return self._prediction(
            plate,
            yield_factor,
            k_loaded,
            mean,
            var,
            var_par,
            var_scatter,
            var_par_scatter=tied[1],
            inspection_var=noise,
        )

    def scatter_upper_scale(self, confidence: float) -> float:
        """The scatter's variance at the ``confidence`` upper credible bound of its posterior, over
        its estimate: ``nu / chi2_{1 - confidence}(nu)`` (the scaled inverse chi-square posterior of
        the conjugate update, ``nu`` its degrees of freedom, the prior's rows included)."""
        nu = max(self.scatter_dof, 1.0)
        return float(nu / stats.chi2.ppf(1.0 - confidence, nu))

    def _untied(self, tied: float) -> tuple[float, float]:
        """A variance share weighed with the scatter's posterior mean variance ``nu s^2 / (nu - 2)``
        (the fit's last round), and the same share at the t's scale, ``s^2`` (mm)."""
        nu = max(self.scatter_dof, 3.0)
        return tied, tied * (nu - 2.0) / nu

    def _prediction(
        self,
        plate: PlateRecord,
        yield_factor: float | None,
        k_loaded: float,
        mean: float,
        var: float,
        var_par: float,
        var_scatter: float,
        floor: float = -np.inf,
        var_par_scatter: float = 0.0,
        inspection_var: float = 0.0,
    ) -> Prediction:
        """The Student-t of a prediction from its variance's shares (:func:`_effective_dof`).

        ``var_par_scatter`` is the part of the parameters' share ``var_par`` that the rows pinned
        with the estimated scatter's weight (:attr:`Fit.cov_scatter`): it is as uncertain as the
        scatter, and joins the passes' scatter (one estimated variance, the scatter's degrees of
        freedom); the rest of ``var_par`` is known (the plate has passes of its own, or its factor is
        given) or as well as the plates' spread."""
        own = self.rows_per_plate.get(plate.plate_id, 0) > 0 or yield_factor is not None
        tied = min(max(var_par_scatter, 0.0), var_par)
        dof = _effective_dof(
            var,
            (var_scatter + tied, self.scatter_dof),
            (var_par - tied, np.inf if own else self.spread_dof),
        )
        return Prediction(
            k_loaded,
            mean,
            float(np.sqrt(var)),
            dof,
            float(np.sqrt(var_scatter)),
            floor,
            inspection_var,
        )

    def _single(
        self, plate: PlateRecord, machine_id: str, displacement_mm: float, theta: np.ndarray
    ) -> tuple[float, float]:
        """Loaded and unloaded curvature of the plate after one pass from flat (1/mm): by the
        history rule, its shape after any pass that loads it beyond every earlier one."""
        one = PlateRecord(plate.plate_id, plate.target, (RollPass(machine_id, displacement_mm),))
        kl, ku = self.curvatures(one, theta)
        return float(kl[0]), float(ku[0])

    def _gradient(
        self, f: Callable[[np.ndarray], float], theta: np.ndarray, idx: list[int], f0: float
    ) -> np.ndarray:
        """Forward-difference gradient of ``f`` over the parameters ``idx`` (machines' compliances
        and gains, then the plate's factor last)."""
        grad = np.zeros(len(idx))
        for j, i in enumerate(idx):
            step = _H_C if j < len(idx) - 1 else _H_F
            th = theta.copy()
            th[i] += step
            grad[j] = (f(th) - f0) / step
        return grad

    def _anchor_peak(
        self,
        plate: PlateRecord,
        theta: np.ndarray,
        idx: list[int],
        cov: np.ndarray,
        anchor: State,
        cov_s: np.ndarray | None = None,
    ) -> _Peak | None:
        """Where the pass that made the plate's latest shape really loaded it (module docstring).

        The pass's displacement error ``x`` (mm) is what its setting, at the parameters ``theta``,
        needs to give the measured shape: ``u(theta, d_p + x) = k_a`` (``u`` the curvature after one
        pass, ``k_a`` the shape's). It is the scatter the fit attributes to that pass, and it moves
        with the parameters: ``dx/dtheta = -(du/dtheta) / (du/dd)``, so its variance is the
        parameters' (``cov`` over ``idx``). Passes after it that by the model loaded the plate
        beyond it but left the shape unchanged (``anchor.unchanged``) each say ``x - e_j >= L_j`` (the
        mm the model put them beyond it, ``e_j ~ N(0, s^2)`` their own error, independent): ``x``
        is then conditioned on all of them (:func:`_stalled_peak`).

        Returns None when the shape is not past the elastic range (flat, or no plastic set: the
        model cannot place its peak).
        """
        q = plate.passes[anchor.peak_pass]
        m, d_p, k_a = q.machine_id, q.top_roll_displacement_mm, anchor.curvature
        if k_a <= 0:
            return None
        x = 0.0
        for _ in range(20):
            ku = self._single(plate, m, d_p + x, theta)[1]
            g = (self._single(plate, m, d_p + x + _H_D, theta)[1] - ku) / _H_D
            if not g > 0:
                return None
            step = (k_a - ku) / g
            x += float(np.clip(step, -5.0, 5.0))
            if abs(step) < 1e-6:
                break
        else:
            return None
        ku0 = self._single(plate, m, d_p + x, theta)[1]
        g_peak = (self._single(plate, m, d_p + x + _H_D, theta)[1] - ku0) / _H_D
        dx = -self._gradient(lambda th: self._single(plate, m, d_p + x, th)[1], theta, idx, ku0)
        dx /= g_peak
        v_x = max(float(dx @ cov @ dx), 0.0)
        mean_x, var_x = x, v_x
        if anchor.unchanged:
            kl = self.curvatures(plate, theta)[0]
            slope = (
                self._single(plate, m, d_p + _H_D, theta)[0] - self._single(plate, m, d_p, theta)[0]
            ) / _H_D
            if slope > 0:
                lower = [float(kl[j] - kl[anchor.peak_pass]) / slope for j in anchor.unchanged]
                mean_x, var_x = _stalled_peak(x, v_x, lower, self.scatter_mm)
        v_s = 0.0 if cov_s is None else min(max(float(dx @ cov_s @ dx), 0.0), v_x)
        return _Peak(m, d_p, x, mean_x, v_x, var_x, g_peak, v_s)

    def _beyond_anchor(
        self,
        plate: PlateRecord,
        machine_id: str,
        displacement_mm: float,
        theta: np.ndarray,
        idx: list[int],
        covs: tuple[np.ndarray, np.ndarray],
        anchor: State,
        peak: _Peak,
    ) -> Prediction:
        """A prediction from the plate's latest shape whose peak :meth:`_anchor_peak` placed.

        A pass that does not load the plate beyond that peak leaves the shape (its inspections' noise);
        one that does gives the shape of that pass alone (the history rule): the measured shape plus
        the model's increment from the peak, ``k_a + u(d) - u(d_p + x)``. Its variance: the
        parameters' propagated through ``u(d) - u(d_p + x(theta))``, i.e. through ``u(d)`` itself
        (``x`` moves with them), less what the unchanged passes told about ``x``; the new pass's
        scatter; the new inspection's noise.
        """
        cov, cov_s = covs
        k_loaded, ku_new = self._single(plate, machine_id, displacement_mm, theta)
        ku_peak = self._single(plate, peak.machine_id, peak.displacement_mm + peak.mean_x, theta)[1]
        mean = anchor.curvature + ku_new - ku_peak
        grad = self._gradient(
            lambda th: self._single(plate, machine_id, displacement_mm, th)[1], theta, idx, ku_new
        )
        var_par = max(float(grad @ cov @ grad) - peak.g_peak**2 * (peak.var_fit - peak.var_x), 0.0)
        # the old peak's share is that pass's scatter, seen through the fit: it takes the scatter's
        # degrees of freedom, not the known share's, and with them the t's scale: the fit weighed
        # the rows with the scatter's posterior mean variance nu s^2 / (nu - 2), which the t's
        # tails already carry
        var_peak = min(peak.g_peak**2 * peak.var_x, var_par)
        g_d = (self._single(plate, machine_id, displacement_mm + _H_D, theta)[1] - ku_new) / _H_D
        var_scatter = (g_d * self.scatter_mm) ** 2 + self._untied(var_peak)[1]
        var_par -= var_peak
        # of the rest, the share the rows pinned with the scatter's weight (a machine's gain and
        # compliance from its plates, the plate's factor beyond its old peak) likewise
        tied = self._untied(
            min(
                max(float(grad @ cov_s @ grad) - peak.g_peak**2 * peak.var_fit_scatter, 0.0),
                var_par,
            )
        )
        var_par += tied[1] - tied[0]
        noise = _inspection_variance(mean, plate, self.priors)
        var = var_par + var_scatter + noise
        return self._prediction(
            plate,
            None,
            k_loaded,
            mean,
            var,
            var_par,
            var_scatter,
            floor=anchor.curvature,
            var_par_scatter=tied[1],
            inspection_var=noise,
        )

    def yield_factor_quantile(self, plate_id: str, p: float) -> float:
        """Quantile of a plate's factor (Student-t: the plates' spread's degrees of freedom when it has no
        inspected passes, else the scatter's)."""
        mean, sd = self.parameter("plate", plate_id)
        dof = self.scatter_dof if self.rows_per_plate.get(plate_id, 0) else self.spread_dof
        return float(mean + sd * stats.t.ppf(p, dof))


def _stalled_peak(
    x: float, v_x: float, lower: Sequence[float], scatter_mm: float
) -> tuple[float, float]:
    """Mean and variance of the old peak's displacement error ``x`` (mm) given the passes that left
    its shape unchanged (:meth:`Fit._anchor_peak`).

    ``x ~ N(x, v_x)`` as the parameters place it; each unchanged pass ``j``, ``L_j`` mm beyond the
    peak by the model with its own error ``e_j ~ N(0, s^2)``, says ``x - e_j > L_j``, with the
    likelihood ``Phi((x - L_j) / s)``. The passes' errors are independent, so the posterior is the
    prior times their product (on a grid). Before, ``x`` was conditioned on the deepest pass alone
    (``x - e > max L_j``, a truncated normal): exact for one unchanged pass, but two or three of them
    at nearly the same depth said no more than the deepest, and the next pass was predicted to move
    the plate more than it did (the creeping plates at a 0.2 mm scatter).
    """
    if not lower or v_x <= 0 or scatter_mm <= 0:
        return x, v_x
    sd_x = float(np.sqrt(v_x))
    lo = min(x - 8.0 * sd_x, min(lower) - 8.0 * scatter_mm)
    hi = max(x + 8.0 * sd_x, max(lower) + 8.0 * scatter_mm)
    grid = np.linspace(lo, hi, 4001)
    log_p = -0.5 * ((grid - x) / sd_x) ** 2
    for bound in lower:
        log_p = log_p + stats.norm.logcdf((grid - bound) / scatter_mm)
    w = np.exp(log_p - log_p.max())
    w /= w.sum()
    mean = float(np.dot(w, grid))
    return mean, max(float(np.dot(w, (grid - mean) ** 2)), 0.0)


#: Degrees of freedom of a prediction whose variance is all known (a Student-t that is a normal).
_KNOWN_DOF = 1e6


def _effective_dof(total: float, *parts: tuple[float, float]) -> float:
    """Welch-Satterthwaite degrees of freedom of a variance ``total`` whose ``parts`` (variance, dof) are
    estimated; the rest of it is known. A prior's share (a fresh machine's gain) keeps its normal
    tails instead of taking the few degrees of freedom of the scatter's estimate."""
    spread = sum(v * v / nu for v, nu in parts if v > 0 and np.isfinite(nu))
    return _KNOWN_DOF if spread <= 0 else float(min(total * total / spread, _KNOWN_DOF))


def _conditioned(
    theta: np.ndarray, cov: np.ndarray, fixed: Mapping[int, float]
) -> tuple[np.ndarray, np.ndarray]:
    """The Gaussian posterior ``(theta, cov)`` conditioned on the parameters ``fixed`` (index: value)."""
    if not fixed:
        return theta, cov
    idx = list(fixed)
    gain = cov[:, idx] @ np.linalg.pinv(cov[np.ix_(idx, idx)])
    theta = theta + gain @ (np.array([fixed[i] for i in idx]) - theta[idx])
    return theta, cov - gain @ cov[idx, :]


@dataclass(frozen=True)
class State:
    """One shape of a plate that its inspections saw (where a prediction of its next pass starts).

    Attributes
    ----------
    pass_index : int
        The latest inspected pass of that shape.
    peak_pass : int
        The pass that gave the shape: the one that loaded the plate most before it.
    peak_loaded : float
        That pass's loaded curvature, 1/mm.
    curvature : float
        The mean measured curvature of the inspections of that shape, 1/mm.
    inspections : int
        How many were averaged.
    unchanged : tuple of int
        Passes after ``peak_pass`` that the model says loaded the plate beyond it, but whose
        inspection found the shape unchanged (:func:`plate_states`): the peak pass really loaded
        the plate further than its setting says.
    variance : float
        Variance of ``curvature`` (the inspections' own, :func:`inspection_variance`, inverse-variance
        weighted), 1/mm^2.
    """

    pass_index: int
    peak_pass: int
    peak_loaded: float
    curvature: float
    inspections: int
    unchanged: tuple[int, ...] = ()
    variance: float = 0.0


#: A pass that may have loaded the plate beyond its peak (by the model, at least as far) left the shape
#: unchanged when its inspection exceeds the shape's by less than this many sd of the two
#: inspections' difference.
UNCHANGED_Z = 2.0


def plate_states(plate: PlateRecord, loaded: np.ndarray, priors: Priors) -> list[State]:
    """The shapes a plate's inspections saw, in order, given its passes' loaded curvatures.

    A pass makes a new shape when it loads the plate at least as far as every earlier pass (the
    history rule; a pass repeating the peak's setting may go beyond it by its scatter), unless its
    inspection says otherwise: a pass a little deeper than the peak (by its setting) can still fall
    short of it, the peak pass's own displacement having scattered upwards. Such a pass's inspection
    joins the shape it did not change and is listed in :attr:`State.unchanged`.
    """
    states: list[State] = []
    ks: list[float] = []
    ws: list[float] = []
    unchanged: list[int] = []
    peak_pass, last, peak = -1, -1, 0.0

    def close() -> None:
        if ks:
            k_state, var_state = _weighted(ks, ws)
            states.append(
                State(last, peak_pass, peak, k_state, len(ks), tuple(unchanged), var_state)
            )

    for j, q in enumerate(plate.passes):
        k = (
            None
            if q.measured_radius_mm is None
            else measured_curvature(plate, q.measured_radius_mm)
        )
        var = None if k is None else inspection_variance(plate, j, priors)
        if loaded[j] >= peak * (1 - 1e-9):
            if k is not None and var is not None and ks and _unchanged(k, var, ks, ws):
                unchanged.append(j)
            else:
                close()
                peak_pass, peak, ks, ws, unchanged = j, float(loaded[j]), [], [], []
        if k is not None and var is not None:
            ks.append(k)
            ws.append(1.0 / var)
            last = j
    close()
    return states


def _weighted(ks: list[float], weights: list[float]) -> tuple[float, float]:
    """Inverse-variance weighted mean of inspections of one shape and its variance, 1/mm and 1/mm^2."""
    w = np.asarray(weights)
    return float(np.dot(w, ks) / w.sum()), float(1.0 / w.sum())


def _unchanged(k: float, var: float, ks: list[float], weights: list[float]) -> bool:
    """An inspection ``k`` (variance ``var``) after a pass that may have loaded the plate beyond its
    peak found the shape inspected as ``ks`` (inverse variances ``weights``; :data:`UNCHANGED_Z`)."""
    k_state, var_state = _weighted(ks, weights)
    return bool(k - k_state < UNCHANGED_Z * np.sqrt(var_state + var))


def inspection_variance(plate: PlateRecord, index: int, priors: Priors) -> float:
    """Variance of the mid-surface curvature the inspection after pass ``index`` measured, 1/mm^2.

    With the inspection's own standard uncertainty ``u`` of the radius
    (:attr:`RollPass.radius_uncertainty_mm`) the curvature's relative sd is ``u / R`` (``R`` the
    measured mid-surface radius); without it (older results, a flat plate) the model's constant:
    ``Priors.radius_noise`` relative and ``Priors.sagitta_noise_mm`` absolute. An inspection that is not
    capable for the tolerance (:attr:`RollPass.capable`) is taken as no better than one at the
    capability limit, a test uncertainty ratio of 4: an expanded uncertainty of a quarter of the
    tolerance band, ``band / 4`` with ``band = 8 tol / w^2``, so a standard one of ``band / 8``.

    Raises
    ------
    ValueError
        Pass ``index`` was not inspected.
    """
    q = plate.passes[index]
    if q.measured_radius_mm is None:
        raise ValueError(f"passes[{index}]: expected an inspected pass, got no measured radius")
    k = measured_curvature(plate, q.measured_radius_mm)
    if q.radius_uncertainty_mm is not None and k > 0:
        var = (q.radius_uncertainty_mm * k * k) ** 2
    else:
        var = _inspection_variance(k, plate, priors)
    if not q.capable:
        w = plate.target.width_mm
        var = max(var, (plate.target.tolerance_mm / (w * w)) ** 2)
    return float(var)


def latest_state(plate: PlateRecord, loaded: np.ndarray, priors: Priors) -> State | None:
    """The plate's latest inspected shape (:func:`plate_states`); None: never inspected."""
    states = plate_states(plate, loaded, priors)
    return states[-1] if states else None


def measured_curvature(plate: PlateRecord, radius_mm: float) -> float:
    """Mid-surface curvature of the plate from an inspected radius of its target's surface (``inf``: 0)."""
    if np.isinf(radius_mm):
        return 0.0
    r_mid = plate.target.mid_radius_mm(radius_mm)
    return 1.0 / r_mid if r_mid > 0 else np.inf


@dataclass(frozen=True)
class _Rows:
    """The inspected states a round fits: pass index, observed curvature, its sd, plate index."""

    state_pass: np.ndarray
    state_obs: np.ndarray
    sd_row: np.ndarray
    state_plate: np.ndarray


@dataclass(frozen=True)
class _Prior:
    """Compliance and group priors (mean, sd), the plates' spread about their group, the groups."""

    mu: np.ndarray
    sd: np.ndarray
    spread: float
    plate_group: np.ndarray


def _solve_round(
    curvatures: Callable[..., tuple[np.ndarray, np.ndarray, np.ndarray]],
    theta: np.ndarray,
    rows: _Rows,
    prior: _Prior,
    sizes: tuple[int, int, int],
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One round of :func:`fit`: bounded least squares with the round's variances; (theta, cov,
    J_rows), the data rows' weighted Jacobian at the optimum (for :func:`_leverage` and
    :func:`_scatter_share`)."""
    M, G, P = sizes
    n_rows = len(rows.state_pass)
    state_pass, state_obs, sd_row, state_plate = (
        rows.state_pass,
        rows.state_obs,
        rows.sd_row,
        rows.state_plate,
    )
    prior_mu, prior_sd, spread, plate_group = prior.mu, prior.sd, prior.spread, prior.plate_group

    def residuals(th: np.ndarray) -> np.ndarray:
        k = curvatures(th)[2]
        return np.concatenate(
            [
                (k[state_pass] - state_obs) / sd_row,
                (th[: M + G] - prior_mu) / prior_sd,
                (th[M + G :] - th[plate_group]) / spread,
            ]
        )

    def jacobian(th: np.ndarray) -> np.ndarray:
        J = np.zeros((n_rows + M + G + P, M + G + P))
        k = curvatures(th)[2]
        for m in range(M):
            t2 = th.copy()
            t2[m] += _H_C
            J[:n_rows, m] = (curvatures(t2)[2] - k)[state_pass] / _H_C / sd_row
        t2 = th.copy()
        t2[M + G :] += _H_F
        dk = (curvatures(t2)[2] - k)[state_pass] / _H_F / sd_row
        J[np.arange(n_rows), M + G + state_plate] = dk
        J[n_rows + np.arange(M + G), np.arange(M + G)] = 1.0 / prior_sd
        J[n_rows + M + G + np.arange(P), M + G + np.arange(P)] = 1.0 / spread
        J[n_rows + M + G + np.arange(P), plate_group] = -1.0 / spread
        return J

    sol = optimize.least_squares(
        residuals,
        theta,
        jac=jacobian,
        method="trf",
        x_scale=1.0,
        bounds=(
            np.concatenate([np.full(M, -np.inf), np.full(G + P, 0.3)]),
            np.concatenate([np.full(M, np.inf), np.full(G + P, 3.0)]),
        ),
    )
    theta = sol.x
    J = jacobian(theta)
    cov = np.linalg.pinv(J.T @ J)
    return theta, cov, J[:n_rows]


def _scatter_share(J_rows: np.ndarray, cov: np.ndarray, share: np.ndarray) -> np.ndarray:
    """The part of the parameters' covariance that scales with the pass scatter's variance,
    ``d cov / d log sigma_d^2``, 1 per unit (n, n).

    ``cov = (J^T J)^-1`` with the rows weighed by their variances ``v_i = m_i + s_i`` (``s_i`` the
    scatter's part, ``share = s_i / v_i``); scaling every ``s_i`` by ``lambda`` gives ``d (J^T J) /
    d log lambda = -sum_i share_i J_i J_i^T`` at ``lambda = 1``, so ``d cov / d log lambda = cov (J^T
    diag(share) J) cov``. A parameter pinned by rows that are all scatter (a plate's factor from its
    own passes, a machine's gain from its plates) has it equal to its variance: it is as uncertain as
    the scatter's estimate; one held by its prior (a fresh machine's gain) or by the inspections' noise
    has ~0.
    """
    middle = (J_rows * share[:, None]).T @ J_rows
    scatter_cov: np.ndarray = cov @ middle @ cov
    return scatter_cov


def _conditioned_share(
    cov: np.ndarray, share: np.ndarray, fixed: Mapping[int, float]
) -> np.ndarray:
    """The scatter's share (:func:`_scatter_share`) of the covariance conditioned on the parameters
    ``fixed`` (:func:`_conditioned`): the derivative of ``C - C_xF C_FF^-1 C_Fx``."""
    if not fixed:
        return share
    idx = list(fixed)
    gain = cov[:, idx] @ np.linalg.pinv(cov[np.ix_(idx, idx)])
    out: np.ndarray = (
        share
        - share[:, idx] @ gain.T
        - gain @ share[idx, :]
        + gain @ share[np.ix_(idx, idx)] @ gain.T
    )
    return out


def _leverage(J_rows: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """Each data row's leverage, the diagonal of the hat matrix over the rows, ``J_i cov J_i^T``
    (``J`` the weighted Jacobian, the priors in ``cov``).

    A plate's factor fitted to one row takes that row whole (leverage ~1, its residual ~0); the
    machine's compliance and gain and the groups' means take a share of every row. A row's squared
    residual is short of its variance by that share (:func:`_scatter_estimate`).
    """
    leverage: np.ndarray = np.einsum("ij,jk,ik->i", J_rows, cov, J_rows)
    return leverage


def _peaks(loaded: np.ndarray, starts: np.ndarray) -> np.ndarray:
    """Each pass's plate's largest loaded curvature so far (plates' passes contiguous from ``starts``)."""
    peak = [np.maximum.accumulate(loaded[a:b]) for a, b in pairwise(starts)]
    return np.concatenate(peak) if peak else loaded


def _inspection_variance(curvature: float, plate: PlateRecord, priors: Priors) -> float:
    w = plate.target.width_mm
    return (priors.radius_noise * curvature) ** 2 + (8.0 * priors.sagitta_noise_mm / (w * w)) ** 2


def fit(
    plates: Sequence[PlateRecord],
    machines: Mapping[str, Machine],
    priors: Priors = Priors(),
    *,
    also_machines: Sequence[str] = (),
) -> Fit:
    """Fit compliances, group yield factors and plate yield factors to the plates' inspected passes.

    Parameters
    ----------
    plates : sequence of PlateRecord
        Distinct plate ids. Plates without passes still get a factor (their group's distribution).
    machines : mapping of machine id to Machine
        Every machine the passes name.
    priors : Priors
    also_machines : sequence of str
        Machines to give a compliance even if no pass names them (the next pass's machine).

    Returns
    -------
    Fit

    Raises
    ------
    ValueError
        Duplicate plate ids, an unknown machine, an inspected radius tighter than half the thickness.
    """
    ids, machine_ids = _checked_ids(plates, machines, also_machines)
    groups = tuple(sorted({p.group for p in plates}))
    # theta: compliances and gains (the machine block, 2 per machine), group means, plate factors
    m_ = len(machine_ids)
    M, G, P = 2 * m_, len(groups), len(plates)

    pass_plate, pass_machine, d, setup, starts = _pass_rows(plates, machines, machine_ids)
    plate_group = np.array([M + groups.index(p.group) for p in plates], dtype=int)

    prior_mu, prior_sd = _prior_block(m_, G, priors)
    x0 = np.concatenate([prior_mu, np.full(P, priors.yield_factor)])

    curvatures = _pass_curvatures(setup, d, pass_plate + M + G, pass_machine, m_, starts)
    # states: the passes after which an inspection saw a new shape (nominal parameters decide which pass
    # raised the peak, the inspections whether it did), with the mean of their inspections
    state_pass, state_obs, meas_var, state_plate = _inspected_states(
        plates, starts, curvatures(x0)[0], priors
    )
    plates_with_rows = np.unique(state_plate)
    # the rows' degrees of freedom for the scatter: the rows less the plates' factors, until a
    # round's fit gives the rows' leverage (:func:`_leverage`)
    dof_rows = float(max(len(state_pass) - len(plates_with_rows), 0))

    scatter, spread = priors.scatter_mm, priors.plate_spread
    theta = x0
    for round_ in range(_ROUNDS):
        ku = curvatures(theta)[2]
        g = (curvatures(theta, _H_D)[2] - ku)[state_pass] / _H_D
        # the last round weighs the rows with the scatter's posterior mean variance, nu s^2 / (nu - 2)
        # (nu its degrees of freedom, at least 3): with few rows the parameters' covariance carries
        # the doubt about the scatter it was weighed with
        nu = max(priors.scatter_weight + dof_rows, 3.0)
        inflate = nu / (nu - 2.0) if round_ == _ROUNDS - 1 else 1.0
        sd_row = np.sqrt(meas_var + inflate * (g * scatter) ** 2)
        theta, cov, J_rows = _solve_round(
            curvatures,
            theta,
            _Rows(state_pass, state_obs, sd_row, state_plate),
            _Prior(prior_mu, prior_sd, spread, plate_group),
            (M, G, P),
        )
        if round_ == _ROUNDS - 1:
            cov_scatter = (
                _scatter_share(J_rows, cov, inflate * (g * scatter) ** 2 / sd_row**2)
                if priors.scatter_share_dof
                else None
            )
            break
        leverage = _leverage(J_rows, cov)
        # variance updates (module docstring)
        r2 = (curvatures(theta)[2][state_pass] - state_obs) ** 2
        scatter, dof_rows = _scatter_estimate(r2, meas_var, g, leverage, scatter, priors)
        spread = _updated_spread(theta, cov, plate_group, plates_with_rows, M + G, priors)
    rows_per_plate = {plates[i].plate_id: int(np.sum(state_plate == i)) for i in range(P)}
    return Fit(
        machine_ids,
        groups,
        tuple(ids),
        theta,
        cov,
        scatter,
        spread,
        len(state_pass),
        rows_per_plate,
        priors.scatter_weight + dof_rows,
        priors.plate_spread_weight + len(plates_with_rows),
        {m: machines[m] for m in machine_ids},
        priors,
        cov_scatter,
    )


def _pass_curvatures(
    setup: PassSetup,
    d: np.ndarray,
    plate_param: np.ndarray,
    pass_machine: np.ndarray,
    n_machines: int,
    starts: np.ndarray,
) -> Callable[..., tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """The passes' curvatures as a function of the parameters ``theta`` (and a shift of every
    displacement, ``d_shift``): each pass's loaded curvature, the largest so far, the curvature after
    it. ``plate_param``: each pass's plate factor's index in ``theta``; the machines' compliances and
    gains are its first ``2 * n_machines`` entries."""

    def curvatures(
        theta: np.ndarray, d_shift: float = 0.0
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        f = theta[plate_param]
        kl = setup.loaded_curvature(
            d + d_shift, f, theta[pass_machine], theta[n_machines + pass_machine]
        )
        peak = _peaks(kl, starts)
        return kl, peak, setup.unloaded_curvature(peak, f)

    return curvatures


def _prior_block(n_machines: int, n_groups: int, priors: Priors) -> tuple[np.ndarray, np.ndarray]:
    """Prior means and sds of the machines' compliances and gains and the groups' mean factors, in
    the parameters' order (the plates' factors are tied to their groups instead)."""
    mu = np.concatenate(
        [
            np.full(n_machines, priors.compliance_mm_per_mn),
            np.ones(n_machines),
            np.full(n_groups, priors.yield_factor),
        ]
    )
    sd = np.concatenate(
        [
            np.full(n_machines, priors.compliance_sd_mm_per_mn),
            np.full(n_machines, priors.gain_sd),
            np.full(n_groups, priors.yield_factor_sd),
        ]
    )
    return mu, sd


def _inspected_states(
    plates: Sequence[PlateRecord],
    starts: np.ndarray,
    loaded: np.ndarray,
    priors: Priors,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The plates' shapes (:func:`plate_states`) as the fit's rows.

    ``loaded`` are the nominal loaded curvatures, one per pass, plates contiguous from ``starts``.
    Returns each shape's pass index (the pass that gave it, among all passes), mean measured
    curvature, its variance (:attr:`State.variance`) and plate index (arrays of one length).

    Raises
    ------
    ValueError
        An inspected radius tighter than half the plate's thickness.
    """
    state_pass: list[int] = []
    state_obs: list[float] = []
    state_var: list[float] = []
    state_plate: list[int] = []
    for i, p in enumerate(plates):
        for q in p.passes:
            if q.measured_radius_mm is not None and not np.isfinite(
                measured_curvature(p, q.measured_radius_mm)
            ):
                raise ValueError(
                    f"measured_radius_mm: expected more than half the thickness, "
                    f"got {q.measured_radius_mm!r} (plate {p.plate_id})"
                )
        a, b = starts[i], starts[i + 1]
        for state in plate_states(p, loaded[a:b], priors):
            state_pass.append(a + state.peak_pass)
            state_obs.append(state.curvature)
            state_var.append(state.variance)
            state_plate.append(i)
    return (
        np.array(state_pass, dtype=int),
        np.array(state_obs),
        np.array(state_var),
        np.array(state_plate, dtype=int),
    )


def _scatter_estimate(
    r2: np.ndarray,
    meas_var: np.ndarray,
    g: np.ndarray,
    leverage: np.ndarray,
    scatter: float,
    priors: Priors,
) -> tuple[float, float]:
    """The pass scatter re-estimated with its prior, and the rows' degrees of freedom (module
    docstring): ``(sigma_d, n)``, mm and rows.

    Row ``i`` (squared residual ``r2``, inspection variance ``m``, sensitivity ``g`` per mm, leverage
    ``h``) has ``E r2 = (1 - h) (m + g^2 sigma_d^2)``, so ``(r2 - (1 - h) m) / g^2`` estimates
    ``(1 - h) sigma_d^2``. The rows are pooled with the weights of their information about the
    scatter, ``w = (g^2 sigma_d^2 / (m + g^2 sigma_d^2))^2`` (1 for a row all scatter, ~0 for one
    all inspection noise): unweighted, a thin plate's row at a large radius (``g`` small) counted as
    much as any other, and an inspection noise stated above the real one (the model's constant
    sagitta noise on a finer inspection) pulled the scatter ~30 % low, the predictions with it. The
    weights follow the estimate (a few fixed-point steps); ``n = sum w (1 - h)``, the estimate's
    degrees of freedom besides the prior's ``nu0``.
    """
    g2 = g * g
    informative = g2 > 0
    per_row = np.where(
        informative, (r2 - (1.0 - leverage) * meas_var) / np.where(informative, g2, 1.0), 0.0
    )
    free = np.clip(1.0 - leverage, 0.0, 1.0)
    var, n = scatter**2, 0.0
    for _ in range(8):
        share = g2 * var
        w = np.where(informative, (share / np.maximum(share + meas_var, 1e-300)) ** 2, 0.0)
        n = float(np.sum(w * free))
        data = max(float(np.sum(w * per_row)), 0.0)
        var = (priors.scatter_weight * priors.scatter_mm**2 + data) / (priors.scatter_weight + n)
    return float(np.sqrt(var)), n


def _updated_spread(
    theta: np.ndarray,
    cov: np.ndarray,
    plate_group: np.ndarray,
    plates_with_rows: np.ndarray,
    offset: int,
    priors: Priors,
) -> float:
    """The plates' spread about their groups' means re-estimated with its prior (module docstring);
    ``offset`` is the index of the first plate factor in ``theta``."""
    dev = [
        (theta[offset + i] - theta[plate_group[i]]) ** 2
        + cov[offset + i, offset + i]
        + cov[plate_group[i], plate_group[i]]
        - 2 * cov[offset + i, plate_group[i]]
        for i in plates_with_rows
    ]
    return float(
        np.sqrt(
            (priors.plate_spread_weight * priors.plate_spread**2 + float(np.sum(dev)))
            / (priors.plate_spread_weight + len(plates_with_rows))
        )
    )


def _pass_rows(
    plates: Sequence[PlateRecord], machines: Mapping[str, Machine], machine_ids: tuple[str, ...]
) -> tuple[np.ndarray, np.ndarray, np.ndarray, PassSetup, np.ndarray]:
    """One row per pass, plates contiguous: its plate index, machine index, top-roll displacement,
    the passes' setup, and where each plate's rows start (``len(plates) + 1`` offsets)."""
    pass_plate = np.array([i for i, p in enumerate(plates) for _ in p.passes], dtype=int)
    pass_machine = np.array(
        [machine_ids.index(q.machine_id) for p in plates for q in p.passes], dtype=int
    )
    d = np.array([q.top_roll_displacement_mm for p in plates for q in p.passes], dtype=np.float64)
    setup = PassSetup.of(
        [machines[q.machine_id] for p in plates for q in p.passes],
        [p for p in plates for _ in p.passes],
    )
    starts = np.concatenate([[0], np.cumsum([len(p.passes) for p in plates])])
    return pass_plate, pass_machine, d, setup, starts


def _checked_ids(
    plates: Sequence[PlateRecord], machines: Mapping[str, Machine], also_machines: Sequence[str]
) -> tuple[list[str], tuple[str, ...]]:
    """The plates' ids (distinct) and the machines to fit (sorted, each known); ValueError otherwise."""
    ids = [p.plate_id for p in plates]
    if len(set(ids)) != len(ids):
        raise ValueError("plates: expected distinct plate ids")
    machine_ids = tuple(
        sorted({q.machine_id for p in plates for q in p.passes} | set(also_machines))
    )
    unknown = [m for m in machine_ids if m not in machines]
    if unknown:
        raise ValueError(f"machine_id: no machine {unknown[0]!r} among {sorted(machines)}")
    return ids, machine_ids
