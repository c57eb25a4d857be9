"""From photometric images to a metric surface: normals, integration and fusion with the stereo pair.

Two light models (:mod:`pipeline.lights.model`):

- **Distant lights** (``direction``): the normals do not depend on the surface; they are
  estimated once (:func:`pipeline.surface.normals.estimate_normals`), integrated, and the stereo pair
  sets the low frequencies (:func:`pipeline.surface.fusion.fuse_low_frequencies`). Nominal directions of
  what really are near-field LEDs, or a light bumped by a degree, bend the integrated surface
  smoothly; the stereo pair takes that bend out. A glossy coating's lobe is measured on the stereo
  pair's smooth surface (:func:`stereo_lobe`, beside the integration) and, when there is one, the
  normals are fitted with it and integrated again (:func:`with_lobe`), as under point lights.
- **Point lights** (``position_mm``): the light vectors and irradiance at a pixel depend on the
  surface point it sees. Starting from the stereo pair's smooth surface (or, without one, the plane
  at the working distance), normals (:func:`pipeline.lights.nearfield.estimate_normals_near`) and the
  fused surface are computed alternately until the depth stops moving.

Normals that still face away from their pixel's ray are filled from their neighbours and counted
(never an error while most of the plate is measurable).
"""

from __future__ import annotations

import functools
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from pipeline.formats import CaptureError
from pipeline.lights import glare, nearfield
from pipeline.lights import refinement as light_refinement
from pipeline.lights.model import Lights
from pipeline.surface import fusion, integration, normals
from pipeline.surface.normals.noise import image_noise

#: Point lights: the alternation stops when the 99th percentile of the depth's change is below this
#: (mm): a 1 mm move turns a light's direction by ~0.02 deg at 3 m.
DEPTH_STEP_TOL_MM = 1.0
#: Point lights: at most this many normal estimates (the first from the starting surface).
MAX_NEAR_FIELD_ITERATIONS = 4
#: The coarsest stereo correction of normals fitted with a specular lobe: the quadric, so that the
#: stereo pair sets their bend. Per pixel the lobe fit is nonlinear in the normal, and the images'
#: noise leaves a bend of its own in the integrated plate that no stated uncertainty covered (18 LEDs
#: with positions, glossy, a cylinder R 5000 formed exactly: -0.035 % radius at the simulator's noise
#: with the lobe's exponent and amplitude measured exactly, -0.004 % at 1/8 of that noise, -0.18 % at
#: 0.35 of the exposure), while the lack-of-fit test, which compares each rung with the finest spline,
#: kept the plane. The bend's uncertainty is the quadric's in any case (``bend_rel``).
LOBE_BEND_FROM_STEREO: fusion.Rung = fusion.QUADRIC


@dataclass(frozen=True)
class Surface:
    """A reconstructed surface on the undistorted left grid.

    Attributes
    ----------
    depth_mm : (H, W) float64
        Depth along the optical axis, mm; NaN outside ``mask``.
    mask : (H, W) bool
    field : NormalField
        The photometric normals the surface was integrated from.
    fusion : Fusion or None
        How the stereo pair corrected the low frequencies (None without a stereo prior).
    iterations : int
        Normal estimates made (1 for distant lights).
    depth_steps_mm : tuple of float
        Point lights: the 99th percentile of the depth's change at each alternation, mm.
    normals_facing_away : int
        Normals dropped as facing away from their ray and filled.
    refinement : LightRefinement or None
        The lights refitted against the stereo geometry, when the given ones disagreed with it
        (:func:`remeasure_with_refined_lights`).
    """

    depth_mm: np.ndarray
    mask: np.ndarray
    field: normals.NormalField
    fusion: fusion.Fusion | None
    iterations: int
    depth_steps_mm: tuple[float, ...]
    normals_facing_away: int
    refinement: light_refinement.LightRefinement | None = None


def integrate_and_fuse(
    field: normals.NormalField,
    K: np.ndarray,
    *,
    prior_mm: np.ndarray | None,
    working_distance_mm: float | None,
    stereo_weight: float,
    tol: float,
    coarsest: fusion.Rung = fusion.PLANE,
) -> tuple[np.ndarray, np.ndarray, normals.NormalField, fusion.Fusion | None, int]:
    """Integrate a normal field to metric depth and give its low frequencies to the stereo pair.

    Parameters
    ----------
    field : NormalField
    K : (3, 3) float
        Intrinsics of the undistorted left grid, pixels.
    prior_mm : (H, W) float or None
        Stereo depth (mm, NaN where unmatched); None: the working distance sets the scale.
    working_distance_mm : float or None
        Depth (mm) on the optical axis; needed without a prior.
    stereo_weight : float
        Weight of the stereo depth in the integration (see :class:`pipeline.stages.InspectOptions`).
    tol : float
        Relative residual of the depth solve.
    coarsest : {"plane", "quadric"}
        The coarsest correction the stereo pair may give (:func:`pipeline.surface.fusion.fuse_low_frequencies`).

    Returns
    -------
    (depth_mm, mask, field, fusion, dropped)
        Depth (H, W) float64 mm (NaN outside ``mask``), the field after dropping normals facing
        away, the fusion (None without a prior) and how many normals were dropped.
    """
    field, dropped = normals.drop_facing_away(field, K)
    if prior_mm is not None:
        depth = integration.integrate_normals(
            field.normals,
            field.mask,
            K,
            prior_depth_mm=prior_mm,
            prior_weight=stereo_weight,
            tol=tol,
        )
        mask = depth.mask & np.isfinite(depth.depth_mm)
        fused = fusion.fuse_low_frequencies(depth.depth_mm, prior_mm, mask, coarsest=coarsest)
        return fused.depth_mm, mask, field, fused, dropped
    if working_distance_mm is None:
        raise ValueError(
            "working_distance_mm: expected a distance without a stereo prior, got none"
        )
    depth = integration.integrate_normals(
        field.normals, field.mask, K, reference_depth_mm=working_distance_mm, tol=tol
    )
    z = scale_to_working_distance(depth.depth_mm, K, working_distance_mm)
    return z, depth.mask & np.isfinite(z), field, None, dropped


def distant_surface(field: normals.NormalField, K: np.ndarray, **kwargs: Any) -> Surface:
    """The surface of normals estimated under distant lights (see :func:`integrate_and_fuse` for kwargs)."""
    depth, mask, field, fused, dropped = integrate_and_fuse(field, K, **kwargs)
    return Surface(depth, mask, field, fused, 1, (), dropped)


@dataclass(frozen=True)
class StereoLobe:
    """A coating's lobe measured on the stereo pair's smooth surface (:func:`stereo_lobe`).

    Attributes
    ----------
    lobe : glare.Lobe
        Its exponent, amplitude and F-ratio (about 1 on a matte plate).
    start_mm : (H, W) float64
        The smooth surface (:func:`pipeline.surface.fusion.smooth_stereo_depth`), NaN off the plate.
    """

    lobe: glare.Lobe
    start_mm: np.ndarray

    @property
    def significant(self) -> bool:
        """Whether the lobe is worth modelling (:data:`pipeline.lights.glare.MIN_F`)."""
        return bool(self.lobe.f_ratio >= glare.MIN_F and self.lobe.amplitude > 0)


def stereo_lobe(
    images: np.ndarray,
    valid: np.ndarray | None,
    lights: Lights,
    K: np.ndarray,
    prior_mm: np.ndarray,
    mask: np.ndarray,
    *,
    smooth_mm: np.ndarray | None = None,
) -> StereoLobe:
    """The lobe of the plate ``mask`` measured on the stereo pair's smooth surface through ``prior_mm``
    (:func:`pipeline.lights.glare.measure_lobe`), whose normals owe nothing to the photometric model.
    ``smooth_mm``: that surface when the caller has it already (:func:`pipeline.surface.fusion.
    smooth_stereo_depth` of ``prior_mm`` over ``mask``).

    Under distant lights the specular stage of the normals (:mod:`pipeline.surface.normals.specular`)
    fits the lobe from the images alone; a broad lobe (e = 15-25) lies almost within the span of the
    Lambertian model there, so that stage finds little of it and the integrated plate bends (a plate
    formed exactly read p95 0.4-1.0 mm and failed, 12 distant lights). On the stereo surface the
    lobe is told from the diffuse light. Needs no photometric result: it runs beside the integration.
    No parallel kernel, so that it may run on a worker thread (those stay on the main one).
    """
    start = fusion.smooth_stereo_depth(prior_mm, mask) if smooth_mm is None else smooth_mm
    lobe = glare.measure_lobe(images, valid, lights, start, None, mask, K, start_mm=start)
    return StereoLobe(lobe, start)


def with_lobe(
    surface: Surface,
    images: np.ndarray,
    lights: Lights,
    K: np.ndarray,
    valid: np.ndarray | None,
    measured: StereoLobe,
    solve_kw: dict[str, Any],
    *,
    noise: float | None = None,
) -> Surface:
    """``surface`` with its normals fitted with the lobe ``measured`` from the stereo surface's normals
    (:func:`pipeline.lights.glare.fit_with_lobe`), integrated and fused once more (``solve_kw``: as
    for :func:`integrate_and_fuse`); ``surface`` itself when the lobe is not significant (a matte
    plate). ``noise``: the images' noise (default: measured on the surface's mask)."""
    if not measured.significant:
        return surface
    if noise is None:
        noise = float(np.median(image_noise(images, surface.mask)))
    return _refit_with_lobe(
        surface, images, lights, K, valid, measured.start_mm, measured.lobe, noise, solve_kw
    )


def near_field_surface(
    images: np.ndarray,
    lights: Lights,
    K: np.ndarray,
    mask: np.ndarray,
    *,
    valid: np.ndarray | None,
    method: str,
    prior_mm: np.ndarray | None,
    working_distance_mm: float | None,
    stereo_weight: float,
    tol: float,
    max_iterations: int = MAX_NEAR_FIELD_ITERATIONS,
    step_tol_mm: float = DEPTH_STEP_TOL_MM,
    start_mm: np.ndarray | None = None,
    model_lobe: bool = True,
) -> Surface:
    """Alternate near-field normals and the fused surface until the depth stops moving.

    Parameters
    ----------
    images : (N, H, W) float32
        Preprocessed photometric images (dark-subtracted, undistorted, divided by intensity).
    lights : Lights
        Left-camera frame, mm; point lights (distant ones may be mixed in).
    K : (3, 3) float
        Intrinsics of the undistorted left grid.
    mask : (H, W) bool
        Plate pixels.
    valid : (N, H, W) bool or None
    method : {"robust", "lstsq"}
    prior_mm, working_distance_mm, stereo_weight, tol
        As for :func:`integrate_and_fuse`.
    max_iterations : int
        Normal estimates at most.
    step_tol_mm : float
        Stop when the 99th percentile of the depth's change falls below this, mm.
    start_mm : (H, W) float, optional
        The starting surface, when already computed (default: the stereo pair's smooth surface,
        or the plane at the working distance).
    model_lobe : bool
        With a stereo prior and the robust estimator: test the images for a specular lobe on the
        starting surface and, when there is one, fit the normals with it once the alternation
        stops (:mod:`pipeline.lights.glare`). Refitted lights: True when they were fitted with the
        lobe (:attr:`LightRefinement.lobe`); refitted as if Lambertian on a glossy plate, their
        distances were too far off for the lobe's half vectors (max 6.6 mm against 4.5 mm without).
        The lobe's exponent is refined between the grid's points (:func:`pipeline.lights.glare.lobe_of`),
        for refitted lights too: a broad lobe (e 15) read on the grid (15.87) left a plate under
        18 LEDs given by their directions at p95 0.66-0.71 mm, max 1.8 mm; refined, 0.25 / 0.9-1.0 mm.

    Returns
    -------
    Surface

    Raises
    ------
    CaptureError
        A light lies behind the plate's surface (the plate would not be lit from the camera side).
    """
    if start_mm is not None:
        start = start_mm
    elif prior_mm is not None:
        start = fusion.smooth_stereo_depth(prior_mm, mask)
    elif working_distance_mm is not None:
        start = np.where(mask, float(working_distance_mm), np.nan)
    else:
        raise ValueError(
            "working_distance_mm: expected a distance without a stereo prior, got none"
        )
    _check_lights_in_front(lights, start, mask)
    noise = float(np.median(image_noise(images, mask)))  # the images', the same at every estimate
    solve_kw: dict[str, Any] = dict(
        prior_mm=prior_mm,
        working_distance_mm=working_distance_mm,
        stereo_weight=stereo_weight,
        tol=tol,
    )
    lobe_wanted = model_lobe and prior_mm is not None and method == "robust"
    with ThreadPoolExecutor(max_workers=1) as pool:
        surface, matte = _alternate(
            images,
            lights,
            K,
            np.where(mask, start, np.nan),
            mask,
            valid=valid,
            method=method,
            noise=noise,
            solve_kw=solve_kw,
            max_iterations=max_iterations,
            step_tol_mm=step_tol_mm,
            pretest=(pool, start) if lobe_wanted else None,
        )
    if lobe_wanted:
        lobe = matte.result() if matte is not None else None
        if lobe is None:  # not plainly matte on the starting surface: measured on the final one
            lobe = glare.measure_lobe(
                images, valid, lights, surface.depth_mm, None, surface.mask, K, start_mm=start
            )
        surface = with_lobe(
            surface, images, lights, K, valid, StereoLobe(lobe, start), solve_kw, noise=noise
        )
    return surface


def _alternate(
    images: np.ndarray,
    lights: Lights,
    K: np.ndarray,
    depth: np.ndarray,
    mask: np.ndarray,
    *,
    valid: np.ndarray | None,
    method: str,
    noise: float,
    solve_kw: dict[str, Any],
    max_iterations: int,
    step_tol_mm: float,
    pretest: tuple[ThreadPoolExecutor, np.ndarray] | None,
) -> tuple[Surface, Future[glare.Lobe | None] | None]:
    """:func:`near_field_surface`'s alternation from ``depth`` (NaN off ``mask``): the surface, and with
    ``pretest`` (a worker and the starting surface) the lobe's pretest on that surface
    (:func:`pipeline.lights.glare.matte_lobe`), run on the worker beside the first depth solve: a matte
    plate (the usual one) then waits for no lobe measurement after the last."""
    steps: list[float] = []
    field = fused = None
    dropped = 0
    surface_mask = mask
    matte = None
    for it in range(1, max_iterations + 1):  # noqa: B007 (the count is returned)
        est_mask = surface_mask & np.isfinite(depth)
        field = nearfield.estimate_normals_near(
            images, lights, depth, K, est_mask, valid=valid, method=method, noise=noise
        )
        if pretest is not None and matte is None:
            pool, start = pretest
            matte = pool.submit(
                glare.matte_lobe, images, valid, lights, depth, est_mask, K, start_mm=start
            )
        new_depth, surface_mask, field, fused, dropped = integrate_and_fuse(field, K, **solve_kw)
        both = surface_mask & np.isfinite(depth)
        step = (
            float(np.percentile(np.abs(new_depth[both] - depth[both]), 99))
            if both.any()
            else np.inf
        )
        steps.append(round(step, 4))
        depth = new_depth
        if step < step_tol_mm:
            break
    if field is None:
        raise ValueError(f"max_iterations: expected at least 1, got {max_iterations}")
    return Surface(depth, surface_mask, field, fused, it, tuple(steps), dropped), matte


def _refit_with_lobe(
    surface: Surface,
    images: np.ndarray,
    lights: Lights,
    K: np.ndarray,
    valid: np.ndarray | None,
    start: np.ndarray,
    lobe: glare.Lobe,
    noise: float,
    solve_kw: dict[str, Any],
) -> Surface:
    """The normals fitted with ``lobe`` from the normals of the smooth surface ``start``, integrated and
    fused once more (:func:`with_lobe`), the stereo pair's correction at least a quadric: normals
    fitted with a lobe carry a bend of their own at the images' noise (:data:`LOBE_BEND_FROM_STEREO`)."""
    depth = surface.depth_mm
    normals_start = glare.surface_normals(start, K)
    glossy, _ = glare.fit_with_lobe(
        images, valid, lights, depth, normals_start, K, lobe, surface.field, noise
    )
    new_depth, mask, field, fused, dropped = integrate_and_fuse(
        glossy, K, coarsest=LOBE_BEND_FROM_STEREO, **solve_kw
    )
    both = mask & np.isfinite(depth)
    step = float(np.percentile(np.abs(new_depth[both] - depth[both]), 99)) if both.any() else np.inf
    return Surface(
        new_depth,
        mask,
        field,
        fused,
        surface.iterations + 1,
        (*surface.depth_steps_mm, round(step, 4)),
        dropped,
    )


def disagrees(surface: Surface, tolerance_mm: float, fraction: float) -> bool:
    """Whether the photometric and stereo shapes disagree beyond noise and ``fraction`` of the tolerance."""
    f = surface.fusion
    return f is not None and f.disagreement_mm > max(f.noise_floor_mm, fraction * tolerance_mm)


def remeasure_with_refined_lights(
    first: Surface,
    images: np.ndarray,
    lights: Lights,
    K: np.ndarray,
    mask: np.ndarray,
    *,
    valid: np.ndarray | None,
    method: str,
    prior_mm: np.ndarray,
    working_distance_mm: float | None,
    stereo_weight: float,
    tol: float,
) -> Surface:
    """Refit the given lights on the stereo geometry and measure again with them.

    For a surface measured with distant lights whose shape disagreed with the stereo pair's (see
    :mod:`pipeline.lights.refinement`): the refined lights are point lights (near-field
    reconstruction) or corrected distant ones. The new surface is kept when it agrees better with
    the stereo pair, and then ``refinement`` records the fit; otherwise the first surface is returned
    as it was (the given lights stand). Point lights that measure the plate no closer are followed by
    the distant model alone (with the coating's lobe where it shows), kept on the same terms.

    Parameters
    ----------
    first : Surface
        The surface measured with the given lights.
    images : (N, H, W) float32
        Preprocessed images (divided by the given intensities).
    lights : Lights
        The given lights.
    K, mask, valid, method, prior_mm, working_distance_mm, stereo_weight, tol
        As for :func:`near_field_surface`; ``prior_mm`` is required.

    Returns
    -------
    Surface
    """
    smooth = fusion.smooth_stereo_depth(prior_mm, mask)
    refined = light_refinement.refine_lights(images, valid, mask, lights, smooth, K)
    if refined is None:
        return first
    solve: dict[str, Any] = dict(
        prior_mm=prior_mm,
        working_distance_mm=working_distance_mm,
        stereo_weight=stereo_weight,
        tol=tol,
    )
    measure = functools.partial(
        _with_refined, images, lights, K, mask, valid, method, smooth, solve
    )
    second = measure(refined)
    if not _closer(second, first) and refined.model == "point":
        # The images preferred point lights, yet the plate measured with them is no closer to the stereo
        # pair's: the distant lights refitted (with the coating's lobe where it shows) are measured too.
        # A broad lobe under distant lights written a degree off is fitted far better by free point lights
        # than by distant Lambertian ones, and the lobe under those is then never tested (12 lights,
        # lobe 0.4 at shininess 15: the point lights kept a 4 mm disagreement, a plate formed exactly
        # failed).
        distant = light_refinement.refine_lights(
            images, valid, mask, lights, smooth, K, point_model=False
        )
        if distant is not None:
            refined, second = distant, measure(distant)
    # the refitted lights count only if the plate measured with them is kept: otherwise the given
    # lights stand, and the result says nothing about lights it did not use
    return replace(second, refinement=refined) if _closer(second, first) else first


def _closer(second: Surface, first: Surface) -> bool:
    """Whether ``second`` agrees better with the stereo pair than ``first`` (both fused)."""
    return (
        second.fusion is not None
        and first.fusion is not None
        and second.fusion.disagreement_mm < first.fusion.disagreement_mm
    )


def _with_refined(
    images: np.ndarray,
    lights: Lights,
    K: np.ndarray,
    mask: np.ndarray,
    valid: np.ndarray | None,
    method: str,
    smooth: np.ndarray,
    solve: dict[str, Any],
    refined: light_refinement.LightRefinement,
) -> Surface:
    """The plate measured with the ``refined`` lights (:func:`remeasure_with_refined_lights`)."""
    # the images were divided by the given intensities: by the refined ones instead
    gain = (lights.intensity / refined.lights.intensity).astype(np.float32)
    scaled = images * gain[:, None, None]
    if refined.model == "point":
        return near_field_surface(
            scaled,
            refined.lights,
            K,
            mask,
            valid=valid,
            method=method,
            start_mm=smooth,
            model_lobe=refined.lobe is not None,
            **solve,
        )
    field = normals.estimate_normals(
        scaled, refined.lights.directions, mask, valid=valid, method=method, camera_matrix=K
    )
    second = distant_surface(field, K, **solve)
    if field.specular is not None and field.specular.modelled:  # as for given distant lights
        # the smooth surface the lights were refitted on: the same prior over the same mask
        lobe = stereo_lobe(
            scaled, valid, refined.lights, K, solve["prior_mm"], mask, smooth_mm=smooth
        )
        second = with_lobe(second, scaled, refined.lights, K, valid, lobe, solve)
    return second


def _check_lights_in_front(lights: Lights, depth_mm: np.ndarray, mask: np.ndarray) -> None:
    """A point light at or beyond the plate's nearest depth would light it from behind."""
    if not lights.any_point:
        return
    nearest = float(np.nanmin(np.where(mask, depth_mm, np.nan)))
    for k in np.flatnonzero(lights.is_point):
        if lights.positions_mm[k, 2] >= nearest:
            raise CaptureError(
                f"photometric.lights[{k}].position_mm: the light (z = {lights.positions_mm[k, 2]:.0f} mm) is not in "
                f"front of the plate, whose nearest point is at z = {nearest:.0f} mm (left camera frame)"
            )


def scale_to_working_distance(
    depth_mm: np.ndarray, K: np.ndarray, working_distance_mm: float
) -> np.ndarray:
    """Scale an up-to-scale depth so the plate's depth on the optical axis is the working distance.

    The working distance is the depth (mm, along the optical axis) of the surface point seen at the
    principal point; where the plate does not cover it, the median depth over the plate stands in.
    """
    z = depth_mm
    cx, cy = int(round(K[0, 2])), int(round(K[1, 2]))
    window = z[max(cy - 2, 0) : cy + 3, max(cx - 2, 0) : cx + 3]
    on_axis = window[np.isfinite(window)]
    reference = float(np.median(on_axis)) if on_axis.size else float(np.nanmedian(z))
    if not reference > 0:
        raise CaptureError("depth: the integrated surface has no positive depth to scale")
    return z * (working_distance_mm / reference)
