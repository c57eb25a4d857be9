"""The segmentation's result: where the plate is on the left undistorted grid, and what was left out."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Segmentation:
    """Where the plate is on the left undistorted grid, and what was left out.

    Attributes
    ----------
    mask : (H, W) bool
        The plate's pixels to measure (edge band excluded).
    edge_band : (H, W) bool
        Plate pixels within ``edge_px`` of the plate's outline or of an opening, excluded from
        ``mask`` because they may mix plate and surroundings.
    holes : (H, W) bool
        Regions enclosed by the plate that are not measured: openings (depth behind the plate or
        dark) and areas the stereo pair could not match that are too large to fill.
    surface_depth_mm : (H, W) float32
        Depth of the fitted smooth surface (mm, every pixel; NaN where it does not face the camera
        or in brightness-only mode).
    surroundings_step_mm : (H, W) float32
        At plate pixels (``mask | edge_band``) within ``step_zone_px`` of the plate's boundary: the
        stereo depth of the nearest pixel beside the plate that has one, minus the fitted surface's
        depth here (mm; positive when the surroundings lie behind the plate, away from the cameras);
        ``+inf`` where darkness (no depth: a dark background) is nearer; NaN elsewhere and where
        neither is near (a wide unmatched strip).
    pixel_area_mm2 : (H, W) float32
        Area of the fitted surface one pixel sees, mm^2 (NaN in brightness-only mode).
    plate_area_mm2, edge_band_area_mm2, holes_area_mm2, filled_area_mm2 : float
        Areas on the fitted surface (NaN in brightness-only mode), mm^2: the mask, the edge band, the
        holes kept, and the unmatched areas filled (dropouts, or with agreeing normals).
    n_mask, n_edge_band, n_holes, n_hole_pixels, n_off_depth, n_dark, n_unmatched : int
        Pixels in the mask and edge band; openings and unmatched
        regions kept as holes (count and pixels); candidate pixels whose stereo depth lies off the
        plate's surface; dark pixels; candidate pixels without stereo depth.
    fit_rms_mm : float
        Robust RMS (1.4826 MAD) of the stereo depth about the fitted surface over the plate, mm
        (NaN in brightness-only mode).
    depth_band_mm : float
        The band used.
    method : {"stereo", "brightness"}
    reasons : tuple of str
        What the segmentation decided that the operator should be able to read (fallbacks, holes
        kept, dropouts filled, edge band, area against the target's).
    """

    mask: np.ndarray
    edge_band: np.ndarray
    holes: np.ndarray
    surface_depth_mm: np.ndarray
    surroundings_step_mm: np.ndarray
    pixel_area_mm2: np.ndarray
    plate_area_mm2: float
    edge_band_area_mm2: float
    holes_area_mm2: float
    filled_area_mm2: float
    n_mask: int
    n_edge_band: int
    n_holes: int
    n_hole_pixels: int
    n_off_depth: int
    n_dark: int
    n_unmatched: int
    fit_rms_mm: float
    depth_band_mm: float
    method: str
    reasons: tuple[str, ...]

    def stereo_prior(self, depth_mm: np.ndarray | None) -> np.ndarray:
        """The stereo depth to fuse with the normals: ``depth_mm`` (H, W) where the mask is and the depth lies
        within the band of the plate's surface, NaN elsewhere (mm; so a filled dropout, an edge band or a
        stray match of the floor never pulls the surface)."""
        d = np.asarray(depth_mm, dtype=np.float32)
        if d.shape != self.mask.shape:
            raise ValueError(f"depth_mm: expected shape {self.mask.shape}, got {d.shape}")
        if self.method != "stereo":
            return np.where(self.mask, d, np.float32(np.nan))
        with np.errstate(invalid="ignore"):
            near = np.abs(d - self.surface_depth_mm) < self.depth_band_mm
        return np.where(self.mask & near, d, np.float32(np.nan))

    @property
    def region(self) -> np.ndarray:
        """(H, W) bool: every pixel segmented as plate, ``mask | edge_band``."""
        both: np.ndarray = self.mask | self.edge_band
        return both

    def area_ratio(self, target_area_mm2: float) -> float:
        """Segmented plate area (mask and edge band) over the target's area (dimensionless)."""
        if not (math.isfinite(target_area_mm2) and target_area_mm2 > 0):
            raise ValueError(
                f"target_area_mm2: expected a positive area in mm^2, got {target_area_mm2}"
            )
        return (self.plate_area_mm2 + self.edge_band_area_mm2) / target_area_mm2
