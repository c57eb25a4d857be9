"""Plain scenes: a plate alone over a dark conveyor, whose brightness mask is the plate (no segmentation needed)."""

from __future__ import annotations

import math

import cv2
import numpy as np

from pipeline.solvers import labelled

from .checks import check_bool_image, check_camera_matrix
from .classify import SUPPORT_WIDTH_MM, narrow_parts, wide_parts
from .surface import DEPTH_BAND_MM, FIT_SAMPLES, design, fit_surface, normalised_coords

#: plain_outline / plain_depth: the shares of the brightness mask's area that may be dark inside it (an opening), lit
#: outside it (a floor, supports) and off its smooth surface in depth. Measured at 1224x1024: plain
#: plates 0 dark inside, 0.06-0.4 % lit outside (more with LEDs); a 60 mm round hole 0.13 % dark
#: inside; a lit floor 34-400 % lit outside.
PLAIN_OPENING_SHARE = 0.0005
PLAIN_LIT_SHARE = 0.02
PLAIN_OFF_SURFACE_SHARE = 0.002
#: ... lit pixels within this many pixels of the mask are its own (mixed) edge.
PLAIN_MARGIN_PX = 5
#: plain_depth: the narrowest support (mm) whose top, lit beside the plate and joined to its brightness mask,
#: is looked for (rails and blocks are 100-200 mm wide; the slivers the stereo pair leaves unmatched along
#: the plate's rim are a few pixels wide).
PLAIN_SUPPORT_MIN_WIDTH_MM = 100.0


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
        surface fitted to them, and no part of the mask narrower than a support
        (:func:`pipeline.segmentation.classify.narrow_parts`, SUPPORT_WIDTH_MM) but at least
        PLAIN_SUPPORT_MIN_WIDTH_MM wide is mostly unmatched. The bright tops of rails under a plate's
        edge join the brightness mask and reach out beside the plate: flat where its continuation turns
        away (off the surface), or without a depth where their tops show the stereo pair nothing to
        match. A bent corner is matched and within the band: it stays, to be measured and judged. With
        :func:`plain_outline`, the brightness mask is then the plate and :func:`segment_plate` is not
        needed (docs/figures.md: what it costs).
    """
    mask = check_bool_image("bright_mask", bright_mask, np.shape(bright_mask))
    depth = np.asarray(depth_mm, dtype=np.float64)
    K = check_camera_matrix(camera_matrix)
    stride = max(1, int(round(math.sqrt(depth.size / FIT_SAMPLES))))
    z = depth[::stride, ::stride]
    inside = mask[::stride, ::stride] & np.isfinite(z) & (z > 0)
    if not inside.any():
        return False
    mm_per_px = float(np.median(z[inside])) / math.sqrt(K[0, 0] * K[1, 1])
    parts = narrow_parts(mask, mm_per_px, SUPPORT_WIDTH_MM)
    if _unmatched_support(parts, depth, mm_per_px):
        return False
    surface = fit_surface(depth, mask, K, depth_band_mm)
    if surface is None:
        return False
    x, y = normalised_coords(K, depth.shape, stride)
    x, y = x[: z.shape[0], : z.shape[1]], y[: z.shape[0], : z.shape[1]]
    X = design(x[inside], y[inside], surface.degree, surface.scale)
    with np.errstate(divide="ignore", invalid="ignore"):
        off = np.abs(z[inside] - 1.0 / (X @ surface.coef)) > depth_band_mm
    n_inside = int(np.count_nonzero(inside))
    return bool(np.count_nonzero(off) <= PLAIN_OFF_SURFACE_SHARE * max(n_inside, 1))


def _unmatched_support(parts: np.ndarray, depth: np.ndarray, mm_per_px: float) -> bool:
    """Whether a part of ``parts`` at least PLAIN_SUPPORT_MIN_WIDTH_MM wide somewhere has most of its
    pixels unmatched (no finite ``depth``)."""
    wide = wide_parts(parts, 0.5 * PLAIN_SUPPORT_MIN_WIDTH_MM / mm_per_px)
    if not wide.any():
        return False
    n, labels, areas = labelled(wide, connectivity=8)
    unmatched = ~np.isfinite(depth[wide])
    share = (
        np.bincount(labels[wide], weights=unmatched.astype(np.float64), minlength=n)[1:] / areas[1:]
    )
    return bool(np.any(share > 0.5))
