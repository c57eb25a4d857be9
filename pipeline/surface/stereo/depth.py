"""Binocular metric depth: rectify, match (semi-global), triangulate, resample on the left grid.

The stereo pair is rectified from the raw (distorted) images with the rig's
calibration and matched by OpenCV's semi-global block matching (3-way mode) in
two passes: a coarse one on the pair reduced 4x over the whole depth range the
caller allows finds the plate's disparity span; the full-size pass searches only
that span (widened a little, rounded outward to 16 px), so the caller's range
(e.g. from a working-distance hint) does not decide the result. Matches are
checked for left-right consistency, triangulated in the rectified-left frame and
brought back to the left camera frame. The result is a depth map on the *left
undistorted grid* (the grid of :meth:`CameraModel.undistort_image`: pixel
``(u, v)`` sees the ray ``K^-1 (u, v, 1)``), so a point is ``depth * K^-1 (u, v, 1)``.
Pixels without a trustworthy match are holes (NaN); nothing is filled in.

Matching is SGBM (3-way, ``BLOCK_SIZE`` px window, 1/16 px parabolic sub-pixel) with its left-right
check (``disp12MaxDiff = LR_MAX_DIFF_PX``), uniqueness and speckle filters, then (``refine``) the
sub-pixel refinement, then a correlation check (windowed ZNCC of the match >= ``MIN_ZNCC``: SGM's
smoothness term propagates disparities into textureless areas, which this rejects); rejected pixels
stay NaN. The coarse pass uses the same matcher and correlation check on images reduced by area
averaging. Each pixel of the left undistorted grid looks up the rectified depth on the same ray
(homography ``K_rect R1 K^-1``, bilinear); a lookup touching any hole is a hole, and
``z_left = z_rect / (R1 K^-1 (u, v, 1))_z``.

References
----------
H. Hirschmueller, "Stereo processing by semiglobal matching and mutual
information", IEEE TPAMI 30(2), 2008.
A. Fusiello, E. Trucco, A. Verri, "A compact algorithm for rectification of
stereo pairs", Machine Vision and Applications 12, 2000.
"""

from __future__ import annotations

import itertools
import math
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any

import cv2
import numba
import numpy as np
import numpy.typing as npt

from pipeline.camera import StereoRig
from pipeline.parallel import default_workers
from pipeline.solvers import bounding_box, percentile
from pipeline.surface.stereo.matching import (
    BLOCK_SIZE,
    MatchPass,
    bbox_corners,
    match_pass,
    rectification,
    reduced_camera,
    search_range,
)
from pipeline.surface.stereo.refine import (
    MIN_ZNCC,
    REFINE_ITERATIONS,
    REFINE_MAX_STEP_PX,
    REFINE_SIGMA_PX,
    match_correlation,
    refine_disparity,
    scaled,
)

#: An array argument of the kernels (their dtypes are set by the callers).
Arr = npt.NDArray[Any]

#: Extra disparity searched on each side of the range implied by z_min..z_max, pixels.
RANGE_MARGIN_PX = 2
#: The coarse pass matches the pair reduced this many times (area averaging) to find the scene's disparity span.
COARSE_FACTOR = 4
#: Percentiles of the coarse disparities (over the mask) taken as the scene's span: robust to a few wild matches.
COARSE_PERCENTILES = (0.5, 99.5)
#: Added to each side of the coarse span (full-size pixels) before rounding the fine range outward to multiples
#: of 16: two coarse pixels, the coarse pass's error plus the plate's parts beyond the percentiles.
FINE_MARGIN_PX = 8
#: Fewer trusted coarse matches than this: the fine pass searches the whole given depth range instead.
COARSE_MIN_MATCHES = 50
#: The radius of the refinement's Gaussian window (OpenCV's kernel for float images reaches ``4 sigma``).
WINDOW_RADIUS_PX = math.ceil(4 * REFINE_SIGMA_PX)
#: Rows of its neighbours computed beside each band of the refinement and correlation check
#: (:func:`_checked_disparity`): a disparity depends on the windows around it only, each step's on
#: those within one radius, so a row on those within ``REFINE_ITERATIONS + 1`` radii.
CHECK_HALO_PX = (REFINE_ITERATIONS + 1) * WINDOW_RADIUS_PX


@dataclass(frozen=True)
class StereoDepth:
    """Metric depth from the stereo pair.

    Attributes
    ----------
    depth_mm : (H, W) float32
        Depth (z, mm, left camera frame) on the left undistorted grid; NaN = hole.
    valid : (H, W) bool
        ``isfinite(depth_mm)``.
    disparity_px : (H', W') float32
        Disparity ``x_left - x_right`` (pixels) on a window of the rectified-left image; NaN = no
        match. For diagnostics: the rectified cameras are ``K0 = [[f, 0, 0], [0, f, 0], [0, 0, 1]]``
        (``f`` from :func:`rectification`) and ``disparity_px[i, j]`` is rectified pixel
        ``(x0 + j, y0 + i)``.
    disparity_origin_px : (int, int)
        ``(x0, y0)`` above.
    search_disparity_px : (int, int)
        First and last disparity (full-size pixels) the fine SGBM pass searched.
    coarse_span_px : (float, float) or None
        The scene's disparity span found by the coarse pass (its ``COARSE_PERCENTILES``, full-size
        pixels); None if the coarse pass found too few matches and the whole given range was searched.
    timings : dict of str to float
        Seconds per step: ``coarse`` (the coarse pass), ``rectify``, ``match``, ``refine``
        (refinement and ZNCC check), ``triangulate``, ``resample``.
    """

    depth_mm: np.ndarray
    valid: np.ndarray
    disparity_px: np.ndarray
    disparity_origin_px: tuple[int, int] = (0, 0)
    search_disparity_px: tuple[int, int] = (0, 0)
    coarse_span_px: tuple[float, float] | None = None
    timings: dict[str, float] = field(default_factory=dict)


def _grey(name: str, image: npt.ArrayLike, size: tuple[int, int]) -> np.ndarray:
    arr = np.asarray(image)
    if arr.ndim == 3 and arr.shape[2] in (3, 4):
        arr = cv2.cvtColor(
            arr.astype(np.float32), cv2.COLOR_BGRA2GRAY if arr.shape[2] == 4 else cv2.COLOR_BGR2GRAY
        )
    if arr.ndim != 2:
        raise ValueError(
            f"{name}: expected an (H, W) or (H, W, 3) image, got shape {np.asarray(image).shape}"
        )
    if arr.shape != (size[1], size[0]):
        raise ValueError(
            f"{name}: expected shape {(size[1], size[0])} to match the calibration's image_size {size}, got {arr.shape}"
        )
    if not np.issubdtype(arr.dtype, np.number) or np.issubdtype(arr.dtype, np.complexfloating):
        raise ValueError(f"{name}: expected a real-valued image, got dtype {arr.dtype}")
    arr = arr.astype(np.float32)
    if not np.all(np.isfinite(arr)):
        raise ValueError(
            f"{name}: expected finite pixel values, got {np.count_nonzero(~np.isfinite(arr))} NaN/inf"
        )
    return arr


def stereo_depth(
    left_raw: np.ndarray,
    right_raw: np.ndarray,
    rig: StereoRig,
    *,
    z_min_mm: float,
    z_max_mm: float,
    mask: np.ndarray | None = None,
    refine: bool = True,
) -> StereoDepth:
    """Metric depth of the scene from one stereo pair.

    Two passes: a coarse one finds where the scene actually is, the fine one measures it. The
    coarse pass matches the pair reduced ``COARSE_FACTOR`` times over ``z_min_mm .. z_max_mm``; the
    ``COARSE_PERCENTILES`` of its disparities over the mask, widened by ``FINE_MARGIN_PX`` and rounded
    outward to multiples of 16 px, are the fine pass's range. So two depth ranges that both contain
    the scene give the same depth map (unless a coarse percentile sits on a rounding boundary).

    Parameters
    ----------
    left_raw, right_raw : (H, W) or (H, W, 3) array, any real dtype
        The pair as the cameras gave it (distorted; 8-, 12- or 16-bit counts or float).
        ``(W, H) == rig.image_size``.
    rig : StereoRig
        Calibration; ``X_right = R @ X_left + T`` (mm), horizontal baseline.
    z_min_mm, z_max_mm : float
        Range of depths (left camera z, mm) where the scene may be: the coarse pass searches
        all of it (the cell's whole working range is fine: it is matched at reduced size). If the
        coarse pass finds fewer than ``COARSE_MIN_MATCHES`` matches, the fine pass searches this
        whole range instead.
    mask : (H, W) bool, optional
        Pixels of the left *undistorted* grid that matter (the plate). Only they set the
        disparity range, and depth outside it is a hole.
        Pixels within ``BLOCK_SIZE // 2 + 1`` px of its edge are holes too (their matching
        blocks straddle the edge), and only its pixels feed the sub-pixel refinement.
    refine : bool
        Refine SGBM's disparities by :func:`refine_disparity` (windowed Gauss-Newton on the
        float images). Right for smooth surfaces such as a plate: on a simulated plate at
        3 m it takes the median depth error from ~1.3 mm to ~0.65 mm and removes SGBM's
        ~0.6 mm bias. Across depth discontinuities (cluttered scenes) it mixes depths: on
        Middlebury Aloe it raises the share of pixels off by > 1 px; pass False there.

    Returns
    -------
    StereoDepth
        ``depth_mm`` (H, W) float32 on the left undistorted grid (NaN = hole; matching and checks: see
        the module docstring), ``valid``, ``disparity_px`` on the rectified grid, the fine search
        range ``search_disparity_px``, ``timings``.

    Raises
    ------
    ValueError
        Bad shapes, non-finite pixels, a depth range that is not ``0 < z_min < z_max``,
        a mask that is not (H, W) bool, or a vertical baseline.
    """
    timings: dict[str, float] = {}
    left, right, z_min, z_max, mask = _check_inputs(
        left_raw, right_raw, rig, z_min_mm, z_max_mm, mask
    )
    w, h = rig.image_size
    K_inv = np.linalg.inv(rig.left.K)
    R1, R2, f, bx = rectification(rig)
    fp, shift, num_disp, coarse_span = _two_passes(
        left, right, rig, (R1, R2, f, bx), mask, K_inv, z_min, z_max, timings
    )
    t0 = time.perf_counter()
    disparity = _checked_disparity(fp, shift, refine)
    timings["refine"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    z_rect = _triangulate(disparity, f, bx)
    timings["triangulate"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    depth, valid = _on_left_grid(z_rect, fp.K1w @ R1 @ K_inv, R1 @ K_inv, (w, h), mask)
    timings["resample"] = time.perf_counter() - t0
    return StereoDepth(
        depth_mm=depth,
        valid=valid,
        disparity_px=disparity,
        disparity_origin_px=(fp.x0, fp.y0),
        search_disparity_px=(shift, shift + num_disp - 1),
        coarse_span_px=coarse_span,
        timings=timings,
    )


def _check_inputs(
    left_raw: npt.ArrayLike,
    right_raw: npt.ArrayLike,
    rig: StereoRig,
    z_min_mm: float,
    z_max_mm: float,
    mask: npt.ArrayLike | None,
) -> tuple[np.ndarray, np.ndarray, float, float, np.ndarray | None]:
    """The arguments of :func:`stereo_depth` checked: (left, right float32 grey, z_min, z_max, mask or None)."""
    if not isinstance(rig, StereoRig):
        raise TypeError(f"rig: expected a StereoRig, got {type(rig).__name__}")
    size = rig.image_size
    left = _grey("left_raw", left_raw, size)
    right = _grey("right_raw", right_raw, size)
    z_min, z_max = float(z_min_mm), float(z_max_mm)
    if not (np.isfinite(z_min) and np.isfinite(z_max) and 0 < z_min < z_max):
        raise ValueError(
            f"z_min_mm, z_max_mm: expected 0 < z_min_mm < z_max_mm, got {z_min_mm!r}, {z_max_mm!r}"
        )
    if mask is not None:
        mask = np.asarray(mask)
        if mask.dtype != bool or mask.shape != (size[1], size[0]):
            raise ValueError(
                f"mask: expected a {(size[1], size[0])} bool array, got {mask.shape} {mask.dtype}"
            )
        if not mask.any():
            raise ValueError("mask: expected at least one True pixel, got none")
    return left, right, z_min, z_max, mask


def _two_passes(
    left: np.ndarray,
    right: np.ndarray,
    rig: StereoRig,
    rect: tuple[np.ndarray, np.ndarray, float, float],
    mask: np.ndarray | None,
    K_inv: np.ndarray,
    z_min: float,
    z_max: float,
    timings: dict[str, float],
) -> tuple[MatchPass, int, int, tuple[float, float] | None]:
    """The coarse pass over the given depth range, then the fine pass over the span it found: the fine pass,
    its SGBM ``shift`` and ``num_disp``, and the coarse span (None: the given range was searched).
    ``rect``: :func:`rectification` of the rig; ``timings`` receives ``coarse``, ``rectify`` and ``match``."""
    R1, R2, f, bx = rect
    rays, user_lo, user_hi = _search_region(rig, mask, K_inv, R1, f, bx, z_min, z_max)
    t0 = time.perf_counter()
    coarse_span = _coarse_span(left, right, rig, R1, R2, f, rays, user_lo, user_hi, mask, K_inv)
    shift, num_disp, coarse_span = _fine_range(coarse_span, user_lo, user_hi)
    timings["coarse"] = time.perf_counter() - t0
    w, h = rig.image_size
    fp = match_pass(
        left,
        right,
        rig.left.K,
        rig.left.dist,
        rig.right.K,
        rig.right.dist,
        R1,
        R2,
        f,
        rays,
        shift,
        num_disp,
        mask,
        K_inv,
        4 * w * h,
    )
    timings["rectify"], timings["match"] = fp.seconds
    return fp, shift, num_disp, coarse_span


def _search_region(
    rig: StereoRig,
    mask: np.ndarray | None,
    K_inv: np.ndarray,
    R1: np.ndarray,
    f: float,
    bx: float,
    z_min: float,
    z_max: float,
) -> tuple[np.ndarray, float, float]:
    """The region to match and the disparities the given depth range allows.

    The region is the mask's bounding box (the whole image without a mask) seen in the rectified-left
    camera ``K0 = [[f, 0, 0], [0, f, 0], [0, 0, 1]]``: its corners' rays (4, 3), rectified frame, z = left
    depth 1. Returns them and the lowest and highest disparity (``RANGE_MARGIN_PX`` wider).
    """
    corners = bbox_corners(mask, rig.image_size)
    rays = np.c_[corners, np.ones(4)] @ (R1 @ K_inv).T
    if np.any(rays[:, 2] <= 0):
        raise ValueError(
            "rig: the rectified left camera does not look forward over the image; check R and T"
        )
    # disparity x_left - x_right = -f * bx / Z_rect is extreme at the box corners and the range ends
    disps = np.concatenate([-f * bx / (z * rays[:, 2]) for z in (z_min, z_max)])
    return rays, float(disps.min()) - RANGE_MARGIN_PX, float(disps.max()) + RANGE_MARGIN_PX


def _coarse_span(
    left: np.ndarray,
    right: np.ndarray,
    rig: StereoRig,
    R1: np.ndarray,
    R2: np.ndarray,
    f: float,
    rays: np.ndarray,
    user_lo: float,
    user_hi: float,
    mask: np.ndarray | None,
    K_inv: np.ndarray,
) -> tuple[float, float] | None:
    """The coarse pass: where is the scene? The ``COARSE_PERCENTILES`` of the trusted disparities of the pair
    reduced ``COARSE_FACTOR`` times (full-size pixels), or None with too few matches or too small a pair."""
    c = COARSE_FACTOR
    w, h = rig.image_size
    wc, hc = w // c, h // c
    if min(wc, hc) < 4 * BLOCK_SIZE:
        return None
    small_l = cv2.resize(left[: hc * c, : wc * c], (wc, hc), interpolation=cv2.INTER_AREA)
    small_r = cv2.resize(right[: hc * c, : wc * c], (wc, hc), interpolation=cv2.INTER_AREA)
    fc = f / c
    shift_c, num_c = search_range(user_lo / c - RANGE_MARGIN_PX, user_hi / c + RANGE_MARGIN_PX)
    cp = match_pass(
        small_l,
        small_r,
        reduced_camera(rig.left.K, c),
        rig.left.dist,
        reduced_camera(rig.right.K, c),
        rig.right.dist,
        R1,
        R2,
        fc,
        rays,
        shift_c,
        num_c,
        mask,
        K_inv,
        4 * wc * hc,
        # grey levels from the whole reduced images, not the window (whose width follows the given range):
        # the coarse pass then sees the same pixels whatever the range, and its span barely moves with it
        levels=(
            tuple(percentile(small_l, [0.5, 99.5])),
            tuple(percentile(small_r, [0.5, 99.5])),
        ),
    )
    d_c = cp.d_win
    sl, sr = scaled(cp.rect_l, *cp.levels[0]), scaled(cp.rect_r, *cp.levels[1])
    zncc = match_correlation(
        sl, sr, np.where(np.isfinite(d_c), d_c - shift_c, np.nan), sigma_px=REFINE_SIGMA_PX / 2
    )
    good = d_c[np.isfinite(d_c) & (zncc >= MIN_ZNCC)]
    if good.size < COARSE_MIN_MATCHES:
        return None
    p_lo, p_hi = percentile(good, COARSE_PERCENTILES)
    return float(c * p_lo), float(c * p_hi)


def _fine_range(
    coarse_span: tuple[float, float] | None, user_lo: float, user_hi: float
) -> tuple[int, int, tuple[float, float] | None]:
    """The fine pass's SGBM ``(shift, num_disp)``: the coarse span widened by ``FINE_MARGIN_PX`` and rounded
    outward to multiples of 16, never beyond the given range (all of it without a coarse span); and the
    coarse span kept (None when the given range is searched)."""
    lo = user_lo if coarse_span is None else max(coarse_span[0] - FINE_MARGIN_PX, user_lo)
    hi = user_hi if coarse_span is None else min(coarse_span[1] + FINE_MARGIN_PX, user_hi)
    if (
        hi < lo
    ):  # unreachable unless the coarse pass matched only at the range's ends; search it all
        lo, hi, coarse_span = user_lo, user_hi, None
    shift, num_disp = search_range(lo, hi, quantum=16 if coarse_span is not None else 1)
    return shift, num_disp, coarse_span


def _triangulate(disparity: np.ndarray, f: float, bx: float) -> np.ndarray:
    """Rectified depth ``z = -f bx / d`` (float32, mm) of disparities; NaN where not finite and positive."""
    with np.errstate(divide="ignore", invalid="ignore"):
        z_rect = (np.float32(-f * bx) / disparity).astype(np.float32)
    z_rect[~(np.isfinite(z_rect) & (z_rect > 0))] = np.nan
    return z_rect


def _checked_disparity(fp: MatchPass, shift: int, refine: bool) -> np.ndarray:
    """The fine pass's disparities refined (``refine``) and correlation-checked: matches whose windowed ZNCC
    is under ``MIN_ZNCC`` are holes (NaN). Rectified window grid, full-size pixels.

    Only the matches' bounding box, one window radius wider, is computed: the windowed sums are
    weighted by the matches, zero beyond it. It is checked in bands of rows on
    :func:`pipeline.parallel.default_workers` threads (OpenCV's filters and numpy's loops release the
    GIL), each with :data:`CHECK_HALO_PX` rows of its neighbours. So the result is the very values of one
    pass over the whole window (``tests/pipeline/test_stereo.py``)."""
    d_rel = fp.d_win - np.float32(shift)
    checked = np.full(d_rel.shape, np.nan, np.float32)
    matched = bounding_box(np.isfinite(d_rel), WINDOW_RADIUS_PX)
    if matched is None:
        return checked
    rows, cols = matched
    # the right image keeps every column: a match's right pixel lies up to the disparity to the left
    scaled_l = scaled(fp.rect_l[rows, cols], *fp.levels[0])
    scaled_r = scaled(fp.rect_r[rows], *fp.levels[1])
    d_box = d_rel[rows, cols]
    bands = row_bands(d_box.shape[0], default_workers(), CHECK_HALO_PX)

    def check(band: tuple[int, int, int, int]) -> np.ndarray:
        lo, hi, keep_lo, keep_hi = band
        band_rows = slice(lo, hi)
        d = _checked_band(
            scaled_l[band_rows], scaled_r[band_rows], d_box[band_rows], refine, cols.start
        )
        return d[keep_lo - lo : keep_hi - lo]

    if len(bands) == 1:
        box = check(bands[0])
    else:
        with ThreadPoolExecutor(max_workers=len(bands)) as pool:
            box = np.concatenate(list(pool.map(check, bands)))
    checked[rows, cols] = box + np.float32(shift)
    return checked


def _checked_band(
    scaled_l: np.ndarray, scaled_r: np.ndarray, d_rel: np.ndarray, refine: bool, right_x0: int
) -> np.ndarray:
    """:func:`_checked_disparity` on one band of rows (disparities relative to the pass's shift; the left
    image and the disparities from column ``right_x0`` of the right image on)."""
    if refine:
        d_rel = refine_disparity(
            scaled_l,
            scaled_r,
            d_rel,
            sigma_px=REFINE_SIGMA_PX,
            iterations=REFINE_ITERATIONS,
            max_step_px=REFINE_MAX_STEP_PX,
            right_x0=right_x0,
        )
    else:
        d_rel = d_rel.copy()
    zncc = match_correlation(scaled_l, scaled_r, d_rel, sigma_px=REFINE_SIGMA_PX, right_x0=right_x0)
    d_rel[~(zncc >= MIN_ZNCC)] = np.nan
    return d_rel


def row_bands(height: int, parts: int, halo: int) -> list[tuple[int, int, int, int]]:
    """``parts`` bands of rows of an image ``height`` tall, each ``(lo, hi, keep_lo, keep_hi)``: rows
    ``lo:hi`` are computed, ``keep_lo:keep_hi`` kept (the bands' kept rows tile the image); ``halo``
    rows of each neighbour are computed beside a band's own. One band when the image is under
    ``4 halo`` rows a band."""
    parts = max(1, min(int(parts), height // (4 * halo) if halo > 0 else height))
    edges = [round(i * height / parts) for i in range(parts + 1)]
    return [(max(0, a - halo), min(height, b + halo), a, b) for a, b in itertools.pairwise(edges)]


def _on_left_grid(
    z_rect: np.ndarray,
    H_win: np.ndarray,
    M: np.ndarray,
    size: tuple[int, int],
    mask: np.ndarray | None,
) -> tuple[np.ndarray, np.ndarray]:
    """The rectified depth brought onto the left undistorted grid: (depth (H, W) float32, NaN = hole; valid).

    Each left undistorted pixel (u, v) looks up the rectified depth on its own ray: window pixel
    ~ ``H_win (u, v, 1)`` (``H_win = K1w R1 K^-1``) and ``z_left = z_rect / (M (u, v, 1))_z``
    (``M = R1 K^-1``); a lookup touching any hole is a hole.
    """
    w, h = size
    depth = np.full((h, w), np.nan, np.float32)
    valid = np.zeros((h, w), bool)
    box = (slice(0, h), slice(0, w)) if mask is None else bounding_box(mask)
    if box is None:  # an empty mask: every pixel a hole
        return depth, valid
    rows, cols = box
    # the mask's bounding box only: every other pixel is a hole (the same values on it)
    shape = (rows.stop - rows.start, cols.stop - cols.start)
    map_x, map_y, ray_z = (np.empty(shape, np.float32) for _ in range(3))
    _lookup_maps(
        np.ascontiguousarray(H_win, dtype=np.float64),
        np.ascontiguousarray(M, dtype=np.float64),
        rows.start,
        cols.start,
        map_x,
        map_y,
        ray_z,
    )
    finite = np.isfinite(z_rect)
    z_filled = np.where(finite, z_rect, 0).astype(np.float32)
    z_on_left = cv2.remap(
        z_filled, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0
    )
    support = cv2.remap(
        finite.astype(np.float32),
        map_x,
        map_y,
        cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=0,
    )
    box_depth = (z_on_left / ray_z).astype(np.float32)
    box_valid = (support > 0.999) & (box_depth > 0)
    if mask is not None:
        box_valid &= mask[rows, cols]
    depth[rows, cols] = np.where(box_valid, box_depth, np.float32(np.nan))
    valid[rows, cols] = box_valid
    return depth, valid


@numba.njit(nogil=True, cache=True)
def _lookup_maps(
    H_win: Arr, M: Arr, r0: int, c0: int, map_x: Arr, map_y: Arr, ray_z: Arr
) -> None:  # pragma: no cover - compiled
    """:func:`_on_left_grid`'s lookups for the pixels ``(c0 + j, r0 + i)``: the window pixel
    ``H_win (u, v, 1)`` (its denominator rounded to float32 first) and the ray's ``(M (u, v, 1))_z``,
    in float64 in numpy's order of operations, stored as float32 (the array expressions' values);
    single-threaded (the stereo pair's worker)."""
    h, w = map_x.shape
    for i in range(h):
        v = np.float64(r0 + i)
        for j in range(w):
            u = np.float64(c0 + j)
            den = np.float64(np.float32(H_win[2, 0] * u + H_win[2, 1] * v + H_win[2, 2]))
            map_x[i, j] = (H_win[0, 0] * u + H_win[0, 1] * v + H_win[0, 2]) / den
            map_y[i, j] = (H_win[1, 0] * u + H_win[1, 1] * v + H_win[1, 2]) / den
            ray_z[i, j] = M[2, 0] * u + M[2, 1] * v + M[2, 2]
