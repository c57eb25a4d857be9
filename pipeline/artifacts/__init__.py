"""Result artifacts of an inspection: the measured surface mesh, the deviation map, normals, depth; their file names.

All coordinates are millimetres in the left camera frame (OpenCV: x right,
y down, z forward into the scene). Deviation is signed: positive where the
measured surface lies on the cameras' side of the target ("above", red),
negative where it lies away from the cameras ("below", blue).

One colour map serves the PNG, the PLY vertex colours and the 3D viewer
(the 3D view, ``app/viewer``, colours with it): a diverging blue - white - red scale
saturated at ``+/- limit_mm``. With the default ``limit_mm = 2 * tolerance_mm``
the light blue and orange stops sit exactly at ``-/+ tolerance_mm``, so
everything out of tolerance is drawn in the darker half of the scale.

Modules: :mod:`~pipeline.artifacts.colours` (the colour map), :mod:`~pipeline.artifacts.ply` (surface.ply,
target.ply), :mod:`~pipeline.artifacts.png` (deviation.png, normals.png), :mod:`~pipeline.artifacts.depth`
(depth.npy), :mod:`~pipeline.artifacts.checks` (argument checks).
"""

from .colours import COLOUR_STOPS, NO_DATA_RGB, default_limit_mm, deviation_colormap
from .depth import save_depth
from .ply import write_surface_ply, write_target_ply
from .png import (
    MAX_PNG_HEIGHT,
    MAX_PNG_WIDTH,
    MIN_PNG_HEIGHT,
    write_deviation_png,
    write_normals_png,
)
from .uncertainty import UNCERTAINTY_FILES, write_uncertainty

#: File names of an inspection's artifacts in its output folder, keyed as ``plate-result/1``'s ``artifacts``.
ARTIFACT_FILES = {
    "surface": "surface.ply",
    "target_surface": "target.ply",
    "deviation_map": "deviation.png",
    "normals": "normals.png",
    "depth": "depth.npy",
    "details": "details.json",
    **UNCERTAINTY_FILES,
}
#: File name of the ``plate-result/1`` document beside them.
RESULT_FILE = "result.json"

__all__ = [
    "ARTIFACT_FILES",
    "COLOUR_STOPS",
    "MAX_PNG_HEIGHT",
    "MAX_PNG_WIDTH",
    "MIN_PNG_HEIGHT",
    "NO_DATA_RGB",
    "RESULT_FILE",
    "default_limit_mm",
    "deviation_colormap",
    "save_depth",
    "write_deviation_png",
    "write_normals_png",
    "write_surface_ply",
    "write_target_ply",
    "write_uncertainty",
]
