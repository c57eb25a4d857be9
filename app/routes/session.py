"""Dashboard write sessions: trade the API token for an HttpOnly same-site cookie.

Browsers of the dashboard post to the API with this cookie instead of a bearer header (the token
never reaches page scripts). In demo mode the dashboard may issue the cookie itself
(:func:`app.deps.issue_session_cookie`).
"""

from __future__ import annotations

import hmac

from fastapi import APIRouter, Request, Response, status
from pydantic import BaseModel

from app.deps import SESSION_COOKIE, issue_session_cookie
from app.errors import ApiError
from app.schemas import ErrorOut

router = APIRouter(tags=["session"])


class LoginIn(BaseModel):
    token: str


@router.post("/session", status_code=status.HTTP_204_NO_CONTENT, responses={401: {"model": ErrorOut}})
def login(body: LoginIn, request: Request, response: Response):
    """Set the dashboard session cookie when ``token`` is the API token."""
    token: str = request.app.state.api_token
    if not hmac.compare_digest(body.token.encode("utf-8"), token.encode("utf-8")):
        raise ApiError(401, "token: wrong token", field="token")
    issue_session_cookie(response, token, secure=request.url.scheme == "https")
    response.status_code = status.HTTP_204_NO_CONTENT
    return response


@router.delete("/session", status_code=status.HTTP_204_NO_CONTENT)
def logout(response: Response):
    response.delete_cookie(SESSION_COOKIE, path="/")
    response.status_code = status.HTTP_204_NO_CONTENT
    return response
