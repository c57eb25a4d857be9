"""Security headers on every response: Content-Security-Policy, X-Frame-Options, nosniff, Referrer-Policy.

:class:`SecurityHeaders` adds to every HTTP response the headers it does not set itself:

- ``Content-Security-Policy``: :data:`DASHBOARD_CSP`, the dashboard's own scripts, styles and
  images only (no inline script or style, nothing from another origin), the 3D view framed from
  the same origin, and the page itself never framed;
- ``X-Frame-Options: DENY`` (the same, for browsers without ``frame-ancestors``);
- ``X-Content-Type-Options: nosniff``;
- ``Referrer-Policy: same-origin`` (not ``no-referrer``: with it browsers send ``Origin: null``
  on the dashboard's own POSTs, which the cookie-write origin check must refuse).

Two pages set their own policy: the 3D view (:func:`viewer_csp`: viser's bundled client, framed by
the dashboard, so ``SAMEORIGIN``) and the API docs (:func:`docs_csp`). Both allow their inline
bootstrap script by its sha256, computed from the page served, never a blanket ``'unsafe-inline'``
for scripts.
"""

from __future__ import annotations

import base64
import hashlib
import re

from starlette.datastructures import MutableHeaders
from starlette.types import ASGIApp, Message, Receive, Scope, Send


def csp(**directives: str) -> str:
    """A policy from directives given as keywords (``script_src="'self'"`` -> ``script-src 'self'``)."""
    return "; ".join(f"{name.replace('_', '-')} {value}" for name, value in directives.items())


_COMMON = {"base_uri": "'none'", "object_src": "'none'"}
_DASHBOARD = {
    "default_src": "'self'",
    "script_src": "'self'",
    "style_src": "'self'",
    "img_src": "'self' data:",
    "connect_src": "'self'",
    "frame_src": "'self'",
    "frame_ancestors": "'none'",
    "form_action": "'self'",
    **_COMMON,
}

#: Every page and answer of the service, unless it sets its own.
DASHBOARD_CSP = csp(**_DASHBOARD)
#: Headers of a page the dashboard frames (the 3D view's messages; its client page adds its own CSP).
FRAMED_HEADERS = {
    "Content-Security-Policy": csp(**{**_DASHBOARD, "frame_ancestors": "'self'"}),
    "X-Frame-Options": "SAMEORIGIN",
}

#: Headers added to every HTTP response that has none of its own.
DEFAULT_HEADERS = {
    "Content-Security-Policy": DASHBOARD_CSP,
    "X-Frame-Options": "DENY",
    "X-Content-Type-Options": "nosniff",
    "Referrer-Policy": "same-origin",
}

_INLINE_SCRIPT = re.compile(
    rb"<script(?![^>]*\bsrc=)[^>]*>(.*?)</script>", re.DOTALL | re.IGNORECASE
)


def inline_script_hashes(html: bytes) -> list[str]:
    """CSP hash sources (``'sha256-...'``) of the inline scripts of a page, in order."""
    return [
        f"'sha256-{base64.b64encode(hashlib.sha256(body).digest()).decode()}'"
        for body in _INLINE_SCRIPT.findall(html)
    ]


def viewer_csp(page: bytes) -> str:
    """The policy of viser's bundled client page ``page`` (the 3D view, framed by the dashboard).

    Its inline loader (allowed by hash) unpacks the client with WebAssembly and inserts it as a
    script of its own (``'strict-dynamic'`` trusts scripts a trusted one inserts; no other
    script runs). The client needs ``'unsafe-eval'``: the bindings of its WebAssembly modules
    (Emscripten embind) build functions from strings, and it compiles WebAssembly. It styles
    itself inline (Mantine, so ``style-src 'unsafe-inline'``), draws textures from
    ``blob:``/``data:`` URLs, and talks to the websocket bridge on this origin.
    """
    return csp(
        default_src="'self'",
        script_src=" ".join([*inline_script_hashes(page), "'strict-dynamic'", "'unsafe-eval'"]),
        style_src="'self' 'unsafe-inline'",
        img_src="'self' data: blob:",
        font_src="'self' data:",
        connect_src="'self' data: blob:",
        worker_src="'self' blob:",
        frame_ancestors="'self'",
        form_action="'none'",
        **_COMMON,
    )


def docs_csp(page: bytes) -> str:
    """The policy of the Swagger UI page ``page`` (/docs): its files, its inline start script by hash."""
    return csp(
        default_src="'self'",
        script_src=" ".join(["'self'", *inline_script_hashes(page)]),
        style_src="'self' 'unsafe-inline'",
        img_src="'self' data:",
        connect_src="'self'",
        frame_ancestors="'none'",
        form_action="'self'",
        **_COMMON,
    )


class SecurityHeaders:
    """ASGI middleware adding :data:`DEFAULT_HEADERS` a response does not set itself.

    Install it outermost (around Starlette's error middleware) so that 500 answers get them too.
    """

    def __init__(self, app: ASGIApp):
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return

        async def send_with_headers(message: Message) -> None:
            if message["type"] == "http.response.start":
                headers = MutableHeaders(scope=message)
                for name, value in DEFAULT_HEADERS.items():
                    headers.setdefault(name, value)
            await send(message)

        await self.app(scope, receive, send_with_headers)
