"""The FastAPI application: ``create_app()``.

The web process serves the REST API (``/api/v1``, OpenAPI at ``/docs``), ``/healthz``, and the
operator dashboard (``web.routes.router``, static files at ``/static``) when it is installed. The
pipeline runs elsewhere (:mod:`app.worker`); this process only queues job ids. Every response
carries the security headers of :mod:`app.security_headers`.
"""

from __future__ import annotations

import importlib
import logging
import secrets
from collections.abc import AsyncIterator
from contextlib import AsyncExitStack, asynccontextmanager
from types import ModuleType

from fastapi import FastAPI, Request
from fastapi.openapi.docs import get_swagger_ui_html
from fastapi.responses import HTMLResponse
from fastapi_offline import FastAPIOffline
from pydantic import SecretStr

from app.db import make_engine, make_session_factory, upgrade_database
from app.errors import install_error_handlers
from app.jobs import JobQueue
from app.limits.body import BodySizeLimit
from app.openapi import install_openapi
from app.routes import api_router
from app.routes.health import router as health_router
from app.security_headers import SecurityHeaders, docs_csp
from app.services.camera_monitor import CameraMonitor
from app.services.cell import ensure_demo_cell
from app.settings import Settings
from app.storage import Storage
from app.throttle import TokenThrottle

#: Where FastAPIOffline serves Swagger UI's files.
DOCS_STATIC_URL = "/static-docs"

log = logging.getLogger(__name__)


def resolve_token(settings: Settings) -> tuple[Settings, str]:
    """Settings with an API token (the configured one, or a generated one in demo mode), and the token.

    Raises
    ------
    ValueError
        No token configured and not in demo mode.
    """
    if settings.api_token is not None:
        if not settings.api_token.get_secret_value().strip():
            raise ValueError(
                "PLATE_INSPECT_API_TOKEN: expected a non-empty token, got an empty string"
            )
        return settings, settings.api_token.get_secret_value()
    if not settings.demo:
        raise ValueError(
            "PLATE_INSPECT_API_TOKEN: expected a token for writes (or demo mode, which generates one), got none"
        )
    token = secrets.token_urlsafe(24)
    return settings.model_copy(update={"api_token": SecretStr(token)}), token


def create_app(settings: Settings | None = None) -> FastAPI:
    """Build the web application.

    Parameters
    ----------
    settings : Settings, optional
        Defaults to ``Settings()`` (the ``PLATE_INSPECT_*`` environment). Without an API token,
        demo mode generates one (``app.state.settings.api_token``); otherwise a ValueError.

    Notes
    -----
    When the app is built (before any request, also under a TestClient without lifespan) the
    database is brought to the current schema with Alembic. On start (lifespan) the viewer hook
    ``app.viewer.attach(app, settings)`` runs if that module exists; what it returns is closed at
    shutdown (an async context manager is exited, else its ``close()`` is called). ``app.state`` holds ``settings``, ``api_token``,
    ``engine``, ``session_factory``, ``storage``, ``jobs`` (:class:`app.jobs.JobQueue`),
    ``token_throttle`` (:class:`app.throttle.TokenThrottle`) and ``cell``
    (:class:`app.services.camera_monitor.CameraMonitor`). In demo mode without a cell config the demo cell is
    written under the data dir (:func:`app.services.cell.ensure_demo_cell`).
    """
    settings, api_token = resolve_token(settings or Settings())
    storage = Storage(settings.data_dir)

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        async with AsyncExitStack() as stack:
            viewer = _optional_module("app.viewer")
            if viewer is not None and hasattr(viewer, "attach"):
                hook = viewer.attach(app, settings)
                if hasattr(hook, "__aenter__"):
                    await stack.enter_async_context(hook)
                elif hasattr(hook, "close"):
                    stack.callback(hook.close)
            yield
        app.state.engine.dispose()

    # Swagger UI's files from the fastapi-offline wheel: the cell's network is closed (FastAPI's own
    # /docs page loads them from a CDN). The /docs page itself is ours (_include_docs: it needs its
    # CSP). No ReDoc page (it would fetch web fonts).
    app = FastAPIOffline(
        title="plate-inspect",
        version="1",
        summary="Forming inspection of curved hull plates: inspections, results and targets for the MES.",
        lifespan=lifespan,
        docs_url=None,
        redoc_url=None,
        static_url=DOCS_STATIC_URL,
        swagger_ui_parameters={"validatorUrl": None},  # no badge fetched from an outside validator
    )
    app.add_middleware(BodySizeLimit, max_bytes=settings.max_upload_bytes)
    # Outermost, around Starlette's error middleware: a 500 answer gets the headers too.
    build_stack = app.build_middleware_stack
    # (FastAPIOffline builds a FastAPI instance: no subclass to override the method in.)
    app.build_middleware_stack = lambda: SecurityHeaders(build_stack())  # type: ignore[method-assign]
    # The database is ready before the first request (also under TestClient without lifespan).
    storage.ensure()
    ensure_demo_cell(settings)
    upgrade_database(settings.sqlalchemy_url)
    engine = make_engine(settings.sqlalchemy_url)
    app.state.settings = settings
    app.state.api_token = api_token
    app.state.engine = engine
    app.state.session_factory = make_session_factory(engine)
    app.state.storage = storage
    app.state.jobs = JobQueue(settings, app.state.session_factory, storage)
    app.state.cell = CameraMonitor(settings)
    app.state.token_throttle = TokenThrottle(
        free_failures=settings.login_free_failures,
        window_s=settings.login_window_s,
        max_delay_s=settings.login_max_delay_s,
    )

    install_error_handlers(app)
    install_openapi(app)
    app.include_router(health_router)
    app.include_router(api_router)
    _include_docs(app)
    _include_dashboard(app)
    return app


def _include_docs(app: FastAPI) -> None:
    """``/docs``: Swagger UI from local files, its inline start script allowed by its hash."""

    @app.get("/docs", include_in_schema=False)
    def swagger_ui(request: Request) -> HTMLResponse:
        root = request.scope.get("root_path", "")
        page = get_swagger_ui_html(
            openapi_url=f"{root}{app.openapi_url}",
            title=f"{app.title} - Swagger UI",
            swagger_js_url=f"{root}{DOCS_STATIC_URL}/swagger-ui-bundle.js",
            swagger_css_url=f"{root}{DOCS_STATIC_URL}/swagger-ui.css",
            swagger_favicon_url=f"{root}{DOCS_STATIC_URL}/favicon.png",
            oauth2_redirect_url=None,
            swagger_ui_parameters=app.swagger_ui_parameters,
        )
        return HTMLResponse(
            page.body, headers={"Content-Security-Policy": docs_csp(bytes(page.body))}
        )


def _optional_module(name: str) -> ModuleType | None:
    """Import ``name`` if it exists (the dashboard is developed apart); errors inside it propagate."""
    try:
        return importlib.import_module(name)
    except ModuleNotFoundError as err:
        if err.name is not None and (name == err.name or name.startswith(err.name + ".")):
            return None
        raise


def _include_dashboard(app: FastAPI) -> None:
    from fastapi.staticfiles import StaticFiles

    routes = _optional_module("web.routes")
    if routes is not None and hasattr(routes, "router"):
        app.include_router(routes.router)
        app.state.html_error_page = getattr(routes, "error_page", None)
    static_dir = getattr(_optional_module("web"), "STATIC_DIR", None)
    if static_dir is not None and static_dir.is_dir():
        app.mount("/static", StaticFiles(directory=static_dir), name="static")
