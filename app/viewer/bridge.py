"""The FastAPI side: viser's client page and the websocket bridge from the app's port to an
inspection's loopback viser server.
"""

from __future__ import annotations

import asyncio
import html
import logging
from collections.abc import AsyncIterator
from contextlib import AbstractAsyncContextManager, asynccontextmanager, suppress
from functools import cache
from pathlib import Path
from typing import TYPE_CHECKING

import viser
import websockets
from fastapi import APIRouter, FastAPI, Request, WebSocket, WebSocketDisconnect
from fastapi.responses import HTMLResponse
from starlette.concurrency import run_in_threadpool
from starlette.requests import HTTPConnection
from uvicorn.protocols.utils import ClientDisconnected
from websockets.asyncio.client import ClientConnection
from websockets.typing import Subprotocol

from app.deps import client_address, has_dashboard_session, is_loopback
from app.security_headers import FRAMED_HEADERS, viewer_csp
from app.viewer.pool import PlateViewer, ViewerBusyError

if TYPE_CHECKING:
    from app.settings import Settings

logger = logging.getLogger(__name__)

#: The websocket subprotocol viser's bundled client offers (client and server versions must match).
VISER_SUBPROTOCOL = f"viser-v{viser.__version__}"
#: Close code sent to the browser when an inspection has nothing to show.
CLOSE_NOT_FOUND = 4404
#: Close code (RFC 6455 "try again later") when every allowed viewer server is busy.
CLOSE_TRY_AGAIN_LATER = 1013


@cache
def _client_page() -> bytes:
    return (Path(viser.__file__).parent / "client" / "build" / "index.html").read_bytes()


router = APIRouter(tags=["viewer"])


def _viewer(app: FastAPI) -> PlateViewer | None:
    return getattr(app.state, "viewer", None)


@cache
def _client_page_csp() -> str:
    return viewer_csp(_client_page())


def _operator(conn: HTTPConnection) -> bool:
    """True for the operator: a client on loopback (the cell's screen) or with a valid dashboard session."""
    return is_loopback(conn) or has_dashboard_session(conn)


@router.get("/viewer/{inspection_id}/", response_class=HTMLResponse, include_in_schema=False)
def viewer_page(inspection_id: int, request: Request) -> HTMLResponse:
    """viser's bundled client page; its websocket goes to ``/viewer/{inspection_id}`` (the bridge).

    Every answer may be framed by the dashboard (same origin only); the client page gets the
    policy of :func:`app.security_headers.viewer_csp`.
    """
    viewer = _viewer(request.app)
    if viewer is None:
        return HTMLResponse(
            "<p>The 3D view is not running on this server.</p>",
            status_code=503,
            headers=FRAMED_HEADERS,
        )
    if not viewer.has_view(inspection_id):
        return HTMLResponse(
            f"<p>Inspection {inspection_id} has no surface to show.</p>",
            status_code=404,
            headers=FRAMED_HEADERS,
        )
    operator = _operator(request)
    try:
        viewer.check_capacity(inspection_id, privileged=operator)
        viewer.check_client(None if operator else client_address(request))
    except ViewerBusyError as err:
        return HTMLResponse(
            f"<p>{html.escape(str(err))}.</p>", status_code=503, headers=FRAMED_HEADERS
        )
    return HTMLResponse(
        _client_page(), headers={**FRAMED_HEADERS, "Content-Security-Policy": _client_page_csp()}
    )


@router.websocket("/viewer/{inspection_id}")
async def viewer_bridge(websocket: WebSocket, inspection_id: int) -> None:
    """Forward a browser's viser websocket to the inspection's viser server on loopback.

    The browser's socket is accepted before the inspection's server is started: viser's client
    closes a socket that is not open within 5 s (and the browser then sees 1006), and loading a
    large plate's meshes on a busy 2-core machine takes longer than that.
    """
    viewer = _viewer(websocket.app)
    if viewer is None or not viewer.has_view(inspection_id):
        await websocket.close(code=CLOSE_NOT_FOUND)
        return
    offered = websocket.scope.get("subprotocols", [])
    if VISER_SUBPROTOCOL not in offered:
        reason = f"expected subprotocol {VISER_SUBPROTOCOL}, got {offered}"
        await websocket.close(code=1002, reason=reason)
        return
    operator = is_loopback(websocket) or await run_in_threadpool(has_dashboard_session, websocket)
    client = None if operator else client_address(websocket)
    # Counted before the server starts, so that it is stopped when idle however this ends.
    try:
        viewer.bridge_opened(inspection_id, client)
    except ViewerBusyError as err:
        logger.warning("viewer: inspection %s refused to %s: %s", inspection_id, client, err)
        await websocket.close(code=CLOSE_TRY_AGAIN_LATER, reason=str(err)[:120])
        return
    try:
        await websocket.accept(subprotocol=VISER_SUBPROTOCOL)
        port = await _start_view(viewer, websocket, inspection_id, privileged=operator)
        if port is not None:
            await _relay(websocket, port)
    except (OSError, websockets.exceptions.WebSocketException) as err:
        logger.warning("viewer: bridge for inspection %s ended: %s", inspection_id, _reason(err))
    finally:
        viewer.bridge_closed(inspection_id, client)
        with suppress(RuntimeError, WebSocketDisconnect):  # the browser side is closed already
            await websocket.close()


def _reason(err: BaseException) -> str:
    """What ended a bridge, never empty (uvicorn's ClientDisconnected has no message)."""
    if isinstance(err, ClientDisconnected):
        return "the browser closed its socket"
    return f"{type(err).__name__}: {err}" if str(err) else type(err).__name__


async def _start_view(
    viewer: PlateViewer, websocket: WebSocket, inspection_id: int, *, privileged: bool
) -> int | None:
    """The port of the inspection's viser server, started if needed; None (the browser told
    why, the socket closed) if it cannot be."""
    try:
        return await run_in_threadpool(viewer.port_for, inspection_id, privileged=privileged)
    except ViewerBusyError as err:
        logger.warning("viewer: inspection %s refused: %s", inspection_id, err)
        await websocket.close(code=CLOSE_TRY_AGAIN_LATER, reason=str(err)[:120])
    except (OSError, ValueError) as err:
        logger.error("viewer: inspection %s cannot be shown: %s", inspection_id, err)
        await websocket.close(code=CLOSE_NOT_FOUND)
    return None


async def _relay(websocket: WebSocket, port: int) -> None:
    """Connect to the viser server on loopback ``port`` and copy messages until either side closes."""
    async with websockets.connect(
        f"ws://127.0.0.1:{port}",
        subprotocols=[Subprotocol(VISER_SUBPROTOCOL)],
        max_size=None,
        compression=None,
        open_timeout=10,
    ) as upstream:
        await _pump(websocket, upstream)


async def _pump(browser: WebSocket, upstream: ClientConnection) -> None:
    """Copy messages both ways until either side closes."""

    async def browser_to_viser() -> None:
        while True:
            message = await browser.receive()
            if message["type"] == "websocket.disconnect":
                return
            data = message.get("bytes")
            await upstream.send(data if data is not None else message.get("text", ""))

    async def viser_to_browser() -> None:
        async for data in upstream:
            if isinstance(data, bytes):
                await browser.send_bytes(data)
            else:
                await browser.send_text(data)

    tasks = [asyncio.create_task(browser_to_viser()), asyncio.create_task(viser_to_browser())]
    try:
        done, _pending = await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
    finally:
        for task in tasks:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
    for task in done:
        err = task.exception()
        if err is not None and not isinstance(
            err, (WebSocketDisconnect, websockets.exceptions.ConnectionClosed)
        ):
            raise err


def attach(app: FastAPI, settings: Settings) -> AbstractAsyncContextManager[PlateViewer]:
    """Create the app's 3D viewer as ``app.state.viewer``; called in the app's lifespan.

    Servers start on demand (the first browser to open an inspection's view), bound to
    loopback; ``settings.viewer_idle_s`` and ``settings.viewer_max_servers`` bound them,
    ``settings.viewer_max_sockets_per_client`` and ``settings.viewer_reserved_servers`` keep
    room for the operator. The routes (:data:`router`) are included by :mod:`web.routes`.

    Parameters
    ----------
    app : FastAPI
    settings : app.settings.Settings, its ``data_dir`` locates the artifacts.

    Returns
    -------
    An async context manager that stops every viewer server on exit (app shutdown).
    """
    from app.storage import Storage

    storage = Storage(settings.data_dir)
    viewer = PlateViewer(
        storage.artifacts_dir,
        idle_s=settings.viewer_idle_s,
        max_servers=settings.viewer_max_servers,
        max_sockets_per_client=settings.viewer_max_sockets_per_client,
        reserved_servers=settings.viewer_reserved_servers,
    )
    app.state.viewer = viewer

    @asynccontextmanager
    async def running() -> AsyncIterator[PlateViewer]:
        try:
            yield viewer
        finally:
            viewer.close()

    return running()
