"""The virtual templates of a result page: frames at a spacing, through each defect and through a
point the operator chose on the plate map, with each frame's line in the target's frame for the map.
"""

from __future__ import annotations

import logging
import math
from dataclasses import replace
from typing import Annotated, Any

import numpy as np
from fastapi import Query

from app.errors import scrub_paths
from app.models import Inspection, JobStatus
from app.plate_frame import frame_places
from app.storage import Storage
from pipeline.judge.sections import load_sections
from web.charts import section_drawings

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
) -> dict[str, Any]:
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
    places = frame_places(folder, frame, sections)
    if places is not None:  # each frame's line on the map and its place, in the target's frame
        drawings = [
            replace(
                drawing,
                line_mm=" ".join(f"{v:.1f}" for v in np.ravel(place.line_mm)),
                where=place.where,
                ends=place.ends,
            )
            for drawing, place in zip(drawings, places, strict=True)
        ]
    return {"drawings": drawings, "templates_error": None, "chosen": chosen}
