"""The API's writes, one function each: what a route hands its parsed, authorised request to.

Each stages the request's files, creates the rows and answers through
:func:`app.services.writes.staged_write` (one transaction, once per ``Idempotency-Key``, errors
answered as JSON). Checks that belong to the write (a multipart field's JSON, an operator's name)
run inside it, so a refusal is remembered under the key like any other.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from pydantic import TypeAdapter, ValidationError
from sqlalchemy.orm import Session
from starlette.datastructures import UploadFile
from starlette.responses import JSONResponse

from app.errors import relabel_input_error
from app.jobs import JobQueue
from app.limits import Limits
from app.models import Calibration, LightCalibration, Machine, Target
from app.schemas import AcquireInspectionIn, OperatorName, ProcessIn
from app.services import calibrations, forming, light_calibrations
from app.services import inspections as inspection_svc
from app.services.acquisitions import create_acquired_inspection
from app.services.calibrations import CALIBRATION_FILE
from app.services.cell import CellUnavailable, demo_target, load_cell
from app.services.errors import ConflictError, UnprocessableError
from app.services.inspections import CAPTURE_FILE
from app.services.stations import PARTS_DIR, part_names
from app.services.targets import TARGET_FILE, create_target
from app.services.writes import (
    Location,
    UploadField,
    WorkAnswer,
    WriteRequest,
    idempotent_write,
    queued_inspection,
    save_upload,
    staged_write,
    write_staged,
)
from app.settings import Settings
from app.storage import Staged, Storage
from pipeline.formats import InputError


def submit_uploaded_inspection(
    write: WriteRequest,
    *,
    session: Session,
    storage: Storage,
    jobs: JobQueue,
    limits: Limits,
    plate_id: str,
    capture: Sequence[UploadFile],
    target: UploadFile | None,
    process: str | None,
    operator: str | None,
    location: Location,
) -> JSONResponse:
    """Store an uploaded bundle (and target) and queue its inspection: 202 ``{"id", "status"}``.

    ``capture``: the multipart parts ``capture``; one (a bundle, or a zip of a plate's station
    folders) or several (a plate's conveyor stations, one bundle each; :mod:`app.services.stations`).
    ``process`` (JSON) and ``operator`` are the multipart fields as sent; a bad one is refused
    with 422 naming it (:func:`parse_process`, :func:`parse_operator`). A bad bundle is refused
    naming the file (and the part or the zip's folder of a station) as the client sent it
    (``bad.zip: ...``, ``s1.zip:capture.json: ...``).
    """
    sent = part_names([part.filename for part in capture])

    def work(staged: Staged) -> WorkAnswer:
        pass_ = None if process is None else parse_process(process)
        who = None if operator is None else parse_operator(operator)
        _save_capture(capture, staged.folder)
        if target is not None:
            (staged.folder / "target").mkdir()
            save_upload(target, staged.folder / "target" / TARGET_FILE)
        try:
            row = inspection_svc.create_uploaded_inspection(
                session=session,
                storage=storage,
                plate_id=plate_id,
                staging_dir=staged.folder,
                limits=limits,
                process=pass_,
                sent_names=sent,
            )
        except InputError as err:
            raise _named_as_sent(
                relabel_input_error(err, staged.folder), capture[0].filename
            ) from None
        row.operator = who
        return queued_inspection(row, staged, storage=storage, jobs=jobs)

    return staged_write(
        write,
        session=session,
        storage=storage,
        work=work,
        upload_field=_upload_part,
        location=location,
    )


def submit_simulated_inspection(
    write: WriteRequest,
    *,
    session: Session,
    storage: Storage,
    jobs: JobQueue,
    limits: Limits,
    plate_id: str,
    simulation: dict[str, Any],
    operator: str | None,
    location: Location,
) -> JSONResponse:
    """Queue a job that renders a capture of the described plate, then inspects it (202)."""

    def work(staged: Staged) -> WorkAnswer:
        row = inspection_svc.create_simulated_inspection(
            session=session,
            storage=storage,
            plate_id=plate_id,
            simulation=simulation,
            limits=limits,
        )
        row.operator = operator
        return queued_inspection(row, staged, storage=storage, jobs=jobs)

    return staged_write(
        write, session=session, storage=storage, work=work, folder=False, location=location
    )


def submit_acquired_inspection(
    write: WriteRequest,
    *,
    session: Session,
    storage: Storage,
    jobs: JobQueue,
    settings: Settings,
    plate_id: str,
    body: AcquireInspectionIn,
    location: Location,
) -> JSONResponse:
    """Queue a job that photographs the plate in the server's cell, then inspects it (202).

    Raises
    ------
    ConflictError
        No usable cell (its setting unset, or its file refused: named); checked before the
        ``Idempotency-Key`` is claimed, so never remembered under it.
    """
    try:
        cell = load_cell(settings)
    except CellUnavailable as err:
        raise ConflictError(err.detail) from None

    def prepare(staged: Staged) -> None:
        (staged.folder / TARGET_FILE).write_text(json.dumps(body.target), encoding="utf-8")

    def work(staged: Staged) -> WorkAnswer:
        row = create_acquired_inspection(
            session=session,
            storage=storage,
            plate_id=plate_id,
            cell=cell,
            process=None if body.process is None else body.process.model_dump(mode="json"),
            target_dir=staged.dir,
            default_target=demo_target(settings),
            limits=Limits.from_settings(settings),
        )
        row.operator = body.operator
        return queued_inspection(row, staged, storage=storage, jobs=jobs)

    with_target = body.target is not None
    return staged_write(
        write,
        session=session,
        storage=storage,
        work=work,
        folder=with_target,
        prepare=prepare if with_target else None,
        upload_field="target",
        location=location,
    )


def submit_calibration(
    write: WriteRequest,
    *,
    session: Session,
    storage: Storage,
    limits: Limits,
    upload: UploadFile,
    body_of: Callable[[Calibration], dict[str, Any]],
    location: Location,
) -> JSONResponse:
    """Store an uploaded ``stereo-calibration/1`` as the current one (201)."""

    def work(staged: Staged) -> WorkAnswer:
        save_upload(upload, staged.folder / CALIBRATION_FILE)
        row = calibrations.create_calibration(
            session=session, storage=storage, staging_dir=staged.folder, limits=limits
        )
        staged.track(storage.calibration_dir(row.id))
        return 201, body_of(row), None

    return staged_write(
        write,
        session=session,
        storage=storage,
        work=work,
        upload_field="calibration",
        location=location,
    )


def submit_light_calibration(
    write: WriteRequest,
    staged: Staged,
    *,
    session: Session,
    storage: Storage,
    limits: Limits,
    file_name: str | None,
    upload_field: UploadField,
    body_of: Callable[[LightCalibration], dict[str, Any]],
    location: Location,
) -> JSONResponse:
    """Store a ``light-calibration/1`` staged in ``staged`` as the current one (201)."""

    def work(staged: Staged) -> WorkAnswer:
        row = light_calibrations.create_light_calibration(
            session=session,
            storage=storage,
            staging_dir=staged.folder,
            file_name=file_name,
            limits=limits,
        )
        staged.track(storage.light_calibration_dir(row.id))
        return 201, body_of(row), None

    return write_staged(
        write, staged, session=session, work=work, upload_field=upload_field, location=location
    )


def submit_target(
    write: WriteRequest,
    staged: Staged,
    *,
    session: Session,
    storage: Storage,
    plate_id: str,
    body_of: Callable[[Target], dict[str, Any]],
) -> JSONResponse:
    """Make the target staged in ``staged`` (``target.json``, + mesh) the plate's current one (200)."""

    def work(staged: Staged) -> WorkAnswer:
        row = create_target(
            session=session, storage=storage, plate_id=plate_id, staging_dir=staged.folder
        )
        staged.track(storage.target_dir(plate_id, row.id))
        return 200, body_of(row), None

    return write_staged(write, staged, session=session, work=work, upload_field="target")


def submit_machine(
    write: WriteRequest,
    *,
    session: Session,
    machine_id: str,
    spec: dict[str, Any],
    body_of: Callable[[Machine], dict[str, Any]],
    location: Location,
) -> JSONResponse:
    """Add or replace a roll bender: 201 when new, 200 when replaced."""

    def work() -> WorkAnswer:
        row, created = forming.put_machine(session=session, machine_id=machine_id, spec=spec)
        return 201 if created else 200, body_of(row), None

    return idempotent_write(write, session=session, work=work, location=location)


def parse_process(text: str) -> dict[str, Any]:
    """The multipart field ``process`` (JSON) checked as :class:`app.schemas.ProcessIn`, as a dict.

    Raises
    ------
    UnprocessableError
        422 naming ``process`` (not JSON) or the field of it that is wrong (``process.machine_id``).
    """
    try:
        return ProcessIn.model_validate_json(text).model_dump(mode="json")
    except ValidationError as err:
        first = err.errors()[0]
        loc = ".".join(str(p) for p in first["loc"])
        field = f"process.{loc}" if loc and first["type"] != "json_invalid" else "process"
        raise UnprocessableError(f"{field}: {first['msg']}", field=field) from None


_OPERATOR = TypeAdapter(OperatorName)


def parse_operator(text: str) -> str:
    """The multipart field ``operator`` checked as :data:`app.schemas.OperatorName`.

    Raises
    ------
    UnprocessableError
        422 naming ``operator``: empty, over 80 characters, or with control characters.
    """
    try:
        return _OPERATOR.validate_python(text)
    except ValidationError:
        raise UnprocessableError(
            f"operator: expected a name of 1-80 printable characters, got {text[:100]!r}",
            field="operator",
        ) from None


def _save_capture(parts: Sequence[UploadFile], folder: Path) -> None:
    """One part as :data:`CAPTURE_FILE`; several (stations) as ``parts/0.zip``, ``1.zip``, ... in the
    order sent (:data:`app.services.stations.PARTS_DIR`)."""
    if len(parts) == 1:
        save_upload(parts[0], folder / CAPTURE_FILE)
        return
    (folder / PARTS_DIR).mkdir()
    for i, part in enumerate(parts):
        save_upload(part, folder / PARTS_DIR / f"{i}.zip")


def _named_as_sent(err: InputError, filename: str | None) -> InputError:
    """The error with the bundle named as the client sent it (``bad.zip``), not as it is stored."""
    sent = Path(filename or "").name
    if not sent or sent == CAPTURE_FILE or not err.file.startswith(CAPTURE_FILE):
        return err
    return InputError(sent + err.file[len(CAPTURE_FILE) :], err.field, err.reason)


def _upload_part(err: InputError) -> str:
    """The multipart field a refused file of an upload is about: the target (staged in target/) or the capture."""
    return "target" if err.file.startswith("target/") else "capture"
