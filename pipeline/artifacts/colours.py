"""The one colour map of signed deviations: PNG, PLY vertex colours and the 3D viewer (``app/viewer`` colours with :func:`deviation_colormap`)."""

from __future__ import annotations

import math

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
    if np.isinf(dev).any():
        raise ValueError(
            f"deviation_mm: expected finite values or NaN, got {int(np.isinf(dev).sum())} infinite"
        )
    # a lookup table of _LUT_SIZE steps over [-limit, +limit] (finer than 8-bit colour can show), last entry = no data
    index = np.rint((dev / float(limit_mm) + 1.0) * (0.5 * (_LUT_SIZE - 1)))
    np.clip(index, 0, _LUT_SIZE - 1, out=index)
    index[np.isnan(dev)] = _LUT_SIZE
    rgb: npt.NDArray[np.uint8] = _COLOUR_LUT[index.astype(np.intp)]
    return rgb


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
