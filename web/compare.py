"""Two inspections of one plate side by side (issue 13): their numbers and the change between them,
and each one's deviation map in the plate's frame (same axes, same colours), so that an operator
sees what the last pass changed and where."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from sqlalchemy.orm import Session

from app.models import Inspection, JobStatus
from app.services import inspections as inspection_svc


class CannotCompare(Exception):
    """The chosen inspections cannot be compared; says why (the page answers 404 or 422)."""

    def __init__(self, status_code: int, detail: str) -> None:
        super().__init__(detail)
        self.status_code = status_code
        self.detail = detail


@dataclass(frozen=True)
class Quantity:
    """One row of the comparison: a label, the two values, their unit, digits, and the change."""

    label: str
    a: float | None
    b: float | None
    unit: str
    digits: int
    #: whether a smaller magnitude is better (the change is coloured by it); None: neither
    smaller_is_better: bool | None

    @property
    def change(self) -> float | None:
        return None if self.a is None or self.b is None else self.b - self.a

    @property
    def better(self) -> bool | None:
        """The change went the right way (None: no change, or no better way)."""
        if self.change is None or self.smaller_is_better is None or self.a is None:
            return None
        if self.b is None or abs(self.b) == abs(self.a):
            return None
        return (abs(self.b) < abs(self.a)) == self.smaller_is_better


def done_inspections(session: Session, plate_id: str) -> list[Inspection]:
    """The plate's done inspections, oldest first (at most 200)."""
    rows, _total = inspection_svc.list_inspections(session=session, plate_id=plate_id, limit=200)
    return [r for r in reversed(rows) if r.status == JobStatus.DONE]


def compare_context(
    session: Session, plate_id: str, a: int | None, b: int | None
) -> dict[str, Any]:
    """The page's context: ``first``, ``second`` (inspections), ``quantities``, ``choices``.

    Without ``a`` and ``b``: the plate's last two done inspections.

    Raises
    ------
    CannotCompare
        404: no such plate or inspection of it; 422: the same inspection twice, one not done, or
        fewer than two done inspections.
    """
    done = done_inspections(session, plate_id)
    if a is None and b is None:
        if len(done) < 2:
            raise CannotCompare(
                422, f"plate {plate_id!r} has {len(done)} done inspection(s); comparing needs two"
            )
        first, second = done[-2], done[-1]
    elif a is None or b is None:
        raise CannotCompare(422, "a, b: give both inspections to compare, or neither")
    else:
        first, second = (_of_plate(session, plate_id, k, name) for k, name in ((a, "a"), (b, "b")))
        if first.id == second.id:
            raise CannotCompare(422, f"b: inspection {b} is a; choose two different inspections")
    quantities = [
        Quantity("Radius", first.radius_mm, second.radius_mm, "mm", 1, None),
        Quantity("Radius error", first.radius_error_pct, second.radius_error_pct, "%", 2, True),
        Quantity("RMS deviation", first.rms_mm, second.rms_mm, "mm", 2, True),
        Quantity("95th percentile |dev|", first.p95_mm, second.p95_mm, "mm", 2, True),
        Quantity("Max |dev|", first.max_abs_mm, second.max_abs_mm, "mm", 2, True),
        Quantity(
            "Within tolerance",
            first.within_tolerance_pct,
            second.within_tolerance_pct,
            "%",
            1,
            False,
        ),
        Quantity("Setting", _setting(first), _setting(second), "mm", 1, None),
    ]
    return {"first": first, "second": second, "quantities": quantities, "choices": done}


def _of_plate(session: Session, plate_id: str, inspection_id: int, name: str) -> Inspection:
    row = inspection_svc.get_inspection(session=session, inspection_id=inspection_id)
    if row is None or row.plate_id != plate_id:
        raise CannotCompare(404, f"{name}: plate {plate_id!r} has no inspection {inspection_id}")
    if row.status != JobStatus.DONE:
        raise CannotCompare(
            422, f"{name}: inspection {inspection_id} is {row.status}; only done ones have results"
        )
    return row


def _setting(row: Inspection) -> float | None:
    """The top-roll setting of the pass that produced the shape, if recorded."""
    value = (row.process or {}).get("top_roll_displacement_mm")
    return None if value is None else float(value)
