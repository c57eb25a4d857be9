"""Dashboard write sessions: trade the API token for an HttpOnly same-site session cookie.

Browsers of the dashboard post to the API with this cookie instead of a bearer header (the token
never reaches page scripts). Each login opens a new server-side session (a random id, stored
hashed) that lasts ``PLATE_INSPECT_SESSION_HOURS``; logout revokes it on the server. Wrong tokens
are throttled per client address (:mod:`app.throttle`); the right one always logs in. In demo
mode the dashboard's pages open a session themselves (:func:`app.deps.start_dashboard_session`).
"""

from __future__ import annotations

from fastapi import APIRouter, Request, Response, status
from pydantic import BaseModel, Field
from starlette.concurrency import run_in_threadpool

from app.deps import SessionDep, check_token, end_dashboard_session, start_dashboard_session
from app.schemas import ErrorOut

router = APIRouter(tags=["session"])


class LoginIn(BaseModel):
    """The API token (``PLATE_INSPECT_API_TOKEN``)."""

    token: str = Field(max_length=4096)


@router.post(
    "/session",
    status_code=status.HTTP_204_NO_CONTENT,
    response_class=Response,
    responses={
        401: {"model": ErrorOut, "description": "wrong token"},
        429: {
            "model": ErrorOut,
            "description": "wrong token from an address that sent too many; see Retry-After",
        },
    },
)
async def login(body: LoginIn, request: Request, session: SessionDep) -> Response:
    """Open a dashboard session and set its cookie when ``token`` is the API token."""
    await check_token(request, body.token, field="token")
    response = Response(status_code=status.HTTP_204_NO_CONTENT)
    await run_in_threadpool(start_dashboard_session, response, request, db=session)
    return response


@router.delete("/session", status_code=status.HTTP_204_NO_CONTENT, response_class=Response)
async def logout(request: Request, session: SessionDep) -> Response:
    """End the dashboard session: revoked on the server, its cookie dropped (204 without one too)."""
    response = Response(status_code=status.HTTP_204_NO_CONTENT)
    await run_in_threadpool(end_dashboard_session, response, request, db=session)
    return response
