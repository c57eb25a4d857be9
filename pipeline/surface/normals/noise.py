"""The photometric images' own noise, measured on the plate (Immerkaer's estimator)."""

from __future__ import annotations

import numpy as np


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
    for k, im in enumerate(images):
        x = np.asarray(im[win], dtype=np.float32)
        lap = (
            4 * x[1:-1, 1:-1]
            - 2 * (x[:-2, 1:-1] + x[2:, 1:-1] + x[1:-1, :-2] + x[1:-1, 2:])
            + x[:-2, :-2]
            + x[:-2, 2:]
            + x[2:, :-2]
            + x[2:, 2:]
        )
        vals = np.abs(lap[inner])
        vals = vals[np.isfinite(vals)]
        out[k] = float(np.sqrt(np.pi / 2.0) / 6.0 * np.mean(vals)) if vals.size else 0.0
    return out
