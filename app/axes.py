"""Round axis ticks, for the dashboard's SVG charts (:mod:`web.charts`) and the PDF report's map."""

from __future__ import annotations

import numpy as np


def nice_ticks(lo: float, hi: float, *, max_ticks: int = 6) -> tuple[list[float], int]:
    """Round axis ticks covering ``[lo, hi]``: a step of 1, 2, 2.5 or 5 times a power of ten.

    Returns
    -------
    ticks : the tick values, ascending, the first <= lo and the last >= hi (at least 2).
    decimals : digits after the point that print every tick exactly.
    """
    if not (np.isfinite(lo) and np.isfinite(hi)) or hi < lo:
        raise ValueError(f"axis range: expected finite lo <= hi, got [{lo}, {hi}]")
    if hi - lo < 1e-12:
        lo, hi = lo - 0.5 * max(abs(lo), 1.0), hi + 0.5 * max(abs(hi), 1.0)
    raw = (hi - lo) / (max_ticks - 1)
    power = 10.0 ** np.floor(np.log10(raw))
    step = next(m * power for m in (1.0, 2.0, 2.5, 5.0, 10.0) if m * power >= raw * (1 - 1e-9))
    first, last = np.floor(lo / step + 1e-9), np.ceil(hi / step - 1e-9)
    ticks = [float(k * step) + 0.0 for k in np.arange(first, last + 1)]
    decimals = max(
        0, int(-np.floor(np.log10(step) + 1e-9)) + (1 if round(step / power) * power != step else 0)
    )
    return ticks, decimals
