"""Light calibration: the cell's point lights (LEDs) measured on a flat, matte reference plate.

The plate's pose comes from the capture's stereo pair (stereo depth, robust plane fit), so every
plate pixel has a known surface point X (left-camera frame, mm) and the plate's unit normal n. The
lights are then fitted jointly on the images' ratios (:mod:`pipeline.lights.fit`: the model, the
variable projection that eliminates the plate's albedo, the Levenberg-Marquardt steps). Samples are
block means of the undistorted, dark-subtracted images (a block of a few pixels sees one surface
point to well under a millimetre of the model), taken where all of a block's samples are valid (lit,
not saturated).

Ratios fix the intensities up to one common factor: it is chosen so that the lights keep the
meaning of the capture format (``intensity`` = irradiance 1000 mm from the light on its axis,
relative units), at the scale of the capture's own lights: the mean over the lights of the
irradiance each casts on a surface facing it at the plate's centre equals that of the lights the
capture gives (a distant light's given intensity is that irradiance).

The joint fit starts from the nominal lights (a few mm, see benchmarks/bench_light_calibration.py).
It runs first with every ``mu`` held at its start, then with all parameters free, then once more
without the samples whose residual exceeds 6 robust standard deviations.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, replace

import cv2
import numpy as np

from pipeline.formats import CaptureError, InputError
from pipeline.io import Capture
from pipeline.judge.fits import fit_plane
from pipeline.lights.fit import JointFit, PlatePose, Samples, initial_point_lights, joint_fit
from pipeline.lights.model import Lights
from pipeline.parallel import single_threaded_blas
from pipeline.preprocess import preprocess
from pipeline.surface import stereo

#: Stereo depth search when the capture gives no working distance: around this depth (mm) ...
NOMINAL_DISTANCE_MM = 3500.0
#: ... within ``/ (1 + margin)`` .. ``* (1 + margin)``.
DEPTH_MARGIN = 1.0
#: The stereo pair is matched at most this wide (px): the plane needs no finer depth.
STEREO_MAX_WIDTH = 1224
#: A sample darker than this fraction of the pixel's brightest (in counts) is in an attached shadow.
SHADOW_FRACTION = 0.05
#: Fewer stereo points on the plate than this and the plate's pose is not measured.
MIN_STEREO_POINTS = 500


@dataclass(frozen=True)
class LightCalibration:
    """The measured lights and how well they are determined.

    Attributes
    ----------
    lights : Lights
        N point lights in image order (left-camera frame, mm), each with an axis, ``mu`` and
        ``intensity`` (irradiance 1000 mm away on its axis, relative units; see the module
        docstring for the common scale).
    rms : float
        RMS of the fit's residuals ``I - rho E`` over all samples used, as a fraction of the mean
        sample (dimensionless; block-mean samples, so sensor noise enters reduced by the block
        size: mostly the model's misfit).
    position_std_mm : (N,) float64
        Standard error of each light's position, ``sqrt(var x + var y + var z)`` (mm), from the
        Jacobian at the solution scaled by the residual (assumes independent residuals).
    intensity_std : (N,) float64
        Standard error of each light's log intensity, i.e. of its intensity relative to the others'
        (geometric) mean, as a fraction (0.002 = 0.2 %).
    mu_std : (N,) float64
        Standard error of each ``mu``.
    lit_fraction : (N,) float64
        Fraction of the plate's pixels each light lights (valid samples: not in an attached
        shadow, not saturated); the smallest over the captures.
    n_samples : int
        Samples (blocks of ``block_px`` x ``block_px`` pixels, each with all N lights) in the fit.
    block_px : int
        Side of a sample block, pixels.
    iterations : int
        Evaluations of the joint fit's Jacobian (both rounds).
    plates : tuple of PlatePose
        The plate's pose in each capture.
    seconds : float
        Wall time of :func:`calibrate_lights` (s).
    """

    lights: Lights
    rms: float
    position_std_mm: np.ndarray
    intensity_std: np.ndarray
    mu_std: np.ndarray
    lit_fraction: np.ndarray
    n_samples: int
    block_px: int
    iterations: int
    plates: tuple[PlatePose, ...]
    seconds: float


def calibrate_lights(
    captures: Sequence[Capture],
    *,
    max_samples: int = 6000,
    block_px: int | None = None,
    min_lit_fraction: float = 0.5,
    min_plate_fraction: float = 0.05,
    max_position_std_mm: float = 15.0,
    initial_mu: float = 1.0,
    seed: int = 0,
) -> LightCalibration:
    """Measure the cell's point lights from captures of a flat, matte reference plate.

    Parameters
    ----------
    captures : sequence of Capture
        One or more ``plate-capture/1`` bundles (:func:`pipeline.io.load_capture`) of a flat plate,
        each with its stereo pair, all under the same N lights in the same order (the plate at
        different heights or places: all are fitted jointly). The lights they give (nominal
        directions, or positions) are the starting point: the first capture's.
    max_samples : int
        At most this many sample blocks enter the fit (spread over the captures).
    block_px : int, optional
        Side (pixels) of the square blocks whose means are the samples; default: as large as lets
        about ``max_samples`` blocks cover the plate (all its pixels enter the fit), at least 1.
    min_lit_fraction : float
        Refuse a light that lights (valid samples) less than this fraction of the plate (0..1).
    min_plate_fraction : float
        Refuse a plate that covers less than this fraction of the image (0..1).
    max_position_std_mm : float
        Refuse a light whose position's standard error exceeds this (mm). The default, 15 mm,
        keeps 2.5 standard errors within 40 mm. On simulated plates the errors follow the
        standard errors (a 3 x 3 m plate 2.8 m below a ring of 12 LEDs: 5-8 mm at 612 x 512 px;
        a 2 x 2 m plate: ~22 mm, refused; 1.5 x 1.5 m: ~60 mm).
    initial_mu : float
        LED exponent to start from where the capture gives none (directions only).
    seed : int
        Seeds the choice of sample blocks.

    Returns
    -------
    LightCalibration

    Raises
    ------
    CaptureError
        What cannot be measured, in one line naming the capture and, where it is one light's
        fault, ``lights[k]``: no plate, a plate covering too little of the image, no stereo pair or
        too little of it matched, a light lighting too little of the plate, a fit that does not
        converge, a light whose position is determined worse than ``max_position_std_mm`` or that
        ends up behind the plate.
    InputError
        Captures with different numbers of lights.
    ValueError
        Bad option values.
    """
    t0 = time.perf_counter()
    captures = list(captures)
    _check_arguments(
        captures,
        max_samples,
        block_px,
        min_lit_fraction,
        min_plate_fraction,
        max_position_std_mm,
        initial_mu,
    )
    per_capture = max(100, max_samples // len(captures))
    rng = np.random.default_rng(seed)
    samples, plates, lit, blocks = [], [], [], []
    for cap in captures:
        s, pose, lit_fraction, b = _capture_samples(
            cap,
            block_px=block_px,
            min_lit_fraction=min_lit_fraction,
            min_plate_fraction=min_plate_fraction,
            max_samples=per_capture,
            rng=rng,
        )
        samples.append(s)
        plates.append(pose)
        lit.append(lit_fraction)
        blocks.append(b)
    data = Samples(
        intensity=np.concatenate([s.intensity for s in samples]),
        points=np.concatenate([s.points for s in samples]),
        normals=np.concatenate([s.normals for s in samples]),
    )
    fit, data, iterations = _fit(captures[0].lights, plates[0], data, initial_mu)
    _check_fit(fit, captures, plates, max_position_std_mm)
    lights = fit.lights.with_intensity(
        fit.lights.intensity * _intensity_scale(captures, plates, fit.lights)
    )
    return LightCalibration(
        lights=lights,
        rms=fit.rms,
        position_std_mm=fit.position_std_mm,
        intensity_std=fit.intensity_std,
        mu_std=fit.mu_std,
        lit_fraction=np.min(np.stack(lit), axis=0),
        n_samples=len(data.intensity),
        block_px=int(blocks[0]),
        iterations=int(iterations),
        plates=tuple(plates),
        seconds=round(time.perf_counter() - t0, 3),
    )


def _check_arguments(
    captures: list[Capture],
    max_samples: int,
    block_px: int | None,
    min_lit_fraction: float,
    min_plate_fraction: float,
    max_position_std_mm: float,
    initial_mu: float,
) -> None:
    """ValueError (InputError for captures of different cells) naming what :func:`calibrate_lights` cannot use."""
    if not captures:
        raise ValueError("captures: expected at least one capture")
    if not (isinstance(max_samples, (int, np.integer)) and max_samples >= 100):
        raise ValueError(f"max_samples: expected an integer >= 100, got {max_samples}")
    if block_px is not None and not (isinstance(block_px, (int, np.integer)) and block_px >= 1):
        raise ValueError(f"block_px: expected a whole number of pixels >= 1, got {block_px}")
    for name, value in (
        ("min_lit_fraction", min_lit_fraction),
        ("min_plate_fraction", min_plate_fraction),
    ):
        if not 0.0 <= value < 1.0:
            raise ValueError(f"{name}: expected a fraction in [0, 1), got {value}")
    if not max_position_std_mm > 0:
        raise ValueError(f"max_position_std_mm: expected > 0 mm, got {max_position_std_mm}")
    if not (np.isfinite(initial_mu) and initial_mu >= 0):
        raise ValueError(f"initial_mu: expected >= 0, got {initial_mu}")
    n = captures[0].n_lights
    for cap in captures[1:]:
        if cap.n_lights != n:
            raise InputError(
                str(cap.source),
                "photometric.lights",
                f"expected {n} lights like {captures[0].source} (the same cell, same order), got {cap.n_lights}",
            )


def _fit(
    given: Lights, pose: PlatePose, data: Samples, initial_mu: float
) -> tuple[JointFit, Samples, int]:
    """The joint fit from the capture's lights: mu held, then free, then once more without the outliers.

    Returns the fit, the samples it used and the Jacobian evaluations of all rounds.
    """
    with single_threaded_blas():  # small products: a second BLAS thread only spins
        start = initial_point_lights(given, pose, data, initial_mu=initial_mu)
        # mu held first: a light aimed far from where the start has it would otherwise run mu down to 0,
        # where its axis no longer changes anything and stays wrong
        fit = joint_fit(start, data, fixed_mu=True)
        iterations = fit.njev
        fit = joint_fit(fit.lights, data)
        iterations += fit.njev
    # one round without the outliers (dust, a specular speck, a stereo outlier's block), from the solution
    r = fit.residuals
    sigma = 1.4826 * np.median(np.abs(r)) + 1e-12
    keep = np.all(np.abs(r) <= 6.0 * sigma, axis=1)
    if np.count_nonzero(~keep) > 0 and np.count_nonzero(keep) >= 0.5 * len(keep):
        data = Samples(data.intensity[keep], data.points[keep], data.normals[keep])
        with single_threaded_blas():
            fit = joint_fit(fit.lights, data)
        iterations += fit.njev
    return fit, data, iterations


def _check_fit(
    fit: JointFit, captures: list[Capture], plates: list[PlatePose], max_position_std_mm: float
) -> None:
    """CaptureError when a light's position is not determined, the fit did not converge, or a light was
    fitted behind the reference plate."""
    where = ", ".join(str(c.source) for c in captures)
    lights = fit.lights
    worst = int(np.argmax(np.where(np.isfinite(fit.position_std_mm), fit.position_std_mm, np.inf)))
    std = fit.position_std_mm[worst]
    if not std <= max_position_std_mm:  # the first question even when not converged
        raise CaptureError(
            f"{where}: lights[{worst}]: position not determined: standard error "
            + (
                f"{std:.1f} mm, "
                if np.isfinite(std)
                else "unbounded (the data do not constrain it), "
            )
            + f"expected at most {max_position_std_mm:.1f} mm (a larger reference plate, or a second bundle with "
            f"the plate at another height, determines it better)"
        )
    if not fit.success:
        raise CaptureError(
            f"{where}: light calibration: the joint fit did not converge ({fit.message})"
        )
    for cap, pose in zip(captures, plates):
        behind = np.flatnonzero((lights.positions_mm - pose.centre_mm) @ pose.normal <= 0)
        if len(behind):
            k = int(behind[0])
            raise CaptureError(
                f"{cap.source}: lights[{k}]: fitted behind the reference plate "
                f"(at {np.round(lights.positions_mm[k], 1).tolist()} mm), expected in front of it"
            )


def plate_pose(capture: Capture, mask: np.ndarray) -> PlatePose:
    """The plane of a flat plate from a capture's stereo pair.

    Parameters
    ----------
    capture : Capture
        With a stereo pair.
    mask : (H, W) bool
        The plate on the left undistorted grid (:func:`pipeline.preprocess.preprocess`).

    Returns
    -------
    PlatePose
        Normal towards the cameras and centre (mm, left-camera frame) of the plate; the plane
        is a total-least-squares fit to the stereo points, refitted twice without the points
        farther than 4 robust standard deviations (at least 2 mm) from it.

    Raises
    ------
    CaptureError
        No stereo pair, or fewer than ``MIN_STEREO_POINTS`` matched points on the plate.
    """
    left, right, stereo_mask = capture.stereo_left, capture.stereo_right, mask
    if left is None or right is None:  # not capture.has_stereo
        raise CaptureError(
            f"{capture.source}: stereo: a light calibration needs the stereo pair (the plate's pose)"
        )
    rig = capture.rig
    width, height = rig.image_size
    step = -(-width // STEREO_MAX_WIDTH)
    if step > 1:
        small = (width // step, height // step)
        left, right = (cv2.resize(im, small, interpolation=cv2.INTER_AREA) for im in (left, right))
        rig = replace(rig, left=rig.left.resized(small), right=rig.right.resized(small))
        stereo_mask = cv2.resize(
            mask.view(np.uint8), small, interpolation=cv2.INTER_NEAREST
        ).astype(bool)
    z = capture.working_distance_mm or NOMINAL_DISTANCE_MM
    sd = stereo.stereo_depth(
        left,
        right,
        rig,
        z_min_mm=z / (1 + DEPTH_MARGIN),
        z_max_mm=z * (1 + DEPTH_MARGIN),
        mask=stereo_mask,
    )
    ok = stereo_mask & np.isfinite(sd.depth_mm)
    if np.count_nonzero(ok) < MIN_STEREO_POINTS:
        raise CaptureError(
            f"{capture.source}: stereo: {np.count_nonzero(ok)} points of the plate matched in the stereo pair, "
            f"expected at least {MIN_STEREO_POINTS}"
        )
    points = sd.depth_mm[ok].astype(np.float64)[:, None] * rig.left.pixel_rays()[ok]
    if len(points) > 40000:
        points = points[np.random.default_rng(0).choice(len(points), 40000, replace=False)]
    keep = np.ones(len(points), bool)
    for _ in range(3):
        plane = fit_plane(points[keep])
        d = (points - plane.point_mm) @ plane.normal
        sigma = 1.4826 * np.median(np.abs(d[keep] - np.median(d[keep])))
        keep = np.abs(d) <= max(4.0 * sigma, 2.0)
    plane = fit_plane(points[keep])
    # the centre: the mean surface point of the plate's pixels, on the plane
    vs, us = np.nonzero(mask[::4, ::4])  # every 16th pixel is plenty for a mean
    K = capture.rig.left.K
    y = (4.0 * vs - K[1, 2]) / K[1, 1]
    rays = np.stack([(4.0 * us - K[0, 2] - K[0, 1] * y) / K[0, 0], y, np.ones_like(y)], axis=1)
    along = (plane.point_mm @ plane.normal) / (rays @ plane.normal)
    centre = (rays * along[:, None]).mean(axis=0)
    return PlatePose(
        normal=plane.normal, centre_mm=centre, rms_mm=plane.rms_mm, stereo_points=int(keep.sum())
    )


# =========================================================================== samples


def _capture_samples(
    cap: Capture,
    *,
    block_px: int | None,
    min_lit_fraction: float,
    min_plate_fraction: float,
    max_samples: int,
    rng: np.random.Generator,
) -> tuple[Samples, PlatePose, np.ndarray, int]:
    """Block-mean samples of one capture, its plate pose, each light's lit fraction of the plate, the block side (px)."""
    # shadows are told here, on the images in counts: the given (nominal) intensities that preprocess
    # divides by may be far off, and would move its relative shadow threshold with them
    pre = preprocess(cap, shadow_fraction=0.0)
    mask = pre.mask
    plate_fraction = float(mask.mean())
    if plate_fraction < min_plate_fraction:
        raise CaptureError(
            f"{cap.source}: the plate covers {100 * plate_fraction:.1f} % of the image, expected at least "
            f"{100 * min_plate_fraction:.0f} % for a light calibration"
        )
    # ours: back to fractions of full scale (dark subtracted, undistorted) in place
    images = pre.images
    for k in range(cap.n_lights):
        images[k] *= np.float32(cap.lights.intensity[k])
    threshold = np.float32(SHADOW_FRACTION) * images.max(axis=0)
    n_plate = np.count_nonzero(mask)
    usable = mask.copy()
    lit = np.empty(cap.n_lights)
    for k in range(cap.n_lights):
        # not saturated, seen, not in an attached shadow
        valid = pre.valid[k] & (images[k] >= threshold)
        lit[k] = np.count_nonzero(valid & mask) / n_plate
        usable &= valid
    worst = int(np.argmin(lit))
    if lit[worst] < min_lit_fraction:
        raise CaptureError(
            f"{cap.source}: lights[{worst}]: lights {100 * lit[worst]:.1f} % of the plate (not shadowed, not "
            f"saturated), expected at least {100 * min_lit_fraction:.0f} %"
        )
    pose = plate_pose(cap, mask)

    # block means
    if block_px is None:  # blocks so that about max_samples of them cover the plate
        block_px = max(1, int(np.sqrt(np.count_nonzero(usable) / max_samples)))
    h, w = mask.shape
    hb, wb = h // block_px, w // block_px

    def blocks(img: np.ndarray) -> np.ndarray:
        img = img[: hb * block_px, : wb * block_px]
        return img if block_px == 1 else cv2.resize(img, (wb, hb), interpolation=cv2.INTER_AREA)

    full = blocks(usable.astype(np.float32)) >= 1.0 - 1e-6
    ii, jj = np.nonzero(full)
    if len(ii) < 50:
        raise CaptureError(
            f"{cap.source}: {len(ii)} blocks of {block_px} x {block_px} px of the plate are lit by every light "
            f"(not shadowed, not saturated), expected at least 50"
        )
    if len(ii) > max_samples:
        pick = np.sort(rng.choice(len(ii), max_samples, replace=False))
        ii, jj = ii[pick], jj[pick]
    intensity = np.empty((len(ii), cap.n_lights))
    weight = np.zeros((h, w), np.float32)
    for k in range(cap.n_lights):
        intensity[:, k] = blocks(images[k])[ii, jj]
        weight += images[k]
    # a block's sample is the model at its albedo-weighted centre (the irradiance is smooth over a block)
    weight = np.maximum(weight, 0.0)
    vv, uu = np.mgrid[0:h, 0:w].astype(np.float32)
    total = blocks(weight)[ii, jj].astype(np.float64)
    u = blocks(weight * uu)[ii, jj] / total
    v = blocks(weight * vv)[ii, jj] / total
    K = cap.rig.left.K
    y = (v - K[1, 2]) / K[1, 1]
    x = (u - K[0, 2] - K[0, 1] * y) / K[0, 0]
    rays = np.stack([x, y, np.ones_like(x)], axis=1)
    along = (pose.centre_mm @ pose.normal) / (rays @ pose.normal)
    points = rays * along[:, None]
    normals = np.broadcast_to(pose.normal, points.shape).copy()
    return Samples(intensity=intensity, points=points, normals=normals), pose, lit, block_px


def _intensity_scale(
    captures: Sequence[Capture], plates: Sequence[PlatePose], lights: Lights
) -> float:
    """The common factor of the fitted intensities (see the module docstring)."""
    given, fitted = [], []
    for cap, pose in zip(captures, plates):
        given.append(np.mean(cap.lights.intensity * cap.lights.attenuation_at(pose.centre_mm)))
        fitted.append(np.mean(lights.intensity * lights.attenuation_at(pose.centre_mm)))
    return float(np.mean(given) / np.mean(fitted))
