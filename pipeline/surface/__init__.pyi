"""The public API of :mod:`pipeline.surface` (read by type checkers, and by ``__init__.py`` to load it lazily)."""

from .fusion import Fusion, fuse_low_frequencies, smooth_stereo_depth
from .integration import integrate_gradient, integrate_normals
from .normals import METHODS, NormalField, estimate_normals
from .reconstruct import (
    Surface,
    disagrees,
    distant_surface,
    integrate_and_fuse,
    near_field_surface,
    remeasure_with_refined_lights,
)
from .stereo import StereoDepth, rectification, stereo_depth

__all__ = [
    "METHODS",
    "Fusion",
    "NormalField",
    "StereoDepth",
    "Surface",
    "disagrees",
    "distant_surface",
    "estimate_normals",
    "fuse_low_frequencies",
    "integrate_and_fuse",
    "integrate_gradient",
    "integrate_normals",
    "near_field_surface",
    "rectification",
    "remeasure_with_refined_lights",
    "smooth_stereo_depth",
    "stereo_depth",
]
