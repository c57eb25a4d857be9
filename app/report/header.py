"""The header on every page of the report: who, what, where and with what it was measured, and
"Page X of Y" (the canvas holds every page until the last, so the total is known when it draws).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from reportlab.lib import colors
from reportlab.lib.pagesizes import A4
from reportlab.lib.units import mm
from reportlab.pdfbase.pdfmetrics import stringWidth
from reportlab.pdfgen.canvas import Canvas

#: Page margins, points; the header sits in the top margin.
MARGIN_X = 18 * mm
MARGIN_BOTTOM = 14 * mm
HEADER_TOP = 10 * mm
#: Rows of the header's grid, and the space the body leaves for them.
HEADER_ROW = 9.6
FONT_SIZE = 7.4


@dataclass(frozen=True)
class PageHeader:
    """What the header of every page says.

    Attributes
    ----------
    title : str
        ``Forming inspection report: plate H77-B21-P07``.
    report_number : str
    cells : list of (label, value)
        Read left to right, three to a row; a value is never blank (``not recorded``).
    """

    title: str
    report_number: str
    cells: list[tuple[str, str]]

    @property
    def rows(self) -> int:
        return (len(self.cells) + 2) // 3

    @property
    def height(self) -> float:
        """Points from the page's top edge to the body."""
        return float(HEADER_TOP + 14 + self.rows * HEADER_ROW + 7 * mm)


def draw_header(canvas: Canvas, header: PageHeader, page: int, pages: int) -> None:
    """Draw ``header`` at the top of the current page, with ``Page page of pages``."""
    width, height = A4
    top = height - HEADER_TOP
    canvas.saveState()
    canvas.setFillColor(colors.black)
    canvas.setFont("Helvetica-Bold", 9.5)
    canvas.drawString(MARGIN_X, top - 9, _clip(header.title, "Helvetica-Bold", 9.5, 110 * mm))
    canvas.setFont("Helvetica", 8.5)
    canvas.drawRightString(
        width - MARGIN_X, top - 9, f"Report {header.report_number}   Page {page} of {pages}"
    )
    column = (width - 2 * MARGIN_X) / 3
    label_w = 23 * mm
    for k, (label, value) in enumerate(header.cells):
        x = MARGIN_X + (k % 3) * column
        y = top - 14 - (k // 3 + 1) * HEADER_ROW + 2
        canvas.setFont("Helvetica", FONT_SIZE)
        canvas.setFillColor(colors.HexColor("#4a4a4a"))
        canvas.drawString(x, y, label)
        canvas.setFillColor(colors.black)
        canvas.setFont("Helvetica-Bold", FONT_SIZE)
        canvas.drawString(
            x + label_w, y, _clip(value, "Helvetica-Bold", FONT_SIZE, column - label_w - 2)
        )
    rule = top - 14 - header.rows * HEADER_ROW - 2
    canvas.setStrokeColor(colors.HexColor("#333333"))
    canvas.setLineWidth(0.6)
    canvas.line(MARGIN_X, rule, width - MARGIN_X, rule)
    canvas.restoreState()


def _clip(text: str, font: str, size: float, width: float) -> str:
    """``text`` cut (with an ellipsis) to fit ``width`` points."""
    if stringWidth(text, font, size) <= width:
        return text
    while text and stringWidth(text + "...", font, size) > width:
        text = text[:-1]
    return text + "..."


def numbered_canvas(header: PageHeader) -> Callable[..., Canvas]:
    """A ReportLab canvas maker whose pages all get ``header`` and ``Page X of Y``."""

    class _NumberedCanvas(Canvas):  # type: ignore[misc]  # ReportLab is untyped
        def __init__(self, *args: Any, **kwargs: Any) -> None:
            super().__init__(*args, **kwargs)
            self._held: list[dict[str, Any]] = []

        def showPage(self) -> None:
            self._held.append(dict(self.__dict__))
            self._startPage()

        def save(self) -> None:
            pages = len(self._held)
            for number, state in enumerate(self._held, start=1):
                self.__dict__.update(state)
                draw_header(self, header, number, pages)
                super().showPage()
            super().save()

    return _NumberedCanvas
