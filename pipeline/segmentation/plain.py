"""Plain scenes: a plate alone over a dark conveyor, whose brightness mask is the plate (no segmentation needed)."""

from __future__ import annotations

import math

import cv2
import numpy as np

from .checks import check_bool_image, check_camera_matrix
from .classify import PROTRUSION_RESIDUAL_MM, SUPPORT_WIDTH_MM, protrusions, support_feet
from .surface import (
    DEPTH_BAND_MM,
    FIT_SAMPLES,
    design,
    fit_surface,
    normalised_coords,
)

#: plain_outline / plain_depth: the shares of the brightness mask's area that may be dark inside it (an opening), lit
#: outside it (a floor, supports) and off its smooth surface in depth. Measured at 1224x1024: plain
#: plates 0 dark inside, 0.06-0.4 % lit outside (more with LEDs); a 60 mm round hole 0.13 % dark
#: inside; a lit floor 34-400 % lit outside.
PLAIN_OPENING_SHARE = 0.0005
PLAIN_LIT_SHARE = 0.02
PLAIN_OFF_SURFACE_SHARE = 0.002
#: ... lit pixels within this many pixels of the mask are its own (mixed) edge.
PLAIN_MARGIN_PX = 5


def plain_outline(bright_mask: np.ndarray, candidates: np.ndarray) -> bool:
    """Whether the plate looks alone in the image: nothing lit around the brightness mask, no opening in it.

    The usual cell: a plate over a dark conveyor. Then the stereo pair and the normals need only the
    brightness mask, and :func:`plain_depth` decides from the stereo depth whether the mask is one sheet.

    Parameters
    ----------
    bright_mask : (H, W) bool
        The brightness mask (:func:`pipeline.preprocess.plate_mask`: Otsu, holes filled, eroded).
    candidates : (H, W) bool
        :func:`candidate_mask`.

    Returns
    -------
    bool
        True when at most PLAIN_OPENING_SHARE of the mask's area is dark inside it (an opening) and at
        most PLAIN_LIT_SHARE is lit outside it beyond PLAIN_MARGIN_PX (a floor, supports).
    """
    mask = check_bool_image("bright_mask", bright_mask, np.shape(bright_mask))
    cand = check_bool_image("candidates", candidates, mask.shape)
    n = int(np.count_nonzero(mask))
    if n == 0 or np.count_nonzero(mask & ~cand) > PLAIN_OPENING_SHARE * n:
        return False
    size = 2 * PLAIN_MARGIN_PX + 1
    grown = cv2.dilate(mask.view(np.uint8), np.ones((size, size), np.uint8)).view(bool)
    return bool(np.count_nonzero(cand & ~grown) <= PLAIN_LIT_SHARE * n)


def plain_depth(
    bright_mask: np.ndarray,
    depth_mm: np.ndarray,
    camera_matrix: np.ndarray,
    *,
    depth_band_mm: float = DEPTH_BAND_MM,
) -> bool:
    """Whether the stereo depth over the brightness mask is one smooth sheet (no floor taken in).

    Parameters
    ----------
    bright_mask : (H, W) bool
        The brightness mask.
    depth_mm : (H, W) float
        Stereo depth (mm, NaN where unmatched).
    camera_matrix : (3, 3) float
        Intrinsics of the grid, pixels.
    depth_band_mm : float
        Half width of the band around the fitted smooth surface that counts as the plate, mm.

    Returns
    -------
    bool
        True when at most PLAIN_OFF_SURFACE_SHARE of the matched mask pixels lie off the smooth
        surface fitted to them, and no part of the mask narrower than SUPPORT_WIDTH_MM leaves that
        surface as a support does (:func:`pipeline.segmentation.classify.protrusions`, the test of
        :func:`segment_plate`'s step 3): the bright top of a rail under the plate's edge, reaching out
        beside it at its depth, joins the brightness mask and stays within the depth band near the
        plate. With :func:`plain_outline`, the brightness mask is then the plate and
        :func:`segment_plate` is not needed (docs/figures.md: what it costs).
    """
    mask = check_bool_image("bright_mask", bright_mask, np.shape(bright_mask))
    depth = np.asarray(depth_mm, dtype=np.float64)
    K = check_camera_matrix(camera_matrix)
    surface = fit_surface(depth, mask, K, depth_band_mm)
    if surface is None:
        return False
    stride = max(1, int(round(math.sqrt(depth.size / FIT_SAMPLES))))
    z = depth[::stride, ::stride]
    inside = mask[::stride, ::stride] & np.isfinite(z) & (z > 0)
    x, y = normalised_coords(K, depth.shape, stride)
    x, y = x[: z.shape[0], : z.shape[1]], y[: z.shape[0], : z.shape[1]]
    X = design(x[inside], y[inside], surface.degree, surface.scale)
    with np.errstate(divide="ignore", invalid="ignore"):
        off = np.abs(z[inside] - 1.0 / (X @ surface.coef)) > depth_band_mm
    n_inside = int(np.count_nonzero(inside))
    if np.count_nonzero(off) > PLAIN_OFF_SURFACE_SHARE * max(n_inside, 1):
        return False
    # on every pixel, as the segmentation tests them: a support's part is a few of the sampled pixels
    Kinv = np.linalg.inv(K)

    def residual_at(parts: np.ndarray) -> np.ndarray:
        v, u = np.nonzero(parts)
        x = Kinv[0, 0] * u + Kinv[0, 1] * v + Kinv[0, 2]
        y = Kinv[1, 1] * v + Kinv[1, 2]
        with np.errstate(invalid="ignore"):
            return np.asarray(depth[parts] - surface.depth(x, y), dtype=np.float64)

    mm_per_px = float(np.median(z[inside])) / math.sqrt(K[0, 0] * K[1, 1])
    supports = protrusions(
        mask & np.isfinite(depth) & (depth > 0),
        residual_at,
        mm_per_px,
        SUPPORT_WIDTH_MM,
        max(PROTRUSION_RESIDUAL_MM, 5.0 * surface.rms_mm),
    )
    return not support_feet(supports, mm_per_px, SUPPORT_WIDTH_MM).any()
