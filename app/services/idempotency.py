"""Idempotency keys: an MES retry with the same ``Idempotency-Key`` gets the first answer again.

A key is scoped by the route (``"POST /api/v1/plates/P1/inspections"``) and the writer's token.
The first request *claims* the key (a committed "pending" row: the unique constraint makes a
concurrent twin fail), does its work, and stores its answer in the same transaction as the work.
The claim records the request's :func:`fingerprint`: a key sent again with another body is refused
(the caller answers 422 naming ``Idempotency-Key``), the same body is answered with the first answer.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Iterable
from typing import Any

from sqlalchemy import delete, select
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from app.models import IdempotencyKey

MAX_KEY_LENGTH = 255


def check_key(key: str) -> str:
    if not key or len(key) > MAX_KEY_LENGTH or not key.isprintable():
        raise ValueError(
            f"Idempotency-Key: expected 1-{MAX_KEY_LENGTH} printable characters, got {key[:40]!r}"
        )
    return key


def canonical_json(raw: bytes) -> bytes:
    """A JSON body written one way (keys sorted, no spaces), so that key order and spacing do not
    make another body; bytes that are not JSON are returned as they are."""
    try:
        doc = json.loads(raw)
    except (ValueError, RecursionError):
        return raw
    return json.dumps(doc, sort_keys=True, separators=(",", ":"), ensure_ascii=False).encode()


def fingerprint(fields: Iterable[tuple[str, str]]) -> str:
    """sha256 hex of a request body as its fields: ``(name, sha256 hex of the content)`` pairs.

    The pairs' order does not count: a multipart body with its parts in another order, or with
    another boundary, has the same fingerprint; so has a JSON body with its keys in another order.
    """
    pairs = sorted((str(name), str(digest)) for name, digest in fields)
    return hashlib.sha256(json.dumps(pairs).encode()).hexdigest()


def find(*, session: Session, key: str, scope: str, token_hash: str) -> IdempotencyKey | None:
    return session.scalars(
        select(IdempotencyKey).where(
            IdempotencyKey.key == key,
            IdempotencyKey.scope == scope,
            IdempotencyKey.token_hash == token_hash,
        )
    ).first()


def claim(
    *, session: Session, key: str, scope: str, token_hash: str, request_sha256: str | None = None
) -> tuple[IdempotencyKey, bool]:
    """Claim ``key`` for this request, or find the request that claimed it first.

    ``request_sha256`` (the request's :func:`fingerprint`) is stored with a new claim. Commits (the claim must be visible to a concurrent twin before the work starts).

    Returns
    -------
    (row, claimed)
        ``claimed`` is True when this request owns the key; otherwise ``row`` is the first
        request's: ``state == "done"`` with its answer, or ``"pending"`` while it still runs.
    """
    check_key(key)
    existing = find(session=session, key=key, scope=scope, token_hash=token_hash)
    if existing is not None:
        return existing, False
    row = IdempotencyKey(
        key=key,
        scope=scope,
        token_hash=token_hash,
        state="pending",
        request_sha256=request_sha256,
    )
    session.add(row)
    try:
        session.commit()
    except IntegrityError:
        session.rollback()
        existing = find(session=session, key=key, scope=scope, token_hash=token_hash)
        if existing is None:
            raise
        return existing, False
    return row, True


def same_request(row: IdempotencyKey, request_sha256: str | None) -> bool:
    """Whether a request of this fingerprint is the one that claimed ``row`` (a claim stored
    without a fingerprint, before migration 0010, matches any)."""
    return (
        row.request_sha256 is None or request_sha256 is None or row.request_sha256 == request_sha256
    )


def stored_answer(row: IdempotencyKey) -> tuple[int, dict[str, Any] | None] | None:
    """The answer recorded for the key (status code, JSON body), or None while its first request runs."""
    if row.state != "done" or row.status_code is None:
        return None
    return row.status_code, row.body


def record(*, session: Session, row_id: int, status_code: int, body: dict[str, Any]) -> None:
    """Store the answer of the request that claimed the key (caller commits)."""
    row = session.get(IdempotencyKey, row_id)
    if row is None:
        raise LookupError(f"idempotency key row {row_id}: not found")
    row.state = "done"
    row.status_code = int(status_code)
    row.body = body
    session.flush()


def release(*, session: Session, row_id: int) -> None:
    """Forget a claim whose request failed by a bug (a retry may then try again; caller commits)."""
    session.execute(delete(IdempotencyKey).where(IdempotencyKey.id == row_id))
