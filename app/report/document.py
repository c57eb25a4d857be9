"""The report's pages: what a QA engineer reads before signing, in the order of deviation reports
(plate, part and verdict first).

Every page: the header (:mod:`app.report.header`). Then: the verdict and why; every warning of the
result; the decision rule; the target and the alignment; the radius and the surface judged
(nominal, actual, deviation, tolerance, uncertainty, result); the statistics and histogram; the
deviation map with its colour bar and a callout per defect; the defects and the virtual templates
judged; the acquisition and calibrations; signature blocks for the operator and a QA approver with
the disposition.
"""

from __future__ import annotations

import io
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path
from typing import Any

import numpy as np
from reportlab.lib import colors
from reportlab.lib.pagesizes import A4
from reportlab.lib.styles import ParagraphStyle, getSampleStyleSheet
from reportlab.lib.units import mm
from reportlab.platypus import Flowable, Paragraph, SimpleDocTemplate, Spacer, Table, TableStyle
from reportlab.platypus.flowables import KeepTogether

from app.report import tables
from app.report.figures import DeviationMap, GapProfile, Histogram, PlateMapFigure
from app.report.header import MARGIN_BOTTOM, MARGIN_X, PageHeader, numbered_canvas
from app.report.text import NOT_RECORDED, escape, finite, num, text_or, when
from app.schemas import StationOut
from pipeline.artifacts.colours import default_limit_mm
from pipeline.judge.plate_map import PlateMap
from pipeline.judge.sections import Section

#: Width of the page's text block, points.
TEXT_WIDTH = A4[0] - 2 * MARGIN_X
#: Column widths of the judged items' tables (their sum is at most the text width).
RADIUS_WIDTHS = tuple(w * mm for w in (42, 21, 21, 33, 27, 16, 14))
DEFECT_WIDTHS = tuple(w * mm for w in (7, 13, 13, 17, 16, 15, 15, 17, 17, 16, 14))
TEMPLATE_WIDTHS = tuple(w * mm for w in (46, 18, 14, 14, 16, 16, 16, 14))
STATION_WIDTHS = tuple(w * mm for w in (16, 27, 25, 31, 25, 22, 22))
#: Test uncertainty ratio (tolerance / U95) below which the measurement is flagged not capable.
CAPABLE_RATIO = 4.0


@dataclass(frozen=True)
class ReportData:
    """What a report shows.

    Attributes
    ----------
    inspection : dict
        The inspection's API document (``InspectionOut`` as JSON): result, defects, reasons, times.
    artifacts_dir : Path
        Its artifact folder (deviation.png, depth.npy for the camera's map).
    target : dict or None
        The ``plate-target/1`` document it was judged against (drawing, hull, block, material).
    light_calibration : dict or None
        ``{"id", "rms", "file_name"}`` of the light calibration applied; None: the bundle's lights.
    software_version : str
    printed_at : datetime
        Aware; shown with its zone.
    plate_map : PlateMap or None
        The deviation map in the target's frame; the camera's deviation.png is printed otherwise.
    sections : list of Section
        The virtual templates (:mod:`pipeline.judge.sections`): each frame's gap along it.
    template_places : list of str
        Each section's place in the target's frame (:mod:`app.plate_frame`), in the same order;
        empty without a registration (the frames are then given from the target's first edge).
    template_spacing_mm : float
        Their spacing (besides one through each defect), mm.
    yard : str or None
        The yard's name (setting ``PLATE_INSPECT_YARD``).
    capture : dict or None
        The bundle's ``capture.json`` (``captured_at``, the ``acquisition`` record).
    stereo_calibration : dict or None
        ``{"id", "created_at", "rms_px", "sha256"}`` of the bundle's calibration; ``id`` and
        ``created_at`` are those of the uploaded calibration with the same content, else None.
    details : dict or None
        The inspection's details.json (``registration_rms_mm``).
    stations : list of StationOut
        The conveyor stations of a plate measured at stations (empty for one view): the map draws
        their outlines and a table lists their travel and overlaps.
    """

    inspection: dict[str, Any]
    artifacts_dir: Path
    target: dict[str, Any] | None
    light_calibration: dict[str, Any] | None
    software_version: str
    printed_at: datetime
    plate_map: PlateMap | None = None
    sections: list[Section] = field(default_factory=list)
    template_places: list[str] = field(default_factory=list)
    template_spacing_mm: float = 700.0
    yard: str | None = None
    capture: dict[str, Any] | None = None
    stereo_calibration: dict[str, Any] | None = None
    details: dict[str, Any] | None = None
    stations: list[StationOut] = field(default_factory=list)


def report_number(inspection: dict[str, Any]) -> str:
    """The report's number: one per inspection (``IR-000042``); a reprint keeps it."""
    return f"IR-{int(inspection['id']):06d}"


def build_report(data: ReportData) -> bytes:
    """The PDF (A4) of a done inspection."""
    doc = data.inspection
    header = page_header(data)
    buffer = io.BytesIO()
    pdf = SimpleDocTemplate(
        buffer,
        pagesize=A4,
        leftMargin=MARGIN_X,
        rightMargin=MARGIN_X,
        topMargin=header.height,
        bottomMargin=MARGIN_BOTTOM,
        title=f"Inspection report {doc['plate_id']} #{doc['id']} ({report_number(doc)})",
        author="plate-inspect",
    )
    pdf.build(_story(data, getSampleStyleSheet()), canvasmaker=numbered_canvas(header))
    return buffer.getvalue()


def _story(data: ReportData, styles: Any) -> list[Flowable]:
    doc = data.inspection
    result = doc.get("result") or {}
    return [
        *_verdict(doc, styles),
        *_warnings(result, styles),
        _section("Decision rule", styles),
        Paragraph(decision_rule(result), styles["Normal"]),
        _section("Target and alignment", styles),
        _pairs(tables.target_rows(data.target, result), styles),
        Spacer(1, 2 * mm),
        _pairs(tables.alignment_rows(data.target, data.details), styles),
        _section("Radius and surface", styles),
        _table(tables.radius_rows(result, data.target), header=True, widths=RADIUS_WIDTHS),
        _note(_radius_note(data), styles),
        KeepTogether(_statistics(data, styles)),
        KeepTogether([_section("Deviation map", styles), *_deviation_map(data, styles)]),
        *_stations(data.stations, styles),
        *_defects(doc, data.details, styles),
        *_templates(data.sections, data.template_places, result, data.template_spacing_mm, styles),
        _section("Acquisition and calibrations", styles),
        _pairs(_acquisition_rows(data), styles),
        KeepTogether(_approval(styles, doc.get("operator"))),
    ]


def page_header(data: ReportData) -> PageHeader:
    """The header of every page (a value is never blank: ``not recorded``)."""
    doc, target = data.inspection, data.target or {}
    drawing = target.get("drawing") or {}
    cal = data.stereo_calibration or {}
    cell = doc.get("cell_id") or ((data.capture or {}).get("acquisition") or {}).get("cell_id")
    cells = [
        ("Yard", text_or(data.yard)),
        ("Hull", text_or(target.get("hull"))),
        ("Block", text_or(target.get("block"))),
        ("Plate", str(doc["plate_id"])),
        ("Drawing", text_or(drawing.get("number"))),
        ("Revision", text_or(drawing.get("revision"))),
        ("Inspection", f"#{doc['id']} ({text_or(doc.get('source'))})"),
        ("Cell", text_or(cell)),
        ("Camera serials", tables.camera_serials(data.capture)),
        ("Calibration", _calibration_id(cal)),
        (
            "Calibration date",
            when(cal.get("created_at")) if cal.get("created_at") else NOT_RECORDED,
        ),
        ("Calibration RMS", num(cal.get("rms_px"), 3, "px")),
        ("Operator", text_or(doc.get("operator"))),
        ("Software", f"plate-inspect {data.software_version}"),
        ("Verdict", text_or(doc.get("verdict")).upper()),
        ("Measured", when(doc.get("finished_at"))),
        ("Printed", when(data.printed_at)),
        ("Started", when(doc.get("started_at"))),
    ]
    title = f"Forming inspection report: plate {doc['plate_id']}"
    return PageHeader(title=title, report_number=report_number(doc), cells=cells)


def _calibration_id(cal: dict[str, Any]) -> str:
    if cal.get("id") is not None:
        return f"#{cal['id']}"
    if cal.get("sha256"):
        return f"bundle's own, sha256 {str(cal['sha256'])[:10]}"
    return NOT_RECORDED


def decision_rule(result: dict[str, Any]) -> str:
    """The rule the verdict applies, and whether the measurement is capable for the tolerance."""
    rule = (
        "Simple acceptance per ISO 14253-1 (shared risk): an item conforms when its measured value "
        "lies within its tolerance; the measurement uncertainty is neither added to nor deducted "
        "from the tolerance. "
    )
    tol = finite(result.get("tolerance_mm"))
    u95 = tables.uncertainty(result, "deviation_mm")
    if tol is None or u95 is None or u95 <= 0:
        return rule + (
            "The uncertainty of this measurement is not stated (U95 not recorded with the result), "
            "so its capability for the tolerance is not known."
        )
    ratio = tol / u95
    verdict = (
        "capable"
        if ratio >= CAPABLE_RATIO
        else f"<b>NOT CAPABLE</b> (below {CAPABLE_RATIO:g}): the verdict carries a high risk"
    )
    return rule + (
        f"Test uncertainty ratio: tolerance {num(tol, 2)} mm / U95 {num(u95, 2)} mm = "
        f"{num(ratio, 1)}; the measurement is {verdict}."
    )


def _verdict(doc: dict[str, Any], styles: Any) -> list[Flowable]:
    verdict = text_or(doc.get("verdict")).upper()
    colour = "#1b7f3b" if verdict == "PASS" else "#b3261e"
    out: list[Flowable] = [
        Paragraph(
            f'<font size="20" color="{colour}"><b>{escape(verdict)}</b></font>',
            ParagraphStyle("verdict", parent=styles["Normal"], leading=26),
        )
    ]
    for reason in doc.get("reasons") or []:
        out.append(Paragraph(f"• {escape(reason)}", styles["Normal"]))
    return out


def _warnings(result: dict[str, Any], styles: Any) -> list[Flowable]:
    """Every warning of the result, as the result page shows them."""
    warnings = [str(w) for w in result.get("warnings") or []]
    out: list[Flowable] = [_section("Warnings", styles)]
    if not warnings:
        return [*out, Paragraph("None.", styles["Normal"])]
    return out + [Paragraph(f"• {escape(w)}", styles["Normal"]) for w in warnings]


def _radius_note(data: ReportData) -> str:
    band = tables.radius_band_mm(data.target)
    text = (
        "Signed: + where the plate is larger or stands proud of the target. U (k=2): the expanded "
        "uncertainty the result states. "
    )
    if band is None:
        return (
            text + "No radius tolerance is stated for this target; the verdict judges the surface."
        )
    return text + (
        f"Radius tolerance: the radii ({num(band[0], 0)} to {num(band[1], 0)} mm) at which the "
        "plate, touching the target at its crown, leaves the surface tolerance at its edges "
        "(8 x tolerance / width² in curvature); informative, the verdict judges the surface."
    )


def _statistics(data: ReportData, styles: Any) -> list[Flowable]:
    result = data.inspection.get("result") or {}
    values = np.empty(0)
    if data.plate_map is not None:
        values = data.plate_map.deviation_mm[np.isfinite(data.plate_map.deviation_mm)]
    stats = _table(
        tables.statistics_rows(values, result),
        header=True,
        size=7.6,
        widths=(32 * mm, 22 * mm, 50 * mm),
    )
    stats.setStyle(TableStyle([("ALIGN", (2, 0), (2, -1), "LEFT")]))
    out: list[Flowable] = [_section("Statistics of the signed deviation", styles)]
    tol = finite(result.get("tolerance_mm"))
    if not (values.size and tol):
        return [*out, stats]
    cell = num(data.plate_map.cell_mm if data.plate_map else None, 1)
    side = TEXT_WIDTH - 104 * mm
    beside = Table([[stats, Histogram(values, tol, side)]], colWidths=(104 * mm, side))
    beside.setStyle(
        TableStyle([("VALIGN", (0, 0), (-1, -1), "MIDDLE"), ("LEFTPADDING", (0, 0), (-1, -1), 0)])
    )
    return [
        *out,
        beside,
        _note(
            f"The map's {values.size} cells ({cell} mm squares, each the mean deviation of its "
            f"points) per 0.25 x tolerance bin; beyond ±{default_limit_mm(tol):g} mm counted in "
            "the end bins.",
            styles,
        ),
    ]


def _deviation_map(data: ReportData, styles: Any) -> list[Flowable]:
    tolerance = finite((data.inspection.get("result") or {}).get("tolerance_mm"))
    defects = data.inspection.get("defects") or []
    if data.plate_map is not None and tolerance:
        return [
            PlateMapFigure(data.plate_map, tolerance, defects, TEXT_WIDTH, data.stations),
            _note(
                f"The plate in its target's frame, mm (x along the target's first side, y along its "
                f"second, origin at its centre). Green: within ±{tolerance:g} mm; orange to dark "
                "red: proud of the target (towards the cameras); light to dark blue: below it, "
                f"deepest at ±{default_limit_mm(tolerance):g} mm (colour bar, mm); light grey: not "
                "measured. Callouts: defect number, peak deviation and tolerance, as in the table "
                "below.",
                styles,
            ),
        ]
    png, depth = data.artifacts_dir / "deviation.png", data.artifacts_dir / "depth.npy"
    if not png.is_file() or not depth.is_file():
        return [Paragraph("No deviation map was written for this inspection.", styles["Normal"])]
    shape_hw = np.load(depth, mmap_mode="r").shape[:2]
    return [
        DeviationMap(png, shape_hw, defects, TEXT_WIDTH),
        _note(
            "The camera's view. Numbers mark the defects of the table below (red: proud of the "
            "target, towards the cameras; blue: below it).",
            styles,
        ),
    ]


def _stations(stations: list[StationOut], styles: Any) -> list[Flowable]:
    """The stations of a plate measured at stations (nothing for one view)."""
    if not stations:
        return []
    return [
        KeepTogether(
            [
                _section("Stations", styles),
                _table(tables.station_rows(stations), header=True, size=7.6, widths=STATION_WIDTHS),
                _note(
                    f"The plate was measured at {len(stations)} conveyor stations and stitched into "
                    "one. Travel since station 0 as the registration found it (the plate's texture "
                    "matched in each overlap) and as the conveyor's encoder read it. Overlap: with "
                    "the station before; the distance between the two registered surfaces there. "
                    "The map draws each station's view, numbered.",
                    styles,
                ),
            ]
        )
    ]


def _defects(doc: dict[str, Any], details: dict[str, Any] | None, styles: Any) -> list[Flowable]:
    defects = doc.get("defects") or []
    head = _section("Defects", styles)
    if not defects:
        return [head, Paragraph("No region out of tolerance.", styles["Normal"])]
    found = [d for d in (details or {}).get("defects") or [] if isinstance(d, dict)]
    peak_u = [finite(d.get("uncertainty_mm")) for d in found]
    rows = tables.defect_rows(defects, doc.get("result") or {}, peak_u)
    note = _note(
        "Position in the target's frame (mm from its centre); nominal, actual (the peak) and "
        "deviation in mm, signed: + proud of the target (towards the cameras), - below it. "
        "U (k=2): at the defect's peak where the result states it, else the plate's U95.",
        styles,
    )
    return [head, _table(rows, header=True, size=7.6, widths=DEFECT_WIDTHS), note]


def _worst_gap(section: Section) -> float | None:
    gaps = section.gap_mm[np.isfinite(section.gap_mm)]
    return float(gaps[np.argmax(np.abs(gaps))]) if gaps.size else None


def _templates(
    sections: list[Section],
    places: list[str],
    result: dict[str, Any],
    spacing_mm: float,
    styles: Any,
) -> list[Flowable]:
    """The table of frames judged by their largest gap, then each frame's gap along it; ``places``:
    each frame's place in the target's frame (empty: given from the target's first edge)."""
    if not sections:
        return []
    placed: list[str | None] = [*places] if len(places) == len(sections) else [None] * len(sections)
    out: list[Flowable] = [
        _section("Virtual templates", styles),
        _table(
            tables.template_rows(sections, result, _worst_gap, spacing_mm, placed),
            header=True,
            size=7.6,
            widths=TEMPLATE_WIDTHS,
        ),
    ]
    tolerance = finite(result.get("tolerance_mm"))
    if tolerance is None:
        return out
    frame_words = (
        "Frame at: its place in the target's frame, as on the dashboard's map (origin at the "
        "target's centre; edge A where y is smallest, then B, C, D counter-clockwise)."
        if places
        else "Frame at: its distance, mm, from the target's first edge in the direction the "
        "frames are stacked (for a cylinder, along its axis)."
    )
    out.append(
        _note(
            f"{frame_words} The gap under each template along its "
            "frame line (mm, + where the plate stands proud of the target); the band is the "
            f"±{tolerance:g} mm tolerance, red beyond it.",
            styles,
        )
    )
    ordered = sorted(
        zip(sections, placed), key=lambda sp: (sp[0].defect is None, sp[0].position_mm)
    )
    return out + [GapProfile(s, tolerance, TEXT_WIDTH, place=p) for s, p in ordered]


def _acquisition_rows(data: ReportData) -> list[list[str]]:
    doc = data.inspection
    rows = tables.acquisition_rows(doc.get("source"), doc.get("cell_id"), data.capture)
    cal = data.stereo_calibration or {}
    light = data.light_calibration
    stereo = (
        f"{_calibration_id(cal)}, uploaded {when(cal['created_at'])}"
        if cal.get("id") is not None
        else f"{_calibration_id(cal)} (not among the uploaded calibrations; date not recorded)"
    )
    rows += [
        ["Stereo calibration", f"{stereo}, RMS {num(cal.get('rms_px'), 3, 'px')}"],
        [
            "Light calibration",
            "none: the light positions of the capture bundle"
            if light is None
            else f"#{light['id']} {light.get('file_name') or ''} (fit RMS {num(light.get('rms'), 4)})",
        ],
    ]
    return rows


def _approval(styles: Any, operator: str | None) -> list[Flowable]:
    """Signature blocks: the operator who measured, and the QA approver with the disposition."""
    line = "_" * 30
    rows = [
        ["Sign-off", "Operator", "QA approver"],
        ["Name", operator or line, line],
        ["Date", line, line],
        ["Signature", line, line],
    ]
    table = _table(rows, header=True, widths=(26 * mm, 52 * mm, None))
    table.setStyle(TableStyle([("ALIGN", (0, 0), (-1, -1), "LEFT")]))
    disposition = _pairs(
        [["Disposition (QA)", "[  ] accept    [  ] rework    [  ] concession no. ____________"]],
        styles,
    )
    return [Spacer(1, 6 * mm), _section("Approval", styles), table, Spacer(1, 3 * mm), disposition]


def _table(
    rows: list[list[str]],
    *,
    widths: tuple[float | None, ...] | None = None,
    header: bool = False,
    size: float = 8.6,
) -> Table:
    table = Table(rows, colWidths=widths, hAlign="LEFT", repeatRows=1 if header else 0)
    style = [
        ("FONT", (0, 0), (-1, -1), "Helvetica", size),
        ("VALIGN", (0, 0), (-1, -1), "TOP"),
        ("BOTTOMPADDING", (0, 0), (-1, -1), 2.5),
        ("TOPPADDING", (0, 0), (-1, -1), 2.5),
        ("LEFTPADDING", (0, 0), (-1, -1), 3),
        ("RIGHTPADDING", (0, 0), (-1, -1), 3),
    ]
    if header:
        style += [
            ("FONT", (0, 0), (-1, 0), "Helvetica-Bold", size),
            ("LINEBELOW", (0, 0), (-1, 0), 0.8, colors.black),
            ("LINEBELOW", (0, 1), (-1, -1), 0.3, colors.lightgrey),
            ("ALIGN", (1, 0), (-1, -1), "RIGHT"),
        ]
    else:
        style += [("TEXTCOLOR", (0, 0), (0, -1), colors.HexColor("#4a4a4a"))]
    table.setStyle(TableStyle(style))
    return table


def _pairs(rows: list[list[str]], styles: Any) -> Table:
    """A two-column table of labels and values, long values wrapped."""
    style = ParagraphStyle("value", parent=styles["Normal"], fontSize=8.6, leading=10.4)
    wrapped = [[label, Paragraph(escape(value), style)] for label, value in rows]
    return _table(wrapped, widths=(36 * mm, TEXT_WIDTH - 36 * mm))


def _section(title: str, styles: Any) -> Paragraph:
    return Paragraph(title, styles["Heading3"])


def _note(text: str, styles: Any) -> Paragraph:
    return Paragraph(text, ParagraphStyle("note", parent=styles["Italic"], fontSize=8, leading=10))
