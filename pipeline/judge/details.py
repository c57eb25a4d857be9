"""``details.json``: what an inspection found that the fixed ``plate-result/1`` format has no field for.

:class:`Details` is its model: one attribute per key, in the file's key order (README: *Formats*
says what each holds). The builders below make its parts from the stages' results;
:meth:`Details.to_json` writes the file's text.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from pipeline.judge.verdict import DefectRegion
    from pipeline.lights.refinement import LightRefinement
    from pipeline.segmentation import Segmentation
    from pipeline.surface.fusion import Fusion


@dataclass(frozen=True)
class RegionDetails:
    """An out-of-tolerance region: centroid ``(u, v)`` px, area mm^2, signed peak deviation mm.

    ``centroid_mm``: the centroid ``(x, y)`` in the target's own frame, mm (the frame of target.json:
    for a simulated plate, the plate coordinates its dents are given in); ``mean_deviation_mm``: the
    area-weighted mean deviation over the region. Both null in details.json files written before
    they were added, and ``centroid_mm`` where no depth is known at the centroid.
    """

    centroid_px: list[float]
    area_mm2: float
    peak_deviation_mm: float
    mean_deviation_mm: float | None = field(default=None, kw_only=True)
    centroid_mm: list[float] | None = field(default=None, kw_only=True)
    #: Expanded uncertainty (k = 2) of the measurement at the peak, mm (null before it was added).
    uncertainty_mm: float | None = field(default=None, kw_only=True)


@dataclass(frozen=True)
class ExcludedRegionDetails(RegionDetails):
    """A region left out of the verdict, and why (in details.json files written before issue 24)."""

    reason: str


@dataclass(frozen=True)
class BrightnessSegmentationDetails:
    """The plate told from its surroundings by brightness (no segmentation ran): its measured area."""

    method: str
    plate_area_mm2: float
    target_area_mm2: float
    area_ratio: float
    reasons: list[str]


@dataclass(frozen=True)
class SegmentationDetails:
    """The plate told from its surroundings by the stereo depth (:func:`pipeline.segmentation.segment_plate`)."""

    method: str
    plate_area_mm2: float
    edge_band_px: int
    edge_band_area_mm2: float
    holes: int
    holes_area_mm2: float
    filled_area_mm2: float
    target_area_mm2: float
    area_ratio: float | None
    fit_rms_mm: float | None
    reasons: list[str]


@dataclass(frozen=True)
class FusionDetails:
    """How the stereo pair corrected the photometric shape (:class:`pipeline.surface.fusion.Fusion`)."""

    disagreement_mm: float
    noise_floor_mm: float
    stereo_noise_mm: float
    correction_max_abs_mm: float
    stereo_pixels: int
    correction: str
    knot_spacing_px: float | None
    #: The lack-of-fit test per rung: {rung: [statistic, threshold]} (pipeline.surface.fusion.Fusion.evidence).
    evidence: dict[str, list[float]] = field(default_factory=dict)
    #: Variance inflation of the stereo noise by its correlation between neighbouring blocks.
    noise_inflation: float = 1.0


@dataclass(frozen=True)
class UncertaintyDetails:
    """How the expanded uncertainties were made (:mod:`pipeline.judge.uncertainty`): ``k``, the figures (mm)
    and the standard uncertainties behind them (``components``), and what was left out of the judgement
    by geometry: the edge band (mm from the plate's outline and openings) and the measured surface
    beyond the target's outline (mm^2, :mod:`pipeline.judge.outline`)."""

    k: float
    deviation_mm: float
    radius_mm: float | None
    components: dict[str, float]
    edge_band_mm: float
    beyond_outline_mm2: float = 0.0


@dataclass(frozen=True)
class RefinementDetails:
    """The lights refitted on the stereo geometry (:mod:`pipeline.lights.refinement`)."""

    model: str
    rms_given: float
    rms_distant: float
    rms_point: float | None
    samples: int
    corrections: list[dict[str, Any]]


@dataclass(frozen=True)
class OverlapDetails:
    """Two stations where they overlap, after the registration (docs/stations.md): the texture matches
    the poses were fitted to and their RMS distance after the fit, and the distance along the normal
    between the two surfaces over the overlap (RMS and max over ``points`` compared), mm."""

    stations: list[int]
    matches: int
    match_rms_mm: float
    rms_mm: float
    max_mm: float
    points: int


@dataclass(frozen=True)
class StationDetails:
    """One conveyor station of a plate measured at stations (docs/stations.md).

    ``T_plate_station``: (4, 4) its left camera frame into the plate frame (the frame of the result's
    points and ``T_cam_target``), mm; ``travel_encoder_mm`` the encoder's travel since station 0,
    ``travel_mm`` the travel the registration found (the plate point under the head), mm;
    ``registration_sd_mm`` the standard uncertainty its registration adds to a point, mm;
    ``footprint_mm`` (4, 2) the corners of its image frame at the depth of its plate (the median of
    its measured points), in the target's frame (x, y), mm: the outline the plate map draws.
    """

    index: int
    bundle: str
    T_plate_station: list[list[float]]
    travel_encoder_mm: float
    travel_mm: float
    stereo_matched_pct: float | None
    registration_sd_mm: float
    stereo_fusion: FusionDetails | None = None
    light_refinement: RefinementDetails | None = None
    footprint_mm: list[list[float]] | None = None


@dataclass(frozen=True)
class StitchDetails:
    """How the stations were stitched into one plate: the grid's cell (mm), each station, each overlap."""

    cell_mm: float
    stations: list[StationDetails]
    overlaps: list[OverlapDetails]


@dataclass(frozen=True)
class Details:
    """The content of ``details.json``, one attribute per key in the file's order.

    Attributes
    ----------
    T_cam_target : list of list of float
        The registration, (4, 4) target frame to camera frame, mm.
    registration_rms_mm : float
    principal_directions : list of list of float
        (2, 3) unit tangent directions of the principal curvatures, camera frame.
    defects : list of RegionDetails
    reasons : list of str
        Why the plate failed (empty when it passed).
    excluded_regions : list of ExcludedRegionDetails
        Empty since the plate's edge band is left out by geometry before judging (issue 24); kept
        for the format, and for files written before, which listed edge artefacts here.
    segmentation : SegmentationDetails or BrightnessSegmentationDetails
    normals_filled, normals_facing_away : int
    light_model : {"distant", "near-field"}
    near_field_iterations : int or None
    near_field_depth_steps_mm : list of float or None
    stereo_fusion : FusionDetails or None
    light_refinement : RefinementDetails or None
    samples_saturated, samples_shadowed : int
    stereo_matched_pct : float or None
    metric_scale : {"stereo", "working_distance"}
    uncertainty : UncertaintyDetails or None
    stations : StitchDetails or None
        A plate measured at conveyor stations (docs/stations.md); absent for one view.
    """

    T_cam_target: list[list[float]]
    registration_rms_mm: float
    principal_directions: list[list[float]]
    defects: list[RegionDetails]
    reasons: list[str]
    excluded_regions: list[ExcludedRegionDetails]
    segmentation: SegmentationDetails | BrightnessSegmentationDetails
    normals_filled: int
    normals_facing_away: int
    light_model: str
    near_field_iterations: int | None
    near_field_depth_steps_mm: list[float] | None
    stereo_fusion: FusionDetails | None
    light_refinement: RefinementDetails | None
    samples_saturated: int
    samples_shadowed: int
    stereo_matched_pct: float | None
    metric_scale: str
    uncertainty: UncertaintyDetails | None = None
    stations: StitchDetails | None = None

    def to_json(self) -> str:
        """The text of ``details.json`` (indented JSON, a final newline; no ``stations`` for one view)."""
        doc = asdict(self)
        if doc["stations"] is None:
            del doc["stations"]
        return json.dumps(doc, indent=2) + "\n"


def region_details(
    region: DefectRegion, centroid_mm: tuple[float, float] | None = None
) -> RegionDetails:
    """A :class:`pipeline.judge.verdict.DefectRegion` for details.json (``centroid_mm``: target frame)."""
    return RegionDetails(
        centroid_px=list(map(float, region.centroid_px)),
        area_mm2=float(region.area_mm2),
        peak_deviation_mm=float(region.peak_deviation_mm),
        mean_deviation_mm=float(region.mean_deviation_mm),
        centroid_mm=None if centroid_mm is None else [float(c) for c in centroid_mm],
        uncertainty_mm=round(region.uncertainty_mm, 3)
        if np.isfinite(region.uncertainty_mm)
        else None,
    )


def segmentation_details(
    seg: Segmentation | None, target_area_mm2: float, *, plain: bool, measured_area_mm2: float
) -> SegmentationDetails | BrightnessSegmentationDetails:
    """How the plate was told from its surroundings, and its area against the target's.

    Parameters
    ----------
    seg : pipeline.segmentation.Segmentation or None
        None: the brightness mask is the plate (a plain scene, or no stereo pair).
    target_area_mm2 : float
    plain : bool
        A plain scene (nothing lit around the plate, no opening, one sheet in the stereo depth).
    measured_area_mm2 : float
        Without a segmentation: the measured surface's area (the brightness mask is eroded by 3 px).
    """
    if seg is None:
        why = (
            "a plain scene: nothing lit around the plate, no opening in it, one smooth sheet in the stereo "
            "depth; the brightness mask (Otsu) is the plate"
            if plain
            else "no stereo pair: the plate was told from its surroundings by brightness (Otsu, holes filled)"
        )
        return BrightnessSegmentationDetails(
            method="brightness",
            plate_area_mm2=round(measured_area_mm2, 0),
            target_area_mm2=round(target_area_mm2, 0),
            area_ratio=round(measured_area_mm2 / target_area_mm2, 4),
            reasons=[why],
        )
    measured = seg.plate_area_mm2 + seg.edge_band_area_mm2
    return SegmentationDetails(
        method=seg.method,
        plate_area_mm2=round(seg.plate_area_mm2, 0),
        edge_band_px=seg.n_edge_band,
        edge_band_area_mm2=round(seg.edge_band_area_mm2, 0),
        holes=seg.n_holes,
        holes_area_mm2=round(seg.holes_area_mm2, 0),
        filled_area_mm2=round(seg.filled_area_mm2, 0),
        target_area_mm2=round(target_area_mm2, 0),
        area_ratio=round(measured / target_area_mm2, 4) if measured == measured else None,
        fit_rms_mm=round(seg.fit_rms_mm, 2) if seg.fit_rms_mm == seg.fit_rms_mm else None,
        reasons=list(seg.reasons),
    )


def fusion_details(fused: Fusion | None) -> FusionDetails | None:
    """How the stereo pair corrected the photometric shape (a :class:`pipeline.surface.fusion.Fusion` or None)."""
    if fused is None:
        return None
    return FusionDetails(
        disagreement_mm=round(fused.disagreement_mm, 3),
        noise_floor_mm=round(fused.noise_floor_mm, 3),
        stereo_noise_mm=round(fused.stereo_noise_mm, 3),
        correction_max_abs_mm=round(float(np.nanmax(np.abs(fused.correction_mm))), 3),
        stereo_pixels=fused.n_stereo,
        correction=fused.model,
        knot_spacing_px=None if fused.knot_spacing_px is None else round(fused.knot_spacing_px, 1),
        evidence=fused.evidence,
        noise_inflation=round(fused.noise_inflation, 3),
    )


def refinement_details(refined: LightRefinement | None) -> RefinementDetails | None:
    """The lights refitted on the stereo geometry (a :class:`pipeline.lights.refinement.LightRefinement` or None)."""
    if refined is None:
        return None
    return RefinementDetails(
        model=refined.model,
        rms_given=round(refined.rms_given, 5),
        rms_distant=round(refined.rms_distant, 5),
        rms_point=None if not np.isfinite(refined.rms_point) else round(refined.rms_point, 5),
        samples=refined.n_samples,
        corrections=refined.corrections,
    )
