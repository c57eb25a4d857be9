"""Request dependencies as typed ``Annotated`` aliases: settings, session, storage, job queue, auth.

Auth: writes need the API token as ``Authorization: Bearer <token>``, or the cookie of a dashboard
session (:mod:`app.services.sessions`) opened with it. Every check of a presented token goes
through the app's :class:`app.throttle.TokenThrottle`.
"""

from __future__ import annotations

import hashlib
import hmac
import ipaddress
from collections.abc import Iterator
from dataclasses import dataclass
from datetime import timedelta
from typing import Annotated

from fastapi import Depends, Request, Response
from fastapi.security import APIKeyCookie, HTTPAuthorizationCredentials, HTTPBearer
from sqlalchemy.orm import Session, sessionmaker
from starlette.concurrency import run_in_threadpool
from starlette.requests import HTTPConnection

from app.errors import ApiError
from app.jobs import JobQueue
from app.services import sessions as session_svc
from app.settings import Settings
from app.storage import Storage
from app.throttle import TokenThrottle, client_key

#: Cookie holding a dashboard write session's id (HttpOnly, SameSite=Strict).
SESSION_COOKIE = "plate_inspect_session"


def get_settings(request: Request) -> Settings:
    settings: Settings = request.app.state.settings
    return settings


def get_session(request: Request) -> Iterator[Session]:
    """One session per request; rolled back if the request fails before it commits."""
    with request.app.state.session_factory() as session:
        try:
            yield session
        except BaseException:
            session.rollback()
            raise


def get_storage(request: Request) -> Storage:
    storage: Storage = request.app.state.storage
    return storage


def get_jobs(request: Request) -> JobQueue:
    jobs: JobQueue = request.app.state.jobs
    return jobs


SettingsDep = Annotated[Settings, Depends(get_settings)]
SessionDep = Annotated[Session, Depends(get_session)]
StorageDep = Annotated[Storage, Depends(get_storage)]
JobsDep = Annotated[JobQueue, Depends(get_jobs)]


# ------------------------------------------------------------------ auth


def token_hash(token: str) -> str:
    """sha256 hex of a token (idempotency keys and sessions are scoped by it; the token itself is never stored)."""
    return hashlib.sha256(token.encode("utf-8")).hexdigest()


def client_address(conn: HTTPConnection) -> str:
    """The peer's address as the token throttle counts it (see :func:`app.throttle.client_key`)."""
    return client_key(conn.client.host if conn.client is not None else None)


def is_loopback(conn: HTTPConnection) -> bool:
    """True for a client on this machine (127.0.0.0/8, ::1)."""
    host = conn.client.host if conn.client is not None else ""
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


async def check_token(
    conn: HTTPConnection, presented: str, *, field: str, headers: dict[str, str] | None = None
) -> None:
    """Check a presented API token, throttled per client address.

    The right token always passes (after the address's turn when it is throttled).

    Raises
    ------
    ApiError
        401 for a wrong token; 429 with ``Retry-After`` for a wrong one from an address that
        sent more than ``login_free_failures`` wrong tokens within ``login_window_s``.
    """
    throttle: TokenThrottle = conn.app.state.token_throttle
    client = client_address(conn)
    await throttle.wait_turn(client)
    if hmac.compare_digest(presented.encode("utf-8"), conn.app.state.api_token.encode("utf-8")):
        throttle.succeeded(client)
        return
    wait_s = throttle.failed(client)
    if wait_s is None:
        raise ApiError(401, f"{field}: wrong token", field=field, headers=headers)
    raise ApiError(
        429,
        f"{field}: wrong token; {throttle.failures(client)} wrong tokens from this address in the last "
        f"{throttle.window_s:g} s, its next token is checked in {TokenThrottle.retry_after(wait_s)} s",
        field=field,
        headers={**(headers or {}), "Retry-After": TokenThrottle.retry_after(wait_s)},
    )


def session_cookie(conn: HTTPConnection) -> str | None:
    """The session id in the request's cookie, or None (no cookie, or a value this server never issues)."""
    value = conn.cookies.get(SESSION_COOKIE)
    return value if value is not None and session_svc.well_formed(value) else None


def has_dashboard_session(conn: HTTPConnection, *, db: Session | None = None) -> bool:
    """True if the request carries the cookie of a valid dashboard session.

    Parameters
    ----------
    conn : Request or WebSocket
    db : Session, optional; by default one from ``app.state.session_factory`` (False without one).
    """
    session_id = session_cookie(conn)
    factory: sessionmaker[Session] | None = getattr(conn.app.state, "session_factory", None)
    if session_id is None:
        return False
    if db is not None:
        return _session_known(conn, db, session_id)
    if factory is None:
        return False
    with factory() as own:
        return _session_known(conn, own, session_id)


def _session_known(conn: HTTPConnection, db: Session, session_id: str) -> bool:
    """True if ``session_id`` is a valid session of the app's current token."""
    current = token_hash(conn.app.state.api_token)
    return (
        session_svc.find_session(session=db, session_id=session_id, token_hash=current) is not None
    )


def start_dashboard_session(response: Response, conn: HTTPConnection, *, db: Session) -> None:
    """Open a dashboard session (committed) and give the browser its cookie (HttpOnly, SameSite=Strict).

    The cookie lasts as long as the session (``PLATE_INSPECT_SESSION_HOURS``); it is ``Secure``
    when the request came over https.
    """
    settings: Settings = conn.app.state.settings
    lifetime = timedelta(hours=settings.session_hours)
    session_id = session_svc.open_session(
        session=db, token_hash=token_hash(conn.app.state.api_token), lifetime=lifetime
    )
    db.commit()
    response.set_cookie(
        SESSION_COOKIE,
        session_id,
        max_age=int(lifetime.total_seconds()),
        httponly=True,
        samesite="strict",
        secure=conn.url.scheme in ("https", "wss"),
        path="/",
    )


def end_dashboard_session(response: Response, conn: HTTPConnection, *, db: Session) -> None:
    """Revoke the request's dashboard session on the server (committed) and drop its cookie."""
    session_id = session_cookie(conn)
    if session_id is not None and session_svc.revoke_session(session=db, session_id=session_id):
        db.commit()
    response.delete_cookie(SESSION_COOKIE, path="/", httponly=True, samesite="strict")


@dataclass(frozen=True)
class Writer:
    """An authenticated writer; ``token_hash`` scopes its idempotency keys."""

    token_hash: str
    via: str  # "bearer" or "cookie"


_bearer = HTTPBearer(auto_error=False, description="the API token (PLATE_INSPECT_API_TOKEN)")
_session_cookie = APIKeyCookie(
    name=SESSION_COOKIE,
    auto_error=False,
    description="a dashboard session (POST /api/v1/session), same-origin only",
)


async def require_writer(
    request: Request,
    bearer: Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)],
    cookie: Annotated[str | None, Depends(_session_cookie)],
) -> Writer:
    """Writes need ``Authorization: Bearer <token>`` (or the cookie of a valid dashboard session).

    Raises
    ------
    ApiError
        401 when the header is missing, malformed or carries a wrong token, or the session is
        unknown, expired or revoked; 429 for a wrong token from a throttled address
        (:func:`check_token`); 403 for a cookie write from another origin.
    """
    token: str = request.app.state.api_token
    challenge = {"WWW-Authenticate": "Bearer"}
    if request.headers.get("authorization") is not None:
        if bearer is None or not bearer.credentials.strip():
            raise ApiError(
                401,
                "Authorization: expected 'Bearer <token>'",
                field="Authorization",
                headers=challenge,
            )
        await check_token(
            request, bearer.credentials.strip(), field="Authorization", headers=challenge
        )
        return Writer(token_hash=token_hash(token), via="bearer")
    if cookie is not None:
        if not await run_in_threadpool(has_dashboard_session, request):
            raise ApiError(
                401,
                f"{SESSION_COOKIE}: session expired, ended or unknown, log in again",
                field=SESSION_COOKIE,
            )
        origin = request.headers.get("origin")
        if origin is not None and origin.split("://", 1)[-1] != request.headers.get("host", ""):
            raise ApiError(
                403, f"Origin: cross-site write refused (origin {origin})", field="Origin"
            )
        return Writer(token_hash=token_hash(token), via="cookie")
    raise ApiError(
        401,
        "Authorization: a write needs 'Authorization: Bearer <token>'",
        field="Authorization",
        headers=challenge,
    )


WriterDep = Annotated[Writer, Depends(require_writer)]
