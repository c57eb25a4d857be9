"""The report's tables as rows of text: each judged item with its nominal, actual, deviation,
tolerance, uncertainty and result; the statistics; the target, alignment and calibrations.

Uncertainties are the result's optional ``uncertainty`` (expanded, k = 2): ``radius_mm`` for the
radius, ``deviation_mm`` (U95 over the plate) for every deviation; ``not stated`` without it.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from app.report.text import (
    NOT_RECORDED,
    NOT_STATED,
    finite,
    mm,
    num,
    shape_text,
    signed,
    size_text,
    text_or,
    when,
)
from app.schemas import StationOut
from pipeline.judge.sections import Section

#: Columns of the judged items' tables after the item's own.
JUDGED = ["Nominal", "Actual", "Deviation", "Tolerance", "U (k=2)", "Result"]


def uncertainty(result: dict[str, Any], key: str) -> float | None:
    """The result's expanded uncertainty ``key`` (``radius_mm`` or ``deviation_mm``), mm."""
    return finite((result.get("uncertainty") or {}).get(key))


def _u(value: float | None) -> str:
    return NOT_STATED if value is None else num(value, 2, "mm")


def _verdict(ok: bool | None) -> str:
    return "not judged" if ok is None else ("pass" if ok else "FAIL")


def radius_band_mm(target: dict[str, Any] | None) -> tuple[float, float] | None:
    """The radii between which a cylinder target's plate stays within its tolerance at its edges
    (the curvature band ``1/R +- 8 tol / w^2`` over the width ``w`` across the bend, as the forming
    advice and the dashboard use); None for other targets."""
    shape = (target or {}).get("shape") or {}
    radius, size = finite(shape.get("radius_mm")), (target or {}).get("size_mm") or []
    tol = finite((target or {}).get("tolerance_mm"))
    if shape.get("type") != "cylinder" or radius is None or not size or tol is None:
        return None
    band = 8.0 * tol / float(size[0]) ** 2
    hi = math.inf if band >= 1.0 / radius else 1.0 / (1.0 / radius - band)
    return 1.0 / (1.0 / radius + band), hi


def radius_rows(result: dict[str, Any], target: dict[str, Any] | None) -> list[list[str]]:
    """The radius (when the target has one) and the surface's largest deviation, judged."""
    tol = finite(result.get("tolerance_mm"))
    u_dev = uncertainty(result, "deviation_mm")
    rows = [["Item", *JUDGED]]
    nominal, actual = finite(result.get("target_radius_mm")), finite(result.get("radius_mm"))
    if nominal is not None:
        band = radius_band_mm(target)
        ok = None if band is None or actual is None else band[0] <= actual <= band[1]
        tolerance = (
            NOT_STATED
            if band is None
            else f"{signed(band[0] - nominal, 1)} / {signed(band[1] - nominal, 1)} mm"
        )
        deviation = NOT_RECORDED if actual is None else f"{signed(actual - nominal, 1)} mm"
        pct = signed(result.get("radius_error_pct"), 2, "%", missing="")
        rows.append(
            [
                "Radius",
                mm(nominal, 1),
                mm(actual, 1),
                f"{deviation} ({pct})" if pct else deviation,
                tolerance,
                _u(uncertainty(result, "radius_mm")),
                _verdict(ok),
            ]
        )
    peak = finite((result.get("deviation_mm") or {}).get("max_abs"))
    rows.append(
        [
            "Surface, largest |deviation|",
            "0.00 mm",
            mm(peak, 2),
            mm(peak, 2),
            NOT_RECORDED if tol is None else f"±{num(tol, 2)} mm",
            _u(u_dev),
            _verdict(None if peak is None or tol is None else peak <= tol),
        ]
    )
    return rows


def defect_rows(
    defects: list[dict[str, Any]], result: dict[str, Any], peak_u_mm: list[float | None]
) -> list[list[str]]:
    """One row per defect: its place (target frame), area and peak, judged against the tolerance.

    ``peak_u_mm``: each defect's expanded uncertainty at its peak (details.json), where stated;
    the plate's U95 otherwise.
    """
    tol = finite(result.get("tolerance_mm"))
    u95 = uncertainty(result, "deviation_mm")
    rows = [["#", "x, mm", "y, mm", "Area, cm²", "Mean, mm", *JUDGED]]
    for k, d in enumerate(defects):
        x, y = d.get("centroid_mm") or (None, None)
        peak = finite(d.get("peak_mm"))
        own = finite(peak_u_mm[k]) if k < len(peak_u_mm) else None
        rows.append(
            [
                str(d["id"]),
                num(x, 0),
                num(y, 0),
                num((finite(d.get("area_mm2")) or math.nan) / 100.0, 1),
                signed(d.get("mean_mm"), 2),
                "0.00",
                signed(peak, 2),
                signed(peak, 2),
                NOT_RECORDED if tol is None else f"±{num(tol, 2)}",
                _u(own if own is not None else u95),
                _verdict(None if peak is None or tol is None else abs(peak) <= tol),
            ]
        )
    return rows


def template_rows(
    sections: list[Section],
    result: dict[str, Any],
    worst: Any,
    spacing_mm: float,
    places: list[str | None] | None = None,
) -> list[list[str]]:
    """One row per virtual template frame (at ``spacing_mm`` or through a defect): its largest gap,
    judged (``worst``: a section's gap of largest magnitude, mm, or None); ``places``: each frame's
    place in the target's frame (None: its distance from the target's first edge, mm)."""
    places = places or [None] * len(sections)
    spacing = f"{num(spacing_mm, 0)} mm grid"
    tol = finite(result.get("tolerance_mm"))
    u_dev = _u(uncertainty(result, "deviation_mm"))
    rows = [["Frame at" if any(places) else "Frame at, mm", "Through", *JUDGED]]
    for s, place in zip(sections, places, strict=True):
        gap = worst(s)
        rows.append(
            [
                place or num(s.position_mm, 0),
                f"defect {s.defect}" if s.defect else spacing,
                "0.00",
                signed(gap, 2),
                signed(gap, 2),
                NOT_RECORDED if tol is None else f"±{num(tol, 2)}",
                u_dev,
                _verdict(None if gap is None or tol is None else abs(gap) <= tol),
            ]
        )
    return rows


def statistics_rows(values_mm: np.ndarray, result: dict[str, Any]) -> list[list[str]]:
    """Signed min and max, mean, standard deviation, RMS and p95 of the map's cells, then the
    verdict's own figures (over every judged pixel), each row saying what it is over."""
    dev = result.get("deviation_mm") or {}
    cells = f"the map's {values_mm.size} cells"
    rows = [["Statistic", "Value", "Over"]]
    if values_mm.size:
        a = np.abs(values_mm)
        rows += [
            ["Minimum (signed)", signed(values_mm.min(), 2, "mm"), cells],
            ["Maximum (signed)", signed(values_mm.max(), 2, "mm"), cells],
            ["Mean", signed(values_mm.mean(), 2, "mm"), cells],
            ["Standard deviation", num(values_mm.std(), 2, "mm"), cells],
            ["RMS", num(np.sqrt(np.mean(a * a)), 2, "mm"), cells],
            ["p95 of |deviation|", num(np.percentile(a, 95), 2, "mm"), cells],
        ]
    else:
        rows.append(["Map statistics", NOT_RECORDED, "no deviation map in the target's frame"])
    judged = "every judged pixel (the verdict's)"
    return [
        *rows,
        ["RMS", mm(dev.get("rms"), 2), judged],
        ["p95 of |deviation|", mm(dev.get("p95"), 2), judged],
        ["Largest |deviation|", mm(dev.get("max_abs"), 2), judged],
        ["Within tolerance", num(result.get("within_tolerance_pct"), 2, "%"), "the judged area"],
    ]


def target_rows(target: dict[str, Any] | None, result: dict[str, Any]) -> list[list[str]]:
    """The target as the inspection used it (``target.json`` of its inputs)."""
    t = target or {}
    drawing = t.get("drawing") or {}
    material = t.get("material")
    rows = [
        ["Drawing", text_or(drawing.get("number"))],
        ["Revision", text_or(drawing.get("revision"))],
        ["Hull, block", f"{text_or(t.get('hull'))}, {text_or(t.get('block'))}"],
        ["Shape", shape_text(t.get("shape"))],
        ["Size", size_text(t.get("size_mm"))],
        ["Tolerance", mm(result.get("tolerance_mm"), 2, prefix="±")],
    ]
    if material:
        rows.append(
            [
                "Material",
                f"{text_or(material.get('grade'))}, {num(material.get('thickness_mm'), 0)} mm, "
                f"yield {num(material.get('yield_mpa'), 0)} MPa",
            ]
        )
    return rows


def alignment_rows(
    target: dict[str, Any] | None, details: dict[str, Any] | None
) -> list[list[str]]:
    """How the measured surface was put on the target: method, residual and the frame."""
    shape = ((target or {}).get("shape") or {}).get("type")
    if shape == "mesh":
        method = "best fit: ICP, then robust point-to-surface least squares (6 degrees of freedom)"
    elif shape in ("plane", "cylinder", "sphere"):
        method = (
            f"best fit: robust least squares of the {shape}"
            + (", its radius fixed at the target's" if shape != "plane" else "")
            + " (6 degrees of freedom)"
        )
    else:
        method = NOT_RECORDED
    size = (target or {}).get("size_mm") or []
    axis = ", the cylinder's axis" if shape == "cylinder" else ""
    frame = (
        "the target's: origin at the plate's centre, x along its first side"
        + (f" ({num(size[0], 0)} mm)" if size else "")
        + ", y along its second"
        + (f" ({num(size[1], 0)} mm{axis})" if len(size) > 1 else "")
        + "; deviation + towards the cameras (proud of the target)"
    )
    residual = (details or {}).get("registration_rms_mm")
    return [
        ["Method", method],
        ["Residual", num(residual, 2, "mm RMS")],
        ["Frame", frame],
    ]


def acquisition_rows(
    source: str | None, cell_id: str | None, capture: dict[str, Any] | None
) -> list[list[str]]:
    """The cell and cameras that took the images (the bundle's ``acquisition`` record)."""
    record = (capture or {}).get("acquisition") or {}
    cameras = record.get("cameras") or {}
    rows = [
        ["Source", text_or(source)],
        ["Cell", text_or(cell_id or record.get("cell_id"))],
        ["Captured", when((capture or {}).get("captured_at"))],
    ]
    for side in ("left", "right"):
        cam = cameras.get(side) or {}
        parts = [text_or(cam.get("vendor"), ""), text_or(cam.get("model"), "")]
        name = " ".join(p for p in parts if p) or NOT_RECORDED
        rows.append([f"Camera {side}", f"{name}, serial {text_or(cam.get('serial'))}"])
    return rows


def camera_serials(capture: dict[str, Any] | None) -> str:
    """``L 22334455, R 22334456`` from the bundle's acquisition record, or ``not recorded``."""
    cameras = ((capture or {}).get("acquisition") or {}).get("cameras") or {}
    serials = [
        f"{side[0].upper()} {cameras[side]['serial']}"
        for side in ("left", "right")
        if isinstance(cameras.get(side), dict) and cameras[side].get("serial")
    ]
    return ", ".join(serials) or NOT_RECORDED


#: Header of the stations' table.
STATION_HEADER = [
    "Station",
    "Travel registered",
    "Travel encoder",
    "Registered - encoder",
    "Overlap matches",
    "Overlap RMS",
    "Overlap max",
]


def station_rows(stations: list[StationOut]) -> list[list[str]]:
    """The stations of a plate measured at stations: each one's travel (registered, encoder and
    their difference, mm) and its overlap with the station before (matches, RMS and max distance
    between the two surfaces, mm); ``-`` for station 0's overlap."""
    rows = [STATION_HEADER]
    for s in stations:
        rows.append(
            [
                str(s.index),
                num(s.travel_mm, 1, "mm"),
                num(s.travel_encoder_mm, 1, "mm"),
                signed(s.travel_mm - s.travel_encoder_mm, 1, "mm"),
                "-" if s.overlap_matches is None else str(s.overlap_matches),
                num(s.overlap_rms_mm, 2, "mm", missing="-"),
                num(s.overlap_max_mm, 2, "mm", missing="-"),
            ]
        )
    return rows
