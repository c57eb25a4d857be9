"""Curvature of the measured plate: geometric plane, sphere and cylinder fits, principal curvatures.

All points are in the left-camera frame (OpenCV: x right, y down, z forward), in mm. The camera centre
is the origin of that frame; it is used to orient normals and to give curvature a sign.

Sign convention (every function here): a curvature or radius is **positive where the surface is convex
towards the camera** (its centre of curvature lies on the far side of the surface, away from the camera)
and negative where it is concave towards the camera.

Why geometric fits: a global graph quadric ``z = a x^2 + b xy + c y^2 + ...`` takes the parabola's vertex
curvature for the circle's; over a 3 m plate that understates the radius by 2 % (cylinder, R 5 m) to
4.5 % (sphere). The fits below minimise true orthogonal distances instead, in a parametrisation by
curvature ``k = 1/R`` that stays well conditioned as ``k -> 0`` (a flat plate is ``k = 0``, not ``R = inf``).

References
----------
.. [1] Al-Sharadqah, A., Chernov, N., "Error analysis for circle fitting algorithms", Electronic Journal of
   Statistics 3 (2009) -- the curvature parametrisation of the geometric circle/sphere fit.
.. [2] do Carmo, M., "Differential Geometry of Curves and Surfaces" (1976), sec. 3-3 -- shape operator of a graph.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.polynomial import legendre as leg
from scipy import ndimage

#: At most this many points go into a fit; more are subsampled uniformly (every n-th point). With 0.2 mm
#: noise 20 000 points over a 3 m plate leave a radius uncertainty of ~0.005 % at R 20 m (tests check 0.05 %).
MAX_FIT_POINTS = 20_000

#: A principal direction whose sagitta over the plate, ``|k| L^2 / 8`` (L = plate extent along that
#: direction), is below this many mm counts as flat: its radius is reported as None.
FLAT_SAGITTA_MM = 0.5


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


@dataclass(frozen=True)
class CurvatureResult:
    """Principal curvatures of the measured surface.

    Attributes
    ----------
    principal_radii_mm : (float or None, float or None)
        ``(r1, r2)``, signed (+ convex towards the camera), ``|r1| <= |r2|``; None where the surface is flat
        in that direction (sagitta over the plate below ``flat_sagitta_mm``).
    principal_curvatures_per_mm : (float, float)
        ``(k1, k2)`` behind the radii, signed, ``|k1| >= |k2|`` (reported even when flat).
    principal_directions : (2, 3) float64
        Unit tangent directions of k1 and k2 at the plate centre, left-camera frame.
    curvature_map : (H, W, 2) float32
        Per-pixel principal curvatures ``(k1, k2)`` in 1/mm, signed, ``|k1| >= |k2|``; NaN outside the mask.
    polynomial_degree : int
        Total degree of the height polynomial the map comes from.
    fit_rms_mm : float
        RMS height residual of that polynomial, mm.
    """

    principal_radii_mm: tuple[float | None, float | None]
    principal_curvatures_per_mm: tuple[float, float]
    principal_directions: np.ndarray
    curvature_map: np.ndarray
    polynomial_degree: int
    fit_rms_mm: float


# --------------------------------------------------------------------------- input checks


def _check_points(points_mm, *, name: str = "points_mm", min_points: int) -> np.ndarray:
    pts = np.asarray(points_mm, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"{name}: expected shape (M, 3), got {pts.shape}")
    if pts.shape[0] < min_points:
        raise ValueError(f"{name}: expected at least {min_points} points, got {pts.shape[0]}")
    if not np.all(np.isfinite(pts)):
        bad = int(np.count_nonzero(~np.isfinite(pts).all(axis=1)))
        raise ValueError(f"{name}: expected finite coordinates, got {bad} points with NaN/inf")
    return pts


def _check_radius(radius_mm) -> float | None:
    if radius_mm is None:
        return None
    r = float(radius_mm)
    if not math.isfinite(r) or r <= 0:
        raise ValueError(f"radius_mm: expected a positive finite radius in mm or None, got {radius_mm}")
    return r


def check_grid(points_mm, mask, *, min_points: int = 10) -> tuple[np.ndarray, np.ndarray]:
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
    # One sum per point: NaN or inf in any coordinate makes it non-finite (cheaper than isfinite on all three).
    with np.errstate(invalid="ignore", over="ignore"):
        bad = m & ~np.isfinite(pts[..., 0] + pts[..., 1] + pts[..., 2])
    if bad.any():
        raise ValueError(f"points_mm: expected finite points inside the mask, got {int(bad.sum())} with NaN/inf")
    return pts, m


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
    return points_mm[::step, ::step][mask[::step, ::step]]


def _subsample(pts: np.ndarray, max_points: int) -> np.ndarray:
    if pts.shape[0] <= max_points:
        return pts
    idx = np.linspace(0, pts.shape[0] - 1, max_points).round().astype(np.int64)
    return pts[idx]


# --------------------------------------------------------------------------- local frame


def _pca_frame(pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Centroid and rows (ex, ey, ez) of a right-handed PCA frame; ez is the least-variance direction
    and points away from the camera (``ez . centroid > 0``)."""
    c = pts.mean(axis=0)
    _, _, vt = np.linalg.svd(pts - c, full_matrices=False)
    ex, ez = vt[0], vt[2]
    if ez @ c < 0:
        ez = -ez
    ey = np.cross(ez, ex)
    return c, np.stack([ex, ey, ez])


def _local_quadric(q: np.ndarray) -> np.ndarray:
    """Least-squares ``h = a0 + a1 x + a2 y + a3 x^2 + a4 xy + a5 y^2`` of local coordinates (M, 3)."""
    x, y = q[:, 0], q[:, 1]
    A = np.stack([np.ones_like(x), x, y, x * x, x * y, y * y], axis=1)
    scale = np.abs(A).max(axis=0)
    coef, *_ = np.linalg.lstsq(A / scale, q[:, 2], rcond=None)
    return coef / scale


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
    return g / (1.0 + np.sqrt(np.maximum(1.0 + k * g, 0.0)))


def _robust_gauss_newton(fun, x0: np.ndarray, steps: np.ndarray, f_scale: float, *, max_iter: int = 60,
                         rtol: float = 1e-12):
    """Levenberg-Marquardt on the soft-L1 cost ``sum 2 f^2 (sqrt(1 + (r/f)^2) - 1)`` by iteratively
    reweighted normal equations (weights ``1/sqrt(1 + (r/f)^2)``), forward-difference Jacobian.
    A few parameters and many residuals: the normal equations are tiny, each step costs ~p+2
    residual evaluations. Stops when a step lowers the cost by less than ``rtol`` of it, or moves every
    parameter by less than 1e-3 of its difference step. Returns (x, cost)."""

    def cost_of(r):
        return float(np.sum(2 * f_scale**2 * (np.sqrt(1 + (r / f_scale) ** 2) - 1)))

    x = np.asarray(x0, dtype=np.float64).copy()
    r = fun(x)
    cost = cost_of(r)
    lam = 1e-6
    for _ in range(max_iter):
        J = np.empty((r.size, x.size))
        for i, h in enumerate(steps):
            dx = np.zeros_like(x)
            dx[i] = h
            J[:, i] = (fun(x + dx) - r) / h
        wgt = 1.0 / np.sqrt(1 + (r / f_scale) ** 2)
        A = J.T @ (J * wgt[:, None])
        g = J.T @ (wgt * r)
        improved = False
        for _ in range(20):
            delta = np.linalg.solve(A + lam * np.diag(np.diag(A)), -g)
            r_new = fun(x + delta)
            cost_new = cost_of(r_new)
            if cost_new <= cost:
                improved = True
                break
            lam *= 10.0
        if not improved:
            break
        x, r = x + delta, r_new
        converged = cost - cost_new <= rtol * cost or np.all(np.abs(delta) <= 1e-3 * steps)
        cost = cost_new
        lam = max(lam / 10.0, 1e-9)
        if converged:
            break
    return x, cost


def _robust_scale(r: np.ndarray) -> float:
    return float(1.4826 * np.median(np.abs(r - np.median(r))))


# --------------------------------------------------------------------------- plane


def fit_plane(points_mm) -> PlaneFit:
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
    c, frame = _pca_frame(pts)
    normal = -frame[2]  # towards the camera
    d = (pts - c) @ normal
    return PlaneFit(normal=normal, point_mm=c, rms_mm=float(np.sqrt(np.mean(d * d))))


# --------------------------------------------------------------------------- sphere and cylinder


def _fit_curved(pts: np.ndarray, *, cylinder: bool, radius_mm: float | None, max_points: int,
                curvature_per_mm: float | None = None):
    """Shared geometric fit. Returns (n, p0, k, axis, rms_all) in the camera frame; ``n`` is the unit
    normal at ``p0`` pointing away from the camera, the centre is ``p0 + n / k``. ``radius_mm`` fixes
    ``|k|`` (sign chosen by cost); ``curvature_per_mm`` fixes ``k`` itself (0: a robust plane)."""
    sub = _subsample(pts, max_points)
    c, frame = _pca_frame(sub)
    q = (sub - c) @ frame.T
    a = _local_quadric(q)
    hess = np.array([[2 * a[3], a[4]], [a[4], 2 * a[5]]])
    evals, evecs = np.linalg.eigh(hess)
    n0 = frame.T @ np.array([-a[1], -a[2], 1.0])
    n0 /= np.linalg.norm(n0)
    p_ref = c + a[0] * frame[2]  # on the quadric above the centroid
    w_all = sub - p_ref
    if cylinder:
        i_curved = int(np.argmax(np.abs(evals)))
        axis0 = frame[:2].T @ evecs[:, 1 - i_curved]
        axis0 -= (axis0 @ n0) * n0
        axis0 /= np.linalg.norm(axis0)
        k0 = float(evals[i_curved])
        u1, u2 = _orthonormal_pair(axis0)
    else:
        axis0 = None
        k0 = float(np.mean(evals))
        u1, u2 = _orthonormal_pair(n0)

    def unpack(x):
        if cylinder:
            ax = axis0 + x[0] * u1 + x[1] * u2
            ax /= np.linalg.norm(ax)
            b1 = n0 - (n0 @ ax) * ax
            b1 /= np.linalg.norm(b1)
            b2 = np.cross(ax, b1)
            n = math.cos(x[2]) * b1 + math.sin(x[2]) * b2
            t = x[3]
        else:
            ax = None
            n = n0 + x[0] * u1 + x[1] * u2
            n /= np.linalg.norm(n)
            t = x[2]
        return n, ax, t

    n_shape = 4 if cylinder else 3  # parameters besides k
    ww_all = np.einsum("ij,ij->i", w_all, w_all)  # |w|^2, fixed over the fit

    def residuals(x, k_fixed, w):
        # _signed_distance(w - t n, n, k, ax) expanded so each call costs two mat-vecs: n is orthogonal to the
        # axis (unpack), hence (w - t n).ax = w.ax, (w - t n).n = w.n - t, |w - t n|^2 = |w|^2 - 2 t w.n + t^2.
        n, ax, t = unpack(x)
        k = x[n_shape] if k_fixed is None else k_fixed
        if ax is None:
            wn = w @ n
            s2 = ww_all - 2.0 * t * wn + t * t
        else:
            wa = w @ np.stack([n, ax], axis=1)
            wn = wa[:, 0]
            s2 = ww_all - wa[:, 1] * wa[:, 1] - 2.0 * t * wn + t * t
        g = k * s2 - 2.0 * (wn - t)
        return g / (1.0 + np.sqrt(np.maximum(1.0 + k * g, 0.0)))

    steps = np.full(n_shape + 1, 1e-6)  # rad for the angles / axis offsets
    steps[n_shape - 1] = 1e-3  # mm, offset along the normal
    steps[n_shape] = 1e-9  # 1/mm, curvature

    def solve(x0, k_fixed, f_scale, max_iter=60):
        n_free = n_shape + (k_fixed is None)
        return _robust_gauss_newton(lambda x: residuals(x, k_fixed, w_all), x0[:n_free], steps[:n_free], f_scale,
                                    max_iter=max_iter)

    # Stage 1: free curvature, robust scale from the quadric's residuals; stage 2: scale from stage 1.
    x = np.zeros(n_shape + 1)
    x[n_shape] = k0 if curvature_per_mm is None else curvature_per_mm
    k_fix = curvature_per_mm
    f_scale = max(3.0 * _robust_scale(residuals(x, k_fix, w_all)), 0.05)
    x[: n_shape + (k_fix is None)], _ = solve(x, k_fix, f_scale)
    f_scale = max(3.0 * _robust_scale(residuals(x, k_fix, w_all)), 0.01)
    x[: n_shape + (k_fix is None)], _ = solve(x, k_fix, f_scale)
    k_free = float(x[n_shape])
    if radius_mm is not None and curvature_per_mm is None:
        # Radius fixed: when the free fit's curvature is clearly on one side (at least half the fixed
        # curvature), that side is taken; otherwise both orientations (convex / concave towards the camera)
        # are tried for a few steps and the lower cost decides. The winner is solved to convergence.
        k_abs = 1.0 / radius_mm
        sides = (math.copysign(k_abs, k_free),) if abs(k_free) >= 0.5 * k_abs else (k_abs, -k_abs)
        best = (x[:n_shape].copy(), sides[0], None)
        if len(sides) > 1:
            best = None
            for k_try in sides:
                xs, cost = solve(x[:n_shape].copy(), k_try, f_scale, max_iter=6)
                if best is None or cost < best[2]:
                    best = (xs, k_try, cost)
        xs, _ = solve(best[0], best[1], f_scale)
        x = np.append(xs, best[1])
    n, ax, t = unpack(x)
    k = float(x[n_shape])
    p0 = p_ref + t * n
    rms = float(np.sqrt(np.mean(_signed_distance(pts - p0, n, k, ax) ** 2)))
    return n, p0, k, ax, rms, k_free


def fit_sphere(points_mm, *, radius_mm: float | None = None, max_points: int = MAX_FIT_POINTS) -> SphereFit:
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
    n, p0, k, _, rms, k_free = _fit_curved(pts, cylinder=False, radius_mm=r, max_points=max_points)
    center = p0 + n / k if k != 0 else np.full(3, np.inf)
    return SphereFit(center_mm=center, radius_mm=abs(1.0 / k) if k != 0 else math.inf, curvature_per_mm=k, rms_mm=rms,
                     free_curvature_per_mm=None if r is None else k_free)


def fit_cylinder(points_mm, *, radius_mm: float | None = None, max_points: int = MAX_FIT_POINTS) -> CylinderFit:
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
    n, p0, k, ax, rms, k_free = _fit_curved(pts, cylinder=True, radius_mm=r, max_points=max_points)
    if ax[1] < 0 or (ax[1] == 0 and ax[0] < 0):
        ax = -ax
    if k != 0:
        centre = p0 + n / k
        c = pts.mean(axis=0)
        point = centre + ((c - centre) @ ax) * ax
    else:
        point = np.full(3, np.inf)
    return CylinderFit(axis=ax, point_on_axis_mm=point, radius_mm=abs(1.0 / k) if k != 0 else math.inf,
                       curvature_per_mm=k, rms_mm=rms, free_curvature_per_mm=None if r is None else k_free)


# --------------------------------------------------------------------------- principal curvatures


def _choose_degree(rho: float) -> int:
    """Polynomial degree for a height field whose worst ``|k| * half-extent`` is rho.

    The height of a circular arc, ``R (1 - sqrt(1 - (rho t)^2))`` on ``t in [-1, 1]``, has its singularity
    at ``t = 1/rho``; a Legendre series converges like ``r^-deg`` with ``r = 1/rho + sqrt(1/rho^2 - 1)``
    (Bernstein ellipse). Take the degree for ``r^-deg <= 1e-4``, even, between 4 and 12."""
    rho = min(max(rho, 1e-6), 0.95)
    r = 1.0 / rho + math.sqrt(1.0 / rho**2 - 1.0)
    deg = math.ceil(math.log(1e4) / math.log(r))
    deg += deg % 2
    return int(min(max(deg, 4), 12))


class _HeightPoly:
    """``h(x, y)`` as a total-degree Legendre polynomial on the normalised plate box."""

    def __init__(self, q: np.ndarray, deg: int):
        lo, hi = q[:, :2].min(axis=0), q[:, :2].max(axis=0)
        self.mid = (lo + hi) / 2
        self.half = np.maximum((hi - lo) / 2, 1e-9)
        self.deg = deg
        ii, jj = np.meshgrid(np.arange(deg + 1), np.arange(deg + 1), indexing="ij")
        self.keep = ((ii + jj) <= deg).ravel()
        xn, yn = self._norm(q[:, 0], q[:, 1])
        V = leg.legvander2d(xn, yn, [deg, deg])[:, self.keep]
        # Normal equations: Legendre columns on [-1, 1] are close to orthogonal, so V^T V is well conditioned
        # (far cheaper than an SVD least squares on 20 000 x 91).
        coef = np.linalg.solve(V.T @ V, V.T @ q[:, 2])
        C = np.zeros((deg + 1) ** 2)
        C[self.keep] = coef
        self.C = C.reshape(deg + 1, deg + 1)
        self.rms = float(np.sqrt(np.mean((V @ coef - q[:, 2]) ** 2)))
        sx, sy = 1.0 / self.half
        dx = leg.legder(self.C, 1, sx, axis=0)
        self.d = {
            "x": dx,
            "y": leg.legder(self.C, 1, sy, axis=1),
            "xx": leg.legder(self.C, 2, sx, axis=0),
            "xy": leg.legder(dx, 1, sy, axis=1),
            "yy": leg.legder(self.C, 2, sy, axis=1),
        }

    def _norm(self, x, y):
        return (x - self.mid[0]) / self.half[0], (y - self.mid[1]) / self.half[1]

    def tensor(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Second fundamental form in an orthonormal tangent basis (e1 along r_x), (M, 3): B11, B12, B22.
        Normal is the graph's upward normal (+h)."""
        xn, yn = self._norm(x, y)
        hx, hy, hxx, hxy, hyy = (leg.legval2d(xn, yn, self.d[key]) for key in ("x", "y", "xx", "xy", "yy"))
        E, F, G = 1 + hx * hx, hx * hy, 1 + hy * hy
        w = np.sqrt(1 + hx * hx + hy * hy)
        L, M, N = hxx / w, hxy / w, hyy / w
        den = E * G - F * F
        a11 = 1 / np.sqrt(E)
        a22 = np.sqrt(E / den)
        a21 = -F / np.sqrt(E * den)
        b11 = a11 * a11 * L
        b12 = a11 * (a21 * L + a22 * M)
        b22 = a21 * a21 * L + 2 * a21 * a22 * M + a22 * a22 * N
        return np.stack([b11, b12, b22], axis=1)


def _eig_sym2(b: np.ndarray) -> np.ndarray:
    """Eigenvalues of symmetric 2x2 tensors (M, 3) -> (M, 2) ordered by decreasing magnitude."""
    mean = (b[:, 0] + b[:, 2]) / 2
    rad = np.sqrt(((b[:, 0] - b[:, 2]) / 2) ** 2 + b[:, 1] ** 2)
    lam = np.stack([mean + rad, mean - rad], axis=1)
    swap = np.abs(lam[:, 1]) > np.abs(lam[:, 0])
    lam[swap] = lam[swap][:, ::-1]
    return lam


def principal_curvatures(points_mm, mask, *, flat_sagitta_mm: float = FLAT_SAGITTA_MM,
                         max_points: int = MAX_FIT_POINTS) -> CurvatureResult:
    """Principal radii and a per-pixel principal-curvature map of the measured surface.

    Parameters
    ----------
    points_mm : (H, W, 3) array_like of float
        Surface point of each pixel, left-camera frame, mm (ignored outside the mask).
    mask : (H, W) bool
        True where the point is valid; at least 50 valid pixels.
    flat_sagitta_mm : float
        A principal direction counts as flat (radius None) when ``|k| L^2 / 8 < flat_sagitta_mm``, L the
        plate's extent along it (mm). Default 0.5 mm: a quarter of the usual 2 mm tolerance.
    max_points : int
        The height polynomial is fitted on at most this many points (uniform subsample).

    Returns
    -------
    CurvatureResult
        Signed principal radii (+ convex towards the camera, ``|r1| <= |r2|``), curvatures, directions,
        and the (H, W, 2) float32 curvature map (1/mm, NaN outside the mask).

    Raises
    ------
    ValueError
        On bad shapes, dtypes, non-finite points in the mask, or a non-positive ``flat_sagitta_mm``.

    Notes
    -----
    The surface is written as a height field ``h(x, y)`` over its PCA plane and fitted by a Legendre
    polynomial of total degree 4..12 (chosen from a first quadric's curvature so the truncation error
    of a circular arc stays below ~1e-4 of the height). The exact shape operator of the graph (first and
    second fundamental forms, [2]) gives the curvature at every point -- not the vertex curvature of a
    parabola, which is what biases a global quadric. The plate's principal curvatures are the eigenvalues
    of the median of the per-point curvature tensor (expressed in a tangent basis aligned with the plate
    axes), so a sphere gives two equal radii without the bias of sorting noisy pairs. The map is evaluated
    on a grid of at most ~300 x 300 pixels and interpolated bilinearly to full size (it is a smooth
    polynomial field; its resolution is that of the polynomial, not of the pixels).
    """
    pts, m = check_grid(points_mm, mask, min_points=50)
    if not (math.isfinite(flat_sagitta_mm) and flat_sagitta_mm > 0):
        raise ValueError(f"flat_sagitta_mm: expected a positive number of mm, got {flat_sagitta_mm}")
    H, W = m.shape
    sub = grid_sample(pts, m, max_points)
    c, frame = _pca_frame(sub)
    frame = frame * np.array([[1.0], [-1.0], [-1.0]])  # ez towards the camera, still right-handed
    q = (sub - c) @ frame.T
    a = _local_quadric(q)
    evals, evecs = np.linalg.eigh(np.array([[2 * a[3], a[4]], [a[4], 2 * a[5]]]))
    # Turn x_p to the quadric's direction of strongest curvature: the tangent basis below (e1 along r_x)
    # then follows the principal directions, so their median tensor does not mix k1 into k2.
    i_max = int(np.argmax(np.abs(evals)))
    ex = evecs[0, i_max] * frame[0] + evecs[1, i_max] * frame[1]
    frame = np.stack([ex, np.cross(frame[2], ex), frame[2]])
    q = (sub - c) @ frame.T
    half = (q[:, :2].max(axis=0) - q[:, :2].min(axis=0)) / 2
    deg = _choose_degree(float(np.max(np.abs(evals)) * np.max(half)))
    poly = _HeightPoly(q, deg)

    # Plate curvature: median tensor over the points. The graph normal points towards the camera, so a
    # surface convex towards the camera has negative II; flip to our sign convention.
    b = -poly.tensor(q[:, 0], q[:, 1])
    bm = np.median(b, axis=0)
    tens = np.array([[bm[0], bm[1]], [bm[1], bm[2]]])
    lam, vec = np.linalg.eigh(tens)
    order = np.argsort(-np.abs(lam))
    lam, vec = lam[order], vec[:, order]
    directions = (vec.T @ frame[:2])
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    radii: list[float | None] = []
    for i in range(2):
        proj = q[:, :2] @ vec[:, i]
        extent = float(proj.max() - proj.min())
        sag = abs(lam[i]) * extent**2 / 8
        radii.append(float(1.0 / lam[i]) if sag >= flat_sagitta_mm else None)

    # Per-pixel map: evaluated at every valid pixel of small grids; on large grids at every step-th pixel
    # (step odd, at most ~300 x 300 samples) and interpolated bilinearly. With an odd step, sample j sits at
    # pixel j*step + (step-1)/2, exactly where cv2.resize by the factor step puts source pixel j.
    n_valid = int(np.count_nonzero(m))
    step = max(1, math.ceil(max(H, W) / 300))
    step += 1 - step % 2
    o = (step - 1) // 2
    coarse_mask = m[o::step, o::step]
    if n_valid <= 200_000 or not coarse_mask.any():
        qv = (pts[m] - c) @ frame.T
        kmap = np.full((H, W, 2), np.nan, dtype=np.float32)
        kmap[m] = _eig_sym2(-poly.tensor(qv[:, 0], qv[:, 1]))
    else:
        qc = (pts[o::step, o::step][coarse_mask] - c) @ frame.T
        kmap_c = np.empty(coarse_mask.shape + (2,), dtype=np.float32)
        kmap_c[coarse_mask] = _eig_sym2(-poly.tensor(qc[:, 0], qc[:, 1]))
        if not coarse_mask.all():
            # Extend the smooth field nearest-neighbour outside the mask so the interpolation at the mask's
            # border stays defined; those pixels are set to NaN again below.
            _, (ri, ci) = ndimage.distance_transform_edt(~coarse_mask, return_indices=True)
            kmap_c = kmap_c[ri, ci]
        hc, wc = coarse_mask.shape
        kmap = cv2.resize(kmap_c, (wc * step, hc * step), interpolation=cv2.INTER_LINEAR)
        if kmap.shape[0] < H or kmap.shape[1] < W:
            kmap = np.pad(kmap, ((0, max(0, H - kmap.shape[0])), (0, max(0, W - kmap.shape[1])), (0, 0)), mode="edge")
        kmap = kmap[:H, :W]
    kmap = np.asarray(kmap, dtype=np.float32)
    np.copyto(kmap, np.float32(np.nan), where=~m[..., None])
    return CurvatureResult(
        principal_radii_mm=(radii[0], radii[1]),
        principal_curvatures_per_mm=(float(lam[0]), float(lam[1])),
        principal_directions=directions,
        curvature_map=kmap,
        polynomial_degree=deg,
        fit_rms_mm=poly.rms,
    )
