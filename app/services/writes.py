"""Writes of the API: their staged files, one transaction, once per ``Idempotency-Key``, and the
errors a request may cause answered as JSON.

A route parses and authorises its request, then hands the write to one service function, which
runs the recipe of :func:`staged_write`: stage the upload's files, do the work (rows added, not
committed), commit the rows with the remembered answer (:func:`idempotent_write`), and undo the
files when the rows are not committed.
"""

from __future__ import annotations

import json
import shutil
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from sqlalchemy.orm import Session
from starlette.datastructures import UploadFile
from starlette.responses import JSONResponse

from app.errors import error_body, known_error, relabel_input_error
from app.jobs import JobQueue
from app.limits.queue import QueueFullError
from app.models import Inspection
from app.services import idempotency
from app.storage import Staged, Storage
from pipeline.formats import InputError

#: What a write's work answers: (status code, JSON body, called after the commit (e.g. enqueue) or None).
WorkAnswer = tuple[int, dict[str, Any], Callable[[], None] | None]
#: work() -> :data:`WorkAnswer`
Work = Callable[[], WorkAnswer]
#: The multipart field a refused file is about: one name, or a function of the (relabelled) error.
UploadField = str | Callable[[InputError], str] | None
#: A 201 or 202 answer's ``Location`` from its body (the resource created or the job queued).
Location = Callable[[dict[str, Any]], str]


@dataclass(frozen=True)
class WriteRequest:
    """What a write needs of its HTTP request to be run once per ``Idempotency-Key``.

    Attributes
    ----------
    scope : str
        ``"<method> <path>"``: a key is remembered per route (and token).
    token_hash : str
        The writer's token hash (:class:`app.deps.Writer`): a key is remembered per token.
    key : str or None
        The request's ``Idempotency-Key``; None runs the write without remembering it.
    request_sha256 : str or None
        The request's fingerprint (:func:`app.routes.common.request_fingerprint`), to refuse the
        same key with another body.
    """

    scope: str
    token_hash: str
    key: str | None
    request_sha256: str | None


def staged_write(
    write: WriteRequest,
    *,
    session: Session,
    storage: Storage,
    work: Callable[[Staged], WorkAnswer],
    folder: bool = True,
    prepare: Callable[[Staged], None] | None = None,
    upload_field: UploadField = None,
    location: Location | None = None,
) -> JSONResponse:
    """Stage a write's files, then run it once (:func:`idempotent_write`); the staging folder goes.

    ``folder``: stage the upload in a folder of its own (``Staged.folder``); ``prepare`` writes
    files into it before the key is claimed. ``work`` adds the write's rows and
    :meth:`~app.storage.Staged.track`\\ s the folders it makes: they are removed with the staging
    folder when the rows are not committed.
    """
    with storage.staging(folder=folder) as staged:
        if prepare is not None:
            prepare(staged)
        return write_staged(
            write,
            staged,
            session=session,
            work=work,
            upload_field=upload_field,
            location=location,
        )


def write_staged(
    write: WriteRequest,
    staged: Staged,
    *,
    session: Session,
    work: Callable[[Staged], WorkAnswer],
    upload_field: UploadField = None,
    location: Location | None = None,
) -> JSONResponse:
    """Run a write whose upload is staged already in ``staged`` (see :func:`staged_write`)."""
    return idempotent_write(
        write,
        session=session,
        work=lambda: work(staged),
        cleanup=staged.undo,
        staging=staged.dir,
        upload_field=upload_field,
        location=location,
    )


def save_upload(upload: UploadFile, path: Path) -> None:
    """Stream an uploaded file (FastAPI's ``UploadFile``) to ``path`` in 1 MiB chunks."""
    with open(path, "wb") as fh:
        shutil.copyfileobj(upload.file, fh, length=1 << 20)


def queued_inspection(
    row: Inspection, staged: Staged, *, storage: Storage, jobs: JobQueue
) -> WorkAnswer:
    """The answer of a write that queued inspection ``row``: 202 ``{"id", "status"}``, its folder
    tracked (removed if the row is not committed), the job enqueued once it is."""
    staged.track(storage.inspection_dir(row.id))
    return 202, {"id": row.id, "status": row.status}, lambda: jobs.enqueue(row.id)


def idempotent_write(
    write: WriteRequest,
    *,
    session: Session,
    work: Work,
    cleanup: Callable[[], None] = lambda: None,
    upload_field: UploadField = None,
    staging: Path | None = None,
    location: Location | None = None,
) -> JSONResponse:
    """Run a write once per ``Idempotency-Key`` (per route and token) and answer with JSON.

    ``work`` adds rows without committing; this commits them together with the stored answer,
    then calls the after-commit hook. A refused request (4xx) is remembered too, so a retry gets
    the same refusal; a bug (5xx) forgets the key, and so does a full queue
    (:class:`~app.limits.queue.QueueFullError`, answered 429 with ``Retry-After``): a retry may be
    admitted. The same key with another body (``write.request_sha256``) is refused with 422
    naming ``Idempotency-Key``. ``cleanup`` undoes files ``work`` wrote when its rows are not
    committed. File errors name files relative to ``staging`` (the upload's folder);
    ``upload_field`` is the multipart field they are about, or a function of the (relabelled)
    error giving it when the upload has several files. ``location`` gives a 201 or 202 answer's
    ``Location`` header from its body (the resource created or the job queued).
    """
    row_id = None
    if write.key is not None:
        claimed = _claim(write, session=session, key=write.key)
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


def _claim(write: WriteRequest, *, session: Session, key: str) -> int | JSONResponse:
    """The id of the key's claim for this request, or the answer when another request made it:
    the first answer replayed, 409 while it runs, 422 when it was sent with another body."""
    sha = write.request_sha256
    try:
        row, claimed = idempotency.claim(
            session=session,
            key=key,
            scope=write.scope,
            token_hash=write.token_hash,
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


def _with_location(response: JSONResponse, location: Location | None) -> JSONResponse:
    """The answer with ``Location`` when it created something (201) or queued a job (202)."""
    if location is not None and response.status_code in (201, 202):
        response.headers["Location"] = location(json.loads(bytes(response.body)))
    return response
