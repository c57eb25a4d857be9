"""The joint fit of point lights (LEDs) on samples of a plate of known geometry (variable projection).

Every light k is a point light (:mod:`pipeline.lights.model`) with position ``P_k`` (mm), LED axis ``a_k``
(unit, 2 degrees of freedom), beam exponent ``mu_k >= 0`` and intensity ``e_k``; sample ``I_pk`` of
surface point ``X_p`` (normal ``n_p``) under light k is modelled as

    I_pk = rho_p * E_k(X_p, n_p)

with the sample's unknown albedo (times exposure) ``rho_p``. All lights are fitted jointly
(Levenberg-Marquardt on the 7 N x 7 N normal equations, analytic Jacobian) on the residuals
``I_pk - rho_p E_k(X_p)`` with ``rho_p`` eliminated in closed form per sample (variable projection,
``rho_p = sum_k I E / sum_k E^2``): only the ratios of a sample's values matter, so any albedo
pattern cancels. Residuals stay linear in the image counts (the sensor's noise is additive), which
keeps the fit unbiased where a fit of log ratios would not be. A fit per light with the other lights
held fixed stalls far from the solution (the albedo estimate couples them); the joint fit from
nominal lights converges.

Used by the light calibration on a flat reference plate (:mod:`pipeline.lights.calibration`) and by
the lights refitted at inspection on the stereo geometry (:mod:`pipeline.lights.refinement`).

References
----------
.. [1] G. H. Golub, V. Pereyra, "The differentiation of pseudo-inverses and nonlinear least
   squares problems whose variables separate", SIAM J. Numer. Anal. 10(2), 1973.
.. [2] Y. Queau, B. Durix, T. Wu, D. Cremers, F. Lauze, J.-D. Durou, "LED-based photometric
   stereo: modeling, calibration and numerical solution", J. Math. Imaging Vis. 60, 2018.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, overload

import numpy as np

from pipeline.lights.model import REFERENCE_DISTANCE_MM, Lights

#: Parameters per light in the joint fit: position (3, mm), axis (2, tangent offsets), mu, log intensity.
_N_PARAMS = 7


@dataclass(frozen=True)
class PlatePose:
    """The reference plate's plane in one capture, from its stereo pair.

    Attributes
    ----------
    normal : (3,) float64
        Unit normal, left-camera frame, towards the cameras.
    centre_mm : (3,) float64
        Centre of the plate (the mean of its pixels' surface points), left-camera frame, mm.
    rms_mm : float
        RMS orthogonal distance (mm) of the stereo points kept by the robust fit to the plane.
    stereo_points : int
        Stereo points on the plate used by the fit.
    """

    normal: np.ndarray
    centre_mm: np.ndarray
    rms_mm: float
    stereo_points: int


@dataclass(frozen=True)
class Samples:
    """Block-mean samples of one or more captures (P samples, N lights)."""

    intensity: np.ndarray  # (P, N) fraction of full scale, dark subtracted
    points: np.ndarray  # (P, 3) mm
    normals: np.ndarray  # (P, 3)


@dataclass(frozen=True)
class _Param:
    """How the fit's parameter vector maps to lights: axis offsets in a fixed tangent basis."""

    axis0: np.ndarray  # (N, 3) unit
    tangents: np.ndarray  # (N, 2, 3) orthonormal, across axis0

    @classmethod
    def around(cls, axes: np.ndarray) -> _Param:
        """The parametrisation about ``axes`` (N, 3): a tangent basis across each."""
        tangents = np.empty((len(axes), 2, 3))
        for k, a in enumerate(axes):
            helper = np.eye(3)[int(np.argmin(np.abs(a)))]
            t1 = np.cross(a, helper)
            t1 /= np.linalg.norm(t1)
            tangents[k] = (t1, np.cross(a, t1))
        return cls(axis0=axes.copy(), tangents=tangents)

    def vector(self, lights: Lights) -> np.ndarray:
        """(N * 7,) from lights whose axes are ``axis0``."""
        x = np.zeros((lights.n, _N_PARAMS))
        x[:, :3] = lights.positions_mm
        x[:, 5] = lights.mu
        x[:, 6] = np.log(lights.intensity)
        return x.ravel()

    def axes(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Unit axes (N, 3) and the unnormalised ones' lengths (N,)."""
        p = x.reshape(-1, _N_PARAMS)
        raw = self.axis0 + p[:, 3:4] * self.tangents[:, 0] + p[:, 4:5] * self.tangents[:, 1]
        length = np.linalg.norm(raw, axis=1)
        return raw / length[:, None], length

    def lights(self, x: np.ndarray) -> Lights:
        """The point lights of a parameter vector."""
        p = x.reshape(-1, _N_PARAMS)
        axes, _ = self.axes(x)
        return Lights.points(p[:, :3], np.exp(p[:, 6]), axes=axes, mu=np.maximum(p[:, 5], 0.0))


def _geometry(
    x: np.ndarray, param: _Param, points: np.ndarray, normals: np.ndarray
) -> tuple[np.ndarray, ...]:
    """The point lights' geometry at the samples: parameters (N, 7), unit axes (N, 3) and their raw
    lengths (N,), the vectors surface -> light v (P, N, 3), their squared lengths and lengths, the
    cosine of the axis against the ray light -> surface, and ``n . v`` (each (P, N))."""
    p = x.reshape(-1, _N_PARAMS)
    axes, length = param.axes(x)
    v = p[None, :, :3] - points[:, None, :]
    d2 = np.einsum("pnc,pnc->pn", v, v)
    d = np.sqrt(d2)
    cos = -np.einsum("pnc,nc->pn", v, axes) / d
    facing = np.einsum("pnc,pc->pn", v, normals)
    return p, axes, length, v, d2, d, cos, facing


def _irradiance_of(lights: Lights, points: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """E (P, N) of point lights (with axes) at samples: :meth:`Lights.irradiance`, vectorised over the lights."""
    param = _Param(axis0=lights.axes, tangents=np.zeros((lights.n, 2, 3)))
    return _irradiance(param.vector(lights), param, points, normals, jac=False)[0]


@overload
def _irradiance(
    x: np.ndarray, param: _Param, points: np.ndarray, normals: np.ndarray, *, jac: Literal[False]
) -> tuple[np.ndarray, None]: ...


@overload
def _irradiance(
    x: np.ndarray, param: _Param, points: np.ndarray, normals: np.ndarray, *, jac: Literal[True]
) -> tuple[np.ndarray, np.ndarray]: ...


def _irradiance(
    x: np.ndarray, param: _Param, points: np.ndarray, normals: np.ndarray, *, jac: bool
) -> tuple[np.ndarray, np.ndarray | None]:
    """E (P, N) of every light at every sample and, with ``jac``, dE/d(parameters of its light) (P, N, 7)."""
    p, axes, length, v, d2, d, cos, facing = _geometry(x, param, points, normals)
    mu = p[:, 5]
    lit = (cos > 0) & (facing > 0)
    cos_c = np.where(lit, cos, 1.0)
    facing_c = np.where(lit, facing, 1.0)
    log_cos = np.log(cos_c)
    E = np.where(
        lit,
        np.exp(p[None, :, 6] + mu[None, :] * log_cos)
        * REFERENCE_DISTANCE_MM**2
        * facing_c
        / (d2 * d),
        0.0,
    )
    if not jac:
        return E, None
    G = np.empty((*E.shape, _N_PARAMS))
    inv_d2 = 1.0 / d2
    # d log E / d P = -3 v / d^2 + mu (-a / (cos d) - v / d^2) + n / (n . v)
    G[..., :3] = (
        -(3.0 + mu[None, :, None]) * v * inv_d2[..., None]
        - (mu[None, :] / (cos_c * d))[..., None] * axes[None]
        + normals[:, None, :] / facing_c[..., None]
    )
    # d log E / d a = -mu v / (d cos); da/du = (t - a (a . t)) / |raw|
    g_axis = -(mu[None, :] / (d * cos_c))[..., None] * v
    for i in range(2):
        t = param.tangents[:, i]
        da = (t - axes * np.einsum("nc,nc->n", axes, t)[:, None]) / length[:, None]
        G[..., 3 + i] = np.einsum("pnc,nc->pn", g_axis, da)
    G[..., 5] = log_cos
    G[..., 6] = 1.0
    G *= E[..., None]
    return E, G


def _lobe(
    x: np.ndarray,
    param: _Param,
    points: np.ndarray,
    normals: np.ndarray,
    exponent: float,
    *,
    jac: bool,
) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
    """The coating's lobe per unit amplitude, S (P, N), with ``jac`` dS/d(parameters of its light)
    (P, N, 7), and ``log(n . h)`` (P, N) (0 where S is 0: dS/d exponent = S log(n . h)).

    ``S_pk = e_k a_k(X_p) max(0, n_p . h_pk)^exponent`` where the light lights the sample (the same
    ``lit`` as :func:`_irradiance`), ``h = normalize(l + v)`` the half vector between the light's
    unit vector l and the unit vector v towards the camera (at the origin); the simulated cell's and
    :mod:`pipeline.lights.glare`'s lobe.
    """
    p, axes, length, v, d2, d, cos, facing = _geometry(x, param, points, normals)
    mu = p[:, 5]
    l = v / d[..., None]
    view = -points / np.linalg.norm(points, axis=1, keepdims=True)
    half = l + view[:, None, :]
    half_len = np.linalg.norm(half, axis=-1)
    h = half / half_len[..., None]
    c = np.einsum("pnc,pc->pn", h, normals)
    lit = (cos > 0) & (facing > 0) & (c > 0)
    cos_c = np.where(lit, cos, 1.0)
    c_c = np.where(lit, c, 1.0)
    base = np.where(
        lit,
        np.exp(p[None, :, 6] + mu[None, :] * np.log(cos_c)) * REFERENCE_DISTANCE_MM**2 / d2,
        0.0,
    )
    log_c = np.log(c_c)
    S = base * np.exp(exponent * log_c)
    if not jac:
        return S, None, log_c
    T = np.empty((*S.shape, _N_PARAMS))
    inv_d2 = 1.0 / d2
    # d log S / d P = -2 v / d^2 + mu (-a / (cos d) - v / d^2) + e (dc/dP) / c, with
    # dc/dP = (I - l l^T) / d (I - h h^T) / |l + v| n
    w = (normals[:, None, :] - h * c[..., None]) / half_len[..., None]
    dc = (w - l * np.einsum("pnc,pnc->pn", l, w)[..., None]) / d[..., None]
    T[..., :3] = (
        -(2.0 + mu[None, :, None]) * v * inv_d2[..., None]
        - (mu[None, :] / (cos_c * d))[..., None] * axes[None]
        + exponent * dc / c_c[..., None]
    )
    g_axis = -(mu[None, :] / (d * cos_c))[..., None] * v
    for i in range(2):
        t = param.tangents[:, i]
        da = (t - axes * np.einsum("nc,nc->n", axes, t)[:, None]) / length[:, None]
        T[..., 3 + i] = np.einsum("pnc,nc->pn", g_axis, da)
    T[..., 5] = np.log(cos_c)
    T[..., 6] = 1.0
    T *= S[..., None]
    return S, T, log_c


def lobe_of(lights: Lights, points: np.ndarray, normals: np.ndarray, exponent: float) -> np.ndarray:
    """The lobe (P, N) per unit amplitude at samples of point lights (with axes, :func:`_lobe`) or
    of distant lights (all of them, :class:`_DistantModel`)."""
    if not lights.any_point:
        model = _DistantModel(lights)
        return model.lobe(model.vector(lights), points, normals, exponent, jac=False)[0]
    param = _Param(axis0=lights.axes, tangents=np.zeros((lights.n, 2, 3)))
    return _lobe(param.vector(lights), param, points, normals, exponent, jac=False)[0]


class _PointModel:
    """Point lights in :func:`joint_fit`: 7 parameters a light (:class:`_Param`)."""

    n_params = _N_PARAMS
    log_intensity = 6

    def __init__(self, start: Lights) -> None:
        self.param = _Param.around(start.axes)

    def vector(self, lights: Lights) -> np.ndarray:
        x = self.param.vector(lights)
        self.project(x)
        return x

    def lights(self, x: np.ndarray) -> Lights:
        return self.param.lights(x)

    def project(self, x: np.ndarray) -> None:
        """Keeps mu >= 0 (in place)."""
        x[5::_N_PARAMS] = np.maximum(x[5::_N_PARAMS], 0.0)

    def irradiance(
        self, x: np.ndarray, points: np.ndarray, normals: np.ndarray, *, jac: bool
    ) -> tuple[np.ndarray, np.ndarray | None]:
        if jac:
            return _irradiance(x, self.param, points, normals, jac=True)
        return _irradiance(x, self.param, points, normals, jac=False)

    def lobe(
        self, x: np.ndarray, points: np.ndarray, normals: np.ndarray, exponent: float, *, jac: bool
    ) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
        return _lobe(x, self.param, points, normals, exponent, jac=jac)


class _DistantModel:
    """Distant lights in :func:`joint_fit_distant`: 3 parameters a light, two offsets of its direction
    across the start's (a tangent basis, as the point lights' axes) and its log intensity.

    ``E_pk = e_k max(0, n_p . d_k)`` and the lobe per unit amplitude ``S_pk = e_k max(0, n_p . h_pk)^e``
    where ``n_p . d_k > 0``, ``h = normalize(d_k + v_p)`` (v towards the camera at the origin): the
    simulated cell's and :mod:`pipeline.lights.glare`'s lobe under distant lights.
    """

    n_params = 3
    log_intensity = 2

    def __init__(self, start: Lights) -> None:
        self.param = _Param.around(start.directions)

    def vector(self, lights: Lights) -> np.ndarray:
        x = np.zeros((lights.n, 3))
        x[:, 2] = np.log(lights.intensity)
        return x.ravel()

    def _directions(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        p = x.reshape(-1, 3)
        t = self.param.tangents
        raw = self.param.axis0 + p[:, 0:1] * t[:, 0] + p[:, 1:2] * t[:, 1]
        length = np.linalg.norm(raw, axis=1)
        return raw / length[:, None], length

    def lights(self, x: np.ndarray) -> Lights:
        d, _ = self._directions(x)
        return Lights.distant(d, np.exp(x.reshape(-1, 3)[:, 2]))

    def project(self, x: np.ndarray) -> None:
        """Nothing to keep in bounds."""

    def _ddir(self, d: np.ndarray, length: np.ndarray) -> np.ndarray:
        """d(direction)/d(offsets) (N, 2, 3)."""
        t = self.param.tangents
        along = np.einsum("nc,nic->ni", d, t)[..., None] * d[:, None, :]
        out: np.ndarray = (t - along) / length[:, None, None]
        return out

    def irradiance(
        self, x: np.ndarray, points: np.ndarray, normals: np.ndarray, *, jac: bool
    ) -> tuple[np.ndarray, np.ndarray | None]:
        d, length = self._directions(x)
        e = np.exp(x.reshape(-1, 3)[:, 2])
        cos = normals @ d.T  # (P, N)
        E = np.where(cos > 0, e[None, :] * cos, 0.0)
        if not jac:
            return E, None
        G = np.empty((*E.shape, 3))
        dd = self._ddir(d, length)
        lit = (cos > 0)[..., None]
        G[..., :2] = np.where(lit, e[None, :, None] * np.einsum("pc,nic->pni", normals, dd), 0.0)
        G[..., 2] = E
        return E, G

    def lobe(
        self, x: np.ndarray, points: np.ndarray, normals: np.ndarray, exponent: float, *, jac: bool
    ) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
        d, length = self._directions(x)
        e = np.exp(x.reshape(-1, 3)[:, 2])
        view = -points / np.linalg.norm(points, axis=1, keepdims=True)
        half = d[None, :, :] + view[:, None, :]  # (P, N, 3)
        half_len = np.linalg.norm(half, axis=-1)
        h = half / half_len[..., None]
        c = np.einsum("pnc,pc->pn", h, normals)
        lit = (normals @ d.T > 0) & (c > 0)
        log_c = np.log(np.where(lit, c, 1.0))
        S = np.where(lit, e[None, :] * np.exp(exponent * log_c), 0.0)
        if not jac:
            return S, None, log_c
        T = np.empty((*S.shape, 3))
        # d log S / d d = e (I - h h^T) n / (|d + v| c)
        w = (normals[:, None, :] - h * c[..., None]) / half_len[..., None]
        dd = self._ddir(d, length)
        T[..., :2] = exponent * np.einsum("pnc,nic->pni", w, dd) / np.where(lit, c, 1.0)[..., None]
        T[..., 2] = 1.0
        T *= S[..., None]
        return S, T, log_c


_Model = _PointModel | _DistantModel


# =========================================================================== fit


@dataclass(frozen=True)
class JointFit:
    """What :func:`joint_fit` found: the lights, the residuals ``I - rho E`` (P, N), their RMS as a fraction
    of the mean sample, the standard errors of the positions (mm), log intensities and mu, the Jacobian
    evaluations, and whether (and how) it converged."""

    lights: Lights
    residuals: np.ndarray  # (P, N)
    rms: float
    position_std_mm: np.ndarray
    intensity_std: np.ndarray
    mu_std: np.ndarray
    njev: int
    success: bool
    message: str
    lobe_amplitude: float = float("nan")
    lobe_exponent: float = float("nan")


def albedo_projected(I: np.ndarray, E: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-sample albedo ``rho`` (P,) eliminated in closed form, ``S = |E_p|^2`` (P,) and the residuals (P, N)."""
    S = np.einsum("pn,pn->p", E, E)
    rho = np.einsum("pn,pn->p", I, E) / np.maximum(S, 1e-300)
    return rho, S, I - rho[:, None] * E


def joint_fit(
    start: Lights,
    data: Samples,
    *,
    fixed_mu: bool = False,
    max_iter: int = 100,
    rays: np.ndarray | None = None,
    free_origin: bool = False,
    lobe: tuple[float, float] | None = None,
) -> JointFit:
    """All lights at once: Levenberg-Marquardt on the variable-projection residuals.

    The 7 N parameters (position mm, two axis offsets, mu, log intensity per light) are solved on
    the normal equations ``(J^T J + lambda D^2) dx = -J^T r`` (D: the columns' norms), 7 N x 7 N:
    far cheaper than factorising the (P N) x 7 N Jacobian every step (as scipy's least_squares
    does). ``mu`` is kept >= 0 by projection; ``fixed_mu`` holds it at the start's
    values. The common factor of the intensities is pinned by one extra residual,
    ``w * mean(log e)``, which the data do not see (ratios).

    Parameters
    ----------
    start : Lights
        N point lights with axes, the start.
    data : Samples
        P samples of the N lights.
    fixed_mu : bool
    max_iter : int
        Most Levenberg-Marquardt steps.
    rays : (N, 3) float, optional
        Unit directions along which each light's position may move (NaN rows: free in 3-D): a light
        whose direction is known (a nominal direction from the plate's centre) keeps it, and the fit
        finds only its distance along it. Steps are taken in that subspace of the parameters.
    free_origin : bool
        With ``rays``: the rays' common origin (the point the directions were given from, the
        plate's centre, which the images' own estimate of it misses by tens of mm) moves too, as one
        shift of every light on a ray (3 parameters for all of them); the rays keep their directions.
    lobe : (exponent, amplitude), optional
        A glossy coating: the samples are modelled as ``rho_p E_pk + s S_pk`` with the lobe
        ``S`` of :func:`_lobe` (this exponent) and one amplitude ``s`` for the plate, fitted with
        the lights from the given start; ``JointFit.lobe_amplitude`` is the fitted ``s``.

    Returns
    -------
    JointFit
    """
    problem = _Problem(_PointModel(start), data, lobe is not None)
    basis = _step_basis(start.n, fixed_mu, rays, free_origin)
    return _solve(problem, start, data, basis, lobe, max_iter, rays, free_origin)


def joint_fit_distant(
    start: Lights, data: Samples, *, lobe: tuple[float, float], max_iter: int = 100
) -> JointFit:
    """All distant lights at once with the coating's lobe: :func:`joint_fit` for lights given by their
    directions (3 parameters a light, :class:`_DistantModel`) and the lobe's amplitude and exponent,
    from ``start`` and ``lobe`` (exponent, amplitude).

    ``JointFit.position_std_mm`` and ``mu_std`` are NaN (distant lights have neither).
    """
    problem = _Problem(_DistantModel(start), data, True)
    basis = np.eye(problem.n_light)
    return _solve(problem, start, data, basis, lobe, max_iter, None, False)


def _solve(
    problem: _Problem,
    start: Lights,
    data: Samples,
    basis: np.ndarray,
    lobe: tuple[float, float] | None,
    max_iter: int,
    rays: np.ndarray | None,
    free_origin: bool,
) -> JointFit:
    """Levenberg-Marquardt of ``problem`` from ``start`` (and ``lobe``) in the span of ``basis``, and the
    fit's standard errors: the shared part of :func:`joint_fit` and :func:`joint_fit_distant`."""
    x = problem.model.vector(start)
    if lobe is not None:  # the amplitude and the log exponent, after the lights
        x = np.append(x, [float(lobe[1]), np.log(float(lobe[0]))])
        basis = np.block(
            [[basis, np.zeros((len(basis), 2))], [np.zeros((2, basis.shape[1])), np.eye(2)]]
        )
    x, r, njev, success, message = _levenberg_marquardt(problem, x, basis, max_iter)
    A, _ = problem.normal_equations(x)
    njev += 1
    P, N = data.intensity.shape
    s2 = float(np.sum(r * r)) / max(P * N - P - (problem.n_par - 1), 1)
    if rays is None:
        diag = _diagonal_of_inverse(A)
    elif free_origin:  # the columns overlap: the covariance in the subspace, mapped back
        diag = _diagonal_in_subspace(A, basis)
    else:  # in the subspace the lights moved in, mapped back (NaN-free where a variance is inf)
        reduced = _diagonal_of_inverse(basis.T @ A @ basis)
        with np.errstate(invalid="ignore"):  # inf * 0 off a column's rows: masked out
            diag = np.where(basis != 0, basis**2 * reduced, 0.0).sum(axis=1)
    var = (s2 * diag[: problem.n_light]).reshape(N, problem.model.n_params)
    point = isinstance(problem.model, _PointModel)
    nan = np.full(N, np.nan)
    return JointFit(
        lights=problem.lights(x),
        residuals=r,
        rms=float(np.sqrt(np.mean(r * r)) / np.mean(data.intensity)),
        position_std_mm=np.sqrt(var[:, :3].sum(axis=1)) if point else nan,
        intensity_std=np.sqrt(var[:, problem.model.log_intensity]),
        mu_std=np.sqrt(var[:, 5]) if point else nan,
        njev=njev,
        success=success and bool(np.all(np.isfinite(x))),
        message=message,
        lobe_amplitude=float("nan") if lobe is None else float(x[-2]),
        lobe_exponent=float("nan") if lobe is None else float(np.exp(x[-1])),
    )


def _step_basis(
    n: int, fixed_mu: bool, rays: np.ndarray | None, free_origin: bool = False
) -> np.ndarray:
    """The columns (7 N, m) that span the fit's steps: every parameter, less each held ``mu``, with a
    light's three position columns replaced by its ray where ``rays`` gives one; with
    ``free_origin``, three more that shift every light on a ray alike (orthonormalised)."""
    columns = []
    for k in range(n):
        for j in range(_N_PARAMS):
            if j == 5 and fixed_mu:
                continue
            on_ray = rays is not None and bool(np.all(np.isfinite(rays[k])))
            if j < 3 and on_ray:
                if j == 0:
                    assert rays is not None
                    col = np.zeros(n * _N_PARAMS)
                    col[k * _N_PARAMS : k * _N_PARAMS + 3] = rays[k] / np.linalg.norm(rays[k])
                    columns.append(col)
                continue
            col = np.zeros(n * _N_PARAMS)
            col[k * _N_PARAMS + j] = 1.0
            columns.append(col)
    basis = np.stack(columns, axis=1)
    ray_lights = [] if rays is None else [k for k in range(n) if np.all(np.isfinite(rays[k]))]
    if not (free_origin and ray_lights):
        return basis
    shift = np.zeros((n * _N_PARAMS, 3))
    for k in ray_lights:
        shift[k * _N_PARAMS : k * _N_PARAMS + 3] = np.eye(3)
    q, _ = np.linalg.qr(np.concatenate([basis, shift], axis=1))
    return q


class _Problem:
    """The variable-projection least squares of :func:`joint_fit`: its cost and its normal equations.

    With a lobe (``lobe=True``), the parameter vector ends with its amplitude s and the log of its
    exponent, and the data are ``I - s S`` (:func:`_lobe`), whose dependence on the lights enters
    the Jacobian too.
    """

    def __init__(self, model: _Model, data: Samples, lobe: bool = False) -> None:
        self.I, self.X, self.nrm = data.intensity, data.points, data.normals
        self.P, self.N = self.I.shape
        self.lobe = lobe
        self.model = model
        self.k = model.n_params
        self.n_light = self.N * self.k
        self.n_par = self.n_light + (2 if lobe else 0)
        self.gauge_row = np.zeros(self.n_par)
        self.gauge_row[model.log_intensity : self.n_light : self.k] = 1.0 / self.N
        self.gauge_weight = float(np.sqrt(self.P) * np.mean(self.I))

    def lights(self, x: np.ndarray) -> Lights:
        """The lights of a parameter vector (without the lobe's amplitude)."""
        return self.model.lights(x[: self.n_light])

    def project(self, x: np.ndarray) -> None:
        """The lights' parameters back in bounds (in place)."""
        self.model.project(x[: self.n_light])

    def cost(self, x: np.ndarray) -> tuple[float, np.ndarray]:
        """The cost (data and gauge residuals squared) and the data residuals (P, N) at ``x``."""
        xl = x[: self.n_light]
        E, _ = self.model.irradiance(xl, self.X, self.nrm, jac=False)
        data = self.I
        if self.lobe:
            S, _, _ = self.model.lobe(xl, self.X, self.nrm, float(np.exp(x[-1])), jac=False)
            data = data - x[-2] * S
        _, _, r = albedo_projected(data, E)
        gauge = self.gauge_weight * (self.gauge_row @ x)
        return float(np.sum(r * r) + gauge * gauge), r

    def normal_equations(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """J^T J (n_par, n_par) and J^T r (n_par,) of the data and the gauge residual.

        With the albedo eliminated, ``r_pk = D_pk - rho_p E_pk`` (data ``D = I``, or ``I - s S``
        with a lobe) and ``rho_p = (D_p . E_p) / S_p`` (``S_p = |E_p|^2``), the Jacobian is
        ``J[p, k, j] = -E_pk h_pj - [k == j] q_pj`` with ``G_pj = dE_pj / d(light j's parameters)``,
        ``h_pj = G_pj (D_pj - 2 rho_p E_pj) / S_p`` and ``q_pj = rho_p G_pj`` (Golub and Pereyra's,
        exact for one linear parameter per sample); a lobe adds ``-s E_pj T_pj / S_p`` to h and
        ``s T_pj`` to q (``T = dS/d(parameters)``), and the amplitude's column is ``-S`` projected
        off ``E_p``. Its products are summed in closed form instead of forming the (P N) x 7 N
        matrix; ``E_p . r_p = 0`` leaves ``J^T r = -sum_p q_pj r_pj``.
        """
        I, P, N, n_light = self.I, self.P, self.N, self.n_light
        xl = x[:n_light]
        k = self.k
        E, G = self.model.irradiance(xl, self.X, self.nrm, jac=True)
        assert G is not None
        data, S, T, s, e, log_c = I, None, None, 0.0, 0.0, None
        if self.lobe:
            e = float(np.exp(x[-1]))
            S, T, log_c = self.model.lobe(xl, self.X, self.nrm, e, jac=True)
            s = float(x[-2])
            data = I - s * S
        rho, SE, r = albedo_projected(data, E)
        inv_se = 1.0 / np.maximum(SE, 1e-300)
        coef = (data - 2.0 * rho[:, None] * E) * inv_se[:, None]
        H3 = coef[:, :, None] * G
        Q3 = rho[:, None, None] * G
        if T is not None:
            H3 -= s * (E * inv_se[:, None])[:, :, None] * T
            Q3 += s * T
        H = H3.reshape(P, n_light)
        Q = Q3.reshape(P, n_light)
        cross = H.T @ (np.repeat(E, k, axis=1) * Q)
        A = np.zeros((self.n_par, self.n_par))
        g = np.zeros(self.n_par)
        A[:n_light, :n_light] = H.T @ (SE[:, None] * H) + cross + cross.T
        for j in range(N):
            sl = slice(j * k, (j + 1) * k)
            A[sl, sl] += Q[:, sl].T @ Q[:, sl]
        g[:n_light] = -np.einsum("pj,pj->j", Q, np.repeat(r, k, axis=1))
        if S is not None and log_c is not None:
            # the amplitude's and the log exponent's columns: -dD/d(.) projected off E_p
            cols = []
            for dD in (S, s * e * S * log_c):
                cols.append(-(dD - E * (np.einsum("pn,pn->p", dD, E) * inv_se)[:, None]))
            for i, Jc in enumerate(cols):
                col = -np.einsum("pj,pj->j", Q, np.repeat(Jc, k, axis=1))
                A[:n_light, n_light + i] = col
                A[n_light + i, :n_light] = col
                g[n_light + i] = float(np.sum(Jc * r))
                for i2, Jc2 in enumerate(cols):
                    A[n_light + i, n_light + i2] = float(np.sum(Jc * Jc2))
        A += self.gauge_weight**2 * np.outer(self.gauge_row, self.gauge_row)
        g += self.gauge_weight**2 * (self.gauge_row @ x) * self.gauge_row
        return A, g


def _levenberg_marquardt(
    problem: _Problem, x: np.ndarray, basis: np.ndarray, max_iter: int
) -> tuple[np.ndarray, np.ndarray, int, bool, str]:
    """Levenberg-Marquardt steps within the span of ``basis`` (7 N, m) from ``x`` (mu kept >= 0 by
    projection).

    Returns the parameters, the residuals there, the Jacobian evaluations, whether it converged and how.
    """
    cost, r = problem.cost(x)
    lam, njev, success, message = 1e-3, 0, False, "maximum number of iterations reached"
    for _ in range(max_iter):
        A, g = problem.normal_equations(x)
        njev += 1
        Ab, gb = basis.T @ A @ basis, basis.T @ g
        D2 = np.maximum(np.diag(Ab), 1e-12 * np.max(np.diag(Ab)))
        improved = False
        while lam < 1e12:
            try:
                step = basis @ -np.linalg.solve(Ab + lam * np.diag(D2), gb)
            except np.linalg.LinAlgError:
                lam *= 10.0
                continue
            trial = x + step
            problem.project(trial)
            new_cost, new_r = problem.cost(trial)
            if np.isfinite(new_cost) and new_cost < cost:
                improved = True
                break
            lam *= 4.0
        if not improved:
            success, message = True, "no step lowers the cost (converged)"
            break
        decrease = cost - new_cost
        moved = basis.T @ (trial - x)  # the step's coordinates (the columns are orthonormal)
        scaled_step = np.sqrt(np.sum(D2 * moved**2) / max(cost, 1e-300))
        x, cost, r = trial, new_cost, new_r
        lam = max(lam / 3.0, 1e-9)
        if decrease <= 1e-10 * cost or scaled_step < 1e-8:
            success, message = True, "converged"
            break
    return x, r, njev, success, message


def _diagonal_in_subspace(A: np.ndarray, basis: np.ndarray) -> np.ndarray:
    """diag(B (B^T A B)^+ B^T) for orthonormal columns B (7 N, m): the variances of the parameters when
    the fit moves in the span of B; ``inf`` on the parameters a null direction touches."""
    reduced = basis.T @ A @ basis
    d = np.diag(reduced).copy()
    scale = 1.0 / np.sqrt(np.maximum(d, 1e-300))
    w, V = np.linalg.eigh(reduced * scale[:, None] * scale[None, :])
    keep = w > 1e-12 * w.max()
    Vs = (V * scale[:, None])[:, keep]
    mapped = basis @ Vs  # (7 N, kept)
    diag = (mapped * mapped) @ (1.0 / w[keep])
    null = basis @ (V * scale[:, None])[:, ~keep]
    diag[np.any(np.abs(null) > 1e-3, axis=1)] = np.inf
    out: np.ndarray = diag
    return out


def _diagonal_of_inverse(A: np.ndarray) -> np.ndarray:
    """diag(A^+) of a symmetric positive semi-definite matrix, scaled to unit diagonal first.

    Columns the data do not see at all (an LED axis when ``mu = 0``) get ``inf``; a parameter that
    is not determined gets a large variance, never a zero one.
    """
    d = np.diag(A).copy()
    seen = d > 1e-300 * max(float(d.max()), 1e-300)
    out = np.full(len(d), np.inf)
    scale = 1.0 / np.sqrt(d[seen])
    As = A[np.ix_(seen, seen)] * scale[:, None] * scale[None, :]
    w, V = np.linalg.eigh(As)
    keep = w > 1e-12 * w.max()
    inv = np.where(keep, 1.0 / np.where(keep, w, 1.0), 0.0)
    diag = (V * V) @ inv
    diag[(V[:, ~keep] ** 2).sum(axis=1) > 1e-6] = np.inf  # along a null direction: undetermined
    out[seen] = diag * scale * scale
    return out


def initial_point_lights(
    given: Lights, pose: PlatePose, data: Samples, *, initial_mu: float
) -> Lights:
    """Point lights to start the joint fit from.

    Point lights the capture gives are taken as they are (an axis towards the plate's centre and
    ``initial_mu`` where none is given). A distant light (a nominal direction) becomes a point light on
    the ray from the plate's centre in its direction, aimed at the centre, with the irradiance the
    capture gives at the centre; its distance along the ray comes from a 1-D search (41 distances
    from 0.15 to 4 times the centre's distance from the camera), one distance for all of them.
    """
    c = pose.centre_mm
    n = given.n
    dirs = given.directions_at(c)
    positions = given.positions_mm.copy()
    axes = given.axes.copy()
    mu = given.mu.copy()
    distant = ~given.is_point
    at_centre = given.intensity * given.attenuation_at(
        c
    )  # irradiance at the centre, facing the light
    for k in range(n):
        if not np.isfinite(axes[k]).all():
            towards = c - positions[k] if given.is_point[k] else -dirs[k]
            axes[k] = towards / np.linalg.norm(towards)
            mu[k] = initial_mu
    intensity = given.intensity.copy()
    if not distant.any():
        return Lights.points(positions, intensity, axes=axes, mu=mu)

    # a subsample is plenty for the search
    step = max(1, len(data.intensity) // 1500)
    I, X, nrm = data.intensity[::step], data.points[::step], data.normals[::step]
    centre_distance = float(np.linalg.norm(c))

    def lights_at(t: np.ndarray) -> Lights:
        pos = positions.copy()
        pos[distant] = c + t[distant, None] * dirs[distant]
        ax = axes.copy()
        ax[distant] = -dirs[distant]
        unit = Lights.points(pos, np.ones(n), axes=ax, mu=mu)
        return unit.with_intensity(at_centre / unit.attenuation_at(c))

    def cost(t: np.ndarray) -> float:
        E = _irradiance_of(lights_at(t), X, nrm)
        _, _, r = albedo_projected(I, E)
        return float(np.sum(r * r))

    # one distance for all of them (a ring of lights at one height is the usual cell); a search per
    # light with the others fixed was tried and can settle a light in a wrong, ill-determined minimum
    t = np.full(n, np.nan)
    grid = centre_distance * np.geomspace(0.15, 4.0, 41)
    costs = []
    for value in grid:
        t[distant] = value
        costs.append(cost(t))
    t[distant] = grid[int(np.argmin(costs))]
    return lights_at(t)
