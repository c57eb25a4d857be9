"""The area of the surface patch each pixel sees (the verdict's and details.json's area weights)."""

from __future__ import annotations

from typing import Any

import numba
import numpy as np
import numpy.typing as npt

#: An array argument of the kernel (its dtype is set by the caller).
Arr = npt.NDArray[Any]


def pixel_area_mm2(
    depth_mm: np.ndarray, normals: np.ndarray, rays: np.ndarray, K: np.ndarray
) -> np.ndarray:
    """(H, W) area (mm^2) of the surface patch each pixel sees.

    A pixel spans the solid angle ``cos^3(a) / (fx fy)`` (``a``: its ray's angle to
    the optical axis); at distance ``z / cos(a)`` on a surface tilted by ``t``
    against the ray that is ``z^2 / (fx fy |n . r|)`` with ``r = K^-1 (u, v, 1)``.

    Parameters
    ----------
    depth_mm : (H, W) float64
        Depth along the optical axis, NaN where unknown.
    normals : (H, W, 3) float
        Unit normals, NaN where unknown.
    rays : (H, W, 3) float64
        ``K^-1 (u, v, 1)``.
    K : (3, 3) float64

    Returns
    -------
    (H, W) float64
        NaN where the depth or the normal is unknown.
    """
    area = np.empty(depth_mm.shape)
    _areas(
        np.ascontiguousarray(depth_mm, dtype=np.float64),
        np.ascontiguousarray(normals),
        np.ascontiguousarray(rays, dtype=np.float64),
        float(K[0, 0] * K[1, 1]),
        area,
    )
    return area


@numba.njit(nogil=True, cache=True, error_model="numpy")
def _areas(
    depth: Arr, normals: Arr, rays: Arr, fxfy: float, out: Arr
) -> None:  # pragma: no cover - compiled
    """out = depth^2 / (fxfy |n . r|) in float64, the dot product summed as ``np.einsum("hwc,hwc->hw")``
    sums it ((x + z) + y), so that the areas are the array expression's to the bit; single-threaded
    (it runs on a worker beside the registration)."""
    h, w = depth.shape
    for i in range(h):
        for j in range(w):
            x = np.float64(normals[i, j, 0]) * rays[i, j, 0]
            y = np.float64(normals[i, j, 1]) * rays[i, j, 1]
            z = np.float64(normals[i, j, 2]) * rays[i, j, 2]
            d = depth[i, j]
            out[i, j] = d * d / (fxfy * abs((x + z) + y))
