"""The public API of :mod:`pipeline.lights` (read by type checkers, and by ``__init__.py`` to load it lazily)."""

from .calibration import calibrate_lights
from .model import CAMERA_HEAD_RADIUS_MM, Lights, light_vectors_block
from .nearfield import estimate_normals_near
from .refinement import LightRefinement, refine_lights

__all__ = [
    "CAMERA_HEAD_RADIUS_MM",
    "LightRefinement",
    "Lights",
    "calibrate_lights",
    "estimate_normals_near",
    "light_vectors_block",
    "refine_lights",
]
