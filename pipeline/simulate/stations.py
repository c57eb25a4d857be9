"""A plate longer than the view, photographed at conveyor stations: one capture bundle per station.

The conveyor carries the plate under the head along its length (the plate's ``y_p``) in steps of
``spacing_mm``; station ``k`` sees the part of the plate around ``y_p = c_k``, ``c_k = (k - (n - 1) / 2)
spacing``. Its pose is the one :func:`~pipeline.simulate.plate_pose` gives a plate centred under the
head, with the plate shifted so that ``(0, c_k)`` lies there and turned about that point's normal by
a small yaw (none at station 0)::

    T_cam_plate(k) = plate_pose(plate) @ Rz(yaw_k) @ Trans(0, -c_k, 0)

The plate moves along ``direction = -plate_pose(plate)[:3, 1]`` (left camera frame); its true travel
since station 0 is ``k spacing``, the encoder's reading of it (written into each bundle's ``station``)
is off by up to ``encoder_error_mm``. Every station renders the same plate (one texture, one target of
the whole plate) with its own noise and light intensities.
"""

from __future__ import annotations

import json
import math
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np

from ..camera import StereoRig
from .capture import CaptureSpec, simulate_capture
from .geometry import plate_pose
from .rig import rot_z
from .scene import PlateSpec

#: The default plate: 3 m wide, 9 m long.
LONG_PLATE = PlateSpec(size_mm=(3000.0, 9000.0))
_CAPTURE = CaptureSpec()
#: A station's yaw and encoder error are drawn uniformly within +- the given bounds from this stream.
_STREAM = 7919


def station_pose(plate: PlateSpec, centre_y_mm: float, yaw_deg: float) -> np.ndarray:
    """``T_cam_plate`` (4, 4) of the plate with its point ``(0, centre_y_mm)`` under the head, yawed.

    Parameters
    ----------
    plate : PlateSpec
    centre_y_mm : float
        Plate coordinate ``y_p`` (mm) of the point on the optical axis.
    yaw_deg : float
        Turn about the plate's normal at that point, degrees.

    Returns
    -------
    (4, 4) float64
    """
    shift = np.eye(4)
    shift[1, 3] = -float(centre_y_mm)
    turn = np.eye(4)
    turn[:3, :3] = rot_z(math.radians(yaw_deg))
    pose: np.ndarray = plate_pose(plate) @ turn @ shift
    return pose


def carried_pose(
    plate: PlateSpec,
    *,
    first_centre_y_mm: float,
    travel_mm: float,
    direction: np.ndarray,
    yaw_deg: float = 0.0,
) -> np.ndarray:
    """``T_cam_plate`` (4, 4) of a plate that a conveyor carried ``travel_mm`` along ``direction``.

    At station 0 the plate lies as :func:`station_pose` puts it with its point ``(0,
    first_centre_y_mm)`` under the head; the conveyor translates it by ``travel_mm * direction``
    (left camera frame), and the plate then turns by ``yaw_deg`` about its normal through the point
    under the head (:func:`~pipeline.simulate.plate_pose`'s origin). With ``direction = -plate_pose(
    plate)[:3, 1]`` this is ``station_pose(plate, first_centre_y_mm + travel_mm, yaw_deg)``; another
    direction carries the plate across or out of its own plane, as a conveyor not aligned with the
    plate would.

    Parameters
    ----------
    plate : PlateSpec
    first_centre_y_mm : float
        Plate coordinate ``y_p`` (mm) under the head at station 0.
    travel_mm : float
        The plate's true travel since station 0, mm.
    direction : (3,) float
        Unit direction of the travel, left camera frame.
    yaw_deg : float
        Degrees.

    Returns
    -------
    (4, 4) float64
    """
    base = plate_pose(plate)
    pose = station_pose(plate, first_centre_y_mm, 0.0)
    pose[:3, 3] += float(travel_mm) * np.asarray(direction, np.float64)
    axis = base[:3, 2] * math.radians(yaw_deg)
    turn = np.eye(4)
    turn[:3, :3] = cv2.Rodrigues(axis.reshape(3, 1))[0]
    turn[:3, 3] = base[:3, 3] - turn[:3, :3] @ base[:3, 3]
    carried: np.ndarray = turn @ pose
    return carried


def simulate_stations(
    out_dir: str | Path,
    *,
    n_stations: int,
    spacing_mm: float,
    plate: PlateSpec = LONG_PLATE,
    capture: CaptureSpec = _CAPTURE,
    rig: StereoRig | None = None,
    plate_id: str = "SIM-0001",
    tolerance_mm: float = 2.0,
    seed: int = 0,
    encoder_error_mm: float = 4.0,
    yaw_deg: float = 0.3,
    workers: int | None = None,
) -> list[Path]:
    """Render the stations of a long plate: ``out_dir/station_00``, ``station_01``, ... (one bundle each).

    Parameters
    ----------
    out_dir : str or Path
    n_stations : int
        At least 2.
    spacing_mm : float
        The conveyor's true step between stations, mm (> 0).
    plate : PlateSpec
        The whole plate (its target, written into every bundle and ``out_dir/target.json``, is the
        whole plate); its ``y_p`` runs along the conveyor.
    capture : CaptureSpec
    rig : StereoRig or None
    plate_id : str
    tolerance_mm : float
    seed : int
        Seeds the plate's texture (the same at every station), each station's noise and lights, the
        encoder errors and the yaws.
    encoder_error_mm : float
        The encoder's reading of each travel (station 1 on) is off by a uniform error within +- this, mm.
    yaw_deg : float
        Each station (1 on) is turned by a uniform yaw within +- this, degrees.
    workers : int, optional

    Returns
    -------
    list of Path
        The bundles in station order. ``out_dir/stations_truth.json`` holds the true travels (mm),
        the encoder's, the yaws (deg) and the direction.
    """
    if n_stations < 2:
        raise ValueError(f"n_stations: expected at least 2 stations, got {n_stations}")
    if not (math.isfinite(spacing_mm) and spacing_mm > 0):
        raise ValueError(f"spacing_mm: expected a step > 0 mm, got {spacing_mm}")
    if not (math.isfinite(encoder_error_mm) and encoder_error_mm >= 0):
        raise ValueError(f"encoder_error_mm: expected >= 0, got {encoder_error_mm}")
    if not (math.isfinite(yaw_deg) and 0 <= yaw_deg < 5):
        raise ValueError(f"yaw_deg: expected in [0, 5), got {yaw_deg}")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng([int(seed), _STREAM])
    if capture.albedo_seed is None:  # one plate, one texture at every station
        capture = replace(capture, albedo_seed=int(rng.integers(2**31)))
    direction = -plate_pose(plate)[:3, 1]
    travel = spacing_mm * np.arange(n_stations)
    encoder = travel + np.r_[0.0, rng.uniform(-encoder_error_mm, encoder_error_mm, n_stations - 1)]
    yaws = np.r_[0.0, rng.uniform(-yaw_deg, yaw_deg, n_stations - 1)]
    centres = (np.arange(n_stations) - (n_stations - 1) / 2.0) * spacing_mm
    bundles = []
    for k in range(n_stations):
        station = {
            "index": k,
            "travel_mm": round(float(encoder[k]), 3),
            "direction": [float(v) for v in direction],
        }
        bundles.append(
            simulate_capture(
                out / f"station_{k:02d}",
                plate=plate,
                capture=capture,
                rig=rig,
                plate_id=plate_id,
                tolerance_mm=tolerance_mm,
                seed=int(seed) * 1000 + k,
                workers=workers,
                pose=station_pose(plate, float(centres[k]), float(yaws[k])),
                station=station,
            )
        )
    (out / "target.json").write_text((bundles[0] / "target.json").read_text())
    truth = {
        "travel_mm": travel.tolist(),
        "encoder_mm": encoder.tolist(),
        "yaw_deg": yaws.tolist(),
        "centre_y_mm": centres.tolist(),
        "direction": direction.tolist(),
    }
    (out / "stations_truth.json").write_text(json.dumps(truth, indent=2) + "\n")
    return bundles
