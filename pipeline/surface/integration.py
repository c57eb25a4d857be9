"""Normal integration: from a field of surface normals to metric depth.

Step 6 of the method (README: How a plate is measured, *Depth*): every 4-neighbour pair of pixels
inside the mask gives one linear equation on the depth, and the overdetermined system is
solved by least squares over the masked domain. We integrate in *log depth*
under the pinhole camera (perspective, not orthographic), and optionally fuse a
sparse or noisy metric depth prior from binocular stereo (Nehab et al. 2005,
linearised in log depth): the stereo depth gives the scale and the low
frequencies, the normals the detail.

For a pixel ``(u, v)`` with ray ``r = K^-1 (u, v, 1)`` the surface point is ``X = z r``. Its
tangents ``X_u = z_u r + z K^-1 e_1`` and ``X_v = z_v r + z K^-1 e_2`` are orthogonal to the normal
``n``, so

    d(log z)/du = -(n . K^-1 e_1) / (n . r),    d(log z)/dv = -(n . K^-1 e_2) / (n . r)

(for ``K`` without skew: ``-n_x / (fx n . r)`` and ``-n_y / (fy n . r)``). These are independent of
the length of ``n`` and exact for any surface.

The normal equations are a masked graph Laplacian plus a diagonal prior term: a grid system,
assembled here on padded grids and solved by :func:`pipeline.solvers.solve_grid_system`
(conjugate gradients preconditioned with a geometric multigrid V-cycle;
``benchmarks/bench_integration.py`` measures its speed). The first call in a fresh installation
compiles the numba kernels; they are cached on disk.

References
----------
.. [1] J.-D. Durou, J.-F. Aujol, F. Courteille, "Integrating the normal field of a surface in the
   presence of discontinuities", EMMCVPR 2009.
.. [2] Y. Queau, J.-D. Durou, J.-F. Aujol, "Normal integration: a survey", J. Math. Imaging Vis.
   60, 2018 (perspective case, log depth).
.. [3] D. Nehab, S. Rusinkiewicz, J. Davis, R. Ramamoorthi, "Efficiently combining positions and
   normals for precise 3D geometry", SIGGRAPH 2005.

Kept as one module (~600 lines) on purpose: the equations, their prior terms and the scaling of the
parts without a prior are one problem, and its public functions share every kernel; the generic
solver is already apart (:mod:`pipeline.solvers`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numba as nb
import numpy as np
import numpy.typing as npt
import scipy.ndimage

from pipeline.camera import check_camera_matrix
from pipeline.solvers import bounding_box, solve_grid_system

#: An array argument of the kernels (their dtypes are set by the callers).
Arr = npt.NDArray[Any]
#: The normal equations on the padded grid: (ex, ey, wd, dg, idg) float32 and b float64.
System = tuple[Arr, Arr, Arr, Arr, Arr, Arr]
#: Parts of the mask a prior does not reach: (labels, number of parts, parts without a prior,
#: has_prior per label).
Floating = tuple[Arr, int, int, Arr]

__all__ = ["DepthResult", "HeightResult", "integrate_gradient", "integrate_normals"]

#: Tolerance on the length of a normal inside the mask (normals are unit vectors).
_UNIT_TOL = 1e-2


@dataclass(frozen=True)
class DepthResult:
    """Depth integrated from a normal field.

    Attributes
    ----------
    depth_mm : (H, W) float64
        Depth ``z`` along the optical axis of the left camera, mm (a pixel
        ``(u, v)`` sees the point ``depth_mm[v, u] * K^-1 (u, v, 1)``); NaN
        outside ``mask``.
    mask : (H, W) bool
        Pixels with a metric depth: the input mask, minus the connected parts
        of it that no prior pixel reaches when a prior but no
        ``reference_depth_mm`` is given.
    iterations : int
        Preconditioned conjugate-gradient iterations taken.
    residual : float
        Relative residual ``||b - A x|| / ||b||`` of the normal equations at
        the end of the solve (0 when ``b = 0``).
    """

    depth_mm: np.ndarray
    mask: np.ndarray
    iterations: int
    residual: float


@dataclass(frozen=True)
class HeightResult:
    """Height integrated from an orthographic gradient field.

    Attributes
    ----------
    height : (H, W) float64
        Height in the units of ``gradient * pixel``, zero mean over each
        connected component of ``mask``; NaN outside ``mask``.
    mask : (H, W) bool
    iterations : int
    residual : float
        Relative residual of the normal equations.
    """

    height: np.ndarray
    mask: np.ndarray
    iterations: int
    residual: float


# The kernels below assemble the problem; the grid system's layout (padded grids, ex, ey, wd, dg,
# idg, b) is described in pipeline.solvers. Parallel kernels run on the caller's thread only.


@nb.njit(cache=True, parallel=True)
def _log_depth_gradients(
    normals: Arr, mask: Arr, kinv: Arr, unit_tol: float, p: Arr, q: Arr, usable: Arr
) -> int:
    """p = d(log z)/du, q = d(log z)/dv on the mask (0 outside) and where each is ``usable`` (the
    normal a finite unit vector facing the camera); returns the count of unusable normals."""
    h, w = mask.shape
    bad = 0
    a0, a1, a2 = kinv[0, 0], kinv[0, 1], kinv[0, 2]
    b0, b1, b2 = kinv[1, 0], kinv[1, 1], kinv[1, 2]
    c0, c1, c2 = kinv[2, 0], kinv[2, 1], kinv[2, 2]
    for i in nb.prange(h):
        v = np.float64(i)
        for j in range(w):
            p[i, j] = 0.0
            q[i, j] = 0.0
            usable[i, j] = False
            if not mask[i, j]:
                continue
            nx = np.float64(normals[i, j, 0])
            ny = np.float64(normals[i, j, 1])
            nz = np.float64(normals[i, j, 2])
            u = np.float64(j)
            nr = (
                nx * (a0 * u + a1 * v + a2)
                + ny * (b0 * u + b1 * v + b2)
                + nz * (c0 * u + c1 * v + c2)
            )
            nn = nx * nx + ny * ny + nz * nz
            # NaN fails both comparisons and is counted as bad.
            if not (nr < 0.0 and abs(nn - 1.0) <= unit_tol):
                bad += 1
                continue
            p[i, j] = -(nx * a0 + ny * b0 + nz * c0) / nr
            q[i, j] = -(nx * a1 + ny * b1 + nz * c1) / nr
            usable[i, j] = True
    return bad


@nb.njit(cache=True, parallel=True)
def _fine_system(
    mask: Arr,
    p: Arr,
    q: Arr,
    wd: Arr,
    prior: Arr,
    shift: float,
    ex: Arr,
    ey: Arr,
    wdp: Arr,
    dg: Arr,
    idg: Arr,
    b: Arr,
) -> None:
    """The normal equations on the padded grid from (H, W) inputs.

    Edge (a, c) with c the right/lower neighbour of a: x_c - x_a = (g_a + g_c) / 2; prior term
    wd * (x - (prior - shift)). Outputs ex, ey, wdp (float32 copy of wd), dg, idg, b are
    (H + 2, W + 2) and must be zero on the padding.
    """
    h, w = mask.shape
    for i in nb.prange(h):
        for j in range(w):
            m = mask[i, j]
            ex[i + 1, j + 1] = 1.0 if (m and j + 1 < w and mask[i, j + 1]) else 0.0
            ey[i + 1, j + 1] = 1.0 if (m and i + 1 < h and mask[i + 1, j]) else 0.0
    for i in nb.prange(h):
        for j in range(w):
            if not mask[i, j]:
                continue
            wij = np.float32(wd[i, j])
            wdp[i + 1, j + 1] = wij
            d = np.float64(wij)
            s = d * (prior[i, j] - shift) if wij > 0.0 else 0.0
            if ex[i + 1, j + 1] > 0.0:
                d += 1.0
                s -= 0.5 * (p[i, j] + p[i, j + 1])
            if ex[i + 1, j] > 0.0:
                d += 1.0
                s += 0.5 * (p[i, j - 1] + p[i, j])
            if ey[i + 1, j + 1] > 0.0:
                d += 1.0
                s -= 0.5 * (q[i, j] + q[i + 1, j])
            if ey[i, j + 1] > 0.0:
                d += 1.0
                s += 0.5 * (q[i - 1, j] + q[i, j])
            b[i + 1, j + 1] = s
            if d > 0.0:
                dg[i + 1, j + 1] = d
                idg[i + 1, j + 1] = 1.0 / d


def _assemble(mask: Arr, p: Arr, q: Arr, wd: Arr, log_prior: Arr, shift: float) -> System:
    """The normal equations on the padded grid: (ex, ey, wd, dg, idg) float32 and b float64."""
    h, w = mask.shape
    ex, ey, wdp, dg, idg = (np.zeros((h + 2, w + 2), np.float32) for _ in range(5))
    b = np.zeros((h + 2, w + 2))
    _fine_system(mask, p, q, wd, log_prior, shift, ex, ey, wdp, dg, idg, b)
    return ex, ey, wdp, dg, idg, b


def _check_mask(mask: npt.ArrayLike, shape_hw: tuple[int, ...], name: str = "mask") -> Arr:
    m: Arr = np.asarray(mask)
    if m.shape != shape_hw:
        raise ValueError(f"{name}: expected shape {shape_hw}, got {m.shape}")
    if m.dtype != np.bool_:
        raise ValueError(f"{name}: expected dtype bool, got {m.dtype}")
    if not m.any():
        raise ValueError(f"{name}: expected at least one valid (True) pixel, got none")
    return m


def _check_options(tol: float, max_iter: int) -> None:
    if not (np.isfinite(tol) and 0.0 < tol < 1.0):
        raise ValueError(f"tol: expected a relative residual in (0, 1), got {tol}")
    if int(max_iter) != max_iter or max_iter < 1:
        raise ValueError(f"max_iter: expected a positive integer, got {max_iter}")


def integrate_normals(
    normals: np.ndarray,
    mask: np.ndarray,
    K: np.ndarray,
    *,
    prior_depth_mm: np.ndarray | None = None,
    prior_weight: float | np.ndarray = 1e-2,
    reference_depth_mm: float | None = None,
    tol: float = 1e-6,
    max_iter: int = 200,
) -> DepthResult:
    """Integrate a normal field seen by a pinhole camera into metric depth.

    Every pair of 4-neighbour pixels inside ``mask`` gives one equation on the log depth
    ``t = log z``: ``t_b - t_a = (g_a + g_b) / 2`` where ``g`` is the derivative of ``t`` along the
    pair (pixel units) computed from the normal and the pixel's ray (see the module docstring);
    optional prior equations ``sqrt(w) (t - log z_prior) = 0`` fuse a metric depth. The
    overdetermined system is solved by least squares over the masked domain.

    Parameters
    ----------
    normals : (H, W, 3) float32 or float64
        Unit normals in the left-camera frame (OpenCV: x right, y down, z forward), pointing out
        of the surface towards the camera (``n . ray < 0``), on the *undistorted* left image grid.
        Values outside ``mask`` are ignored (may be NaN).
    mask : (H, W) bool
        Pixels to integrate (True = valid).
    K : (3, 3) array_like
        Intrinsics of the undistorted left image, pixels (``fx`` may differ from ``fy``).
    prior_depth_mm : (H, W) float, optional
        Metric depth along the optical axis (mm, > 0), NaN where unknown, e.g. from binocular
        stereo. Fixes the scale; with a large weight it also fixes the low frequencies. A
        connected part of the mask without any prior pixel gets its scale from
        ``reference_depth_mm``, or, without it, NaN depth and is left out of the result's ``mask``.
    prior_weight : float or (H, W) float, optional
        Weight ``w >= 0`` of each prior equation relative to a neighbour equation (both are in
        log depth). ``w`` sets the length scale ``~ 1 / sqrt(w)`` pixels below which the normals
        dominate. Used in float32 (the solution is the exact least-squares one for those weights).
    reference_depth_mm : float, optional
        Without a prior the solution is known only up to a scale: it is fixed so that the median
        depth over the mask equals this value (mm). Each connected part of the mask that has no
        prior pixel is scaled on its own this way (its relative scale is not observable).
    tol : float, optional
        Relative residual ``||b - A x|| / ||b||`` of the normal equations at which the solve stops
        (:func:`pipeline.solvers.solve_grid_system`).
    max_iter : int, optional
        Maximum number of conjugate-gradient iterations. If it is reached first, the result
        carries its larger ``residual``: compare with ``tol``.

    Returns
    -------
    DepthResult
        ``depth_mm`` (H, W) float64, mm along the left optical axis, NaN outside ``mask``.

    Raises
    ------
    ValueError
        On bad shapes or values: normals inside the mask that are not finite, not unit, or not
        facing the camera; a prior that is not positive; negative weights; neither
        ``prior_depth_mm`` nor ``reference_depth_mm``.
    """
    normals, mask, K = _check_normals_inputs(
        normals, mask, K, prior_depth_mm, reference_depth_mm, tol, max_iter
    )
    box = _mask_box(mask)
    if box is not None:
        return _on_box(
            box, normals, mask, K, prior_depth_mm, prior_weight, reference_depth_mm, tol, max_iter
        )
    wd, log_prior, shift, n_prior = _prior_terms(prior_depth_mm, prior_weight, mask)
    if n_prior == 0 and reference_depth_mm is None:
        raise ValueError(
            "prior_depth_mm: expected at least one depth with a weight > 0 inside the mask to fix the scale, "
            "got none (give reference_depth_mm to integrate without a prior)"
        )
    p, q = _gradients(normals, mask, K)
    system = _assemble(mask, p, q, wd, log_prior, shift)
    del p, q, log_prior  # the largest inputs are not needed by the solve
    x, it, rel, floating = _integrate(mask, system, wd, tol=tol, max_iter=max_iter)
    del system
    depth, result_mask = _metric_depth(x, mask, shift, floating, reference_depth_mm)
    return DepthResult(depth_mm=depth, mask=result_mask, iterations=it, residual=rel)


#: The integration runs on the mask's bounding box (its origin on even rows and columns) when that
#: leaves out at least this share of the grid: the pixels outside have no equation, and every
#: kernel of the solve would pass over them.
BOX_MIN_SAVING = 0.1


def _mask_box(mask: Arr) -> tuple[slice, slice] | None:
    """The mask's bounding box, its first row and column rounded down to even ones (the coarse grids
    aggregate the same 2x2 blocks as on the whole grid), or None when it is nearly the whole grid."""
    box = bounding_box(mask)
    if box is None:
        return None
    r0, c0 = box[0].start - box[0].start % 2, box[1].start - box[1].start % 2
    r1, c1 = box[0].stop, box[1].stop
    if (r1 - r0) * (c1 - c0) > (1.0 - BOX_MIN_SAVING) * mask.size:
        return None
    return slice(r0, r1), slice(c0, c1)


def _on_box(
    box: tuple[slice, slice],
    normals: Arr,
    mask: Arr,
    K: Arr,
    prior_depth_mm: npt.ArrayLike | None,
    prior_weight: float | np.ndarray,
    reference_depth_mm: float | None,
    tol: float,
    max_iter: int,
) -> DepthResult:
    """:func:`integrate_normals` solved on ``box`` of the grid (the camera's principal point moved to
    it), its depth and mask put back on the whole grid. The same equations: only the solve's
    preconditioner sees other coarse grids, and the solution agrees within the solve's ``tol``."""
    rows, cols = box
    K_box = K.copy()
    K_box[0, 2] -= cols.start
    K_box[1, 2] -= rows.start
    weight = np.asarray(prior_weight)
    inner = integrate_normals(
        normals[box],
        mask[box],
        K_box,
        prior_depth_mm=None if prior_depth_mm is None else np.asarray(prior_depth_mm)[box],
        prior_weight=weight[box] if weight.ndim == 2 else prior_weight,
        reference_depth_mm=reference_depth_mm,
        tol=tol,
        max_iter=max_iter,
    )
    depth = np.full(mask.shape, np.nan)
    depth[box] = inner.depth_mm
    result_mask = np.zeros_like(mask)
    result_mask[box] = inner.mask
    return DepthResult(
        depth_mm=depth, mask=result_mask, iterations=inner.iterations, residual=inner.residual
    )


def _check_normals_inputs(
    normals: npt.ArrayLike,
    mask: npt.ArrayLike,
    K: npt.ArrayLike,
    prior_depth_mm: npt.ArrayLike | None,
    reference_depth_mm: float | None,
    tol: float,
    max_iter: int,
) -> tuple[Arr, Arr, Arr]:
    """The arguments of :func:`integrate_normals` checked: (normals, mask, K) as contiguous arrays."""
    n = np.asarray(normals)
    if n.ndim != 3 or n.shape[2] != 3:
        raise ValueError(f"normals: expected shape (H, W, 3), got {n.shape}")
    if n.dtype not in (np.float32, np.float64):
        raise ValueError(f"normals: expected dtype float32 or float64, got {n.dtype}")
    m = _check_mask(mask, n.shape[:2])
    k = check_camera_matrix(K)
    _check_options(tol, max_iter)
    if reference_depth_mm is not None and not (
        np.isfinite(reference_depth_mm) and reference_depth_mm > 0
    ):
        raise ValueError(
            f"reference_depth_mm: expected a positive depth in mm, got {reference_depth_mm}"
        )
    if prior_depth_mm is None and reference_depth_mm is None:
        raise ValueError(
            "prior_depth_mm, reference_depth_mm: expected at least one to fix the scale of the depth, got neither"
        )
    return np.ascontiguousarray(n), np.ascontiguousarray(m), k


def log_depth_gradients(normals: Arr, mask: Arr, kinv: Arr) -> tuple[Arr, Arr, Arr]:
    """The log-depth gradients p = d(log z)/du, q = d(log z)/dv (H, W) float64 that the integration
    takes from unit normals (H, W, 3) on ``mask`` (``kinv``: the grid's pixel (u, v, 1) to its ray,
    ``K^-1`` or a subsampled grid's), and where they are usable (a finite unit normal facing the
    camera; 0 elsewhere)."""
    p, q, usable, _ = _slopes(normals, mask, kinv)
    return p, q, usable


def _slopes(normals: Arr, mask: Arr, kinv: Arr) -> tuple[Arr, Arr, Arr, int]:
    """:func:`log_depth_gradients` and the count of the mask's unusable normals."""
    p = np.empty(mask.shape)
    q = np.empty(mask.shape)
    usable = np.empty(mask.shape, np.bool_)
    bad = _log_depth_gradients(
        np.ascontiguousarray(normals),
        np.ascontiguousarray(mask),
        np.ascontiguousarray(kinv, dtype=np.float64),
        _UNIT_TOL,
        p,
        q,
        usable,
    )
    return p, q, usable, bad


def _gradients(normals: Arr, mask: Arr, K: Arr) -> tuple[Arr, Arr]:
    """The log-depth gradients p = d(log z)/du, q = d(log z)/dv (H, W) float64 of the normals on the mask."""
    p, q, _, bad = _slopes(normals, mask, np.linalg.inv(K))
    if bad:
        raise ValueError(
            f"normals: expected finite unit vectors facing the camera (n . ray < 0) inside the mask, "
            f"got {bad} pixel(s) that are not"
        )
    return p, q


def _metric_depth(
    x: Arr, mask: Arr, shift: float, floating: Floating | None, reference_depth_mm: float | None
) -> tuple[Arr, Arr]:
    """The depth (mm) of the solved log depth ``x`` and the mask of the pixels that have one.

    Parts of the mask without a prior pixel (``floating``, see :func:`_integrate`) are scaled to
    ``reference_depth_mm`` when given, else left out (NaN).
    """
    depth = np.empty(mask.shape)
    _exp_depth(x, mask, shift, depth)
    result_mask = mask.copy()
    if floating is not None:
        if reference_depth_mm is not None:
            _scale_to_median(depth, mask, *floating, float(reference_depth_mm))
        else:  # only with a prior: parts it does not reach have no metric depth
            labels, has_prior = floating[0], floating[3]
            unscaled = ~has_prior[labels]
            depth[unscaled] = np.nan
            result_mask &= ~unscaled
    return depth, result_mask


def integrate_gradient(
    grad_u: np.ndarray,
    grad_v: np.ndarray,
    mask: np.ndarray,
    *,
    tol: float = 1e-6,
    max_iter: int = 200,
) -> HeightResult:
    """Least-squares integration of an orthographic gradient field on a masked grid.

    The same solver as :func:`integrate_normals`, for a field given directly as
    derivatives of a height: every 4-neighbour pair inside ``mask`` gives
    ``h_b - h_a = (g_a + g_b) / 2``.

    Parameters
    ----------
    grad_u : (H, W) float
        ``dh/du``: derivative along image columns (u = column index, rightwards),
        in height units per pixel.
    grad_v : (H, W) float
        ``dh/dv``: derivative along image rows (v = row index, downwards).
    mask : (H, W) bool
        Pixels to integrate; the gradients must be finite there.
    tol, max_iter
        As in :func:`integrate_normals`.

    Returns
    -------
    HeightResult
        ``height`` (H, W) float64 with zero mean over each connected part of
        the mask, NaN outside it.

    Raises
    ------
    ValueError
        On bad shapes, or gradients that are not finite inside the mask.
    """
    grad_u = np.asarray(grad_u, dtype=np.float64)
    grad_v = np.asarray(grad_v, dtype=np.float64)
    if grad_u.ndim != 2:
        raise ValueError(f"grad_u: expected shape (H, W), got {grad_u.shape}")
    if grad_v.shape != grad_u.shape:
        raise ValueError(f"grad_v: expected shape {grad_u.shape} like grad_u, got {grad_v.shape}")
    mask = np.ascontiguousarray(_check_mask(mask, grad_u.shape))
    _check_options(tol, max_iter)
    for name, g in (("grad_u", grad_u), ("grad_v", grad_v)):
        n_bad = int(np.count_nonzero(~np.isfinite(g[mask])))
        if n_bad:
            raise ValueError(
                f"{name}: expected finite values inside the mask, got {n_bad} that are not"
            )
    p = np.where(mask, grad_u, 0.0)
    q = np.where(mask, grad_v, 0.0)
    wd = np.zeros(grad_u.shape, np.float32)
    system = _assemble(mask, p, q, wd, np.zeros(grad_u.shape), 0.0)
    x, it, rel, floating = _integrate(mask, system, wd, tol=tol, max_iter=max_iter)
    if floating is None:
        raise RuntimeError("integrate_gradient: without a prior every part floats, got none")
    labels, n = floating[0], floating[1]
    sums = np.bincount(labels.ravel(), weights=x.ravel(), minlength=n + 1)
    counts = np.bincount(labels.ravel(), minlength=n + 1)
    means = sums / np.maximum(counts, 1)
    means[0] = 0.0
    x = x - means[labels]
    x[~mask] = np.nan
    return HeightResult(height=x, mask=mask.copy(), iterations=it, residual=rel)


def _prior_terms(
    prior_depth_mm: npt.ArrayLike | None, prior_weight: npt.ArrayLike, mask: Arr
) -> tuple[Arr, Arr, float, int]:
    """Prior weights ``wd`` (H, W) float32 (0 where no prior is used), log prior (H, W) float64, a
    shift (the median log prior of a subsample) that centres the unknowns, and the count of pixels
    with a prior."""
    hw = mask.shape
    if prior_depth_mm is None:
        return np.zeros(hw, np.float32), np.zeros(hw), 0.0, 0
    # contiguous (a box of a grid too): the kernel is compiled for one layout
    prior = np.ascontiguousarray(prior_depth_mm, dtype=np.float64)
    if prior.shape != hw:
        raise ValueError(f"prior_depth_mm: expected shape {hw}, got {prior.shape}")
    weight = np.asarray(prior_weight, dtype=np.float64)
    if weight.ndim == 0:
        if not (np.isfinite(weight) and weight >= 0):
            raise ValueError(f"prior_weight: expected a finite weight >= 0, got {float(weight)}")
        weight = weight.reshape(1, 1)
    elif weight.shape != hw:
        raise ValueError(f"prior_weight: expected a scalar or shape {hw}, got {weight.shape}")
    else:
        weight = np.ascontiguousarray(weight)
    wd = np.empty(hw, np.float32)
    log_prior = np.empty(hw)
    bad_prior, bad_weight, n_used = _prior_arrays(
        np.ascontiguousarray(mask), prior, weight, wd, log_prior
    )
    if bad_prior:
        raise ValueError(
            f"prior_depth_mm: expected depths > 0 mm or NaN, got {bad_prior} pixel(s) infinite or <= 0"
        )
    if bad_weight:
        raise ValueError(
            f"prior_weight: expected finite weights >= 0 where the prior is known, got {bad_weight} that are not"
        )
    sample = log_prior[::7, ::7][wd[::7, ::7] > 0]
    if sample.size == 0:
        sample = log_prior[wd > 0]
    shift = float(np.median(sample)) if sample.size else 0.0
    return wd, log_prior, shift, n_used


@nb.njit(cache=True, parallel=True)
def _prior_arrays(
    mask: Arr, prior: Arr, weight: Arr, wd: Arr, log_prior: Arr
) -> tuple[int, int, int]:
    """wd = weight and log_prior = log(prior) where the mask and a prior are given (0 elsewhere);
    ``weight`` is (1, 1) for a scalar. Returns the counts of bad priors, of bad weights and of the
    pixels with a prior."""
    h, w = mask.shape
    scalar = weight.shape[0] == 1 and weight.shape[1] == 1
    bad_prior = 0
    bad_weight = 0
    used = 0
    for i in nb.prange(h):
        for j in range(w):
            wd[i, j] = 0.0
            log_prior[i, j] = 0.0
            z = prior[i, j]
            if not mask[i, j] or np.isnan(z):
                continue
            if not (0.0 < z < np.inf):
                bad_prior += 1
                continue
            wt = weight[0, 0] if scalar else weight[i, j]
            if not (0.0 <= wt < np.inf):
                bad_weight += 1
                continue
            wf = np.float32(wt)  # the weight as the solver uses it
            if wf > 0.0:
                wd[i, j] = wf
                log_prior[i, j] = np.log(z)
                used += 1
    return bad_prior, bad_weight, used


def _integrate(
    mask: Arr, system: System, wd: Arr, *, tol: float, max_iter: int
) -> tuple[Arr, int, float, Floating | None]:
    """Solve and find the parts without prior; returns (x, iterations, residual, floating) with
    ``x`` (H, W) float64 (a view) and ``floating = (labels, n, n_floating, has_prior)`` describing
    the connected parts of the mask that have no prior pixel, or None when every part has one."""
    x, it, rel = solve_grid_system(*system, tol=tol, max_iter=max_iter)
    labels, n = scipy.ndimage.label(mask)
    has_prior = _parts_with_prior(labels, wd, n)
    has_prior[0] = True
    if has_prior.all():
        return x, it, rel, None
    return x, it, rel, (labels, n, int(np.count_nonzero(~has_prior)), has_prior)


@nb.njit(nogil=True, cache=True)
def _parts_with_prior(labels: Arr, wd: Arr, n: int) -> Arr:
    out = np.zeros(n + 1, np.bool_)
    h, w = labels.shape
    for i in range(h):
        for j in range(w):
            if wd[i, j] > 0.0:
                out[labels[i, j]] = True
    return out


@nb.njit(cache=True, parallel=True)
def _exp_depth(x: Arr, mask: Arr, shift: float, depth: Arr) -> None:
    """depth = exp(x + shift) on the mask, NaN elsewhere."""
    h, w = mask.shape
    for i in nb.prange(h):
        for j in range(w):
            depth[i, j] = np.exp(x[i, j] + shift) if mask[i, j] else np.nan


@nb.njit(nogil=True, cache=True)
def _gather(values: Arr, labels: Arr, label: int | np.integer[Any], out: Arr) -> int:
    """The values of the cells with ``labels == label`` (label -1: every cell with label > 0), in
    row-major order; returns how many."""
    k = 0
    h, w = labels.shape
    for i in range(h):
        for j in range(w):
            lab = labels[i, j]
            if (label < 0 and lab > 0) or lab == label:
                out[k] = values[i, j]
                k += 1
    return k


@nb.njit(nogil=True, cache=True)
def _scale_parts(depth: Arr, labels: Arr, factor: Arr) -> None:
    """depth *= factor[label] on the cells with label > 0."""
    h, w = labels.shape
    for i in range(h):
        for j in range(w):
            lab = labels[i, j]
            if lab > 0:
                depth[i, j] *= factor[lab]


def _scale_to_median(
    depth: Arr,
    mask: Arr,
    labels: Arr,
    n: int,
    n_floating: int,
    has_prior: Arr,
    reference: float,
) -> None:
    """Scale each part of the mask without prior so that its median depth is ``reference``, in place."""
    factor = np.ones(n + 1)
    if n == 1:
        buf = np.empty(int(np.count_nonzero(mask)))
        _gather(depth, labels, 1, buf)
        factor[1] = reference / np.median(buf, overwrite_input=True)
    else:
        counts = np.bincount(labels.ravel(), minlength=n + 1)
        buf = np.empty(int(counts[1:].max()))
        for part in np.flatnonzero(~has_prior):
            k = _gather(depth, labels, part, buf)
            factor[part] = reference / np.median(buf[:k])
    _scale_parts(depth, labels, factor)
