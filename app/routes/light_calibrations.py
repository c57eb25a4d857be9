"""Light calibrations of the cell: upload a new one (it becomes current), read the current one, the list."""

from __future__ import annotations

from pathlib import Path

from fastapi import APIRouter, Request, status
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import JSONResponse
from starlette.datastructures import UploadFile

from app.deps import SessionDep, SettingsDep, StorageDep, WriterDep
from app.errors import ApiError
from app.limits import Limits
from app.models import LightCalibration
from app.routes.common import (
    API_PREFIX,
    IdempotencyKeyHeader,
    LightCalibrationIdPath,
    write_request,
)
from app.schemas import ErrorOut, LightCalibrationOut
from app.services import light_calibrations as svc
from app.services import submissions
from app.services.light_calibrations import LIGHT_CALIBRATION_FILE

router = APIRouter(tags=["light calibrations"])

#: The multipart field of an uploaded light calibration (as for the stereo calibration).
UPLOAD_FIELD = "calibration"


def light_calibration_out(row: LightCalibration) -> LightCalibrationOut:
    return LightCalibrationOut.model_validate(
        {name: getattr(row, name) for name in LightCalibrationOut.model_fields}
    )


@router.post(
    "/light-calibrations",
    status_code=status.HTTP_201_CREATED,
    response_model=LightCalibrationOut,
    responses={
        401: {"model": ErrorOut},
        413: {"model": ErrorOut},
        415: {"model": ErrorOut},
        422: {"model": ErrorOut},
    },
    openapi_extra={
        "requestBody": {
            "required": True,
            "content": {
                "application/json": {
                    "schema": {"type": "object", "description": "a light-calibration/1 document"}
                },
                "multipart/form-data": {
                    "schema": {
                        "type": "object",
                        "required": [UPLOAD_FIELD],
                        "properties": {
                            UPLOAD_FIELD: {
                                "type": "string",
                                "format": "binary",
                                "description": "a light-calibration/1 JSON file",
                            },
                        },
                    }
                },
            },
        }
    },
    summary="Upload a light calibration (JSON body or multipart 'calibration'); it becomes the current one",
)
async def upload_light_calibration(
    request: Request,
    session: SessionDep,
    storage: StorageDep,
    writer: WriterDep,
    settings: SettingsDep,
    idempotency_key: IdempotencyKeyHeader = None,
) -> JSONResponse:
    """Store a ``light-calibration/1`` (from ``plate-inspect calibrate-lights``) as the cell's current one.

    From now on, uploaded captures whose lights are only nominal directions are inspected with
    these lights (the inspection records which calibration; the result's ``warnings`` say it
    was applied). Captures that give point lights keep their own.
    """
    content_type = request.headers.get("content-type", "").split(";")[0].strip().lower()
    with storage.staging() as staged:
        file_name = await _stage_upload(
            request, content_type, staged.folder / LIGHT_CALIBRATION_FILE
        )

        return await run_in_threadpool(
            submissions.submit_light_calibration,
            write_request(request, writer, idempotency_key),
            staged,
            session=session,
            storage=storage,
            limits=Limits.from_settings(settings),
            file_name=file_name,
            upload_field=UPLOAD_FIELD if file_name is not None else None,
            body_of=lambda row: light_calibration_out(row).model_dump(mode="json"),
            location=lambda body: f"{API_PREFIX}/light-calibrations/{body['id']}",
        )


async def _stage_upload(request: Request, content_type: str, path: Path) -> str | None:
    """Write the request's light-calibration/1 (a JSON body or a multipart upload) to ``path``.

    Returns the uploaded file's name (None for a JSON body); 422 without the file part, 415 for
    another Content-Type.
    """
    if content_type == "application/json":
        path.write_bytes(await request.body())
        return None
    if content_type == "multipart/form-data":
        upload = (await request.form()).get(UPLOAD_FIELD)
        if not isinstance(upload, UploadFile):
            raise ApiError(
                422,
                f"{UPLOAD_FIELD}: expected a light-calibration/1 JSON file upload",
                field=UPLOAD_FIELD,
            )
        path.write_bytes(await upload.read())
        return svc.upload_name(upload.filename)
    raise ApiError(
        415,
        f"Content-Type: expected application/json or multipart/form-data, got {content_type or 'none'!r}",
        field="Content-Type",
    )


@router.get(
    "/light-calibrations/current",
    response_model=LightCalibrationOut,
    responses={404: {"model": ErrorOut}},
)
def current_light_calibration(session: SessionDep) -> LightCalibrationOut:
    row = svc.current_light_calibration(session=session)
    if row is None:
        raise ApiError(404, "light calibration: no light calibration uploaded yet", field=None)
    return light_calibration_out(row)


@router.get(
    "/light-calibrations/{light_calibration_id}",
    response_model=LightCalibrationOut,
    responses={404: {"model": ErrorOut}},
    summary="One light calibration (e.g. the one an inspection was run with)",
)
def get_light_calibration(
    light_calibration_id: LightCalibrationIdPath, session: SessionDep
) -> LightCalibrationOut:
    row = svc.get_light_calibration(session=session, light_calibration_id=light_calibration_id)
    if row is None:
        raise ApiError(
            404,
            f"light_calibration_id: no light calibration {light_calibration_id}",
            field="light_calibration_id",
        )
    return light_calibration_out(row)


@router.get(
    "/light-calibrations",
    response_model=list[LightCalibrationOut],
    summary="Light calibrations, newest first",
)
def list_light_calibrations(session: SessionDep) -> list[LightCalibrationOut]:
    return [light_calibration_out(r) for r in svc.list_light_calibrations(session=session)]
