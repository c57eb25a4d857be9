"""Request body size limit: 413 with a JSON message, before and while the body is read."""

from __future__ import annotations

import json

from starlette.types import ASGIApp, Message, Receive, Scope, Send

from app.errors import ApiError


def _too_large(max_bytes: int) -> tuple[str, str]:
    return (
        f"request body: expected at most {max_bytes} bytes ({max_bytes / 2**20:.3g} MiB), got more",
        "body",
    )


class BodySizeLimit:
    """ASGI middleware refusing request bodies over ``max_bytes`` with 413 and a JSON body.

    A declared ``Content-Length`` over the limit is refused before anything is read; a body
    without one (chunked) is counted as it streams, and reading past the limit raises a 413
    :class:`~app.errors.ApiError` (answered by the app's error handler).
    """

    def __init__(self, app: ASGIApp, *, max_bytes: int) -> None:
        if max_bytes <= 0:
            raise ValueError(f"max_bytes: expected a positive size, got {max_bytes}")
        self.app = app
        self.max_bytes = max_bytes

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        declared = dict(scope.get("headers") or []).get(b"content-length")
        if declared is not None and declared.isdigit() and int(declared) > self.max_bytes:
            detail, field = _too_large(self.max_bytes)
            body = json.dumps({"detail": detail, "field": field}).encode()
            await send(
                {
                    "type": "http.response.start",
                    "status": 413,
                    "headers": [
                        (b"content-type", b"application/json"),
                        (b"content-length", str(len(body)).encode()),
                        (b"connection", b"close"),
                    ],
                }
            )
            await send({"type": "http.response.body", "body": body})
            return
        received = 0

        async def limited_receive() -> Message:
            nonlocal received
            message = await receive()
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                if received > self.max_bytes:
                    detail, field = _too_large(self.max_bytes)
                    raise ApiError(413, detail, field=field)
            return message

        await self.app(scope, limited_receive, send)
