"""Plates: the list with each plate's latest verdict, one plate, its target (read and replace)."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Annotated

from fastapi import APIRouter, Query, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import JSONResponse
from starlette.datastructures import FormData, UploadFile

from app.deps import SessionDep, StorageDep, WriterDep
from app.errors import ApiError
from app.routes.common import (
    IdempotencyKeyHeader,
    OffsetQuery,
    PlateIdPath,
    plate_out,
    target_out,
    write_request,
)
from app.schemas import ErrorOut, Page, PlateOut, TargetOut
from app.services import plates as svc
from app.services import submissions
from app.services.targets import TARGET_FILE
from app.services.writes import save_upload
from app.storage import ARTIFACT_NAME_PATTERN
from pipeline.io import MESH_SUFFIXES

router = APIRouter(tags=["plates"])


@router.get("/plates", response_model=Page[PlateOut], summary="Plates with their latest verdict")
def list_plates(
    session: SessionDep,
    limit: Annotated[int, Query(ge=1, le=500)] = 50,
    offset: OffsetQuery = 0,
) -> Page[PlateOut]:
    views, total = svc.list_plates(session=session, limit=limit, offset=offset)
    return Page[PlateOut](
        items=[plate_out(v) for v in views], total=total, limit=limit, offset=offset
    )


@router.get("/plates/{plate_id}", response_model=PlateOut, responses={404: {"model": ErrorOut}})
def get_plate(plate_id: PlateIdPath, session: SessionDep) -> PlateOut:
    view = svc.overview(session=session, plate_id=plate_id)
    if view is None:
        raise ApiError(404, f"plate_id: no plate {plate_id!r}", field="plate_id")
    return plate_out(view)


@router.get(
    "/plates/{plate_id}/target", response_model=TargetOut, responses={404: {"model": ErrorOut}}
)
def get_target(plate_id: PlateIdPath, session: SessionDep) -> TargetOut:
    row = svc.current_target(session=session, plate_id=plate_id)
    if row is None:
        raise ApiError(404, f"plate_id: plate {plate_id!r} has no target", field="plate_id")
    return target_out(row)


@router.put(
    "/plates/{plate_id}/target",
    response_model=TargetOut,
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
                    "schema": {"type": "object", "description": "a plate-target/1 document"}
                },
                "multipart/form-data": {
                    "schema": {
                        "type": "object",
                        "required": ["mesh"],
                        "properties": {
                            "mesh": {
                                "type": "string",
                                "format": "binary",
                                "description": "STL, PLY or OBJ, mm",
                            },
                            "target": {
                                "type": "string",
                                "format": "binary",
                                "description": "plate-target/1 JSON with shape mesh (file = the mesh's name)",
                            },
                            "size_x_mm": {"type": "number"},
                            "size_y_mm": {"type": "number"},
                            "tolerance_mm": {"type": "number"},
                        },
                    }
                },
            },
        }
    },
    summary="Set the plate's target: a plate-target/1 JSON body, or a mesh upload",
)
async def put_target(
    request: Request,
    plate_id: PlateIdPath,
    session: SessionDep,
    storage: StorageDep,
    writer: WriterDep,
    idempotency_key: IdempotencyKeyHeader = None,
) -> JSONResponse:
    """Replace the plate's target (the old one stays with the inspections that used it).

    JSON body: a ``plate-target/1`` document (plane, cylinder or sphere). Multipart: ``mesh``
    (STL/PLY/OBJ in mm) and either ``target`` (a plate-target/1 JSON whose ``shape.file`` names
    the mesh) or the fields ``size_x_mm``, ``size_y_mm``, ``tolerance_mm``.
    """
    content_type = request.headers.get("content-type", "").split(";")[0].strip().lower()
    with storage.staging() as staged:
        staging = staged.folder
        if content_type == "application/json":
            (staging / TARGET_FILE).write_bytes(await request.body())
        elif content_type == "multipart/form-data":
            await _stage_mesh_form(await request.form(), staging)
        else:
            raise ApiError(
                415,
                f"Content-Type: expected application/json or multipart/form-data, got {content_type or 'none'!r}",
                field="Content-Type",
            )

        return await run_in_threadpool(
            submissions.submit_target,
            write_request(request, writer, idempotency_key),
            staged,
            session=session,
            storage=storage,
            plate_id=plate_id,
            body_of=lambda row: target_out(row).model_dump(mode="json"),
        )


async def _stage_mesh_form(form: FormData, staging: Path) -> None:
    mesh = form.get("mesh")
    if not isinstance(mesh, UploadFile):
        raise ApiError(422, "mesh: expected a mesh file upload (STL, PLY or OBJ)", field="mesh")
    target_part = form.get("target")
    if target_part is not None:
        raw = (
            await target_part.read()
            if isinstance(target_part, UploadFile)
            else str(target_part).encode()
        )
        try:
            document = json.loads(raw)
            mesh_name = document["shape"]["file"]
        except (
            ValueError,
            KeyError,
            TypeError,
            RecursionError,
        ):  # ValueError: also over-long integers
            raise ApiError(
                422,
                "target: expected a plate-target/1 JSON with shape.file naming the mesh",
                field="target",
            ) from None
        if (
            not isinstance(mesh_name, str)
            or not ARTIFACT_NAME_PATTERN.match(mesh_name)
            or ".." in mesh_name
        ):
            raise ApiError(
                422,
                f"target: shape.file: expected a plain file name, got {mesh_name!r}",
                field="target",
            )
        (staging / TARGET_FILE).write_bytes(raw)
    else:
        suffix = (
            "." + (mesh.filename or "").rsplit(".", 1)[-1].lower()
            if "." in (mesh.filename or "")
            else ""
        )
        if suffix not in MESH_SUFFIXES:
            raise ApiError(
                422,
                f"mesh: expected a .stl, .ply or .obj file, got {mesh.filename!r}",
                field="mesh",
            )
        mesh_name = "plate" + suffix
        document = {"format": "plate-target/1", "shape": {"type": "mesh", "file": mesh_name}}
        for name in ("size_x_mm", "size_y_mm", "tolerance_mm"):
            value = form.get(name)
            if value is None or isinstance(value, UploadFile):
                raise ApiError(
                    422,
                    f"{name}: expected a number (mm) with the mesh upload, got none",
                    field=name,
                )
            try:
                number = float(value)
            except ValueError:
                raise ApiError(
                    422, f"{name}: expected a number (mm), got {value[:40]!r}", field=name
                ) from None
            if not math.isfinite(number):
                raise ApiError(
                    422, f"{name}: expected a finite number (mm), got {value[:40]!r}", field=name
                )
            document[name] = number
        document["size_mm"] = [document.pop("size_x_mm"), document.pop("size_y_mm")]
        (staging / TARGET_FILE).write_text(json.dumps(document, indent=2), encoding="utf-8")
    save_upload(mesh, staging / mesh_name)
