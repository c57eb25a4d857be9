"""Forming (issue 14): the roll benders, the advice for a plate's next pass, the forming history export."""

from __future__ import annotations

import csv
import io
from typing import Annotated

from fastapi import APIRouter, Path, Query, Request
from fastapi.responses import JSONResponse, Response
from pydantic import AfterValidator

from app.deps import SessionDep, WriterDep
from app.errors import ApiError
from app.models import Machine
from app.routes.common import (
    API_PREFIX,
    IdempotencyKeyHeader,
    PlateIdPath,
    csv_cell,
    write_request,
)
from app.schemas import (
    MACHINE_ID_MAX_LENGTH,
    MACHINE_ID_REGEX,
    AdviceOut,
    ErrorOut,
    MachineIn,
    MachineOut,
)
from app.services import forming as svc
from app.services import submissions
from app.storage import check_plate_id

router = APIRouter(tags=["forming"])


def _machine_id(value: str) -> str:
    try:
        return check_plate_id(value)  # the same characters as a plate id
    except ValueError:
        raise ValueError(
            f"expected 1-{MACHINE_ID_MAX_LENGTH} letters, digits, '.', '_' or '-', starting with a letter "
            f"or digit, without '..', got {value!r}"
        ) from None


MachineIdPath = Annotated[
    str,
    AfterValidator(_machine_id),
    Path(
        max_length=MACHINE_ID_MAX_LENGTH,
        description="the shop's machine id",
        examples=["R3-01"],
        json_schema_extra={"pattern": MACHINE_ID_REGEX},
    ),
]
MachineIdQuery = Annotated[
    str | None,
    AfterValidator(lambda v: v if v is None else _machine_id(v)),
    Query(
        max_length=MACHINE_ID_MAX_LENGTH,
        description="the next pass's machine (default: the latest pass's)",
        json_schema_extra={"pattern": MACHINE_ID_REGEX},
    ),
]


def machine_out(row: Machine) -> MachineOut:
    return MachineOut.model_validate({name: getattr(row, name) for name in MachineOut.model_fields})


@router.put(
    "/machines/{machine_id}",
    response_model=MachineOut,
    responses={
        201: {"model": MachineOut, "description": "The machine was new"},
        401: {"model": ErrorOut},
        422: {"model": ErrorOut},
    },
    summary="Add or replace a roll bender (three-roll pyramid)",
)
def put_machine(
    request: Request,
    machine_id: MachineIdPath,
    body: MachineIn,
    session: SessionDep,
    writer: WriterDep,
    idempotency_key: IdempotencyKeyHeader = None,
) -> JSONResponse:
    """Store the machine's geometry (mm): 201 when new, 200 when replaced. Later advice uses the new geometry."""

    return submissions.submit_machine(
        write_request(request, writer, idempotency_key),
        session=session,
        machine_id=machine_id,
        spec=body.model_dump(),
        body_of=lambda row: machine_out(row).model_dump(mode="json"),
        location=lambda body: f"{API_PREFIX}/machines/{body['id']}",
    )


@router.get("/machines", response_model=list[MachineOut], summary="Every roll bender, by id")
def list_machines(session: SessionDep) -> list[MachineOut]:
    return [machine_out(row) for row in svc.list_machines(session=session)]


@router.get(
    "/machines/{machine_id}", response_model=MachineOut, responses={404: {"model": ErrorOut}}
)
def get_machine(machine_id: MachineIdPath, session: SessionDep) -> MachineOut:
    row = svc.get_machine(session=session, machine_id=machine_id)
    if row is None:
        raise ApiError(404, f"machine_id: no machine {machine_id!r}", field="machine_id")
    return machine_out(row)


@router.get(
    "/plates/{plate_id}/advice",
    response_model=AdviceOut,
    responses={404: {"model": ErrorOut}, 409: {"model": ErrorOut}, 422: {"model": ErrorOut}},
    summary="What to do with the plate next: bend (with the top-roll setting), done or reverse",
)
def get_advice(
    plate_id: PlateIdPath, session: SessionDep, machine_id: MachineIdQuery = None
) -> AdviceOut:
    """Roll-bending advice from the plate's current target (a cylinder with its ``material``), its done
    inspections with a ``process`` and the other plates' (docs/forming.md).

    409 when the plate's target is missing, not a cylinder, has no material, or is tighter than the
    machine can roll; 422 for an unknown machine, or none given for a plate without passes.
    """
    advice = svc.advise(session=session, plate_id=plate_id, machine_id=machine_id)
    return AdviceOut.model_validate(advice.to_dict())


@router.get(
    "/forming-history.csv",
    response_class=Response,
    responses={
        200: {
            "content": {"text/csv": {}},
            "description": "one row per inspected pass, oldest first",
        }
    },
    summary="The forming history: one row per inspected roll-bending pass",
)
def forming_history_csv(session: SessionDep) -> Response:
    """Columns: inspection_id, created_at, plate_id, machine_id, grade, thickness_mm,
    top_roll_displacement_mm, measured_radius_mm, target_radius_mm, verdict (grade and thickness of the
    target the inspection was judged against; empty when it had no material)."""
    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow(svc.HISTORY_COLUMNS)
    for row in svc.exported_passes(session=session):
        writer.writerow([csv_cell(v) for v in svc.export_row(row)])
    return Response(
        out.getvalue(),
        media_type="text/csv; charset=utf-8",
        headers={"Content-Disposition": 'attachment; filename="forming-history.csv"'},
    )
