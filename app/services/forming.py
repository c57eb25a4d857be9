"""Forming (issue 14): the roll benders, the passes of inspected plates, and the advice for the next pass.

A pass is an inspection's ``process`` (``{"method": "roll-bending", "machine_id", "top_roll_displacement_mm"}``);
the inspection after it gives the measured radius and the verdict. The advice is
:func:`pipeline.forming.advise` on the plate's current target (a cylinder with its ``material``), its done
inspections with a process (oldest first) and the other plates' (see docs/forming.md).
"""

from __future__ import annotations

import math
from typing import Any, Literal

from sqlalchemy import func, select
from sqlalchemy.orm import Session

from app.models import Inspection, JobStatus, Machine, Target, utcnow
from app.services.errors import ConflictError, NotFoundError, UnprocessableError
from app.services.plates import current_target, get_plate
from pipeline import forming
from pipeline.io import load_target

#: Other plates whose passes are read for an advice: the most recently rolled ones. The fit itself uses
#: the latest ``Priors.max_plates`` (40) of them that went through the advised machine.
MAX_HISTORY_PLATES = 200


# ------------------------------------------------------------------ machines


def put_machine(*, session: Session, machine_id: str, spec: dict[str, Any]) -> tuple[Machine, bool]:
    """Add or replace a machine; ``spec`` is a validated :class:`app.schemas.MachineIn` as a dict.

    Returns
    -------
    (Machine, bool)
        The row and whether it is new.

    Raises
    ------
    pipeline.formats.InputError
        A geometry the forming model refuses (e.g. bottom rolls wider than their spacing; names the field).
    """
    forming.Machine.from_dict(machine_id, spec)
    found = session.get(Machine, machine_id)
    created = found is None
    if found is None:
        row = Machine(id=machine_id)
        session.add(row)
    else:
        row = found
    for name, value in spec.items():
        setattr(row, name, value)
    row.updated_at = utcnow()
    session.flush()
    return row, created


def list_machines(*, session: Session) -> list[Machine]:
    """Every machine, by id."""
    return list(session.scalars(select(Machine).order_by(Machine.id)))


def get_machine(*, session: Session, machine_id: str) -> Machine | None:
    return session.get(Machine, machine_id)


def machine_model(row: Machine) -> forming.Machine:
    """The forming model's record of a machine row."""
    return forming.Machine(
        row.id,
        row.bottom_roll_spacing_mm,
        row.bottom_roll_diameter_mm,
        row.top_roll_diameter_mm,
        kind=row.kind,
    )


def check_process(*, session: Session, process: dict[str, Any] | None) -> None:
    """Refuse a process (validated :class:`app.schemas.ProcessIn` as a dict) naming an unknown machine.

    Raises
    ------
    UnprocessableError
        Field ``process.machine_id``.
    """
    if process is not None and session.get(Machine, process["machine_id"]) is None:
        raise UnprocessableError(
            f"process.machine_id: no machine {process['machine_id']!r}: add it first with PUT /api/v1/machines/{process['machine_id']}",
            field="process.machine_id",
        )


# ------------------------------------------------------------------ passes and advice


def target_material(target: Target | None) -> dict[str, Any] | None:
    """The ``material`` object of a stored target's document, or None."""
    return None if target is None else target.document.get("material")


def forming_target(target: Target | None, plate_id: str) -> forming.FormingTarget:
    """The forming model's target of a plate's stored target.

    Raises
    ------
    ConflictError
        No target, not a single-curvature cylinder, or no material (the message says which).
    """
    if target is None:
        raise ConflictError(
            f"plate_id: plate {plate_id!r} has no target: set a cylinder target with its material "
            "(PUT /api/v1/plates/{plate_id}/target)",
            field="plate_id",
        )
    if target.shape != "cylinder":
        raise ConflictError(
            f"plate_id: plate {plate_id!r}'s target is a {target.shape}: roll-bending advice is for "
            "single-curvature (cylinder) targets only",
            field="plate_id",
        )
    if target_material(target) is None:
        raise ConflictError(
            f"plate_id: plate {plate_id!r}'s target has no material: roll-bending advice needs its "
            "grade, thickness and yield (plate-target/1 'material')",
            field="plate_id",
        )
    loaded = load_target(target.document, file_label="target.json")
    return forming.FormingTarget.from_target(loaded, target_material(target))


def roll_pass(row: Inspection) -> forming.RollPass:
    """A done inspection with a process as the pass and the measurement after it.

    A done inspection without a radius (nothing curved was measured) counts as a flat plate (``inf``).
    The stored result document gives the radius's uncertainty and whether the inspection is capable
    for the tolerance (:func:`pipeline.forming.records.inspection_quality`); older results have neither.
    """
    verdict: Literal["pass", "fail"] | None = (
        "pass" if row.verdict == "pass" else "fail" if row.verdict == "fail" else None
    )
    radius = math.inf if row.radius_mm is None else row.radius_mm
    return forming.RollPass.from_dict(
        _process(row), measured_radius_mm=radius, verdict=verdict, result=row.result
    )


def _process(row: Inspection) -> dict[str, Any]:
    """The forming pass an inspection was started with (the passes listed all have one).

    Raises
    ------
    ValueError
        The inspection was started without a process.
    """
    if row.process is None:
        raise ValueError(f"inspection {row.id}: no forming process recorded")
    return row.process


def plate_passes(*, session: Session, plate_id: str) -> list[Inspection]:
    """The plate's done inspections with a process, oldest first."""
    return list(
        session.scalars(
            select(Inspection)
            .where(
                Inspection.plate_id == plate_id,
                Inspection.status == JobStatus.DONE,
                Inspection.process.is_not(None),
            )
            .order_by(Inspection.id)
        )
    )


def plate_record(*, session: Session, plate_id: str) -> forming.PlateRecord:
    """The forming model's record of a plate: current target and passes.

    Raises
    ------
    ConflictError
        See :func:`forming_target`.
    """
    target = forming_target(current_target(session=session, plate_id=plate_id), plate_id)
    passes = tuple(roll_pass(r) for r in plate_passes(session=session, plate_id=plate_id))
    return forming.PlateRecord(plate_id, target, passes)


def history(
    *, session: Session, exclude: str, limit: int = MAX_HISTORY_PLATES
) -> list[forming.PlateRecord]:
    """Other plates with roll-bending passes, oldest first: the ``limit`` most recently rolled.

    Plates whose current target is not a cylinder with a material are left out (the model cannot use them).
    """
    latest = (
        select(Inspection.plate_id, func.max(Inspection.id).label("last_id"))
        .where(
            Inspection.status == JobStatus.DONE,
            Inspection.process.is_not(None),
            Inspection.plate_id != exclude,
        )
        .group_by(Inspection.plate_id)
        .order_by(func.max(Inspection.id).desc())
        .limit(limit)
    )
    plate_ids = [plate_id for plate_id, _ in session.execute(latest).all()]
    records = []
    for plate_id in reversed(plate_ids):
        try:
            records.append(plate_record(session=session, plate_id=plate_id))
        except ConflictError:
            continue
    return records


def advise(*, session: Session, plate_id: str, machine_id: str | None) -> forming.Advice:
    """The advice for the plate's next pass (:func:`pipeline.forming.advise`).

    Raises
    ------
    NotFoundError
        No such plate.
    ConflictError
        The plate's target is not a cylinder with its material, or the machine cannot roll it.
    pipeline.formats.InputError
        No machine given for a plate without passes, or an unknown machine (field ``machine_id``).
    """
    if get_plate(session=session, plate_id=plate_id) is None:
        raise NotFoundError(f"plate_id: no plate {plate_id!r}", field="plate_id")
    plate = plate_record(session=session, plate_id=plate_id)
    machines = {row.id: machine_model(row) for row in list_machines(session=session)}
    try:
        return forming.advise(
            plate,
            machines,
            history=history(session=session, exclude=plate_id),
            machine_id=machine_id,
        )
    except forming.FormingError as err:
        raise ConflictError(f"plate_id: {err}", field="plate_id") from None


# ------------------------------------------------------------------ export


#: Columns of the forming history export, in order.
HISTORY_COLUMNS = (
    "inspection_id",
    "created_at",
    "plate_id",
    "machine_id",
    "grade",
    "thickness_mm",
    "top_roll_displacement_mm",
    "measured_radius_mm",
    "target_radius_mm",
    "verdict",
    "flipped",
)


def export_row(row: Inspection) -> tuple[Any, ...]:
    """One pass of the forming history export, :data:`HISTORY_COLUMNS` in order."""
    material = target_material(row.target) or {}
    process = _process(row)
    return (
        row.id,
        row.created_at.isoformat(),
        row.plate_id,
        process["machine_id"],
        material.get("grade"),
        material.get("thickness_mm"),
        process["top_roll_displacement_mm"],
        row.radius_mm,
        row.target_radius_mm,
        row.verdict,
        bool(process.get("flipped", False)),
    )


def exported_passes(*, session: Session) -> list[Inspection]:
    """Every done inspection with a process, oldest first."""
    return list(
        session.scalars(
            select(Inspection)
            .where(Inspection.status == JobStatus.DONE, Inspection.process.is_not(None))
            .order_by(Inspection.id)
        )
    )
