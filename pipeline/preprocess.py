"""Preprocessing of a capture: dark frame, light intensity, undistortion, plate mask, per-image validity.

Everything after this stage works on the *undistorted* left image grid with the
calibration's K: pixel ``(u, v)`` sees the ray ``K^-1 (u, v, 1)``.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace
from typing import Any

import cv2
import numba
import numpy as np
import numpy.typing as npt

from pipeline.camera import StereoRig
from pipeline.formats import CaptureError
from pipeline.io import Capture
from pipeline.parallel import default_workers
from pipeline.solvers import labelled
from pipeline.surface.normals.noise import image_noise

#: An array argument of the kernels (their dtypes are set by the callers).
Arr = npt.NDArray[Any]

#: A raw sample at or above this fraction of full scale counts as saturated.
SATURATION_FRACTION = 0.98


def saturation_level(bit_depth: int) -> float:
    """The raw count at and above which a sample of a ``bit_depth``-bit capture is saturated."""
    return SATURATION_FRACTION * float(2**bit_depth - 1)


#: The working grid's coarsest cell on the plate (mm): a capture whose pixels see a finer footprint at
#: its working distance is binned by the largest whole factor that keeps the cell within this (see
#: :func:`working_binning`). At 4 mm the default smallest failing region (100 mm^2,
#: pipeline.judge.verdict.MIN_DEFECT_AREA_MM2) still covers ~6 cells.
WORKING_CELL_MM = 4.0


#: The share of a pixel's samples, its brightest, set aside from the brightness the plate is told
#: from its surroundings by (highlights; the robust normals' first fit sets aside as many,
#: pipeline.surface.normals.robust.TRIM_TOP_FRACTION).
HIGHLIGHT_SHARE = 0.3
#: The share of a pixel's samples, its darkest, below the sample it is told from glare-lit surroundings
#: by (:attr:`Preprocessed.glare_free`): a broad lobe lights every sample, least the darkest; the
#: darkest quarter's brightest keeps clear of up to a quarter of the samples in attached shadow or
#: noise. On bench_lights case 11 the glare-lit conveyor reads 0.26-0.28 of the plate beside it in
#: any of its six darkest samples (0.34 in the median, true albedos 0.12).
GLARE_FREE_SHARE = 0.25


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
    brightest : (H, W) float32 or None
        The brightest of the images at each pixel (same unit as ``images``): the
        attached shadows are judged against it.
    seen : (H, W) bool or None
        Pixels whose undistorted ray lands inside the raw images (samples exist).
    brightness : (H, W) float32 or None
        The pixel's brightest sample once its brightest HIGHLIGHT_SHARE are set aside
        (the highlights of a glossy plate or conveyor under a few lights do not reach
        it): a part of the plate mask, and what :func:`pipeline.segmentation.segment_plate`
        takes as its brightness.
    glare_free : (H, W) float32 or None
        The brightest of the pixel's darkest GLARE_FREE_SHARE samples (rank ``N - 1 - int(N / 4)``
        from the top): a broad glare lobe lights every sample (of a conveyor beside the plate, too), least
        the darkest, so there the plate and its surroundings differ most nearly by their albedos. The
        outline beside lit surroundings is found by it (:mod:`pipeline.segmentation.outline`). (It was the
        median sample until a rust patch at the plate's edge beside a glare-lit conveyor was not told
        apart in it: docs/figures.md, bench_lights case 11 seed 1.)
    """

    images: np.ndarray
    valid: np.ndarray
    mask: np.ndarray
    n_saturated: int
    n_shadowed: int
    brightest: np.ndarray | None = None
    seen: np.ndarray | None = None
    brightness: np.ndarray | None = None
    glare_free: np.ndarray | None = None


def working_binning(capture: Capture, cell_mm: float | None, distance_mm: float) -> int:
    """The whole factor the capture's images are binned by for the working grid (1: full resolution).

    Derived from the cell's geometry, not from the scene: the largest factor ``b`` with
    ``b * z / f <= cell_mm``, ``z`` the working distance (``distance_mm`` without one) and ``f`` the
    left camera's larger focal length (px).

    Parameters
    ----------
    capture : Capture
    cell_mm : float or None
        The coarsest working cell on the plate, mm (None: full resolution).
    distance_mm : float
        The depth assumed without a working distance, mm.

    Returns
    -------
    int
        ``>= 1``.
    """
    return binning_factor(capture.rig.left.K, capture.working_distance_mm or distance_mm, cell_mm)


def binning_factor(K: np.ndarray, z_mm: float, cell_mm: float | None) -> int:
    """:func:`working_binning` of a left camera ``K`` at the depth ``z_mm``."""
    if cell_mm is None:
        return 1
    return max(1, int(cell_mm * max(K[0, 0], K[1, 1]) / z_mm))


def bin_capture(capture: Capture, factor: int, *, workers: int | None = None) -> Capture:
    """The capture on a grid ``factor`` times coarser: every image (photometric, dark, stereo pair)
    averaged over ``factor x factor`` blocks, both cameras resized to match.

    Averaging leaves the raw counts' unit. The sensor's noise, independent from pixel to pixel, falls
    by ``factor``: it is measured on the images as given and divided by ``factor``
    (``Capture.raw_noise``), as the binned images would take texture at the scale of a few bins for
    noise. A block holding a saturated raw sample (``SATURATION_FRACTION`` of full scale) takes its
    brightest sample, so that it is still found saturated; the calibration's RMS (px) is scaled with
    the pixels.

    Parameters
    ----------
    capture : Capture
        As loaded (raw counts, distorted), ``(W, H)`` = its rig's ``image_size``.
    factor : int
        ``>= 1``; 1 returns ``capture`` itself.
    workers : int, optional
        Threads (None: :func:`pipeline.parallel.default_workers`).

    Returns
    -------
    Capture
        Images ``(H // factor, W // factor)``, rig :meth:`pipeline.camera.CameraModel.resized` to it.
    """
    if factor < 1:
        raise ValueError(f"factor: expected a whole factor >= 1, got {factor}")
    if factor == 1:
        return capture
    w, h = capture.rig.image_size
    size = (w // factor, h // factor)
    threshold = saturation_level(capture.bit_depth)
    raws = [*capture.images, capture.dark, capture.stereo_left, capture.stereo_right]
    outs = [np.empty((size[1], size[0]), np.float32) for _ in raws]

    def one(k: int) -> None:
        raw = raws[k]
        if raw is not None:
            _bin_into(raw, outs[k], factor, threshold)

    with ThreadPoolExecutor(max_workers=workers or default_workers()) as pool:
        list(pool.map(one, range(len(raws))))
    own, dark = raw_noise_counts(capture)
    n = capture.n_lights
    return replace(
        capture,
        rig=binned_rig(capture.rig, factor),
        images=np.stack(outs[:n]),
        dark=None if capture.dark is None else outs[n],
        stereo_left=None if capture.stereo_left is None else outs[n + 1],
        stereo_right=None if capture.stereo_right is None else outs[n + 2],
        raw_noise=(own / factor, None if dark is None else dark / factor),
    )


def binned_rig(rig: StereoRig, factor: int) -> StereoRig:
    """The calibration of images binned ``factor`` times (:func:`bin_capture`): both cameras resized to
    ``image_size // factor``, the RMS (px) scaled with the pixels."""
    w, h = rig.image_size
    size = (w // factor, h // factor)
    rms = None if rig.rms_px is None else rig.rms_px / factor
    # the images' last rows and columns beyond a whole block are cropped first (K unchanged), so the
    # resize is by exactly 1 / factor
    whole = (size[0] * factor, size[1] * factor)
    left, right = (replace(cam, image_size=whole).resized(size) for cam in (rig.left, rig.right))
    return replace(rig, left=left, right=right, rms_px=rms)


def bin_into(raw: np.ndarray, out: np.ndarray, factor: int, bit_depth: int) -> None:
    """``out`` = ``raw`` binned ``factor`` times as :func:`bin_capture` bins each image (``bit_depth``:
    the capture's, which sets the saturation level)."""
    _bin_into(raw, out, factor, saturation_level(bit_depth))


def raw_noise_counts(capture: Capture) -> tuple[np.ndarray, float | None]:
    """The sensor noise (raw counts, standard deviation) of each photometric image, (N,) float64, and
    of the dark frame (None without one): as measured before binning (``Capture.raw_noise``), else
    measured on the images as given (:func:`pipeline.surface.normals.noise.image_noise`)."""
    if capture.raw_noise is not None:
        return capture.raw_noise
    everywhere = np.ones(capture.images.shape[1:], bool)
    own = image_noise(capture.images, everywhere)
    dark = None if capture.dark is None else float(image_noise(capture.dark[None], everywhere)[0])
    return own, dark


def _bin_into(raw: np.ndarray, out: np.ndarray, factor: int, threshold: float) -> None:
    """out (h, w) = the block means of ``raw`` (H, W); a block with a sample at or above ``threshold``
    takes its brightest sample."""
    h, w = out.shape
    whole = raw[: h * factor, : w * factor]
    cv2.resize(whole, (w, h), dst=out, interpolation=cv2.INTER_AREA)
    if raw.max() >= threshold:
        # a block's brightest sample is one of its samples at or above the threshold (and its mean no
        # brighter): the saturated samples alone set those blocks
        rows, cols = np.nonzero(whole >= threshold)
        np.maximum.at(out, (rows // factor, cols // factor), whole[rows, cols].astype(np.float32))


def preprocess(
    capture: Capture,
    *,
    shadow_fraction: float = 0.05,
    erode_px: int = 3,
    workers: int | None = None,
) -> Preprocessed:
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
    workers : int, optional
        Threads that prepare the images (None: :func:`pipeline.parallel.default_workers`).

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
    per-pixel maximum over the lights, joined with the same on the pixel's
    brightest sample once its brightest HIGHLIGHT_SHARE are set aside, then
    the largest connected component with its holes filled. On a glossy plate
    the highlights of a few lights make a third, brighter population of the
    maxima, and Otsu's threshold of the maxima alone fell between the plate's
    highlights and its body, leaving a quarter of the plate out (18 lights, a
    lobe half as bright as the diffuse part); the brightness without the
    highlights alone loses a dim rim that few lights reach (near-field LEDs'
    corners). Each lies on the plate; their union keeps both parts.
    """
    _check_shadow_fraction(shadow_fraction)
    return plate_found(
        undistorted(capture, workers=workers), shadow_fraction=shadow_fraction, erode_px=erode_px
    )


def _check_shadow_fraction(shadow_fraction: float) -> None:
    if not 0.0 <= shadow_fraction < 1.0:
        raise ValueError(f"shadow_fraction: expected a value in [0, 1), got {shadow_fraction}")


@dataclass(frozen=True)
class Undistorted:
    """The first part of :func:`preprocess`: the photometric images ready (as in :class:`Preprocessed`)
    with their brightness ranks, the plate not yet found (:func:`plate_found`).

    Attributes
    ----------
    images : (N, H, W) float32
    saturated : (N, H, W) bool
        Samples that interpolate from a saturated raw pixel (all False when ``any_saturated`` is).
    any_saturated : bool
    seen, brightest, brightness, glare_free
        As in :class:`Preprocessed`.
    """

    images: np.ndarray
    saturated: np.ndarray
    any_saturated: bool
    seen: np.ndarray
    brightest: np.ndarray
    brightness: np.ndarray
    glare_free: np.ndarray


def undistorted(
    capture: Capture,
    *,
    workers: int | None = None,
    folded: tuple[np.ndarray, np.ndarray, bool] | None = None,
) -> Undistorted:
    """Dark-subtract, normalise and undistort a capture's photometric images, and rank each pixel's
    samples (the first part of :func:`preprocess`; ``workers`` as there).

    ``folded``: the images already undistorted one by one as they were taken (``(images, saturated,
    any_saturated)`` as :func:`undistort_into` gives them, :mod:`pipeline.acquisition.streaming`), only ranked here.
    """
    map1, map2 = capture.rig.left.undistort_maps()
    raw, dark = capture.images, capture.dark
    n, (h, w) = capture.n_lights, raw.shape[1:]
    # undistorted pixels whose ray leaves the raw image have no sample in any image
    seen = cv2.remap(
        np.ones(raw.shape[1:], np.uint8), map1, map2, cv2.INTER_NEAREST, borderValue=0
    ).astype(bool)
    if folded is not None:
        images, saturated, any_saturated = folded
    else:
        images = np.empty((n, h, w), np.float32)
        # zero pages: only the images with a saturated pixel touch theirs
        saturated = np.zeros((n, h, w), bool)
        threshold = saturation_level(capture.bit_depth)
        gains = undistort_gains(capture.light_intensity, capture.bit_depth)

        def one(k: int) -> bool:
            return undistort_into(
                raw[k], dark, float(gains[k]), (map1, map2), threshold, images[k], saturated[k]
            )

        with ThreadPoolExecutor(max_workers=workers or default_workers()) as pool:
            any_saturated = any(list(pool.map(one, range(n))))  # list: every image must be done

    brightest = np.empty((h, w), np.float32)
    brightness = np.empty((h, w), np.float32)
    glare_free = np.empty((h, w), np.float32)
    low_rank = n - 1 - int(GLARE_FREE_SHARE * n)  # from the top
    _brightest(images, brightest, int(HIGHLIGHT_SHARE * n), brightness, low_rank, glare_free)
    return Undistorted(images, saturated, any_saturated, seen, brightest, brightness, glare_free)


def undistort_gains(intensity: np.ndarray, bit_depth: int) -> np.ndarray:
    """Each photometric image's gain in :func:`undistort_into`: its samples as fractions of full scale
    under a light of unit intensity."""
    return 1.0 / (np.asarray(intensity, np.float64) * float(2**bit_depth - 1))


def undistort_into(
    raw: np.ndarray,
    dark: np.ndarray | None,
    gain: float,
    maps: tuple[np.ndarray, np.ndarray],
    threshold: float,
    image: np.ndarray,
    saturated: np.ndarray,
) -> bool:
    """One photometric image of :func:`undistorted`: ``image`` = ``(raw - dark) * gain`` on the undistorted
    grid (``maps``: the left camera's :meth:`~pipeline.camera.CameraModel.undistort_maps`), ``saturated``
    its samples that interpolate from a raw pixel at or above ``threshold`` (written only when there is
    one: returns whether there is)."""
    map1, map2 = maps
    # (raw - dark) * gain in one pass
    signal = (
        cv2.addWeighted(raw, gain, dark, -gain, 0.0)
        if dark is not None
        else cv2.multiply(raw, gain)  # type: ignore[call-overload]  # (the stubs lack the scalar)
    )
    cv2.remap(
        signal,
        map1,
        map2,
        cv2.INTER_LINEAR,
        dst=image,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=0,
    )
    if raw.max() >= threshold:
        # a sample is bad if any raw pixel it interpolates from is saturated: dilate by one pixel first
        bad = cv2.dilate((raw >= threshold).view(np.uint8), np.ones((3, 3), np.uint8))
        saturated[...] = cv2.remap(bad, map1, map2, cv2.INTER_NEAREST, borderValue=0).astype(bool)
        return True
    return False


def plate_found(
    u: Undistorted, *, shadow_fraction: float = 0.05, erode_px: int = 3
) -> Preprocessed:
    """The second part of :func:`preprocess`: the plate mask and each sample's validity (the
    arguments as there)."""
    _check_shadow_fraction(shadow_fraction)
    n, h, w = u.images.shape
    # what either brightness tells from the dark: the maxima keep a rim that few lights reach, the
    # maxima without their highlights keep a glossy plate's body (see preprocess, Notes)
    mask = plate_mask(u.brightest, erode_px=erode_px, highlight_free=u.brightness) & u.seen
    valid = np.empty((n, h, w), bool)
    n_lit, n_saturated = _validity(
        u.images,
        u.brightest,
        u.saturated,
        u.any_saturated,
        u.seen,
        mask,
        np.float32(shadow_fraction),
        valid,
    )
    return Preprocessed(
        images=u.images,
        valid=valid,
        mask=mask,
        n_saturated=n_saturated,
        n_shadowed=n * int(np.count_nonzero(mask)) - n_lit - n_saturated,
        brightest=u.brightest,
        seen=u.seen,
        brightness=u.brightness,
        glare_free=u.glare_free,
    )


@numba.njit(parallel=True, cache=True)
def _brightest(images: Arr, out: Arr, rank: int, ranked: Arr, rank2: int, ranked2: Arr) -> None:
    """out (H, W) = the brightest of the N images (N, H, W) at each pixel; ranked, ranked2 (H, W) the
    samples of the given ranks from the top (0: the brightest)."""
    n, h, w = images.shape
    deep = max(rank, rank2) + 1
    for i in numba.prange(h):
        # the row's deep brightest samples, descending: each image's row is passed down through
        # them by compare-exchanges (branch-free, vectorised over the row's pixels); two arrays a row
        # (every thread allocates from one malloc arena, pipeline.parallel.MALLOC_ARENAS)
        top = np.full((deep, w), -np.inf, np.float32)
        x = np.empty(w, np.float32)
        for k in range(n):
            x[:] = images[k, i]
            for p in range(deep):
                row = top[p]
                for j in range(w):
                    hi = max(row[j], x[j])
                    x[j] = min(row[j], x[j])
                    row[j] = hi
        out[i] = top[0]
        ranked[i] = top[rank]
        ranked2[i] = top[rank2]


@numba.njit(parallel=True, cache=True)
def _validity(
    images: Arr,
    brightest: Arr,
    saturated: Arr,
    use_saturated: bool,
    seen: Arr,
    mask: Arr,
    shadow_fraction: float | np.floating[Any],
    valid: Arr,
) -> tuple[int, int]:
    """valid (N, H, W) = lit (not darker than shadow_fraction * brightest), not saturated, seen.

    Returns (samples inside ``mask`` that are lit and not saturated, saturated samples inside
    ``mask``).
    """
    n, h, w = images.shape
    lit_rows = np.zeros(h, np.int64)
    sat_rows = np.zeros(h, np.int64)
    for i in numba.prange(h):
        lit_i = 0
        sat_i = 0
        for k in range(n):
            for j in range(w):
                lit = images[k, i, j] >= shadow_fraction * brightest[i, j]
                sat = use_saturated and saturated[k, i, j]
                valid[k, i, j] = lit and not sat and seen[i, j]
                if mask[i, j]:
                    lit_i += 1 if (lit and not sat) else 0
                    sat_i += 1 if sat else 0
        lit_rows[i] = lit_i
        sat_rows[i] = sat_i
    return int(lit_rows.sum()), int(sat_rows.sum())


def plate_mask(
    brightness: np.ndarray,
    *,
    erode_px: int = 3,
    min_fraction: float = 0.02,
    highlight_free: np.ndarray | None = None,
) -> np.ndarray:
    """Tell the plate from the conveyor by an adaptive (Otsu) threshold.

    Parameters
    ----------
    brightness : (H, W) float
        Per-pixel brightest sample over the lights (any unit; NaN/0 outside).
    erode_px : int
        Erosion of the final mask, pixels.
    min_fraction : float
        The plate must cover at least this fraction of the image.
    highlight_free : (H, W) float, optional
        A second brightness of the same pixels, the brightest samples once the highlights are set
        aside, thresholded by its own Otsu level: a pixel bright in either is plate (see
        :func:`preprocess`, Notes).

    Returns
    -------
    (H, W) bool, True on the plate.

    Raises
    ------
    CaptureError
        When the plate covers less than ``min_fraction`` of the image or the
        image has no contrast.
    """
    binary = _otsu_binary(brightness)
    if highlight_free is not None:
        binary |= _otsu_binary(highlight_free)
    binary = cv2.morphologyEx(binary, cv2.MORPH_OPEN, np.ones((5, 5), np.uint8))
    n, labels, areas = labelled(binary, connectivity=4)
    if n <= 1:
        raise CaptureError(
            "photometric images: no plate found (no region brighter than the background)"
        )
    largest = 1 + int(np.argmax(areas[1:]))
    mask = _fill_holes(labels == largest)
    if erode_px > 0:
        k = 2 * erode_px + 1
        mask = cv2.erode(mask.view(np.uint8), np.ones((k, k), np.uint8)).astype(bool)
        # erosion can cut off slivers at a ragged edge: keep the plate itself
        n, labels, areas = labelled(mask, connectivity=4)
        if n > 2:
            mask = labels == 1 + int(np.argmax(areas[1:]))
    if mask.mean() < min_fraction:
        raise CaptureError(
            f"photometric images: the plate covers {100 * mask.mean():.1f} % of the image, "
            f"expected at least {100 * min_fraction:.0f} %"
        )
    return mask


def _otsu_binary(brightness: np.ndarray) -> np.ndarray:
    """(H, W) uint8, 1 above Otsu's threshold of the smoothed brightness."""
    b = np.asarray(brightness, dtype=np.float32)
    if np.isnan(b).any():
        b = np.nan_to_num(b, nan=0.0)
    # smooth the texture so the threshold sees the plate, not its rust spots or a single highlight
    smooth = cv2.GaussianBlur(b, (0, 0), 2.0)
    hi = float(smooth.max())
    if not hi > 0:
        raise CaptureError("photometric images: no light on the plate (all images dark)")
    # 0..255: negative values (dark-subtracted noise) to 0 first
    eight = cv2.convertScaleAbs(
        cv2.threshold(smooth, 0.0, 0.0, cv2.THRESH_TOZERO)[1], alpha=255.0 / hi
    )
    binary: np.ndarray = cv2.threshold(eight, 0, 1, cv2.THRESH_BINARY + cv2.THRESH_OTSU)[1]
    return binary


def _fill_holes(mask: np.ndarray) -> np.ndarray:
    """Fill the holes of a (H, W) bool region: background parts that do not touch the image border.

    The region is framed by one pixel of background, which joins every background part that
    touches the border; one 4-connected flood fill from the frame's corner reaches exactly those.
    """
    h, w = mask.shape
    framed = np.zeros((h + 2, w + 2), np.uint8)
    framed[1:-1, 1:-1] = mask
    cv2.floodFill(framed, None, (0, 0), 2, flags=4)
    inside: npt.NDArray[np.bool_] = framed[1:-1, 1:-1] != 2
    return inside
