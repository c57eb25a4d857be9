"""An inspection's deviation map in the plate's own frame (:mod:`pipeline.judge.plate_map`), as the page
draws it: a tolerance-band PNG (one pixel per cell, ``y`` up) and the cells' values for the hover
read-out and the comparison of two passes.

Maps are computed from the artifact folder on first use and kept for the few inspections last
looked at (a map of a 3 m plate takes ~0.1 s from its 250k-vertex surface).
"""

from __future__ import annotations

import io
import logging
import math
from functools import lru_cache
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image

from app.models import Inspection, JobStatus
from app.schemas import StationOut
from app.storage import Storage
from pipeline.artifacts.colours import default_limit_mm, tolerance_band_colormap
from pipeline.judge.plate_map import PlateMap, load_plate_map

log = logging.getLogger(__name__)


class NoPlateMap(Exception):
    """The inspection has no plate map (not done, or its artifacts cannot give one); says why."""


def plate_map_of(storage: Storage, row: Inspection) -> PlateMap:
    """The plate map of a done inspection.

    Raises
    ------
    NoPlateMap
        The inspection is not done, or its surface.ply / details.json are missing or unreadable.
    """
    if row.status != JobStatus.DONE:
        raise NoPlateMap(f"inspection {row.id} is {row.status}; only a done inspection has a map")
    folder = storage.artifacts_dir(row.id)
    try:
        stamp = (folder / "surface.ply").stat().st_mtime_ns
    except OSError:
        raise NoPlateMap(
            f"inspection {row.id}: surface.ply: not found among its artifacts"
        ) from None
    try:
        return _cached(str(folder), stamp)
    except (OSError, ValueError) as err:
        raise NoPlateMap(f"inspection {row.id}: {err}") from None


@lru_cache(maxsize=8)
def _cached(folder: str, stamp: int) -> PlateMap:
    del stamp  # part of the key only: a rewritten surface is read again
    return load_plate_map(Path(folder))


def plate_map_png(plate: PlateMap, *, tolerance_mm: float) -> bytes:
    """The map coloured by tolerance band, one pixel per cell, first row at the largest ``y`` (so
    that the image shows the plate with ``x`` to the right and ``y`` up); transparent where no cell."""
    rows = plate.deviation_mm[::-1]
    rgb = tolerance_band_colormap(
        rows, tolerance_mm=tolerance_mm, limit_mm=default_limit_mm(tolerance_mm)
    )
    alpha = np.where(np.isfinite(rows), 255, 0).astype(np.uint8)
    buffer = io.BytesIO()
    Image.fromarray(np.dstack([rgb, alpha]), mode="RGBA").save(buffer, format="PNG", optimize=True)
    return buffer.getvalue()


def plate_map_document(
    plate: PlateMap,
    *,
    tolerance_mm: float,
    defects: list[Any],
    stations: list[StationOut] | None = None,
) -> dict[str, Any]:
    """The map as JSON (:class:`app.schemas.PlateMapOut`): its grid (cells rounded to 0.01 mm, null
    where empty, row 0 at the smallest ``y``), the tolerance, the defects, and the stations of a plate
    measured at stations (each with its outline; :func:`app.services.stations.read_stations`)."""
    values = np.round(plate.deviation_mm, 2)
    x0, x1, y0, y1 = plate.extent_mm
    return {
        "frame": "target",
        "x0_mm": plate.x0_mm,
        "y0_mm": plate.y0_mm,
        "cell_mm": plate.cell_mm,
        "extent_mm": [x0, x1, y0, y1],
        "nx": int(values.shape[1]),
        "ny": int(values.shape[0]),
        "tolerance_mm": tolerance_mm,
        "deviation_mm": [[None if math.isnan(v) else float(v) for v in row] for row in values],
        "defects": defects,
        "stations": [s.model_dump(mode="json") for s in stations or []],
    }
