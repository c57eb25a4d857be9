"""Geometric multigrid for a masked grid Laplacian plus a diagonal: the conjugate-gradient preconditioner.

A system on an (H, W) grid is held on arrays padded with one cell of zeros on every side (interior
cells 1..H, 1..W; see :mod:`pipeline.solvers`). :class:`Multigrid` builds the hierarchy by 2x2
aggregation and applies one symmetric V(1,1)-cycle (red-black Gauss-Seidel smoothing) in float32.
The cycle's kernels are single-threaded and fuse several sweeps into one pass over memory (a row
wavefront; the solve is memory-bound).
"""

from __future__ import annotations

from typing import Any

import numba as nb
import numpy as np
import numpy.typing as npt

#: An array argument of the kernels (their dtypes are set by the callers).
Arr = npt.NDArray[Any]

#: LLVM fast-math flags for the solver kernels: reassociation lets sums and dot products
#: vectorise; NaN/Inf semantics are kept (inputs are checked before).
FASTMATH = {"reassoc", "contract", "arcp"}
#: Coarsest multigrid level: at most this many cells, solved by Gauss-Seidel sweeps.
_COARSEST_CELLS = 64
#: Symmetric Gauss-Seidel sweeps that solve the coarsest level (<= 64 cells: error / 1e5 or better).
_COARSEST_SWEEPS = 100


class Multigrid:
    """Symmetric V(1,1)-cycle for the masked Laplacian + diagonal, in float32.

    Coarse operators are Galerkin products with piecewise-constant 2x2 prolongation, with the
    edge part scaled by ``edge_scale`` (1/2 corrects the energy overestimate of piecewise-constant
    interpolation of a smooth field in 2-D); the diagonal part is kept exact. Smoothing is red-black
    Gauss-Seidel (red then black before, black then red after), so one cycle from a zero guess
    is a symmetric positive (semi)definite operator and can precondition conjugate gradients.

    Parameters
    ----------
    ex, ey, wd, dg, idg : (H + 2, W + 2) float32
        The finest level's operator (see :mod:`pipeline.solvers`); kept, not copied.
    edge_scale : float
        Scale of the coarse levels' edge weights.
    """

    def __init__(
        self,
        ex: np.ndarray,
        ey: np.ndarray,
        wd: np.ndarray,
        dg: np.ndarray,
        idg: np.ndarray,
        *,
        edge_scale: float = 0.5,
    ) -> None:
        lv = _Level(ex, ey, wd, dg, idg, with_rhs=False)
        self.levels = [lv]
        while (lv.dg.shape[0] - 2) * (lv.dg.shape[1] - 2) > _COARSEST_CELLS:
            hc, wc = (
                (lv.dg.shape[0] - 1) // 2,
                (lv.dg.shape[1] - 1) // 2,
            )  # ceil(h / 2), ceil(w / 2)
            arrs = [np.zeros((hc + 2, wc + 2), np.float32) for _ in range(5)]
            _coarsen(lv.ex, lv.ey, lv.wd, np.float32(edge_scale), *arrs)
            lv = _Level(*arrs)
            self.levels.append(lv)

    def apply(self, r: np.ndarray) -> tuple[np.ndarray, float]:
        """z = M^-1 r (one V-cycle from a zero guess) and r . z; z is a float32 padded grid, a
        buffer that the next call overwrites."""
        rz = self._vcycle(0, r, zero_start=True)
        return self.levels[0].x, rz

    def full_multigrid(self, b: np.ndarray) -> np.ndarray:
        """Approximate solution of A x = b by nested iteration (coarse solve, interpolated, one
        V-cycle per level); float32 padded grid, a buffer that the next call overwrites."""
        lv = self.levels
        rhs = [b] + [lv[k].rhs for k in range(1, len(lv))]
        for k in range(len(lv) - 1):
            _restrict(rhs[k], rhs[k + 1])
        self._vcycle(len(lv) - 1, rhs[-1], zero_start=True)
        for k in range(len(lv) - 2, -1, -1):
            _interpolate(lv[k + 1].x, lv[k + 1].dg, lv[k].idg, lv[k].x)
            # lv[k].b is overwritten below level k only, so it still holds the restricted b.
            self._vcycle(k, rhs[k], zero_start=False)
        return lv[0].x

    def _vcycle(self, k: int, b: np.ndarray, *, zero_start: bool) -> float:
        lv = self.levels[k]
        if k == len(self.levels) - 1:
            return float(_coarsest_solve(lv.ex, lv.ey, lv.idg, lv.x, b, _COARSEST_SWEEPS))
        nxt = self.levels[k + 1]
        _presmooth_restrict(lv.ex, lv.ey, lv.dg, lv.idg, lv.x, b, nxt.rhs, zero_start)
        self._vcycle(k + 1, nxt.rhs, zero_start=True)
        return float(_prolong_postsmooth(lv.ex, lv.ey, lv.idg, lv.x, b, nxt.x))


class _Level:
    """One level of the multigrid hierarchy: its operator and work buffers (padded grids)."""

    def __init__(
        self, ex: Arr, ey: Arr, wd: Arr, dg: Arr, idg: Arr, *, with_rhs: bool = True
    ) -> None:
        self.ex, self.ey, self.wd, self.dg, self.idg = ex, ey, wd, dg, idg
        self.x = np.zeros(dg.shape, dg.dtype)
        # the finest level's right-hand side is always given by the caller
        self.b = np.zeros(dg.shape, dg.dtype) if with_rhs else None

    @property
    def rhs(self) -> Arr:
        """The level's right-hand side buffer (a coarse level's; the finest one's is the caller's)."""
        if self.b is None:
            raise ValueError("the finest level has no right-hand side buffer: the caller gives it")
        return self.b


@nb.njit(nogil=True, cache=True, fastmath=FASTMATH)
def _presmooth_restrict(
    ex: Arr, ey: Arr, dg: Arr, idg: Arr, x: Arr, b: Arr, bc: Arr, zero_start: bool
) -> None:
    """Red then black Gauss-Seidel half-sweeps on A x = b, then bc = P^T (b - A x).

    One pass over the rows: at step t, red row t, black row t - 1, residual of row t - 2.
    With ``zero_start`` the initial guess is x = 0 (x is overwritten), else x is the guess.
    A half-sweep computes the update of the whole row into a buffer (a contiguous loop that
    vectorises) and copies back the cells of its colour.
    """
    h, w = dg.shape[0] - 2, dg.shape[1] - 2
    tmp = np.empty(w + 2, x.dtype)
    for t in range(1, h + 3):
        for phase in range(2):  # 0: red half-sweep of row t, 1: black half-sweep of row t - 1
            i = t - phase
            if i < 1 or i > h:
                continue
            j0 = 1 + (i + 1 + phase) % 2
            if zero_start and phase == 0:
                for j in range(1, w + 1):
                    tmp[j] = b[i, j] * idg[i, j]
                    x[i, j] = 0.0
            else:
                for j in range(1, w + 1):
                    tmp[j] = (
                        b[i, j]
                        + ex[i, j] * x[i, j + 1]
                        + ex[i, j - 1] * x[i, j - 1]
                        + ey[i, j] * x[i + 1, j]
                        + ey[i - 1, j] * x[i - 1, j]
                    ) * idg[i, j]
            for j in range(j0, w + 1, 2):
                x[i, j] = tmp[j]
        i = t - 2
        if i < 1:
            continue
        for j in range(1, w + 1):
            tmp[j] = (
                b[i, j]
                - dg[i, j] * x[i, j]
                + ex[i, j] * x[i, j + 1]
                + ex[i, j - 1] * x[i, j - 1]
                + ey[i, j] * x[i + 1, j]
                + ey[i - 1, j] * x[i - 1, j]
            )
        tmp[w + 1] = 0.0
        ic = (i + 1) // 2
        if i % 2 == 1:
            for jc in range(1, (w + 1) // 2 + 1):
                bc[ic, jc] = tmp[2 * jc - 1] + tmp[2 * jc]
        else:
            for jc in range(1, (w + 1) // 2 + 1):
                bc[ic, jc] += tmp[2 * jc - 1] + tmp[2 * jc]


@nb.njit(nogil=True, cache=True, fastmath=FASTMATH)
def _prolong_postsmooth(ex: Arr, ey: Arr, idg: Arr, x: Arr, b: Arr, xc: Arr) -> float:
    """x += P xc, then black then red Gauss-Seidel half-sweeps; returns b . x (final x).

    One pass over the rows: at step t, prolongation into row t, black row t - 1, red row t - 2.
    The prolongation also writes cells outside the system; the sweeps reset them to 0 (idg = 0),
    and their edges have weight 0 in between. Half-sweeps as in :func:`_presmooth_restrict`.
    """
    h, w = idg.shape[0] - 2, idg.shape[1] - 2
    tmp = np.empty(w + 2, x.dtype)
    acc = 0.0
    for t in range(1, h + 3):
        if t <= h:
            ic = (t + 1) // 2
            for j in range(1, w + 1):
                x[t, j] += xc[ic, (j + 1) // 2]
        for phase in (1, 2):  # 1: black half-sweep of row t - 1, 2: red half-sweep of row t - 2
            i = t - phase
            if i < 1 or i > h:
                continue
            for j in range(1, w + 1):
                tmp[j] = (
                    b[i, j]
                    + ex[i, j] * x[i, j + 1]
                    + ex[i, j - 1] * x[i, j - 1]
                    + ey[i, j] * x[i + 1, j]
                    + ey[i - 1, j] * x[i - 1, j]
                ) * idg[i, j]
            for j in range(1 + (i + 1 + phase) % 2, w + 1, 2):
                x[i, j] = tmp[j]
        i = t - 2
        if i >= 1:
            for j in range(1, w + 1):
                acc += np.float64(b[i, j]) * np.float64(x[i, j])
    return acc


@nb.njit(nogil=True, cache=True, fastmath=FASTMATH)
def _coarsen(
    ex: Arr,
    ey: Arr,
    wd: Arr,
    edge_scale: float | np.floating[Any],
    exc: Arr,
    eyc: Arr,
    wdc: Arr,
    dgc: Arr,
    idgc: Arr,
) -> None:
    """Operator of the next level by 2x2 aggregation: coarse cell (I, J) is the block of fine cells
    2I - 1, 2I by 2J - 1, 2J (padded indices); fine edges between two blocks are summed. The
    coarse arrays must be zero on the padding."""
    hc, wc = wdc.shape[0] - 2, wdc.shape[1] - 2
    for ic in range(1, hc + 1):
        i0, i1 = 2 * ic - 1, 2 * ic
        for jc in range(1, wc + 1):
            j0, j1 = 2 * jc - 1, 2 * jc
            wdc[ic, jc] = wd[i0, j0] + wd[i0, j1] + wd[i1, j0] + wd[i1, j1]
            exc[ic, jc] = edge_scale * (ex[i0, j1] + ex[i1, j1])
            eyc[ic, jc] = edge_scale * (ey[i1, j0] + ey[i1, j1])
    for ic in range(1, hc + 1):
        for jc in range(1, wc + 1):
            d = wdc[ic, jc] + exc[ic, jc] + exc[ic, jc - 1] + eyc[ic, jc] + eyc[ic - 1, jc]
            dgc[ic, jc] = d
            idgc[ic, jc] = 1.0 / d if d > 0.0 else 0.0


@nb.njit(nogil=True, cache=True, fastmath=FASTMATH)
def _restrict(r: Arr, rc: Arr) -> None:
    """rc = P^T r: sums over the 2x2 blocks (padded grids)."""
    hc, wc = rc.shape[0] - 2, rc.shape[1] - 2
    for ic in range(1, hc + 1):
        for jc in range(1, wc + 1):
            rc[ic, jc] = (
                r[2 * ic - 1, 2 * jc - 1]
                + r[2 * ic - 1, 2 * jc]
                + r[2 * ic, 2 * jc - 1]
                + r[2 * ic, 2 * jc]
            )


@nb.njit(nogil=True, cache=True, fastmath=FASTMATH)
def _interpolate(xc: Arr, dgc: Arr, idg: Arr, x: Arr) -> None:
    """x = bilinear interpolation of the coarse cells in the system (cell-centred: a fine cell lies
    1/4 of a coarse cell from its block's centre); cells outside the system get 0. Used for the
    nested-iteration start only (the V-cycle uses piecewise-constant prolongation)."""
    h, w = x.shape[0] - 2, x.shape[1] - 2
    for i in range(1, h + 1):
        ic0 = (i + 1) // 2
        ic1 = ic0 - 1 if i % 2 == 1 else ic0 + 1
        for j in range(1, w + 1):
            if idg[i, j] == 0.0:
                x[i, j] = 0.0
                continue
            jc0 = (j + 1) // 2
            jc1 = jc0 - 1 if j % 2 == 1 else jc0 + 1
            s = 0.0
            sw = 0.0
            for ic, wi in ((ic0, 0.75), (ic1, 0.25)):
                for jc, wj in ((jc0, 0.75), (jc1, 0.25)):
                    if dgc[ic, jc] != 0.0:
                        s += wi * wj * xc[ic, jc]
                        sw += wi * wj
            x[i, j] = s / sw if sw > 0.0 else xc[ic0, jc0]


@nb.njit(nogil=True, cache=True, fastmath=FASTMATH)
def _coarsest_solve(ex: Arr, ey: Arr, idg: Arr, x: Arr, b: Arr, sweeps: int) -> float:
    """x ~ A^-1 b on the coarsest grid by ``sweeps`` symmetric red-black Gauss-Seidel sweeps from
    zero, in the palindromic order red, black, red, ..., black, red (a symmetric operator);
    returns b . x."""
    h, w = idg.shape[0] - 2, idg.shape[1] - 2
    x[:, :] = 0.0
    for k in range(2 * sweeps + 1):
        for i in range(1, h + 1):
            for j in range(1 + (i + 1 + k) % 2, w + 1, 2):
                x[i, j] = (
                    b[i, j]
                    + ex[i, j] * x[i, j + 1]
                    + ex[i, j - 1] * x[i, j - 1]
                    + ey[i, j] * x[i + 1, j]
                    + ey[i - 1, j] * x[i - 1, j]
                ) * idg[i, j]
    acc = 0.0
    for i in range(1, h + 1):
        for j in range(1, w + 1):
            acc += np.float64(b[i, j]) * np.float64(x[i, j])
    return acc
