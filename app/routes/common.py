"""Helpers shared by the routers: path and query parameters, idempotent writes, response builders."""

from __future__ import annotations

import hashlib
import json
import logging
import re
import shutil
from collections.abc import Callable
from pathlib import Path as FilePath
from typing import Annotated, Any

from fastapi import Header, Path, Query, Request
from fastapi.responses import JSONResponse
from pydantic import AfterValidator
from sqlalchemy.orm import Session
from starlette.datastructures import UploadFile

from app.deps import Writer
from app.errors import error_body, known_error, relabel_input_error
from app.limits.queue import QueueFullError
from app.models import FINISHED, Inspection, JobStatus, Target
from app.schemas import (
    PLATE_ID_MAX_LENGTH,
    PLATE_ID_REGEX,
    DefectOut,
    InspectionOut,
    InspectionSummary,
    PlateOut,
    TargetOut,
)
from app.services import idempotency
from app.services.inspections import artifact_names
from app.services.plates import PlateOverview
from app.storage import Storage, check_plate_id
from pipeline.formats import InputError

log = logging.getLogger(__name__)

API_PREFIX = "/api/v1"

#: Largest row id (and list offset) the database holds: SQLite INTEGER is a signed 64-bit integer.
MAX_ROW_ID = 2**63 - 1


def _plate_id(value: str) -> str:
    try:
        return check_plate_id(value)
    except ValueError:
        raise ValueError(
            f"expected 1-{PLATE_ID_MAX_LENGTH} letters, digits, '.', '_' or '-', starting with a letter or digit, "
            f"without '..' (plate ids name folders), got {value!r}"
        ) from None


PlateIdPath = Annotated[
    str,
    AfterValidator(_plate_id),
    Path(
        max_length=PLATE_ID_MAX_LENGTH,
        description="the yard's plate id: letters, digits, '.', '_', '-', starting with a letter or digit, no '..'",
        examples=["H1234-P07"],
        json_schema_extra={"pattern": PLATE_ID_REGEX},
    ),
]
InspectionIdPath = Annotated[int, Path(ge=1, le=MAX_ROW_ID, description="the inspection's id")]
LightCalibrationIdPath = Annotated[
    int, Path(ge=1, le=MAX_ROW_ID, description="the light calibration's id")
]
OffsetQuery = Annotated[int, Query(ge=0, le=MAX_ROW_ID, description="items to skip (newest first)")]
IdempotencyKeyHeader = Annotated[
    str | None,
    Header(
        alias="Idempotency-Key",
        description="a retry with the same key returns the first answer",
        max_length=255,
    ),
]


async def request_fingerprint(request: Request) -> None:
    """Keep a write's :func:`~app.services.idempotency.fingerprint` in ``request.state`` when it
    carries an ``Idempotency-Key`` (a dependency of every API route; the body is read once and cached).

    A multipart body counts as its fields, each by name and content (not its boundary, part order
    or file names); a JSON body by its content (not its key order or spacing).
    """
    if request.method not in ("POST", "PUT", "PATCH") or "idempotency-key" not in request.headers:
        return
    content_type = request.headers.get("content-type", "").split(";")[0].strip().lower()
    if content_type == "multipart/form-data":
        fields = [
            (name, await _digest(value)) for name, value in (await request.form()).multi_items()
        ]
    else:
        canonical = idempotency.canonical_json(await request.body())
        fields = [("body", hashlib.sha256(canonical).hexdigest())]
    request.state.request_sha256 = idempotency.fingerprint(fields)


async def _digest(value: Any) -> str:
    """sha256 hex of a form field: its text, or an uploaded file's bytes (read back to its start)."""
    if isinstance(value, str):
        return hashlib.sha256(value.encode()).hexdigest()
    digest = hashlib.sha256()
    await value.seek(0)
    while chunk := await value.read(1 << 20):
        digest.update(chunk)
    await value.seek(0)
    return digest.hexdigest()


#: What a write's work answers: (status code, JSON body, called after the commit (e.g. enqueue) or None).
WorkAnswer = tuple[int, dict[str, Any], Callable[[], None] | None]
#: work() -> :data:`WorkAnswer`
Work = Callable[[], WorkAnswer]


def idempotent_write(
    *,
    request: Request,
    session: Session,
    writer: Writer,
    key: str | None,
    work: Work,
    cleanup: Callable[[], None] = lambda: None,
    upload_field: str | Callable[[InputError], str] | None = None,
    staging: FilePath | None = None,
    location: Callable[[dict[str, Any]], str] | None = None,
) -> JSONResponse:
    """Run a write once per ``Idempotency-Key`` (per route and token) and answer with JSON.

    ``work`` adds rows without committing; this commits them together with the stored answer,
    then calls the after-commit hook. A refused request (4xx) is remembered too, so a retry gets
    the same refusal; a bug (5xx) forgets the key, and so does a full queue
    (:class:`~app.limits.queue.QueueFullError`, answered 429 with ``Retry-After``): a retry may be
    admitted. The same key with another body (:func:`request_fingerprint`) is refused with 422
    naming ``Idempotency-Key``. ``cleanup`` undoes files ``work`` wrote when its rows are not
    committed. File errors name files relative to ``staging`` (the upload's folder);
    ``upload_field`` is the multipart field they are about, or a function of the (relabelled)
    error giving it when the upload has several files. ``location`` gives a 201 or 202 answer's
    ``Location`` header from its body (the resource created or the job queued).
    """
    row_id = None
    if key is not None:
        claimed = _claim(request=request, session=session, writer=writer, key=key)
        if isinstance(claimed, JSONResponse):
            cleanup()
            return _with_location(claimed, location)
        row_id = claimed
    try:
        status, body, after_commit = work()
        if row_id is not None:
            idempotency.record(session=session, row_id=row_id, status_code=status, body=body)
        session.commit()
    except Exception as exc:
        session.rollback()
        cleanup()
        if isinstance(exc, QueueFullError):  # not final: a retry with the same key may be admitted
            _release(session, row_id)
            return JSONResponse(
                error_body(exc.detail, exc.field),
                status_code=429,
                headers={"Retry-After": str(exc.retry_after_s)},
            )
        if isinstance(exc, InputError) and staging is not None:
            exc = relabel_input_error(exc, staging)
        if callable(upload_field):
            upload_field = upload_field(exc) if isinstance(exc, InputError) else None
        known = known_error(exc, upload_field=upload_field)
        if known is None:
            _release(session, row_id)
            raise
        status, body = known
        if row_id is not None:
            idempotency.record(session=session, row_id=row_id, status_code=status, body=body)
            session.commit()
        return JSONResponse(body, status_code=status)
    if after_commit is not None:
        after_commit()
    return _with_location(JSONResponse(body, status_code=status), location)


def _claim(*, request: Request, session: Session, writer: Writer, key: str) -> int | JSONResponse:
    """The id of the key's claim for this request, or the answer when another request made it:
    the first answer replayed, 409 while it runs, 422 when it was sent with another body."""
    sha = getattr(request.state, "request_sha256", None)
    try:
        row, claimed = idempotency.claim(
            session=session,
            key=key,
            scope=f"{request.method} {request.url.path}",
            token_hash=writer.token_hash,
            request_sha256=sha,
        )
    except ValueError as err:
        return JSONResponse(error_body(str(err), "Idempotency-Key"), status_code=422)
    if claimed:
        return row.id
    if not idempotency.same_request(row, sha):
        detail = (
            f"Idempotency-Key: {key[:40]!r} was already used on this route with another body; "
            "send a new key for a new request (or the same body to get the first answer)"
        )
        return JSONResponse(error_body(detail, "Idempotency-Key"), status_code=422)
    answer = idempotency.stored_answer(row)
    if answer is not None:
        status_code, body = answer
        return JSONResponse(body, status_code=status_code, headers={"Idempotent-Replayed": "true"})
    return JSONResponse(
        error_body(
            "Idempotency-Key: the first request with this key is still in progress, retry later",
            "Idempotency-Key",
        ),
        status_code=409,
    )


def _release(session: Session, row_id: int | None) -> None:
    if row_id is not None:
        idempotency.release(session=session, row_id=row_id)
        session.commit()


def _with_location(
    response: JSONResponse, location: Callable[[dict[str, Any]], str] | None
) -> JSONResponse:
    """The answer with ``Location`` when it created something (201) or queued a job (202)."""
    if location is not None and response.status_code in (201, 202):
        response.headers["Location"] = location(json.loads(bytes(response.body)))
    return response


def inspection_location(body: dict[str, Any]) -> str:
    """Where a queued inspection is followed."""
    return f"{API_PREFIX}/inspections/{body['id']}"


# ------------------------------------------------------------------ response builders


def save_upload(upload: UploadFile, path: FilePath) -> None:
    """Stream an uploaded file (FastAPI ``UploadFile``) to ``path`` in 1 MiB chunks."""
    with open(path, "wb") as fh:
        shutil.copyfileobj(upload.file, fh, length=1 << 20)


def artifact_url(inspection_id: int, name: str) -> str:
    return f"{API_PREFIX}/inspections/{inspection_id}/artifacts/{name}"


def inspection_out(row: Inspection, *, storage: Storage) -> InspectionOut:
    names = artifact_names(storage=storage, inspection=row) if row.status in FINISHED else []
    return InspectionOut(
        id=row.id,
        plate_id=row.plate_id,
        status=row.status,
        progress=row.progress,
        stage=row.stage,
        result=row.result,
        error=row.error,
        source=row.source,
        verdict=row.verdict,
        process=row.process,
        operator=row.operator,
        light_calibration_id=row.light_calibration_id,
        cell_id=row.cell_id,
        created_at=row.created_at,
        started_at=row.started_at,
        finished_at=row.finished_at,
        artifacts={name: artifact_url(row.id, name) for name in names},
        **defects_and_reasons(storage, row, names),
    )


def defects_and_reasons(
    storage: Storage, row: Inspection, names: list[str]
) -> dict[str, list[Any]]:
    """``defects`` and ``reasons`` of a done inspection, from its details.json."""
    if row.status != JobStatus.DONE or "details.json" not in names:
        return {"defects": [], "reasons": []}
    try:
        details = json.loads((storage.artifacts_dir(row.id) / "details.json").read_text())
    except (OSError, ValueError) as err:
        log.warning("inspection %s: details.json unreadable: %s", row.id, err)
        return {"defects": [], "reasons": []}
    defects = [
        DefectOut(
            id=k,
            centroid_mm=d.get("centroid_mm"),
            centroid_px=d["centroid_px"],
            area_mm2=d["area_mm2"],
            peak_mm=d["peak_deviation_mm"],
            mean_mm=d.get("mean_deviation_mm"),
        )
        for k, d in enumerate(details.get("defects", []), start=1)
    ]
    return {"defects": defects, "reasons": [in_cm2(r) for r in details.get("reasons", [])]}


_AREA_MM2 = re.compile(r"(\d+(?:\.\d+)?) mm\^2")
_REGIONS = re.compile(r"\b1 region\(s\)|(\d+) region\(s\)")


def in_cm2(reason: str) -> str:
    """A reason as today's results word it: areas in cm² (results before issue 26 said mm^2, e.g.
    "1 region(s) ... over 100 mm^2 (largest 13786 mm^2)" -> "1 region ... over 1 cm² (largest
    137.9 cm²)")."""
    reason = _AREA_MM2.sub(
        lambda m: f"{float(m.group(1)) / 100.0:.1f}".removesuffix(".0") + " cm²", reason
    )
    return _REGIONS.sub(lambda m: f"{m.group(1)} regions" if m.group(1) else "1 region", reason)


def inspection_summary(row: Inspection) -> InspectionSummary:
    return InspectionSummary.model_validate(
        {name: getattr(row, name) for name in InspectionSummary.model_fields}
    )


def target_out(row: Target) -> TargetOut:
    return TargetOut.model_validate({name: getattr(row, name) for name in TargetOut.model_fields})


def plate_out(view: PlateOverview) -> PlateOut:
    latest = view.latest_inspection
    return PlateOut(
        id=view.plate.id,
        created_at=view.plate.created_at,
        inspection_count=view.inspection_count,
        latest_verdict=latest.verdict if latest is not None else None,
        latest_inspection=inspection_summary(latest) if latest is not None else None,
        target=target_out(view.target) if view.target is not None else None,
    )


def csv_cell(value: object) -> str:
    """A CSV cell; text a spreadsheet would run as a formula (``=``, ``+``, ``-``, ``@``) is quoted with ``'``."""
    if value is None:
        return ""
    text = str(value)
    return "'" + text if isinstance(value, str) and text[:1] in ("=", "+", "-", "@") else text
