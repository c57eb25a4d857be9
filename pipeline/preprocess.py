"""Preprocessing of a capture: dark frame, light intensity, undistortion, plate mask, per-image validity.

Everything after this stage works on the *undistorted* left image grid with the
calibration's K: pixel ``(u, v)`` sees the ray ``K^-1 (u, v, 1)``.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import cv2
import numpy as np

from .formats import CaptureError
from .io import Capture

#: A raw sample at or above this fraction of full scale counts as saturated.
SATURATION_FRACTION = 0.98


@dataclass(frozen=True)
class Preprocessed:
    """Photometric images ready for normal estimation.

    Attributes
    ----------
    images : (N, H, W) float32
        Dark-subtracted, undistorted, divided by light intensity; counts relative
        to full scale (so a white surface facing a unit light is ~1).
    valid : (N, H, W) bool
        True where sample k of a pixel is usable: inside the raw image, not
        saturated, not in an attached shadow.
    mask : (H, W) bool
        The plate, True = plate pixel (undistorted grid).
    n_saturated : int
        Samples dropped as saturated (inside the plate).
    n_shadowed : int
        Samples dropped as shadowed (inside the plate).
    """

    images: np.ndarray
    valid: np.ndarray
    mask: np.ndarray
    n_saturated: int
    n_shadowed: int


def preprocess(capture: Capture, *, shadow_fraction: float = 0.05, erode_px: int = 3) -> Preprocessed:
    """Dark-subtract, normalise, undistort and mask a capture's photometric images.

    Parameters
    ----------
    capture : Capture
        As loaded by :func:`pipeline.io.load_capture` (raw counts, distorted).
    shadow_fraction : float
        A sample darker than this fraction of the pixel's brightest sample is
        treated as an attached shadow (dimensionless, 0..1).
    erode_px : int
        The plate mask is eroded by this many pixels so that mixed pixels at the
        plate's edge do not enter the solve.

    Returns
    -------
    Preprocessed

    Raises
    ------
    CaptureError
        When no plate can be told from the background.

    Notes
    -----
    The plate mask is the source paper's adaptive threshold: Otsu's threshold
    (chosen from the histogram of this capture, not a fixed level) on the
    per-pixel maximum over the lights, then the largest connected component
    with its holes filled.
    """
    if not 0.0 <= shadow_fraction < 1.0:
        raise ValueError(f"shadow_fraction: expected a value in [0, 1), got {shadow_fraction}")
    full_scale = float(2**capture.bit_depth - 1)
    camera = capture.rig.left
    map1, map2 = camera.undistort_maps()
    raw, dark = capture.images, capture.dark
    n, (h, w) = capture.n_lights, raw.shape[1:]
    # undistorted pixels whose ray leaves the raw image have no sample in any image
    seen = cv2.remap(np.ones(raw.shape[1:], np.uint8), map1, map2, cv2.INTER_NEAREST, borderValue=0).astype(bool)
    images = np.empty((n, h, w), np.float32)
    saturated = np.zeros((n, h, w), bool)
    threshold = SATURATION_FRACTION * full_scale

    def one(k: int) -> bool:
        img = raw[k]
        gain = 1.0 / (capture.light_intensity[k] * full_scale)
        # (img - dark) * gain in one pass
        signal = cv2.addWeighted(img, gain, dark, -gain, 0.0) if dark is not None else cv2.multiply(img, gain)
        cv2.remap(signal, map1, map2, cv2.INTER_LINEAR, dst=images[k], borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        if img.max() >= threshold:
            # a sample is bad if any raw pixel it interpolates from is saturated: dilate by one pixel first
            bad = cv2.dilate((img >= threshold).view(np.uint8), np.ones((3, 3), np.uint8))
            saturated[k] = cv2.remap(bad, map1, map2, cv2.INTER_NEAREST, borderValue=0).astype(bool)
            return True
        return False

    with ThreadPoolExecutor(max_workers=2) as pool:
        any_saturated = any(list(pool.map(one, range(n))))  # list: every image must be done

    brightest = images.max(axis=0)
    mask = plate_mask(brightest, erode_px=erode_px) & seen
    valid = images >= shadow_fraction * brightest[None]  # not in an attached shadow
    n_lit = int(np.count_nonzero(valid & mask))
    n_saturated = 0
    if any_saturated:
        n_saturated = int(np.count_nonzero(saturated & mask))
        n_lit -= int(np.count_nonzero(valid & saturated & mask))
        valid &= ~saturated
    valid &= seen
    return Preprocessed(
        images=images,
        valid=valid,
        mask=mask,
        n_saturated=n_saturated,
        n_shadowed=n * int(np.count_nonzero(mask)) - n_lit - n_saturated,
    )


def plate_mask(brightness: np.ndarray, *, erode_px: int = 3, min_fraction: float = 0.02) -> np.ndarray:
    """Tell the plate from the conveyor by an adaptive (Otsu) threshold.

    Parameters
    ----------
    brightness : (H, W) float
        Per-pixel brightest sample over the lights (any unit; NaN/0 outside).
    erode_px : int
        Erosion of the final mask, pixels.
    min_fraction : float
        The plate must cover at least this fraction of the image.

    Returns
    -------
    (H, W) bool, True on the plate.

    Raises
    ------
    CaptureError
        When the plate covers less than ``min_fraction`` of the image or the
        image has no contrast.
    """
    b = np.nan_to_num(np.asarray(brightness, dtype=np.float32), nan=0.0)
    # smooth the texture so the threshold sees the plate, not its rust spots or a single highlight
    smooth = cv2.GaussianBlur(b, (0, 0), 2.0)
    hi = float(smooth.max())
    if not hi > 0:
        raise CaptureError("photometric images: no light on the plate (all images dark)")
    eight = np.clip(smooth * (255.0 / hi), 0, 255).astype(np.uint8)
    _, binary = cv2.threshold(eight, 0, 1, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
    binary = cv2.morphologyEx(binary, cv2.MORPH_OPEN, np.ones((5, 5), np.uint8))
    n, labels, stats, _ = cv2.connectedComponentsWithStats(binary, connectivity=4)
    if n <= 1:
        raise CaptureError("photometric images: no plate found (no region brighter than the background)")
    largest = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    mask = _fill_holes(labels == largest)
    if erode_px > 0:
        k = 2 * erode_px + 1
        mask = cv2.erode(mask.view(np.uint8), np.ones((k, k), np.uint8)).astype(bool)
        # erosion can cut off slivers at a ragged edge: keep the plate itself
        n, labels, stats, _ = cv2.connectedComponentsWithStats(mask.view(np.uint8), connectivity=4)
        if n > 2:
            mask = labels == 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    if mask.mean() < min_fraction:
        raise CaptureError(
            f"photometric images: the plate covers {100 * mask.mean():.1f} % of the image, "
            f"expected at least {100 * min_fraction:.0f} %"
        )
    return mask


def _fill_holes(mask: np.ndarray) -> np.ndarray:
    """Fill the holes of a (H, W) bool region: background parts that do not touch the image border."""
    n, labels = cv2.connectedComponents((~mask).view(np.uint8), connectivity=4)
    border = np.unique(np.concatenate([labels[0], labels[-1], labels[:, 0], labels[:, -1]]))
    keep = np.zeros(n, bool)
    keep[border] = True
    keep[0] = False  # label 0 is the region itself
    return ~keep[labels]
