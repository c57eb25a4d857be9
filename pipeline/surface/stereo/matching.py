"""Rectification of the pair, and one rectify-and-match pass: a window of the rectified pair matched by SGBM."""

from __future__ import annotations

import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any

import cv2
import numba
import numpy as np
import numpy.typing as npt

from pipeline.camera import StereoRig
from pipeline.solvers import percentile

#: An array argument of the kernels (their dtypes are set by the callers).
Arr = npt.NDArray[Any]

#: Matching window of SGBM, pixels (odd).
BLOCK_SIZE = 5
#: Largest left-right disagreement accepted, pixels (SGBM ``disp12MaxDiff``).
LR_MAX_DIFF_PX = 1
#: Interpolation of the raw images onto the rectified grids.
RECTIFY_INTERPOLATION = cv2.INTER_CUBIC


def rectification(rig: StereoRig) -> tuple[np.ndarray, np.ndarray, float, float]:
    """Rectifying rotations of the rig and the rectified focal length and baseline.

    Returns
    -------
    R1, R2 : (3, 3) float64
        Rotations from the left / right camera frame to its rectified frame
        (``cv2.stereoRectify``); both rectified frames share their axes.
    f_rect_px : float
        Focal length of the rectified cameras: the largest of the four focal
        lengths, so rectification never lowers the resolution.
    baseline_x_mm : float
        ``(R2 @ T)[0]``: x of the left camera centre in the rectified-right frame
        (negative when the right camera is to the right). A point at rectified
        depth ``Z`` has disparity ``x_left - x_right = -f_rect * baseline_x / Z``.

    Raises
    ------
    ValueError
        If the baseline is more vertical than horizontal (the matcher searches along rows).
    """
    T = rig.T
    if abs(T[0]) < abs(T[1]):
        raise ValueError(
            f"rig.T: expected a horizontal baseline (|Tx| >= |Ty|) for row-wise matching, got T = {T.tolist()} mm"
        )
    R1, R2, _, _, _, _, _ = cv2.stereoRectify(
        rig.left.K,
        rig.left.dist,
        rig.right.K,
        rig.right.dist,
        rig.image_size,
        rig.R,
        T.reshape(3, 1),
    )
    f_rect = float(max(rig.left.K[0, 0], rig.left.K[1, 1], rig.right.K[0, 0], rig.right.K[1, 1]))
    return R1, R2, f_rect, float((R2 @ T)[0])


def bbox_corners(mask: np.ndarray | None, size: tuple[int, int]) -> np.ndarray:
    """Corners ``(4, 2)`` (u, v) of the mask's bounding box (of the image without a mask), pixel edges."""
    w, h = size
    if mask is None:
        u0, u1, v0, v1 = 0, w - 1, 0, h - 1
    else:
        cols = np.flatnonzero(mask.any(axis=0))
        rows = np.flatnonzero(mask.any(axis=1))
        u0, u1, v0, v1 = cols[0], cols[-1], rows[0], rows[-1]
    return np.array(
        [[u0 - 0.5, v0 - 0.5], [u1 + 0.5, v0 - 0.5], [u0 - 0.5, v1 + 0.5], [u1 + 0.5, v1 + 0.5]],
        np.float64,
    )


def _grey_levels(
    image: np.ndarray,
    valid: np.ndarray,
    low_pct: float = 0.5,
    high_pct: float = 99.5,
    stride: int = 2,
) -> tuple[float, float]:
    """The ``low_pct`` / ``high_pct`` percentiles of ``image`` over ``valid`` (all pixels if none is), taken
    on every ``stride``-th row and column: the same levels to a fraction of a grey level, at a fraction
    of the cost of sorting every pixel."""
    img, ok = image[::stride, ::stride], valid[::stride, ::stride]
    lo, hi = percentile(img[ok] if ok.any() else img.ravel(), [low_pct, high_pct])
    return float(lo), float(hi)


@dataclass(frozen=True)
class MatchPass:
    """One rectify-and-match pass on a window of the rectified pair (internal)."""

    d_win: (
        np.ndarray
    )  # (h', w') float32 disparity (x_left - x_right, pixels of this pass); NaN = no match
    rect_l: np.ndarray
    rect_r: np.ndarray
    seen_l: np.ndarray
    seen_r: np.ndarray
    K1w: np.ndarray
    x0: int
    y0: int
    win: tuple[int, int]
    levels: tuple[
        tuple[float, float], tuple[float, float]
    ]  # grey levels mapped to 0 / 255, left and right
    seconds: tuple[float, float]  # rectify, match


def match_pass(
    left: np.ndarray,
    right: np.ndarray,
    K_l: np.ndarray,
    dist_l: np.ndarray,
    K_r: np.ndarray,
    dist_r: np.ndarray,
    R1: np.ndarray,
    R2: np.ndarray,
    f: float,
    box_rays: np.ndarray,
    shift: int,
    num_disp: int,
    mask: np.ndarray | None,
    K_mask_inv: np.ndarray,
    limit_px: int,
    levels: tuple[tuple[float, float], tuple[float, float]] | None = None,
) -> MatchPass:
    """Rectify the window of ``left``/``right`` that holds ``box_rays`` and match it by SGBM over ``shift .. shift + num_disp - 1``.

    ``K_l``, ``K_r`` are the cameras of the given images (full or reduced size), ``f`` the rectified
    focal length at that size; ``mask`` lives on the full-size left undistorted grid (``K_mask_inv``).
    ``levels``: the grey levels ``((lo, hi) left, (lo, hi) right)`` mapped to 0 / 255 for SGBM; None: the
    0.5 / 99.5 percentiles of each rectified window (over its pixels seen by the camera).
    """
    t0 = time.perf_counter()
    xs, ys = f * box_rays[:, 0] / box_rays[:, 2], f * box_rays[:, 1] / box_rays[:, 2]
    pad = BLOCK_SIZE + 2
    x0 = int(np.floor(xs.min())) - pad - num_disp
    x1 = int(np.ceil(xs.max())) + pad
    y0 = int(np.floor(ys.min())) - pad
    y1 = int(np.ceil(ys.max())) + pad
    win = (x1 - x0 + 1, y1 - y0 + 1)
    if win[0] * win[1] > limit_px:
        raise ValueError(
            f"rig, z_min_mm, z_max_mm: the rectified search window would be {win[0]}x{win[1]} px "
            f"for a {left.shape[1]}x{left.shape[0]} image; the rig or the depth range is implausible"
        )
    # window cameras: x_left' = x_left - x0, x_right' = x_right - x0 + shift, so SGBM's disparity is d - shift >= 0
    K1w = np.array([[f, 0.0, -x0], [0.0, f, -y0], [0.0, 0.0, 1.0]])
    K2w = np.array([[f, 0.0, -x0 + shift], [0.0, f, -y0], [0.0, 0.0, 1.0]])
    # the right image on a thread of its own beside the left (OpenCV's remaps release the GIL), the
    # mask's window beside the matching
    with ThreadPoolExecutor(max_workers=1) as side:
        right_job = side.submit(_rectified, right, K_r, dist_r, R2, K2w, win)
        rect_l, seen_l = _rectified(left, K_l, dist_l, R1, K1w, win)
        rect_r, seen_r = right_job.result()
        if levels is None:
            levels = (_grey_levels(rect_l, seen_l), _grey_levels(rect_r, seen_r))
        img_l, img_r = _levels_uint8(rect_l, *levels[0]), _levels_uint8(rect_r, *levels[1])
        t1 = time.perf_counter()
        mask_job = (
            None if mask is None else side.submit(_mask_window, mask, K1w @ R1 @ K_mask_inv, win)
        )
        d_win = _sgbm(img_l, img_r, num_disp, seen_l, seen_r)
        if mask_job is not None:  # only plate pixels count (the background lies at another depth)
            d_win[~mask_job.result()] = np.nan
    d_win = (d_win + np.float32(shift)).astype(np.float32)
    return MatchPass(
        d_win,
        rect_l,
        rect_r,
        seen_l,
        seen_r,
        K1w,
        x0,
        y0,
        win,
        levels,
        (t1 - t0, time.perf_counter() - t1),
    )


def _mask_window(mask: np.ndarray, H: np.ndarray, win: tuple[int, int]) -> np.ndarray:
    """The pixels of the rectified window (``H``: the mask's grid to the window) whose matching block lies
    on the mask: a block that straddles the plate's edge mixes two depths."""
    mask_win = cv2.warpPerspective(mask.astype(np.uint8), H, win, flags=cv2.INTER_NEAREST) > 0
    edge = BLOCK_SIZE // 2 + 1
    eroded: np.ndarray = (
        cv2.erode(mask_win.astype(np.uint8), np.ones((2 * edge + 1, 2 * edge + 1), np.uint8)) > 0
    )
    return eroded


def _rectified(
    image: np.ndarray,
    K: np.ndarray,
    dist: np.ndarray,
    R: np.ndarray,
    K_win: np.ndarray,
    win: tuple[int, int],
) -> tuple[np.ndarray, np.ndarray]:
    """A camera's raw image on the rectified window ``K_win`` (rotation ``R``): (image, pixels it sees)."""
    maps = cv2.initUndistortRectifyMap(K, dist, R, K_win, win, cv2.CV_32FC1)
    seen = (
        cv2.remap(
            np.ones(image.shape, np.float32),
            *maps,
            cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_CONSTANT,
            borderValue=0,
        )
        > 0.999
    )
    rect = cv2.remap(
        image, *maps, RECTIFY_INTERPOLATION, borderMode=cv2.BORDER_CONSTANT, borderValue=0
    )
    return rect, seen


def _sgbm(
    img_l: np.ndarray, img_r: np.ndarray, num_disp: int, seen_l: np.ndarray, seen_r: np.ndarray
) -> np.ndarray:
    """SGBM disparities (float32, pixels of the window pair, 0 .. num_disp - 1) of rectified 8-bit images;
    NaN where SGBM found no match or either camera does not see the matched pixel."""
    win = (img_l.shape[1], img_l.shape[0])
    matcher = cv2.StereoSGBM_create(  # type: ignore[attr-defined]  # not in OpenCV 5's stubs
        minDisparity=0,
        numDisparities=num_disp,
        blockSize=BLOCK_SIZE,
        P1=8 * BLOCK_SIZE**2,
        P2=32 * BLOCK_SIZE**2,
        disp12MaxDiff=LR_MAX_DIFF_PX,
        preFilterCap=63,
        uniquenessRatio=10,
        speckleWindowSize=100,
        speckleRange=2,
        mode=cv2.StereoSGBM_MODE_SGBM_3WAY,
    )
    raw = matcher.compute(img_l, img_r)
    d_win = np.empty((win[1], win[0]), np.float32)
    _seen_matches(raw, seen_l, seen_r, d_win)
    return d_win


@numba.njit(nogil=True, cache=True)
def _seen_matches(
    raw: Arr, seen_l: Arr, seen_r: Arr, out: Arr
) -> None:  # pragma: no cover - compiled
    """SGBM's fixed-point disparities ``raw`` (int16, 1/16 px) as float32 pixels into ``out``, NaN where
    SGBM found no match or either camera does not see the matched pixel (the matched right pixel,
    rounded half to even, must lie inside the right image too); single-threaded (the stereo pair's
    worker)."""
    h, w = raw.shape
    sixteen, zero = np.float32(16.0), np.float32(0.0)
    for i in range(h):
        for j in range(w):
            d = np.float32(raw[i, j]) / sixteen
            col = np.float32(j) - d
            c = min(max(np.rint(col), zero), np.float32(w - 1))
            if raw[i, j] >= 0 and seen_l[i, j] and col >= zero and seen_r[i, int(c)]:
                out[i, j] = d
            else:
                out[i, j] = np.nan


def _levels_uint8(image: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """``image`` mapped so ``lo`` / ``hi`` become 0 / 255, saturating beyond (all 0 if ``hi <= lo``)."""
    if not hi > lo:
        return np.zeros(image.shape, np.uint8)
    levels = np.empty(image.shape, np.uint8)
    _to_levels(image, np.float32(lo), np.float32(255.0 / (hi - lo)), levels)
    return levels


@numba.njit(nogil=True, cache=True)
def _to_levels(
    image: Arr, lo: np.float32, gain: np.float32, out: Arr
) -> None:  # pragma: no cover - compiled
    """out = ``(image - lo) * gain + 0.5`` clipped to 0..255 and truncated to uint8, in float32 (the
    array expression's values); single-threaded."""
    h, w = image.shape
    half, top, zero = np.float32(0.5), np.float32(255.0), np.float32(0.0)
    for i in range(h):
        for j in range(w):
            out[i, j] = np.uint8(min(max((image[i, j] - lo) * gain + half, zero), top))


def search_range(d_lo: float, d_hi: float, quantum: int = 1) -> tuple[int, int]:
    """SGBM's ``(shift, num_disp)`` covering disparities ``d_lo .. d_hi``: ``num_disp`` a multiple of 16,
    ``shift`` rounded down to a multiple of ``quantum``."""
    shift = int(np.floor(d_lo / quantum)) * quantum
    num_disp = int(np.ceil((np.ceil(d_hi) - shift + 1) / 16.0)) * 16
    return shift, num_disp


def reduced_camera(K: np.ndarray, factor: int) -> np.ndarray:
    """Camera matrix of an image reduced by ``factor`` by area averaging (pixel centres: ``u = factor * u' + (factor - 1) / 2``)."""
    S = np.array(
        [
            [1.0 / factor, 0.0, -(factor - 1) / (2.0 * factor)],
            [0.0, 1.0 / factor, -(factor - 1) / (2.0 * factor)],
            [0, 0, 1],
        ]
    )
    scaled: np.ndarray = S @ K
    return scaled
