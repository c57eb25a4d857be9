"""Lights refined against the stereo geometry: what the images say the lights are, on the measured plate.

A capture's light list can be wrong in ways that bend the photometric surface: a light bumped by a
crane (its direction off by a degree), or LEDs 3 m away given only as their nominal direction from
the plate's centre. The stereo pair measures the plate's shape independently; on a smooth surface
through it (:func:`pipeline.surface.fusion.smooth_stereo_depth`) every sample block has a known point X and
normal n, and its images must be ``I_k = rho * E_k(X, n)`` with one unknown albedo rho per block.
Two models of the lights are fitted to block samples with the albedo eliminated in closed form:

- **distant**: ``E_k = max(0, n . g_k)`` with ``g_k = e_k d_k``, by alternating least squares (rho
  given g is a ratio, g given rho a 3x3 system per light). Where the plate's normals span too little
  to fix a component of ``g_k`` (a cylinder bends one way only), a weak pull towards the given light
  keeps it (Tikhonov);
- **point**: position, LED axis and profile, intensity per light, the joint fit of
  :mod:`pipeline.lights.fit` started on the given directions from the plate's centre; a light given
  by its direction stays on it (only its distance along it is fitted).

On a glossy plate (a lobe under the point lights that passes :mod:`pipeline.lights.glare`'s test),
the point lights are fitted jointly with the coating's lobe, and the rays' common origin with them
(:func:`_fit_points_with_lobe`); likewise the distant lights with a lobe under them
(:func:`_fit_distant_with_lobe`), unless the Lambertian point lights already explain the samples
far better (then the distant model's misfit reads as a lobe); a caller whose plate measured with the
point lights came out no better asks for the distant model alone (``point_model=False``:
:func:`pipeline.surface.reconstruct.remeasure_with_refined_lights`).

The point model is taken when it explains the samples clearly better than any distant model
(nominal directions of what really are near-field LEDs); else the refined distant lights.

References
----------
.. [1] Y. Queau et al., "LED-based photometric stereo: modeling, calibration and numerical solution",
   J. Math. Imaging Vis. 60, 2018 (calibration of near-field lights on a known surface).
.. [2] G. H. Golub, V. Pereyra, "The differentiation of pseudo-inverses and nonlinear least squares
   problems whose variables separate", SIAM J. Numer. Anal. 10(2), 1973.
"""

from __future__ import annotations

import contextlib
import functools
from dataclasses import dataclass

import cv2
import numpy as np
from scipy import special

from pipeline.lights import fit as light_fit
from pipeline.lights import glare
from pipeline.lights.model import Lights
from pipeline.parallel import single_threaded_blas

#: At most this many sample blocks enter the fits.
MAX_SAMPLES = 3000
#: The point model is taken when its residual is below this fraction of the refined distant one's.
POINT_MODEL_GAIN = 0.7
#: Alternating least-squares rounds of the distant model.
DISTANT_ROUNDS = 30
#: Pull of a distant light towards the given one, relative to the data's mean eigenvalue.
DISTANT_PRIOR = 1e-2
#: Free parameters per light of the distant model (direction times intensity), of the point model
#: (position, axis, profile, intensity) and of a point light on its given direction (distance, axis,
#: profile, intensity).
DISTANT_PARAMS, POINT_PARAMS, ON_RAY_PARAMS = 3, 7, 5
#: Parameters of the coating's lobe fitted with the point lights (amplitude and exponent).
LOBE_PARAMS = 2
#: Side (px) of the sample blocks of the lights' fit with the lobe (the smallest; see refine_lights).
GLOSSY_BLOCK_PX = 2
#: Significance level of the F-test that lets refined lights replace the given ones.
SIGNIFICANCE = 1e-3


def _significant(rms_given: float, rms_model: float, n_params: int, n_blocks: int) -> bool:
    """Whether a refitted light model explains the samples better than the given lights beyond chance.

    An F-test of the drop of the residual variance for the model's ``n_params`` parameters, with one
    degree of freedom per sample block (a block's residuals under the N lights share its albedo and
    the smooth surface's normal error, so they are counted as one observation, not N).
    """
    dof = n_blocks - n_params
    if not (rms_model > 0 and dof > 0 and np.isfinite(rms_model)):
        return False
    f = ((rms_given**2 - rms_model**2) / n_params) / (rms_model**2 / dof)
    # the F distribution's quantile through the regularised incomplete beta function
    x = float(special.betaincinv(n_params / 2.0, dof / 2.0, 1.0 - SIGNIFICANCE))
    return bool(f > dof / n_params * x / (1.0 - x))


@dataclass(frozen=True)
class LightRefinement:
    """Lights fitted to a capture on the stereo geometry.

    Attributes
    ----------
    lights : Lights
        The refined lights (left-camera frame, mm): point lights when ``model == "point"``, else
        distant ones. Intensities on the scale of the given lights (the same mean irradiance at the
        plate's centre).
    model : {"distant", "point"}
    rms_given, rms_distant, rms_point : float
        RMS residual of the samples under the given lights, the refined distant ones and the fitted
        point lights, as a fraction of the mean sample (``rms_point`` NaN if the fit failed).
    corrections : list of dict
        Per light: ``turn_deg`` (angle between the given and the refined direction, seen from the
        plate's centre), ``intensity_ratio`` (refined / given irradiance at the centre) and, for the
        point model, ``position_mm``.
    n_samples : int
        Sample blocks used.
    lobe : Lobe or None
        The coating's lobe fitted with the lights (per unit irradiance, on the scale of the
        fitted lights), None for a matte plate.
    """

    lights: Lights
    model: str
    rms_given: float
    rms_distant: float
    rms_point: float
    corrections: list[dict[str, float | list[float]]]
    n_samples: int
    lobe: glare.Lobe | None = None


def _plate_pose(data: light_fit.Samples) -> light_fit.PlatePose:
    """The plate's pose the point lights are fitted against: its mean normal, and its centre on its
    surface, the sample nearest the samples' centroid across the view (the centroid itself lies off a
    bent plate, behind its middle)."""
    mean = data.points.mean(axis=0)
    across = data.points[:, :2] / data.points[:, 2:] - mean[:2] / mean[2]
    centre = data.points[int(np.argmin(np.einsum("pc,pc->p", across, across)))]
    normal = data.normals.mean(axis=0)
    normal /= np.linalg.norm(normal)
    return light_fit.PlatePose(normal, centre, 0.0, 0)


def _distant_with_lobe(
    data: light_fit.Samples,
    glossy: _GlossySamples,
    distant: Lights,
    rms_distant: float,
    *,
    near: bool,
) -> tuple[Lights, float, glare.Lobe | None]:
    """The distant lights refitted with the coating's lobe where it shows, with their residual and lobe.

    A glossy coating under distant lights: refitted as if Lambertian, the glare turned them 15-21 deg
    off on the glossy 18-light cell written 1 deg off; so the lobe is tested under them and fitted
    with them. Not where the Lambertian point lights already explain the samples far better
    (``near``): there the distant model's misfit (light falling off across the plate) reads as a
    lobe (F 25 on the matte 12-LED nominal cell, 0.9 under its point lights).
    """
    tested = None if near else glossy.lobe_under(distant)
    if tested is not None:
        fitted = _fit_distant_with_lobe(tested[0], distant, tested[1])
        if fitted is not None:
            distant, lobe = fitted
            return distant, _rms(data, distant, lobe), lobe
    return distant, rms_distant, None


def _points_with_lobe(
    data: light_fit.Samples,
    glossy: _GlossySamples,
    point: Lights,
    rms_point: float,
    pose: light_fit.PlatePose,
    rays: np.ndarray,
) -> tuple[Lights, float, glare.Lobe | None]:
    """The point lights refitted with the coating's lobe where it shows, with their residual (on the
    blocks the other models are scored on) and lobe: the lobe is tested under the fitted lights on
    pixels of the smooth surface, as for given point lights (a matte plate stops at the pretest, F
    about 1)."""
    tested = glossy.lobe_under(point)
    if tested is not None:
        fine, measured = tested
        fitted = _fit_points_with_lobe(fine, point, pose, rays, measured)
        if fitted is not None:
            point, _, lobe = fitted
            return point, _rms(data, point, lobe), lobe
    return point, rms_point, None


def refine_lights(
    images: np.ndarray,
    valid: np.ndarray | None,
    mask: np.ndarray,
    lights: Lights,
    depth_mm: np.ndarray,
    K: np.ndarray,
    *,
    max_samples: int = MAX_SAMPLES,
    seed: int = 0,
    point_model: bool = True,
) -> LightRefinement | None:
    """Fit the lights to the images on a known smooth surface.

    Parameters
    ----------
    images : (N, H, W) float32
        Preprocessed images (dark-subtracted, undistorted, divided by each given light's intensity).
    valid : (N, H, W) bool or None
        Usable samples.
    mask : (H, W) bool
        Plate pixels.
    lights : Lights
        The lights the capture gives, in image order.
    depth_mm : (H, W) float
        A smooth surface through the stereo depth (mm along the optical axis), finite on ``mask``.
    K : (3, 3) float
        Intrinsics of the undistorted left grid, pixels.
    max_samples : int
        Sample blocks at most.
    seed : int
        Seeds the choice of blocks.
    point_model : bool
        Whether point lights are fitted too (False: the distant model only, with the coating's lobe where
        it shows whatever point lights would explain).

    Returns
    -------
    LightRefinement or None
        None when fewer than 50 blocks of the plate are lit by every light (nothing to fit), or when
        neither refitted model explains the samples significantly better than the given lights
        (:func:`_significant`): the given lights then stand.
    """
    data = _samples(images, valid, mask, lights, depth_mm, K, max_samples=max_samples, seed=seed)
    if data is None:
        return None
    pose = _plate_pose(data)
    centre = pose.centre_mm
    with single_threaded_blas():
        rms_given = _rms(data, lights)
        glossy = _GlossySamples(images, valid, mask, lights, depth_mm, K, max_samples, seed)
        distant = _refine_distant(data, lights)
        rms_distant = _rms(data, distant)
        point, rms_point = _fit_points(data, lights, pose) if point_model else (None, np.nan)
        near = point is not None and rms_point < POINT_MODEL_GAIN * rms_distant
        distant, rms_distant, distant_lobe = _distant_with_lobe(
            data, glossy, distant, rms_distant, near=near
        )
        lobe = None
        if point is not None:
            point, rms_point, lobe = _points_with_lobe(
                data, glossy, point, rms_point, pose, _rays(lights, pose)
            )
    chosen: Lights
    n_blocks = len(data.intensity)
    # the glossy fit ends free in 3-D: 7 parameters a light, and the lobe's 2
    point_params = _point_params(lights) if lobe is None else POINT_PARAMS * lights.n + LOBE_PARAMS
    distant_params = DISTANT_PARAMS * lights.n + (0 if distant_lobe is None else LOBE_PARAMS)
    if (
        point is not None
        and rms_point < POINT_MODEL_GAIN * rms_distant
        and _significant(rms_given, rms_point, point_params, n_blocks)
    ):
        model, chosen = "point", point
    elif _significant(rms_given, rms_distant, distant_params, n_blocks):
        model, chosen, lobe = "distant", distant, distant_lobe
    else:
        return None  # the images do not prove other lights: the given ones stand
    # the given scale: the same mean irradiance at the plate's centre, facing the light
    given_at_c = lights.intensity * lights.attenuation_at(centre)
    chosen_at_c = chosen.intensity * chosen.attenuation_at(centre)
    scale = float(np.mean(given_at_c) / np.mean(chosen_at_c))
    chosen = chosen.with_intensity(chosen.intensity * scale)
    if lobe is not None:  # per unit irradiance of the rescaled lights
        lobe = glare.Lobe(lobe.exponent, lobe.amplitude / scale, lobe.f_ratio)
    chosen_at_c = chosen.intensity * chosen.attenuation_at(centre)
    before, after = lights.directions_at(centre), chosen.directions_at(centre)
    corrections = []
    for k in range(lights.n):
        item: dict[str, float | list[float]] = {
            "light": k,
            "turn_deg": round(
                float(np.degrees(np.arccos(np.clip(before[k] @ after[k], -1.0, 1.0)))), 3
            ),
            "intensity_ratio": round(float(chosen_at_c[k] / given_at_c[k]), 4),
        }
        if model == "point":
            item["position_mm"] = [round(float(v), 1) for v in chosen.positions_mm[k]]
        corrections.append(item)
    return LightRefinement(
        lights=chosen,
        model=model,
        rms_given=rms_given,
        rms_distant=rms_distant,
        rms_point=rms_point,
        corrections=corrections,
        n_samples=len(data.intensity),
        lobe=lobe,
    )


@dataclass
class _GlossySamples:
    """The lobe's pretest under refitted lights and the samples of the fits with it, shared by the
    distant and the point model: the fine blocks are made once, when a first pretest finds a lobe."""

    images: np.ndarray
    valid: np.ndarray | None
    mask: np.ndarray
    lights: Lights
    depth_mm: np.ndarray
    K: np.ndarray
    max_samples: int
    seed: int

    @functools.cached_property
    def fine(self) -> light_fit.Samples | None:
        """The samples from the smallest blocks: fitted on the default blocks (13 px at 1224 x 1024)
        the ring of LEDs came out 27-39 mm too high, on 2 px ones 3-9 mm."""
        return _samples(
            self.images,
            self.valid,
            self.mask,
            self.lights,
            self.depth_mm,
            self.K,
            max_samples=self.max_samples,
            seed=self.seed,
            block_px=GLOSSY_BLOCK_PX,
        )

    def lobe_under(self, fitted: Lights) -> tuple[light_fit.Samples, glare.Lobe] | None:
        """The fine samples and the lobe measured under ``fitted`` on pixels of the smooth surface (a
        matte plate stops at the pretest, F about 1); None without a significant lobe."""
        measured = glare.measure_lobe(
            self.images,
            self.valid,
            fitted,
            self.depth_mm,
            None,
            self.mask,
            self.K,
            start_mm=self.depth_mm,
            gain=self.lights.intensity / fitted.intensity,
            refine=False,
        )
        if not (measured.f_ratio >= glare.MIN_F and measured.amplitude > 0):
            return None
        return None if self.fine is None else (self.fine, measured)


def _samples(
    images: np.ndarray,
    valid: np.ndarray | None,
    mask: np.ndarray,
    lights: Lights,
    depth_mm: np.ndarray,
    K: np.ndarray,
    *,
    max_samples: int,
    seed: int,
    block_px: int | None = None,
) -> light_fit.Samples | None:
    """Block means of the images in counts (P, N), with the smooth surface's points and normals.

    Blocks of ``block_px`` pixels a side (default: as large as ``max_samples`` blocks cover the
    plate), at most ``max_samples`` of them chosen at random."""
    n, h, w = images.shape
    usable = mask & np.isfinite(depth_mm)
    if valid is not None:
        usable = usable & valid.all(axis=0)
    count = int(np.count_nonzero(usable))
    if count == 0:
        return None
    block = max(2, int(np.sqrt(count / max_samples))) if block_px is None else block_px
    hb, wb = h // block, w // block

    def blocks(img: np.ndarray) -> np.ndarray:
        return cv2.resize(
            np.ascontiguousarray(img[: hb * block, : wb * block]),
            (wb, hb),
            interpolation=cv2.INTER_AREA,
        )

    full = blocks(usable.astype(np.float32)) >= 1.0 - 1e-6
    ii, jj = np.nonzero(full)
    if len(ii) < 50:
        return None
    if len(ii) > max_samples:
        pick = np.sort(np.random.default_rng(seed).choice(len(ii), max_samples, replace=False))
        ii, jj = ii[pick], jj[pick]
    intensity = np.empty((len(ii), n))
    for k in range(n):
        intensity[:, k] = blocks(images[k])[ii, jj] * lights.intensity[k]
    # the block's centre and the smooth surface's point and normal there
    u = jj * block + (block - 1) / 2.0
    v = ii * block + (block - 1) / 2.0
    z = blocks(np.where(usable, depth_mm, 0.0).astype(np.float64))[ii, jj]
    kinv = np.linalg.inv(K)

    def point(du: float, dv: float) -> np.ndarray:
        pix = np.stack([u + du, v + dv, np.ones_like(u)], axis=1)
        ui = np.clip(np.rint(u + du).astype(int), 0, w - 1)
        vi = np.clip(np.rint(v + dv).astype(int), 0, h - 1)
        zz = np.where(np.isfinite(depth_mm[vi, ui]), depth_mm[vi, ui], z)
        return (pix @ kinv.T) * zz[:, None]

    step = float(block)
    tu = point(step, 0) - point(-step, 0)
    tv = point(0, step) - point(0, -step)
    normals = np.cross(tv, tu)
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    points = (np.stack([u, v, np.ones_like(u)], axis=1) @ kinv.T) * z[:, None]
    flip = np.einsum("pc,pc->p", normals, points) > 0  # towards the camera
    normals[flip] *= -1.0
    ok = np.all(np.isfinite(normals), axis=1) & np.all(intensity > 0, axis=1)
    return light_fit.Samples(intensity=intensity[ok], points=points[ok], normals=normals[ok])


def _point_params(lights: Lights) -> int:
    """Free parameters of the point model fitted from ``lights``: a given point light moves in 3-D, a
    light given by its direction only along it (:func:`_fit_points`)."""
    n_point = int(np.count_nonzero(lights.is_point))
    return POINT_PARAMS * n_point + ON_RAY_PARAMS * (lights.n - n_point)


def _rms(data: light_fit.Samples, lights: Lights, lobe: glare.Lobe | None = None) -> float:
    """RMS residual of the samples under ``lights`` (and the coating's ``lobe``, per unit irradiance
    of point lights), as a fraction of the mean sample."""
    E = lights.irradiance(data.points, data.normals).T  # (P, N)
    I = data.intensity
    if lobe is not None:
        I = I - lobe.amplitude * light_fit.lobe_of(lights, data.points, data.normals, lobe.exponent)
    _, _, r = light_fit.albedo_projected(I, E)
    return float(np.sqrt(np.mean(r * r)) / np.mean(data.intensity))


def _refine_distant(data: light_fit.Samples, lights: Lights) -> Lights:
    """Distant lights g_k = e_k d_k refitted by alternating least squares (see the module docstring)."""
    I, nrm = data.intensity, data.normals
    centre = data.points.mean(axis=0)
    g0 = lights.directions_at(centre) * (lights.intensity * lights.attenuation_at(centre))[:, None]
    g = g0.copy()
    for _ in range(DISTANT_ROUNDS):
        E = np.maximum(nrm @ g.T, 0.0)  # (P, N)
        rho = np.einsum("pn,pn->p", I, E) / np.maximum(np.einsum("pn,pn->p", E, E), 1e-300)
        for k in range(lights.n):
            lit = E[:, k] > 0
            a = rho[lit, None] * nrm[lit]
            M = a.T @ a
            lam = DISTANT_PRIOR * np.trace(M) / 3.0
            g[k] = np.linalg.solve(M + lam * np.eye(3), a.T @ I[lit, k] + lam * g0[k])
        g *= np.mean(np.linalg.norm(g0, axis=1)) / np.mean(
            np.linalg.norm(g, axis=1)
        )  # the gauge of rho
    e = np.linalg.norm(g, axis=1)
    return Lights.distant(g / e[:, None], e)


def _fit_points(
    data: light_fit.Samples, lights: Lights, pose: light_fit.PlatePose
) -> tuple[Lights | None, float]:
    """Point lights fitted from the given ones (directions: along them from the plate's centre).

    First with the LEDs' beam profile fixed (mu = 1), then free; when the free fit does not converge
    to lights in front of the plate, the fixed-profile fit stands if it did. A light the capture gives
    by its direction stays on the ray from the plate's centre in that direction: the images fit its
    distance, axis, profile and intensity. (Free in 3-D, on plates formed exactly with exact nominal
    directions, the fit turned the lights 4 to 8 degrees off them to fit the smooth stereo surface's
    own error a little better, and the plate's edges read up to 1.3 mm; held on their rays, 0.5 to
    0.8 mm, and still better than free when the directions were written 1 or 3 degrees off.)
    """
    # a light given by its direction keeps it: the images find its distance along it (its axis, beam
    # and intensity too); fitted freely, its direction absorbed the smooth stereo surface's own error
    try:
        start = light_fit.initial_point_lights(lights, pose, data, initial_mu=1.0)
    except (np.linalg.LinAlgError, ValueError, FloatingPointError):
        return None, float("nan")
    return _fit_points_lambertian(data, start, pose, _rays(lights, pose))


def _rays(lights: Lights, pose: light_fit.PlatePose) -> np.ndarray:
    """Each light's given direction from the plate's centre (N, 3); NaN rows for given point lights."""
    return np.where(lights.is_point[:, None], np.nan, lights.directions_at(pose.centre_mm))


def _fit_distant_with_lobe(
    data: light_fit.Samples, start: Lights, lobe: glare.Lobe
) -> tuple[Lights, glare.Lobe] | None:
    """The distant lights fitted jointly with the coating's lobe (:func:`light_fit.joint_fit_distant`),
    from ``start`` (the Lambertian refit) and ``lobe`` (measured under it); None unless it converges
    with a positive lobe of finite exponent."""
    try:
        fit = light_fit.joint_fit_distant(start, data, lobe=(lobe.exponent, lobe.amplitude))
    except (np.linalg.LinAlgError, ValueError, FloatingPointError):
        return None
    if not (fit.success and fit.lobe_amplitude > 0 and np.isfinite(fit.lobe_exponent)):
        return None
    return fit.lights, glare.Lobe(fit.lobe_exponent, fit.lobe_amplitude, lobe.f_ratio)


def _fit_points_with_lobe(
    data: light_fit.Samples,
    start: Lights,
    pose: light_fit.PlatePose,
    rays: np.ndarray,
    lobe: glare.Lobe,
) -> tuple[Lights, float, glare.Lobe] | None:
    """The point lights fitted jointly with the coating's lobe, from ``start`` (the Lambertian fit) and
    ``lobe`` (measured under it): on the given rays with their common origin free, fixed profile
    first, then free; then every light free in 3-D from there (kept if it converges). None if no
    fit on the rays converges to lights in front of the plate with a positive lobe.

    Fitted as if Lambertian, the glare near the mirror directions pulled the LEDs of the glossy
    18-LED cell to half their distance (1.6 m instead of 3.2 m). With the lobe in the model, the
    mirror geometry also fixes where the rays start: their common origin (the plate's centre the
    directions were given from, which the view's middle misses by tens of mm) is fitted too
    (``free_origin``). On a matte plate that origin is not determined (moved 0.5 m for the same
    residual in a trial), which is why only the glossy fit frees it.
    """
    try:
        fixed = light_fit.joint_fit(
            start,
            data,
            fixed_mu=True,
            rays=rays,
            free_origin=True,
            lobe=(lobe.exponent, lobe.amplitude),
        )
    except (np.linalg.LinAlgError, ValueError, FloatingPointError):
        return None
    candidates = [fixed]
    with contextlib.suppress(np.linalg.LinAlgError, ValueError, FloatingPointError):
        candidates.insert(
            0,
            light_fit.joint_fit(
                fixed.lights,
                data,
                rays=rays,
                free_origin=True,
                lobe=(fixed.lobe_exponent, fixed.lobe_amplitude),
            ),
        )
    on_rays = next((f for f in candidates if _usable_glossy(f, pose)), None)
    if on_rays is None:
        return None
    best = on_rays
    # then free in 3-D: the highlights place each light, so its direction, given a degree off, is
    # found too (on a matte plate the free fit turned exact directions 4-8 deg to explain the smooth
    # stereo surface's error instead)
    with contextlib.suppress(np.linalg.LinAlgError, ValueError, FloatingPointError):
        free = light_fit.joint_fit(
            on_rays.lights, data, lobe=(on_rays.lobe_exponent, on_rays.lobe_amplitude)
        )
        if _usable_glossy(free, pose):
            best = free
    fitted = glare.Lobe(best.lobe_exponent, best.lobe_amplitude, lobe.f_ratio)
    return best.lights, best.rms, fitted


def _usable_glossy(fit: light_fit.JointFit, pose: light_fit.PlatePose) -> bool:
    """:func:`_usable`, with a positive lobe of finite exponent."""
    return _usable(fit, pose) and fit.lobe_amplitude > 0 and bool(np.isfinite(fit.lobe_exponent))


def _usable(fit: light_fit.JointFit, pose: light_fit.PlatePose) -> bool:
    """A converged fit whose lights are finite and in front of the plate."""
    behind = (fit.lights.positions_mm - pose.centre_mm) @ pose.normal <= 0
    return bool(fit.success and not behind.any() and np.all(np.isfinite(fit.lights.positions_mm)))


def _fit_points_lambertian(
    data: light_fit.Samples, start: Lights, pose: light_fit.PlatePose, rays: np.ndarray
) -> tuple[Lights | None, float]:
    """:func:`_fit_points` on a matte plate: the lights' joint fit from ``start``."""
    try:
        fixed = light_fit.joint_fit(start, data, fixed_mu=True, rays=rays)
    except (np.linalg.LinAlgError, ValueError, FloatingPointError):
        return None, float("nan")
    candidates = [fixed]
    with contextlib.suppress(np.linalg.LinAlgError, ValueError, FloatingPointError):
        candidates.insert(0, light_fit.joint_fit(fixed.lights, data, rays=rays))
    for fit in candidates:
        if _usable(fit, pose):
            return fit.lights, _rms(data, fit.lights)
    return None, float("nan")
