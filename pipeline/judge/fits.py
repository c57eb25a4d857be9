"""Geometric fits of a plane, a sphere and a cylinder to measured points, and the checks of a measured grid.

All points are in the left-camera frame (OpenCV: x right, y down, z forward), in mm. The camera centre
is the origin of that frame; it is used to orient normals and to give curvature a sign.

Sign convention (every function here): a curvature or radius is **positive where the surface is convex
towards the camera** (its centre of curvature lies on the far side of the surface, away from the camera)
and negative where it is concave towards the camera.

Why geometric fits: a global graph quadric ``z = a x^2 + b xy + c y^2 + ...`` takes the parabola's vertex
curvature for the circle's; over a 3 m plate that understates the radius by 2 % (cylinder, R 5 m) to
4.5 % (sphere). The fits below minimise true orthogonal distances instead, in a parametrisation by
curvature ``k = 1/R`` that stays well conditioned as ``k -> 0`` (a flat plate is ``k = 0``, not ``R = inf``).
The curvature measure of a plate (``radius_mm``, ``principal_radii_mm``) uses them: :mod:`pipeline.judge.curvature`;
the registration to the target too: :mod:`pipeline.judge.registration`.

References
----------
.. [1] Al-Sharadqah, A., Chernov, N., "Error analysis for circle fitting algorithms", Electronic Journal of
   Statistics 3 (2009) -- the curvature parametrisation of the geometric circle/sphere fit.

Kept as one module (~590 lines) on purpose: the three fits share one parametrised model
(:func:`fit_curved`) and its checks, and half of the module is their result types' documentation.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numba
import numpy as np
import numpy.typing as npt

from pipeline.solvers import robust_gauss_newton, robust_scale

#: At most this many points go into a fit; more are subsampled uniformly (every n-th point). With 0.2 mm
#: noise 20 000 points over a 3 m plate leave a radius uncertainty of ~0.005 % at R 20 m (tests check 0.05 %).
MAX_FIT_POINTS = 20_000


# --------------------------------------------------------------------------- results


@dataclass(frozen=True)
class PlaneFit:
    """Least-squares plane, left-camera frame.

    Attributes
    ----------
    normal : (3,) float64
        Unit normal pointing towards the camera (``normal . point_mm < 0``).
    point_mm : (3,) float64
        The centroid of the points (lies on the plane), mm.
    rms_mm : float
        RMS orthogonal distance of the points to the plane, mm.
    """

    normal: np.ndarray
    point_mm: np.ndarray
    rms_mm: float


@dataclass(frozen=True)
class SphereFit:
    """Geometric sphere fit, left-camera frame.

    Attributes
    ----------
    center_mm : (3,) float64
        Sphere centre, mm; ``inf`` components when the fit is exactly flat (``curvature_per_mm == 0``).
    radius_mm : float
        Unsigned radius, mm (``inf`` for a flat fit).
    curvature_per_mm : float
        Signed curvature ``+-1/radius_mm``: positive when the surface is convex towards the camera.
    rms_mm : float
        RMS orthogonal distance of the points to the sphere, mm (all points, robust loss or not).
    free_curvature_per_mm : float or None
        With ``radius_mm`` fixed: the signed curvature of the radius-free fit made first on the same
        points (what ``fit_sphere`` without a radius returns); None when the radius was free.
    """

    center_mm: np.ndarray
    radius_mm: float
    curvature_per_mm: float
    rms_mm: float
    free_curvature_per_mm: float | None = None

    @property
    def convex_towards_camera(self) -> bool:
        return self.curvature_per_mm > 0


@dataclass(frozen=True)
class CylinderFit:
    """Geometric circular-cylinder fit, left-camera frame.

    Attributes
    ----------
    axis : (3,) float64
        Unit axis direction (sign arbitrary but ``axis[1] >= 0``, pointing down the image when possible).
    point_on_axis_mm : (3,) float64
        The point of the axis closest to the centroid of the points, mm (``inf`` for a flat fit).
    radius_mm : float
        Unsigned radius, mm (``inf`` for a flat fit).
    curvature_per_mm : float
        Signed curvature ``+-1/radius_mm``: positive when convex towards the camera.
    rms_mm : float
        RMS orthogonal distance of the points to the cylinder, mm.
    free_curvature_per_mm : float or None
        With ``radius_mm`` fixed: the signed curvature of the radius-free fit made first on the same
        points (what ``fit_cylinder`` without a radius returns); None when the radius was free.
    """

    axis: np.ndarray
    point_on_axis_mm: np.ndarray
    radius_mm: float
    curvature_per_mm: float
    rms_mm: float
    free_curvature_per_mm: float | None = None

    @property
    def convex_towards_camera(self) -> bool:
        return self.curvature_per_mm > 0


class CurvedFit(NamedTuple):
    """What :func:`fit_curved` found, left-camera frame.

    Attributes
    ----------
    normal : (3,) float64
        Unit normal at ``point_mm``, pointing away from the camera; the centre of curvature is
        ``point_mm + normal / curvature_per_mm``.
    point_mm : (3,) float64
        The surface point nearest the points' centroid along the normal, mm.
    curvature_per_mm : float
        Signed curvature (+ convex towards the camera; 0: flat).
    axis : (3,) float64 or None
        Cylinder axis (unit vector); None for a sphere or plane.
    rms_mm : float
        RMS orthogonal distance of all the points to the surface, mm.
    free_curvature_per_mm : float
        Curvature of the radius-free fit made first (what the fit gives without ``radius_mm``).
    """

    normal: np.ndarray
    point_mm: np.ndarray
    curvature_per_mm: float
    axis: np.ndarray | None
    rms_mm: float
    free_curvature_per_mm: float


# --------------------------------------------------------------------------- input checks


def _check_points(
    points_mm: npt.ArrayLike, *, name: str = "points_mm", min_points: int
) -> np.ndarray:
    pts = np.asarray(points_mm, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"{name}: expected shape (M, 3), got {pts.shape}")
    if pts.shape[0] < min_points:
        raise ValueError(f"{name}: expected at least {min_points} points, got {pts.shape[0]}")
    if not np.all(np.isfinite(pts)):
        bad = int(np.count_nonzero(~np.isfinite(pts).all(axis=1)))
        raise ValueError(f"{name}: expected finite coordinates, got {bad} points with NaN/inf")
    return pts


def _check_radius(radius_mm: float | None) -> float | None:
    if radius_mm is None:
        return None
    r = float(radius_mm)
    if not math.isfinite(r) or r <= 0:
        raise ValueError(
            f"radius_mm: expected a positive finite radius in mm or None, got {radius_mm}"
        )
    return r


def check_grid(
    points_mm: npt.ArrayLike, mask: npt.ArrayLike, *, min_points: int = 10
) -> tuple[np.ndarray, np.ndarray]:
    """Check a measured surface grid and return it as float64 points and a bool mask.

    Parameters
    ----------
    points_mm : (H, W, 3) array_like
        Surface point of each pixel, left-camera frame, mm. Values outside the mask are ignored.
    mask : (H, W) array_like of bool
        True where the point is valid.
    min_points : int
        Fewest valid points accepted.

    Returns
    -------
    points_mm : (H, W, 3) float64
    mask : (H, W) bool

    Raises
    ------
    ValueError
        On a wrong shape or dtype, too few valid points, or non-finite points inside the mask.
    """
    pts = np.asarray(points_mm)
    if pts.ndim != 3 or pts.shape[2] != 3:
        raise ValueError(f"points_mm: expected shape (H, W, 3), got {pts.shape}")
    pts = pts.astype(np.float64, copy=False)
    m = np.asarray(mask)
    if m.dtype != np.bool_:
        raise ValueError(f"mask: expected a bool array, got dtype {m.dtype}")
    if m.shape != pts.shape[:2]:
        raise ValueError(f"mask: expected shape {pts.shape[:2]} to match points_mm, got {m.shape}")
    n = int(np.count_nonzero(m))
    if n < min_points:
        raise ValueError(f"mask: expected at least {min_points} valid pixels, got {n}")
    bad = _nonfinite_inside(pts, m)
    if bad:
        raise ValueError(
            f"points_mm: expected finite points inside the mask, got {bad} with NaN/inf"
        )
    return pts, m


@numba.njit(parallel=True, cache=True)
def _nonfinite_inside(points: np.ndarray, mask: np.ndarray) -> int:
    """How many points (H, W, 3) inside ``mask`` have a NaN or inf coordinate (one pass, rows in
    parallel; the grid is checked by each stage that takes it)."""
    h, w = mask.shape
    counts = np.zeros(h, np.int64)
    for i in numba.prange(h):
        c = 0
        for j in range(w):
            if mask[i, j] and not np.isfinite(points[i, j, 0] + points[i, j, 1] + points[i, j, 2]):
                c += 1
        counts[i] = c
    return int(counts.sum())


def grid_sample(points_mm: np.ndarray, mask: np.ndarray, max_points: int) -> np.ndarray:
    """Valid points of a strided sub-grid, about ``max_points`` spread evenly over the mask.

    Parameters
    ----------
    points_mm : (H, W, 3) float64, checked (see :func:`check_grid`).
    mask : (H, W) bool.
    max_points : int

    Returns
    -------
    (M, 3) float64, left-camera frame, mm; every valid point when there are at most ``max_points``.
    """
    n = int(np.count_nonzero(mask))
    step = max(1, int(math.floor(math.sqrt(n / max_points))))
    sample: np.ndarray = points_mm[::step, ::step][mask[::step, ::step]]
    return sample


def _subsample(pts: np.ndarray, max_points: int) -> np.ndarray:
    if pts.shape[0] <= max_points:
        return pts
    idx = np.linspace(0, pts.shape[0] - 1, max_points).round().astype(np.int64)
    return pts[idx]


# --------------------------------------------------------------------------- local frame


def pca_frame(pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Centroid (3,) and rows (ex, ey, ez) (3, 3) of a right-handed PCA frame of points (M, 3); ez is the
    least-variance direction and points away from the camera (``ez . centroid > 0``)."""
    c = pts.mean(axis=0)
    _, _, vt = np.linalg.svd(pts - c, full_matrices=False)
    ex, ez = vt[0], vt[2]
    if ez @ c < 0:
        ez = -ez
    ey = np.cross(ez, ex)
    return c, np.stack([ex, ey, ez])


def local_quadric(q: np.ndarray) -> np.ndarray:
    """Least-squares ``h = a0 + a1 x + a2 y + a3 x^2 + a4 xy + a5 y^2`` of local coordinates (M, 3)."""
    x, y = q[:, 0], q[:, 1]
    A = np.stack([np.ones_like(x), x, y, x * x, x * y, y * y], axis=1)
    scale = np.abs(A).max(axis=0)
    coef, *_ = np.linalg.lstsq(A / scale, q[:, 2], rcond=None)
    scaled: np.ndarray = coef / scale
    return scaled


#: Angle step (rad) of the central differences of :meth:`_CurvedModel.unpack` in its Jacobian.
_ANGLE_STEP = 1e-6


def _cross3(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``np.cross`` of two 3-vectors (the same arithmetic; np.cross costs ~10 us of overhead a call)."""
    return np.array(
        [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
    )


def _orthonormal_pair(v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    a = np.eye(3)[np.argmin(np.abs(v))]
    u1 = np.cross(v, a)
    u1 /= np.linalg.norm(u1)
    return u1, np.cross(v, u1)


def _signed_distance(w: np.ndarray, n: np.ndarray, k: float, axis: np.ndarray | None) -> np.ndarray:
    """Signed orthogonal distance of points ``p_ref + w`` to the sphere (axis None) or cylinder through
    ``p_ref`` with unit normal ``n`` there and centre ``p_ref + n / k``; exact, finite at ``k = 0`` (plane).
    Positive on the side away from the centre (for k > 0)."""
    if axis is not None:
        w = w - np.outer(w @ axis, axis)
    g = k * np.einsum("ij,ij->i", w, w) - 2.0 * (w @ n)
    sag: np.ndarray = g / (1.0 + np.sqrt(np.maximum(1.0 + k * g, 0.0)))
    return sag


@numba.njit(nogil=True, cache=True)
def _sag(
    w: np.ndarray,
    ww: np.ndarray,
    n: np.ndarray,
    ax: np.ndarray,
    cylinder: bool,
    t: float,
    k: float,
    out: np.ndarray,
) -> None:  # pragma: no cover - compiled
    """``out`` = :func:`_signed_distance` of ``w - t n`` (``_CurvedModel.residuals``) in one pass over the
    points: with ``n`` orthogonal to the axis, ``(w - t n).ax = w.ax``, ``(w - t n).n = w.n - t`` and
    ``|w - t n|^2 = |w|^2 - 2 t w.n + t^2``. ``ax`` is ignored for a sphere."""
    for i in range(w.shape[0]):
        wn = w[i, 0] * n[0] + w[i, 1] * n[1] + w[i, 2] * n[2]
        s2 = ww[i] - 2.0 * t * wn + t * t
        if cylinder:
            wa = w[i, 0] * ax[0] + w[i, 1] * ax[1] + w[i, 2] * ax[2]
            s2 -= wa * wa
        g = k * s2 - 2.0 * (wn - t)
        out[i] = g / (1.0 + math.sqrt(max(1.0 + k * g, 0.0)))


@numba.njit(nogil=True, cache=True)
def _sag_jacobian(
    w: np.ndarray,
    ww: np.ndarray,
    columns: np.ndarray,
    cylinder: bool,
    t: float,
    k: float,
    k_free: bool,
    jac: np.ndarray,
) -> None:  # pragma: no cover - compiled
    """``jac`` (M, angles + 1 [+ 1 with ``k_free``]) = the derivatives of :func:`_sag` (see
    ``_CurvedModel.jacobian``): ``columns`` holds the normal, for a cylinder the axis, then per angle the
    normal's derivative and, for a cylinder, the axis's. One pass over the points."""
    n_cols = columns.shape[0]
    first = 2 if cylinder else 1  # the first derivative column
    per = 2 if cylinder else 1
    n_angles = (n_cols - first) // per
    wc = np.empty(n_cols)
    for i in range(w.shape[0]):
        for c in range(n_cols):
            wc[c] = w[i, 0] * columns[c, 0] + w[i, 1] * columns[c, 1] + w[i, 2] * columns[c, 2]
        wn = wc[0]
        s2 = ww[i] - 2.0 * t * wn + t * t
        if cylinder:  # |w - t n|^2 less its part along the axis
            s2 -= wc[1] * wc[1]
        g = k * s2 - 2.0 * (wn - t)
        q2 = 1.0 + k * g
        if q2 > 0.0:
            q = math.sqrt(q2)
            d_sag_dg = (1.0 + q - 0.5 * k * g / q) / ((1.0 + q) * (1.0 + q))
            d_sag_dk = -0.5 * g * g / (q * (1.0 + q) * (1.0 + q))
        else:  # beyond the reach the sag is clamped to g: d sag / d g = 1
            d_sag_dg, d_sag_dk = 1.0, 0.0
        for a in range(n_angles):
            d_g = -2.0 * (k * t + 1.0) * wc[first + per * a]
            if cylinder:
                d_g -= 2.0 * k * wc[1] * wc[first + per * a + 1]
            jac[i, a] = d_sag_dg * d_g
        jac[i, n_angles] = d_sag_dg * (2.0 + 2.0 * k * (t - wn))
        if k_free:
            jac[i, n_angles + 1] = d_sag_dg * s2 + d_sag_dk


# --------------------------------------------------------------------------- plane


def fit_plane(points_mm: npt.ArrayLike) -> PlaneFit:
    """Least-squares (total least squares) plane through 3-D points.

    Parameters
    ----------
    points_mm : (M, 3) array_like of float
        Points in the left-camera frame, mm; M >= 3.

    Returns
    -------
    PlaneFit
        Normal towards the camera, centroid, RMS orthogonal distance (mm).

    Raises
    ------
    ValueError
        Wrong shape, fewer than 3 points or non-finite values.
    """
    pts = _check_points(points_mm, min_points=3)
    c, frame = pca_frame(pts)
    normal = -frame[2]  # towards the camera
    d = (pts - c) @ normal
    return PlaneFit(normal=normal, point_mm=c, rms_mm=float(np.sqrt(np.mean(d * d))))


# --------------------------------------------------------------------------- sphere and cylinder


def fit_curved(
    pts: np.ndarray,
    *,
    cylinder: bool,
    radius_mm: float | None,
    max_points: int,
    curvature_per_mm: float | None = None,
) -> CurvedFit:
    """The geometric fit shared by :func:`fit_sphere`, :func:`fit_cylinder` and the plane registration.

    Parameters
    ----------
    pts : (M, 3) float64
        Checked points, left-camera frame, mm.
    cylinder : bool
        A cylinder (else a sphere, or a plane with ``curvature_per_mm=0``).
    radius_mm : float or None
        Fixes ``|k|``; the sign is the free fit's when clearly on one side, else the lower cost.
    max_points : int
        The fit uses at most this many points (uniform subsample); the RMS is over all.
    curvature_per_mm : float, optional
        Fixes ``k`` itself (0: a robust plane).

    Returns
    -------
    CurvedFit
    """
    model = _CurvedModel(_subsample(pts, max_points), cylinder=cylinder)
    x, f_scale = model.fit_free(curvature_per_mm)
    k_free = float(x[model.n_shape])
    if radius_mm is not None and curvature_per_mm is None:
        x = model.fit_radius(x, k_free, radius_mm, f_scale)
    n, ax, t = model.unpack(x)
    k = float(x[model.n_shape])
    p0 = model.p_ref + t * n
    rms = float(np.sqrt(np.mean(_signed_distance(pts - p0, n, k, ax) ** 2)))
    return CurvedFit(n, p0, k, ax, rms, k_free)


class _CurvedModel:
    """A sphere or cylinder through points, parametrised about a local quadric's guess.

    Parameters ``x``: the shape (sphere: normal offsets 2, offset t along it; cylinder: axis offsets 2,
    normal angle about the axis, offset t) then the signed curvature ``k`` (``n_shape`` is the index
    of ``k``). Initial guess from a local quadric in the PCA frame: its Hessian's eigen-decomposition
    gives the axis (the direction of least curvature) and the curvature.
    """

    def __init__(self, sub: np.ndarray, *, cylinder: bool) -> None:
        c, frame = pca_frame(sub)
        q = (sub - c) @ frame.T
        a = local_quadric(q)
        hess = np.array([[2 * a[3], a[4]], [a[4], 2 * a[5]]])
        evals, evecs = np.linalg.eigh(hess)
        n0 = frame.T @ np.array([-a[1], -a[2], 1.0])
        n0 /= np.linalg.norm(n0)
        self.n0 = n0
        self.p_ref = c + a[0] * frame[2]  # on the quadric above the centroid
        self.w = sub - self.p_ref
        self.ww = np.einsum("ij,ij->i", self.w, self.w)  # |w|^2, fixed over the fit
        self.cylinder = cylinder
        if cylinder:
            i_curved = int(np.argmax(np.abs(evals)))
            axis0 = frame[:2].T @ evecs[:, 1 - i_curved]
            axis0 -= (axis0 @ n0) * n0
            axis0 /= np.linalg.norm(axis0)
            self.axis0 = axis0
            self.k0 = float(evals[i_curved])
            self.u1, self.u2 = _orthonormal_pair(axis0)
        else:
            self.axis0 = None
            self.k0 = float(np.mean(evals))
            self.u1, self.u2 = _orthonormal_pair(n0)
        self.n_shape = 4 if cylinder else 3  # parameters besides k
        self.steps = np.full(self.n_shape + 1, 1e-6)  # rad for the angles / axis offsets
        self.steps[self.n_shape - 1] = 1e-3  # mm, offset along the normal
        self.steps[self.n_shape] = 1e-9  # 1/mm, curvature

    def unpack(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray | None, float]:
        """Normal, axis (None for a sphere) and offset along the normal of parameters ``x``."""
        if self.cylinder:
            ax = self.axis0 + x[0] * self.u1 + x[1] * self.u2
            # math.sqrt(v @ v): np.linalg.norm's arithmetic, without its overhead on 3 numbers
            ax /= math.sqrt(ax @ ax)
            b1 = self.n0 - (self.n0 @ ax) * ax
            b1 /= math.sqrt(b1 @ b1)
            b2 = _cross3(ax, b1)
            n = math.cos(x[2]) * b1 + math.sin(x[2]) * b2
            t = x[3]
        else:
            ax = None
            n = self.n0 + x[0] * self.u1 + x[1] * self.u2
            n /= math.sqrt(n @ n)
            t = x[2]
        return n, ax, t

    def residuals(self, x: np.ndarray, k_fixed: float | None) -> np.ndarray:
        """Signed orthogonal distances of the points (``k`` from ``x`` unless ``k_fixed``)."""
        # _signed_distance(w - t n, n, k, ax) expanded so each call costs two mat-vecs: n is orthogonal to the
        # axis (unpack), hence (w - t n).ax = w.ax, (w - t n).n = w.n - t, |w - t n|^2 = |w|^2 - 2 t w.n + t^2.
        n, ax, t = self.unpack(x)
        k = x[self.n_shape] if k_fixed is None else k_fixed
        sag = np.empty(len(self.ww))
        _sag(self.w, self.ww, n, n if ax is None else ax, ax is not None, float(t), float(k), sag)
        return sag

    def jacobian(self, x: np.ndarray, k_fixed: float | None) -> np.ndarray:
        """The residuals' derivatives (M, free parameters) at ``x``: the chain rule through the sag of
        :meth:`residuals`; the normal's and the axis's derivatives in the angles by central differences
        of :meth:`unpack` (3-vectors: exact to ~1e-10, where differences of the residuals cost a pass
        over the points each and were exact to ~1e-6)."""
        n, ax, t = self.unpack(x)
        k = x[self.n_shape] if k_fixed is None else k_fixed
        n_angles = self.n_shape - 1  # the parameters before the offset t
        columns = [n] if ax is None else [n, ax]
        for i in range(n_angles):
            step = np.zeros_like(x)
            step[i] = _ANGLE_STEP
            (n_p, ax_p, _), (n_m, ax_m, _) = self.unpack(x + step), self.unpack(x - step)
            columns.append((n_p - n_m) / (2.0 * _ANGLE_STEP))
            if ax_p is not None and ax_m is not None:
                columns.append((ax_p - ax_m) / (2.0 * _ANGLE_STEP))
        jac = np.empty((len(self.ww), len(x)))
        _sag_jacobian(
            self.w,
            self.ww,
            np.array(columns),
            ax is not None,
            float(t),
            float(k),
            k_fixed is None,
            jac,
        )
        return jac

    def solve(
        self, x0: np.ndarray, k_fixed: float | None, f_scale: float, max_iter: int = 60
    ) -> tuple[np.ndarray, float]:
        """Robust Levenberg-Marquardt from ``x0`` over the free parameters: (their values, cost)."""
        n_free = self.n_shape + (k_fixed is None)
        return robust_gauss_newton(
            lambda x: self.residuals(x, k_fixed),
            x0[:n_free],
            self.steps[:n_free],
            f_scale,
            max_iter=max_iter,
            jacobian=lambda x, _: self.jacobian(x, k_fixed),
        )

    def fit_free(self, curvature_per_mm: float | None) -> tuple[np.ndarray, float]:
        """Stage 1: robust scale from the quadric's residuals; stage 2: scale from stage 1. Returns the
        parameters (``k`` free unless ``curvature_per_mm``) and the last robust scale."""
        x = np.zeros(self.n_shape + 1)
        x[self.n_shape] = self.k0 if curvature_per_mm is None else curvature_per_mm
        k_fix = curvature_per_mm
        f_scale = max(3.0 * robust_scale(self.residuals(x, k_fix)), 0.05)
        x[: self.n_shape + (k_fix is None)], _ = self.solve(x, k_fix, f_scale)
        f_scale = max(3.0 * robust_scale(self.residuals(x, k_fix)), 0.01)
        x[: self.n_shape + (k_fix is None)], _ = self.solve(x, k_fix, f_scale)
        return x, f_scale

    def fit_radius(
        self, x: np.ndarray, k_free: float, radius_mm: float, f_scale: float
    ) -> np.ndarray:
        """The fit with the radius fixed, from the free fit ``x``.

        When the free fit's curvature is clearly on one side (at least half the fixed curvature), that
        side is taken; otherwise both orientations (convex / concave towards the camera) are tried for a
        few steps and the lower cost decides. The winner is solved to convergence.
        """
        k_abs = 1.0 / radius_mm
        sides = (math.copysign(k_abs, k_free),) if abs(k_free) >= 0.5 * k_abs else (k_abs, -k_abs)
        start, k_start = x[: self.n_shape].copy(), sides[0]
        if len(sides) > 1:
            best_cost = math.inf
            for k_try in sides:
                xs, cost = self.solve(x[: self.n_shape].copy(), k_try, f_scale, max_iter=6)
                if cost < best_cost or k_try == sides[0]:
                    start, k_start, best_cost = xs, k_try, cost
        xs, _ = self.solve(start, k_start, f_scale)
        fitted: np.ndarray = np.append(xs, k_start)
        return fitted


def fit_sphere(
    points_mm: npt.ArrayLike, *, radius_mm: float | None = None, max_points: int = MAX_FIT_POINTS
) -> SphereFit:
    """Geometric least-squares sphere through 3-D points of a (possibly small) spherical cap.

    Parameters
    ----------
    points_mm : (M, 3) array_like of float
        Points in the left-camera frame, mm; M >= 5.
    radius_mm : float, optional
        Fix the radius (mm). Convex or concave: the side of the radius-free fit made first when its
        curvature is at least half of ``1 / radius_mm``, else the lower cost of both.
    max_points : int
        Fit on at most this many points (uniform subsample); the RMS is over all points.

    Returns
    -------
    SphereFit
        Centre, unsigned radius, signed curvature (+ convex towards the camera), RMS distance.

    Raises
    ------
    ValueError
        Bad shape, too few or non-finite points, non-positive radius.

    Notes
    -----
    Initial guess from a local quadric in the PCA frame, then robust Levenberg-Marquardt on the
    exact orthogonal distances with a soft-L1 loss (scale 3 robust sigmas of the previous stage), so a
    local dent does not pull the radius. Parametrised by the signed curvature ``k``, a tangent point and
    its normal: stable for arcs of any size, and a flat plate gives ``k = 0``.
    """
    pts = _check_points(points_mm, min_points=5)
    r = _check_radius(radius_mm)
    n, p0, k, _, rms, k_free = fit_curved(pts, cylinder=False, radius_mm=r, max_points=max_points)
    center = p0 + n / k if k != 0 else np.full(3, np.inf)
    return SphereFit(
        center_mm=center,
        radius_mm=abs(1.0 / k) if k != 0 else math.inf,
        curvature_per_mm=k,
        rms_mm=rms,
        free_curvature_per_mm=None if r is None else k_free,
    )


def fit_cylinder(
    points_mm: npt.ArrayLike, *, radius_mm: float | None = None, max_points: int = MAX_FIT_POINTS
) -> CylinderFit:
    """Geometric least-squares circular cylinder through 3-D points of a (possibly small) arc.

    Parameters
    ----------
    points_mm : (M, 3) array_like of float
        Points in the left-camera frame, mm; M >= 6.
    radius_mm : float, optional
        Fix the radius (mm). Convex or concave: the side of the radius-free fit made first when its
        curvature is at least half of ``1 / radius_mm``, else the lower cost of both.
    max_points : int
        Fit on at most this many points (uniform subsample); the RMS is over all points.

    Returns
    -------
    CylinderFit
        Axis, point on the axis, unsigned radius, signed curvature (+ convex towards the camera), RMS.

    Raises
    ------
    ValueError
        Bad shape, too few or non-finite points, non-positive radius.

    Notes
    -----
    Initial axis and curvature from the eigen-decomposition of a local quadric's Hessian in the PCA
    frame (the axis is the direction of least curvature), then robust Levenberg-Marquardt (soft-L1 loss,
    scale 3 robust sigmas) on the exact orthogonal distances over five parameters (axis direction 2, normal angle about the axis, offset along the normal,
    signed curvature). The curvature parametrisation keeps a 22 mm sagitta (R 50 m over 3 m) as well
    conditioned as a 225 mm one.
    """
    pts = _check_points(points_mm, min_points=6)
    r = _check_radius(radius_mm)
    n, p0, k, ax, rms, k_free = fit_curved(pts, cylinder=True, radius_mm=r, max_points=max_points)
    if ax is None:
        raise ValueError("points_mm: the cylinder fit found no axis")
    if ax[1] < 0 or (ax[1] == 0 and ax[0] < 0):
        ax = -ax
    if k != 0:
        centre = p0 + n / k
        c = pts.mean(axis=0)
        point = centre + ((c - centre) @ ax) * ax
    else:
        point = np.full(3, np.inf)
    return CylinderFit(
        axis=ax,
        point_on_axis_mm=point,
        radius_mm=abs(1.0 / k) if k != 0 else math.inf,
        curvature_per_mm=k,
        rms_mm=rms,
        free_curvature_per_mm=None if r is None else k_free,
    )
