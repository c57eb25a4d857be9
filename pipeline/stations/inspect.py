"""One plate measured from its conveyor stations: each reconstructed, all registered, one judgement.

Called by :func:`pipeline.run.inspect` when it is given several bundles. Each station goes through the
stages of one view (:func:`pipeline.stages.load_inputs`, :func:`~pipeline.stages.preprocess_scene`,
:func:`~pipeline.stages.reconstruct_view`); the stations are registered to one another
(:mod:`.register`) and resampled onto one grid (:mod:`.mosaic`); the whole plate is then registered to
its target, its deviation judged, its curvature and uncertainty found and its artifacts written as for
one view. The stations' frames, travels and overlaps go into details.json (``stations``).
"""

from __future__ import annotations

import math
import os
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from pipeline import artifacts
from pipeline.artifacts import ARTIFACT_FILES
from pipeline.io import Capture, Target, load_capture, load_target
from pipeline.judge import (
    curvature,
    registration,
    target_geometry,
    uncertainty,
    verdict,
)
from pipeline.judge.details import (
    BrightnessSegmentationDetails,
    Details,
    StationDetails,
    StitchDetails,
    UncertaintyDetails,
    fusion_details,
    refinement_details,
    region_details,
)
from pipeline.lights.model import Lights
from pipeline.parallel import Deferred, default_workers, finish
from pipeline.solvers import percentile
from pipeline.stages import (
    DISAGREEMENT_FRACTION,
    EDGE_BAND_PX,
    STAGES,
    InspectOptions,
    ProgressCallback,
    StageClock,
    edge_band,
    judged_deviation,
    load_inputs,
    preprocess_scene,
    reconstruct_view,
    start_capture_work,
    uncertainty_inputs,
    write_deviation,
    write_target,
)
from pipeline.stations.mosaic import Mosaic, build_mosaic
from pipeline.stations.plan import StationRef, plan_stations
from pipeline.stations.register import StationPoses, StationView, register_stations


@dataclass(frozen=True)
class StationResult:
    """One station reconstructed (the stages of one view, nothing judged): its view for the registration
    and what its uncertainty and details need. :func:`measure_stations` makes it, or takes one made
    already by :func:`reconstruct_station` (:class:`pipeline.stations.EarlyStations`: while the conveyor
    moves on to the next station)."""

    ref: StationRef
    view: StationView
    #: Its points' own uncertainty (the radius's needs the whole plate's radius, found later).
    qualified: uncertainty.PointUncertainty
    matched_pct: float | None
    details: dict[str, Any]
    warnings: list[str]
    light_model: str
    normals_filled: int
    normals_facing_away: int
    saturated: int
    shadowed: int
    metric_scale: str
    #: Seconds of each stage of its view (``load`` .. ``depth``, as :class:`pipeline.stages.StageClock`).
    timings: dict[str, float]


@dataclass(frozen=True)
class StitchedPlate:
    """The plate measured from its stations, judged (what the documents are written from)."""

    plate_id: str
    mosaic: Mosaic
    poses: StationPoses
    pose: registration.Registration
    judgement: verdict.Judgement
    curv: curvature.CurvatureResult
    uncertainty: uncertainty.Uncertainty
    pixel_area: np.ndarray
    registration_sd_mm: list[float]
    stations: list[StationResult]
    edge_band_mm: float
    warnings: list[str]
    #: Measured surface beyond the target's outline, left out of the judgement, mm^2.
    beyond_outline_mm2: float = 0.0


#: The station reconstructed already for a planned station (its reference), or None: reconstruct it
#: now. Raises what its reconstruction raised.
Precomputed = Callable[[StationRef], "StationResult | None"]


def measure_stations(
    captures: Sequence[Capture | str | os.PathLike[str]],
    target: Target | dict[str, Any] | str | Path,
    out: Path,
    clock: StageClock,
    opts: InspectOptions,
    light_calibration: Lights | None,
    *,
    precomputed: Precomputed | None = None,
) -> tuple[StitchedPlate, Target]:
    """Every stage of a plate at stations but the documents (details.json, result.json).

    ``precomputed``: stations reconstructed already (with the same target, options and light
    calibration: :class:`pipeline.stations.EarlyStations`), each taken in place of its
    reconstruction; their stage timings add to ``clock``'s as a fresh station's do.

    Raises
    ------
    pipeline.formats.InputError
        A bad bundle or a bad set of stations (named by bundle and field).
    pipeline.formats.CaptureError
        A station that cannot be measured or registered (named).
    """
    clock.begin("load")
    refs = plan_stations(captures)
    tgt = target if isinstance(target, Target) else load_target(target)
    clock.end("load")
    # one station at a time: the numba kernels take every core (decoding the next station beside them
    # makes each parallel region wait for the busy core: measured slower)
    stations = []
    for k, ref in enumerate(refs):
        report = station_progress(clock.progress, k, len(refs))
        station = None if precomputed is None else precomputed(ref)
        if station is None:
            station = reconstruct_station(ref, tgt, opts, light_calibration, progress=report)
        elif report is not None:
            report("depth", 1.0)
        for stage, seconds in station.timings.items():
            clock.timings[stage] = round(clock.timings.get(stage, 0.0) + seconds, 4)
        stations.append(station)
    views = [s.view for s in stations]
    t = time.perf_counter()
    poses = register_stations(views, seam_limit_mm=DISAGREEMENT_FRACTION * tgt.tolerance_mm)
    clock.timings["stations_registration"] = round(time.perf_counter() - t, 4)
    t = time.perf_counter()
    mosaic = build_mosaic(views, poses.poses, poses.travel_mm)
    clock.timings["stations_mosaic"] = round(time.perf_counter() - t, 4)
    plate = _judge(stations, poses, mosaic, tgt, out, opts, clock)
    return plate, tgt


def station_progress(progress: ProgressCallback | None, k: int, n: int) -> ProgressCallback | None:
    """The progress of station ``k`` (0-based) of ``n`` as the whole plate's: each stage of its view
    reported as ``"station <k+1>/<n>: <stage>"``, its fraction within the share of the plate's
    progress that :data:`pipeline.stages.STAGES` gives the stages of a view (``load`` .. ``depth``),
    split evenly among the stations. None without ``progress``."""
    if progress is None:
        return None
    view_stages = STAGES.index("curvature")
    share = view_stages / len(STAGES)

    def report(stage: str, fraction: float) -> None:
        within = STAGES.index(stage) / view_stages if stage in STAGES[:view_stages] else 1.0
        progress(f"station {k + 1}/{n}: {stage}", share * (k + within) / n)

    return report


def reconstruct_station(
    ref: StationRef,
    tgt: Target,
    opts: InspectOptions,
    light_calibration: Lights | None,
    *,
    progress: ProgressCallback | None = None,
) -> StationResult:
    """One station (``ref``; decoded here unless loaded already) through the stages of one view
    (:func:`pipeline.stages.load_inputs` .. :func:`~pipeline.stages.reconstruct_view`), timed by a
    clock of its own (``StationResult.timings``; the decoding counts in *load*) that reports to
    ``progress``.

    Its parallel numba kernels run on the calling thread: no other thread may run one meanwhile.
    """
    own = StageClock(progress)
    t = time.perf_counter()
    capture = ref.source if isinstance(ref.source, Capture) else load_capture(ref.source)
    decode_s = time.perf_counter() - t
    warnings: list[str] = []
    cap, _ = load_inputs(capture, tgt, light_calibration, warnings, own, opts)
    own.timings["load"] = round(own.timings["load"] + decode_s, 4)
    with ThreadPoolExecutor(max_workers=opts.workers or default_workers()) as pool:
        started = start_capture_work(cap, pool)
        scene = preprocess_scene(cap, opts, own)
        view, _ = reconstruct_view(cap, tgt, scene, opts, pool, own, started)
    surface = view.surface
    judged = surface.mask & ~edge_band(surface.mask)
    qualified = uncertainty.propagate_points(uncertainty_inputs(cap, scene.pre, view, judged))
    index = ref.station.index
    station_view = StationView(
        index=index,
        label=ref.label,
        points=view.points,
        mask=surface.mask & np.isfinite(view.points[..., 2]),
        albedo=surface.field.albedo,
        normals=surface.field.normals,
        K=cap.rig.left.K,
        encoder_mm=float(ref.station.travel_mm),
        direction=ref.direction,
    )
    warnings += _station_warnings(index, surface, tgt)
    return StationResult(
        ref=ref,
        view=station_view,
        qualified=qualified,
        matched_pct=view.plate.matched_pct,
        details={
            "stereo_fusion": fusion_details(surface.fusion),
            "light_refinement": refinement_details(surface.refinement),
        },
        warnings=[f"station {index}: {w}" for w in warnings],
        light_model="near-field" if cap.lights.any_point else "distant",
        normals_filled=int(surface.field.n_filled),
        normals_facing_away=surface.normals_facing_away,
        saturated=scene.pre.n_saturated,
        shadowed=scene.pre.n_shadowed,
        metric_scale="stereo" if view.plate.prior is not None else "working_distance",
        timings=dict(own.timings),
    )


def _station_warnings(index: int, surface: Any, tgt: Target) -> list[str]:
    """What the operator should know of one station (the lights refitted, shapes that disagree)."""
    out = []
    if surface.refinement is not None:
        out.append(
            "the capture's lights did not fit the plate the stereo pair measured and were refitted "
            f"(details.json: stations.stations[{index}].light_refinement)"
        )
    fused = surface.fusion
    if fused is not None and fused.disagreement_mm > max(
        fused.noise_floor_mm, DISAGREEMENT_FRACTION * tgt.tolerance_mm
    ):
        out.append(
            f"the photometric and the stereo shapes disagreed by {fused.disagreement_mm:.1f} mm: the stereo "
            "pair set the plate's overall shape; check the light positions"
        )
    return out


def _judge(
    stations: list[StationResult],
    poses: StationPoses,
    mosaic: Mosaic,
    tgt: Target,
    out: Path,
    opts: InspectOptions,
    clock: StageClock,
) -> StitchedPlate:
    """The stitched plate registered to its target, judged, qualified; its artifacts written."""
    points, mask = mosaic.points, mosaic.mask
    clock.begin("curvature")
    with ThreadPoolExecutor(max_workers=opts.workers or default_workers()) as pool:
        # beside the registration, as for one view: the curvature, the grid's normals and areas
        curvature_job = pool.submit(_curvature, points, mask)
        normals_job = pool.submit(_grid_normals, points, mosaic.cell_mm)
        writes = [
            Deferred(pool, artifacts.save_depth, out / ARTIFACT_FILES["depth"], points[..., 2])
        ]
        clock.begin("deviation")
        pose = registration.register_to_target(points, mask, tgt)
        band = edge_band(mask)
        beyond, _, band, judged, dev = judged_deviation(points, mask, band, mask & ~band, tgt, pose)
        qualified, reg_sd = _qualify(stations, poses, mosaic, pose, judged, tgt)
        normals, area = normals_job.result()
        has_normal = mask & np.isfinite(normals).all(axis=-1)
        writes.append(
            Deferred(
                pool,
                artifacts.write_normals_png,
                out / ARTIFACT_FILES["normals"],
                normals,
                has_normal,
            )
        )
        judgement = verdict.judge(
            dev, judged, tgt.tolerance_mm, pixel_area_mm2=area, uncertainty_mm=qualified.map_mm
        )
        clock.end("deviation")
        clock.begin("artifacts")
        writes += _write_artifacts(pool, out, mosaic, dev, qualified.map_mm, judged, tgt, pose)
        finish(writes)  # the writes no worker has started yet are made here, instead of waiting
        curv, clock.timings["curvature"] = curvature_job.result()
    return StitchedPlate(
        plate_id=stations[0].ref.plate_id,
        mosaic=mosaic,
        poses=poses,
        pose=pose,
        judgement=judgement,
        curv=curv,
        uncertainty=qualified,
        pixel_area=area,
        registration_sd_mm=reg_sd,
        stations=stations,
        edge_band_mm=round(EDGE_BAND_PX * mosaic.cell_mm, 1),
        beyond_outline_mm2=float(np.nansum(area[beyond])),
        warnings=[w for s in stations for w in s.warnings],
    )


def _curvature(points: np.ndarray, mask: np.ndarray) -> tuple[curvature.CurvatureResult, float]:
    """Principal curvatures of the stitched plate and their run time (s)."""
    t = time.perf_counter()
    curv = curvature.principal_curvatures(points, mask)
    return curv, round(time.perf_counter() - t, 4)


def _write_artifacts(
    pool: ThreadPoolExecutor,
    out: Path,
    mosaic: Mosaic,
    dev: np.ndarray,
    u_map: np.ndarray,
    judged: np.ndarray,
    tgt: Target,
    pose: registration.Registration,
) -> list[Deferred[Any]]:
    """Submit the writes of surface.ply, deviation.png, the uncertainty's files and target.ply."""
    points, mask, tol = mosaic.points, mosaic.mask, tgt.tolerance_mm
    return [
        *write_deviation(pool, out, points, mask, dev, tol),
        Deferred(pool, artifacts.write_uncertainty, out, u_map, judged, tolerance_mm=tol),
        write_target(pool, out, tgt, pose),
    ]


def _grid_normals(points: np.ndarray, cell_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """Unit normals (towards the cameras, -z; NaN where a neighbour is missing) and the area of each
    cell (mm^2) of a grid of points (central differences; ``cell_mm`` squared where a neighbour is
    missing)."""
    p = points.astype(np.float32)
    dx = np.full_like(p, np.nan)
    dy = np.full_like(p, np.nan)
    dx[:, 1:-1] = 0.5 * (p[:, 2:] - p[:, :-2])
    dy[1:-1] = 0.5 * (p[2:] - p[:-2])
    cross = np.empty_like(p)
    cross[..., 0] = dx[..., 1] * dy[..., 2] - dx[..., 2] * dy[..., 1]
    cross[..., 1] = dx[..., 2] * dy[..., 0] - dx[..., 0] * dy[..., 2]
    cross[..., 2] = dx[..., 0] * dy[..., 1] - dx[..., 1] * dy[..., 0]
    length = np.sqrt(np.einsum("hwc,hwc->hw", cross, cross))
    area = length.astype(np.float64)
    measured = np.isfinite(p[..., 2])
    area = np.where(np.isfinite(area), area, np.where(measured, cell_mm**2, np.nan))
    with np.errstate(invalid="ignore", divide="ignore"):
        n = cross / length[..., None]
    n = np.where(n[..., 2:3] > 0, -n, n)
    return n.astype(np.float32), area


def _qualify(
    stations: list[StationResult],
    poses: StationPoses,
    mosaic: Mosaic,
    pose: registration.Registration,
    judged: np.ndarray,
    tgt: Target,
) -> tuple[uncertainty.Uncertainty, list[float]]:
    """The stitched plate's expanded uncertainty: each station's own (:func:`pipeline.judge.uncertainty.with_radius`
    at the plate's fitted radius) resampled onto the grid, with each station's registration added.

    A station's registration adds ``u_reg``: the RMS surface distance of its overlaps with its neighbours
    over sqrt(2) (the distance holds both stations' errors; their own noise is counted again, on the safe
    side). The radius's ``U`` adds the registration's share of the plate's sagitta across its bend to the
    stations' own (their RMS; not averaged down: the scale and the bend are common to them all).
    """
    radius = pose.fitted_radius_mm
    own, u_reg = [], []
    for s in stations:
        k = s.view.index
        to_station = np.linalg.inv(mosaic.frame @ poses.poses[k])
        direction = to_station[:3, :3] @ np.asarray(pose.T_cam_target)[:3, 0]
        own.append(
            uncertainty.with_radius(
                s.qualified,
                radius_mm=None if radius is None else float(radius),
                curved_direction=direction,
            )
        )
        seams = [
            o.rms_mm
            for o in poses.overlaps
            if k in o.stations and o.stations[1] == o.stations[0] + 1
        ]
        u_reg.append(float(max(seams)) / math.sqrt(2.0))
    u_own = mosaic.resample([u.map_mm for u in own], squared=True)
    u_seam = mosaic.blend_constants([uncertainty.COVERAGE_K * r for r in u_reg])
    u_map = np.where(judged, np.sqrt(u_own**2 + u_seam**2), np.nan).astype(np.float32)
    u_map = np.where(np.isfinite(u_map), u_map, np.nan).astype(np.float32)
    finite = judged & np.isfinite(u_map)
    u95 = float(percentile(u_map[finite], 95)) if finite.any() else math.nan
    radius_u = None
    if radius is not None and math.isfinite(radius):
        parts = [u.radius_mm for u in own if u.radius_mm is not None]
        chord = float(min(tgt.size_mm)) if tgt.shape == "sphere" else float(tgt.size_mm[0])
        half = min(chord / 2.0, 0.999 * radius)
        sagitta = radius - math.sqrt(radius**2 - half**2)
        reg_rel = max(u_reg) / sagitta if sagitta > 0 else 0.0
        own_u = math.sqrt(float(np.mean(np.square(parts)))) if parts else 0.0
        radius_u = math.sqrt(own_u**2 + (uncertainty.COVERAGE_K * radius * reg_rel) ** 2)
    components = dict(own[0].components)
    for key in ("photometric_mm", "correction_mm"):
        components[key] = round(max(u.components[key] for u in own), 4)
    components["stations_registration_mm"] = round(max(u_reg), 4)
    return (
        uncertainty.Uncertainty(
            map_mm=u_map, deviation_mm=u95, radius_mm=radius_u, components=components
        ),
        u_reg,
    )


def _segmentation(
    plate: StitchedPlate, target_area_mm2: float, measured_area_mm2: float
) -> BrightnessSegmentationDetails:
    """The stitched plate's measured area against its target's (each station told its plate from its
    surroundings as one view does)."""
    return BrightnessSegmentationDetails(
        method="stations",
        plate_area_mm2=round(measured_area_mm2, 0),
        target_area_mm2=round(target_area_mm2, 0),
        area_ratio=round(measured_area_mm2 / target_area_mm2, 4),
        reasons=[
            f"the plate stitched from {len(plate.stations)} stations, each told from its surroundings "
            "as one view is; the area is the stitched surface's"
        ],
    )


def station_footprint(
    view: StationView, T_plate_station: np.ndarray, T_cam_target: np.ndarray
) -> list[list[float]] | None:
    """Where a station looked, on the target: the four corners of its image frame (the first pixel's,
    then round the image: along its first row, ...) at the depth of its plate (the median z of its measured points), moved by
    ``T_plate_station`` ((4, 4), its camera frame into the plate frame) into the plate frame and by
    the inverse of ``T_cam_target`` ((4, 4), target frame into the plate frame) into the target's;
    (4, 2) x, y, mm, rounded to 0.1 mm. None when the station measured no point."""
    z = view.points[..., 2][view.mask]
    if z.size == 0:
        return None
    height, width = view.mask.shape
    corners = np.array(
        [[-0.5, -0.5], [width - 0.5, -0.5], [width - 0.5, height - 0.5], [-0.5, height - 0.5]]
    )
    rays = np.linalg.solve(view.K, np.column_stack([corners, np.ones(4)]).T).T
    in_station = rays / rays[:, 2:3] * float(np.median(z))
    in_plate = in_station @ T_plate_station[:3, :3].T + T_plate_station[:3, 3]
    T = np.asarray(T_cam_target, dtype=np.float64)
    in_target = (in_plate - T[:3, 3]) @ T[:3, :3]
    return [[float(x), float(y)] for x, y in np.round(in_target[:, :2], 1)]


def stitched_details(plate: StitchedPlate, tgt: Target) -> Details:
    """details.json of a plate measured at stations (``stations`` says how it was stitched)."""
    m, judgement, first = plate.mosaic, plate.judgement, plate.stations[0]
    measured_area = float(np.sum(plate.pixel_area[m.mask & np.isfinite(plate.pixel_area)]))
    stations = [
        StationDetails(
            index=s.view.index,
            bundle=s.ref.label,
            T_plate_station=(m.frame @ plate.poses.poses[s.view.index]).round(6).tolist(),
            travel_encoder_mm=round(s.view.encoder_mm, 3),
            travel_mm=round(plate.poses.travel_mm[s.view.index], 3),
            stereo_matched_pct=None if s.matched_pct is None else round(float(s.matched_pct), 2),
            registration_sd_mm=round(plate.registration_sd_mm[s.view.index], 4),
            stereo_fusion=s.details["stereo_fusion"],
            light_refinement=s.details["light_refinement"],
            footprint_mm=station_footprint(
                s.view, m.frame @ plate.poses.poses[s.view.index], plate.pose.T_cam_target
            ),
        )
        for s in plate.stations
    ]
    overlaps = list(plate.poses.overlaps)
    matched = [s.matched_pct for s in plate.stations if s.matched_pct is not None]
    return Details(
        T_cam_target=plate.pose.T_cam_target.tolist(),
        registration_rms_mm=float(plate.pose.rms_mm),
        principal_directions=np.asarray(plate.curv.principal_directions).tolist(),
        defects=[
            region_details(
                d,
                registration.pixel_in_target_frame(
                    m.points, m.mask, d.centroid_px, plate.pose.T_cam_target
                ),
            )
            for d in judgement.defects
        ],
        reasons=list(judgement.reasons),
        excluded_regions=[],
        segmentation=_segmentation(plate, target_geometry.target_area_mm2(tgt), measured_area),
        normals_filled=sum(s.normals_filled for s in plate.stations),
        normals_facing_away=sum(s.normals_facing_away for s in plate.stations),
        light_model=first.light_model,
        near_field_iterations=None,
        near_field_depth_steps_mm=None,
        stereo_fusion=stations[0].stereo_fusion,
        light_refinement=stations[0].light_refinement,
        samples_saturated=sum(s.saturated for s in plate.stations),
        samples_shadowed=sum(s.shadowed for s in plate.stations),
        stereo_matched_pct=round(float(min(matched)), 2) if matched else None,
        metric_scale=first.metric_scale,
        uncertainty=UncertaintyDetails(
            k=uncertainty.COVERAGE_K,
            deviation_mm=round(plate.uncertainty.deviation_mm, 4),
            radius_mm=None
            if plate.uncertainty.radius_mm is None
            else round(plate.uncertainty.radius_mm, 3),
            components=plate.uncertainty.components,
            edge_band_mm=plate.edge_band_mm,
            beyond_outline_mm2=round(plate.beyond_outline_mm2, 1),
        ),
        stations=StitchDetails(cell_mm=round(m.cell_mm, 3), stations=stations, overlaps=overlaps),
    )
