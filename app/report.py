"""The inspection report to sign: one PDF per done inspection (``GET /api/v1/inspections/{id}/report.pdf``).

Built with ReportLab: pure Python (no browser, TeX or system fonts to install on a cell PC), long
maintained, and its platypus layer flows paragraphs and tables over A4 pages while its canvas draws
the deviation map with numbered callouts at the defects. The report is built from plain data (the
inspection's API document, its target and light calibration, its artifact folder); the route reads
the database, this module only draws.

Contents, following the conventions of deviation reports (plate, part, verdict first): plate,
inspection, time (with its zone), software version; verdict and why; target (shape, radius, size,
tolerance, material); radius and deviation statistics; the deviation map with callouts; the defect
table; the virtual templates (largest gaps, and each one's gap along its frame); the calibrations used; operator, date and signature lines.
"""

from __future__ import annotations

import io
import math
from dataclasses import dataclass, field
from datetime import datetime
from itertools import pairwise
from pathlib import Path
from typing import Any

import numpy as np
from reportlab.lib import colors
from reportlab.lib.pagesizes import A4
from reportlab.lib.styles import ParagraphStyle, getSampleStyleSheet
from reportlab.lib.units import mm
from reportlab.platypus import Flowable, Paragraph, SimpleDocTemplate, Spacer, Table, TableStyle
from reportlab.platypus.flowables import KeepTogether

from app.axes import nice_ticks
from pipeline.artifacts.colours import default_limit_mm, tolerance_band_colormap
from pipeline.artifacts.png import deviation_png_layout
from pipeline.plate_map import PlateMap
from pipeline.sections import Section

#: Width of the page's text block, points (A4 less 18 mm margins).
TEXT_WIDTH = A4[0] - 36 * mm


@dataclass(frozen=True)
class ReportData:
    """What a report shows.

    Attributes
    ----------
    inspection : dict
        The inspection's API document (``InspectionOut`` as JSON): result, defects, reasons, times.
    artifacts_dir : Path
        Its artifact folder (deviation.png, depth.npy for the map's size).
    target : dict or None
        The ``plate-target/1`` document it was judged against (with its ``material``, if any).
    light_calibration : dict or None
        ``{"id", "rms", "file_name"}`` of the light calibration applied; None: the bundle's lights.
    sections : list of Section
        The virtual templates (:mod:`pipeline.sections`): each frame's gap along it.
    software_version : str
    printed_at : datetime
        Aware; shown with its zone.
    plate_map : PlateMap or None
        The deviation map in the target's frame (:mod:`pipeline.plate_map`).
    """

    inspection: dict[str, Any]
    artifacts_dir: Path
    target: dict[str, Any] | None
    light_calibration: dict[str, Any] | None
    software_version: str
    printed_at: datetime
    #: The deviation map in the target's frame (mm axes), when the artifacts give one; the camera's
    #: deviation.png is printed otherwise.
    plate_map: PlateMap | None = None
    sections: list[Section] = field(default_factory=list)


def build_report(data: ReportData) -> bytes:
    """The PDF (A4) of a done inspection."""
    styles = getSampleStyleSheet()
    doc = data.inspection
    buffer = io.BytesIO()
    pdf = SimpleDocTemplate(
        buffer,
        pagesize=A4,
        leftMargin=18 * mm,
        rightMargin=18 * mm,
        topMargin=16 * mm,
        bottomMargin=16 * mm,
        title=f"Inspection report {doc['plate_id']} #{doc['id']}",
        author="plate-inspect",
    )
    story: list[Flowable] = [
        Paragraph(f"Forming inspection report: plate {doc['plate_id']}", styles["Title"]),
        _table(_header_rows(data), widths=(45 * mm, None)),
        Spacer(1, 4 * mm),
        *_verdict(doc, styles),
        _section("Target and measurement", styles),
        _table(_measurement_rows(doc, data.target), widths=(60 * mm, None)),
        KeepTogether([_section("Deviation map", styles), *_deviation_map(data, styles)]),
        *_defects(doc, styles),
        *_templates(data.sections, _tolerance(data), styles),
        _section("Calibrations", styles),
        _table(_calibration_rows(data), widths=(45 * mm, None)),
        KeepTogether(_signature(styles, doc.get("operator"))),
    ]
    pdf.build(story)
    return buffer.getvalue()


def _header_rows(data: ReportData) -> list[list[str]]:
    doc = data.inspection
    finished = doc.get("finished_at")
    return [
        ["Plate", str(doc["plate_id"])],
        ["Inspection", f"#{doc['id']} ({doc.get('source', '')})"],
        ["Measured", _when(finished) if finished else "—"],
        ["Report printed", _when(data.printed_at)],
        ["Software", f"plate-inspect {data.software_version}"],
    ]


def _verdict(doc: dict[str, Any], styles: Any) -> list[Flowable]:
    verdict = (doc.get("verdict") or "").upper() or "—"
    colour = "#1b7f3b" if verdict == "PASS" else "#b3261e"
    out: list[Flowable] = [
        Paragraph(
            f'<font size="20" color="{colour}"><b>{verdict}</b></font>',
            ParagraphStyle("verdict", parent=styles["Normal"], leading=26),
        )
    ]
    for reason in doc.get("reasons") or []:
        out.append(Paragraph(f"• {_escape(reason)}", styles["Normal"]))
    return out


def _measurement_rows(doc: dict[str, Any], target: dict[str, Any] | None) -> list[list[str]]:
    result = doc.get("result") or {}
    dev = result.get("deviation_mm") or {}
    shape = (target or {}).get("shape", {})
    rows = [
        ["Target shape", _shape_text(shape)],
        ["Target size", _size_text((target or {}).get("size_mm"))],
        ["Tolerance", _mm(result.get("tolerance_mm"), 1, prefix="±")],
    ]
    material = (target or {}).get("material")
    if material:
        rows.append(
            [
                "Material",
                f"{material.get('grade', '')}, {_num(material.get('thickness_mm'), 0)} mm, "
                f"yield {_num(material.get('yield_mpa'), 0)} MPa",
            ]
        )
    rows += [
        ["Measured radius", _mm(result.get("radius_mm"), 1)],
        ["Target radius", _mm(result.get("target_radius_mm"), 1)],
        ["Radius error", _signed(result.get("radius_error_pct"), 2, "%")],
        ["Deviation RMS / p95", f"{_mm(dev.get('rms'), 2)} / {_mm(dev.get('p95'), 2)}"],
        ["Largest |deviation|", _mm(dev.get("max_abs"), 2)],
        ["Within tolerance", _num(result.get("within_tolerance_pct"), 2, "%")],
    ]
    return rows


def _deviation_map(data: ReportData, styles: Any) -> list[Flowable]:
    tolerance = (data.inspection.get("result") or {}).get("tolerance_mm")
    if data.plate_map is not None and tolerance:
        return [
            PlateMapFigure(
                data.plate_map, float(tolerance), data.inspection.get("defects") or [], TEXT_WIDTH
            ),
            Paragraph(
                f"The plate in its target's frame, mm (x along the target's first side, y along its "
                f"second, origin at its centre). Green: within ±{float(tolerance):g} mm; orange to "
                "dark red: proud of the target (towards the cameras); light to dark blue: below it, "
                f"deepest at ±{default_limit_mm(float(tolerance)):g} mm; grey: not measured. "
                "Numbers mark the defects of the table below.",
                styles["Italic"],
            ),
        ]
    png = data.artifacts_dir / "deviation.png"
    depth = data.artifacts_dir / "depth.npy"
    if not png.is_file() or not depth.is_file():
        return [Paragraph("No deviation map was written for this inspection.", styles["Normal"])]
    shape_hw = np.load(depth, mmap_mode="r").shape[:2]
    return [
        DeviationMap(png, shape_hw, data.inspection.get("defects") or [], TEXT_WIDTH),
        Paragraph(
            "Numbers mark the defects of the table below (red: proud of the target, towards the "
            "cameras; blue: below it).",
            styles["Italic"],
        ),
    ]


def _defects(doc: dict[str, Any], styles: Any) -> list[Flowable]:
    defects = doc.get("defects") or []
    if not defects:
        return [
            _section("Defects", styles),
            Paragraph("No region out of tolerance.", styles["Normal"]),
        ]
    rows = [["#", "x, mm", "y, mm", "area, cm²", "peak, mm", "mean, mm"]]
    for d in defects:
        x, y = d.get("centroid_mm") or (None, None)
        rows.append(
            [
                str(d["id"]),
                _num(x, 0),
                _num(y, 0),
                _num(d["area_mm2"] / 100.0, 1),
                _signed(d["peak_mm"], 1),
                _signed(d.get("mean_mm"), 1),
            ]
        )
    note = Paragraph(
        "Position in the target's frame (its centre, x along its first side); peak and mean "
        "deviation signed: + proud of the target (towards the cameras), − below it.",
        styles["Italic"],
    )
    return [_section("Defects", styles), _table(rows, header=True), note]


def _tolerance(data: ReportData) -> float | None:
    value = (data.inspection.get("result") or {}).get("tolerance_mm")
    return None if value is None else float(value)


def _worst_gap(section: Section) -> float | None:
    gaps = section.gap_mm[np.isfinite(section.gap_mm)]
    return float(gaps[np.argmax(np.abs(gaps))]) if gaps.size else None


def _templates(sections: list[Section], tolerance: float | None, styles: Any) -> list[Flowable]:
    """The table of frames and their largest gaps, then each frame's gap along it (defects first)."""
    if not sections:
        return []
    rows = [["Frame at, mm", "Largest gap, mm", "Through"]]
    rows += [
        [
            _num(s.position_mm, 0),
            _signed(_worst_gap(s), 2),
            f"defect {s.defect}" if s.defect else "",
        ]
        for s in sections
    ]
    out: list[Flowable] = [_section("Virtual templates", styles), _table(rows, header=True)]
    if tolerance is None:
        return out
    out.append(
        Paragraph(
            "The gap under each template along its frame line (mm, + where the plate stands proud of "
            f"the target); the band is the ±{tolerance:g} mm tolerance, red beyond it.",
            styles["Italic"],
        )
    )
    ordered = sorted(sections, key=lambda s: (s.defect is None, s.position_mm))
    out += [GapProfile(s, tolerance, TEXT_WIDTH) for s in ordered]
    return out


def _calibration_rows(data: ReportData) -> list[list[str]]:
    light = data.light_calibration
    return [
        ["Stereo calibration", "the capture bundle's own (calibration.json in its inputs)"],
        [
            "Light calibration",
            "none: the light positions of the capture bundle"
            if light is None
            else f"#{light['id']} {light.get('file_name') or ''} (fit RMS {_num(light.get('rms'), 4)})",
        ],
    ]


def _signature(styles: Any, operator: str | None) -> list[Flowable]:
    """Approval lines; the operator who started the inspection is printed when known."""
    line = "_" * 38
    rows = [["Operator", operator or line], ["Date", line], ["Signature", line]]
    return [Spacer(1, 10 * mm), _section("Approval", styles), _table(rows, widths=(45 * mm, None))]


class DeviationMap(Flowable):  # type: ignore[misc]  # ReportLab is untyped
    """deviation.png at the text width, a numbered circle at each defect's centroid."""

    def __init__(
        self, png: Path, shape_hw: tuple[int, ...], defects: list[dict[str, Any]], width: float
    ) -> None:
        super().__init__()
        from PIL import Image

        with Image.open(png) as image:
            self.png_size = image.size
        self.png, self.defects = png, defects
        self.stride, self.k = deviation_png_layout(shape_hw)
        self.width = width
        self.height = width * self.png_size[1] / self.png_size[0]

    def draw(self) -> None:
        c = self.canv
        c.drawImage(str(self.png), 0, 0, width=self.width, height=self.height)
        scale = self.width / self.png_size[0] * self.k / self.stride  # points per image pixel
        radius = max(7.0, 0.012 * self.width)
        for d in self.defects:
            col, row = d["centroid_px"]
            x, y = col * scale, self.height - row * scale
            c.setStrokeColor(colors.black)
            c.setFillColor(colors.white)
            c.setLineWidth(1.2)
            c.circle(x + 2.2 * radius, y + 2.2 * radius, radius, stroke=1, fill=1)
            c.line(x, y, x + 1.5 * radius, y + 1.5 * radius)
            c.setFillColor(colors.black)
            c.setFont("Helvetica-Bold", radius * 1.1)
            c.drawCentredString(x + 2.2 * radius, y + 1.8 * radius, str(d["id"]))


class PlateMapFigure(Flowable):  # type: ignore[misc]  # ReportLab is untyped
    """The deviation map in the target's frame: tolerance-band colours, mm axes, the origin, and a
    numbered circle at each defect's ``centroid_mm``."""

    MAX_HEIGHT = 108 * mm  # with the heading above it, it still fits under page 1's tables
    LEFT, BOTTOM, TOP = 16 * mm, 11 * mm, 7 * mm

    def __init__(
        self, plate: PlateMap, tolerance_mm: float, defects: list[dict[str, Any]], width: float
    ) -> None:
        super().__init__()
        self.plate, self.defects = plate, defects
        x0, x1, y0, y1 = plate.extent_mm
        self.scale = min(  # points per mm
            (width - self.LEFT - 6 * mm) / (x1 - x0),
            (self.MAX_HEIGHT - self.BOTTOM - self.TOP) / (y1 - y0),
        )
        self.width = width
        self.height = self.BOTTOM + (y1 - y0) * self.scale + self.TOP
        rows = plate.deviation_mm[::-1]  # first row at the largest y: y up on the page
        rgb = tolerance_band_colormap(
            rows, tolerance_mm=tolerance_mm, limit_mm=default_limit_mm(tolerance_mm)
        )
        alpha = np.where(np.isfinite(rows), 255, 0).astype(np.uint8)
        from PIL import Image
        from reportlab.lib.utils import ImageReader

        image = Image.fromarray(np.dstack([rgb, alpha]), mode="RGBA")
        k = max(1, 1200 // max(image.size))  # enlarged: cells stay square in any PDF viewer
        self.image = ImageReader(image.resize((image.width * k, image.height * k), Image.NEAREST))

    def _at(self, x_mm: float, y_mm: float) -> tuple[float, float]:
        x0, _, y0, _ = self.plate.extent_mm
        return self.LEFT + (x_mm - x0) * self.scale, self.BOTTOM + (y_mm - y0) * self.scale

    def draw(self) -> None:
        c = self.canv
        x0, x1, y0, y1 = self.plate.extent_mm
        c.drawImage(
            self.image,
            *self._at(x0, y0),
            width=(x1 - x0) * self.scale,
            height=(y1 - y0) * self.scale,
            mask="auto",
        )
        c.setStrokeColor(colors.HexColor("#555555"))
        c.setFillColor(colors.black)
        c.setLineWidth(0.5)
        c.setFont("Helvetica", 7)
        left, bottom = self._at(x0, y0)
        right, top = self._at(x1, y1)
        c.line(left, bottom - 2, right, bottom - 2)
        c.line(left - 2, bottom, left - 2, top)
        for t in (v for v in nice_ticks(x0, x1, max_ticks=8)[0] if x0 <= v <= x1):
            px, _ = self._at(t, y0)
            c.line(px, bottom - 2, px, bottom - 5)
            c.drawCentredString(px, bottom - 12, f"{t:.0f}")
        for t in (v for v in nice_ticks(y0, y1, max_ticks=7)[0] if y0 <= v <= y1):
            _, py = self._at(x0, t)
            c.line(left - 2, py, left - 5, py)
            c.drawRightString(left - 7, py - 2.5, f"{t:.0f}")
        c.drawRightString(right, bottom - 22, "x, mm")
        c.drawString(left - 7, top + 9, "y, mm")
        self._origin(c)
        for d in self.defects:
            if d.get("centroid_mm"):
                self._badge(c, *self._at(*d["centroid_mm"]), str(d["id"]))

    def _origin(self, c: Any) -> None:
        ox, oy = self._at(0.0, 0.0)
        arm = 9 * mm
        c.setStrokeColor(colors.black)
        c.setLineWidth(1.0)
        c.line(ox, oy, ox + arm, oy)
        c.line(ox, oy, ox, oy + arm)
        c.setFont("Helvetica-Bold", 8)
        c.drawString(ox + arm + 2, oy - 3, "x")
        c.drawCentredString(ox, oy + arm + 3, "y")

    def _badge(self, c: Any, x: float, y: float, label: str) -> None:
        radius = 6.0
        c.setStrokeColor(colors.black)
        c.setLineWidth(1.0)
        c.line(x, y, x + 1.6 * radius, y + 1.6 * radius)
        c.setFillColor(colors.white)
        c.circle(x + 2.2 * radius, y + 2.2 * radius, radius, stroke=1, fill=1)
        c.setFillColor(colors.black)
        c.setFont("Helvetica-Bold", 7.5)
        c.drawCentredString(x + 2.2 * radius, y + 1.9 * radius, label)


class GapProfile(Flowable):  # type: ignore[misc]  # ReportLab is untyped
    """One virtual template's gap along its frame line: the tolerance band, the gap (red beyond it),
    the frame's position and, if it goes through one, its defect."""

    HEIGHT = 24 * mm
    LABEL = 34 * mm

    def __init__(self, section: Section, tolerance_mm: float, width: float) -> None:
        super().__init__()
        self.section, self.tolerance = section, tolerance_mm
        self.width, self.height = width, self.HEIGHT + 3 * mm
        gaps = section.gap_mm[np.isfinite(section.gap_mm)]
        self.limit = max(2.0 * tolerance_mm, float(np.abs(gaps).max()) if gaps.size else 0.0)

    def draw(self) -> None:
        c, s = self.canv, self.section
        plot_w = self.width - self.LABEL
        length = float(s.u_mm[-1]) or 1.0
        mid = self.HEIGHT / 2

        def xy(u: float, gap: float) -> tuple[float, float]:
            return self.LABEL + u / length * plot_w, mid + gap / self.limit * (self.HEIGHT / 2 - 1)

        c.setFont("Helvetica", 7.5)
        c.setFillColor(colors.black)
        c.drawString(0, mid + 2, f"Frame at {s.position_mm:.0f} mm")
        if s.defect:
            c.setFont("Helvetica-Bold", 7.5)
            c.drawString(0, mid - 8, f"through defect {s.defect}")
        x0, band_lo = xy(0.0, -self.tolerance)
        _, band_hi = xy(0.0, self.tolerance)
        c.setFillColor(colors.HexColor("#e3f1e3"))
        c.rect(x0, band_lo, plot_w, band_hi - band_lo, stroke=0, fill=1)
        c.setStrokeColor(colors.HexColor("#999999"))
        c.setLineWidth(0.4)
        c.line(x0, mid, x0 + plot_w, mid)
        c.setFont("Helvetica", 6)
        c.setFillColor(colors.HexColor("#555555"))
        c.drawRightString(x0 - 2, band_hi - 2, f"+{self.tolerance:g}")
        c.drawRightString(x0 - 2, band_lo - 2, f"−{self.tolerance:g}")
        c.drawRightString(x0 + plot_w, -2 * mm, f"{length:.0f} mm")
        c.setLineWidth(1.0)
        for (u0, g0), (u1, g1) in pairwise(zip(s.u_mm, s.gap_mm, strict=True)):
            if not (np.isfinite(g0) and np.isfinite(g1)):
                continue
            bad = max(abs(g0), abs(g1)) > self.tolerance
            c.setStrokeColor(colors.HexColor("#b3261e") if bad else colors.HexColor("#1d2733"))
            c.line(*xy(float(u0), float(g0)), *xy(float(u1), float(g1)))


def _table(
    rows: list[list[str]], *, widths: tuple[float | None, ...] | None = None, header: bool = False
) -> Table:
    table = Table(rows, colWidths=widths, hAlign="LEFT")
    style = [
        ("FONT", (0, 0), (-1, -1), "Helvetica", 9.5),
        ("VALIGN", (0, 0), (-1, -1), "TOP"),
        ("BOTTOMPADDING", (0, 0), (-1, -1), 3),
        ("TOPPADDING", (0, 0), (-1, -1), 3),
    ]
    if header:
        style += [
            ("FONT", (0, 0), (-1, 0), "Helvetica-Bold", 9.5),
            ("LINEBELOW", (0, 0), (-1, 0), 0.8, colors.black),
            ("LINEBELOW", (0, 1), (-1, -1), 0.3, colors.lightgrey),
            ("ALIGN", (1, 0), (-1, -1), "RIGHT"),
        ]
    else:
        style += [("TEXTCOLOR", (0, 0), (0, -1), colors.HexColor("#555555"))]
    table.setStyle(TableStyle(style))
    return table


def _section(title: str, styles: Any) -> Paragraph:
    return Paragraph(title, styles["Heading3"])


def _when(value: datetime | str) -> str:
    moment = datetime.fromisoformat(value) if isinstance(value, str) else value
    if moment.tzinfo is None:
        from datetime import UTC

        moment = moment.replace(tzinfo=UTC)
    return moment.strftime("%Y-%m-%d %H:%M:%S %Z").replace("+00:00", "")


def _num(value: Any, digits: int, unit: str = "") -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "—"
    return f"{float(value):.{digits}f}{(' ' + unit) if unit else ''}"


def _mm(value: Any, digits: int, *, prefix: str = "") -> str:
    text = _num(value, digits, "mm")
    return text if text == "—" else prefix + text


def _signed(value: Any, digits: int, unit: str = "") -> str:
    if value is None:
        return "—"
    return f"{float(value):+.{digits}f}{(' ' + unit) if unit else ''}"


def _shape_text(shape: dict[str, Any]) -> str:
    kind = shape.get("type", "—")
    if shape.get("radius_mm") is not None:
        return f"{kind}, radius {float(shape['radius_mm']):.0f} mm"
    if kind == "mesh":
        return f"mesh {shape.get('file', '')}"
    return str(kind)


def _size_text(size: Any) -> str:
    if not size:
        return "—"
    return " × ".join(f"{float(v):.0f}" for v in size) + " mm"


def _escape(text: str) -> str:
    return text.replace("&", "&amp;").replace("<", "&lt;").replace(">", "&gt;")
