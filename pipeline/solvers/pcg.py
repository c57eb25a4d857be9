"""Preconditioned conjugate gradients for a grid system (see :mod:`pipeline.solvers`).

The per-cell kernels (matrix-vector product, residual, vector updates) are parallel over rows.
"""

from __future__ import annotations

from typing import Any

import numba as nb
import numpy as np
import numpy.typing as npt

from .multigrid import FASTMATH, Multigrid

#: An array argument of the kernels (their dtypes are set by the callers).
Arr = npt.NDArray[Any]


def solve_grid_system(
    ex: np.ndarray,
    ey: np.ndarray,
    wd: np.ndarray,
    dg: np.ndarray,
    idg: np.ndarray,
    b: np.ndarray,
    *,
    tol: float,
    max_iter: int,
) -> tuple[np.ndarray, int, float]:
    """Solve a grid system (see :mod:`pipeline.solvers`) by multigrid-preconditioned conjugate gradients.

    The start is a full-multigrid approximation (nested iteration); each iteration then divides
    the residual by about 8, independently of the grid's size.

    Parameters
    ----------
    ex, ey, wd, dg, idg : (H + 2, W + 2) float32
        The operator on the padded grid.
    b : (H + 2, W + 2) float64
        The right-hand side, 0 on the padding and outside the system.
    tol : float
        Relative residual ``||b - A x|| / ||b||`` at which the iterations stop.
    max_iter : int
        Most conjugate-gradient iterations.

    Returns
    -------
    x : (H, W) float64
        The solution (a view of a padded array; 0 outside the system).
    iterations : int
    residual : float
        The relative residual reached.
    """
    mg = Multigrid(ex, ey, wd, dg, idg)
    x = mg.full_multigrid(b).astype(np.float64)
    it, rel = pcg(ex, ey, wd, b, x, mg, tol=tol, max_iter=max_iter)
    return x[1:-1, 1:-1], it, rel


def pcg(
    ex: np.ndarray,
    ey: np.ndarray,
    wd: np.ndarray,
    b: np.ndarray,
    x: np.ndarray,
    precond: Multigrid,
    *,
    tol: float,
    max_iter: int,
) -> tuple[int, float]:
    """Preconditioned conjugate gradients on the padded grid, from ``x`` in place (cells outside the system stay 0).

    Parameters
    ----------
    ex, ey, wd : (H + 2, W + 2) float32
        The operator (the diagonal is summed in float64 from these weights).
    b : (H + 2, W + 2) float64
    x : (H + 2, W + 2) float64
        The start; the solution on return.
    precond : Multigrid
        ``precond.apply(r)`` gives ``M^-1 r`` and ``r . M^-1 r``.
    tol, max_iter
        As in :func:`solve_grid_system`.

    Returns
    -------
    (int, float)
        Iterations and the relative residual ``||b - A x|| / ||b||``.
    """
    bnorm = float(np.sqrt(_norm2(b)))  # not np.dot: BLAS threads would spin beside the solve
    if bnorm == 0.0:
        x[...] = 0.0
        return 0, 0.0
    r = np.zeros(b.shape)
    rel = np.sqrt(_residual_norm2(ex, ey, wd, x, b, r)) / bnorm
    it = 0
    pdir = np.zeros(b.shape)
    ap = np.zeros(b.shape)
    rz_old = 1.0
    while rel > tol and it < max_iter:
        z, rz = precond.apply(r)
        pap = _direction_matvec(z, rz / rz_old if it else 0.0, pdir, ex, ey, wd, ap)
        if (
            not pap > 0.0
        ):  # the direction lies in the null space (constants of a part): nothing left to do
            break
        it += 1
        rel = np.sqrt(_cg_step(rz / pap, pdir, ap, x, r)) / bnorm
        rz_old = rz
    return it, float(rel)


@nb.njit(cache=True, fastmath=FASTMATH, parallel=True)
def _residual_norm2(ex: Arr, ey: Arr, wd: Arr, x: Arr, b: Arr, r: Arr) -> float:
    """r = b - A x with the diagonal summed in float64 from the weights; returns ||r||^2."""
    h, w = wd.shape[0] - 2, wd.shape[1] - 2
    acc = 0.0
    for i in nb.prange(1, h + 1):
        for j in range(1, w + 1):
            e, wst, s_, n_ = ex[i, j], ex[i, j - 1], ey[i, j], ey[i - 1, j]
            d = np.float64(wd[i, j]) + e + wst + s_ + n_
            s = (
                b[i, j]
                - d * x[i, j]
                + e * x[i, j + 1]
                + wst * x[i, j - 1]
                + s_ * x[i + 1, j]
                + n_ * x[i - 1, j]
            )
            r[i, j] = s
            acc += s * s
    return acc


@nb.njit(cache=True, fastmath=FASTMATH, parallel=True)
def _direction_matvec(z: Arr, beta: float, pdir: Arr, ex: Arr, ey: Arr, wd: Arr, ap: Arr) -> float:
    """p = z + beta p, then ap = A p (diagonal summed in float64 from the weights); returns p . A p."""
    h, w = wd.shape[0] - 2, wd.shape[1] - 2
    for i in nb.prange(1, h + 1):
        for j in range(1, w + 1):
            pdir[i, j] = z[i, j] + beta * pdir[i, j]
    acc = 0.0
    for i in nb.prange(1, h + 1):
        for j in range(1, w + 1):
            e, wst, s_, n_ = ex[i, j], ex[i, j - 1], ey[i, j], ey[i - 1, j]
            d = np.float64(wd[i, j]) + e + wst + s_ + n_
            s = d * pdir[i, j] - (
                e * pdir[i, j + 1]
                + wst * pdir[i, j - 1]
                + s_ * pdir[i + 1, j]
                + n_ * pdir[i - 1, j]
            )
            ap[i, j] = s
            acc += s * pdir[i, j]
    return acc


@nb.njit(cache=True, fastmath=FASTMATH, parallel=True)
def _norm2(a: Arr) -> float:
    h, w = a.shape
    acc = 0.0
    for i in nb.prange(h):
        for j in range(w):
            acc += a[i, j] * a[i, j]
    return acc


@nb.njit(cache=True, fastmath=FASTMATH, parallel=True)
def _cg_step(alpha: float, pdir: Arr, ap: Arr, x: Arr, r: Arr) -> float:
    """x += alpha p, r -= alpha A p; returns ||r||^2."""
    h, w = x.shape
    acc = 0.0
    for i in nb.prange(h):
        for j in range(w):
            x[i, j] += alpha * pdir[i, j]
            s = r[i, j] - alpha * ap[i, j]
            r[i, j] = s
            acc += s * s
    return acc
