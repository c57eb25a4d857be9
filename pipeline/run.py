"""The one orchestration entry point: a capture bundle and a target in, a judged plate out.

The CLI (``plate-inspect inspect``) and the service's job both call
:func:`inspect`; neither re-implements a stage.
"""

from __future__ import annotations

import json
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

import cv2
import numpy as np
from threadpoolctl import threadpool_limits

from . import (
    artifacts,
    curvature,
    deviation,
    normals,
    reconstruct,
    registration,
    segmentation,
    stereo,
    target_geometry,
    verdict,
)
from .formats import RESULT_FORMAT, CaptureError, PipelineError, ResultFile
from .io import Capture, Target, load_capture, load_target
from .lights import Lights
from .parallel import default_workers
from .preprocess import preprocess

#: Stage names in the order they run; ``progress`` reports these.
STAGES = ("load", "preprocess", "normals", "stereo", "depth", "curvature", "deviation", "artifacts")

ProgressCallback = Callable[[str, float], None]

#: A measured area (mask and edge band) under this share of the target's gets a warning in the result.
AREA_WARNING_RATIO = 0.9

#: Without a working-distance hint the stereo pair is searched around this depth (mm):
#: with the default ``depth_margin`` of 1.0 that is 1750-7000 mm, the cell's whole range.
NOMINAL_DISTANCE_MM = 3500.0
#: The result warns that the photometric and stereo shapes disagree when the disagreement (see
#: :class:`pipeline.fusion.Fusion`) exceeds both the noise floor and this fraction of the tolerance.
DISAGREEMENT_FRACTION = 0.25


@dataclass(frozen=True)
class InspectOptions:
    """Knobs of the measurement; the defaults are the product's settings.

    Attributes
    ----------
    normals_method : {"robust", "lstsq"}
        Per-pixel photometric estimator (see :func:`pipeline.normals.estimate_normals`).
    stereo_weight : float
        Weight of the stereo depth against the normal equations in the fusion
        (dimensionless, per pixel, log-depth units). The normals win above the
        wavelength ``2 pi / sqrt(stereo_weight)`` pixels (~630 px at 1e-4): the
        stereo pair sets scale, position and tilt, the normals the shape. Measured
        on simulated plates (1224x1024): 1e-2 lets stereo noise through
        (deviation RMS 0.15 mm on a perfect cylinder), 1e-4 gives 0.03 mm, 1e-5
        starts to lose the scale (+0.05 % radius).
    depth_margin : float
        The stereo pair's coarse search covers ``working distance / (1 + depth_margin)``
        .. ``working distance * (1 + depth_margin)`` (1500-6000 mm for a 3000 mm hint at 1.0;
        1750-7000 mm without a hint). It only bounds where the plate is looked for: the fine
        search range comes from the plate's disparities found by the coarse pass, so a wrong
        hint that still brackets the plate changes nothing (see :func:`pipeline.stereo.stereo_depth`).
    min_stereo_pct : float
        Below this share of the plate matched (percent), the stereo depth is not
        trusted (a plate outside the searched range gives a few wrong matches): the
        working distance sets the scale instead, or the capture is refused without one.
    stereo_max_width : int
        A stereo pair wider than this (px) is matched reduced by the smallest whole
        factor that fits: its depth only anchors the scale and the lowest frequencies
        of the fused surface.
    depth_tol : float
        Relative residual at which the depth solve stops (``tol`` of
        :func:`pipeline.integration.integrate_normals`). Measured on a simulated plate at
        2448x2048 against a solve to 1e-8: 1e-4 changes no depth by more than 1 um
        (1e-3: 20 um), in 4 iterations instead of 6 for 1e-6 (0.11 s less).
    workers : int or None
        Threads for the work that runs beside the main line (stereo, curvature, artifact
        writing) and for preprocessing; None: :func:`pipeline.parallel.default_workers`. The
        result does not depend on it.
    """

    normals_method: str = "robust"
    stereo_weight: float = 1e-4
    depth_margin: float = 1.0
    min_stereo_pct: float = 20.0
    stereo_max_width: int = 1600
    depth_tol: float = 1e-4
    workers: int | None = None


@dataclass(frozen=True)
class InspectionResult:
    """What :func:`inspect` produced.

    Attributes
    ----------
    document : dict
        The ``plate-result/1`` object, as written to ``out_dir/result.json``.
    out_dir : Path
    """

    document: dict
    out_dir: Path

    @property
    def verdict(self) -> str:
        return self.document["verdict"]


class _Clock:
    """Times the stages and reports progress."""

    def __init__(self, progress: ProgressCallback | None):
        self.progress = progress
        self.timings: dict[str, float] = {}
        self.start = time.perf_counter()
        self._t = self.start

    def begin(self, stage: str) -> None:
        self._t = time.perf_counter()
        if self.progress is not None:
            self.progress(stage, STAGES.index(stage) / len(STAGES))

    def end(self, stage: str) -> None:
        self.timings[stage] = round(time.perf_counter() - self._t, 4)

    def total(self) -> float:
        return round(time.perf_counter() - self.start, 4)


def inspect(
    capture: Capture | str | Path,
    target: Target | dict | str | Path,
    *,
    out_dir: str | Path,
    progress: ProgressCallback | None = None,
    options: InspectOptions | None = None,
    light_calibration: Lights | None = None,
) -> InspectionResult:
    """Measure a plate and judge it against its CAD target.

    Parameters
    ----------
    capture : Capture or path
        A capture bundle (folder or .zip, ``plate-capture/1``) or one already loaded.
    target : Target, dict or path
        The ``plate-target/1`` target.
    out_dir : path
        Where ``result.json`` and the artifacts are written (created if needed).
    progress : callable(stage, fraction), optional
        Called when each stage of :data:`STAGES` starts (fraction 0..1 of the
        stages done) and once with ``("done", 1.0)``.
    options : InspectOptions, optional
    light_calibration : pipeline.lights.Lights, optional
        The cell's measured lights (``plate-inspect calibrate-lights``, read with
        :func:`pipeline.io.load_light_calibration`). Applied to a capture whose lights are all
        given only as directions (nominal lights) and as many as its images; the result then
        carries a warning that says so. A capture that gives point lights keeps its own; a
        calibration with another count of lights is not applied (a warning says why).

    Returns
    -------
    InspectionResult

    Raises
    ------
    pipeline.formats.InputError
        Bad input files (names the file and the field).
    pipeline.formats.CaptureError
        A valid capture that cannot be measured (no plate found, no metric scale).
    """
    opts = options or InspectOptions()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    clock = _Clock(progress)
    try:
        # BLAS calls here are small (3x3 systems, N x 3 products): OpenBLAS threads would only spin
        # after each one and take a core from the work running beside it (measured: ~0.3 core-s
        # per inspection at 1224x1024)
        with threadpool_limits(limits=1, user_api="blas"):
            return _inspect(capture, target, out, clock, opts, light_calibration)
    except PipelineError as err:
        # a capture that cannot be measured still leaves a result that says why
        _write_error_result(out, capture, target, err, clock)
        raise


def _inspect(capture, target, out: Path, clock: _Clock, opts: InspectOptions, light_calibration) -> InspectionResult:
    clock.begin("load")
    cap = capture if isinstance(capture, Capture) else load_capture(capture)
    tgt = target if isinstance(target, Target) else load_target(target)
    warnings: list[str] = []
    cap = _apply_light_calibration(cap, light_calibration, warnings)
    if not cap.has_stereo and cap.working_distance_mm is None:
        raise CaptureError(
            f"{cap.source}: stereo, working_distance_mm: a metric result needs a stereo pair or a working distance"
        )
    clock.end("load")

    clock.begin("preprocess")
    pre = preprocess(cap, workers=opts.workers)
    # what may be plate: not dark. Over a dark conveyor that is the plate; over a lit floor, most of the
    # image. The stereo pair is matched over it (the segmentation needs the surroundings' depth too) and,
    # under distant lights, the normals are estimated over it while the pair is matched.
    candidates = segmentation.candidate_mask(pre.brightest, seen=pre.seen) if cap.has_stereo else pre.mask
    # a plate alone over a dark conveyor (the usual cell): the brightness mask is all the stereo pair and the
    # normals need; the stereo depth then only confirms it is one sheet
    plain_outline = cap.has_stereo and segmentation.plain_outline(pre.mask, candidates)
    region = pre.mask if plain_outline else candidates
    clock.end("preprocess")

    names = {
        "surface": "surface.ply",
        "target_surface": "target.ply",
        "deviation_map": "deviation.png",
        "normals": "normals.png",
        "depth": "depth.npy",
        "details": "details.json",
    }
    # Work that does not need the main line's next result runs beside it. The stereo pair
    # needs only the plate mask (matched while the normals are estimated); curvature and the pixel
    # areas run beside the registration; the artifacts (image encoding and file writing release the
    # GIL) as soon as they are known.
    # numba's parallel kernels (normals, depth) run on this thread only: never two at once.
    with ThreadPoolExecutor(max_workers=opts.workers or default_workers()) as pool:
        stereo_job = pool.submit(_stereo_depth, cap, region, opts) if cap.has_stereo else None
        rays_job = pool.submit(cap.rig.left.pixel_rays)  # (H, W, 3) float64, for the surface and the areas
        K = cap.rig.left.K
        near_field = cap.lights.any_point
        field = None
        clock.begin("normals")
        if not near_field:
            # distant lights: the normals do not depend on the surface, estimated while stereo matches
            field = normals.estimate_normals(
                pre.images, cap.light_dirs, region, valid=pre.valid, method=opts.normals_method, camera_matrix=K,
            )
            clock.end("normals")
        writes = []
        clock.begin("stereo")
        depth_c, stereo_s, depth_scale = stereo_job.result() if stereo_job is not None else (None, 0.0, 1)
        clock.timings["stereo"] = stereo_s
        # the plate among its surroundings (#17): the near, smooth sheet of the stereo depth; openings stay
        # holes, supports beside the plate and an edge band are left out. Without a pair: the brightness mask.
        t_seg = time.perf_counter()
        seg = None
        plain = plain_outline and depth_c is not None and segmentation.plain_depth(pre.mask, depth_c, K)
        if depth_c is not None and not plain:
            seg = _segment(pre, depth_c, K, candidates, depth_scale, field, tgt)
        # a plain scene (a plate over a dark conveyor, no opening): the brightness mask is the plate
        plate = pre.mask if seg is None else seg.mask
        if seg is not None:
            prior = seg.stereo_prior(depth_c)
        else:
            prior = None if depth_c is None else np.where(plate, depth_c, np.nan)
        if field is not None:
            field = _restricted(field, plate)
        clock.timings["segmentation"] = round(time.perf_counter() - t_seg, 4)
        if field is not None:
            # normals.png now, while the depth is solved on this thread (the few normals dropped later as facing
            # away are then shown as estimated)
            writes.append(pool.submit(artifacts.write_normals_png, out / names["normals"], field.normals, field.mask))
        normals_written = bool(writes)
        matched_pct = (
            None if prior is None else 100.0 * np.count_nonzero(np.isfinite(prior) & plate) / plate.sum()
        )
        if prior is not None and matched_pct < opts.min_stereo_pct:
            if cap.working_distance_mm is None:
                raise CaptureError(
                    f"{cap.source}: stereo: {matched_pct:.1f} % of the plate matched in the stereo pair, expected at "
                    f"least {opts.min_stereo_pct:.0f} %, and there is no working_distance_mm to fall back on"
                )
            prior = None  # too little to trust: the working distance sets the scale (details.json says so)

        solve = dict(prior_mm=prior, working_distance_mm=cap.working_distance_mm, stereo_weight=opts.stereo_weight,
                     tol=opts.depth_tol)
        if near_field:
            # point lights: normals and surface alternate; "normals" times the whole alternation (with its
            # integrations), "depth" what follows
            t_near = time.perf_counter()
            surface = reconstruct.near_field_surface(
                pre.images, cap.lights, K, plate, valid=pre.valid, method=opts.normals_method, **solve
            )
            clock.timings["normals"] = round(time.perf_counter() - t_near, 4)
        clock.begin("depth")
        if not near_field:
            surface = reconstruct.distant_surface(field, K, **solve)
            if prior is not None and reconstruct.disagrees(surface, tgt.tolerance_mm, DISAGREEMENT_FRACTION):
                # the given lights bend the surface away from the stereo pair's: refit them on its geometry
                t_refit = time.perf_counter()
                if seg is None and depth_c is not None:
                    # so far on the brightness mask: lights that do not fit light the plate unevenly, and the
                    # mask follows its darker edges; measured again on the segmented plate
                    seg = _segment(pre, depth_c, K, candidates, depth_scale, field, tgt)
                    plain, plate = False, seg.mask
                    solve["prior_mm"] = seg.stereo_prior(depth_c)
                surface = reconstruct.remeasure_with_refined_lights(
                    surface, pre.images, cap.lights, K, plate, valid=pre.valid, method=opts.normals_method,
                    **solve,
                )
                clock.timings["light_refinement"] = round(time.perf_counter() - t_refit, 4)
        field = surface.field
        rays = rays_job.result()
        points = surface.depth_mm[..., None] * rays
        surface_mask = surface.mask
        clock.end("depth")

        clock.begin("curvature")
        curvature_job = pool.submit(_curvature, points, surface_mask)
        area_job = pool.submit(_pixel_area_mm2, surface.depth_mm, field.normals, rays, K)
        writes.append(pool.submit(artifacts.save_depth, out / names["depth"], surface.depth_mm))
        if not normals_written:
            writes.append(pool.submit(artifacts.write_normals_png, out / names["normals"], field.normals, field.mask))
        clock.begin("deviation")
        pose = registration.register_to_target(points, surface_mask, tgt)
        dev = deviation.deviation_map(points, surface_mask, tgt, pose)
        writes += [
            pool.submit(artifacts.write_surface_ply, out / names["surface"], points, surface_mask, dev,
                        tolerance_mm=tgt.tolerance_mm),
            pool.submit(artifacts.write_deviation_png, out / names["deviation_map"], dev, surface_mask,
                        tolerance_mm=tgt.tolerance_mm),
        ]
        pixel_area = area_job.result()
        judgement = verdict.judge(
            dev, surface_mask, tgt.tolerance_mm, pixel_area_mm2=pixel_area,
            edge_artefacts=None if seg is None else verdict.EdgeArtefacts(seg.surroundings_step_mm),
        )
        clock.end("deviation")
        clock.begin("artifacts")
        verts, faces = target_geometry.target_surface(tgt)
        writes.append(pool.submit(artifacts.write_target_ply, out / names["target_surface"], verts, faces,
                                  pose.T_cam_target))
        curv, clock.timings["curvature"] = curvature_job.result()
        # the registration fits the target's shape radius-free on its way (= registration.fitted_target_radius)
        fitted_radius = pose.fitted_radius_mm
        for write in writes:
            write.result()
    details = {
        "T_cam_target": pose.T_cam_target.tolist(),
        "registration_rms_mm": float(pose.rms_mm),
        "principal_directions": np.asarray(curv.principal_directions).tolist(),
        "defects": [
            {"centroid_px": list(map(float, d.centroid_px)), "area_mm2": float(d.area_mm2),
             "peak_deviation_mm": float(d.peak_deviation_mm)}
            for d in judgement.defects
        ],
        "reasons": list(judgement.reasons),
        "excluded_regions": [
            {"centroid_px": list(map(float, r.centroid_px)), "area_mm2": float(r.area_mm2),
             "peak_deviation_mm": float(r.peak_deviation_mm), "reason": r.reason}
            for r in judgement.excluded
        ],
        "segmentation": _segmentation_details(
            seg, tgt, plain=plain, measured_area_mm2=float(np.sum(pixel_area[surface_mask & np.isfinite(pixel_area)]))),
        "normals_filled": int(field.n_filled),
        "normals_facing_away": surface.normals_facing_away,
        "light_model": "near-field" if near_field else "distant",
        "near_field_iterations": surface.iterations if near_field else None,
        "near_field_depth_steps_mm": list(surface.depth_steps_mm) if near_field else None,
        "stereo_fusion": _fusion_details(surface.fusion),
        "light_refinement": _refinement_details(surface.refinement),
        "samples_saturated": pre.n_saturated,
        "samples_shadowed": pre.n_shadowed,
        "stereo_matched_pct": None if matched_pct is None else round(float(matched_pct), 2),
        "metric_scale": "stereo" if prior is not None else "working_distance",
    }
    if surface.refinement is not None:
        r = surface.refinement
        turn = max(c["turn_deg"] for c in r.corrections)
        what = ("point lights (LEDs near the plate) fitted from the images on the stereo geometry"
                if r.model == "point" else f"distant lights corrected by up to {turn:.2f} deg from the images on "
                "the stereo geometry")
        warnings.append(f"the capture's lights did not fit the plate the stereo pair measured; measured with {what} "
                        "(details.json: light_refinement)")
    if surface.fusion is not None and surface.fusion.disagreement_mm > max(
        surface.fusion.noise_floor_mm, DISAGREEMENT_FRACTION * tgt.tolerance_mm
    ):
        warnings.append(
            f"the photometric and the stereo shapes disagreed by {surface.fusion.disagreement_mm:.1f} mm (95th "
            f"percentile, beyond the {max(surface.fusion.noise_floor_mm, DISAGREEMENT_FRACTION * tgt.tolerance_mm):.1f}"
            f" mm that noise explains): the stereo pair set the plate's overall shape; check the light positions"
        )
    ratio = details["segmentation"]["area_ratio"]
    if ratio is not None and ratio < AREA_WARNING_RATIO:
        warnings.append(
            f"the measured area is {100 * ratio:.0f} % of the target's: openings, a plate "
            f"partly out of view, or areas the stereo pair could not match were not measured (details.json: segmentation)"
        )
    (out / names["details"]).write_text(json.dumps(details, indent=2) + "\n")
    clock.end("artifacts")

    target_radius = tgt.radius_mm if tgt.shape in ("cylinder", "sphere") else None
    radius_error = (
        100.0 * (fitted_radius - target_radius) / target_radius
        if fitted_radius is not None and target_radius is not None
        else None
    )
    timings = dict(clock.timings)
    timings["total"] = clock.total()
    doc = ResultFile(
        format=RESULT_FORMAT,
        plate_id=cap.plate_id,
        radius_mm=_round(fitted_radius, 2),
        principal_radii_mm=[_round(r, 1) for r in curv.principal_radii_mm],
        target_radius_mm=target_radius,
        radius_error_pct=_round(radius_error, 3),
        deviation_mm={
            "rms": round(judgement.rms_mm, 3),
            "max_abs": round(judgement.max_abs_mm, 3),
            "p95": round(judgement.p95_mm, 3),
        },
        tolerance_mm=tgt.tolerance_mm,
        within_tolerance_pct=round(judgement.within_tolerance_pct, 3),
        verdict=judgement.verdict,
        warnings=warnings or None,
        timings_s=timings,
        artifacts=names | {"result": "result.json"},
    ).model_dump(mode="json", exclude_none=False)
    doc["artifacts"].pop("result")
    if doc["warnings"] is None:
        del doc["warnings"]
    (out / "result.json").write_text(json.dumps(doc, indent=2) + "\n")
    if clock.progress is not None:
        clock.progress("done", 1.0)
    return InspectionResult(document=doc, out_dir=out)


def warm_up() -> float:
    """Load the compiled kernels and start the thread pools before the first real inspection.

    The numba kernels are compiled once per installation and cached on disk, but each process
    loads them (and OpenMP starts its threads) on their first call: ~0.5 s that would otherwise
    land in the first inspection's timings. This runs one small simulated glossy inspection
    (320x256, 12 lights, stereo: every kernel of the usual path and of the specular stage) in a
    temporary folder. Returns its run time, seconds.
    """
    from .simulate import CaptureSpec, PlateSpec, simulate_capture

    t = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="plate-inspect-warm-up-") as tmp:
        bundle = simulate_capture(
            Path(tmp) / "capture", plate=PlateSpec(), capture=CaptureSpec(width=320, height=256, specular=0.4), seed=0
        )
        inspect(bundle, bundle / "target.json", out_dir=Path(tmp) / "out")
    return time.perf_counter() - t


def _write_error_result(out: Path, capture, target, err: Exception, clock: _Clock) -> None:
    """Write a ``plate-result/1`` with verdict ``error`` saying why the capture could not be measured."""
    plate_id = capture.plate_id if isinstance(capture, Capture) else None
    if plate_id is None:
        try:
            plate_id = load_capture(capture).plate_id
        except Exception:  # noqa: BLE001 - the bundle itself may be what failed
            plate_id = "unknown"
    try:
        tolerance = (target if isinstance(target, Target) else load_target(target)).tolerance_mm
    except Exception:  # noqa: BLE001 - the target itself may be what failed
        tolerance = 0.0
    doc = ResultFile(
        plate_id=plate_id,
        radius_mm=None,
        principal_radii_mm=[None, None],
        target_radius_mm=None,
        radius_error_pct=None,
        deviation_mm=None,
        tolerance_mm=tolerance,
        within_tolerance_pct=None,
        verdict="error",
        error=" ".join(str(err).split()),
        timings_s=dict(clock.timings) | {"total": clock.total()},
        artifacts={},
    ).model_dump(mode="json", exclude={"warnings"})
    (out / "result.json").write_text(json.dumps(doc, indent=2) + "\n")


def _apply_light_calibration(cap: Capture, calibration: Lights | None, warnings: list[str]) -> Capture:
    """The capture with the calibrated lights in place of nominal ones (see :func:`inspect`)."""
    if calibration is None or cap.lights.any_point:
        return cap
    if calibration.n != cap.n_lights:
        warnings.append(
            f"the light calibration was not applied: it has {calibration.n} lights, the capture "
            f"{cap.n_lights} images; nominal light directions were used"
        )
        return cap
    warnings.append("a light calibration was applied to the capture's nominal light directions")
    return replace(cap, lights=calibration)


def _refinement_details(refined) -> dict | None:
    """details.json's account of the lights refitted on the stereo geometry."""
    if refined is None:
        return None
    return {
        "model": refined.model,
        "rms_given": round(refined.rms_given, 5),
        "rms_distant": round(refined.rms_distant, 5),
        "rms_point": None if not np.isfinite(refined.rms_point) else round(refined.rms_point, 5),
        "samples": refined.n_samples,
        "corrections": refined.corrections,
    }


def _fusion_details(fused) -> dict | None:
    """details.json's account of how the stereo pair corrected the photometric shape."""
    if fused is None:
        return None
    return {
        "disagreement_mm": round(fused.disagreement_mm, 3),
        "noise_floor_mm": round(fused.noise_floor_mm, 3),
        "stereo_noise_mm": round(fused.stereo_noise_mm, 3),
        "correction_max_abs_mm": round(float(np.nanmax(np.abs(fused.correction_mm))), 3),
        "stereo_pixels": fused.n_stereo,
        "correction": fused.model,
        "knot_spacing_px": None if fused.knot_spacing_px is None else round(fused.knot_spacing_px, 1),
    }


def _round(value: float | None, digits: int) -> float | None:
    return None if value is None else round(float(value), digits)


def _curvature(points: np.ndarray, mask: np.ndarray):
    """Principal curvatures and their run time (s)."""
    t = time.perf_counter()
    curv = curvature.principal_curvatures(points, mask)
    return curv, round(time.perf_counter() - t, 4)


def _stereo_depth(cap: Capture, mask: np.ndarray, opts: InspectOptions) -> tuple[np.ndarray, float, int]:
    """Stereo depth (mm, left undistorted grid, NaN where unmatched or outside ``mask``), its run time (s) and
    the reduction the pair was matched at (1: full size)."""
    t = time.perf_counter()
    z_nominal = cap.working_distance_mm or NOMINAL_DISTANCE_MM
    left, right, rig, stereo_mask = cap.stereo_left, cap.stereo_right, cap.rig, mask
    width, height = rig.image_size
    step = -(-width // opts.stereo_max_width)  # the smallest whole reduction that fits
    if step > 1:
        # the stereo depth only anchors scale and the lowest frequencies: a reduced pair is plenty, and cheaper
        small = (width // step, height // step)
        left, right = (cv2.resize(im, small, interpolation=cv2.INTER_AREA) for im in (left, right))
        rig = replace(rig, left=rig.left.resized(small), right=rig.right.resized(small))
        stereo_mask = cv2.resize(mask.view(np.uint8), small, interpolation=cv2.INTER_NEAREST).astype(bool)
    sd = stereo.stereo_depth(
        left,
        right,
        rig,
        z_min_mm=z_nominal / (1 + opts.depth_margin),
        z_max_mm=z_nominal * (1 + opts.depth_margin),
        mask=stereo_mask,
    )
    depth = sd.depth_mm
    if step > 1:  # back onto the full grid; a hole spreads to the pixels that interpolate from it
        depth = cv2.resize(depth, (width, height), interpolation=cv2.INTER_LINEAR)
    return np.where(mask, depth, np.nan), round(time.perf_counter() - t, 4), step


def _segment(pre, depth_mm, K, candidates, depth_scale, field, tgt):
    """The plate told from its surroundings (:func:`pipeline.segmentation.segment_plate`)."""
    return segmentation.segment_plate(
        pre.brightest, depth_mm, K, seen=pre.seen, candidates=candidates, depth_scale_px=depth_scale,
        normals=None if field is None else field.normals,  # NaN off the field's mask (NormalField)
        target_area_mm2=segmentation.target_area_mm2(tgt),
    )


def _restricted(field: normals.NormalField, mask: np.ndarray) -> normals.NormalField:
    """The normal field on ``mask`` only (estimated over the candidates, measured on the plate).

    The field's arrays are this inspection's own: the pixels left out are set to NaN in place.
    """
    drop = field.mask & ~mask
    if not drop.any():
        return field
    field.normals[drop] = np.nan
    field.albedo[drop] = np.nan
    keep = field.mask & ~drop
    filled = field.filled & keep
    return replace(field, mask=keep, filled=filled, n_filled=int(np.count_nonzero(filled)))


def _segmentation_details(seg, tgt: Target, *, plain: bool, measured_area_mm2: float) -> dict:
    """details.json: how the plate was told from its surroundings, and its area against the target's
    (without a segmentation, the measured surface's area: the brightness mask is eroded by 3 px)."""
    target_area = segmentation.target_area_mm2(tgt)
    if seg is None:
        why = ("a plain scene: nothing lit around the plate, no opening in it, one smooth sheet in the stereo "
               "depth; the brightness mask (Otsu) is the plate" if plain else
               "no stereo pair: the plate was told from its surroundings by brightness (Otsu, holes filled)")
        return {"method": "brightness", "plate_area_mm2": round(measured_area_mm2, 0),
                "target_area_mm2": round(target_area, 0), "area_ratio": round(measured_area_mm2 / target_area, 4),
                "reasons": [why]}
    measured = seg.plate_area_mm2 + seg.edge_band_area_mm2
    return {
        "method": seg.method,
        "plate_area_mm2": round(seg.plate_area_mm2, 0),
        "edge_band_px": seg.n_edge_band,
        "edge_band_area_mm2": round(seg.edge_band_area_mm2, 0),
        "holes": seg.n_holes,
        "holes_area_mm2": round(seg.holes_area_mm2, 0),
        "filled_area_mm2": round(seg.filled_area_mm2, 0),
        "target_area_mm2": round(target_area, 0),
        "area_ratio": round(measured / target_area, 4) if measured == measured else None,
        "fit_rms_mm": round(seg.fit_rms_mm, 2) if seg.fit_rms_mm == seg.fit_rms_mm else None,
        "reasons": list(seg.reasons),
    }


def _pixel_area_mm2(depth_mm: np.ndarray, normals: np.ndarray, rays: np.ndarray, K: np.ndarray) -> np.ndarray:
    """(H, W) area (mm^2) of the surface patch each pixel sees.

    A pixel spans the solid angle ``cos^3(a) / (fx fy)`` (``a``: its ray's angle to
    the optical axis); at distance ``z / cos(a)`` on a surface tilted by ``t``
    against the ray that is ``z^2 / (fx fy |n . r|)`` with ``r = K^-1 (u, v, 1)``.
    """
    n_dot_r = np.abs(np.einsum("hwc,hwc->hw", normals, rays))
    with np.errstate(divide="ignore", invalid="ignore"):
        return depth_mm**2 / (K[0, 0] * K[1, 1] * n_dot_r)