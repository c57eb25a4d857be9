"""The one orchestration entry point: a capture bundle and a target in, a judged plate out.

The CLI (``plate-inspect inspect``) and the service's job both call :func:`inspect`; neither
re-implements a stage. The stages themselves are chained in :mod:`pipeline.stages`; this module
writes what they found: ``details.json`` (:mod:`pipeline.judge.details`) and ``result.json``
(``plate-result/1``), or a result with verdict ``error`` when the capture cannot be measured.
"""

from __future__ import annotations

import json
import tempfile
import time
from collections.abc import Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from pipeline.artifacts import ARTIFACT_FILES, RESULT_FILE
from pipeline.formats import RESULT_FORMAT, PipelineError, ResultFile, ResultUncertainty
from pipeline.io import Capture, Target, load_capture, load_target
from pipeline.judge import uncertainty
from pipeline.judge.curvature import CurvatureResult
from pipeline.judge.details import (
    Details,
    UncertaintyDetails,
    fusion_details,
    refinement_details,
    region_details,
    segmentation_details,
)
from pipeline.judge.registration import Registration, pixel_in_target_frame
from pipeline.judge.target_geometry import target_area_mm2
from pipeline.judge.verdict import Judgement
from pipeline.lights.model import Lights
from pipeline.parallel import (
    default_workers,
    load_cached_kernels,
    set_process_policy,
    single_threaded_blas,
)
from pipeline.preprocess import Preprocessed
from pipeline.stages import (
    DISAGREEMENT_FRACTION,
    STAGES,
    InspectOptions,
    Measurement,
    ProgressCallback,
    StageClock,
    load_inputs,
    measure,
    preprocess_scene,
    start_capture_work,
)
from pipeline.surface import reconstruct

if TYPE_CHECKING:
    from pipeline.stations.early import EarlyStations

__all__ = [
    "AREA_WARNING_RATIO",
    "STAGES",
    "EarlyStations",
    "InspectOptions",
    "InspectionResult",
    "ProgressCallback",
    "inspect",
    "warm_up",
]


def __getattr__(name: str) -> Any:
    """``EarlyStations`` on first use: the stations' machinery (and scipy.optimize) stays out of the
    imports of a one-view inspection (the command line's start-up)."""
    if name == "EarlyStations":
        from pipeline.stations.early import EarlyStations

        return EarlyStations
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


#: A measured area (mask and edge band) under this share of the target's gets a warning in the result.
AREA_WARNING_RATIO = 0.9
#: Measured surface beyond the target's outline (left out of the judgement) over this share of the
#: target's area gets a warning: a plate cut to its outline within a few mm has far less beyond it
#: (2 mm all round a 3 m square: 0.3 %).
BEYOND_OUTLINE_WARNING_SHARE = 0.01


@dataclass(frozen=True)
class InspectionResult:
    """What :func:`inspect` produced.

    Attributes
    ----------
    document : dict
        The ``plate-result/1`` object, as written to ``out_dir/result.json``.
    out_dir : Path
    """

    document: dict[str, Any]
    out_dir: Path

    @property
    def verdict(self) -> str:
        return str(self.document["verdict"])


def inspect(
    capture: Capture | str | Path | Sequence[Capture | str | Path],
    target: Target | dict[str, Any] | str | Path,
    *,
    out_dir: str | Path,
    progress: ProgressCallback | None = None,
    options: InspectOptions | None = None,
    light_calibration: Lights | None = None,
    early: EarlyStations | None = None,
    frames: Mapping[str, np.ndarray] | None = None,
) -> InspectionResult:
    """Measure a plate and judge it against its CAD target.

    Parameters
    ----------
    capture : Capture or path, or a sequence of them
        A capture bundle (folder or .zip, ``plate-capture/1``) or one already loaded. Several bundles
        (two or more, in any order): the conveyor stations of one plate longer than the view, each
        with its ``station``, measured as one plate (:mod:`pipeline.stations`, docs/stations.md); a
        sequence of one is that one bundle.
    target : Target, dict or path
        The ``plate-target/1`` target.
    out_dir : path
        Where ``result.json`` and the artifacts are written (created if needed).
    progress : callable(stage, fraction), optional
        Called when each stage of :data:`STAGES` starts (fraction 0..1 of the
        stages done) and once with ``("done", 1.0)``.
    options : InspectOptions, optional
    light_calibration : pipeline.lights.model.Lights, optional
        The cell's measured lights (``plate-inspect calibrate-lights``, read with
        :func:`pipeline.io.load_light_calibration`). Applied to a capture whose lights are all
        given only as directions (nominal lights) and as many as its images; the result then
        carries a warning that says so. A capture that gives point lights keeps its own; a
        calibration with another count of lights is not applied (a warning says why).
    early : EarlyStations, optional
        Stations reconstructed while they were photographed (``station_done`` of
        :func:`pipeline.acquisition.acquire_stations`), made with this ``target``, ``options`` and
        ``light_calibration``: each station among ``capture`` that it reconstructed is taken from
        it (a failure there is this inspection's error, naming the station), the others are
        reconstructed here. Ignored for one bundle.
    frames : mapping of str to array, optional
        One bundle's images already in memory by their bundle path (``ps_00.png``: the frame an
        acquisition's camera gave, which the file holds losslessly), loaded from there instead of
        decoded again (:func:`pipeline.io.load_capture`). Ignored for several bundles and for a
        loaded Capture.

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
    clock = StageClock(progress)
    try:
        with single_threaded_blas():
            if isinstance(capture, (Capture, str, Path)):
                return _inspect(capture, target, out, clock, opts, light_calibration, frames)
            bundles = list(capture)
            if not bundles:
                raise ValueError("capture: expected at least one capture bundle, got none")
            if len(bundles) == 1:
                return _inspect(bundles[0], target, out, clock, opts, light_calibration, frames)
            if early is not None and not early.matches(target, opts, light_calibration):
                raise ValueError(
                    "early: its stations were reconstructed with another target, options or light "
                    "calibration than this inspection's"
                )
            return _inspect_stations(bundles, target, out, clock, opts, light_calibration, early)
    except PipelineError as err:
        # a capture that cannot be measured still leaves a result that says why
        _write_error_result(out, capture, target, err, clock)
        raise


def _inspect(
    capture: Capture | str | Path,
    target: Target | dict[str, Any] | str | Path,
    out: Path,
    clock: StageClock,
    opts: InspectOptions,
    light_calibration: Lights | None,
    frames: Mapping[str, np.ndarray] | None = None,
) -> InspectionResult:
    """:func:`inspect` inside its BLAS limit and error handling: every stage, then the two documents."""
    warnings: list[str] = []
    cap, tgt = load_inputs(capture, target, light_calibration, warnings, clock, opts, frames)
    # Work that does not need the main line's next result runs beside it. What needs the capture
    # only (the pixel rays, the sensor noise) beside the preprocessing; the stereo pair needs only
    # the plate mask (matched while the normals are estimated); curvature and the pixel areas run
    # beside the registration; the artifacts (image encoding and file writing release the GIL) as
    # soon as they are known.
    # numba's parallel kernels (normals, depth) run on this thread only: never two at once.
    with ThreadPoolExecutor(max_workers=opts.workers or default_workers()) as pool:
        started = start_capture_work(cap, pool)
        scene = preprocess_scene(cap, opts, clock, pool, frames)
        m = measure(cap, tgt, scene, opts, out, pool, clock, started)
    details = _details(m, scene.pre, tgt, near_field=cap.lights.any_point)
    warnings += _warnings(m.surface, tgt, details)
    warnings += _capability_warnings(m, cap, tgt)
    (out / ARTIFACT_FILES["details"]).write_text(details.to_json())
    clock.end("artifacts")
    doc = _result_document(cap, tgt, m, warnings, clock)
    (out / RESULT_FILE).write_text(json.dumps(doc, indent=2) + "\n")
    if clock.progress is not None:
        clock.progress("done", 1.0)
    return InspectionResult(document=doc, out_dir=out)


def _inspect_stations(
    captures: list[Capture | str | Path],
    target: Target | dict[str, Any] | str | Path,
    out: Path,
    clock: StageClock,
    opts: InspectOptions,
    light_calibration: Lights | None,
    early: EarlyStations | None,
) -> InspectionResult:
    """:func:`inspect` of a plate at conveyor stations (:mod:`pipeline.stations`)."""
    from pipeline.stations import measure_stations, stitched_details

    plate, tgt = measure_stations(
        captures,
        target,
        out,
        clock,
        opts,
        light_calibration,
        precomputed=None if early is None else early.result,
    )
    details = stitched_details(plate, tgt)
    warnings = list(plate.warnings)
    ratio = details.segmentation.area_ratio
    if ratio is not None and ratio < AREA_WARNING_RATIO:
        warnings.append(
            f"the measured area is {100 * ratio:.0f} % of the target's: openings, a plate partly out of "
            "view, or areas no station measured were not measured"
        )
    warnings += _outline_warning(details, tgt)
    if not plate.uncertainty.capable(tgt.tolerance_mm):
        warnings.append(
            f"the measurement is not capable for this tolerance: its expanded uncertainty (k = 2) is "
            f"{plate.uncertainty.deviation_mm:.2f} mm, tolerance / U = "
            f"{tgt.tolerance_mm / plate.uncertainty.deviation_mm:.1f} < {uncertainty.CAPABLE_RATIO:g}; "
            "the verdict stands by simple acceptance (details.json: uncertainty, stations)"
        )
    (out / ARTIFACT_FILES["details"]).write_text(details.to_json())
    clock.end("artifacts")
    doc = _document(
        plate.plate_id,
        tgt,
        plate.pose,
        plate.curv,
        plate.judgement,
        plate.uncertainty,
        warnings,
        clock,
    )
    (out / RESULT_FILE).write_text(json.dumps(doc, indent=2) + "\n")
    if clock.progress is not None:
        clock.progress("done", 1.0)
    return InspectionResult(document=doc, out_dir=out)


def _details(m: Measurement, pre: Preprocessed, tgt: Target, *, near_field: bool) -> Details:
    """details.json of a measurement."""
    surface, judgement, plate = m.surface, m.judgement, m.plate
    measured_area = float(np.sum(m.pixel_area[surface.mask & np.isfinite(m.pixel_area)]))
    return Details(
        T_cam_target=m.pose.T_cam_target.tolist(),
        registration_rms_mm=float(m.pose.rms_mm),
        principal_directions=np.asarray(m.curv.principal_directions).tolist(),
        defects=[
            region_details(
                d,
                pixel_in_target_frame(m.points, surface.mask, d.centroid_px, m.pose.T_cam_target),
            )
            for d in judgement.defects
        ],
        reasons=list(judgement.reasons),
        excluded_regions=[],  # none since the edge band is left out by geometry (kept for readers)
        segmentation=segmentation_details(
            plate.seg, target_area_mm2(tgt), plain=plate.plain, measured_area_mm2=measured_area
        ),
        normals_filled=int(surface.field.n_filled),
        normals_facing_away=surface.normals_facing_away,
        light_model="near-field" if near_field else "distant",
        near_field_iterations=surface.iterations if near_field else None,
        near_field_depth_steps_mm=list(surface.depth_steps_mm) if near_field else None,
        stereo_fusion=fusion_details(surface.fusion),
        light_refinement=refinement_details(surface.refinement),
        samples_saturated=pre.n_saturated,
        samples_shadowed=pre.n_shadowed,
        stereo_matched_pct=None
        if plate.matched_pct is None
        else round(float(plate.matched_pct), 2),
        metric_scale="stereo" if plate.prior is not None else "working_distance",
        uncertainty=UncertaintyDetails(
            k=uncertainty.COVERAGE_K,
            deviation_mm=round(m.uncertainty.deviation_mm, 4),
            radius_mm=_round(m.uncertainty.radius_mm, 3),
            components=m.uncertainty.components,
            edge_band_mm=m.edge_band_mm,
            beyond_outline_mm2=round(m.beyond_outline_mm2, 1),
        ),
    )


def _warnings(surface: reconstruct.Surface, tgt: Target, details: Details) -> list[str]:
    """What the operator should know about a result that still stands: lights refitted, photometric and
    stereo shapes that disagree beyond noise, a measured area well under the target's."""
    warnings = []
    if surface.refinement is not None:
        r = surface.refinement
        turn = max(c["turn_deg"] for c in r.corrections)
        what = (
            "point lights (LEDs near the plate) fitted from the images on the stereo geometry"
            if r.model == "point"
            else f"distant lights corrected by up to {turn:.2f} deg from the images on "
            "the stereo geometry"
        )
        warnings.append(
            f"the capture's lights did not fit the plate the stereo pair measured; measured with {what} "
            "(details.json: light_refinement)"
        )
    if surface.fusion is not None and surface.fusion.disagreement_mm > max(
        surface.fusion.noise_floor_mm, DISAGREEMENT_FRACTION * tgt.tolerance_mm
    ):
        warnings.append(
            f"the photometric and the stereo shapes disagreed by {surface.fusion.disagreement_mm:.1f} mm (95th "
            f"percentile, beyond the {max(surface.fusion.noise_floor_mm, DISAGREEMENT_FRACTION * tgt.tolerance_mm):.1f}"
            f" mm that noise explains): the stereo pair set the plate's overall shape; check the light positions"
        )
    ratio = details.segmentation.area_ratio
    if ratio is not None and ratio < AREA_WARNING_RATIO:
        warnings.append(
            f"the measured area is {100 * ratio:.0f} % of the target's: openings, a plate "
            f"partly out of view, or areas the stereo pair could not match were not measured (details.json: segmentation)"
        )
    return warnings + _outline_warning(details, tgt)


def _outline_warning(details: Details, tgt: Target) -> list[str]:
    """A warning when much of the measured surface lay beyond the target's outline (not judged)."""
    beyond = 0.0 if details.uncertainty is None else details.uncertainty.beyond_outline_mm2
    target_area = target_area_mm2(tgt)
    if beyond <= BEYOND_OUTLINE_WARNING_SHARE * target_area:
        return []
    return [
        f"{beyond / 1e6:.3f} m^2 of the measured surface ({100 * beyond / target_area:.1f} % of the "
        "target's area) lay beyond the target's outline and was not judged: a plate larger than its "
        "target, or its surroundings measured as plate (details.json: uncertainty.beyond_outline_mm2)"
    ]


def _capability_warnings(m: Measurement, cap: Capture, tgt: Target) -> list[str]:
    """The decision rule's word (docs/uncertainty.md): the verdict stands by simple acceptance, but a
    tolerance under :data:`pipeline.judge.uncertainty.CAPABLE_RATIO` expanded uncertainties is said, with why."""
    u = m.uncertainty
    if u.capable(tgt.tolerance_mm):
        return []
    c = u.components
    why = []
    if c["photometric_mm"] >= c["correction_mm"]:
        lights = cap.n_lights
        reasons = []
        if lights <= 4:
            reasons.append(f"only {lights} lights")
        footprint = float(np.nanmedian(m.points[..., 2])) / float(cap.rig.left.K[0, 0])
        if footprint > 3.5:
            reasons.append(f"{footprint:.1f} mm per pixel (far or coarse camera)")
        if not reasons:
            reasons.append("noisy or glossy photometric images")
        why.append("the photometric normals: " + ", ".join(reasons))
    else:
        why.append("the stereo pair's correction of the shape (its noise over the plate)")
    ratio = tgt.tolerance_mm / u.deviation_mm
    return [
        f"the measurement is not capable for this tolerance: its expanded uncertainty (k = 2) is "
        f"{u.deviation_mm:.2f} mm, tolerance / U = {ratio:.1f} < "
        f"{uncertainty.CAPABLE_RATIO:g}; the verdict stands by simple acceptance (ISO 14253-1, "
        f"shared risk) but a plate near the tolerance may be judged either way. Mostly from "
        + "; ".join(why)
    ]


def _result_document(
    cap: Capture, tgt: Target, m: Measurement, warnings: list[str], clock: StageClock
) -> dict[str, Any]:
    """The ``plate-result/1`` document of a measured plate (``warnings`` only when there are some)."""
    return _document(cap.plate_id, tgt, m.pose, m.curv, m.judgement, m.uncertainty, warnings, clock)


def _document(
    plate_id: str,
    tgt: Target,
    pose: Registration,
    curv: CurvatureResult,
    judgement: Judgement,
    qualified: uncertainty.Uncertainty,
    warnings: list[str],
    clock: StageClock,
) -> dict[str, Any]:
    """The ``plate-result/1`` document of a judged plate."""
    # the registration fits the target's shape radius-free on its way (= registration.fitted_target_radius)
    fitted_radius = pose.fitted_radius_mm
    target_radius = tgt.radius_mm if tgt.shape in ("cylinder", "sphere") else None
    radius_error = (
        100.0 * (fitted_radius - target_radius) / target_radius
        if fitted_radius is not None and target_radius is not None
        else None
    )
    timings = dict(clock.timings)
    timings["total"] = clock.total()
    return ResultFile(
        format=RESULT_FORMAT,
        plate_id=plate_id,
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
        uncertainty=ResultUncertainty(
            k=uncertainty.COVERAGE_K,
            radius_mm=_round(qualified.radius_mm, 2),
            deviation_mm=round(qualified.deviation_mm, 3),
        ),
        timings_s=timings,
        artifacts=dict(ARTIFACT_FILES),
    ).model_dump(mode="json", exclude=set() if warnings else {"warnings"})


def warm_up(*, full: bool = False) -> float:
    """Load the compiled kernels and start the thread pools before the first real inspection.

    The numba kernels are compiled once per installation and cached on disk (``scripts/setup.sh``
    compiles them with ``full=True``), but each process loads them (and OpenMP starts its threads)
    on their first call: time that would otherwise land in the first inspection's timings (README:
    *Command line*). This runs one small simulated inspection (160x128, 12 lights, stereo: every
    kernel of the usual path, the robust estimator's specular stage included, which runs on every
    plate; the same 25 kernels as at 320x256, in 0.4 s instead of 0.6) in a temporary folder: a
    matte plate with exact lights, so that the light refinement (pure numpy, nothing to load) does
    not run. ``full`` adds a plate under near-field LEDs over a lit floor with a cut-out (the
    near-field and segmentation kernels), for the install-time compilation. Returns the run time,
    seconds.
    """
    from pipeline.simulate import (
        CaptureSpec,
        Cutout,
        Floor,
        PlateSpec,
        rail_supports,
        simulate_capture,
    )

    scenes = [(PlateSpec(), CaptureSpec(width=160, height=128))]
    if full:
        floor = Floor(gap_mm=400.0, supports=rail_supports((3000.0, 3000.0), 400.0, 3))
        scenes.append(
            (
                PlateSpec(floor=floor, cutouts=(Cutout.circle(400.0, -300.0, 300.0),)),
                CaptureSpec(width=320, height=256, near_field_mm=2800.0, led_mu=1.0),
            )
        )
    t = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="plate-inspect-warm-up-") as tmp:
        for i, (plate, capture) in enumerate(scenes):
            bundle = simulate_capture(
                Path(tmp) / f"capture{i}", plate=plate, capture=capture, seed=0
            )
            inspect(bundle, bundle / "target.json", out_dir=Path(tmp) / f"out{i}")
    return time.perf_counter() - t


def _write_error_result(
    out: Path,
    capture: Capture | str | Path | Sequence[Capture | str | Path],
    target: Target | dict[str, Any] | str | Path,
    err: Exception,
    clock: StageClock,
) -> None:
    """Write a ``plate-result/1`` with verdict ``error`` saying why the capture could not be measured."""
    if not isinstance(capture, (Capture, str, Path)):
        capture = next(iter(capture), "unknown")
    plate_id = capture.plate_id if isinstance(capture, Capture) else None
    if plate_id is None and not isinstance(capture, Capture):
        try:
            plate_id = load_capture(capture).plate_id
        except Exception:
            plate_id = "unknown"
    try:
        tolerance = (target if isinstance(target, Target) else load_target(target)).tolerance_mm
    except Exception:
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
    ).model_dump(mode="json", exclude={"warnings", "uncertainty"})
    (out / RESULT_FILE).write_text(json.dumps(doc, indent=2) + "\n")


def _round(value: float | None, digits: int) -> float | None:
    return None if value is None else round(float(value), digits)


# A process that imports the entry point inspects: its process policy is set (a caller without the
# entry points' start-up gets the same threads and heap) and the compiled kernels are loaded now, at its
# start, so that not even its first inspection loads them (pipeline.parallel.load_cached_kernels).
set_process_policy()
load_cached_kernels()
