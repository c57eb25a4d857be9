"""Request dependencies as typed ``Annotated`` aliases: settings, session, storage, job queue, auth."""

from __future__ import annotations

import hashlib
import hmac
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Annotated

from fastapi import Depends, Request, Response
from sqlalchemy.orm import Session

from app.errors import ApiError
from app.jobs import JobQueue
from app.settings import Settings
from app.storage import Storage

#: Cookie holding a dashboard write session (HttpOnly, SameSite=Strict).
SESSION_COOKIE = "plate_inspect_session"


def get_settings(request: Request) -> Settings:
    return request.app.state.settings


def get_session(request: Request) -> Iterator[Session]:
    """One session per request; rolled back if the request fails before it commits."""
    with request.app.state.session_factory() as session:
        try:
            yield session
        except BaseException:
            session.rollback()
            raise


def get_storage(request: Request) -> Storage:
    return request.app.state.storage


def get_jobs(request: Request) -> JobQueue:
    return request.app.state.jobs


SettingsDep = Annotated[Settings, Depends(get_settings)]
SessionDep = Annotated[Session, Depends(get_session)]
StorageDep = Annotated[Storage, Depends(get_storage)]
JobsDep = Annotated[JobQueue, Depends(get_jobs)]


# ------------------------------------------------------------------ auth


def token_hash(token: str) -> str:
    """sha256 hex of a token (idempotency keys are scoped by it; the token itself is never stored)."""
    return hashlib.sha256(token.encode("utf-8")).hexdigest()


def session_cookie_value(token: str) -> str:
    """The dashboard session cookie's value for ``token`` (an HMAC of it, not the token)."""
    return hmac.new(token.encode("utf-8"), b"plate-inspect dashboard session", hashlib.sha256).hexdigest()


def issue_session_cookie(response: Response, token: str, *, secure: bool = False) -> None:
    """Give the browser a write session for same-origin pages (HttpOnly, SameSite=Strict)."""
    response.set_cookie(
        SESSION_COOKIE,
        session_cookie_value(token),
        httponly=True,
        samesite="strict",
        secure=secure,
        path="/",
    )


@dataclass(frozen=True)
class Writer:
    """An authenticated writer; ``token_hash`` scopes its idempotency keys."""

    token_hash: str
    via: str  # "bearer" or "cookie"


def require_writer(request: Request) -> Writer:
    """Writes need ``Authorization: Bearer <token>`` (or the dashboard's same-origin session cookie).

    Raises
    ------
    ApiError
        401 when the header is missing, malformed or carries a wrong token.
    """
    token: str = request.app.state.api_token
    header = request.headers.get("authorization")
    challenge = {"WWW-Authenticate": "Bearer"}
    if header is not None:
        scheme, _, value = header.partition(" ")
        if scheme.lower() != "bearer" or not value.strip():
            raise ApiError(401, "Authorization: expected 'Bearer <token>'", field="Authorization", headers=challenge)
        if not hmac.compare_digest(value.strip().encode("utf-8"), token.encode("utf-8")):
            raise ApiError(401, "Authorization: wrong token", field="Authorization", headers=challenge)
        return Writer(token_hash=token_hash(token), via="bearer")
    cookie = request.cookies.get(SESSION_COOKIE)
    if cookie is not None:
        if not hmac.compare_digest(cookie.encode("utf-8"), session_cookie_value(token).encode("utf-8")):
            raise ApiError(401, f"{SESSION_COOKIE}: session expired or wrong, log in again", field=SESSION_COOKIE)
        origin = request.headers.get("origin")
        if origin is not None and origin.split("://", 1)[-1] != request.headers.get("host", ""):
            raise ApiError(403, f"Origin: cross-site write refused (origin {origin})", field="Origin")
        return Writer(token_hash=token_hash(token), via="cookie")
    raise ApiError(401, "Authorization: a write needs 'Authorization: Bearer <token>'", field="Authorization", headers=challenge)


WriterDep = Annotated[Writer, Depends(require_writer)]
