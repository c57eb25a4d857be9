"""Woodham's least squares: b = rho n per pixel from all its valid samples (the plain Lambertian baseline).

Per pixel, ``(sum_k v_k l_k l_k^T) b = sum_k v_k I_k l_k`` over its valid samples (``v_k``). Pixels
with all samples valid share one pseudo-inverse (one float32 matrix product); the others solve
their own 3x3 system (adjugate, a compiled loop over pixels).
"""

from __future__ import annotations

from typing import Any

import numba
import numpy as np
import numpy.typing as npt

from .field import DEGENERATE, FEW, OK, OUTSIDE
from .solve3 import DEGENERATE_RATIO, adjugate3, adjugate_times

#: An array argument of the kernels (their dtypes are set by the callers).
Arr = npt.NDArray[Any]


def lstsq(
    images: np.ndarray, L: np.ndarray, mask: np.ndarray, valid: np.ndarray | None, min_samples: int
) -> tuple[np.ndarray, np.ndarray]:
    """Woodham least squares of every mask pixel.

    Parameters
    ----------
    images : (N, H, W) float32
        Intensity-normalised images (checked by :func:`pipeline.surface.normals.estimate_normals`).
    L : (N, 3) float64
        Unit light directions, spanning 3D.
    mask : (H, W) bool
    valid : (N, H, W) bool or None
        Usable samples; None: all.
    min_samples : int
        Fewer valid samples than this: status :data:`~pipeline.surface.normals.field.FEW`.

    Returns
    -------
    b : (3, H, W) float32
        rho n.
    status : (H, W) int8
        Status codes of :mod:`pipeline.surface.normals.field`.
    """
    n, h, w = images.shape
    flat = images.reshape(n, h * w)
    # Pixels with all samples valid share one pseudo-inverse (the light set spans 3D, checked).
    # Computed over the whole frame: cheaper than gathering the mask when the plate fills it.
    b = (np.linalg.pinv(L).astype(np.float32) @ flat).reshape(3, h, w)
    status = np.where(mask, OK, OUTSIDE).astype(np.int8)
    if valid is not None:
        # Pixels with some invalid samples: their own normal equations, solved per pixel in
        # compiled code (numpy's batched solve over gathered pixels was much slower).
        _lstsq_partial_kernel(images, valid, mask, L, int(min_samples), b, status)
    return b, status


@numba.njit(parallel=True, cache=True)
def _lstsq_partial_kernel(
    images: Arr, valid: Arr, mask: Arr, L: Arr, min_samples: int, b: Arr, status: Arr
) -> None:
    """Least squares over the valid samples of every mask pixel that has an invalid one.

    (sum_k v_k l_k l_k^T) b = sum_k v_k I_k l_k, solved by the adjugate; b (3, H, W) and
    status (H, W) are updated in place (FEW / DEGENERATE where it cannot be solved).
    """
    n, h, w = images.shape
    for i in numba.prange(h):
        for j in range(w):
            if not mask[i, j]:
                continue
            m = 0
            for k in range(n):
                m += valid[k, i, j]
            if m == n:
                continue  # all valid: the shared pseudo-inverse already gave b
            if m < min_samples:
                status[i, j] = FEW
                continue
            m00 = m01 = m02 = m11 = m12 = m22 = 0.0
            r0 = r1 = r2 = 0.0
            for k in range(n):
                if valid[k, i, j]:
                    lx, ly, lz = L[k, 0], L[k, 1], L[k, 2]
                    x = images[k, i, j]
                    m00 += lx * lx
                    m01 += lx * ly
                    m02 += lx * lz
                    m11 += ly * ly
                    m12 += ly * lz
                    m22 += lz * lz
                    r0 += x * lx
                    r1 += x * ly
                    r2 += x * lz
            c00, c01, c02, c11, c12, c22, det = adjugate3(m00, m01, m02, m11, m12, m22)
            tr = (m00 + m11 + m22) / 3.0
            if not det > DEGENERATE_RATIO * tr * tr * tr:
                status[i, j] = DEGENERATE
                continue
            x0, x1, x2 = adjugate_times(c00, c01, c02, c11, c12, c22, r0, r1, r2)
            b[0, i, j] = x0 / det
            b[1, i, j] = x1 / det
            b[2, i, j] = x2 / det
