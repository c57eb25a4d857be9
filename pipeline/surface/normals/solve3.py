"""The per-pixel 3x3 normal equations of photometric stereo, solved in compiled kernels.

Every estimator fits b = rho n (3 unknowns) per pixel from ``M b = r`` with the symmetric
``M = sum_k w_k l_k l_k^T``. The kernels solve it by the adjugate: ``b = adj(M) r / det(M)``,
six cofactors shared by every right-hand side. The helpers are inlined into the calling kernel
(``inline="always"``): the arithmetic is the caller's, in its precision and fast-math flags. The
robust estimator's vectorised float32 loop (``robust._fit_row``) keeps the same solve written out
(through the helpers LLVM compiles that loop differently and the last bit of its results changes).
"""

from __future__ import annotations

import numba

#: A fit needs at least this many samples (3 unknowns).
MIN_FIT = 3

#: A per-pixel system sum_k l_k l_k^T is degenerate (lights nearly coplanar or too few)
#: when det(M) / (trace(M) / 3)^3 falls below this (1 for an isotropic set of lights,
#: 0 for coplanar ones). 1e-4 ~ a condition number of ~1e3 in the worst direction.
DEGENERATE_RATIO = 1e-4


@numba.njit(nogil=True, cache=True, inline="always")
def adjugate3(
    m00: float, m01: float, m02: float, m11: float, m12: float, m22: float
) -> tuple[float, float, float, float, float, float, float]:
    """The adjugate and the determinant of the symmetric matrix ``[[m00, m01, m02], [m01, m11, m12], [m02, m12, m22]]``.

    Returns
    -------
    tuple
        ``(c00, c01, c02, c11, c12, c22, det)``: the adjugate's upper triangle (it is symmetric
        too) and ``det``; the inverse is ``adj / det``.
    """
    c00 = m11 * m22 - m12 * m12
    c01 = m02 * m12 - m01 * m22
    c02 = m01 * m12 - m02 * m11
    c11 = m00 * m22 - m02 * m02
    c12 = m01 * m02 - m00 * m12
    c22 = m00 * m11 - m01 * m01
    det = m00 * c00 + m01 * c01 + m02 * c02
    return c00, c01, c02, c11, c12, c22, det


@numba.njit(nogil=True, cache=True, inline="always")
def adjugate_times(
    c00: float,
    c01: float,
    c02: float,
    c11: float,
    c12: float,
    c22: float,
    r0: float,
    r1: float,
    r2: float,
) -> tuple[float, float, float]:
    """``adj r`` for the symmetric adjugate of :func:`adjugate3` and a right-hand side ``(r0, r1, r2)``.

    Divided by ``det`` (or multiplied by its reciprocal) it is the solution of ``M b = r``.
    """
    return (
        c00 * r0 + c01 * r1 + c02 * r2,
        c01 * r0 + c11 * r1 + c12 * r2,
        c02 * r0 + c12 * r1 + c22 * r2,
    )
