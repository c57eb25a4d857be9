"""The virtual templates of a result page: frames at a spacing, through each defect and through a
point the operator chose on the plate map, with each frame's line in the target's frame for the map.
"""

from __future__ import annotations

import json
import logging
import math
from dataclasses import replace
from pathlib import Path
from typing import Annotated

import numpy as np
from fastapi import Query

from app.errors import scrub_paths
from app.models import Inspection, JobStatus
from app.storage import Storage
from pipeline.plate_map import to_target_frame
from pipeline.sections import load_sections
from web.charts import SectionDrawing, section_drawings

logger = logging.getLogger(__name__)

#: Frame spacings offered for the virtual templates, mm.
SPACINGS_MM = (300, 500, 700, 1000)
DEFAULT_SPACING_MM = 700
#: The ``spacing_mm`` query parameter of the virtual templates, mm.
SpacingQuery = Annotated[
    int, Query(ge=50, le=10_000, description="frame spacing of the virtual templates, mm")
]
#: ``at_x`` / ``at_y``: a point of the plate (target frame, mm) to put one more frame through.
PointQuery = Annotated[
    float | None,
    Query(ge=-100_000, le=100_000, description="a point of the plate, target frame, mm"),
]


def chosen_point(at_x: float | None, at_y: float | None) -> tuple[float, float] | None:
    """The chosen point when both coordinates are given and finite, else None."""
    if at_x is None or at_y is None or not (math.isfinite(at_x) and math.isfinite(at_y)):
        return None
    return (at_x, at_y)


def templates_context(
    storage: Storage, row: Inspection, spacing_mm: int, chosen: tuple[float, float] | None = None
) -> dict:
    """``drawings`` (:class:`web.charts.SectionDrawing`, each with its line on the map),
    ``templates_error`` (why there are none), and the ``chosen`` point."""
    if row.status != JobStatus.DONE:
        return {"drawings": [], "templates_error": None, "chosen": chosen}
    folder = storage.artifacts_dir(row.id)
    try:
        frame, sections, tolerance = load_sections(
            folder, spacing_mm=float(spacing_mm), chosen_xy_mm=[chosen] if chosen else []
        )
    except (OSError, ValueError, KeyError) as err:
        logger.warning("inspection %s: no virtual templates: %s", row.id, err)
        return {"drawings": [], "templates_error": scrub_paths(str(err)), "chosen": chosen}
    drawings = section_drawings(sections, tolerance_mm=tolerance)
    T = _registration(folder)
    if T is not None:  # each frame's line on the map and its place, in the target's frame
        half_mm = 0.5 * (frame.along_range_mm[1] - frame.along_range_mm[0])
        drawings = [
            _in_target_frame(
                drawing, to_target_frame(frame.line_mm(s.position_mm), T)[:, :2], half_mm
            )
            for drawing, s in zip(drawings, sections, strict=True)
        ]
    return {"drawings": drawings, "templates_error": None, "chosen": chosen}


#: The plate's edges as the map names them (target frame, origin at the centre): A where y is
#: smallest, then counter-clockwise.
EDGES = {("y", -1): "A", ("x", 1): "B", ("y", 1): "C", ("x", -1): "D"}


def _signed_mm(value: float) -> str:
    """``-803.4`` -> ``"−803"``, ``0.3`` -> ``"0"`` (no minus zero), ``12`` -> ``"+12"``."""
    rounded = round(value)
    return "0" if rounded == 0 else f"{rounded:+d}".replace("-", "\u2212")


def _in_target_frame(drawing: SectionDrawing, ends_xy: np.ndarray, half_mm: float):
    """A template with its line (target frame, mm), its place ("x = −803 mm, 697 mm from edge D")
    and the edges at its drawing's ends; ``ends_xy`` (2, 2) the line's ends, ``half_mm`` half the
    target's size along the frames' direction."""
    (x0, y0), (x1, y1) = ends_xy
    runs_along_y = abs(y1 - y0) >= abs(x1 - x0)
    at, run = ("x", "y") if runs_along_y else ("y", "x")
    value = 0.5 * (x0 + x1) if runs_along_y else 0.5 * (y0 + y1)
    near = -1 if round(value) <= 0 else 1
    from_edge = half_mm - abs(value)
    where = f"{at} = {_signed_mm(value)} mm, {from_edge:.0f} mm from edge {EDGES[(at, near)]}"
    start, end = (y0, y1) if runs_along_y else (x0, x1)
    ends = tuple(
        f"edge {EDGES[(run, -1 if v < 0 else 1)]} ({run} {_signed_mm(v)})" for v in (start, end)
    )
    line = " ".join(f"{v:.1f}" for v in np.ravel(ends_xy))
    return replace(drawing, line_mm=line, where=where, ends=ends)


def _registration(folder: Path) -> list[list[float]] | None:
    """details.json's ``T_cam_target``; None when the inspection has no readable one."""
    try:
        return json.loads((folder / "details.json").read_text())["T_cam_target"]
    except (OSError, ValueError, KeyError):
        return None
