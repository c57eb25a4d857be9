"""Plates: created on first use, listed with their latest inspection and current target."""

from __future__ import annotations

from dataclasses import dataclass

from sqlalchemy import ColumnElement, func, select
from sqlalchemy.orm import Session

from app.models import Inspection, Plate, Target
from app.storage import check_plate_id


@dataclass(frozen=True)
class PlateOverview:
    """A plate with what the plates list shows about it."""

    plate: Plate
    inspection_count: int
    latest_inspection: Inspection | None
    target: Target | None


def get_plate(*, session: Session, plate_id: str) -> Plate | None:
    return session.get(Plate, plate_id)


def get_or_create_plate(*, session: Session, plate_id: str) -> Plate:
    """The plate ``plate_id``, added to the session if new.

    Raises
    ------
    ValueError
        ``plate_id`` is not a valid plate id (see :func:`app.storage.check_plate_id`).
    """
    check_plate_id(plate_id)
    plate = session.get(Plate, plate_id)
    if plate is None:
        plate = Plate(id=plate_id)
        session.add(plate)
        session.flush()
    return plate


def current_target(*, session: Session, plate_id: str) -> Target | None:
    """The plate's newest target, or None."""
    return session.scalars(
        select(Target).where(Target.plate_id == plate_id).order_by(Target.id.desc()).limit(1)
    ).first()


def latest_inspection(*, session: Session, plate_id: str) -> Inspection | None:
    return session.scalars(
        select(Inspection)
        .where(Inspection.plate_id == plate_id)
        .order_by(Inspection.id.desc())
        .limit(1)
    ).first()


def overview(*, session: Session, plate_id: str) -> PlateOverview | None:
    """One plate's overview, or None if there is no such plate."""
    plate = session.get(Plate, plate_id)
    if plate is None:
        return None
    count = session.scalar(
        select(func.count()).select_from(Inspection).where(Inspection.plate_id == plate_id)
    )
    return PlateOverview(
        plate=plate,
        inspection_count=int(count or 0),
        latest_inspection=latest_inspection(session=session, plate_id=plate_id),
        target=current_target(session=session, plate_id=plate_id),
    )


def _id_contains(text: str) -> ColumnElement[bool]:
    """Plate ids containing ``text`` in any case (``%`` and ``_`` in it taken literally)."""
    escaped = text.replace("\\", "\\\\").replace("%", "\\%").replace("_", "\\_")
    return Plate.id.ilike(f"%{escaped}%", escape="\\")


def list_plates(
    *, session: Session, limit: int = 50, offset: int = 0, search: str | None = None
) -> tuple[list[PlateOverview], int]:
    """Plates, the most recently inspected (or created) first, with their latest inspection.

    ``search``: only plates whose id contains it (any case).

    Returns
    -------
    (overviews, total) with ``total`` the plates that match
    """
    if limit < 1 or offset < 0:
        raise ValueError(
            f"paging: expected limit >= 1 and offset >= 0, got limit={limit}, offset={offset}"
        )
    matching = _id_contains(search) if search else None
    counted = select(func.count()).select_from(Plate)
    total = int(session.scalar(counted if matching is None else counted.where(matching)) or 0)
    last = (
        select(
            Inspection.plate_id, func.max(Inspection.id).label("last_id"), func.count().label("n")
        )
        .group_by(Inspection.plate_id)
        .subquery()
    )
    query = select(Plate, last.c.last_id, last.c.n).outerjoin(last, last.c.plate_id == Plate.id)
    if matching is not None:
        query = query.where(matching)
    rows = session.execute(
        query.order_by(last.c.last_id.desc().nulls_last(), Plate.created_at.desc(), Plate.id)
        .limit(limit)
        .offset(offset)
    ).all()
    out = []
    for plate, last_id, n in rows:
        out.append(
            PlateOverview(
                plate=plate,
                inspection_count=int(n or 0),
                latest_inspection=session.get(Inspection, last_id) if last_id is not None else None,
                target=current_target(session=session, plate_id=plate.id),
            )
        )
    return out, total
