"""The OpenAPI document says what the service sends: one error body, on every operation that can send it.

FastAPI documents a 422 as its own ``HTTPValidationError`` (``detail`` an array), but this service
answers every error with one body (:class:`app.errors.ErrorBody`, named ``ErrorOut``: ``detail``
a string). :func:`install_openapi` makes the generated document match, whatever each route
declares:

- ``ErrorOut`` is the full error body (``detail``, ``field``, and the optional ``file`` and ``errors``);
- 422 (``ErrorOut``) on every operation with parameters or a body (a request that does not match them);
- 400 on every operation with a body (a body that cannot be parsed, e.g. a broken multipart body)
  and 413 (over ``PLATE_INSPECT_MAX_UPLOAD_MB``);
- 401, 403 (a cookie write from another origin) and 429 (a throttled wrong token) on every
  operation that needs the API token (one with ``security``);
- 409 on every operation that takes an ``Idempotency-Key`` (the first request with the key still
  runs), whose 422 also says that the key was used with another body;
- ``Location`` on every 201 and 202 answer (where the new resource, or the queued job, is read);
- 503 on every operation (the database cannot be reached now; ``Retry-After`` says when to retry).
"""

from __future__ import annotations

from http import HTTPStatus
from typing import Any

from fastapi import FastAPI

from app.errors import ErrorBody

#: The component every error response refers to.
ERROR_SCHEMA = "ErrorOut"
_ERROR_REF = {"$ref": f"#/components/schemas/{ERROR_SCHEMA}"}
#: FastAPI's own validation error components, replaced by ErrorOut.
_FASTAPI_VALIDATION = ("HTTPValidationError", "ValidationError")

_BODY_ERRORS = {
    "400": "the body cannot be parsed (not JSON, or a broken multipart body)",
    "413": "the body is larger than PLATE_INSPECT_MAX_UPLOAD_MB",
}
_AUTH_ERRORS = {
    "401": "no token, a wrong one, or no valid dashboard session",
    "403": "a write with the session cookie from another origin",
    "429": "a wrong token from an address that sent too many (Retry-After says when to try again)",
}
_VALIDATION_ERROR = {
    "422": "the request does not match the operation's parameters or body (`errors` lists how)"
}
_UNAVAILABLE_ERROR = {
    "503": "the database cannot be reached now (Retry-After says when to try again)"
}
_IDEMPOTENCY_ERROR = {
    "409": "the first request with this Idempotency-Key is still in progress; retry later"
}
_KEY_REUSED = (
    "; or this Idempotency-Key was used on this route with another body (field `Idempotency-Key`)"
)
#: The header of every 201 and 202 answer.
_LOCATION = {
    "Location": {
        "description": "where the new resource (201) or the queued job (202) is read",
        "schema": {"type": "string"},
    }
}


def install_openapi(app: FastAPI) -> None:
    """Make ``app.openapi()`` return the document completed by :func:`document_errors`."""
    generate = app.openapi

    def openapi() -> dict[str, Any]:
        if app.openapi_schema is None:
            app.openapi_schema = document_errors(generate())
        return app.openapi_schema

    # FastAPI's documented way to customise the schema: replace the method on the instance.
    app.openapi = openapi  # type: ignore[method-assign]


def document_errors(schema: dict[str, Any]) -> dict[str, Any]:
    """Complete an OpenAPI document in place with the error responses listed in the module's docstring."""
    components = schema.setdefault("components", {}).setdefault("schemas", {})
    body = ErrorBody.model_json_schema(ref_template="#/components/schemas/{model}")
    for name, sub in body.pop("$defs", {}).items():
        components.setdefault(name, sub)
    components[ERROR_SCHEMA] = {**body, "title": ERROR_SCHEMA}
    for operations in schema.get("paths", {}).values():
        for operation in operations.values():
            responses = operation.setdefault("responses", {})
            _add(responses, _UNAVAILABLE_ERROR)
            if operation.get("parameters") or operation.get("requestBody"):
                _add(responses, _VALIDATION_ERROR)
            if operation.get("requestBody"):
                _add(responses, _BODY_ERRORS)
            if operation.get("security"):
                _add(responses, _AUTH_ERRORS)
            if any(
                p.get("in") == "header" and p.get("name") == "Idempotency-Key"
                for p in operation.get("parameters", ())
            ):
                _add(responses, _IDEMPOTENCY_ERROR)
                responses["422"]["description"] += _KEY_REUSED
            for created in ("201", "202"):
                if created in responses:
                    responses[created].setdefault("headers", {}).update(_LOCATION)
    for name in _FASTAPI_VALIDATION:
        components.pop(name, None)
    return schema


def _add(responses: dict[str, Any], errors: dict[str, str]) -> None:
    """Document ``errors`` (status -> description) as ErrorOut answers; a route's own description stays."""
    for status, description in errors.items():
        own = responses.get(status, {}).get("description")
        generic = own in (None, "Validation Error", HTTPStatus(int(status)).phrase)
        responses[status] = {
            "description": description if generic else own,
            "content": {"application/json": {"schema": _ERROR_REF}},
        }
