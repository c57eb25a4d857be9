"""Error answers: every error is JSON ``{"detail": <message>, "field": <request field or null>}``.

A bad uploaded file adds ``"file"`` (the file inside the upload the message is about); a request
that does not match the operation's parameters or body (422) adds ``"errors"``, every mismatch
as ``{"type", "loc", "msg"}``. :class:`ErrorBody` is that body; the OpenAPI document names it
``ErrorOut`` (:mod:`app.openapi`). No message carries a server path: absolute paths are cut to
their file name (:func:`scrub_paths`), and a bug answers only the exception's type.
"""

from __future__ import annotations

import logging
import os
import re
import sys
from collections.abc import Callable, Sequence
from typing import Any

from fastapi import FastAPI, HTTPException, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse, Response
from pydantic import BaseModel, Field
from sqlalchemy.exc import DBAPIError
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.routing import Match, Mount

from app.db import database_unavailable
from app.schemas import ErrorOut
from app.services.errors import ConflictError, NotFoundError, ServiceError
from pipeline.formats import InputError

log = logging.getLogger(__name__)

#: An absolute path of two or more parts, at the start of the text or after a space, quote,
#: bracket, '=' or ','; group 1 is its last part (URLs such as ``http://host/a/b`` and this API's
#: own paths, ``/api/v1/machines/R3``, are left alone).
_ABSOLUTE_PATH = re.compile(r"""(?:^|(?<=[\s'"(\[=,]))/(?!api/v1/)(?:[^/\s'"]+/)+([^/\s'"]*)""")
#: Seconds a client is told to wait (``Retry-After``) when the database cannot be reached.
DATABASE_RETRY_AFTER_S = 5
#: Methods a 405's ``Allow`` header may list.
_METHODS = ("GET", "HEAD", "POST", "PUT", "PATCH", "DELETE", "OPTIONS")


class ValidationIssue(BaseModel):
    """One way a request does not match its operation (pydantic's error, without its context)."""

    type: str
    loc: list[str | int]
    msg: str


class ErrorBody(ErrorOut):
    """Every error answer (4xx, 500): ``detail`` and ``field``, plus what some errors add."""

    file: str | None = Field(
        default=None, description="the file inside an upload the message is about"
    )
    errors: list[ValidationIssue] | None = Field(
        default=None,
        description="every way the request does not match its operation (422 of request validation)",
    )


def scrub_paths(text: str) -> str:
    """``text`` with every absolute filesystem path cut to its last part (the file's name)."""
    return _ABSOLUTE_PATH.sub(r"\1", text)


class ApiError(HTTPException):
    """An HTTP error naming the request field it is about."""

    def __init__(
        self,
        status_code: int,
        detail: str,
        *,
        field: str | None = None,
        headers: dict[str, str] | None = None,
    ) -> None:
        super().__init__(status_code=status_code, detail=detail, headers=headers)
        self.field = field


def error_body(detail: str, field: str | None = None, **extra: Any) -> dict[str, Any]:
    """An error answer's JSON (:class:`ErrorBody`); server paths in strings are cut to file names."""
    extra = {k: scrub_paths(v) if isinstance(v, str) else v for k, v in extra.items()}
    return {"detail": scrub_paths(detail), "field": field, **extra}


def allowed_methods(request: Request) -> list[str] | None:
    """Every method the request's path accepts (for a 405's ``Allow``), or None when a mount decides."""
    allowed: list[str] = []
    # Inside a mount the scope's root_path has grown by the mount's path: match from the app's root.
    root_path = request.scope.get("app_root_path", request.scope.get("root_path", ""))
    for method in _METHODS:
        scope = {**request.scope, "method": method, "root_path": root_path}
        for route in request.app.router.routes:
            match, _ = route.matches(scope)
            if match is Match.FULL:
                if isinstance(route, Mount):
                    return None  # the mounted app (static files) sends its own Allow
                allowed.append(method)
                break
    return allowed


#: The errors a request may legitimately cause (:func:`known_error` answers them).
KnownError = InputError | ServiceError | StarletteHTTPException


def known_error(
    exc: BaseException, *, upload_field: str | None = None
) -> tuple[int, dict[str, Any]] | None:
    """(status, body) for an error a request may legitimately cause, or None for a bug.

    ``upload_field`` is the multipart field whose file an :class:`InputError` is about.
    """
    if isinstance(exc, (InputError, ServiceError, StarletteHTTPException)):
        return error_answer(exc, upload_field=upload_field)
    return None


def error_answer(exc: KnownError, *, upload_field: str | None = None) -> tuple[int, dict[str, Any]]:
    """(status, body) of an error a request may legitimately cause (see :func:`known_error`)."""
    if isinstance(exc, InputError):
        field = (
            f"{upload_field}: {exc.field}"
            if upload_field and exc.field
            else (exc.field or upload_field)
        )
        return 422, error_body(str(exc), field, file=exc.file)
    if isinstance(exc, NotFoundError):
        return 404, error_body(exc.detail, exc.field)
    if isinstance(exc, ConflictError):
        return 409, error_body(exc.detail, exc.field)
    if isinstance(exc, ServiceError):
        return 422, error_body(exc.detail, exc.field)
    if isinstance(exc, ApiError):
        return exc.status_code, error_body(str(exc.detail), exc.field)
    reason = body_parse_failure(exc)
    if reason is not None:
        return 400, error_body(f"body: {reason}", "body")
    return exc.status_code, error_body(str(exc.detail))


def body_parse_failure(exc: StarletteHTTPException) -> str | None:
    """What was wrong with a JSON body FastAPI could not parse (its 400), or None for another error.

    FastAPI answers "There was an error parsing the body" (400) when ``json.loads`` fails with
    something else than a syntax error: a body nested deeper than the interpreter's recursion
    limit (RecursionError), an integer of more digits than Python converts, bytes that are not
    UTF-8 (ValueError). Such a body is answered 400 naming ``body`` on every route, as is a body
    that is not JSON at all (:func:`not_json`).
    """
    cause = exc.__cause__
    if exc.status_code != 400 or not isinstance(cause, (RecursionError, ValueError)):
        return None
    if isinstance(cause, RecursionError):
        return "not usable JSON: objects and lists nested too deeply"
    if isinstance(cause, UnicodeDecodeError):
        return f"not UTF-8 text (byte {cause.start})"
    if "digits" in str(cause):
        return f"not usable JSON: a number of more than {sys.get_int_max_str_digits()} digits"
    return f"not usable JSON: {cause}"


def not_json(errors: list[dict[str, Any]]) -> str | None:
    """What is wrong with a JSON body that is not JSON (FastAPI's ``json_invalid`` validation
    error, whose location is a character offset), or None when the body parsed."""
    for e in errors:
        if e.get("type") == "json_invalid":
            reason = str((e.get("ctx") or {}).get("error") or "").strip()
            return "not JSON" + (f" ({reason[:1].lower()}{reason[1:]})" if reason else "")
    return None


def relabel_input_error(err: InputError, base: str | os.PathLike[str]) -> InputError:
    """The same error with paths under the server folder ``base`` written relative to it.

    Uploads are validated in a staging folder; the client should read ``capture.zip: ...``, not
    a server path.
    """
    prefix = str(base).rstrip("/") + "/"
    if prefix not in err.file and prefix not in err.reason:
        return err
    return InputError(err.file.replace(prefix, ""), err.field, err.reason.replace(prefix, ""))


def _validation_field(loc: Sequence[str | int]) -> str | None:
    parts = [str(p) for p in loc]
    if parts and parts[0] in ("body", "query", "path", "header", "cookie", "form"):
        parts = parts[1:]
    return ".".join(parts) or None


#: Renders an error as a dashboard page: (request, status, detail) -> the page, or None if it cannot.
HtmlErrorPage = Callable[[Request, int, str], Response | None]


def wants_page(request: Request) -> bool:
    """A browser navigating to a dashboard page (GET, HTML accepted, not the API, files or viewer)."""
    path = request.url.path
    return (
        request.method == "GET"
        and "text/html" in request.headers.get("accept", "")
        and not path.startswith(("/api/", "/static/", "/viewer", "/docs", "/openapi", "/healthz"))
    )


def install_error_handlers(app: FastAPI) -> None:
    """JSON error bodies for HTTP errors, validation errors, service errors and bugs.

    A browser navigating to a dashboard page gets the error as a page in the dashboard's layout
    instead, when the dashboard set ``app.state.html_error_page`` (:data:`HtmlErrorPage`).
    """

    def page(request: Request, status: int, detail: str) -> Response | None:
        render = getattr(request.app.state, "html_error_page", None)
        if render is None or not wants_page(request):
            return None
        answer: Response | None = render(request, status, detail)
        return answer

    @app.exception_handler(StarletteHTTPException)
    async def _http(request: Request, exc: StarletteHTTPException) -> Response:
        status, body = error_answer(exc)
        headers = getattr(exc, "headers", None)
        if status == 405:
            allowed = allowed_methods(request)
            if allowed is not None:
                # The router stops at the first route of the path; the path may have others.
                headers = {**(headers or {}), "Allow": ", ".join(allowed)}
                body = error_body(
                    f"method: {request.method} is not allowed here; allowed: {', '.join(allowed)}",
                    "method",
                )
        return page(request, status, body["detail"]) or JSONResponse(
            body, status_code=status, headers=headers
        )

    @app.exception_handler(RequestValidationError)
    async def _validation(request: Request, exc: RequestValidationError) -> Response:
        errors = exc.errors()
        reason = not_json(list(errors))
        if reason is not None:
            return JSONResponse(error_body(f"body: {reason}", "body"), status_code=400)
        first = errors[0] if errors else {"loc": (), "msg": "invalid request"}
        field = _validation_field(first.get("loc", ()))
        detail = f"{field}: {first.get('msg')}" if field else str(first.get("msg"))
        if len(errors) > 1:
            detail += f" (and {len(errors) - 1} more)"
        issues = [{**e, "msg": scrub_paths(e["msg"])} for e in jsonable(errors)]
        return JSONResponse(error_body(detail, field, errors=issues), status_code=422)

    @app.exception_handler(ServiceError)
    async def _service(request: Request, exc: ServiceError) -> Response:
        status, body = error_answer(exc)
        return JSONResponse(body, status_code=status)

    @app.exception_handler(InputError)
    async def _input(request: Request, exc: InputError) -> Response:
        status, body = error_answer(exc)
        return JSONResponse(body, status_code=status)

    @app.exception_handler(DBAPIError)
    async def _database(request: Request, exc: DBAPIError) -> Response:
        if not database_unavailable(exc):
            return await _bug(request, exc)
        log.warning(
            "database unavailable on %s %s: %s",
            request.method,
            request.url.path,
            str(exc.orig or exc).splitlines()[0],
        )
        detail = "database unavailable: the service cannot reach its database now; retry shortly"
        headers = {"Retry-After": str(DATABASE_RETRY_AFTER_S)}
        return JSONResponse(error_body(detail), status_code=503, headers=headers)

    @app.exception_handler(Exception)
    async def _bug(request: Request, exc: Exception) -> Response:
        log.exception("internal error on %s %s", request.method, request.url.path)
        detail = f"internal error: {type(exc).__name__}"
        return page(request, 500, detail) or JSONResponse(error_body(detail), status_code=500)


def jsonable(errors: Sequence[Any]) -> list[dict[str, Any]]:
    """Validation errors without the non-JSON bits (exception objects in ``ctx``)."""
    out = []
    for e in errors:
        out.append(
            {k: list(v) if k == "loc" else v for k, v in e.items() if k in ("type", "loc", "msg")}
        )
    return out
