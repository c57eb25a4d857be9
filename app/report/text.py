"""How the report writes numbers, times and missing values.

A decimal point always (f-strings, never the locale); a sign only where a value is signed and not
zero at the printed precision (no ``-0.00``); a missing value is ``not recorded``, never a blank.
"""

from __future__ import annotations

import math
from datetime import UTC, datetime
from typing import Any

#: What the report prints where the data has no value.
NOT_RECORDED = "not recorded"
#: What it prints for an uncertainty the result does not state (results written before it had one).
NOT_STATED = "not stated"


def finite(value: Any) -> float | None:
    """``value`` as a float, or None when it is missing or not finite."""
    if value is None or isinstance(value, bool):
        return None
    try:
        number = float(value)
    except (TypeError, ValueError):
        return None
    return number if math.isfinite(number) else None


def num(value: Any, digits: int, unit: str = "", *, missing: str = NOT_RECORDED) -> str:
    """``value`` with ``digits`` decimals and its unit; ``missing`` when there is none."""
    number = finite(value)
    if number is None:
        return missing
    text = f"{round(number, digits) + 0.0:.{digits}f}"  # + 0.0: no "-0.0"
    return f"{text} {unit}" if unit else text


def signed(value: Any, digits: int, unit: str = "", *, missing: str = NOT_RECORDED) -> str:
    """``value`` with its sign (``+1.25``, ``-0.40``), or no sign where it prints as zero."""
    number = finite(value)
    if number is None:
        return missing
    rounded = round(number, digits)
    text = f"{rounded:+.{digits}f}" if rounded != 0 else f"{0.0:.{digits}f}"
    return f"{text} {unit}" if unit else text


def mm(value: Any, digits: int, *, prefix: str = "", missing: str = NOT_RECORDED) -> str:
    text = num(value, digits, "mm", missing=missing)
    return text if finite(value) is None else prefix + text


def when(value: datetime | str | None) -> str:
    """A time with its zone (``2026-11-26 09:01:02 UTC``); naive times are UTC (as stored)."""
    if value is None or value == "":
        return NOT_RECORDED
    try:
        moment = datetime.fromisoformat(value) if isinstance(value, str) else value
    except ValueError:
        return str(value)
    if moment.tzinfo is None:
        moment = moment.replace(tzinfo=UTC)
    zone = moment.strftime("%Z") or moment.strftime("%z")
    return moment.strftime("%Y-%m-%d %H:%M:%S ") + ("UTC" if zone in ("UTC", "+0000") else zone)


def text_or(value: Any, missing: str = NOT_RECORDED) -> str:
    """``value`` as text, or ``missing`` when it is None or blank."""
    if value is None:
        return missing
    text = str(value).strip()
    return text or missing


def escape(text: str) -> str:
    """Text for a ReportLab paragraph (its markup is XML-like)."""
    return text.replace("&", "&amp;").replace("<", "&lt;").replace(">", "&gt;")


def size_text(size: Any) -> str:
    if not size:
        return NOT_RECORDED
    return " x ".join(num(v, 0) for v in size) + " mm"


def shape_text(shape: dict[str, Any] | None) -> str:
    """The target's shape: ``cylinder, radius 5000 mm``; ``not recorded`` without a target."""
    if not shape:
        return NOT_RECORDED
    kind = str(shape.get("type") or NOT_RECORDED)
    if finite(shape.get("radius_mm")) is not None:
        return f"{kind}, radius {num(shape['radius_mm'], 0)} mm"
    if kind == "mesh":
        return f"mesh {text_or(shape.get('file'))}"
    return kind
