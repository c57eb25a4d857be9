"""Step 1: the candidates, pixels bright enough to be the plate (also where the stereo pair is matched)."""

from __future__ import annotations

import math

import cv2
import numpy as np
import numpy.typing as npt

from pipeline.solvers import labelled, percentile

from .checks import check_bool_image, check_image

#: Default share of the image's bright level (95th percentile of the brightest sample) below which a
#: pixel is dark: painted and rusty steel (albedo 0.25-0.7) stays above it, a dark conveyor (~0.05)
#: below, even when a lit floor's painted lines set the bright level.
DARK_FRACTION = 0.2
#: Dark specks of at most this many pixels enclosed by bright ones are not dark (a rust pore, noise):
#: the stereo matcher would otherwise make a hole of its window's size around each.
DARK_SPECK_PX = 9


def candidate_mask(
    brightness: npt.ArrayLike,
    *,
    seen: npt.ArrayLike | None = None,
    dark_fraction: float = DARK_FRACTION,
) -> np.ndarray:
    """Pixels bright enough to be the plate: not dark against the image's bright level.

    Parameters
    ----------
    brightness : (H, W) array_like of float
        A bright photometric sample per pixel (any linear unit, e.g. fractions of full scale after
        dark subtraction and intensity normalisation; the pipeline gives
        :attr:`pipeline.preprocess.Preprocessed.brightness`); NaN counts as dark.
    seen : (H, W) bool, optional
        Pixels that have samples at all (False where the undistorted ray leaves the raw image).
    dark_fraction : float
        A pixel is dark below ``dark_fraction`` times the 95th percentile of the (lightly smoothed)
        brightness over the seen pixels (dimensionless, 0..1).

    Returns
    -------
    (H, W) bool
        True where a pixel may be the plate. Over a dark conveyor this is the plate; over a lit floor
        it is most of the image. Meant both for :func:`segment_plate` and as the region the stereo
        pair is matched over (``mask`` of :func:`pipeline.surface.stereo.stereo_depth`).

    Raises
    ------
    ValueError
        Bad shapes or ``dark_fraction``, or no light at all.
    """
    b = check_image("brightness", brightness).astype(np.float32)
    shape = b.shape
    ok = np.ones(shape, bool) if seen is None else check_bool_image("seen", seen, shape)
    if not (math.isfinite(dark_fraction) and 0 < dark_fraction < 1):
        raise ValueError(f"dark_fraction: expected a share in (0, 1), got {dark_fraction}")
    b = np.nan_to_num(b, nan=0.0, posinf=0.0, neginf=0.0)
    # smooth the grain so that single dark texels of a rusty plate are not called dark
    smooth = cv2.GaussianBlur(b, (0, 0), 1.0)
    step = max(
        1, int(math.sqrt(b.size / 200_000))
    )  # the level from ~200k pixels: as good, and cheaper
    lit = smooth[::step, ::step][ok[::step, ::step]]
    level = float(percentile(lit, 95)) if lit.size else 0.0
    if not level > 0:
        raise ValueError("brightness: expected some light on the seen pixels, got none above zero")
    bright = ok & (smooth >= dark_fraction * level)
    _n, labels, areas = labelled(~bright, connectivity=4)
    speck = areas <= DARK_SPECK_PX
    speck[0] = False  # label 0: the bright pixels
    candidates: np.ndarray = (bright | speck[labels]) & ok
    return candidates
