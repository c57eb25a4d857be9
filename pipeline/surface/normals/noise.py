"""The photometric images' own noise, measured on the plate (Immerkaer's estimator)."""

from __future__ import annotations

from typing import Any

import numba
import numpy as np
import numpy.typing as npt

#: An array argument of the kernel (its dtype is set by the caller).
Arr = npt.NDArray[Any]


def image_noise(images: np.ndarray, mask: np.ndarray, *, side: int = 384) -> np.ndarray:
    """Each image's noise, in its own units: Immerkaer's estimator on a window of the plate.

    The estimator (the mean absolute response to a Laplacian difference of two Laplacians, which
    cancels planar intensity, times sqrt(pi / 2) / 6) is taken on a window of at most ``side`` px
    around the plate's centre (the noise is the sensor's, the same everywhere; a window keeps it
    cheap at 2448x2048), on the plate's pixels. Texture finer than a few pixels reads as noise too,
    which only makes the figure larger.

    Parameters
    ----------
    images : (N, H, W) float
    mask : (H, W) bool

    Returns
    -------
    (N,) float64
        Standard deviation of each image's noise (0 where the window holds no plate interior).

    References
    ----------
    .. [1] J. Immerkaer, "Fast noise variance estimation", Computer Vision and Image Understanding
       64(2), 1996.
    """
    out = np.zeros(len(images))
    rows = np.flatnonzero(mask.any(axis=1))
    cols = np.flatnonzero(mask.any(axis=0))
    if rows.size < 3 or cols.size < 3:
        return out
    r0 = max(0, (rows[0] + rows[-1]) // 2 - side // 2)
    c0 = max(0, (cols[0] + cols[-1]) // 2 - side // 2)
    win = (slice(r0, r0 + side), slice(c0, c0 + side))
    m = mask[win]
    inner = m[1:-1, 1:-1] & m[:-2, 1:-1] & m[2:, 1:-1] & m[1:-1, :-2] & m[1:-1, 2:]
    if not inner.any():
        return out
    # one contiguous float32 copy of the window: one layout for the kernel whatever the window
    stack = np.ascontiguousarray(np.asarray(images)[(slice(None), *win)], dtype=np.float32)
    vals = np.empty((len(images), int(np.count_nonzero(inner))), np.float32)
    counts = _abs_laplacians(stack, np.ascontiguousarray(inner), vals)
    for k, count in enumerate(counts):
        # numpy's own mean (pairwise float32 sums) of the same values
        out[k] = float(np.sqrt(np.pi / 2.0) / 6.0 * np.mean(vals[k, :count])) if count else 0.0
    return out


@numba.njit(nogil=True, cache=True)
def _abs_laplacians(stack: Arr, inner: Arr, vals: Arr) -> Arr:  # pragma: no cover - compiled
    """The finite ``|Laplacian difference|`` of each image of ``stack`` (N, h, w) float32 at the pixels of
    ``inner`` (h - 2, w - 2), in row order, into ``vals[k]``; returns how many each image has (N,).

    Single-threaded (it runs from worker threads too); float32 in numpy's order of operations, so the
    values are those of the array expression."""
    n, h, w = stack.shape
    counts = np.zeros(n, np.int64)
    four, two = np.float32(4.0), np.float32(2.0)
    row = np.empty(w, np.float32)
    for k in range(n):
        c = 0
        for i in range(1, h - 1):
            up, mid, down = stack[k, i - 1], stack[k, i], stack[k, i + 1]
            for j in range(1, w - 1):  # branch-free: vectorised
                cross = ((up[j] + down[j]) + mid[j - 1]) + mid[j + 1]
                lap = four * mid[j] - two * cross
                lap = (((lap + up[j - 1]) + up[j + 1]) + down[j - 1]) + down[j + 1]
                row[j] = abs(lap)
            for j in range(1, w - 1):
                if inner[i - 1, j - 1] and np.isfinite(row[j]):
                    vals[k, c] = row[j]
                    c += 1
        counts[k] = c
    return counts
