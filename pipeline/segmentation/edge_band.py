"""Step 6 and the result: the edge band (and the normals check near the boundary) on the full grid, areas,
counts and the reasons an operator reads."""

from __future__ import annotations

import math

import cv2
import numpy as np

from .classify import DROPOUT_NORMAL_DEG, Parts
from .outline import OUTLINE_REACH_PX, lit_surroundings
from .result import Segmentation
from .surface import Geometry, surface_depth, surface_geometry

#: Near the boundary (``edge_px`` + this many px) a pixel whose photometric normal is more than
#: EDGE_NORMAL_DEG from the fitted surface's is not measured: a bent edge turns its normal by far less
#: over its first pixels, a support's side by ~90 deg.
EDGE_NORMAL_ZONE_PX = 3
EDGE_NORMAL_DEG = 35.0


def finish(
    parts: Parts,
    b: np.ndarray,
    depth: np.ndarray,
    K: np.ndarray,
    ok: np.ndarray,
    cand: np.ndarray,
    dark: np.ndarray,
    normals: np.ndarray | None,
    reasons: list[str],
    *,
    edge_px: int,
    depth_scale_px: int,
    depth_band_mm: float,
    max_dropout_mm2: float,
    support_width_mm: float,
    target_area_mm2: float | None,
) -> Segmentation:
    """Steps 5b (the outline beside lit surroundings) and 6 (edge band, normals check) on the full grid,
    areas and counts, the result. ``b``: the brightness the outline is found by (glare-free).

    ``reasons`` (what was decided so far) is extended with what the parts and the edge band show.
    """
    shape = b.shape
    surface, region = parts.surface, parts.region
    z_fit = surface_depth(surface, K, shape)
    geometry = surface_geometry(surface, K, shape)
    area = geometry.area_full(shape)
    finite = np.isfinite(depth) & (depth > 0) & ok
    with np.errstate(invalid="ignore"):
        off = finite & cand & ~(np.abs(depth - z_fit) < depth_band_mm)
    # the matcher's reach onto lit surroundings, told by the brightness step (step 5b)
    beside = lit_surroundings(region, b, cand & ok, OUTLINE_REACH_PX * depth_scale_px)
    mask, n_normal_off = _measured(
        parts, region & ~beside, ok, normals, geometry, edge_px, depth_scale_px, support_width_mm
    )
    edge_band = region & ~mask
    step = np.where(region, parts.step, np.float32(np.nan)).astype(np.float32)
    holes = parts.holes
    plate_area = float(np.nansum(area[mask]))
    band_area = float(np.nansum(area[edge_band]))
    holes_area = float(np.nansum(area[holes]))
    reasons += _reasons(
        parts,
        holes_area,
        max_dropout_mm2,
        n_normal_off,
        int(np.count_nonzero(edge_band)),
        band_area,
    )
    if beside.any():
        reasons.append(
            f"{int(np.count_nonzero(beside))} px of lit surroundings that the stereo depth reached onto, told by the "
            "glare-free brightness step at the outline, put in the edge band"
        )
    if target_area_mm2 is not None:
        reasons += _area_reasons(plate_area + band_area, target_area_mm2)
    return Segmentation(
        mask=mask,
        edge_band=edge_band,
        holes=holes,
        surface_depth_mm=z_fit,
        surroundings_step_mm=step,
        pixel_area_mm2=area,
        plate_area_mm2=plate_area,
        edge_band_area_mm2=band_area,
        holes_area_mm2=holes_area,
        filled_area_mm2=parts.filled_mm2 + parts.filled_by_normals_mm2,
        n_mask=int(np.count_nonzero(mask)),
        n_edge_band=int(np.count_nonzero(edge_band)),
        n_holes=parts.n_holes,
        n_hole_pixels=int(np.count_nonzero(holes)),
        n_off_depth=int(np.count_nonzero(off)),
        n_dark=int(np.count_nonzero(dark)),
        n_unmatched=int(np.count_nonzero(ok & cand & ~finite)),
        fit_rms_mm=surface.rms_mm,
        depth_band_mm=depth_band_mm,
        method="stereo",
        reasons=tuple(reasons),
    )


def inner_region(region: np.ndarray, edge_px: int) -> np.ndarray:
    """The region less its pixels within ``edge_px`` of its outline or of a hole (not of the image frame)."""
    if edge_px <= 0:
        return region
    k = 2 * edge_px + 1
    padded = cv2.copyMakeBorder(
        region.view(np.uint8), edge_px, edge_px, edge_px, edge_px, cv2.BORDER_REPLICATE
    )
    return cv2.erode(padded, np.ones((k, k), np.uint8))[edge_px:-edge_px, edge_px:-edge_px].astype(
        bool
    )


def _measured(
    parts: Parts,
    region: np.ndarray,
    ok: np.ndarray,
    normals: np.ndarray | None,
    geometry: Geometry,
    edge_px: int,
    depth_scale_px: int,
    support_width_mm: float,
) -> tuple[np.ndarray, int]:
    """The plate's pixels to measure (the edge band left out, wider where a support met the plate), and how
    many pixels near the boundary the normals check put in the band. ``region``: the plate's region less
    the lit surroundings the stereo depth took in (step 5b)."""
    mask = inner_region(region, edge_px) & ok
    if parts.feet.any():
        # where a support met the plate, its foot may be left at the plate's edge: a wider band there
        foot_px = max(edge_px, int(math.ceil(support_width_mm / parts.mm_per_px / 4)))
        mask &= cv2.distanceTransform((~parts.feet).view(np.uint8), cv2.DIST_L2, 3) > foot_px
    n_normal_off = 0
    if normals is not None:
        zone_px = edge_px + EDGE_NORMAL_ZONE_PX * depth_scale_px
        zone = mask & (cv2.distanceTransform(region.view(np.uint8), cv2.DIST_L2, 3) <= zone_px)
        rows, cols = np.nonzero(zone)
        cos = np.einsum(
            "mc,mc->m", np.asarray(normals[rows, cols], np.float32), geometry.normals_at(rows, cols)
        )
        turned = np.nan_to_num(cos, nan=1.0) < math.cos(math.radians(EDGE_NORMAL_DEG))
        n_normal_off = int(np.count_nonzero(turned))
        mask[rows[turned], cols[turned]] = False
    return mask, n_normal_off


def _reasons(
    parts: Parts,
    holes_area: float,
    max_dropout_mm2: float,
    n_normal_off: int,
    n_band: int,
    band_area: float,
) -> list[str]:
    """What the operator should read about the supports removed, the holes kept, the areas filled and the edge band."""
    reasons = []
    if parts.protrusions_mm2:
        reasons.append(
            f"{parts.protrusions_mm2:.0f} mm^2 of narrow parts at the plate's depth that leave its smooth surface "
            f"(supports reaching out beside the plate) excluded"
        )
    if parts.n_holes:
        reasons.append(
            f"{parts.n_holes} region(s) inside the plate kept as holes, not measured ({holes_area:.0f} mm^2, largest "
            f"{parts.largest_hole_mm2:.0f} mm^2): openings or areas without stereo depth, never filled across a depth step"
        )
    if parts.filled_mm2:
        reasons.append(
            f"{parts.filled_mm2:.0f} mm^2 of stereo dropouts inside the plate filled (each at most {max_dropout_mm2:g} mm^2)"
        )
    if parts.filled_by_normals_mm2:
        reasons.append(
            f"{parts.filled_by_normals_mm2:.0f} mm^2 of larger areas without stereo depth filled (largest "
            f"{parts.largest_by_normals_mm2:.0f} mm^2): their photometric normals follow the plate's surface within "
            f"{DROPOUT_NORMAL_DEG:g} deg"
        )
    if n_normal_off:
        reasons.append(
            f"{n_normal_off} px near the edge whose photometric normals leave the plate's surface by over "
            f"{EDGE_NORMAL_DEG:g} deg put in the edge band (a support's side, or plate and surroundings mixed)"
        )
    if n_band:
        reasons.append(
            f"edge band of {n_band} px ({band_area:.0f} mm^2) along the outline and the "
            f"openings excluded: those pixels mix plate and surroundings"
        )
    return reasons


def _area_reasons(segmented_mm2: float, target_area_mm2: float) -> list[str]:
    """A reason when the segmented area is more than 5 % over or 10 % under the target's."""
    ratio = segmented_mm2 / target_area_mm2
    if ratio > 1.05:
        return [
            f"segmented area {segmented_mm2:.0f} mm^2 is {100 * (ratio - 1):.1f} % over the target's "
            f"{target_area_mm2:.0f} mm^2: surroundings at the plate's depth may be included"
        ]
    if ratio < 0.9:
        return [
            f"segmented area {segmented_mm2:.0f} mm^2 is {100 * (1 - ratio):.1f} % under the target's "
            f"{target_area_mm2:.0f} mm^2 (openings, plate partly out of view, or unmatched areas)"
        ]
    return []
