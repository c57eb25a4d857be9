"""The Calibration page's light calibration: rows of its table and its plan view (numbers only, no markup).

Positions are in the left camera's frame (OpenCV: x right, y down, z towards the plate), mm.
The plan view looks along the cameras' optical axis, so it is oriented like the camera's image:
x to the right, y down.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np


@dataclass(frozen=True)
class LightRow:
    """One light of a ``light-calibration/1`` document, rounded for reading (no ``-0.0``)."""

    index: int
    position_mm: tuple[float, float, float]  # one decimal
    axis: tuple[float, float, float] | None  # two decimals; None: isotropic
    mu: float
    intensity: float


@dataclass(frozen=True)
class PlanLight:
    index: int
    x: float  # px
    y: float  # px
    aim_x: float  # px: end of the axis' projection (where the LED points, in plan)
    aim_y: float


@dataclass(frozen=True)
class LightPlan:
    """Screen geometry (px, y down) of the lights seen from the cameras, camera head at ``(cx, cy)``."""

    size: float
    cx: float
    cy: float
    lights: list[PlanLight]
    scale_px: float  # length of the scale bar, px
    scale_mm: float  # what it stands for, mm


def _rounded(values: Sequence[float], digits: int) -> tuple[float, float, float]:
    x, y, z = (round(float(v), digits) + 0.0 for v in values)  # + 0.0 turns -0.0 into 0.0
    return x, y, z


def light_rows(document: dict[str, Any]) -> list[LightRow]:
    """The table rows of a stored (validated) ``light-calibration/1`` document, in image order."""
    rows = []
    for k, light in enumerate(document["lights"]):
        axis = light.get("axis")
        rows.append(
            LightRow(
                index=k,
                position_mm=_rounded(light["position_mm"], 1),
                axis=None if axis is None else _rounded(axis, 2),
                mu=float(light.get("mu") or 0.0),
                intensity=float(light["intensity"]),
            )
        )
    return rows


def light_plan(
    document: dict[str, Any], *, size: float = 360.0, pad: float = 30.0, aim_px: float = 40.0
) -> LightPlan:
    """The lights in plan (x, y of their positions), scaled to fit a ``size`` px square.

    The camera head (the frame's origin) is at the centre; the same px/mm both ways. Each LED's
    axis is drawn from the light as its projection on the image plane, ``aim_px`` long for an
    axis lying in that plane (an LED aiming along the optical axis gets no line).
    """
    positions = np.array([light["position_mm"] for light in document["lights"]], dtype=np.float64)
    reach_mm = float(np.abs(positions[:, :2]).max()) if len(positions) else 0.0
    reach_mm = max(reach_mm, 1.0)
    px_per_mm = (size / 2 - pad) / reach_mm
    c = size / 2
    lights = []
    for k, (light, p) in enumerate(zip(document["lights"], positions)):
        axis = light.get("axis") or (0.0, 0.0, 1.0)
        x, y = c + p[0] * px_per_mm, c + p[1] * px_per_mm
        lights.append(
            PlanLight(index=k, x=x, y=y, aim_x=x + axis[0] * aim_px, aim_y=y + axis[1] * aim_px)
        )
    # a scale bar of a round length near a quarter of the drawing
    wanted_mm = (size / 4) / px_per_mm
    scale_mm = max(
        [s for s in (10, 20, 50, 100, 200, 500, 1000, 2000, 5000) if s <= wanted_mm] or [10]
    )
    return LightPlan(
        size=size,
        cx=c,
        cy=c,
        lights=lights,
        scale_px=scale_mm * px_per_mm,
        scale_mm=float(scale_mm),
    )
