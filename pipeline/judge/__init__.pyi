"""The public API of :mod:`pipeline.judge` (read by type checkers, and by ``__init__.py`` to load it lazily)."""

from .area import pixel_area_mm2
from .curvature import CurvatureResult, principal_curvatures
from .details import Details
from .deviation import deviation_map
from .fits import CylinderFit, PlaneFit, SphereFit, fit_cylinder, fit_plane, fit_sphere
from .outline import beyond_outline
from .plate_map import PlateMap, load_plate_map, plate_map
from .registration import Registration, register_to_target
from .sections import PlateFrame, Section, cut_sections, load_sections
from .target_geometry import target_area_mm2, target_surface
from .uncertainty import CAPABLE_RATIO, COVERAGE_K, Uncertainty, propagate
from .verdict import Judgement, judge

__all__ = [
    "CAPABLE_RATIO",
    "COVERAGE_K",
    "CurvatureResult",
    "CylinderFit",
    "Details",
    "Judgement",
    "PlaneFit",
    "PlateFrame",
    "PlateMap",
    "Registration",
    "Section",
    "SphereFit",
    "Uncertainty",
    "beyond_outline",
    "cut_sections",
    "deviation_map",
    "fit_cylinder",
    "fit_plane",
    "fit_sphere",
    "judge",
    "load_plate_map",
    "load_sections",
    "pixel_area_mm2",
    "plate_map",
    "principal_curvatures",
    "propagate",
    "register_to_target",
    "target_area_mm2",
    "target_surface",
]
