"""Sub-pixel refinement and the correlation check of a disparity map on a rectified pair."""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np
import numpy.typing as npt

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
        Rectified images on the same grid, same photometric scale.
    disparity : (H, W) float32
        Starting disparity ``x_left - x_right`` in pixels of this grid; NaN = hole.
    sigma_px : float
        Std of the Gaussian window, pixels.
    iterations : int
    max_step_px : float
        A pixel whose refined disparity moved more than this from the start is a hole.

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
    xs = np.arange(w, dtype=np.float32)[None, :]
    ys = np.broadcast_to(np.arange(h, dtype=np.float32)[:, None], (h, w))
    support = valid.copy()
    for _ in range(int(iterations)):
        map_x = xs - d
        inside = (map_x >= 1) & (map_x <= w - 2)
        warped = cv2.remap(right, map_x, ys, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REPLICATE)
        g = 0.5 * (
            gx_l + cv2.remap(gx_r, map_x, ys, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REPLICATE)
        )
        r = left - warped
        wgt = (support & inside).astype(np.float32)
        # right(x - d - delta) + c ~ left, with an offset c per window  ->  delta = -cov(g, r) / var(g)
        num, den = _centred_sums(wgt, g, r, sigma_px)
        with np.errstate(divide="ignore", invalid="ignore"):
            step = np.where(den > 1e-3, -num / den, 0).astype(np.float32)
        d = d + step * valid
        support = valid & inside & (den > 1e-3)
    out = np.where(support & (np.abs(d - np.where(valid, disparity, 0)) <= max_step_px), d, np.nan)
    return out.astype(np.float32)


def _centred_sums(
    wgt: np.ndarray, g: np.ndarray, r: np.ndarray, sigma_px: float
) -> tuple[np.ndarray, np.ndarray]:
    """Gaussian-windowed ``sum(w g r) - sum(w g) sum(w r) / sum(w)`` and ``sum(w g g) - sum(w g)^2 /
    sum(w)``: the Gauss-Newton step's numerator and denominator with an unknown intensity offset per
    window eliminated (zero-mean SSD). A glossy plate's lobe sits at different places in the two
    views (each camera sees its own mirror points), so a matched point differs between them by an
    additive, slowly varying brightness; plain SSD turns that difference into a disparity (mm of
    depth under near-field LEDs), the window's own offset takes it out."""
    s1 = cv2.GaussianBlur(wgt, (0, 0), sigma_px)
    sg = cv2.GaussianBlur(wgt * g, (0, 0), sigma_px)
    sr = cv2.GaussianBlur(wgt * r, (0, 0), sigma_px)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = np.where(s1 > 1e-3, 1.0 / s1, 0).astype(np.float32)
    num = cv2.GaussianBlur(wgt * g * r, (0, 0), sigma_px) - sg * sr * inv
    den = cv2.GaussianBlur(wgt * g * g, (0, 0), sigma_px) - sg * sg * inv
    return num, den


def match_correlation(
    left: np.ndarray, right: np.ndarray, disparity: np.ndarray, *, sigma_px: float
) -> np.ndarray:
    """Zero-mean normalised cross-correlation of each match over a Gaussian window.

    Parameters
    ----------
    left, right : (H, W) float32
        Rectified images on the same grid.
    disparity : (H, W) float32
        ``x_left - x_right``, pixels; NaN = hole.
    sigma_px : float
        Std of the Gaussian window, pixels.

    Returns
    -------
    (H, W) float32
        ZNCC in [-1, 1] between the left window and the right image warped by the disparity
        (each pixel by its own disparity); NaN at holes and where a window has no contrast.
    """
    h, w = disparity.shape
    valid = np.isfinite(disparity)
    xs = np.arange(w, dtype=np.float32)[None, :]
    ys = np.broadcast_to(np.arange(h, dtype=np.float32)[:, None], (h, w))
    map_x = (xs - np.where(valid, disparity, 0)).astype(np.float32)
    warped = cv2.remap(right, map_x, ys, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REPLICATE)
    wgt = valid.astype(np.float32)

    def mean(x: npt.NDArray[Any]) -> npt.NDArray[Any]:
        blurred: npt.NDArray[Any] = cv2.GaussianBlur(wgt * x, (0, 0), sigma_px)
        return blurred

    norm = mean(np.ones_like(left))
    with np.errstate(divide="ignore", invalid="ignore"):
        m_l, m_r = mean(left) / norm, mean(warped) / norm
        var_l = mean(left * left) / norm - m_l * m_l
        var_r = mean(warped * warped) / norm - m_r * m_r
        cov = mean(left * warped) / norm - m_l * m_r
        zncc = cov / np.sqrt(np.maximum(var_l, 0) * np.maximum(var_r, 0))
    return np.where(valid & (var_l > 1e-6) & (var_r > 1e-6), zncc, np.nan).astype(np.float32)
