"""Server-side drawing data for the dashboard's SVGs: template sections, the history trend and the
forming passes (radius against setting).

Functions here turn numbers into screen coordinates; the templates draw them.
Nothing here builds markup.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from app.axes import nice_ticks
from pipeline.judge.sections import Section

#: Nice exaggeration factors for drawing mm-scale gaps on metre-scale sections.
_EXAGGERATIONS = (1, 2, 5, 10, 20, 50, 100, 200, 500, 1000, 2000, 5000)


@dataclass(frozen=True)
class GapLabel:
    x: float
    y_template: float
    y_plate: float
    gap_mm: float
    out_of_tolerance: bool


@dataclass(frozen=True)
class SectionDrawing:
    """Screen geometry (px, y down) of one virtual template."""

    position_mm: float
    width: float
    height: float
    template_polygon: str  # the board: its lower edge is the target section
    plate_polygon: str  # the plate, its upper edge at target + gap x exaggeration
    plate_edge: str  # polyline of that edge
    labels: list[GapLabel]
    exaggeration: int
    length_mm: float
    max_gap_mm: float | None
    defect: int | None = None  # the defect this frame goes through
    chosen: bool = False  # placed through a point the operator chose on the map
    line_mm: str = (
        ""  # "x1 y1 x2 y2": the frame line's ends in the target's frame, mm (for the map)
    )
    where: str = ""  # the frame in the target's frame: "x = −803 mm, 697 mm from edge D"
    ends: tuple[str, str] = ("0", "")  # names of the drawing's left and right ends


def _points(xs: np.ndarray, ys: np.ndarray) -> str:
    return " ".join(f"{x:.1f},{y:.1f}" for x, y in zip(xs, ys))


def section_drawings(
    sections: list[Section], *, tolerance_mm: float, width: float = 1100.0, n_labels: int = 9
) -> list[SectionDrawing]:
    """Lay out each section like the wooden template it replaces.

    The section's shape is drawn true to scale (same px/mm both ways); the gap between
    the template's edge and the plate is exaggerated by one factor for all sections
    (stated in the drawing) so that the larger of the largest gap and the tolerance spans
    about 24 px: a plate within tolerance looks like it fits its template (measurement
    noise of a few hundredths of a mm is not blown up into ripples), one beyond it shows
    its gap.
    """
    if not (np.isfinite(tolerance_mm) and tolerance_mm > 0):
        raise ValueError(f"tolerance_mm: expected a positive number, got {tolerance_mm}")
    if not sections:
        return []
    pad_x, board_px, plate_px, pad_y = 40.0, 46.0, 14.0, 34.0
    length = float(max(s.u_mm[-1] for s in sections))
    sx = (width - 2 * pad_x) / length
    gaps = np.concatenate([s.gap_mm[np.isfinite(s.gap_mm)] for s in sections] or [np.zeros(1)])
    max_gap = float(np.abs(gaps).max()) if gaps.size else 0.0
    wanted = 24.0 / (sx * max(max_gap, tolerance_mm))
    exaggeration = max([e for e in _EXAGGERATIONS if e <= wanted] or [1])
    h_all = np.concatenate([s.target_h_mm[np.isfinite(s.target_h_mm)] for s in sections])
    h_top, h_bottom = float(h_all.max()), float(h_all.min())
    rel = (h_top - h_bottom) * sx
    height = pad_y + board_px + rel + 24.0 + plate_px + pad_y

    def y_of(h_mm: np.ndarray) -> np.ndarray:
        return pad_y + board_px + (h_top - h_mm) * sx

    drawings = []
    for s in sections:
        ok = np.isfinite(s.target_h_mm)
        x = pad_x + s.u_mm[ok] * sx
        y_t = y_of(s.target_h_mm[ok])
        top = pad_y
        template_polygon = _points(np.r_[x[0], x, x[-1]], np.r_[top, y_t, top])
        gap = s.gap_mm[ok]
        has = np.isfinite(gap)
        y_p = np.where(has, y_t - gap * exaggeration * sx, np.nan)
        xp, yp = x[has], y_p[has]
        plate_polygon = (
            _points(np.r_[xp, xp[::-1]], np.r_[yp, yp[::-1] + plate_px]) if xp.size else ""
        )
        labels = [
            GapLabel(
                float(x[k]),
                float(y_t[k]),
                float(y_p[k]),
                float(gap[k]),
                bool(abs(gap[k]) > tolerance_mm),
            )
            for k in _label_indices(x, gap, n_labels)
        ]
        drawings.append(
            SectionDrawing(
                position_mm=s.position_mm,
                width=width,
                height=height,
                template_polygon=template_polygon,
                plate_polygon=plate_polygon,
                plate_edge=_points(xp, yp),
                labels=labels,
                exaggeration=exaggeration,
                length_mm=length,
                max_gap_mm=float(np.nanmax(np.abs(gap))) if has.any() else None,
                defect=s.defect,
                chosen=s.chosen,
            )
        )
    return drawings


#: Least distance between two gap labels' centres, px of the drawing: "+0.00" at 14 px is ~42 px wide.
LABEL_SPACING_PX = 56.0


def _label_indices(x: np.ndarray, gap: np.ndarray, n_labels: int) -> list[int]:
    """Where a section's gaps are written: the largest gap first (the place a template shows its
    worst fit), then up to ``n_labels`` evenly spread over the measured part, each kept only if it
    stays :data:`LABEL_SPACING_PX` from every label already placed, so that labels never overlap."""
    finite = np.flatnonzero(np.isfinite(gap))
    if finite.size == 0:
        return []
    worst = int(finite[np.argmax(np.abs(gap[finite]))])
    spread = finite[np.linspace(0, finite.size - 1, n_labels).round().astype(int)]
    chosen: list[int] = []
    for k in [worst, *(int(i) for i in spread)]:
        if all(abs(x[k] - x[j]) >= LABEL_SPACING_PX for j in chosen):
            chosen.append(k)
    return sorted(chosen)


@dataclass(frozen=True)
class TrendPoint:
    x: float
    y: float
    value: float
    inspection_id: int


@dataclass(frozen=True)
class TrendSeries:
    name: str
    unit: str
    points: list[TrendPoint]
    polyline: str
    ticks: list[tuple[float, str]]  # (y px, label)
    limits: list[tuple[float, str]]  # tolerance lines: (y px, label)
    y0: float  # panel top, px
    y1: float  # panel bottom, px


@dataclass(frozen=True)
class TrendChart:
    width: float
    height: float
    left: float
    right: float
    series: list[TrendSeries]
    x_labels: list[tuple[float, str]]


def trend_chart(
    rows: list[tuple[int, str, float | None, float | None]],
    *,
    tolerance_mm: float | None,
    radius_band_pct: float | None = None,
    width: float = 900.0,
) -> TrendChart:
    """Two stacked panels: radius error (%) and max |deviation| (mm) per inspection, oldest left.

    Parameters
    ----------
    rows : (inspection_id, label, radius_error_pct, max_abs_mm) per done inspection, oldest first.
    tolerance_mm : drawn as a line on the deviation panel when given.
    radius_band_pct : the radius error at which a plate leaves the tolerance at its edges, drawn as
        lines at ± it on the radius panel when given (a trend inside them is noise, not a fault).
    """
    left, right, panel_h, gap, top = 64.0, 20.0, 130.0, 40.0, 20.0
    n = len(rows)
    inner = width - left - right
    xs = [left + (inner * (i + 0.5) / n if n else 0.0) for i in range(n)]
    series = []
    radius_lines = (
        [(radius_band_pct, "edges at tolerance"), (-radius_band_pct, "")] if radius_band_pct else []
    )
    tolerance_lines = [(tolerance_mm, "tolerance")] if tolerance_mm else []
    panels: tuple[tuple[str, str, list[float | None], list[tuple[float, str]]], ...] = (
        ("Radius error", "%", [r[2] for r in rows], radius_lines),
        ("Max |deviation|", "mm", [r[3] for r in rows], tolerance_lines),
    )
    for k, (name, unit, values, lines) in enumerate(panels):
        y0 = top + k * (panel_h + gap)
        finite = [v for v in values if v is not None]
        lo = min(finite + [0.0] + [v for v, _ in lines])
        hi = max(finite + [0.0] + [v for v, _ in lines])
        margin = 0.04 * (hi - lo)  # keep points and the tolerance line off the panel's edge
        tick_values, decimals = nice_ticks(
            lo - margin if lo < 0 else lo, hi + margin if hi > 0 else hi
        )
        lo, hi = tick_values[0], tick_values[-1]

        def y_of(v: float, y0: float = y0, lo: float = lo, hi: float = hi) -> float:
            return y0 + panel_h * (hi - v) / (hi - lo)

        points = [
            TrendPoint(x, y_of(v), v, r[0]) for x, v, r in zip(xs, values, rows) if v is not None
        ]
        ticks = [(y_of(v), f"{v:.{decimals}f}") for v in tick_values]
        series.append(
            TrendSeries(
                name=name,
                unit=unit,
                points=points,
                polyline=" ".join(f"{p.x:.1f},{p.y:.1f}" for p in points),
                ticks=ticks,
                limits=[(y_of(v), label) for v, label in lines],
                y0=y0,
                y1=y0 + panel_h,
            )
        )
    return TrendChart(
        width=width,
        height=top + 2 * panel_h + gap + 30.0,
        left=left,
        right=width - right,
        series=series,
        x_labels=[(x, r[1]) for x, r in zip(xs, rows)],
    )


def _padded(values: list[float]) -> tuple[float, float]:
    """The values' range widened by 4 % each side: points and lines stay off the panel's edge."""
    if not values:
        return 0.0, 1.0
    lo, hi = min(values), max(values)
    margin = 0.04 * (hi - lo)
    return lo - margin, hi + margin


@dataclass(frozen=True)
class FormingPoint:
    """One inspected pass on the forming chart (px) and its numbers."""

    x: float
    y: float
    number: int  # the pass's place among the plate's passes, 1 first
    setting_mm: float
    radius_mm: float
    verdict: str | None
    inspection_id: int


@dataclass(frozen=True)
class NextMarker:
    """The advised next pass: its setting, the expected radius and its 95 % range (px)."""

    x: float
    y: float
    y_lo: float
    y_hi: float
    setting_mm: float
    radius_mm: float


@dataclass(frozen=True)
class FormingChart:
    """Radius after each pass against the pass's setting (px, y down), with the target's band."""

    width: float
    height: float
    left: float
    right: float
    top: float
    bottom: float
    points: list[FormingPoint]
    polyline: str
    x_ticks: list[tuple[float, str]]
    y_ticks: list[tuple[float, str]]
    target_y: float
    band_y: tuple[float, float] | None  # (tight edge, open edge): the band's top and bottom
    next_pass: NextMarker | None
    flat_passes: int  # inspected passes that left the plate flat (not drawn)


def forming_chart(
    passes: list[tuple[int, float, float | None, str | None]],
    *,
    target_radius_mm: float,
    band_mm: tuple[float, float | None] | None = None,
    next_pass: tuple[float, float, tuple[float, float | None]] | None = None,
    width: float = 900.0,
) -> FormingChart:
    """The plate's passes as radius (y) against top-roll displacement (x), oldest first.

    Parameters
    ----------
    passes : (inspection_id, setting_mm, measured radius_mm or None/inf for flat, verdict) per pass.
    target_radius_mm : drawn as a line, with ``band_mm`` (tight, open radius; open None: any) shaded.
    next_pass : (setting_mm, expected radius_mm, (lo, hi) of its 95 % range, hi None: may stay flat),
        drawn as a hollow marker with its range.
    """
    left, right, top, bottom, height = 80.0, 20.0, 28.0, 36.0, 300.0
    drawn = [p for p in passes if p[2] is not None and np.isfinite(p[2])]
    xs_mm = [p[1] for p in passes] + ([next_pass[0]] if next_pass else [])
    ys_mm = [r for _, _, r, _ in drawn if r is not None] + [target_radius_mm]
    if band_mm is not None:
        ys_mm += [v for v in band_mm if v is not None and np.isfinite(v)]
    if next_pass is not None:
        ys_mm += [v for v in (next_pass[1], *next_pass[2]) if v is not None and np.isfinite(v)]
    x_ticks, x_dec = nice_ticks(*_padded(xs_mm))
    y_ticks, y_dec = nice_ticks(*_padded(ys_mm))
    x0, x1 = x_ticks[0], x_ticks[-1]
    y0, y1 = y_ticks[0], y_ticks[-1]

    def x_of(v: float) -> float:
        return left + (width - left - right) * (v - x0) / (x1 - x0)

    def y_of(v: float | None) -> float:
        v = y1 if v is None or not np.isfinite(v) else min(max(v, y0), y1)
        return top + (height - top - bottom) * (y1 - v) / (y1 - y0)

    points = [
        FormingPoint(x_of(s), y_of(r), k + 1, s, r, verdict, iid)
        for k, (iid, s, r, verdict) in enumerate(passes)
        if r is not None and np.isfinite(r)
    ]
    marker = None
    if next_pass is not None:
        setting, expected, (lo, hi) = next_pass
        marker = NextMarker(x_of(setting), y_of(expected), y_of(lo), y_of(hi), setting, expected)
    return FormingChart(
        width=width,
        height=height,
        left=left,
        right=width - right,
        top=top,
        bottom=height - bottom,
        points=points,
        polyline=" ".join(f"{p.x:.1f},{p.y:.1f}" for p in points),
        x_ticks=[(x_of(v), f"{v:.{x_dec}f}") for v in x_ticks],
        y_ticks=[(y_of(v), f"{v:.{y_dec}f}") for v in y_ticks],
        target_y=y_of(target_radius_mm),
        band_y=(y_of(band_mm[0]), y_of(band_mm[1])) if band_mm is not None else None,
        next_pass=marker,
        flat_passes=len(passes) - len(drawn),
    )
