"""Sub-pixel refinement and the correlation check of a disparity map on a rectified pair."""

from __future__ import annotations

from typing import Any

import cv2
import numba
import numpy as np
import numpy.typing as npt

#: An array argument of the kernels (their dtypes are set by the callers).
Arr = npt.NDArray[Any]

#: Sub-pixel refinement: Gaussian window std (pixels) and Gauss-Newton iterations.
REFINE_SIGMA_PX = 3.0
REFINE_ITERATIONS = 3
#: A refined disparity that moved farther than this from SGBM's (pixels) is a hole.
REFINE_MAX_STEP_PX = 1.0
#: Matches whose windowed ZNCC (Gaussian std REFINE_SIGMA_PX) is below this are holes: on simulated
#: plates 99.9 % of the good matches score > 0.9; SGM's propagation into textureless areas scores lower.
MIN_ZNCC = 0.7


def scaled(image: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """Float image mapped so ``lo`` / ``hi`` become 0 / 255 (no clipping; all 0 if ``hi <= lo``)."""
    if not hi > lo:
        return np.zeros(image.shape, np.float32)
    return ((image - np.float32(lo)) * np.float32(255.0 / (hi - lo))).astype(np.float32)


def refine_disparity(
    left: np.ndarray,
    right: np.ndarray,
    disparity: np.ndarray,
    *,
    sigma_px: float = REFINE_SIGMA_PX,
    iterations: int = REFINE_ITERATIONS,
    max_step_px: float = REFINE_MAX_STEP_PX,
    right_x0: int = 0,
) -> np.ndarray:
    """Sub-pixel refinement of a rectified disparity map by windowed Gauss-Newton (Lucas-Kanade along rows).

    Minimises, around every pixel, the Gaussian-weighted sum of squared differences
    ``left(x, y) - right(x - d, y) - c`` over its neighbours, each neighbour warped by its own
    current disparity, with a symmetric (left + warped right) gradient and an intensity offset
    ``c`` of the window's own (zero-mean SSD: a glossy plate's lobe, which each camera sees at its
    own mirror points, does not become disparity). SGBM's parabola fit on integer costs is biased
    towards integer disparities ("pixel locking"); this refinement on the float images is not.

    Parameters
    ----------
    left, right : (H, W) float32
        Rectified images on the same grid, same photometric scale (``right`` may be wider: see
        ``right_x0``).
    disparity : (H, W) float32
        Starting disparity ``x_left - x_right`` in pixels of this grid; NaN = hole.
    sigma_px : float
        Std of the Gaussian window, pixels.
    iterations : int
    max_step_px : float
        A pixel whose refined disparity moved more than this from the start is a hole.
    right_x0 : int
        The column of ``right`` that column 0 of ``left`` and ``disparity`` sits on (a band of
        columns refined against the whole right image).

    Returns
    -------
    (H, W) float32
        Refined disparity, NaN where the start was NaN, the warp left the right image,
        the window had no texture, or the update moved too far.
    """
    h, w = disparity.shape
    valid = np.isfinite(disparity)
    d = np.where(valid, disparity, 0).astype(np.float32)
    kernel = np.array([[-0.5, 0.0, 0.5]], np.float32)
    gx_l = cv2.filter2D(left, cv2.CV_32F, kernel, borderType=cv2.BORDER_REPLICATE)
    gx_r = cv2.filter2D(right, cv2.CV_32F, kernel, borderType=cv2.BORDER_REPLICATE)
    xs = np.arange(right_x0, right_x0 + w, dtype=np.float32)[None, :]
    ys = np.broadcast_to(np.arange(h, dtype=np.float32)[:, None], (h, w))
    support = valid.copy()
    inside = np.empty((h, w), bool)
    sums = np.empty((5, h, w), np.float32)  # wgt, wgt g, wgt r, wgt g r, wgt g g
    blurred = np.empty_like(sums)
    weights = np.empty((h, w), np.float32)  # the last blurred wgt
    for step in range(int(iterations)):
        map_x = xs - d
        warped = cv2.remap(right, map_x, ys, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REPLICATE)
        gx_w = cv2.remap(gx_r, map_x, ys, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REPLICATE)
        # right(x - d - delta) + c ~ left, with an offset c per window  ->  delta = -cov(g, r) / var(g)
        _step_terms(map_x, right.shape[1], gx_l, gx_w, left, warped, support, inside, sums)
        # the weights' window sums stand while no pixel's weight changed (the usual case)
        same_weights = step > 0 and np.array_equal(sums[0], weights)
        if not same_weights:
            weights[...] = sums[0]
        for k in range(1 if same_weights else 0, len(sums)):
            cv2.GaussianBlur(sums[k], (0, 0), sigma_px, dst=blurred[k])
        _gauss_newton_step(blurred, valid, inside, d, support)
    out = np.where(support & (np.abs(d - np.where(valid, disparity, 0)) <= max_step_px), d, np.nan)
    return out.astype(np.float32)


@numba.njit(nogil=True, cache=True)
def _step_terms(
    map_x: Arr,
    right_width: int,
    gx_l: Arr,
    gx_w: Arr,
    left: Arr,
    warped: Arr,
    support: Arr,
    inside: Arr,
    sums: Arr,
) -> None:  # pragma: no cover - compiled
    """The windowed sums' terms of one Gauss-Newton step into ``sums`` (5, H, W): ``wgt``, ``wgt g``,
    ``wgt r``, ``wgt g r`` and ``wgt g g``, with the symmetric gradient ``g`` (the left's and the
    warped right's mean), the residual ``r = left - warped`` and the weight ``wgt`` (the pixel
    supported and its warp ``map_x`` inside the right image, ``right_width`` px wide: ``inside``,
    also written). float32 in numpy's order of operations (the values of the array expressions they
    replace); single-threaded, as it runs on the bands' threads."""
    h, w = map_x.shape
    half, lo, hi = np.float32(0.5), np.float32(1.0), np.float32(right_width - 2)
    for i in range(h):
        for j in range(w):
            mx = map_x[i, j]
            ins = (mx >= lo) & (mx <= hi)
            inside[i, j] = ins
            wgt = np.float32(1.0) if support[i, j] & ins else np.float32(0.0)
            g = half * (gx_l[i, j] + gx_w[i, j])
            r = left[i, j] - warped[i, j]
            wg = wgt * g
            sums[0, i, j] = wgt
            sums[1, i, j] = wg
            sums[2, i, j] = wgt * r
            sums[3, i, j] = wg * r
            sums[4, i, j] = wg * g


@numba.njit(nogil=True, cache=True, error_model="numpy")
def _gauss_newton_step(
    blurred: Arr, valid: Arr, inside: Arr, d: Arr, support: Arr
) -> None:  # pragma: no cover - compiled
    """One Gauss-Newton step from the blurred terms of :func:`_step_terms` (``blurred`` (5, H, W)): ``d`` moved in place by
    ``-num / den`` where ``den`` is not degenerate, ``support`` set to the pixels it moved. The
    numerator and denominator are the windows' centred sums (an intensity offset per window
    eliminated: zero-mean SSD). A glossy plate's lobe sits at different places in the two views (each
    camera sees its own mirror points), so a matched point differs between them by an additive,
    slowly varying brightness; plain SSD turns that difference into a disparity (mm of depth under
    near-field LEDs), the window's own offset takes it out. float32 in numpy's order of operations."""
    h, w = d.shape
    floor, zero = np.float32(1e-3), np.float32(0.0)
    s1, sg, sr, sgr, sgg = blurred[0], blurred[1], blurred[2], blurred[3], blurred[4]
    for i in range(h):
        for j in range(w):
            inv = np.float32(1.0) / s1[i, j] if s1[i, j] > floor else zero
            num = sgr[i, j] - sg[i, j] * sr[i, j] * inv
            den = sgg[i, j] - sg[i, j] * sg[i, j] * inv
            moved = den > floor
            step = -num / den if moved else zero
            d[i, j] = d[i, j] + step * (np.float32(1.0) if valid[i, j] else zero)
            support[i, j] = valid[i, j] & inside[i, j] & moved


def match_correlation(
    left: np.ndarray,
    right: np.ndarray,
    disparity: np.ndarray,
    *,
    sigma_px: float,
    right_x0: int = 0,
) -> np.ndarray:
    """Zero-mean normalised cross-correlation of each match over a Gaussian window.

    Parameters
    ----------
    left, right : (H, W) float32
        Rectified images on the same grid (``right`` may be wider: see ``right_x0``).
    disparity : (H, W) float32
        ``x_left - x_right``, pixels; NaN = hole.
    sigma_px : float
        Std of the Gaussian window, pixels.
    right_x0 : int
        The column of ``right`` that column 0 of ``left`` and ``disparity`` sits on.

    Returns
    -------
    (H, W) float32
        ZNCC in [-1, 1] between the left window and the right image warped by the disparity
        (each pixel by its own disparity); NaN at holes and where a window has no contrast.
    """
    h, w = disparity.shape
    valid = np.isfinite(disparity)
    xs = np.arange(right_x0, right_x0 + w, dtype=np.float32)[None, :]
    ys = np.broadcast_to(np.arange(h, dtype=np.float32)[:, None], (h, w))
    map_x = (xs - np.where(valid, disparity, 0)).astype(np.float32)
    warped = cv2.remap(right, map_x, ys, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REPLICATE)
    sums = np.empty((6, h, w), np.float32)
    _correlation_terms(valid, left, warped, sums)
    blurred = np.empty_like(sums)
    for k in range(len(sums)):
        cv2.GaussianBlur(sums[k], (0, 0), sigma_px, dst=blurred[k])
    zncc = np.empty((h, w), np.float32)
    _zncc(blurred, valid, zncc)
    return zncc


@numba.njit(nogil=True, cache=True)
def _correlation_terms(
    valid: Arr, left: Arr, warped: Arr, sums: Arr
) -> None:  # pragma: no cover - compiled
    """The windowed means' terms of the ZNCC into ``sums`` (6, H, W): ``wgt``, ``wgt l``, ``wgt r``,
    ``wgt l l``, ``wgt r r``, ``wgt l r`` (``l`` the left image, ``r`` the warped right, ``wgt`` 1 at
    the matches). float32 in numpy's order of operations; single-threaded (the bands' threads)."""
    h, w = valid.shape
    for i in range(h):
        for j in range(w):
            wgt = np.float32(1.0) if valid[i, j] else np.float32(0.0)
            a, b = left[i, j], warped[i, j]
            sums[0, i, j] = wgt
            sums[1, i, j] = wgt * a
            sums[2, i, j] = wgt * b
            sums[3, i, j] = wgt * (a * a)
            sums[4, i, j] = wgt * (b * b)
            sums[5, i, j] = wgt * (a * b)


@numba.njit(nogil=True, cache=True, error_model="numpy")
def _zncc(blurred: Arr, valid: Arr, out: Arr) -> None:  # pragma: no cover - compiled
    """The ZNCC from the blurred terms of :func:`_correlation_terms` (``blurred`` (6, H, W)) into ``out``; NaN off the matches
    and where a window has no contrast. float32 in numpy's order of operations."""
    h, w = valid.shape
    floor, zero = np.float32(1e-6), np.float32(0.0)
    norm, sl, sr, sll, srr, slr = (
        blurred[0],
        blurred[1],
        blurred[2],
        blurred[3],
        blurred[4],
        blurred[5],
    )
    for i in range(h):
        for j in range(w):
            n = norm[i, j]
            m_l, m_r = sl[i, j] / n, sr[i, j] / n
            var_l = sll[i, j] / n - m_l * m_l
            var_r = srr[i, j] / n - m_r * m_r
            cov = slr[i, j] / n - m_l * m_r
            if valid[i, j] and var_l > floor and var_r > floor:
                out[i, j] = cov / np.sqrt(max(var_l, zero) * max(var_r, zero))
            else:
                out[i, j] = np.nan
