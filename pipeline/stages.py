"""The stages of one inspection, from the files to the judged plate, and the clock that times them.

:func:`pipeline.run.inspect` calls :func:`load_inputs`, :func:`preprocess_scene` and :func:`measure` in
that order, then writes details.json and result.json from the :class:`Measurement`. Each stage is a
module of the method (docs/method.md); this module only chains them, decides what runs beside the
main line, and times them.

Kept as one module (~720 lines): which stage waits for which, and what runs beside the main line,
are read together; the stages' own work lives in their modules.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable, Mapping
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

import cv2
import numpy as np

from pipeline import artifacts, segmentation
from pipeline.artifacts import ARTIFACT_FILES
from pipeline.camera import points_on_rays
from pipeline.formats import CaptureError
from pipeline.io import Capture, Target, load_capture, load_target
from pipeline.judge import (
    area,
    curvature,
    deviation,
    outline,
    registration,
    target_geometry,
    uncertainty,
    verdict,
)
from pipeline.lights.model import Lights
from pipeline.parallel import Deferred, finish, kernel_threads_spared
from pipeline.preprocess import (
    WORKING_CELL_MM,
    Preprocessed,
    bin_capture,
    plate_found,
    raw_noise_counts,
    undistorted,
    working_binning,
)
from pipeline.surface import fusion, normals, reconstruct, stereo

#: Stage names in the order they run; ``progress`` reports these.
STAGES = ("load", "preprocess", "normals", "stereo", "depth", "curvature", "deviation", "artifacts")

ProgressCallback = Callable[[str, float], None]

#: Without a working-distance hint the stereo pair is searched around this depth (mm):
#: with the default ``depth_margin`` of 1.0 that is 1750-7000 mm, the cell's whole range.
NOMINAL_DISTANCE_MM = 3500.0
#: The lights are refitted, and the result warns that the photometric and stereo shapes disagree, when the
#: disagreement (see :class:`pipeline.surface.fusion.Fusion`) exceeds both the noise floor and this fraction of the
#: tolerance.
DISAGREEMENT_FRACTION = 0.25
#: Pixels of the plate within this many pixels of its segmented outline or an opening (not the image's
#: frame) mix plate and surroundings: they are left out of the judgement by geometry, whatever their
#: deviation (the band's width in mm goes into details.json).
EDGE_BAND_PX = 3
#: The cell on the plate (mm) of the grid ``InspectOptions.stereo_weight`` was chosen on: 1224x1024, a
#: focal length of 900 px, the plate 3 m away. On a finer working grid the weight per pixel is scaled
#: by the square of the cells' ratio (:func:`stereo_weight_on_grid`).
STEREO_WEIGHT_CELL_MM = 3000.0 / 900.0


@dataclass(frozen=True)
class InspectOptions:
    """Knobs of the measurement; the defaults are the product's settings.

    Attributes
    ----------
    normals_method : {"robust", "lstsq"}
        Per-pixel photometric estimator (see :func:`pipeline.surface.normals.estimate_normals`).
    stereo_weight : float
        Weight of the stereo depth against the normal equations in the fusion
        (dimensionless, per pixel, log-depth units; on a working grid finer than
        :data:`STEREO_WEIGHT_CELL_MM` scaled to keep its wavelength in mm, see
        :func:`stereo_weight_on_grid`). The normals win above the
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
        hint that still brackets the plate changes nothing (see :func:`pipeline.surface.stereo.stereo_depth`).
    min_stereo_pct : float
        Below this share of the plate matched (percent), the stereo depth is not
        trusted (a plate outside the searched range gives a few wrong matches): the
        working distance sets the scale instead, or the capture is refused without one.
    stereo_max_width : int
        A stereo pair wider than this (px) is matched reduced by the smallest whole
        factor that fits (it bounds the matcher's time and memory). The working grid's
        pair is matched at full size up to a 2448-wide sensor that cannot be binned to its
        working cell (the head 4.2 m away): what the stereo pair can prove of the plate's
        bend, and so the fusion's correction and the uncertainty, stands on its resolution.
        Matched at half size there, a plate formed exactly read p95 0.089 mm (stereo noise
        4.5 mm a pixel) against 0.028 mm at full size (1.9 mm), and 3 lights reported U95
        only 1.4 times the 12 lights' (1.9 times at full size)
        (``benchmarks/bench_capable.py --size 2448x2048 --seeds 71 --cases "head 4.2 m"``); its
        cost, mostly beside the normals, is in docs/figures.md.
    depth_tol : float
        Relative residual at which the depth solve stops (``tol`` of
        :func:`pipeline.surface.integration.integrate_normals`). Measured on a simulated plate at
        2448x2048 against a solve to 1e-8: 1e-4 changes no depth by more than 1 um
        (1e-3: 20 um), in 4 iterations instead of 6 for 1e-6.
    workers : int or None
        Threads for the work that runs beside the main line (stereo, curvature, artifact
        writing) and for preprocessing; None: :func:`pipeline.parallel.default_workers`. The
        result does not depend on it.
    working_cell_mm : float or None
        The coarsest cell of the working grid on the plate, mm: a capture whose pixels see a finer
        footprint (at its working distance, or :data:`NOMINAL_DISTANCE_MM`) is binned on loading by
        the largest whole factor that keeps the cell within it, and measured on that grid (its
        artifacts too). None: the capture's own pixels. See
        :func:`pipeline.preprocess.working_binning`.
    """

    normals_method: str = "robust"
    stereo_weight: float = 1e-4
    depth_margin: float = 1.0
    min_stereo_pct: float = 20.0
    stereo_max_width: int = 2600
    depth_tol: float = 1e-4
    workers: int | None = None
    working_cell_mm: float | None = WORKING_CELL_MM


class StageClock:
    """Times the stages (``timings``, seconds, rounded to 0.1 ms) and reports progress.

    Parameters
    ----------
    progress : callable(stage, fraction) or None
        Called when each stage of :data:`STAGES` begins, with the fraction of the stages done.
    """

    def __init__(self, progress: ProgressCallback | None) -> None:
        self.progress = progress
        self.timings: dict[str, float] = {}
        self.start = time.perf_counter()
        self._t = self.start

    def begin(self, stage: str) -> None:
        """A stage of :data:`STAGES` begins: its timer starts and progress is reported."""
        self._t = time.perf_counter()
        if self.progress is not None:
            self.progress(stage, STAGES.index(stage) / len(STAGES))

    def end(self, stage: str) -> None:
        """The stage ends: its time since :meth:`begin` is recorded."""
        self.timings[stage] = round(time.perf_counter() - self._t, 4)

    def total(self) -> float:
        """Seconds since the clock was made."""
        return round(time.perf_counter() - self.start, 4)


@runtime_checkable
class FoldedFrames(Protocol):
    """A bundle's frames folded as an acquisition took them
    (:class:`pipeline.acquisition.streaming.StreamedFrames`): the inspection takes the binned capture
    and the undistorted images from them when they were folded for its capture (None: computed here)."""

    def capture(
        self, path: str | os.PathLike[str], *, cell_mm: float | None, distance_mm: float
    ) -> Capture | None: ...

    def undistorted(self, capture: Capture) -> tuple[np.ndarray, np.ndarray, bool] | None: ...


def _folded(frames: object) -> FoldedFrames | None:
    """``frames`` when they were folded as they were taken, else None."""
    return frames if isinstance(frames, FoldedFrames) else None


@dataclass(frozen=True)
class Scene:
    """What preprocessing found: the images, where the plate may be, and whether the scene is plain.

    ``candidates``: what may be plate, i.e. not dark (over a dark conveyor, the plate; over a lit floor,
    most of the image): the stereo pair is matched over it and, under distant lights, the normals are
    estimated over it. ``plain_outline``: a plate alone over a dark conveyor (the usual cell), whose
    brightness mask is all the stereo pair and the normals need (``region``).
    """

    pre: Preprocessed
    candidates: np.ndarray
    plain_outline: bool
    region: np.ndarray


@dataclass
class Plate:
    """The plate among its surroundings and its stereo prior (updated if the lights are refitted)."""

    mask: np.ndarray
    seg: segmentation.Segmentation | None
    prior: np.ndarray | None
    matched_pct: float | None
    depth_mm: np.ndarray | None
    depth_scale: int

    @property
    def plain(self) -> bool:
        """A plain scene's plate: its brightness mask, one sheet in the stereo depth (not segmented)."""
        return self.seg is None and self.depth_mm is not None


@dataclass(frozen=True)
class Measurement:
    """What the measurement stages gave, for the result and details.json."""

    surface: reconstruct.Surface
    plate: Plate
    pose: registration.Registration
    judgement: verdict.Judgement
    curv: curvature.CurvatureResult
    pixel_area: np.ndarray
    #: (H, W, 3) measured points, mm, left camera frame (NaN off the plate).
    points: np.ndarray
    uncertainty: uncertainty.Uncertainty
    #: Width of the edge band left out of the judgement, mm (median pixel footprint times EDGE_BAND_PX).
    edge_band_mm: float
    #: Measured surface beyond the target's outline, left out of the judgement, mm^2
    #: (:mod:`pipeline.judge.outline`).
    beyond_outline_mm2: float = 0.0


def load_inputs(
    capture: Capture | str | Path,
    target: Target | dict[str, Any] | str | Path,
    light_calibration: Lights | None,
    warnings: list[str],
    clock: StageClock,
    opts: InspectOptions,
    frames: Mapping[str, np.ndarray] | None = None,
) -> tuple[Capture, Target]:
    """Stage *load*: the capture (with ``light_calibration`` applied, see :func:`pipeline.run.inspect`) and the target.

    ``frames``: a bundle's images already in memory by their bundle path (see
    :func:`pipeline.io.load_capture`), taken from there instead of decoded from its files; frames
    folded as they were taken (:class:`FoldedFrames`) come from there already binned (the bundle's
    files are then read for their JSON and image headers only).

    The capture comes on the working grid of ``opts.working_cell_mm`` (binned, see
    :class:`InspectOptions`). A warning about the light calibration is appended to ``warnings``.
    CaptureError when the capture has neither a stereo pair nor a working distance (no metric scale).
    """
    clock.begin("load")
    cap: Capture | None = None
    if not isinstance(capture, Capture) and (streamed := _folded(frames)) is not None:
        cap = streamed.capture(
            capture, cell_mm=opts.working_cell_mm, distance_mm=NOMINAL_DISTANCE_MM
        )
    if cap is None:
        cap = capture if isinstance(capture, Capture) else load_capture(capture, frames=frames)
        factor = working_binning(cap, opts.working_cell_mm, NOMINAL_DISTANCE_MM)
        cap = bin_capture(cap, factor, workers=opts.workers)
    tgt = target if isinstance(target, Target) else load_target(target)
    cap = _apply_light_calibration(cap, light_calibration, warnings)
    if not cap.has_stereo and cap.working_distance_mm is None:
        raise CaptureError(
            f"{cap.source}: stereo, working_distance_mm: a metric result needs a stereo pair or a working distance"
        )
    clock.end("load")
    return cap, tgt


def preprocess_scene(
    cap: Capture,
    opts: InspectOptions,
    clock: StageClock,
    pool: ThreadPoolExecutor | None = None,
    frames: Mapping[str, np.ndarray] | None = None,
) -> Scene:
    """Stage *preprocess*: the images ready for the normals, and where the plate may be (see :class:`Scene`).
    With ``pool``, the candidates are found on it while the plate mask is (both need only the images'
    brightness). ``frames``: as for :func:`load_inputs` (images undistorted as they were taken are
    taken from there)."""
    clock.begin("preprocess")
    streamed = _folded(frames)
    folded = None if streamed is None else streamed.undistorted(cap)
    lit = undistorted(cap, workers=opts.workers, folded=folded)
    job = (
        pool.submit(segmentation.candidate_mask, lit.brightness, seen=lit.seen)
        if pool is not None and cap.has_stereo
        else None
    )
    pre = plate_found(lit)
    if job is not None:
        candidates = job.result()
    else:
        candidates = (
            segmentation.candidate_mask(_brightness(pre), seen=pre.seen)
            if cap.has_stereo
            else pre.mask
        )
    plain_outline = cap.has_stereo and segmentation.plain_outline(pre.mask, candidates)
    region = pre.mask if plain_outline else candidates
    clock.end("preprocess")
    return Scene(pre=pre, candidates=candidates, plain_outline=plain_outline, region=region)


@dataclass(frozen=True)
class View:
    """One view reconstructed (stages *normals* to *depth*): the metric surface and the plate it is of.

    Attributes
    ----------
    surface : reconstruct.Surface
    plate : Plate
    points : (H, W, 3) float64
        Measured points, mm, left camera frame (NaN off the plate).
    rays : (H, W, 3) float64
        The left camera's pixel rays ``K^-1 (u, v, 1)`` (undistorted grid).
    raw_noise : ((N,) float64, float or None)
        The sensor noise of the photometric images and of the dark frame, raw counts
        (:func:`pipeline.preprocess.raw_noise_counts`; measured beside the normals).
    """

    surface: reconstruct.Surface
    plate: Plate
    points: np.ndarray
    rays: np.ndarray
    raw_noise: tuple[np.ndarray, float | None]


@dataclass(frozen=True)
class CaptureWork:
    """A view's work that needs its capture only, started on the pool before the images are
    preprocessed (:func:`start_capture_work`): it then fills the preprocessing's serial steps (the
    plate mask, the candidates) instead of taking a core from the stereo pair and the normals.

    Attributes
    ----------
    rays : Future of (H, W, 3) float64
        The left camera's pixel rays, for the surface and the areas.
    raw_noise : Future of ((N,) float64, float or None)
        :func:`pipeline.preprocess.raw_noise_counts`, for the uncertainty.
    """

    rays: Future[np.ndarray]
    raw_noise: Future[tuple[np.ndarray, float | None]]


def start_capture_work(cap: Capture, pool: ThreadPoolExecutor) -> CaptureWork:
    """Submit :class:`CaptureWork` of ``cap`` to ``pool``."""
    return CaptureWork(
        rays=pool.submit(cap.rig.left.pixel_rays), raw_noise=pool.submit(raw_noise_counts, cap)
    )


def reconstruct_view(
    cap: Capture,
    tgt: Target,
    scene: Scene,
    opts: InspectOptions,
    pool: ThreadPoolExecutor,
    clock: StageClock,
    started: CaptureWork,
    *,
    normals_png: Path | None = None,
) -> tuple[View, list[Deferred[Any]]]:
    """Stages *normals*, *stereo* and *depth* of one view, work beside the main line on ``pool``.

    ``started``: the capture's work, submitted before the preprocessing (:func:`start_capture_work`).
    ``normals_png``: where normals.png is written (beside the depth solve), None: not written.
    Returns the view and the artifact writes under way.
    """
    pre, K = scene.pre, cap.rig.left.K
    stereo_job = pool.submit(_stereo_depth, cap, scene.region, opts) if cap.has_stereo else None
    field = None
    clock.begin("normals")
    if not cap.lights.any_point:
        # distant lights: the normals do not depend on the surface, estimated while stereo matches, on a
        # core fewer than the machine has: the stereo pair's chain (coarse pass, matching, refinement) is
        # the longer, and the main line waits for both
        with kernel_threads_spared(1 if stereo_job is not None else 0):
            field = normals.estimate_normals(
                pre.images,
                cap.light_dirs,
                scene.region,
                valid=pre.valid,
                method=opts.normals_method,
                camera_matrix=K,
            )
        clock.end("normals")
    clock.begin("stereo")
    plate, on_plate, plain_check = _plate(stereo_job, cap, scene, field, tgt, opts, clock, pool)
    writes = _normals_written(pool, normals_png, on_plate)
    surface: reconstruct.Surface | None
    try:
        _check_stereo_share(plate, cap, opts)
        surface = _surface(cap, tgt, scene, plate, on_plate, opts, pool, clock, plain_check)
    except Exception as err:  # what a plate taken for plain raised counts only if it is the plate
        _raise_unless_not_plain(plain_check, err)
        surface = None
    if surface is None:
        # the stereo depth shows more than one sheet in the brightness mask (the tops of rails under the
        # plate's edge): the pair matched again over every pixel that may be plate, the plate segmented
        finish(writes)
        plate, on_plate = _not_plain(cap, tgt, scene, field, opts, clock)
        writes = _normals_written(pool, normals_png, on_plate)
        _check_stereo_share(plate, cap, opts)
        surface = _surface(cap, tgt, scene, plate, on_plate, opts, pool, clock)
    rays = started.rays.result()
    points = points_on_rays(surface.depth_mm, rays)
    clock.end("depth")
    view = View(
        surface=surface,
        plate=plate,
        points=points,
        rays=rays,
        raw_noise=started.raw_noise.result(),
    )
    return view, writes


def measure(
    cap: Capture,
    tgt: Target,
    scene: Scene,
    opts: InspectOptions,
    out: Path,
    pool: ThreadPoolExecutor,
    clock: StageClock,
    started: CaptureWork,
) -> Measurement:
    """Stages *normals* to *artifacts* (details.json and result.json excepted), work beside the main line on
    ``pool`` (``started``: see :func:`reconstruct_view`)."""
    view, writes = reconstruct_view(
        cap,
        tgt,
        scene,
        opts,
        pool,
        clock,
        started,
        normals_png=out / ARTIFACT_FILES["normals"],
    )
    pre, surface, points = scene.pre, view.surface, view.points

    def qualify(judged: np.ndarray) -> uncertainty.PointUncertainty:
        return uncertainty.propagate_points(uncertainty_inputs(cap, pre, view, judged))

    K = cap.rig.left.K
    return _judge(points, view.rays, surface, view.plate, tgt, K, out, pool, writes, clock, qualify)


def _plate(
    stereo_job: Future[tuple[np.ndarray, float, int]] | None,
    cap: Capture,
    scene: Scene,
    field: normals.NormalField | None,
    tgt: Target,
    opts: InspectOptions,
    clock: StageClock,
    pool: ThreadPoolExecutor,
) -> tuple[Plate, normals.NormalField | None, Future[bool] | None]:
    """The stereo depth, and the plate among its surroundings (#17): the near, smooth sheet of the stereo
    depth; openings stay holes, supports beside the plate and an edge band are left out. A plain scene (a
    plate over a dark conveyor, no opening), or no stereo pair: the brightness mask. The distant normal
    field comes back restricted to the plate.

    A scene plain by its outline is taken for plain while its depth decides on ``pool``
    (:func:`pipeline.segmentation.plain_depth`, beside the surface's solve): the third value, None
    otherwise. When the depth says no, :func:`_not_plain` gives the plate."""
    pre, K = scene.pre, cap.rig.left.K
    depth_c, stereo_s, depth_scale = (
        stereo_job.result() if stereo_job is not None else (None, 0.0, 1)
    )
    t_seg = time.perf_counter()
    seg = None
    plain_check = None
    if scene.plain_outline and depth_c is not None:
        plain_check = pool.submit(segmentation.plain_depth, pre.mask, depth_c, K)
    elif depth_c is not None:
        seg = _segment(pre, depth_c, K, scene.candidates, depth_scale, field, tgt)
    plate, field = _on_plate(pre, field, seg, depth_c, depth_scale)
    clock.timings["stereo"] = stereo_s
    clock.timings["segmentation"] = round(time.perf_counter() - t_seg, 4)
    return plate, field, plain_check


def _not_plain(
    cap: Capture,
    tgt: Target,
    scene: Scene,
    field: normals.NormalField | None,
    opts: InspectOptions,
    clock: StageClock,
) -> tuple[Plate, normals.NormalField | None]:
    """The plate of a scene taken for plain by its outline whose stereo depth shows more than one sheet
    in its brightness mask (:func:`pipeline.segmentation.plain_depth`): the pair matched
    over the brightness mask only is matched again over every pixel that may be plate and the plate
    segmented on that depth (:func:`_matched_on_candidates`). ``field``: the normals not yet restricted."""
    t_seg = time.perf_counter()
    depth_c, depth_scale, seg, again_s = _matched_on_candidates(cap, tgt, scene, field, opts)
    plate, field = _on_plate(scene.pre, field, seg, depth_c, depth_scale)
    clock.timings["stereo"] = round(clock.timings["stereo"] + again_s, 4)
    clock.timings["segmentation"] = round(
        clock.timings["segmentation"] + time.perf_counter() - t_seg - again_s, 4
    )
    return plate, field


def _on_plate(
    pre: Preprocessed,
    field: normals.NormalField | None,
    seg: segmentation.Segmentation | None,
    depth_c: np.ndarray | None,
    depth_scale: int,
) -> tuple[Plate, normals.NormalField | None]:
    """The plate ``seg`` found (None: the brightness mask, a plain scene's), its stereo prior from the
    depth ``depth_c``, and the distant normal field restricted to it."""
    mask = pre.mask if seg is None else seg.mask
    prior: np.ndarray | None
    if seg is not None:
        prior = seg.stereo_prior(depth_c)
    else:
        prior = None if depth_c is None else np.where(mask, depth_c, np.nan)
    if field is not None:
        field = _restricted(field, mask)
    matched_pct = (
        None if prior is None else 100.0 * np.count_nonzero(np.isfinite(prior) & mask) / mask.sum()
    )
    plate = Plate(
        mask=mask,
        seg=seg,
        prior=prior,
        matched_pct=matched_pct,
        depth_mm=depth_c,
        depth_scale=depth_scale,
    )
    return plate, field


def _normals_written(
    pool: ThreadPoolExecutor, path: Path | None, field: normals.NormalField | None
) -> list[Deferred[Any]]:
    """normals.png of the distant normals on the plate submitted (none without a field or a path), to be
    written while the depth is solved on this thread (the few normals dropped later as facing away are
    then shown as estimated)."""
    if field is None or path is None:
        return []
    return [Deferred(pool, artifacts.write_normals_png, path, field.normals, field.mask)]


class _NotPlain(Exception):
    """The stereo depth of a scene taken for plain says its brightness mask is not the plate."""


def _raise_unless_not_plain(plain_check: Future[bool] | None, err: Exception) -> None:
    """``err``, raised on a plate taken for plain, raised again unless ``plain_check`` says that plate is
    not the plate (then it counts for nothing)."""
    if not isinstance(err, _NotPlain) and (plain_check is None or plain_check.result()):
        raise err


def _confirm_plain(plain_check: Future[bool] | None, work: Future[Any] | None = None) -> None:
    """Raise :class:`_NotPlain` when ``plain_check`` says no (``work`` begun on the plate so taken is then
    cancelled if it has not started)."""
    if plain_check is not None and not plain_check.result():
        if work is not None:
            work.cancel()
        raise _NotPlain


def _check_stereo_share(plate: Plate, cap: Capture, opts: InspectOptions) -> None:
    """Too little of the plate matched in the stereo pair to trust it: the working distance sets the scale
    (the prior is dropped; details.json says so), or the capture cannot be measured without one."""
    if (
        plate.prior is not None
        and plate.matched_pct is not None
        and plate.matched_pct < opts.min_stereo_pct
    ):
        if cap.working_distance_mm is None:
            raise CaptureError(
                f"{cap.source}: stereo: {plate.matched_pct:.1f} % of the plate matched in the stereo pair, expected "
                f"at least {opts.min_stereo_pct:.0f} %, and there is no working_distance_mm to fall back on"
            )
        plate.prior = None


def _surface(
    cap: Capture,
    tgt: Target,
    scene: Scene,
    plate: Plate,
    field: normals.NormalField | None,
    opts: InspectOptions,
    pool: ThreadPoolExecutor,
    clock: StageClock,
    plain_check: Future[bool] | None = None,
) -> reconstruct.Surface:
    """Stages *normals* (point lights) and *depth*: the metric surface, with the lights refitted on the stereo
    geometry when they bend it away from the stereo pair's (``plate`` then holds the segmented plate).
    Under distant lights a glossy coating's lobe is measured on the stereo surface on ``pool`` beside the
    integration, and the normals are fitted with it (:func:`pipeline.surface.reconstruct.with_lobe`).

    ``plain_check``: the depth's verdict on a scene taken for plain (:func:`_plate`), awaited before
    anything but the distant normals' integration (:class:`_NotPlain` when it says no)."""
    pre, K = scene.pre, cap.rig.left.K
    solve: dict[str, Any] = dict(
        prior_mm=plate.prior,
        working_distance_mm=cap.working_distance_mm,
        stereo_weight=stereo_weight_on_grid(
            opts.stereo_weight, K, cap.working_distance_mm or NOMINAL_DISTANCE_MM
        ),
        tol=opts.depth_tol,
    )
    if cap.lights.any_point:
        _confirm_plain(plain_check)
        # point lights: normals and surface alternate; "normals" times the whole alternation (with its
        # integrations), "depth" what follows
        t_near = time.perf_counter()
        surface = reconstruct.near_field_surface(
            pre.images,
            cap.lights,
            K,
            plate.mask,
            valid=pre.valid,
            method=opts.normals_method,
            **solve,
        )
        clock.timings["normals"] = round(time.perf_counter() - t_near, 4)
        clock.begin("depth")
        return surface
    clock.begin("depth")
    if field is None:
        raise ValueError("normals: distant lights need the normals estimated before the surface")
    lobe_job = (
        # the normals' specular stage saw a lobe: measured again on the stereo pair's surface, beside the
        # integration (a broad lobe's exponent is misread from the images alone)
        pool.submit(
            reconstruct.stereo_lobe, pre.images, pre.valid, cap.lights, K, plate.prior, plate.mask
        )
        if plate.prior is not None and field.specular is not None and field.specular.modelled
        else None
    )
    surface = reconstruct.distant_surface(field, K, **solve)
    _confirm_plain(plain_check, lobe_job)
    if lobe_job is not None:
        surface = reconstruct.with_lobe(
            surface, pre.images, cap.lights, K, pre.valid, lobe_job.result(), solve
        )
    if plate.prior is None or not reconstruct.disagrees(
        surface, tgt.tolerance_mm, DISAGREEMENT_FRACTION
    ):
        return surface
    # the given lights bend the surface away from the stereo pair's: refit them on its geometry
    t_refit = time.perf_counter()
    if plate.seg is None and plate.depth_mm is not None:
        solve["prior_mm"] = _segmented_on_candidates(cap, tgt, scene, plate, field, opts)
        # the given lights measured again on that plate: the refit is compared with them there, and
        # they stand on it when it is not kept (the brightness mask may hold what the segmentation
        # left out: the tops of rails beside a plate over a dark floor, at the plate's depth)
        lobe_fitted = lobe_job is not None and lobe_job.result().significant
        surface = _on_segmented_plate(surface, plate.mask, K, solve, lobe_fitted=lobe_fitted)
    surface = reconstruct.remeasure_with_refined_lights(
        surface,
        pre.images,
        cap.lights,
        K,
        plate.mask,
        valid=pre.valid,
        method=opts.normals_method,
        **solve,
    )
    clock.timings["light_refinement"] = round(time.perf_counter() - t_refit, 4)
    return surface


def _segmented_on_candidates(
    cap: Capture,
    tgt: Target,
    scene: Scene,
    plate: Plate,
    field: normals.NormalField,
    opts: InspectOptions,
) -> np.ndarray:
    """A plain scene's plate segmented before its lights are refitted (``plate`` updated); the new stereo
    prior.

    So far on the brightness mask: lights that do not fit light the plate unevenly, and the mask
    follows its darker edges (a rust patch at the edge under LEDs given by their directions fell
    outside it, and the stereo pair, matched over that mask, left it a hole and a notch of the plate
    unmeasured): :func:`_matched_on_candidates`.
    """
    plate.depth_mm, plate.depth_scale, seg, _ = _matched_on_candidates(cap, tgt, scene, field, opts)
    plate.seg, plate.mask = seg, seg.mask
    prior: np.ndarray = seg.stereo_prior(plate.depth_mm)
    return prior


def _matched_on_candidates(
    cap: Capture,
    tgt: Target,
    scene: Scene,
    field: normals.NormalField | None,
    opts: InspectOptions,
) -> tuple[np.ndarray, int, segmentation.Segmentation, float]:
    """A scene taken for plain by its outline, whose stereo pair was matched over the brightness mask
    only: the pair matched again over every pixel that may be plate, and the plate segmented on that
    depth, so that the segmentation sees the plate's rim and what the mask left out. Returns the depth,
    its reduction (:func:`_stereo_depth`), the segmentation and the matching's run time (s)."""
    depth, seconds, scale = _stereo_depth(cap, scene.candidates, opts)
    seg = _segment(scene.pre, depth, cap.rig.left.K, scene.candidates, scale, field, tgt)
    return depth, scale, seg, seconds


def _on_segmented_plate(
    surface: reconstruct.Surface,
    mask: np.ndarray,
    K: np.ndarray,
    solve: dict[str, Any],
    *,
    lobe_fitted: bool,
) -> reconstruct.Surface:
    """The first surface of a plain scene (measured on the brightness mask) measured again on the plate
    segmented for its lights' refit, ``mask``. Normals fitted with a lobe keep the stereo pair's bend
    (:data:`pipeline.surface.reconstruct.LOBE_BEND_FROM_STEREO`)."""
    coarsest = reconstruct.LOBE_BEND_FROM_STEREO if lobe_fitted else fusion.PLANE
    return reconstruct.distant_surface(
        _restricted(surface.field, mask), K, coarsest=coarsest, **solve
    )


def stereo_weight_on_grid(weight: float, K: np.ndarray, distance_mm: float) -> float:
    """The stereo depth's weight per pixel (``InspectOptions.stereo_weight``) on a working grid of
    intrinsics ``K`` at ``distance_mm``.

    The weight sets where the normals take over from the stereo pair: above ``2 pi / sqrt(weight)``
    pixels. On a grid finer than :data:`STEREO_WEIGHT_CELL_MM` (a capture that cannot be binned by a
    whole factor to its working cell: 2448x2048 with the head 4.2 m away, 2.3 mm) the same weight per
    pixel would let the stereo pair reach proportionally shorter wavelengths on the plate, while its
    noise per pixel falls less than the cell (not at all where the pair is matched reduced, above
    ``stereo_max_width``). There the weight keeps the wavelength in mm: it is scaled by
    ``(cell / STEREO_WEIGHT_CELL_MM)^2``. With the pair matched at half size (before
    ``stereo_max_width`` let it be matched whole), a perfect plate read p95 0.119 mm at 2448x2048 and
    4.2 m with the weight per pixel, a smooth dome of stereo noise over U95 0.089 mm; 0.089 mm with it
    scaled, U95 0.099 mm. A coarser grid keeps the weight per
    pixel: the pair's noise grows with the distance (as its square), and scaled up at 1224x1024 and
    4.2 m it let in more of it (p95 0.066 -> 0.090 mm).
    """
    cell = distance_mm / float(max(K[0, 0], K[1, 1]))
    ratio = cell / STEREO_WEIGHT_CELL_MM
    return weight * ratio * ratio if ratio < 1.0 - 1e-9 else weight


def _judge(
    points: np.ndarray,
    rays: np.ndarray,
    surface: reconstruct.Surface,
    plate: Plate,
    tgt: Target,
    K: np.ndarray,
    out: Path,
    pool: ThreadPoolExecutor,
    writes: list[Deferred[Any]],
    clock: StageClock,
    qualify: Callable[[np.ndarray], uncertainty.PointUncertainty],
) -> Measurement:
    """Stages *curvature*, *deviation* and *artifacts* (its files but details.json): curvature, the pixel
    areas and every point's uncertainty beside the registration, each artifact written beside the main
    line as soon as it is known. ``writes``: the artifact writes under way (normals.png when the distant
    normals were written already); ``qualify``: every point's uncertainty on the judged pixels (the
    surface without its edge band: :func:`edge_band`), restricted once the registration has placed the
    target's outline (:mod:`pipeline.judge.outline`)."""
    field, surface_mask = surface.field, surface.mask
    normals_written = bool(writes)
    clock.begin("curvature")
    band = edge_band(surface_mask)
    judged = surface_mask & ~band
    # the two longest first, a worker each: the registration then does not wait for the uncertainty
    curvature_job = pool.submit(_curvature, points, surface_mask)
    points_job = pool.submit(qualify, judged)
    area_job = pool.submit(area.pixel_area_mm2, surface.depth_mm, field.normals, rays, K)
    writes.append(
        Deferred(pool, artifacts.save_depth, out / ARTIFACT_FILES["depth"], surface.depth_mm)
    )
    if not normals_written:
        writes.append(
            Deferred(
                pool,
                artifacts.write_normals_png,
                out / ARTIFACT_FILES["normals"],
                field.normals,
                field.mask,
            )
        )
    clock.begin("deviation")
    pose, beyond, judged, dev, qualified = _registered(
        points, surface_mask, band, judged, tgt, points_job
    )
    writes += write_deviation(pool, out, points, surface_mask, dev, tgt.tolerance_mm)
    writes.append(
        Deferred(
            pool,
            artifacts.write_uncertainty,
            out,
            qualified.map_mm,
            judged,
            tolerance_mm=tgt.tolerance_mm,
        )
    )
    pixel_area = area_job.result()
    judgement = verdict.judge(
        dev,
        judged,
        tgt.tolerance_mm,
        pixel_area_mm2=pixel_area,
        uncertainty_mm=qualified.map_mm,
    )
    footprint = points[..., 2][judged] / float(np.sqrt(K[0, 0] * K[1, 1]))
    clock.end("deviation")
    clock.begin("artifacts")
    writes.append(write_target(pool, out, tgt, pose))
    finish(writes)  # the writes no worker has started yet are made here, instead of waiting
    curv, clock.timings["curvature"] = curvature_job.result()
    return Measurement(
        surface=surface,
        plate=plate,
        pose=pose,
        judgement=judgement,
        curv=curv,
        pixel_area=pixel_area,
        points=points,
        uncertainty=qualified,
        edge_band_mm=round(EDGE_BAND_PX * float(np.median(footprint)), 1),
        beyond_outline_mm2=float(np.nansum(pixel_area[beyond])),
    )


def _registered(
    points: np.ndarray,
    surface_mask: np.ndarray,
    band: np.ndarray,
    judged: np.ndarray,
    tgt: Target,
    points_job: Future[uncertainty.PointUncertainty],
) -> tuple[registration.Registration, np.ndarray, np.ndarray, np.ndarray, uncertainty.Uncertainty]:
    """The target registered to the plate; the pixels beyond its outline (:mod:`pipeline.judge.outline`);
    the judged pixels (``judged`` less them and the band drawn again along the outline so clipped: new
    arrays, the qualifying worker still reads ``judged``); the deviation, NaN in the band (left out by
    geometry, so that every artifact agrees); every judged point's uncertainty (``points_job``'s)."""
    pose = registration.register_to_target(points, surface_mask, tgt)
    beyond, clipped, band, judged, dev = judged_deviation(
        points, surface_mask, band, judged, tgt, pose
    )
    point_u = points_job.result()
    if clipped:
        point_u = uncertainty.restricted(point_u, judged)
    radius = pose.fitted_radius_mm
    qualified = uncertainty.with_radius(
        point_u,
        radius_mm=None if radius is None else float(radius),
        curved_direction=np.asarray(pose.T_cam_target)[:3, 0],
    )
    return pose, beyond, judged, dev, qualified


def judged_deviation(
    points: np.ndarray,
    mask: np.ndarray,
    band: np.ndarray,
    judged: np.ndarray,
    tgt: Target,
    pose: registration.Registration,
) -> tuple[np.ndarray, bool, np.ndarray, np.ndarray, np.ndarray]:
    """The deviation of the registered plate where it is judged (one view and stations alike).

    ``band`` and ``judged``: the :func:`edge_band` of ``mask`` and the rest of it. Returns the pixels
    beyond the target's outline (:mod:`pipeline.judge.outline`), whether there are any, the band and
    the judged pixels once the outline has clipped the plate (:func:`clipped_band`; ``band`` and
    ``judged`` themselves when nothing lies beyond), and the deviation, NaN in the band: left out by
    geometry, so that every artifact agrees.
    """
    beyond = outline.beyond_outline(points, mask, tgt, pose)
    clipped = bool(beyond.any())
    if clipped:
        band, judged = clipped_band(mask, beyond)
    dev = np.where(band, np.nan, deviation.deviation_map(points, mask, tgt, pose))
    return beyond, clipped, band, judged, dev


def clipped_band(mask: np.ndarray, beyond: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The band left out of the judgement when part of ``mask`` lies ``beyond`` the target's outline
    (:mod:`pipeline.judge.outline`), and the judged pixels: the pixels beyond, and the :func:`edge_band`
    of the plate clipped to the outline (the pixels at the cut mix plate and what lies past its edge,
    as at the segmented outline). The judged pixels are a subset of those of ``mask``'s own band."""
    band = beyond | edge_band(mask & ~beyond)
    return band, mask & ~band


def edge_band(mask: np.ndarray, width_px: int = EDGE_BAND_PX) -> np.ndarray:
    """(H, W) bool: the mask's pixels within ``width_px`` of its outline or an opening; the image's frame
    is no edge (the plate goes on beyond it)."""
    pad = width_px + 2
    framed = cv2.copyMakeBorder(mask.view(np.uint8), pad, pad, pad, pad, cv2.BORDER_REPLICATE)
    inner = cv2.erode(framed, np.ones((2 * width_px + 1, 2 * width_px + 1), np.uint8))
    band: np.ndarray = mask & ~inner[pad:-pad, pad:-pad].astype(bool)
    return band


def uncertainty_inputs(
    cap: Capture, pre: Preprocessed, view: View, judged: np.ndarray
) -> uncertainty.Inputs:
    """What :func:`pipeline.judge.uncertainty.propagate` needs of one view, ``judged``: the pixels to qualify."""
    surface, points = view.surface, view.points
    images, lights = pre.images, cap.lights
    if surface.refinement is not None:  # the normals came from the refitted lights
        refined = surface.refinement.lights
        images = images * (lights.intensity / refined.intensity).astype(np.float32)[:, None, None]
        lights = refined
    rig = cap.rig
    board = rig.board or {}
    corners = board.get("inner_corners")
    own_noise, dark_noise = _raw_noise(cap, lights, view.raw_noise)
    return uncertainty.Inputs(
        images=images,
        valid=pre.valid,
        lights=lights,
        field=surface.field,
        points_mm=points,
        mask=judged,
        K=rig.left.K,
        fusion=surface.fusion,
        baseline_mm=float(np.linalg.norm(rig.T)) if cap.has_stereo else None,
        calibration_rms_px=rig.rms_px,
        board_corners=int(np.prod(corners)) if corners else None,
        own_noise=own_noise,
        dark_noise=dark_noise,
    )


def _raw_noise(
    cap: Capture, lights: Lights, counts: tuple[np.ndarray, float | None]
) -> tuple[np.ndarray, np.ndarray | None]:
    """The raw noise of each photometric image and of the dark frame (None without one), each in the
    preprocessed images' units (raw counts / (intensity x full scale)); ``counts`` in raw counts
    (:attr:`View.raw_noise`).

    Measured on the raw frames, before undistortion interpolates (and smooths) them; a binned capture's
    before binning (``Capture.raw_noise``).
    """
    scale = np.asarray(lights.intensity, dtype=np.float64) * float(2**cap.bit_depth - 1)
    own_counts, dark_counts = counts
    own: np.ndarray = own_counts / scale
    if dark_counts is None:
        return own, None
    dark: np.ndarray = dark_counts / scale
    return own, dark


def write_target(
    pool: ThreadPoolExecutor, out: Path, tgt: Target, pose: registration.Registration
) -> Deferred[Any]:
    """Submit the write of target.ply, the target's surface in the measured plate's pose (see
    :class:`pipeline.parallel.Deferred`)."""
    verts, faces = target_geometry.target_surface(tgt)
    return Deferred(
        pool,
        artifacts.write_target_ply,
        out / ARTIFACT_FILES["target_surface"],
        verts,
        faces,
        pose.T_cam_target,
    )


def write_deviation(
    pool: ThreadPoolExecutor,
    out: Path,
    points: np.ndarray,
    mask: np.ndarray,
    dev: np.ndarray,
    tolerance_mm: float,
) -> list[Deferred[Any]]:
    """Submit the writes of surface.ply and deviation.png (the deviation known; see
    :class:`pipeline.parallel.Deferred`)."""
    return [
        Deferred(
            pool,
            artifacts.write_surface_ply,
            out / ARTIFACT_FILES["surface"],
            points,
            mask,
            dev,
            tolerance_mm=tolerance_mm,
        ),
        Deferred(
            pool,
            artifacts.write_deviation_png,
            out / ARTIFACT_FILES["deviation_map"],
            dev,
            mask,
            tolerance_mm=tolerance_mm,
        ),
    ]


def _apply_light_calibration(
    cap: Capture, calibration: Lights | None, warnings: list[str]
) -> Capture:
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


def _curvature(points: np.ndarray, mask: np.ndarray) -> tuple[curvature.CurvatureResult, float]:
    """Principal curvatures and their run time (s)."""
    t = time.perf_counter()
    curv = curvature.principal_curvatures(points, mask)
    return curv, round(time.perf_counter() - t, 4)


def _stereo_depth(
    cap: Capture, mask: np.ndarray, opts: InspectOptions
) -> tuple[np.ndarray, float, int]:
    """Stereo depth (mm, left undistorted grid, NaN where unmatched or outside ``mask``), its run time (s) and
    the reduction the pair was matched at (1: full size)."""
    t = time.perf_counter()
    z_nominal = cap.working_distance_mm or NOMINAL_DISTANCE_MM
    left, right, rig, stereo_mask = cap.stereo_left, cap.stereo_right, cap.rig, mask
    if left is None or right is None:
        raise ValueError("capture: the stereo pair is needed for stereo depth, got none")
    width, height = rig.image_size
    step = -(-width // opts.stereo_max_width)  # the smallest whole reduction that fits
    if step > 1:
        # the stereo depth only anchors scale and the lowest frequencies: a reduced pair is plenty, and cheaper
        small = (width // step, height // step)
        left, right = (cv2.resize(im, small, interpolation=cv2.INTER_AREA) for im in (left, right))
        rig = replace(rig, left=rig.left.resized(small), right=rig.right.resized(small))
        stereo_mask = cv2.resize(
            mask.view(np.uint8), small, interpolation=cv2.INTER_NEAREST
        ).astype(bool)
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


def _segment(
    pre: Preprocessed,
    depth_mm: np.ndarray,
    K: np.ndarray,
    candidates: np.ndarray,
    depth_scale: int,
    field: normals.NormalField | None,
    tgt: Target,
) -> segmentation.Segmentation:
    """The plate told from its surroundings (:func:`pipeline.segmentation.segment_plate`)."""
    return segmentation.segment_plate(
        _brightness(pre),
        depth_mm,
        K,
        seen=pre.seen,
        candidates=candidates,
        depth_scale_px=depth_scale,
        normals=None if field is None else field.normals,  # NaN off the field's mask (NormalField)
        target_area_mm2=target_geometry.target_area_mm2(tgt),
        glare_free=pre.glare_free,
    )


def _brightness(pre: Preprocessed) -> np.ndarray:
    """The brightness the plate is told from its surroundings by (:attr:`Preprocessed.brightness`;
    preprocess always computes it)."""
    if pre.brightness is None:
        raise ValueError("preprocess: the brightness image is missing")
    return pre.brightness


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
