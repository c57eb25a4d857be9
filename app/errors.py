"""Error answers: every error is JSON ``{"detail": <message>, "field": <request field or null>}``.

A bad uploaded file adds ``"file"`` (the file inside the upload the message is about).
"""

from __future__ import annotations

import logging

from fastapi import FastAPI, HTTPException, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException

from app.services.errors import NotFoundError, ServiceError
from pipeline.formats import InputError

log = logging.getLogger(__name__)


class ApiError(HTTPException):
    """An HTTP error naming the request field it is about."""

    def __init__(self, status_code: int, detail: str, *, field: str | None = None, headers: dict | None = None):
        super().__init__(status_code=status_code, detail=detail, headers=headers)
        self.field = field


def error_body(detail: str, field: str | None = None, **extra) -> dict:
    return {"detail": detail, "field": field, **extra}


def known_error(exc: BaseException, *, upload_field: str | None = None) -> tuple[int, dict] | None:
    """(status, body) for an error a request may legitimately cause, or None for a bug.

    ``upload_field`` is the multipart field whose file an :class:`InputError` is about.
    """
    if isinstance(exc, InputError):
        field = f"{upload_field}: {exc.field}" if upload_field and exc.field else (exc.field or upload_field)
        return 422, error_body(str(exc), field, file=exc.file)
    if isinstance(exc, NotFoundError):
        return 404, error_body(exc.detail, exc.field)
    if isinstance(exc, ServiceError):
        return 422, error_body(exc.detail, exc.field)
    if isinstance(exc, ApiError):
        return exc.status_code, error_body(str(exc.detail), exc.field)
    if isinstance(exc, StarletteHTTPException):
        return exc.status_code, error_body(str(exc.detail))
    return None


def relabel_input_error(err: InputError, base) -> InputError:
    """The same error with paths under the server folder ``base`` written relative to it.

    Uploads are validated in a staging folder; the client should read ``capture.zip: ...``, not
    a server path.
    """
    prefix = str(base).rstrip("/") + "/"
    if prefix not in err.file and prefix not in err.reason:
        return err
    return InputError(err.file.replace(prefix, ""), err.field, err.reason.replace(prefix, ""))


def _validation_field(loc) -> str | None:
    parts = [str(p) for p in loc]
    if parts and parts[0] in ("body", "query", "path", "header", "cookie", "form"):
        parts = parts[1:]
    return ".".join(parts) or None


def install_error_handlers(app: FastAPI) -> None:
    """JSON error bodies for HTTP errors, validation errors, service errors and bugs."""

    @app.exception_handler(StarletteHTTPException)
    async def _http(request: Request, exc: StarletteHTTPException):
        status, body = known_error(exc)
        return JSONResponse(body, status_code=status, headers=getattr(exc, "headers", None))

    @app.exception_handler(RequestValidationError)
    async def _validation(request: Request, exc: RequestValidationError):
        errors = exc.errors()
        first = errors[0] if errors else {"loc": (), "msg": "invalid request"}
        field = _validation_field(first.get("loc", ()))
        detail = f"{field}: {first.get('msg')}" if field else str(first.get("msg"))
        if len(errors) > 1:
            detail += f" (and {len(errors) - 1} more)"
        return JSONResponse(error_body(detail, field, errors=jsonable(errors)), status_code=422)

    @app.exception_handler(ServiceError)
    async def _service(request: Request, exc: ServiceError):
        status, body = known_error(exc)
        return JSONResponse(body, status_code=status)

    @app.exception_handler(InputError)
    async def _input(request: Request, exc: InputError):
        status, body = known_error(exc)
        return JSONResponse(body, status_code=status)

    @app.exception_handler(Exception)
    async def _bug(request: Request, exc: Exception):
        log.exception("internal error on %s %s", request.method, request.url.path)
        return JSONResponse(error_body(f"internal error: {type(exc).__name__}"), status_code=500)


def jsonable(errors: list[dict]) -> list[dict]:
    """Validation errors without the non-JSON bits (exception objects in ``ctx``)."""
    out = []
    for e in errors:
        out.append({k: v for k, v in e.items() if k in ("type", "loc", "msg")})
    return out
