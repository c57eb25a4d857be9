"""The one colour map of signed deviations: PNG, PLY vertex colours and the 3D viewer (``app/viewer`` colours with :func:`deviation_colormap`)."""

from __future__ import annotations

import math

import numba
import numpy as np
import numpy.typing as npt

#: Colour stops (RGB) at t = -1, -1/2, 0, 1/2, 1 of ``deviation / limit_mm``; the viewer uses the same.
COLOUR_STOPS = ((33, 102, 172), (146, 197, 222), (247, 247, 247), (244, 165, 130), (178, 24, 43))
_STOP_T = (-1.0, -0.5, 0.0, 0.5, 1.0)
#: RGB of pixels/vertices without a deviation (NaN or outside the mask).
NO_DATA_RGB = (128, 128, 128)


def deviation_colormap(deviation_mm: npt.ArrayLike, *, limit_mm: float) -> npt.NDArray[np.uint8]:
    """Colour signed deviations on a diverging blue - white - red scale.

    Parameters
    ----------
    deviation_mm : (H, W) float array (any shape works), mm, positive towards the cameras.
    limit_mm : float > 0
        Deviation drawn in full colour; larger magnitudes saturate at the end colours.

    Returns
    -------
    (H, W, 3) uint8 RGB
        ``(33, 102, 172)`` dark blue at ``-limit_mm`` (below the target, away from
        the cameras), ``(247, 247, 247)`` near white at 0, ``(178, 24, 43)`` dark
        red at ``+limit_mm``; linear in RGB between the stops of
        :data:`COLOUR_STOPS`. NaN -> neutral grey ``(128, 128, 128)``.

    Raises
    ------
    ValueError
        ``limit_mm`` not a positive finite number; infinite deviations.
    """
    dev = np.asarray(deviation_mm, dtype=np.float64)
    if not (
        isinstance(limit_mm, (int, float, np.floating, np.integer))
        and math.isfinite(limit_mm)
        and limit_mm > 0
    ):
        raise ValueError(f"limit_mm: expected a positive finite number of mm, got {limit_mm!r}")
    rgb: npt.NDArray[np.uint8] = np.empty((*dev.shape, 3), np.uint8)
    infinite = _colour(dev.ravel(), float(limit_mm), _COLOUR_LUT, rgb.reshape(-1, 3))
    if infinite:
        raise ValueError(f"deviation_mm: expected finite values or NaN, got {infinite} infinite")
    return rgb


@numba.njit(cache=True, nogil=True)
def _colour(
    dev: npt.NDArray[np.float64],
    limit_mm: float,
    lut: npt.NDArray[np.uint8],
    rgb: npt.NDArray[np.uint8],
) -> int:
    """Each deviation's colour from ``lut`` (size + 1 entries: ``size`` steps over [-limit, +limit],
    finer than 8-bit colour can show, then no data) into ``rgb`` (N, 3); the count of infinite ones.

    One pass over memory, the same float64 arithmetic as ``np.rint((d / limit + 1) * (size - 1) / 2)``
    clipped (its array temporaries and gather took 12 ms for a map of 1224x1024)."""
    size = lut.shape[0] - 1
    half = 0.5 * (size - 1)
    infinite = 0
    for i in range(dev.size):
        d = dev[i]
        k = size
        if np.isinf(d):
            infinite += 1
        elif not np.isnan(d):
            k = int(min(max(np.rint((d / limit_mm + 1.0) * half), 0.0), size - 1.0))
        rgb[i, 0], rgb[i, 1], rgb[i, 2] = lut[k, 0], lut[k, 1], lut[k, 2]
    return infinite


def _colour_lut(size: int) -> npt.NDArray[np.uint8]:
    t = np.linspace(-1.0, 1.0, size)
    stops = np.asarray(COLOUR_STOPS, dtype=np.float64)
    rgb = np.stack([np.interp(t, _STOP_T, stops[:, k]) for k in range(3)], axis=-1)
    lut: npt.NDArray[np.uint8] = np.rint(np.vstack([rgb, NO_DATA_RGB])).astype(np.uint8)
    return lut


_LUT_SIZE = 2049
_COLOUR_LUT = _colour_lut(_LUT_SIZE)


def default_limit_mm(tolerance_mm: float) -> float:
    """The colour scale of a plate judged against ``tolerance_mm``: ``2 * tolerance_mm``."""
    return 2.0 * float(tolerance_mm)


#: Tolerance-band colours (RGB): one calm band within tolerance, saturated beyond it.
IN_TOLERANCE_RGB = (156, 206, 156)
#: Above the target beyond tolerance: from the tolerance (first) to the scale's limit (second).
ABOVE_RGB = ((253, 174, 97), (165, 0, 38))
#: Below the target beyond tolerance: from the tolerance (first) to the scale's limit (second).
BELOW_RGB = ((116, 173, 209), (49, 54, 149))


def tolerance_band_colormap(
    deviation_mm: npt.ArrayLike, *, tolerance_mm: float, limit_mm: float
) -> npt.NDArray[np.uint8]:
    """Colour signed deviations by tolerance band, as deviation reports do.

    Within ``±tolerance_mm`` one calm colour (:data:`IN_TOLERANCE_RGB`): nothing to act on there.
    Beyond it, saturated colours that deepen with the deviation up to ``limit_mm``: orange to dark
    red above the target (:data:`ABOVE_RGB`), light to dark blue below it (:data:`BELOW_RGB`).
    NaN -> :data:`NO_DATA_RGB`.

    Returns
    -------
    (..., 3) uint8 RGB, the shape of ``deviation_mm`` plus a colour axis.

    Raises
    ------
    ValueError
        ``tolerance_mm`` or ``limit_mm`` not positive and finite, or ``limit_mm <= tolerance_mm``.
    """
    tol, limit = float(tolerance_mm), float(limit_mm)
    if not (math.isfinite(tol) and tol > 0):
        raise ValueError(
            f"tolerance_mm: expected a positive finite number of mm, got {tolerance_mm!r}"
        )
    if not (math.isfinite(limit) and limit > tol):
        raise ValueError(
            f"limit_mm: expected a finite number above tolerance_mm ({tol:g}), got {limit_mm!r}"
        )
    dev = np.asarray(deviation_mm, dtype=np.float64)
    out = np.empty((*dev.shape, 3), dtype=np.float64)
    out[...] = IN_TOLERANCE_RGB
    t = np.clip((np.abs(np.nan_to_num(dev)) - tol) / (limit - tol), 0.0, 1.0)[..., None]
    for mask, (start, end) in ((dev > tol, ABOVE_RGB), (dev < -tol, BELOW_RGB)):
        a, b = np.asarray(start, dtype=np.float64), np.asarray(end, dtype=np.float64)
        out[mask] = (a + t * (b - a))[mask]
    out[np.isnan(dev)] = NO_DATA_RGB
    rgb: npt.NDArray[np.uint8] = np.rint(out).astype(np.uint8)
    return rgb
