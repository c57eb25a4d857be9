"""Dashboard sessions: open one per login, find it from its cookie, revoke it at logout.

A session id is 32 random bytes (URL-safe base64, 43 characters) held by the browser in an
HttpOnly cookie; the database keeps only its sha256 (:class:`app.models.DashboardSession`),
so a copy of the database does not give a usable cookie. A session is valid until it expires
or is revoked, and only under the API token it was opened with.
"""

from __future__ import annotations

import hashlib
import re
import secrets
from datetime import datetime, timedelta

from sqlalchemy import delete, or_
from sqlalchemy.orm import Session

from app.models import DashboardSession, utcnow

#: Random bytes of a session id.
SESSION_ID_BYTES = 32
#: Shape of a session id (``secrets.token_urlsafe(32)``); anything else is no session.
SESSION_ID_PATTERN = re.compile(r"[A-Za-z0-9_-]{43}")
#: Expired or revoked sessions are deleted this long after they ended.
KEEP_ENDED = timedelta(days=1)


def id_hash(session_id: str) -> str:
    """sha256 hex of a session id (what the database stores)."""
    return hashlib.sha256(session_id.encode("ascii")).hexdigest()


def well_formed(session_id: str) -> bool:
    """True if ``session_id`` has the shape of an id this server issues (any other value is no session)."""
    return SESSION_ID_PATTERN.fullmatch(session_id) is not None


def open_session(
    *, session: Session, token_hash: str, lifetime: timedelta, now: datetime | None = None
) -> str:
    """Add a new session (not committed) and return its id, the cookie's value.

    Sessions that ended more than :data:`KEEP_ENDED` ago are deleted on the way.

    Parameters
    ----------
    session : Session
    token_hash : str, sha256 hex of the API token the session is opened under.
    lifetime : timedelta, > 0.
    now : datetime, optional, timezone-aware (defaults to the current time).
    """
    if lifetime <= timedelta(0):
        raise ValueError(f"lifetime: expected a positive duration, got {lifetime}")
    now = now or utcnow()
    purge_ended(session=session, now=now)
    session_id = secrets.token_urlsafe(SESSION_ID_BYTES)
    session.add(
        DashboardSession(
            id_hash=id_hash(session_id),
            token_hash=token_hash,
            created_at=now,
            expires_at=now + lifetime,
        )
    )
    return session_id


def find_session(
    *, session: Session, session_id: str, token_hash: str, now: datetime | None = None
) -> DashboardSession | None:
    """The valid session with this id: not expired, not revoked, opened under ``token_hash``; else None."""
    if not well_formed(session_id):
        return None
    row = session.get(DashboardSession, id_hash(session_id))
    now = now or utcnow()
    if (
        row is None
        or row.revoked_at is not None
        or row.expires_at <= now
        or row.token_hash != token_hash
    ):
        return None
    return row


def revoke_session(*, session: Session, session_id: str, now: datetime | None = None) -> bool:
    """Revoke a session (not committed); True if it existed and was not revoked yet."""
    if not well_formed(session_id):
        return False
    row = session.get(DashboardSession, id_hash(session_id))
    if row is None or row.revoked_at is not None:
        return False
    row.revoked_at = now or utcnow()
    return True


def purge_ended(*, session: Session, now: datetime | None = None) -> None:
    """Delete sessions that expired or were revoked more than :data:`KEEP_ENDED` ago (not committed)."""
    cutoff = (now or utcnow()) - KEEP_ENDED
    session.execute(
        delete(DashboardSession).where(
            or_(DashboardSession.expires_at < cutoff, DashboardSession.revoked_at < cutoff)
        )
    )
