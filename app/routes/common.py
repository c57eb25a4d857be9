"""Helpers shared by the routers: path and query parameters, a write's request, response builders."""

from __future__ import annotations

import hashlib
import json
import logging
import re
from typing import Annotated, Any

from fastapi import Header, Path, Query, Request
from pydantic import AfterValidator

from app.deps import Writer
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
from app.services.writes import WriteRequest
from app.storage import Storage, check_plate_id

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


def write_request(request: Request, writer: Writer, key: str | None) -> WriteRequest:
    """What the write services need of a request: its route, the writer's token, its
    ``Idempotency-Key`` and its fingerprint (:func:`request_fingerprint`)."""
    return WriteRequest(
        scope=f"{request.method} {request.url.path}",
        token_hash=writer.token_hash,
        key=key,
        request_sha256=getattr(request.state, "request_sha256", None),
    )


def inspection_location(body: dict[str, Any]) -> str:
    """Where a queued inspection is followed."""
    return f"{API_PREFIX}/inspections/{body['id']}"


# ------------------------------------------------------------------ response builders


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
