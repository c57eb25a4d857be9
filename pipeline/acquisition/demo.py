"""The demo cell: a ``cell-config/1`` of simulated cameras and lights (and optionally a simulated
conveyor), with its calibration and target."""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

import numpy as np

from ..formats import CELL_CONFIG_FORMAT, TARGET_FORMAT, CellConfigFile, TargetFile
from ..io import calibration_document
from .cameras import simulated_plate

#: Height of the demo cell's LED ring above the plate centre, mm.
DEMO_LED_HEIGHT_MM = 2000.0
#: The demo conveyor's step between stations, mm: 2.1 m of the head's ~3.3 m view along the travel
#: at 3 m, so that neighbouring stations share about a third of it.
DEMO_STATION_SPACING_MM = 2100.0


def write_demo_cell(
    folder: str | os.PathLike[str],
    *,
    n_lights: int = 8,
    width: int = 1224,
    height: int = 1024,
    working_distance_mm: float = 3000.0,
    stations: int | None = None,
    station_spacing_mm: float = DEMO_STATION_SPACING_MM,
) -> Path:
    """Write the demo cell's configuration into ``folder``: simulated cameras and lights.

    The lights are LEDs on a ring :data:`DEMO_LED_HEIGHT_MM` above the plate centre, aimed at it
    (the simulator's near-field lights); the plate the simulated cameras see is the simulator's
    default plate (a convex cylinder of radius 5000 mm, 3000 x 3000 mm) at the working distance.
    With ``stations``, the cell has a simulated conveyor that carries a longer plate (3000 mm wide,
    3000 mm + the last station's position long, :func:`~pipeline.acquisition.cameras.simulated_plate`)
    along its length, ``direction`` the plate's own length axis in the left camera frame; the target
    is the whole plate's.

    Parameters
    ----------
    folder : str or Path
        Created if missing; ``cell.json``, ``calibration.json`` and ``target.json`` are written
        (overwritten) there.
    n_lights : int
    width, height : int
        Image size of the simulated head (:func:`pipeline.simulate.default_rig`).
    working_distance_mm : float
    stations : int, optional
        At least 2: a conveyor with stations ``0, spacing, 2 spacing, ...`` mm (``acquire_stations``);
        None: no conveyor (``acquire``, one view).
    station_spacing_mm : float
        The conveyor's step between stations, mm (> 0).

    Returns
    -------
    Path
        ``folder / "cell.json"``.
    """
    from ..simulate import CaptureSpec, default_rig, plate_pose

    if stations is not None and stations < 2:
        raise ValueError(f"stations: expected at least 2 stations, got {stations}")
    if not (math.isfinite(station_spacing_mm) and station_spacing_mm > 0):
        raise ValueError(f"station_spacing_mm: expected a step > 0 mm, got {station_spacing_mm}")
    out = Path(folder)
    out.mkdir(parents=True, exist_ok=True)
    spec = CaptureSpec(n_lights=n_lights, near_field_mm=DEMO_LED_HEIGHT_MM, led_mu=1.0)
    lights = spec.lights(np.array([0.0, 0.0, working_distance_mm]), np.ones(n_lights))
    (out / "calibration.json").write_text(
        json.dumps(calibration_document(default_rig(width=width, height=height)), indent=2) + "\n"
    )
    cell = {
        "format": CELL_CONFIG_FORMAT,
        "cell_id": "demo",
        "cameras": {"left": {"driver": "simulated"}, "right": {"driver": "simulated"}},
        "lights": {"driver": "simulated", "lights": lights.documents()},
        "calibration": "calibration.json",
        "working_distance_mm": working_distance_mm,
    }
    stations_mm = None
    if stations is not None:
        stations_mm = [k * float(station_spacing_mm) for k in range(stations)]
    plate = simulated_plate(working_distance_mm, stations_mm)
    if stations_mm is not None:
        cell["conveyor"] = {
            "driver": "simulated",
            "direction": [float(v) + 0.0 for v in -plate_pose(plate)[:3, 1]],  # no -0.0
            "stations_mm": stations_mm,
        }
    CellConfigFile.model_validate(cell)
    (out / "cell.json").write_text(json.dumps(cell, indent=2) + "\n")
    target = {
        "format": TARGET_FORMAT,
        "shape": {"type": plate.shape, "radius_mm": plate.radius_mm},
        "size_mm": list(plate.size_mm),
        "tolerance_mm": 2.0,
    }
    TargetFile.model_validate(target)
    (out / "target.json").write_text(json.dumps(target, indent=2) + "\n")
    return out / "cell.json"
