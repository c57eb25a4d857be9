"""Robust nonlinear least squares for small models over many residuals (Levenberg-Marquardt, soft-L1 loss)."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import numpy.typing as npt


def robust_gauss_newton(
    fun: Callable[[np.ndarray], np.ndarray],
    x0: np.ndarray,
    steps: np.ndarray,
    f_scale: float,
    *,
    max_iter: int = 60,
    rtol: float = 1e-12,
    jacobian: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None,
) -> tuple[np.ndarray, float]:
    """Levenberg-Marquardt on the soft-L1 cost ``sum 2 f^2 (sqrt(1 + (r/f)^2) - 1)``.

    Iteratively reweighted normal equations (weights ``1/sqrt(1 + (r/f)^2)``) with the model's
    Jacobian, or a forward-difference one. A few parameters and many residuals: the normal equations
    are tiny, each step costs ~p+2 residual evaluations (~2 with the model's Jacobian).

    Parameters
    ----------
    fun : callable
        ``fun(x)`` -> residuals (M,) float64.
    x0 : (P,) array_like of float
        Start.
    steps : (P,) float
        Forward-difference step of each parameter.
    f_scale : float
        Soft-L1 scale ``f`` (residual units): residuals beyond it weigh less and less.
    max_iter : int
    rtol : float
        Stop when a step lowers the cost by less than ``rtol`` of it, or moves every parameter by
        less than 1e-3 of its difference step.
    jacobian : callable, optional
        ``jacobian(x, r)`` -> (M, P) derivatives of the residuals ``r = fun(x)``; default: forward
        differences of ``fun`` with ``steps``.

    Returns
    -------
    x : (P,) float64
    cost : float
    """

    def cost_of(r: npt.NDArray[np.float64]) -> float:
        return float(np.sum(2 * f_scale**2 * (np.sqrt(1 + (r / f_scale) ** 2) - 1)))

    x = np.asarray(x0, dtype=np.float64).copy()
    r = fun(x)
    cost = cost_of(r)
    lam = 1e-6
    for _ in range(max_iter):
        if jacobian is not None:
            J = jacobian(x, r)
        else:
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


def robust_scale(r: np.ndarray) -> float:
    """The robust standard deviation of residuals: 1.4826 times their median absolute deviation."""
    return float(1.4826 * np.median(np.abs(r - np.median(r))))
