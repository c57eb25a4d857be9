"""The target's frame in the operator's words, shared by the dashboard (:mod:`web.template_views`)
and the PDF report (:mod:`app.report`): the plate's edges named as on the map (A where the target's
y is smallest, then B, C, D counter-clockwise; origin at the target's centre) and each virtual
template's place ("x = −803 mm, 697 mm from edge D").
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.judge.plate_map import to_target_frame
from pipeline.judge.sections import PlateFrame, Section

#: The plate's edges: (axis, side) -> name.
EDGES = {("y", -1): "A", ("x", 1): "B", ("y", 1): "C", ("x", -1): "D"}


@dataclass(frozen=True)
class FramePlace:
    """Where a template frame lies in the target's frame.

    Attributes
    ----------
    where : str, "x = −803 mm, 697 mm from edge D".
    ends : (str, str), the frame line's first and last ends: "edge A (y −1500)", "edge C (y +1500)".
    line_mm : (2, 2) float, the line's ends (x, y) in the target's frame, mm.
    """

    where: str
    ends: tuple[str, str]
    line_mm: np.ndarray


def signed_mm(value: float) -> str:
    """``-803.4`` -> ``"−803"``, ``0.3`` -> ``"0"`` (no minus zero), ``12`` -> ``"+12"``."""
    rounded = round(value)
    return "0" if rounded == 0 else f"{rounded:+d}".replace("-", "\u2212")


def frame_place(ends_xy: np.ndarray, half_mm: float) -> FramePlace:
    """The place of a frame line whose ends are ``ends_xy`` ((2, 2), target frame, mm) on a target
    ``2 half_mm`` long across the frames (the line runs along x or y)."""
    ends_xy = np.asarray(ends_xy, dtype=np.float64)
    (x0, y0), (x1, y1) = ends_xy
    runs_along_y = abs(y1 - y0) >= abs(x1 - x0)
    at, run = ("x", "y") if runs_along_y else ("y", "x")
    value = 0.5 * (x0 + x1) if runs_along_y else 0.5 * (y0 + y1)
    near = -1 if round(value) <= 0 else 1
    where = (
        f"{at} = {signed_mm(value)} mm, {half_mm - abs(value):.0f} mm from edge {EDGES[(at, near)]}"
    )
    start, end = (y0, y1) if runs_along_y else (x0, x1)
    first, last = (
        f"edge {EDGES[(run, -1 if v < 0 else 1)]} ({run} {signed_mm(v)})" for v in (start, end)
    )
    return FramePlace(where=where, ends=(first, last), line_mm=ends_xy)


def frame_places(
    artifact_dir: Path, frame: PlateFrame, sections: list[Section]
) -> list[FramePlace] | None:
    """Each section's place in the target's frame (details.json's registration); None when the
    inspection has no readable registration."""
    try:
        details = json.loads((Path(artifact_dir) / "details.json").read_text())
        T = details["T_cam_target"]
    except (OSError, ValueError, KeyError):
        return None
    half_mm = 0.5 * (frame.along_range_mm[1] - frame.along_range_mm[0])
    return [
        frame_place(to_target_frame(frame.line_mm(s.position_mm), T)[:, :2], half_mm)
        for s in sections
    ]
