"""The forming advice in a roll-bending operator's words, shown first under a result's verdict and on
the plate page: the plate's state ("under-bent: radius +5.0 % (5 251 mm, 5.0 % open)"), the next pass
("next pass on R3-07: top roll 111.3 mm, expected 5 106 mm, then one more pass"), or, with no
advice, what is missing and a link to the page that supplies it. Never an API path.
"""

from __future__ import annotations

import math
import re
from typing import Any
from urllib.parse import quote

from sqlalchemy.orm import Session

from app.services import forming as forming_svc
from app.services import plates as plate_svc
from app.services.errors import ServiceError
from pipeline.formats import InputError

#: An API path in a service's message ("add it first with PUT /api/v1/machines/R3"), left out:
#: the page links the form instead.
_API_PATH = re.compile(r"[:;,]?\s*(?:add it first with )?\(?(?:PUT|GET|POST|DELETE) /api/v1/\S*\)?")

#: A thin space between thousands, as a drawing writes "5 251 mm".
THOUSANDS = "\u202f"


def mm(value: float, digits: int = 0) -> str:
    """``5251.3`` -> ``"5 251 mm"`` (thousands split by a narrow space, a true minus sign)."""
    return f"{value:,.{digits}f}".replace(",", THOUSANDS).replace("-", "\u2212") + " mm"


def count(n: int, one: str, many: str) -> str:
    """``1 pass``, ``3 passes``."""
    return f"{n} {one if n == 1 else many}"


def radius_band_mm(target: dict[str, Any]) -> tuple[float, float] | None:
    """Radii within which a cylinder target's plate stays in tolerance at its edges, from the
    target document: ``R (1 -+ 8 tol R / w^2)`` over the width ``w`` across the bend; None for
    another shape or without a size."""
    shape, size = target.get("shape") or {}, target.get("size_mm") or []
    radius, tolerance = shape.get("radius_mm"), target.get("tolerance_mm")
    if shape.get("type") != "cylinder" or not radius or not size or not tolerance:
        return None
    half = 8.0 * float(tolerance) * float(radius) / float(size[0]) ** 2
    return float(radius) * (1.0 - half), float(radius) * (1.0 + half)


def radius_state(row: Any, band_mm: tuple[float, float] | None) -> str | None:
    """The measured radius against the target's in the operator's words; None without both radii.

    ``band_mm``: radii (lo, hi) within which the plate is on target (the advice's, or
    :func:`radius_band_mm`); without one the radius is given without a judgement.
    """
    radius, target = getattr(row, "radius_mm", None), getattr(row, "target_radius_mm", None)
    if radius is None or target is None or not math.isfinite(radius) or target <= 0:
        return None
    error_pct = 100.0 * (radius - target) / target
    signed = "0.0 %" if round(error_pct, 1) == 0 else f"{error_pct:+.1f} %".replace("-", "\u2212")
    if band_mm is None:
        return f"radius {mm(radius)} against {mm(target)} ({signed})"
    if band_mm[0] <= radius <= band_mm[1]:
        return f"radius on target: {mm(radius)} ({signed})"
    if error_pct > 0:  # larger than the target's: the plate is still too open
        return f"under-bent: radius {signed} ({mm(radius)}, {abs(error_pct):.1f} % open)"
    return f"over-bent: radius {signed} ({mm(radius)}, {abs(error_pct):.1f} % tight)"


def next_pass_words(advice: dict[str, Any]) -> str:
    """The advised action as the operator reads it."""
    machine = advice["machine_id"]
    if advice["action"] == "done":
        return f"done: no further pass on {machine}"
    d, expected = advice.get("top_roll_displacement_mm"), advice.get("expected_radius_mm")
    setting = "" if d is None else f": top roll {d:.1f} mm"
    outcome = "" if expected is None else f", expected {mm(expected)}"
    if advice["action"] == "reverse":
        return f"reverse: turn the plate over on {machine}{setting}{outcome}"
    band = advice.get("basis", {}).get("tolerance_band_radius_mm")
    more = ""
    if expected is not None and band and not band[0] <= expected <= band[1]:
        more = ", then one more pass"
    elif expected is not None:
        more = ", within tolerance"
    return f"next pass on {machine}{setting}{outcome}{more}"


def advice_panel(
    session: Session, plate_id: str, row: Any = None, target: dict[str, Any] | None = None
) -> dict[str, Any]:
    """The "Forming" panel: ``state`` (of ``row``, judged against ``target``, the document it was
    inspected against) and ``next`` sentences with the ``advice`` they come from, or ``reason``
    and ``link`` (``(href, text)``: the page that supplies what is missing)."""
    panel = _advice_or_missing(session, plate_id)
    advice = panel.get("advice")
    band = (
        tuple(advice["basis"]["tolerance_band_radius_mm"])
        if advice
        else radius_band_mm(target or {})
    )
    panel["state"] = None if row is None else radius_state(row, band)
    panel["next"] = next_pass_words(advice) if advice else None
    return panel


def _advice_or_missing(session: Session, plate_id: str) -> dict[str, Any]:
    target_page = (f"/plates/{quote(plate_id)}#target", "Set the plate's target")
    overview = plate_svc.overview(session=session, plate_id=plate_id)
    target = None if overview is None else overview.target
    if target is None:
        why = "no forming advice: this plate has no target (radius, tolerance and material)"
        return {"reason": why, "link": target_page}
    if target.shape != "cylinder":
        why = f"no forming advice: roll-bending advice is for cylinders; this target is a {target.shape}"
        return {"reason": why}
    if not (target.document or {}).get("material"):
        why = "no forming advice: the plate's target has no material (grade, thickness, yield)"
        return {"reason": why, "link": target_page}
    machine_id = None
    if not forming_svc.plate_passes(session=session, plate_id=plate_id):
        machines = forming_svc.list_machines(session=session)
        if len(machines) != 1:
            why = (
                "no forming advice: no roll bender is known"
                if not machines
                else f"no pass of this plate yet, and {len(machines)} roll benders: "
                "the first pass's machine is not known"
            )
            return {"reason": why, "link": ("/machines", "Roll benders")}
        machine_id = machines[0].id
    try:
        advice = forming_svc.advise(session=session, plate_id=plate_id, machine_id=machine_id)
    except (ServiceError, InputError) as err:
        detail = err.detail if isinstance(err, ServiceError) else str(err)
        why = _API_PATH.sub("", detail.split(": ", 1)[-1]).rstrip(" :;,")
        link = ("/machines", "Roll benders") if "machine" in why else None
        return {"reason": f"no forming advice: {why}", "link": link}
    return {"advice": advice.to_dict()}
