"""The measurement's own uncertainty: per point and per result, expanded with k = 2 (GUM).

Every component is propagated from what the inspection itself measured, never from the deviation
it found:

- **Photometric** (per point). The image noise of each photometric image (estimated on the plate
  from its finest detail) and, where a pixel has more lights than unknowns, the residual of its
  fit (Lambertian, less the specular lobe the normals were fitted with on a glossy plate), with the
  lights that lit it, give the covariance of its normal
  ``sigma_I^2 (rho^2 L^T L)^-1``; its tangential part is a slope error per pixel step. The least-squares
  integration of white slope errors over a region ``L`` pixels wide leaves a depth error of variance
  ``sigma_g^2 (ln L / (2 pi) + 0.33)`` (the Neumann Laplacian's Green's function on a square,
  summed exactly over its modes), where ``L`` is the scale above which the stereo pair governs the
  shape (the correction's knot spacing, or the plate's extent when it sets only scale, tilt and
  bend).
- **Stereo correction** (per point). The standard deviation of the chosen correction from its fit's
  covariance, the noise and its correlation measured on the data, of its error beyond the plane in
  (u, v) through it (the registration takes up scale and tilt; :class:`pipeline.surface.fusion.Fusion`).
- **Scale** (per point and radius). The stereo pair's scale rests on its disparities: the matcher's
  disparity quantum (1/16 px, a rectangular distribution) and the calibration's reprojection
  error over its board's corners give a relative scale uncertainty ``u_d / d``; a point moves by
  that share of its height over the plate's best plane.
- **Bend** (radius). How well the stereo pair fixes the plate's bend: the covariance of the
  quadric correction's second derivatives, whichever correction was chosen (if the normals kept
  the bend, the stereo pair could not prove it wrong by more than that).
- **Registration** (per point and radius). The points' own noise over the independent patches the
  best fit is made on (never the fit's residual, which holds the plate's real deviation too).

The deviation's figure is the 95th percentile over the plate of the per-point expanded uncertainty
``U = 2 u``; the radius's is ``U = 2 R sqrt(u_bend^2 + u_scale^2 + u_fit^2)`` (relative parts).

References
----------
.. [1] JCGM 100:2008, "Evaluation of measurement data -- Guide to the expression of uncertainty in
   measurement" (GUM).
.. [2] ISO 14253-1:2017, "Decision rules for verifying conformity or nonconformity with
   specifications".
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any

import cv2
import numba
import numpy as np
import numpy.typing as npt
from scipy import sparse
from scipy.sparse.linalg import factorized

from pipeline.lights import glare
from pipeline.lights.model import Lights
from pipeline.solvers import bounding_box, percentile
from pipeline.surface import fusion as fusion_mod
from pipeline.surface import integration
from pipeline.surface.normals import NormalField, SpecularFit
from pipeline.surface.normals.noise import image_noise

#: An array argument of the kernel (its dtype is set by the caller).
Arr = npt.NDArray[Any]

#: Coverage factor of every expanded uncertainty the inspection reports.
COVERAGE_K = 2.0
#: A tolerance over this many expanded uncertainties (95th percentile over the plate) is a capable
#: measurement (the test uncertainty ratio of ISO 14253-1 practice); below it the result says so.
CAPABLE_RATIO = 4.0
#: Pixels sampled for the photometric part (every ``step``-th pixel in both directions so that about
#: this many remain); the map is interpolated between them.
PHOTOMETRIC_SAMPLES = 12_000
#: The stereo matcher's disparity quantum (px): OpenCV's SGBM gives disparities in 1/16 px.
DISPARITY_QUANTUM_PX = 1.0 / 16.0
#: Patches (px) over which the registration's points count as independent (about the stereo blocks).
REGISTRATION_PATCH_PX = 16.0
#: Pixels of the coarse grid on which the lobe's part re-solves the normals (its error is a bend of the
#: whole plate, smooth on the grid's scale; :func:`_lobe_var_mm2`).
LOBE_GRID_SAMPLES = 1500
#: The least-squares integration's depth variance per unit slope variance over a region L px wide:
#: ``ln(L) / (2 pi) + INTEGRATION_OFFSET`` (exact sum over the Neumann Laplacian's modes of an
#: L x L square; 0.320-0.326 for L = 32-2048).
INTEGRATION_OFFSET = 0.326


@dataclass(frozen=True)
class Uncertainty:
    """Expanded uncertainties (k = :data:`COVERAGE_K`) of an inspection.

    Attributes
    ----------
    map_mm : (H, W) float32
        Per-point expanded uncertainty of the surface along its normal, mm; NaN off the surface.
    deviation_mm : float
        The 95th percentile of ``map_mm`` over the judged surface, mm.
    radius_mm : float or None
        Expanded uncertainty of the fitted radius, mm (None without a radius).
    components : dict
        The standard uncertainties behind them (k = 1): ``photometric_mm``, ``correction_mm``
        (95th percentiles over the plate), ``scale_rel``, ``bend_rel``, ``fit_rel``,
        ``registration_mm``, and ``integration_scale_px`` (the ``L`` above).
    """

    map_mm: np.ndarray
    deviation_mm: float
    radius_mm: float | None
    components: dict[str, float]

    def capable(self, tolerance_mm: float) -> bool:
        """Whether ``tolerance_mm / deviation_mm`` reaches :data:`CAPABLE_RATIO`."""
        return bool(tolerance_mm >= CAPABLE_RATIO * self.deviation_mm)


@dataclass(frozen=True)
class Inputs:
    """What the uncertainty is propagated from (one inspection's measurement).

    Attributes
    ----------
    images : (N, H, W) float32
        The preprocessed photometric images the normals came from (divided by the lights' intensities).
    valid : (N, H, W) bool or None
    lights : Lights
        The lights the normals were estimated with (refined ones when they were refitted).
    field : NormalField
    points_mm : (H, W, 3) float
        The measured surface, left camera frame, mm (NaN off it).
    mask : (H, W) bool
        The judged surface.
    K : (3, 3) float
    fusion : Fusion or None
    baseline_mm : float or None
        The stereo pair's baseline (None without a stereo pair: the working distance sets the scale).
    calibration_rms_px : float or None
    board_corners : int or None
        Corners of the calibration board (None: unknown).
    dark_noise : (N,) float or None
        The dark frame's noise in each image's units (it was subtracted from every image: a noise
        common to all of a pixel's samples), None without a dark frame.
    own_noise : (N,) float or None
        Each image's own noise in its units, measured on the raw (distorted) image: white, as the
        sensor gives it. The undistorted images are interpolated, which lowers their per-pixel noise
        but not the low frequencies the integration accumulates. None: measured on ``images``.
    """

    images: np.ndarray
    valid: np.ndarray | None
    lights: Lights
    field: NormalField
    points_mm: np.ndarray
    mask: np.ndarray
    K: np.ndarray
    fusion: fusion_mod.Fusion | None
    baseline_mm: float | None
    calibration_rms_px: float | None
    board_corners: int | None
    dark_noise: np.ndarray | None = None
    own_noise: np.ndarray | None = None


@dataclass(frozen=True)
class PointUncertainty:
    """What :func:`propagate` finds before the radius is known: the per-point map and what the
    radius's uncertainty needs of the view (:func:`with_radius` completes it).

    Attributes
    ----------
    map_mm, deviation_mm
        As :class:`Uncertainty`'s.
    components : dict
        The radius-free components (``photometric_mm``, ``correction_mm``, ``scale_rel``,
        ``registration_mm``, ``integration_scale_px``, and ``lobe_mm`` where a lobe's parameters
        were propagated).
    u_scale, u_reg : float
        The scale's relative and the registration's standard uncertainties (mm).
    z_typ_mm, f_px, extent_px : float
        The view's median depth, focal length and extent of its measured points (px).
    bend_cov : (3, 3) array or None
        The stereo correction's covariance of the bend (:class:`pipeline.surface.fusion.Fusion`).
    """

    map_mm: np.ndarray
    deviation_mm: float
    components: dict[str, float]
    u_scale: float
    u_reg: float
    z_typ_mm: float
    f_px: float
    extent_px: float
    bend_cov: np.ndarray | None


def propagate(
    x: Inputs, *, radius_mm: float | None, curved_direction: np.ndarray | None
) -> Uncertainty:
    """The inspection's expanded uncertainties (see the module docstring).

    Parameters
    ----------
    x : Inputs
    radius_mm : float or None
        The fitted radius, mm (None: no radius to qualify).
    curved_direction : (3,) float or None
        Unit direction (camera frame) of the plate's stronger curvature (the radius's).

    Returns
    -------
    Uncertainty
        :func:`with_radius` of :func:`propagate_points`.
    """
    return with_radius(propagate_points(x), radius_mm=radius_mm, curved_direction=curved_direction)


def propagate_points(x: Inputs) -> PointUncertainty:
    """The part of :func:`propagate` that needs no radius: every point's uncertainty."""
    mask = x.mask & np.isfinite(x.points_mm[..., 2])
    if not mask.any():
        raise ValueError("mask: expected measured points to qualify, got none")
    # every component on the grid of sampled pixels (the fields are smooth on its scale); the map
    # is interpolated to every pixel at the end
    step = _sample_step(mask)
    grid = mask[::step, ::step]
    z_typ = float(np.median(x.points_mm[::step, ::step, 2][grid]))
    f_px = float(np.sqrt(x.K[0, 0] * x.K[1, 1]))
    extent_px = _extent_px(mask)
    scale_px = _integration_scale_px(x.fusion, extent_px)
    var_ps = _photometric_var_mm2(x, mask, scale_px, step)
    u_corr = np.zeros(grid.shape)
    if (
        x.fusion is not None
    ):  # the chosen correction's noise, and what the next finer one would change
        for part in (x.fusion.correction_sd_mm, x.fusion.model_sd_mm):
            if part is not None:
                u_corr = np.hypot(u_corr, np.nan_to_num(part[::step, ::step].astype(np.float64)))
    u_scale = _scale_rel(x, z_typ, f_px)
    height = _height_over_plane_mm(x.points_mm, mask, step) if u_scale > 0 else 0.0
    u_reg = _registration_sd_mm(var_ps, u_corr, grid, step)
    var = var_ps + u_corr**2 + (u_scale * height) ** 2 + u_reg**2
    var_lobe = _lobe_var_mm2(x, mask)
    lobe_part = {}
    if var_lobe is not None:  # a lobe measured once for the plate: its parameters' uncertainty
        var_lobe = cv2.resize(var_lobe.astype(np.float32), (var.shape[1], var.shape[0]))
        var = var + var_lobe
        lobe_part = {"lobe_mm": round(float(np.sqrt(np.percentile(var_lobe[grid], 95))), 4)}
    h, w = mask.shape
    full = cv2.resize(var.astype(np.float32), (var.shape[1] * step, var.shape[0] * step))[:h, :w]
    u_map = np.where(mask, np.sqrt(np.maximum(full, 0.0)), np.nan).astype(np.float32)
    u95 = COVERAGE_K * float(percentile(u_map[mask], 95))  # the published map's own figure
    return PointUncertainty(
        map_mm=COVERAGE_K * u_map,
        deviation_mm=u95,
        components={
            "photometric_mm": round(float(np.sqrt(np.percentile(var_ps[grid], 95))), 4),
            "correction_mm": round(float(np.percentile(u_corr[grid], 95)), 4),
            "scale_rel": float(f"{u_scale:.3g}"),
            "registration_mm": round(u_reg, 5),
            "integration_scale_px": round(scale_px, 1),
            **lobe_part,
        },
        u_scale=u_scale,
        u_reg=u_reg,
        z_typ_mm=z_typ,
        f_px=f_px,
        extent_px=extent_px,
        bend_cov=None if x.fusion is None else x.fusion.bend_cov,
    )


def restricted(p: PointUncertainty, judged: np.ndarray) -> PointUncertainty:
    """``p`` on the judged pixels ``judged`` (a subset of the mask it was propagated on): the map NaN
    elsewhere and the deviation's figure its 95th percentile there, as :func:`propagate_points` makes it."""
    map_mm = np.where(judged, p.map_mm, np.float32(np.nan)).astype(np.float32)
    values = map_mm[judged]
    values = values[np.isfinite(values)]
    if values.size == 0:
        raise ValueError("judged: expected judged points with an uncertainty, got none")
    return replace(p, map_mm=map_mm, deviation_mm=float(percentile(values, 95)))


def with_radius(
    p: PointUncertainty, *, radius_mm: float | None, curved_direction: np.ndarray | None
) -> Uncertainty:
    """The uncertainties of :func:`propagate` from its radius-free part (see there)."""
    radius_u, bend_rel, fit_rel = None, 0.0, 0.0
    if radius_mm is not None and math.isfinite(radius_mm):
        bend_rel = _bend_rel(p.bend_cov, radius_mm, p.z_typ_mm, p.f_px, curved_direction)
        sagitta = _sagitta_mm(radius_mm, p.extent_px * p.z_typ_mm / p.f_px)
        fit_rel = p.u_reg / sagitta if sagitta > 0 else 0.0
        radius_u = COVERAGE_K * radius_mm * math.sqrt(bend_rel**2 + p.u_scale**2 + fit_rel**2)
    c = p.components
    return Uncertainty(
        map_mm=p.map_mm,
        deviation_mm=p.deviation_mm,
        radius_mm=radius_u,
        components={
            "photometric_mm": c["photometric_mm"],
            "correction_mm": c["correction_mm"],
            "scale_rel": c["scale_rel"],
            "bend_rel": float(f"{bend_rel:.3g}"),
            "fit_rel": float(f"{fit_rel:.3g}"),
            "registration_mm": c["registration_mm"],
            "integration_scale_px": c["integration_scale_px"],
            **({"lobe_mm": c["lobe_mm"]} if "lobe_mm" in c else {}),
        },
    )


def _registration_sd_mm(
    var_ps: np.ndarray, u_corr: np.ndarray, grid: np.ndarray, step: int
) -> float:
    """Standard uncertainty (mm) the best-fit registration adds at a point: the points' own noise over
    the independent patches it is fitted to (:data:`REGISTRATION_PATCH_PX` wide). ``var_ps``,
    ``u_corr`` and ``grid`` on the grid of every ``step``-th pixel.

    Only the measurement's noise enters: the fit's residual also holds the plate's real deviation
    from its target (a dent, an under-bent plate), which is what is measured, not noise.
    """
    typical = float(np.sqrt(np.median((var_ps + u_corr**2)[grid])))
    patches = max(float(np.count_nonzero(grid)) * step**2 / REGISTRATION_PATCH_PX**2, 1.0)
    return typical / math.sqrt(patches)


def _extent_px(mask: np.ndarray) -> float:
    """The larger side (px) of the bounding box of a mask with at least one pixel."""
    box = bounding_box(mask)
    assert box is not None  # propagate_points refuses an empty mask
    rows, cols = box
    return float(max(rows.stop - rows.start, cols.stop - cols.start))


def _integration_scale_px(fused: fusion_mod.Fusion | None, extent_px: float) -> float:
    """The width (px) up to which the normals alone make the shape: the correction's knot spacing, or
    the plate's extent when the stereo pair sets only scale, tilt and bend (or there is none)."""
    if fused is not None and fused.knot_spacing_px is not None:
        return float(min(fused.knot_spacing_px, extent_px))
    return extent_px


def _sample_step(mask: np.ndarray) -> int:
    """The grid step (px) that leaves about PHOTOMETRIC_SAMPLES of the mask's pixels."""
    return max(1, int(math.sqrt(np.count_nonzero(mask) / PHOTOMETRIC_SAMPLES)))


def _photometric_var_mm2(x: Inputs, mask: np.ndarray, scale_px: float, step: int) -> np.ndarray:
    """Variance (mm^2) of the integrated depth from the normals' noise, on the grid of every ``step``-th
    pixel (shape of ``mask[::step, ::step]``).

    The normal's tangential standard deviation from its fit (image noise, and the fit's residual where
    it has degrees of freedom left), times the pixel's footprint (mm per pixel step), smoothed over its
    neighbourhood (the integration averages the slopes around a point) and scaled by the
    integration's gain over ``scale_px``.
    """
    h, w = mask.shape
    rows, cols = np.nonzero(mask[::step, ::step] & x.field.mask[::step, ::step])
    rows, cols = rows * step, cols * step
    images = x.images[:, rows, cols].astype(np.float64)  # (N, P)
    valid = np.ones_like(images, bool) if x.valid is None else x.valid[:, rows, cols]
    n = x.field.normals[rows, cols].astype(np.float64)  # (P, 3)
    rho = x.field.albedo[rows, cols].astype(np.float64)
    pts = x.points_mm[rows, cols]
    dirs = x.lights.directions_at(pts)  # (N, P, 3)
    att = x.lights.attenuation_at(pts)  # (N, P)
    g = att[..., None] * dirs  # irradiance vectors per unit intensity
    shade = np.einsum("npc,pc->np", g, n)
    lit = valid & (shade > 0) & np.isfinite(images)
    pred = rho[None] * shade
    res = np.where(lit, images - pred, 0.0)
    res, lobe_params = _without_lobe(res, lit, x.field.specular, dirs, att, n, pts)
    m = lit.sum(axis=0)
    dark = np.zeros(len(images)) if x.dark_noise is None else np.asarray(x.dark_noise)
    if x.own_noise is not None:
        own = np.asarray(x.own_noise, dtype=np.float64)
    else:  # the undistorted images' noise holds the dark frame's too
        own = np.sqrt(np.maximum(image_noise(x.images, mask) ** 2 - dark**2, 0.0))
    # the fit's residual where the pixel has more lights than unknowns, pooled with the images' own
    # noise as a prior of 3 degrees of freedom; never below that noise (the residual of interpolated
    # images understates the white noise the integration accumulates)
    prior_dof = 3.0
    s0 = (own[:, None] * lit).sum(axis=0) / np.maximum(m, 1)
    pooled = (np.sum(res**2, axis=0) + prior_dof * s0**2) / (
        np.maximum(m - 3 - lobe_params, 0) + prior_dof
    )
    s2 = np.maximum(pooled, s0**2)
    # per unit albedo; the dark frame's noise is one value shared by the pixel's samples: along
    # gram^-1 G^T d
    tangential, shared = _tangential_parts(g, lit, dark, n)
    var_n = s2 * tangential + shared
    var_n = var_n / np.maximum(rho, 1e-6) ** 2
    var_n = np.where((m >= 3) & np.isfinite(var_n), var_n, np.nan)
    footprint = pts[:, 2] / math.sqrt(x.K[0, 0] * x.K[1, 1])  # mm per pixel step
    var_g = var_n * footprint**2 / np.maximum(-n[:, 2], 0.2) ** 4
    gain = math.log(max(scale_px, 2.0)) / (2.0 * math.pi) + INTEGRATION_OFFSET
    coarse = np.full(((h + step - 1) // step, (w + step - 1) // step), np.nan, np.float32)
    coarse[rows // step, cols // step] = var_g * gain
    return _spread(coarse, radius=max(2, int(round(8 / step)) + 1))


def _without_lobe(
    res: np.ndarray,
    lit: np.ndarray,
    specular: SpecularFit | None,
    dirs: np.ndarray,
    att: np.ndarray,
    n: np.ndarray,
    pts: np.ndarray,
) -> tuple[np.ndarray, int]:
    """The Lambertian residuals ``res`` (N, P) of the pixels' lit samples less the specular lobe the
    normals were fitted with, and the parameters the lobe took of each pixel (0 or 1).

    On a glossy plate the normals come from a fit with the coating's lobe
    (:mod:`pipeline.lights.glare`: ``I_k = a_k (rho n . l_k + s max(0, n . h_k)^e)``, ``h_k`` the half
    vector of the light and the view); left in, the lobe reads as the images' noise (on the simulated
    18-light glare cells the photometric part of U95 came out 7-17 times the deviation's p95, and a
    region 1 mm beyond a 2 mm tolerance was no defect). Here each pixel's lobe of the fitted exponent
    takes its own least-squares amplitude ``s >= 0``: one parameter more of the pixel's degrees of
    freedom. Without a modelled lobe the residuals are returned as they are.
    """
    if specular is None or not specular.modelled or not np.isfinite(specular.exponent):
        return res, 0
    lobe = att * glare.lobe_cosines(dirs, pts, n) ** specular.exponent
    lobe = np.where(lit, lobe, 0.0)
    amplitude = np.maximum(
        np.sum(res * lobe, axis=0) / np.maximum(np.sum(lobe * lobe, axis=0), 1e-30), 0.0
    )
    return res - amplitude[None] * lobe, 1


def _lobe_var_mm2(x: Inputs, mask: np.ndarray) -> np.ndarray | None:
    """Variance (mm^2) of the depth from the uncertainty of a lobe measured once for the plate, on a
    coarse grid (every ``step``-th pixel, about :data:`LOBE_GRID_SAMPLES` of the mask); None where
    no such lobe was fitted (a matte plate; a lobe fitted pixel by pixel).

    The lobe's exponent and amplitude bend every pixel's normal the same way: a smooth shape error no
    pixel's residual shows. Each of the two independent directions of the fit's covariance (``ln e``
    by its standard uncertainty with the amplitude its correlation pulls along; the amplitude's own
    part) moves the lobe both ways; the normals are re-solved with it
    (:func:`pipeline.lights.glare.normals_with_lobe`), the half difference integrated to log depth
    (:func:`_integrate_log_depth`), and what the stereo pair's chosen correction takes out of it
    (:func:`pipeline.surface.fusion.correction_basis`; the plane at least) is removed. The rest, times
    the depth, adds in quadrature over the two directions.
    """
    spec = x.field.specular
    if spec is None or not spec.modelled or spec.log_exponent_sd is None:
        return None
    if spec.amplitude_sd is None or not np.isfinite(spec.exponent):
        return None
    step = max(1, int(math.sqrt(np.count_nonzero(mask) / LOBE_GRID_SAMPLES)))
    sub = mask[::step, ::step] & x.field.mask[::step, ::step]
    depth = np.where(sub, x.points_mm[::step, ::step, 2], np.nan)
    start = x.field.normals[::step, ::step].astype(np.float64)
    kinv = np.linalg.inv(x.K) @ np.diag([float(step), float(step), 1.0])
    images = x.images[:, ::step, ::step]
    valid = None if x.valid is None else x.valid[:, ::step, ::step]
    e, s, u_log_e = float(spec.exponent), float(spec.amplitude_median), spec.log_exponent_sd
    rho = spec.lobe_correlation
    # the covariance's Cholesky factor: the exponent with the amplitude it pulls along, then the
    # amplitude's own part
    cholesky = (
        (u_log_e, rho * spec.amplitude_sd),
        (0.0, spec.amplitude_sd * math.sqrt(max(1.0 - rho**2, 0.0))),
    )
    moves = [m for m in cholesky if all(np.isfinite(m)) and any(m)]
    if not moves:
        return None
    solved = [
        glare.normals_with_lobe(
            images,
            valid,
            x.lights,
            depth,
            start,
            kinv,
            e * math.exp(sign * d_log_e),
            max(s + sign * d_s, 0.0),
        )
        for d_log_e, d_s in moves
        for sign in (1.0, -1.0)
    ]
    converged = sub & np.logical_and.reduce([ok for _, ok in solved])
    # the integration's own slopes of each solution, where every one of them is usable
    slopes = [integration.log_depth_gradients(n, converged, kinv) for n, _ in solved]
    good = converged & np.logical_and.reduce([usable for _, _, usable in slopes])
    du = np.stack([0.5 * (a[0] - b[0]) for a, b in zip(slopes[::2], slopes[1::2], strict=True)])
    dv = np.stack([0.5 * (a[1] - b[1]) for a, b in zip(slopes[::2], slopes[1::2], strict=True)])
    change = _without_correction(_integrate_log_depth(du, dv, good), good, x.fusion, step)
    var = np.sum(change**2, axis=0) * np.nan_to_num(depth) ** 2
    # the grid's last values carried two cells beyond the mask, so that the finer grid's interpolation
    # at the plate's edge does not blend them with the zeros outside
    grown = cv2.dilate(cv2.dilate(var.astype(np.float32), np.ones((3, 3))), np.ones((3, 3)))
    return np.where(sub, var, grown)


def _integrate_log_depth(gu: np.ndarray, gv: np.ndarray, good: np.ndarray) -> np.ndarray:
    """The least-squares ``ln z`` (k, h, w) of ``k`` slope fields ``gu``, ``gv`` (k, h, w; per grid
    step) on the pixels ``good`` (0 elsewhere; mean 0): the equations of the pipeline's integration
    (:func:`pipeline.surface.integration.integrate_normals`, neighbours both good, their slopes
    averaged) without its stereo prior, on a coarse grid; one factorisation for all ``k``."""
    out = np.zeros(gu.shape)
    n = int(np.count_nonzero(good))
    if n < 3:
        return out
    idx = np.full(good.shape, -1, np.int64)
    idx[good] = np.arange(n)
    pairs: list[np.ndarray] = []
    rhs: list[np.ndarray] = []
    for a, b, g in (
        (idx[:, :-1], idx[:, 1:], 0.5 * (gu[:, :, :-1] + gu[:, :, 1:])),
        (idx[:-1, :], idx[1:, :], 0.5 * (gv[:, :-1, :] + gv[:, 1:, :])),
    ):
        both = (a >= 0) & (b >= 0) & np.all(np.isfinite(g), axis=0)
        pairs.append(np.stack([a[both], b[both]], axis=1))
        rhs.append(g[:, both])
    pair, values = np.concatenate(pairs), np.concatenate(rhs, axis=1)
    m = len(pair)
    A = sparse.csr_matrix(
        (np.tile([-1.0, 1.0], m), (np.repeat(np.arange(m), 2), pair.ravel())), shape=(m, n)
    )
    # the normal equations, with a vanishing pull towards 0 that fixes the free offset
    solve = factorized((A.T @ A + 1e-9 * sparse.identity(n)).tocsc())
    for k in range(len(gu)):
        sol = solve(A.T @ values[k])
        out[k][good] = sol - sol.mean()
    return out


def _without_correction(
    change: np.ndarray, good: np.ndarray, fused: fusion_mod.Fusion | None, step: int
) -> np.ndarray:
    """``change`` (k, h, w: log depth on the grid of every ``step``-th pixel) less its least-squares
    part in the span of the stereo correction the fusion chose (the plane without a stereo pair: its
    scale is the working distance's, its tilt the registration's); 0 off ``good``."""
    rows, cols = np.nonzero(good)
    out = np.zeros(change.shape)
    if rows.size < 10:
        return out
    r0, c0 = rows.min(), cols.min()
    shape = ((rows.max() - r0 + 1) * step, (cols.max() - c0 + 1) * step)
    model, spacing = ("plane", None) if fused is None else (fused.model, fused.knot_spacing_px)
    basis = sparse.csr_matrix(
        fusion_mod.correction_basis(model, spacing, (rows - r0) * step, (cols - c0) * step, shape)
    )
    # the least-squares coefficients (a vanishing ridge bridges knot cells without a grid point)
    gram = (basis.T @ basis).tocsc()
    ridge = 1e-9 * float(gram.diagonal().mean()) * sparse.identity(gram.shape[0], format="csc")
    solve = factorized(gram + ridge)
    for k in range(len(change)):
        y = change[k][rows, cols]
        out[k][rows, cols] = y - basis @ solve(basis.T @ y)
    return out


def _tangential_parts(
    g: np.ndarray, lit: np.ndarray, dark: np.ndarray, n: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Per pixel, from one inverse of its samples' Gram matrix ``gram = sum lit g g^T`` (``g`` (N, P, 3)
    the irradiance vectors, ``lit`` (N, P) the samples used): the mean variance of the two tangential
    components of ``gram^-1`` (the normal's covariance per unit image variance and albedo), and the
    mean squared tangential component of ``gram^-1 common``, ``common = sum lit dark g`` (a noise
    shared by all the pixel's samples, ``dark`` (N,)); inf where the lights leave the normal
    undetermined (``|det gram| <= 1e-12``). ``n`` (P, 3): the unit normals."""
    independent = np.empty(len(n))
    shared = np.empty(len(n))
    _tangential_kernel(
        np.ascontiguousarray(g, dtype=np.float64),
        np.ascontiguousarray(lit),
        np.ascontiguousarray(dark, dtype=np.float64),
        np.ascontiguousarray(n, dtype=np.float64),
        independent,
        shared,
    )
    return independent, shared


@numba.njit(nogil=True, cache=True)
def _tangential_kernel(
    g: Arr, lit: Arr, dark: Arr, n: Arr, independent: Arr, shared: Arr
) -> None:  # pragma: no cover - compiled
    """:func:`_tangential_parts` pixel by pixel (the 3x3 inverse by its adjugate); single-threaded (a
    worker beside the registration)."""
    m = lit.shape[0]
    gram = np.empty((3, 3))
    common = np.empty(3)
    inv = np.empty((3, 3))
    proj = np.empty((3, 3))
    for p in range(n.shape[0]):
        gram[:, :] = 0.0
        common[:] = 0.0
        for k in range(m):
            if lit[k, p]:
                for c in range(3):
                    common[c] += g[k, p, c] * dark[k]
                    for d in range(3):
                        gram[c, d] += g[k, p, c] * g[k, p, d]
        det = (
            gram[0, 0] * (gram[1, 1] * gram[2, 2] - gram[1, 2] * gram[2, 1])
            - gram[0, 1] * (gram[1, 0] * gram[2, 2] - gram[1, 2] * gram[2, 0])
            + gram[0, 2] * (gram[1, 0] * gram[2, 1] - gram[1, 1] * gram[2, 0])
        )
        if not abs(det) > 1e-12:
            independent[p] = np.inf
            shared[p] = np.inf
            continue
        for r in range(3):  # the adjugate's transpose over the determinant
            r1, r2 = (r + 1) % 3, (r + 2) % 3
            for c in range(3):
                c1, c2 = (c + 1) % 3, (c + 2) % 3
                inv[c, r] = (gram[r1, c1] * gram[r2, c2] - gram[r1, c2] * gram[r2, c1]) / det
        for r in range(3):
            for c in range(3):
                proj[r, c] = (1.0 if r == c else 0.0) - n[p, r] * n[p, c]
        trace = 0.0
        for i in range(3):
            for j in range(3):
                pi_j = 0.0
                for k in range(3):
                    pi_j += proj[i, k] * inv[k, j]
                trace += pi_j * proj[j, i]
        independent[p] = 0.5 * trace
        norm2 = 0.0
        for i in range(3):
            t = 0.0
            for j in range(3):
                pi_j = 0.0
                for k in range(3):
                    pi_j += proj[i, k] * inv[k, j]
                t += pi_j * common[j]
            norm2 += t * t
        shared[p] = 0.5 * norm2


def _spread(coarse_var: np.ndarray, radius: int) -> np.ndarray:
    """Sampled variances averaged over a neighbourhood of ``radius`` samples (NaN: no sample; where
    none is near, the median)."""
    have = np.isfinite(coarse_var)
    num = cv2.blur(np.where(have, coarse_var, 0.0).astype(np.float32), (radius, radius))
    den = cv2.blur(have.astype(np.float32), (radius, radius))
    fallback = float(np.nanmedian(coarse_var)) if have.any() else 0.0
    var: np.ndarray = np.where(den > 0, num / np.maximum(den, 1e-12), fallback).astype(np.float64)
    return var


def _scale_rel(x: Inputs, z_typ: float, f_px: float) -> float:
    """Relative standard uncertainty of the stereo pair's scale (0 without a stereo pair: the working
    distance is then a stated value, its own uncertainty the user's)."""
    if x.baseline_mm is None or x.fusion is None:
        return 0.0
    disparity = f_px * x.baseline_mm / z_typ
    u_d2 = (DISPARITY_QUANTUM_PX / math.sqrt(12.0)) ** 2
    if x.calibration_rms_px is not None:
        corners = max(x.board_corners or 1, 1)
        u_d2 += x.calibration_rms_px**2 / corners
    return math.sqrt(u_d2) / disparity


def _height_over_plane_mm(points: np.ndarray, mask: np.ndarray, step: int) -> np.ndarray:
    """Distance (mm) of the points of every ``step``-th pixel from the surface's best plane (shape of
    ``mask[::step, ::step]``, 0 off the mask)."""
    grid = mask[::step, ::step]
    sampled = points[::step, ::step]
    p = sampled[grid]
    centre = p.mean(axis=0)
    normal = np.linalg.svd(p - centre, full_matrices=False)[2][-1]
    height = np.abs(np.nan_to_num((sampled - centre) @ normal))
    out: np.ndarray = np.where(grid, height, 0.0)
    return out


def _sagitta_mm(radius_mm: float, chord_mm: float) -> float:
    half = min(chord_mm / 2.0, radius_mm)
    return radius_mm - math.sqrt(max(radius_mm**2 - half**2, 0.0))


def _bend_rel(
    bend_cov: np.ndarray | None,
    radius_mm: float,
    z_typ: float,
    f_px: float,
    direction: np.ndarray | None,
) -> float:
    """Relative standard uncertainty of the radius from the stereo pair's hold on the bend
    (``bend_cov``: the correction's covariance of it, None without one)."""
    if bend_cov is None:
        return 0.0
    a, b = 1.0, 0.0
    if direction is not None and np.all(np.isfinite(direction)):
        d = np.asarray(direction, dtype=np.float64)[:2]
        if np.linalg.norm(d) > 1e-9:
            a, b = d / np.linalg.norm(d)
    w = np.array([a * a, 2.0 * a * b, b * b])
    sd = math.sqrt(max(float(w @ bend_cov @ w), 0.0))  # log depth per px^2
    kappa_sd = f_px**2 / z_typ * sd  # 1/mm
    return radius_mm * kappa_sd
