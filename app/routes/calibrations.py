"""Calibrations of the camera pair: upload a new one, read the current one."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, File, Path, Request, UploadFile, status
from fastapi.responses import JSONResponse

from app.deps import SessionDep, SettingsDep, StorageDep, WriterDep
from app.errors import ApiError
from app.limits import Limits
from app.models import Calibration
from app.routes.common import (
    API_PREFIX,
    MAX_ROW_ID,
    IdempotencyKeyHeader,
    write_request,
)
from app.schemas import CalibrationOut, ErrorOut
from app.services import calibrations as svc
from app.services import submissions

router = APIRouter(tags=["calibrations"])


def calibration_out(row: Calibration) -> CalibrationOut:
    return CalibrationOut(
        id=row.id,
        image_size=(row.image_width, row.image_height),
        rms_px=row.rms_px,
        document=row.document,
        created_at=row.created_at,
    )


@router.post(
    "/calibrations",
    status_code=status.HTTP_201_CREATED,
    response_model=CalibrationOut,
    responses={401: {"model": ErrorOut}, 413: {"model": ErrorOut}, 422: {"model": ErrorOut}},
    summary="Upload a stereo calibration; it becomes the current one",
)
def upload_calibration(
    request: Request,
    calibration: Annotated[UploadFile, File(description="a stereo-calibration/1 JSON file")],
    session: SessionDep,
    storage: StorageDep,
    writer: WriterDep,
    settings: SettingsDep,
    idempotency_key: IdempotencyKeyHeader = None,
) -> JSONResponse:
    """Store a ``stereo-calibration/1`` as the cell's current one.

    A bad file, or an ``image_size`` over the image pixel limit, is refused with 422 naming the field.
    """
    return submissions.submit_calibration(
        write_request(request, writer, idempotency_key),
        session=session,
        storage=storage,
        limits=Limits.from_settings(settings),
        upload=calibration,
        body_of=lambda row: calibration_out(row).model_dump(mode="json"),
        location=lambda body: f"{API_PREFIX}/calibrations/{body['id']}",
    )


@router.get(
    "/calibrations/current", response_model=CalibrationOut, responses={404: {"model": ErrorOut}}
)
def current_calibration(session: SessionDep) -> CalibrationOut:
    row = svc.current_calibration(session=session)
    if row is None:
        raise ApiError(404, "calibration: no calibration uploaded yet", field=None)
    return calibration_out(row)


@router.get(
    "/calibrations/{calibration_id}",
    response_model=CalibrationOut,
    responses={404: {"model": ErrorOut}},
    summary="One stereo calibration (where an upload's Location points)",
)
def get_calibration(
    calibration_id: Annotated[int, Path(ge=1, le=MAX_ROW_ID, description="the calibration's id")],
    session: SessionDep,
) -> CalibrationOut:
    row = svc.get_calibration(session=session, calibration_id=calibration_id)
    if row is None:
        raise ApiError(
            404, f"calibration_id: no calibration {calibration_id}", field="calibration_id"
        )
    return calibration_out(row)


@router.get(
    "/calibrations", response_model=list[CalibrationOut], summary="Calibrations, newest first"
)
def list_calibrations(session: SessionDep) -> list[CalibrationOut]:
    return [calibration_out(r) for r in svc.list_calibrations(session=session)]
