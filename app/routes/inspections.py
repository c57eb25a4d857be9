"""Inspections: start one (uploaded bundle, simulated cell, or the cell's cameras), follow it, fetch its artifacts."""

from __future__ import annotations

import csv
import io
import mimetypes
from datetime import datetime
from typing import Annotated, Any

from fastapi import APIRouter, File, Form, Query, Request, UploadFile, status
from fastapi.responses import FileResponse, JSONResponse, Response
from sqlalchemy.orm import Session

from app.deps import JobsDep, SessionDep, SettingsDep, StorageDep, WriterDep
from app.errors import ApiError
from app.limits import Limits
from app.models import JobStatus
from app.routes.common import (
    IdempotencyKeyHeader,
    InspectionIdPath,
    OffsetQuery,
    PlateIdPath,
    csv_cell,
    inspection_location,
    inspection_out,
    inspection_summary,
    write_request,
)
from app.schemas import (
    AcquireInspectionIn,
    ErrorOut,
    InspectionCreated,
    InspectionOut,
    InspectionSummary,
    Page,
    SimulatedInspectionIn,
    Status,
)
from app.services import inspections as svc
from app.services import plates as plates_svc
from app.services import submissions
from app.services.cell import CELL_SETTING
from app.services.reports import inspection_report

router = APIRouter(tags=["inspections"])

ERRORS: dict[int | str, dict[str, Any]] = {
    401: {"model": ErrorOut},
    413: {"model": ErrorOut},
    422: {"model": ErrorOut},
    429: {
        "model": ErrorOut,
        "description": "the queue is full (per plate or in all); see the Retry-After header",
    },
}


CaptureUpload = Annotated[
    list[UploadFile],
    File(
        description="the capture bundle (plate-capture/1) as a .zip; a plate longer than the view: "
        "one part per conveyor station (each a bundle with its station), or one .zip of station "
        "folders (station_00/, station_01/, ...)"
    ),
]
TargetUpload = Annotated[
    UploadFile | None,
    File(description="plate-target/1 JSON; optional if the plate has a target"),
]
ProcessForm = Annotated[
    str | None,
    Form(
        description='the forming pass that produced the shape, JSON: {"method": "roll-bending", '
        '"machine_id": "R3-01", "top_roll_displacement_mm": 97.0}'
    ),
]
OperatorForm = Annotated[
    str | None,
    Form(description="who starts the inspection (printed on the signed report), 1-80 characters"),
]


@router.post(
    "/plates/{plate_id}/inspections",
    status_code=status.HTTP_202_ACCEPTED,
    response_model=InspectionCreated,
    responses=ERRORS,
    summary="Inspect an uploaded capture bundle",
)
def create_inspection(
    request: Request,
    plate_id: PlateIdPath,
    capture: CaptureUpload,
    session: SessionDep,
    storage: StorageDep,
    jobs: JobsDep,
    writer: WriterDep,
    settings: SettingsDep,
    idempotency_key: IdempotencyKeyHeader = None,
    target: TargetUpload = None,
    process: ProcessForm = None,
    operator: OperatorForm = None,
) -> JSONResponse:
    """Check the bundle (and target), store them and queue the inspection: 202 ``{"id", "status"}``.

    A plate measured at conveyor stations: one ``capture`` part per station, or one zip of station
    folders; the set is checked as ``plate-inspect inspect`` checks it (a ``station`` in every
    bundle, one ``plate_id``, indices 0 .. n-1 without a duplicate; 422 naming the part or folder
    and the field) and the stations are measured as one plate.

    The bundle is checked from capture.json and the image headers (no image is decoded here;
    the job decodes them and fails with the reason if a pixel is bad). A bad bundle or target,
    or one over the request limits (image pixels, lights), is refused with 422 naming the file
    and field; a full queue with 429 and ``Retry-After``. Nothing is stored then. ``process`` (JSON)
    is stored with the inspection; a bad one, or one naming an unknown machine, is refused with 422
    naming ``process`` or its field (``process.machine_id``).
    """
    return submissions.submit_uploaded_inspection(
        write_request(request, writer, idempotency_key),
        session=session,
        storage=storage,
        jobs=jobs,
        limits=Limits.from_settings(settings),
        plate_id=plate_id,
        capture=capture,
        target=target,
        process=process,
        operator=operator,
        location=inspection_location,
    )


@router.post(
    "/plates/{plate_id}/inspections/simulated",
    status_code=status.HTTP_202_ACCEPTED,
    response_model=InspectionCreated,
    responses=ERRORS,
    summary="Inspect a plate rendered by the simulator (the demo cell)",
)
def create_simulated_inspection(
    request: Request,
    plate_id: PlateIdPath,
    body: SimulatedInspectionIn,
    session: SessionDep,
    storage: StorageDep,
    jobs: JobsDep,
    writer: WriterDep,
    settings: SettingsDep,
    idempotency_key: IdempotencyKeyHeader = None,
) -> JSONResponse:
    """Queue a job that renders a capture of the described plate, then inspects it.

    Over the request limits (lights, simulated pixels): 422; a full queue: 429 and ``Retry-After``.
    """
    return submissions.submit_simulated_inspection(
        write_request(request, writer, idempotency_key),
        session=session,
        storage=storage,
        jobs=jobs,
        limits=Limits.from_settings(settings),
        plate_id=plate_id,
        simulation=body.model_dump(mode="json", exclude={"operator"}),
        operator=body.operator,
        location=inspection_location,
    )


@router.post(
    "/plates/{plate_id}/inspections/acquire",
    status_code=status.HTTP_202_ACCEPTED,
    response_model=InspectionCreated,
    responses={
        **ERRORS,
        409: {
            "model": ErrorOut,
            "description": f"no usable cell on this server ({CELL_SETTING} unset, or its file refused: named), "
            "or the first request with this Idempotency-Key is still in progress",
        },
    },
    summary="Photograph the plate with the cell's cameras and lights, then inspect it",
)
def acquire_inspection(
    request: Request,
    plate_id: PlateIdPath,
    session: SessionDep,
    storage: StorageDep,
    jobs: JobsDep,
    writer: WriterDep,
    settings: SettingsDep,
    body: AcquireInspectionIn | None = None,
    idempotency_key: IdempotencyKeyHeader = None,
) -> JSONResponse:
    """Queue a job that photographs the plate in the cell (``PLATE_INSPECT_CELL_CONFIG``), then inspects it.

    The job's stages: ``capture`` (progress per image taken), then the pipeline's. A device that
    fails ends the job ``failed`` with the device and the step. The body is optional: ``target``
    (default: the plate's current target; in demo mode, the demo cell's for a plate without one)
    and ``process`` (the forming pass, as for an upload). Without a usable cell: 409 naming the
    setting or the file and field; a bad target or process: 422; a full queue: 429 and
    ``Retry-After``.
    """
    return submissions.submit_acquired_inspection(
        write_request(request, writer, idempotency_key),
        session=session,
        storage=storage,
        jobs=jobs,
        settings=settings,
        plate_id=plate_id,
        body=body or AcquireInspectionIn(),
        location=inspection_location,
    )


@router.get(
    "/plates/{plate_id}/inspections",
    response_model=Page[InspectionSummary],
    responses={404: {"model": ErrorOut}},
    summary="A plate's inspections, newest first",
)
def list_plate_inspections(
    plate_id: PlateIdPath,
    session: SessionDep,
    limit: Annotated[int, Query(ge=1, le=200)] = 20,
    offset: OffsetQuery = 0,
) -> Page[InspectionSummary]:
    """The plate's inspections (404 for a plate the server does not know, as ``GET /plates/{id}``)."""
    _known_plate(session, plate_id)
    items, total = svc.list_inspections(
        session=session, plate_id=plate_id, limit=limit, offset=offset
    )
    return Page[InspectionSummary](
        items=[inspection_summary(r) for r in items], total=total, limit=limit, offset=offset
    )


#: Columns of a plate's inspections.csv, in order.
PLATE_CSV_COLUMNS = (
    "inspection_id",
    "created_at",
    "finished_at",
    "status",
    "verdict",
    "source",
    "operator",
    "radius_mm",
    "target_radius_mm",
    "radius_error_pct",
    "rms_mm",
    "p95_mm",
    "max_abs_mm",
    "within_tolerance_pct",
    "tolerance_mm",
    "process_method",
    "machine_id",
    "top_roll_displacement_mm",
    "error",
)


@router.get(
    "/plates/{plate_id}/inspections.csv",
    response_class=Response,
    responses={
        200: {"content": {"text/csv": {}}, "description": "one row per inspection, oldest first"},
        404: {"model": ErrorOut},
    },
    summary="A plate's inspections as CSV, for a spreadsheet",
)
def plate_inspections_csv(plate_id: PlateIdPath, session: SessionDep) -> Response:
    """Columns: see ``PLATE_CSV_COLUMNS`` (times in UTC with their offset, lengths in mm)."""
    _known_plate(session, plate_id)
    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow(PLATE_CSV_COLUMNS)
    for row in svc.plate_history(session=session, plate_id=plate_id):
        process = row.process or {}
        values = [getattr(row, name, None) for name in PLATE_CSV_COLUMNS[3:15]]
        writer.writerow(
            [
                csv_cell(v)
                for v in (
                    row.id,
                    _iso(row.created_at),
                    _iso(row.finished_at),
                    *values,
                    process.get("method"),
                    process.get("machine_id"),
                    process.get("top_roll_displacement_mm"),
                    row.error,
                )
            ]
        )
    return Response(
        out.getvalue(),
        media_type="text/csv; charset=utf-8",
        headers={"Content-Disposition": f'attachment; filename="{plate_id}-inspections.csv"'},
    )


def _known_plate(session: Session, plate_id: str) -> None:
    if plates_svc.get_plate(session=session, plate_id=plate_id) is None:
        raise ApiError(404, f"plate_id: no plate {plate_id!r}", field="plate_id")


def _iso(when: datetime | None) -> str | None:
    return None if when is None else when.isoformat(timespec="seconds")


@router.get(
    "/inspections", response_model=Page[InspectionSummary], summary="All inspections, newest first"
)
def list_inspections(
    session: SessionDep,
    status_: Annotated[
        list[Status] | None,
        Query(alias="status", description="only these statuses (repeat the parameter)"),
    ] = None,
    limit: Annotated[int, Query(ge=1, le=200)] = 20,
    offset: OffsetQuery = 0,
) -> Page[InspectionSummary]:
    items, total = svc.list_inspections(
        session=session, statuses=tuple(status_) if status_ else None, limit=limit, offset=offset
    )
    return Page[InspectionSummary](
        items=[inspection_summary(r) for r in items], total=total, limit=limit, offset=offset
    )


@router.get(
    "/inspections/{inspection_id}",
    response_model=InspectionOut,
    responses={404: {"model": ErrorOut}},
)
def get_inspection(
    inspection_id: InspectionIdPath, session: SessionDep, storage: StorageDep
) -> InspectionOut:
    """Job state (status, progress 0..1, stage), the plate-result/1 object once done, or the error."""
    row = svc.get_inspection(session=session, inspection_id=inspection_id)
    if row is None:
        raise ApiError(404, f"inspection_id: no inspection {inspection_id}", field="inspection_id")
    return inspection_out(row, storage=storage)


@router.get(
    "/inspections/{inspection_id}/report.pdf",
    response_class=Response,
    responses={
        200: {"content": {"application/pdf": {}}, "description": "the report, A4"},
        404: {"model": ErrorOut},
        409: {"model": ErrorOut},
    },
)
def get_report(
    inspection_id: InspectionIdPath,
    session: SessionDep,
    storage: StorageDep,
    settings: SettingsDep,
) -> Response:
    """The inspection report to sign (A4 PDF): a header on every page (yard, hull, block, plate,
    drawing and revision, report number, cell, camera serials, calibration, operator, times, page X
    of Y); verdict, warnings and the decision rule; target and alignment; radius, surface, defects
    and templates judged with tolerance and uncertainty; statistics and histogram; the deviation map
    with its colour bar and callouts; approval blocks. Only a done inspection has one (409 otherwise)."""
    row = svc.get_inspection(session=session, inspection_id=inspection_id)
    if row is None:
        raise ApiError(404, f"inspection_id: no inspection {inspection_id}", field="inspection_id")
    if row.status != JobStatus.DONE:
        raise ApiError(
            409,
            f"inspection_id: inspection {inspection_id} is {row.status}; only a done inspection "
            "has a report",
            field="inspection_id",
        )
    document = inspection_out(row, storage=storage).model_dump(mode="json")
    pdf = inspection_report(
        session=session, storage=storage, row=row, document=document, yard=settings.yard
    )
    name = f"inspection-{row.plate_id}-{row.id}.pdf"
    return Response(
        pdf,
        media_type="application/pdf",
        headers={"Content-Disposition": f'inline; filename="{name}"'},
    )


@router.get(
    "/inspections/{inspection_id}/artifacts/{name}",
    response_class=FileResponse,
    responses={404: {"model": ErrorOut}, 422: {"model": ErrorOut}},
)
def get_artifact(
    inspection_id: InspectionIdPath, name: str, session: SessionDep, storage: StorageDep
) -> FileResponse:
    """One artifact file of an inspection (result.json, surface.ply, deviation.png, ...)."""
    if svc.get_inspection(session=session, inspection_id=inspection_id) is None:
        raise ApiError(404, f"inspection_id: no inspection {inspection_id}", field="inspection_id")
    try:
        path = storage.artifact_path(inspection_id, name)
    except ValueError as err:
        raise ApiError(422, str(err), field="name") from None
    if path is None:
        raise ApiError(
            404, f"name: inspection {inspection_id} has no artifact {name!r}", field="name"
        )
    media_type = mimetypes.guess_type(name)[0] or "application/octet-stream"
    return FileResponse(
        path, media_type=media_type, filename=name, content_disposition_type="inline"
    )
