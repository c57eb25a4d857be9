"""The stations of one plate checked as a set before any image is decoded, in station order.

Bad input (exit 2), each named by its bundle and field: a bundle without ``station``, a missing or
duplicate index, another plate's id, directions that disagree, travels that do not increase, or
consecutive stations whose views do not overlap by :data:`MIN_OVERLAP` of the view along the travel.
"""

from __future__ import annotations

import itertools
import math
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..camera import StereoRig
from ..formats import InputError, Station
from ..io import Capture, CaptureHeader, read_capture_header

#: Consecutive stations must share at least this fraction of the view along the travel.
MIN_OVERLAP = 0.1
#: Stations' directions of travel must agree within this angle, degrees.
MAX_DIRECTION_SPREAD_DEG = 2.0
#: Without a working distance the overlap is judged at this depth, mm (the stages' nominal one).
NOMINAL_DISTANCE_MM = 3500.0


@dataclass(frozen=True)
class StationRef:
    """One station's bundle as far as the set's checks need it (nothing decoded).

    Attributes
    ----------
    source : Capture or Path
        The bundle (a path) or the capture already loaded.
    label : str
        How errors name its capture.json.
    plate_id : str
    station : pipeline.formats.Station
    rig : StereoRig
    working_distance_mm : float or None
    """

    source: Capture | Path
    label: str
    plate_id: str
    station: Station
    rig: StereoRig
    working_distance_mm: float | None

    @property
    def direction(self) -> np.ndarray:
        """(3,) unit direction of the plate's motion, left camera frame."""
        d = np.asarray(self.station.direction, dtype=np.float64)
        unit: np.ndarray = d / np.linalg.norm(d)
        return unit


def plan_stations(
    captures: Sequence[Capture | str | os.PathLike[str]],
    *,
    headers: Mapping[Path, CaptureHeader] | None = None,
) -> list[StationRef]:
    """The stations of one plate, checked as a set and sorted by index.

    Parameters
    ----------
    captures : list of Capture or path
        Two or more capture bundles (``plate-capture/1`` with ``station``), in any order.
    headers : dict of Path to CaptureHeader, optional
        Headers the caller has read already (:func:`pipeline.io.read_capture_header`), by bundle
        path: those bundles are not read again.

    Returns
    -------
    list of StationRef
        Indices ``0 .. n - 1`` in order.

    Raises
    ------
    pipeline.formats.InputError
        Naming the bundle and the field (see the module docstring).
    """
    known = headers or {}
    refs = [
        station_ref(c, None if isinstance(c, Capture) else known.get(Path(c))) for c in captures
    ]
    first = refs[0]
    for ref in refs[1:]:
        if ref.plate_id != first.plate_id:
            raise InputError(
                ref.label,
                "plate_id",
                f"expected the stations of one plate, got {ref.plate_id!r} beside {first.plate_id!r} ({first.label})",
            )
    seen: dict[int, StationRef] = {}
    for ref in refs:
        other = seen.get(ref.station.index)
        if other is not None:
            raise InputError(
                ref.label,
                "station.index",
                f"duplicate station index {ref.station.index} (also {other.label})",
            )
        seen[ref.station.index] = ref
    ordered = [seen[i] for i in sorted(seen)]
    for i, ref in enumerate(ordered):
        if ref.station.index != i:
            raise InputError(
                ref.label,
                "station.index",
                f"expected stations 0 .. {len(ordered) - 1} with none missing, station {i} is missing "
                f"(this one is {ref.station.index})",
            )
    _check_travel(ordered)
    return ordered


def view_length_mm(ref: StationRef) -> float:
    """The view's length along the travel at the plate's depth, mm (the image's extent along the
    travel's image direction, at the working distance or :data:`NOMINAL_DISTANCE_MM`)."""
    K = ref.rig.left.K
    width, height = ref.rig.image_size
    d = ref.direction
    z = ref.working_distance_mm or NOMINAL_DISTANCE_MM
    along = math.hypot(d[0], d[1])
    if along < 1e-6:
        return 0.0
    # the image's extent along (dx, dy): the longest segment of that direction through the frame
    cx, cy = abs(d[0]) / along, abs(d[1]) / along
    span_px = min(width / cx if cx > 1e-9 else math.inf, height / cy if cy > 1e-9 else math.inf)
    mm_per_px = z / math.sqrt(K[0, 0] * K[1, 1])
    return float(span_px * mm_per_px / along)  # travel moves the image by `along` of itself


def _check_travel(ordered: list[StationRef]) -> None:
    """Directions that agree, travels that increase from 0 and views that overlap."""
    first = ordered[0]
    if abs(first.station.travel_mm) > 1e-6:
        raise InputError(
            first.label,
            "station.travel_mm",
            f"expected 0 at station 0 (travel is counted from it), got {first.station.travel_mm:g}",
        )
    for prev, ref in itertools.pairwise(ordered):
        cos = float(np.clip(ref.direction @ first.direction, -1.0, 1.0))
        angle = math.degrees(math.acos(cos))
        if angle > MAX_DIRECTION_SPREAD_DEG:
            raise InputError(
                ref.label,
                "station.direction",
                f"expected the direction of station 0 within {MAX_DIRECTION_SPREAD_DEG:g} deg, got {angle:.1f} deg off",
            )
        step = ref.station.travel_mm - prev.station.travel_mm
        length = view_length_mm(ref)
        if not step > 0:
            raise InputError(
                ref.label,
                "station.travel_mm",
                f"expected more travel than station {prev.station.index} ({prev.station.travel_mm:g} mm), "
                f"got {ref.station.travel_mm:g} mm",
            )
        if step > (1.0 - MIN_OVERLAP) * length:
            raise InputError(
                ref.label,
                "station.travel_mm",
                f"no overlap with station {prev.station.index}: {step:.0f} mm of travel between them, the view "
                f"is {length:.0f} mm long along it (at most {(1.0 - MIN_OVERLAP) * length:.0f} mm keeps "
                f"{100 * MIN_OVERLAP:.0f} % overlap)",
            )


def station_ref(
    capture: Capture | str | os.PathLike[str], header: CaptureHeader | None = None
) -> StationRef:
    """One bundle's station reference (its header only, for a path: ``header`` when read already);
    InputError naming the bundle when it has no ``station``."""
    if isinstance(capture, Capture):
        label = str(capture.source)
        plate_id, station, rig, wd = (
            capture.plate_id,
            capture.station,
            capture.rig,
            capture.working_distance_mm,
        )
        source: Capture | Path = capture
    else:
        header = header or read_capture_header(capture)
        label = header.label
        plate_id, station, rig, wd = (
            header.plate_id,
            header.station,
            header.rig,
            header.working_distance_mm,
        )
        source = Path(capture)
    if station is None:
        raise InputError(
            label,
            "station",
            "expected a station (index, travel_mm, direction) in every bundle of a plate measured at stations",
        )
    return StationRef(
        source=source,
        label=label,
        plate_id=plate_id,
        station=station,
        rig=rig,
        working_distance_mm=wd,
    )
