"""What a hull plate and the cell can physically be: numbers outside are refused before a job runs.

The file formats only ask for finite, positive numbers; a target radius of 1e308 mm or a light
100 km away passes them and then fails the job as an internal error (overflow, empty overlap).
These bounds are generous for any hull plate and any inspection cell; a refusal says which
bound and why.
"""

from __future__ import annotations

import math

import numpy as np

from pipeline.formats import InputError
from pipeline.io import Target
from pipeline.lights.model import Lights

#: Formed radius of a hull plate, mm: tighter than any plate is formed (bilge, bow), and flatter
#: than a plate can be told from a plane (a 3 m plate bows by about 1 mm at 1 km).
RADIUS_MM = (100.0, 1_000_000.0)
#: One side of a hull plate, mm.
SIZE_MM = (50.0, 30_000.0)
#: Largest deviation tolerance on a hull plate, mm.
MAX_TOLERANCE_MM = 100.0
#: Farthest a point (a mesh vertex, a light) can be from the plate's or the camera's origin, mm.
MAX_COORDINATE_MM = 50_000.0
#: Deepest dent (or bump) of a simulated plate, mm.
MAX_DENT_DEPTH_MM = 500.0
#: Largest radius of a simulated dent, mm.
MAX_DENT_RADIUS_MM = 5_000.0


def radius_reason(radius_mm: float) -> str:
    """The refusal of a formed radius outside :data:`RADIUS_MM`."""
    lo, hi = RADIUS_MM
    return (
        f"expected a hull plate's formed radius between {lo:.0f} mm and {hi:.0f} mm "
        f"(flatter than {hi / 1e6:g} km is a plane: shape type 'plane'), got {radius_mm:g}"
    )


def check_target(target: Target, *, label: str) -> None:
    """Refuse a loaded ``plate-target/1`` that no hull plate can be.

    Parameters
    ----------
    target : pipeline.io.Target
    label : str
        How the message names the target file.

    Raises
    ------
    InputError
        A radius, side, tolerance or mesh vertex outside the bounds of this module (names the field).
    """
    if target.radius_mm is not None and not RADIUS_MM[0] <= target.radius_mm <= RADIUS_MM[1]:
        raise InputError(label, "shape.radius_mm", radius_reason(target.radius_mm))
    for i, side in enumerate(target.size_mm):
        if not SIZE_MM[0] <= side <= SIZE_MM[1]:
            raise InputError(
                label,
                f"size_mm[{i}]",
                f"expected a hull plate's side between {SIZE_MM[0]:g} mm and {SIZE_MM[1]:g} mm, got {side:g}",
            )
    if target.tolerance_mm > MAX_TOLERANCE_MM:
        raise InputError(
            label,
            "tolerance_mm",
            f"expected a hull plate's tolerance of at most {MAX_TOLERANCE_MM:g} mm, got {target.tolerance_mm:g}",
        )
    if target.mesh_vertices_mm is not None:
        reach = float(np.abs(target.mesh_vertices_mm).max())
        if reach > MAX_COORDINATE_MM:
            raise InputError(
                label,
                "shape.file",
                f"expected mesh vertices within {MAX_COORDINATE_MM:g} mm of the mesh's origin (a hull plate, in mm), "
                f"got one {reach:g} mm away",
            )


def check_lights(lights: Lights, *, label: str, field: str) -> None:
    """Refuse point lights farther from the left camera than :data:`MAX_COORDINATE_MM`.

    ``field`` is the list of lights in the file (``"lights"``, ``"photometric.lights"``).

    Raises
    ------
    InputError
        Names the first such light.
    """
    for k in np.flatnonzero(lights.is_point):
        distance = math.hypot(*(float(v) for v in lights.positions_mm[k]))  # no overflow to inf
        if not distance <= MAX_COORDINATE_MM:
            raise InputError(
                label,
                f"{field}[{k}].position_mm",
                f"expected a light within {MAX_COORDINATE_MM:g} mm of the left camera (the cell; positions are mm), "
                f"got one {distance:g} mm away",
            )
