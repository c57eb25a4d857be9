"""The report's drawings: the deviation map in the target's frame (colour bar in mm, a callout per
defect with its value and tolerance, the outline of each conveyor station of a plate measured at
stations), the camera's map when there is no plate map, the histogram
of the deviation and each virtual template's gap along its frame.
"""

from __future__ import annotations

from itertools import pairwise
from pathlib import Path
from typing import Any

import numpy as np
from reportlab.lib import colors
from reportlab.lib.units import mm
from reportlab.platypus import Flowable

from app.axes import nice_ticks
from app.report.text import signed
from app.schemas import StationOut
from pipeline.artifacts.colours import default_limit_mm, tolerance_band_colormap
from pipeline.artifacts.png import deviation_png_layout
from pipeline.judge.plate_map import PlateMap
from pipeline.judge.sections import Section

#: Unmeasured cells of the map, as its legend says ("light grey: not measured").
UNMEASURED_RGB = (214, 214, 214)
RED, INK, GREY = colors.HexColor("#b3261e"), colors.HexColor("#1d2733"), colors.HexColor("#555555")
#: The stations' outlines, as on the dashboard's map.
STATION_COLOUR = colors.HexColor("#6a3fb0")


def band_rgb(values_mm: np.ndarray, tolerance_mm: float) -> np.ndarray:
    """Tolerance-band colours of ``values_mm`` (the map's), unmeasured cells light grey."""
    rgb = tolerance_band_colormap(
        values_mm, tolerance_mm=tolerance_mm, limit_mm=default_limit_mm(tolerance_mm)
    )
    rgb[np.isnan(values_mm)] = UNMEASURED_RGB
    return rgb


class PlateMapFigure(Flowable):  # type: ignore[misc]  # ReportLab is untyped
    """The deviation map in the target's frame: tolerance-band colours, mm axes, the origin, a
    colour bar in mm, and at each defect's ``centroid_mm`` a callout: its number, peak deviation
    and the tolerance."""

    MAX_HEIGHT = 112 * mm
    LEFT, BOTTOM, TOP, BAR = 16 * mm, 11 * mm, 7 * mm, 24 * mm

    def __init__(
        self,
        plate: PlateMap,
        tolerance_mm: float,
        defects: list[dict[str, Any]],
        width: float,
        stations: list[StationOut] | None = None,
    ) -> None:
        super().__init__()
        self.plate, self.defects, self.tolerance = plate, defects, tolerance_mm
        self.stations = stations or []
        x0, x1, y0, y1 = plate.extent_mm
        self.scale = min(  # points per mm
            (width - self.LEFT - self.BAR - 4 * mm) / (x1 - x0),
            (self.MAX_HEIGHT - self.BOTTOM - self.TOP) / (y1 - y0),
        )
        self.width = width
        self.height = self.BOTTOM + (y1 - y0) * self.scale + self.TOP
        from PIL import Image
        from reportlab.lib.utils import ImageReader

        rows = plate.deviation_mm[::-1]  # first row at the largest y: y up on the page
        image = Image.fromarray(band_rgb(rows, tolerance_mm), mode="RGB")
        k = max(1, 1200 // max(image.size))  # enlarged: cells stay square in any PDF viewer
        self.image = ImageReader(
            image.resize((image.width * k, image.height * k), Image.Resampling.NEAREST)
        )

    def _at(self, x_mm: float, y_mm: float) -> tuple[float, float]:
        x0, _, y0, _ = self.plate.extent_mm
        return self.LEFT + (x_mm - x0) * self.scale, self.BOTTOM + (y_mm - y0) * self.scale

    def draw(self) -> None:
        c = self.canv
        x0, x1, y0, y1 = self.plate.extent_mm
        left, bottom = self._at(x0, y0)
        right, top = self._at(x1, y1)
        c.drawImage(self.image, left, bottom, width=right - left, height=top - bottom)
        self._stations(c, left, bottom, right, top)
        self._axes(c, left, bottom, right, top)
        self._origin(c)
        self._colour_bar(c, right + 8 * mm, bottom, top)
        placed: list[tuple[float, float]] = []
        for d in self.defects:
            if d.get("centroid_mm"):
                x, y = self._at(*d["centroid_mm"])
                self._callout(c, x, y, d, placed, right)

    def _stations(self, c: Any, left: float, bottom: float, right: float, top: float) -> None:
        """Each conveyor station's outline (within the map) and its number at the map's left edge, a
        quarter of the way up the part of the plate only that station sees (as the dashboard's map)."""
        x0, _, y0, y1 = self.plate.extent_mm
        c.saveState()
        box = c.beginPath()
        box.rect(left, bottom, right - left, top - bottom)
        c.clipPath(box, stroke=0, fill=0)
        c.setStrokeColor(STATION_COLOUR)
        c.setFillColor(STATION_COLOUR)
        c.setLineWidth(0.9)
        c.setFont("Helvetica-Bold", 7)
        outlines = [(s.index, s.outline_mm) for s in self.stations if s.outline_mm]
        spans = [(min(y for _, y in o), max(y for _, y in o)) for _, o in outlines]
        for k, (index, outline) in enumerate(outlines):
            points = [self._at(x, y) for x, y in outline]
            path = c.beginPath()
            path.moveTo(*points[0])
            for point in points[1:]:
                path.lineTo(*point)
            path.close()
            c.drawPath(path, stroke=1, fill=0)
            lo, hi = spans[k]
            own = (
                max(lo, spans[k - 1][1] if k > 0 else lo, y0),
                min(hi, spans[k + 1][0] if k + 1 < len(spans) else hi, y1),
            )
            if own[0] >= own[1]:
                own = (max(lo, y0), min(hi, y1))
            lx, ly = self._at(x0, own[0] + 0.25 * (own[1] - own[0]))
            c.drawString(lx + 3, ly - 2.5, f"station {index}")
        c.restoreState()

    def _axes(self, c: Any, left: float, bottom: float, right: float, top: float) -> None:
        x0, x1, y0, y1 = self.plate.extent_mm
        c.setStrokeColor(GREY)
        c.setFillColor(colors.black)
        c.setLineWidth(0.5)
        c.setFont("Helvetica", 7)
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

    def _colour_bar(self, c: Any, x: float, bottom: float, top: float) -> None:
        """The colours against deviation in mm, -limit (bottom) to +limit, ticks at 0, the
        tolerance and the limit."""
        limit = default_limit_mm(self.tolerance)
        steps = 120
        values = np.linspace(-limit, limit, steps)
        rgb = band_rgb(values, self.tolerance)
        h = (top - bottom) / steps
        for k in range(steps):
            c.setFillColorRGB(*(rgb[k] / 255.0))
            c.rect(x, bottom + k * h, 5 * mm, h + 0.3, stroke=0, fill=1)
        c.setStrokeColor(GREY)
        c.setLineWidth(0.5)
        c.rect(x, bottom, 5 * mm, top - bottom, stroke=1, fill=0)
        c.setFillColor(colors.black)
        c.setFont("Helvetica", 6.5)
        for v in (-limit, -self.tolerance, 0.0, self.tolerance, limit):
            py = bottom + (v + limit) / (2 * limit) * (top - bottom)
            c.line(x + 5 * mm, py, x + 5 * mm + 2, py)
            c.drawString(x + 5 * mm + 3, py - 2.2, signed(v, 1))
        c.drawString(x, top + 4, "mm")

    def _callout(
        self,
        c: Any,
        x: float,
        y: float,
        d: dict[str, Any],
        placed: list[tuple[float, float]],
        right: float,
    ) -> None:
        """The defect's number, peak and tolerance in a box beside it (moved down past earlier ones)."""
        label = f"{d['id']}: {signed(d.get('peak_mm'), 1)} mm (tol. ±{self.tolerance:g})"
        c.setFont("Helvetica-Bold", 6.8)
        w = c.stringWidth(label, "Helvetica-Bold", 6.8) + 5
        bx = x + 8 if x + 8 + w <= right else x - 8 - w
        by = y + 6
        while any(abs(by - py) < 10 and abs(bx - px) < w for px, py in placed):
            by -= 11
        placed.append((bx, by))
        c.setStrokeColor(colors.black)
        c.setLineWidth(0.8)
        c.line(x, y, bx if bx > x else bx + w, by + 3.5)
        c.circle(x, y, 1.6, stroke=1, fill=0)
        c.setFillColor(colors.white)
        c.rect(bx, by - 1, w, 9.5, stroke=1, fill=1)
        c.setFillColor(colors.black)
        c.drawString(bx + 2.5, by + 1.4, label)


class DeviationMap(Flowable):  # type: ignore[misc]  # ReportLab is untyped
    """deviation.png at the text width, a numbered circle at each defect's centroid (the camera's
    view: printed when the artifacts give no map in the target's frame)."""

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


class Histogram(Flowable):  # type: ignore[misc]  # ReportLab is untyped
    """The share of the map's cells per deviation bin, bars in the map's colours, the tolerance
    marked; values beyond the axis are counted in its end bins (said under it)."""

    HEIGHT = 42 * mm

    def __init__(self, values_mm: np.ndarray, tolerance_mm: float, width: float) -> None:
        super().__init__()
        self.tolerance = tolerance_mm
        self.width, self.height = width, self.HEIGHT
        self.limit = default_limit_mm(tolerance_mm)
        edges = np.linspace(-self.limit, self.limit, 33)
        self.counts, _ = np.histogram(np.clip(values_mm, -self.limit, self.limit), bins=edges)
        self.centres = 0.5 * (edges[:-1] + edges[1:])
        self.share = self.counts / max(1, values_mm.size)

    def draw(self) -> None:
        c = self.canv
        left, bottom = 12 * mm, 9 * mm
        plot_w, plot_h = self.width - left - 8 * mm, self.height - bottom - 4 * mm
        top_share = max(float(self.share.max()), 1e-9)
        bar_w = plot_w / len(self.counts)
        rgb = band_rgb(self.centres, self.tolerance)
        for k, share in enumerate(self.share):
            c.setFillColorRGB(*(rgb[k] / 255.0))
            c.setStrokeColor(GREY)
            c.setLineWidth(0.3)
            c.rect(left + k * bar_w, bottom, bar_w, plot_h * share / top_share, stroke=1, fill=1)
        c.setStrokeColor(colors.black)
        c.setFillColor(colors.black)
        c.setFont("Helvetica", 6.5)
        c.line(left, bottom, left + plot_w, bottom)
        for v in (-self.limit, -self.tolerance, 0.0, self.tolerance, self.limit):
            px = left + (v + self.limit) / (2 * self.limit) * plot_w
            c.line(px, bottom, px, bottom - 3)
            c.drawCentredString(px, bottom - 10, signed(v, 1))
        c.drawString(left + plot_w + 12, bottom - 10, "mm")
        c.drawRightString(left - 3, bottom + plot_h - 2, f"{100 * top_share:.0f} %")
        c.drawRightString(left - 3, bottom - 2, "0 %")


class GapProfile(Flowable):  # type: ignore[misc]  # ReportLab is untyped
    """One virtual template's gap along its frame line: the tolerance band, the gap (red beyond it),
    the frame's position and, if it goes through one, its defect."""

    HEIGHT = 24 * mm
    LABEL = 34 * mm

    def __init__(
        self, section: Section, tolerance_mm: float, width: float, *, place: str | None = None
    ) -> None:
        super().__init__()
        self.section, self.tolerance, self.place = section, tolerance_mm, place
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
        if self.place:  # "x = −803 mm, 697 mm from edge D" on two lines
            at, _, from_edge = self.place.partition(", ")
            c.drawString(0, mid + 10, f"Frame at {at}")
            c.drawString(0, mid + 2, from_edge)
        else:
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
        c.setFillColor(GREY)
        c.drawRightString(x0 - 2, band_hi - 2, f"+{self.tolerance:g}")
        c.drawRightString(x0 - 2, band_lo - 2, f"-{self.tolerance:g}")
        c.drawRightString(x0 + plot_w, -2 * mm, f"{length:.0f} mm")
        c.setLineWidth(1.0)
        for (u0, g0), (u1, g1) in pairwise(zip(s.u_mm, s.gap_mm, strict=True)):
            if not (np.isfinite(g0) and np.isfinite(g1)):
                continue
            bad = max(abs(g0), abs(g1)) > self.tolerance
            c.setStrokeColor(RED if bad else INK)
            c.line(*xy(float(u0), float(g0)), *xy(float(u1), float(g1)))
