"""The cell simulator: what the binocular head with a ring of lights sees, rendered from a known truth.

A plate is a height field ``h(x_p, y_p)`` in a *plate frame* (x_p, y_p in the plate's plane, z_p
pointing away from the cameras, origin at the plate centre, ``h(0, 0) = 0``); ``T_cam_plate`` maps
plate-frame points into the left-camera frame. Every pixel of a camera is rendered as a real
calibrated camera sees it: the raw (distorted) pixel centre is undistorted to its ray with the
camera's K and distortion (iterative ``cv2.undistortPoints``), the ray is intersected with the
surface (analytic for plane, cylinder and sphere; Newton steps along the ray for the saddle and for
dents), and the surface point is shaded there (:mod:`~pipeline.simulate.capture`). No orthographic
shortcut.

Pixels off the plate see a dark, slightly textured conveyor plane behind it (lit by the same
lights). The albedo is a painted/rusty texture fixed to the plate (a function of plate coordinates),
so both cameras see the same texture. The plate's material may have another outline than its size's
rectangle (``PlateSpec.outline``) and openings (``PlateSpec.cutouts``); rays that miss the material
see what lies behind it. Instead of the conveyor a plate may lie over a lit, textured shop floor with
supports standing on it (``PlateSpec.floor``), shaded by the same lights (no cast shadows, no
interreflections). With these options off the bundle is bit-identical to what it was without them.

Modules, one job each:

- :mod:`~pipeline.simulate.scene`: what the cell holds (:class:`PlateSpec`, dents, openings, floor, supports);
- :mod:`~pipeline.simulate.geometry`: the plate's pose, outline and height field, rays cast into the scene;
- :mod:`~pipeline.simulate.texture`: the plate's, the conveyor's and the floor's albedo;
- :mod:`~pipeline.simulate.rig`: the simulated binocular head and its sensor;
- :mod:`~pipeline.simulate.capture`: :func:`simulate_capture`, a capture bundle with its truth;
- :mod:`~pipeline.simulate.stations`: :func:`simulate_stations`, a plate longer than the view at conveyor stations;
- :mod:`~pipeline.simulate.targets`: the nominal target written with it (analytic or a mesh);
- :mod:`~pipeline.simulate.boards`: :func:`render_calibration_pairs`, checkerboard pairs for calibration.

Conventions (docs/formats.md): mm, pixels, radians in code (degrees only in the spec dataclasses, named
``*_deg``); OpenCV camera frame (x right, y down, z forward); left camera = reference frame;
``X_right = R @ X_left + T``; light directions are unit vectors from the surface towards the light
(``l_z < 0``); normals point out of the surface towards the cameras (``n_z < 0``).
"""

from .boards import render_calibration_pairs
from .capture import CaptureSpec, render_radiance, simulate_capture
from .geometry import (
    SURFACE_CONVEYOR,
    SURFACE_FLOOR,
    SURFACE_PLATE,
    SURFACE_SUPPORT,
    outline_polygon,
    plate_height,
    plate_pose,
    plate_region,
)
from .rig import default_rig
from .scene import (
    CURVED_SAGITTA,
    TRAPEZOID_TOP,
    Cutout,
    Dent,
    Floor,
    OutlineName,
    PlateSpec,
    ShapeName,
    Support,
    rail_supports,
)
from .stations import carried_pose, simulate_stations, station_pose
from .targets import plate_mesh

__all__ = [
    "CURVED_SAGITTA",
    "SURFACE_CONVEYOR",
    "SURFACE_FLOOR",
    "SURFACE_PLATE",
    "SURFACE_SUPPORT",
    "TRAPEZOID_TOP",
    "CaptureSpec",
    "Cutout",
    "Dent",
    "Floor",
    "OutlineName",
    "PlateSpec",
    "ShapeName",
    "Support",
    "carried_pose",
    "default_rig",
    "outline_polygon",
    "plate_height",
    "plate_mesh",
    "plate_pose",
    "plate_region",
    "rail_supports",
    "render_calibration_pairs",
    "render_radiance",
    "simulate_capture",
    "simulate_stations",
    "station_pose",
]
