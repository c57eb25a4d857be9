"""The dashboard's pages (server-rendered, Jinja2): cell, inspection result, plate history, calibration,
machines.

Pages read through the service functions (:mod:`app.services`); the browser writes through
the REST API (``/api/v1``) from plain JS modules, with the dashboard's session cookie. In
demo mode every page hands out that cookie; otherwise the operator logs in once with the
API token (``/login``).
"""

from __future__ import annotations

import json
import logging
from datetime import UTC, datetime
from typing import Annotated, Any, Literal

from fastapi import APIRouter, HTTPException, Query, Request
from fastapi.responses import FileResponse, HTMLResponse, RedirectResponse, Response
from fastapi.templating import Jinja2Templates
from sqlalchemy.orm import Session

from app import viewer
from app.deps import SessionDep, StorageDep, has_dashboard_session, start_dashboard_session
from app.errors import scrub_paths
from app.models import ACTIVE, FINISHED, Inspection, JobStatus, Target
from app.routes.common import InspectionIdPath, defects_and_reasons
from app.services import calibrations as calibration_svc
from app.services import cell as cell_svc
from app.services import forming as forming_svc
from app.services import inspections as inspection_svc
from app.services import light_calibrations as light_calibration_svc
from app.services import plates as plate_svc
from app.services.stations import read_stations
from app.storage import Storage
from web import TEMPLATES_DIR
from web.charts import FormingChart, forming_chart, trend_chart
from web.compare import CannotCompare, compare_context, done_inspections
from web.forming_words import advice_panel, count
from web.lights import light_plan, light_rows
from web.template_views import (
    DEFAULT_SPACING_MM,
    SPACINGS_MM,
    PointQuery,
    SpacingQuery,
    chosen_point,
    templates_context,
)

logger = logging.getLogger(__name__)

router = APIRouter(include_in_schema=False)
router.include_router(viewer.router)
templates = Jinja2Templates(directory=TEMPLATES_DIR)


def _fmt(value: float | None, digits: int = 1, unit: str = "", signed: bool = False) -> str:
    if value is None:
        return "—"
    if round(value, digits) == 0:
        value = 0.0  # never "-0.00"
    text = f"{value:+.{digits}f}" if signed else f"{value:.{digits}f}"
    return f"{text} {unit}".strip()


templates.env.filters["fmt"] = _fmt
templates.env.filters["count"] = count


def _when(dt: datetime | None) -> str:
    """A stored time as UTC with its zone said (SQLite gives naive UTC times, PostgreSQL aware ones)."""
    if dt is None:
        return "—"
    aware = dt if dt.tzinfo is not None else dt.replace(tzinfo=UTC)
    return aware.astimezone(UTC).strftime("%Y-%m-%d %H:%M:%S UTC")


templates.env.filters["when"] = _when


def _page(
    request: Request,
    session: Session,
    name: str,
    context: dict[str, Any],
    *,
    status_code: int = 200,
) -> Response:
    """Render a full page: the side list (plates, jobs) plus the page's own context."""
    settings = request.app.state.settings
    signed_in = has_dashboard_session(request, db=session)
    response = templates.TemplateResponse(
        request,
        name,
        {
            **_side_context(session),
            "demo": settings.demo,
            "signed_in": signed_in or settings.demo,
            **context,
        },
        status_code=status_code,
    )
    if settings.demo and not signed_in:
        start_dashboard_session(response, request, db=session)
    return response


#: Plates per page of the side list.
SIDE_PLATES = 40


def _side_context(session: Session, search: str | None = None, page: int = 0) -> dict[str, Any]:
    """The side lists: active jobs (all of them, up to 20) and a page of the plates (40 at a time,
    the most recently inspected first, or those whose id contains ``search``)."""
    plates, plate_total = plate_svc.list_plates(
        session=session, limit=SIDE_PLATES, offset=page * SIDE_PLATES, search=search or None
    )
    jobs, job_total = inspection_svc.list_inspections(session=session, statuses=ACTIVE, limit=20)
    return {
        "side_plates": plates,
        "side_plate_total": plate_total,
        "side_jobs": jobs,
        "side_job_total": job_total,
        "side_search": search or "",
        "side_page": page,
        "side_pages": max(1, -(-plate_total // SIDE_PLATES)),
        "side_first": page * SIDE_PLATES + 1,
    }


@router.get("/side", response_class=HTMLResponse)
def side_lists(
    request: Request,
    session: SessionDep,
    current: str | None = None,
    q: Annotated[str | None, Query(max_length=64)] = None,
    page: Annotated[int, Query(ge=0, le=100_000)] = 0,
) -> Response:
    """The side lists alone (polled by layout.js on every page); ``current`` is the page's plate,
    ``q`` the plate search, ``page`` the page of plates (0: the most recent)."""
    return templates.TemplateResponse(
        request, "_side_body.html", {**_side_context(session, q, page), "current_plate": current}
    )


def error_page(request: Request, status_code: int, detail: str) -> Response | None:
    """An error (404, 500, ...) as a page in the dashboard's layout (app.errors calls it for a browser
    navigating to a page); None when the page cannot be drawn (the database down): the JSON error."""
    try:
        with request.app.state.session_factory() as session:
            return _page(
                request,
                session,
                "error.html",
                {
                    "page": "error",
                    "status_code": status_code,
                    "detail": scrub_paths(detail),
                    "now": datetime.now(UTC),
                },
                status_code=status_code,
            )
    except Exception:
        logger.exception("could not draw the error page for %s", request.url.path)
        return None


def _inspection_or_404(session: Session, inspection_id: int) -> Inspection:
    row = inspection_svc.get_inspection(session=session, inspection_id=inspection_id)
    if row is None:
        raise HTTPException(404, f"inspection {inspection_id} not found")
    return row


@router.get("/")
def home() -> RedirectResponse:
    return RedirectResponse("/cell", status_code=303)


@router.get("/cell", response_class=HTMLResponse)
def cell_page(request: Request, session: SessionDep) -> Response:
    """Start an inspection (simulated, uploaded, or captured by the cell); the cameras; the queue with live progress."""
    recent, _ = inspection_svc.list_inspections(session=session, limit=12)
    return _page(
        request,
        session,
        "cell.html",
        {"page": "cell", "queue": recent, **_cameras_context(request)},
    )


@router.get("/cell/cameras", response_class=HTMLResponse)
def cell_cameras(request: Request) -> Response:
    """The cameras panel (polled by cell.js)."""
    return templates.TemplateResponse(request, "_cameras.html", _cameras_context(request))


@router.get("/cell/cameras/{side}.png", response_class=FileResponse)
def camera_thumbnail(request: Request, side: Literal["left", "right"]) -> Response:
    """The last frame of a camera (its image of the last capture's stereo pair), reduced."""
    path = cell_svc.thumbnail_path(request.app.state.settings.data_dir, side)
    if path is None:
        raise HTTPException(404, f"side: the {side} camera has taken no frame yet")
    return FileResponse(path, media_type="image/png", headers={"Cache-Control": "no-cache"})


def _cameras_context(request: Request) -> dict[str, Any]:
    """The cell's state, and whether its last capture's thumbnails are of this cell's cameras."""
    cell = request.app.state.cell.state()
    last = cell.last_capture or {}
    thumbnails = cell.ready and last.get("cell_id") == cell.cell_id
    return {"cell": cell, "thumbnails_of": last.get("inspection_id") if thumbnails else None}


@router.get("/cell/queue", response_class=HTMLResponse)
def cell_queue(request: Request, session: SessionDep) -> Response:
    """The queue table's rows (polled by cell.js)."""
    recent, _ = inspection_svc.list_inspections(session=session, limit=12)
    return templates.TemplateResponse(request, "_queue.html", {"queue": recent})


@router.get("/inspections/{inspection_id}", response_class=HTMLResponse)
def result_page(
    request: Request,
    inspection_id: InspectionIdPath,
    session: SessionDep,
    storage: StorageDep,
    spacing_mm: SpacingQuery = DEFAULT_SPACING_MM,
    at_x: PointQuery = None,
    at_y: PointQuery = None,
) -> Response:
    """Verdict, radius, deviation, the 3D view, the stations of a plate measured at stations and the
    virtual templates of one inspection (``at_x``, ``at_y``: one more template through that point of
    the plate, target frame, mm)."""
    row = _inspection_or_404(session, inspection_id)
    plate_viewer = getattr(request.app.state, "viewer", None)
    has_view = (
        row.status == JobStatus.DONE
        and plate_viewer is not None
        and plate_viewer.has_view(inspection_id)
    )
    finished = row.status in FINISHED  # a running job's folder holds partial files
    names = inspection_svc.artifact_names(storage=storage, inspection=row) if finished else []
    found = defects_and_reasons(storage, row, names)
    target_doc = _judged_target(session, storage, row)
    context = {
        "page": "result",
        "row": row,
        "result": row.result or {},
        "has_view": has_view,
        "artifacts": names,
        "spacing_mm": spacing_mm,
        "spacings": SPACINGS_MM,
        "trace": {k: target_doc[k] for k in ("drawing", "hull", "block") if target_doc.get(k)},
        "next_pass": advice_panel(
            session, row.plate_id, row if row.status == JobStatus.DONE else None, target_doc
        ),
        **found,
        "stations": read_stations(storage.artifacts_dir(row.id)) if "details.json" in names else [],
        **templates_context(storage, row, spacing_mm, chosen_point(at_x, at_y)),
    }
    return _page(request, session, "result.html", context)


def _judged_target(session: Session, storage: Storage, row: Inspection) -> dict[str, Any]:
    """The target document the inspection was judged against (the plate's stored target, else the
    inputs' target.json, else a simulated bundle's); empty when none is readable."""
    target = session.get(Target, row.target_id) if row.target_id is not None else None
    if target is not None:
        return target.document or {}
    paths = [storage.absolute(row.target_path)] if row.target_path else []
    if row.capture_path:  # a simulated bundle carries the target it was rendered for
        paths.append(storage.absolute(row.capture_path) / "target.json")
    for path in paths:
        try:
            doc = json.loads(path.read_text())
        except (OSError, ValueError):
            continue
        if isinstance(doc, dict):
            return doc
    return {}


@router.get("/inspections/{inspection_id}/templates", response_class=HTMLResponse)
def templates_partial(
    request: Request,
    inspection_id: InspectionIdPath,
    session: SessionDep,
    storage: StorageDep,
    spacing_mm: SpacingQuery = DEFAULT_SPACING_MM,
    at_x: PointQuery = None,
    at_y: PointQuery = None,
) -> Response:
    """The virtual templates at another spacing, or through a point chosen on the map (result.js)."""
    row = _inspection_or_404(session, inspection_id)
    context = templates_context(storage, row, spacing_mm, chosen_point(at_x, at_y))
    return templates.TemplateResponse(
        request, "_templates.html", {"row": row, "spacing_mm": spacing_mm, **context}
    )


@router.get("/plates/{plate_id}", response_class=HTMLResponse)
def plate_page(request: Request, plate_id: str, session: SessionDep) -> Response:
    """Every inspection of a plate, with the trend of radius error and max deviation."""
    overview = plate_svc.overview(session=session, plate_id=plate_id)
    if overview is None:
        raise HTTPException(404, f"plate {plate_id!r} not found")
    rows, total = inspection_svc.list_inspections(session=session, plate_id=plate_id, limit=200)
    done = [r for r in reversed(rows) if r.status == JobStatus.DONE]
    tolerance = (
        overview.target.tolerance_mm
        if overview.target is not None
        else (done[-1].tolerance_mm if done else None)
    )
    chart = trend_chart(
        [
            (r.id, f"{k} · {_when(r.created_at)[5:16]}", r.radius_error_pct, r.max_abs_mm)
            for k, r in enumerate(done, start=1)
        ],
        tolerance_mm=tolerance,
        radius_band_pct=_radius_band_pct(overview.target),
    )
    target_doc = overview.target.document if overview.target is not None else None
    advice = advice_panel(session, plate_id, done[-1] if done else None, target_doc)
    return _page(
        request,
        session,
        "plate.html",
        {
            "page": "plate",
            "overview": overview,
            "rows": rows,
            "total": total,
            "chart": chart,
            "forming": passes_chart(session, plate_id, overview.target, advice.get("advice")),
            "plate_id": plate_id,
            "next_pass": advice,
            "done_rows": done_inspections(session, plate_id),
        },
    )


@router.get("/plates/{plate_id}/compare", response_class=HTMLResponse)
def compare_page(
    request: Request,
    plate_id: str,
    session: SessionDep,
    a: Annotated[int | None, Query(ge=1, description="the earlier inspection's id")] = None,
    b: Annotated[int | None, Query(ge=1, description="the later inspection's id")] = None,
) -> Response:
    """Two done inspections of a plate side by side (default: its last two)."""
    if plate_svc.overview(session=session, plate_id=plate_id) is None:
        raise HTTPException(404, f"plate {plate_id!r} not found")
    try:
        context = compare_context(session, plate_id, a, b)
    except CannotCompare as err:
        raise HTTPException(err.status_code, err.detail) from None
    return _page(
        request, session, "compare.html", {"page": "plate", "plate_id": plate_id, **context}
    )


def _radius_band_pct(target: Target | None) -> float | None:
    """The radius error (%) at which a cylinder target's plate leaves its tolerance at its edges:
    ``100 R 8 tol / w^2`` over the width ``w`` across the bend (None for other targets)."""
    if target is None or target.shape != "cylinder" or not target.radius_mm:
        return None
    size = (target.document or {}).get("size_mm") or []
    if not size:
        return None
    width_squared: float = float(size[0]) ** 2
    return 100.0 * target.radius_mm * 8.0 * target.tolerance_mm / width_squared


def passes_chart(
    session: Session, plate_id: str, target: Target | None, advice: dict[str, Any] | None
) -> FormingChart | None:
    """Radius after each roll-bending pass against its setting, with the target's band and the advised
    next pass; None for a plate without such passes or without a radius target."""
    passes = forming_svc.plate_passes(session=session, plate_id=plate_id)
    if not passes or target is None or not target.radius_mm:
        return None
    band, nxt = None, None
    if advice is not None:
        lo, hi = advice["basis"]["tolerance_band_radius_mm"]
        band = (lo, hi)
        if advice["action"] == "bend" and advice.get("top_roll_displacement_mm") is not None:
            # a bend without a setting (no safe move: the advice says why) draws no next pass
            nxt = (
                advice["top_roll_displacement_mm"],
                advice["expected_radius_mm"],
                tuple(advice["expected_radius_range_mm"]),
            )
    return forming_chart(
        [
            (r.id, r.process["top_roll_displacement_mm"], r.radius_mm, r.verdict)
            for r in passes
            if r.process and r.process.get("top_roll_displacement_mm") is not None
        ],
        target_radius_mm=target.radius_mm,
        band_mm=band,
        next_pass=nxt,
    )


@router.get("/calibration", response_class=HTMLResponse)
def calibration_page(request: Request, session: SessionDep) -> Response:
    """The current stereo calibration and its reprojection error, the current light calibration
    (its lights in a table and in plan); upload a new one of either."""
    current = calibration_svc.current_calibration(session=session)
    history = calibration_svc.list_calibrations(session=session, limit=10)
    light_current = light_calibration_svc.current_light_calibration(session=session)
    light_history = light_calibration_svc.list_light_calibrations(session=session, limit=10)
    context = {
        "page": "calibration",
        "current": current,
        "history": history,
        "light_current": light_current,
        "light_history": light_history,
        "light_rows": light_rows(light_current.document) if light_current is not None else [],
        "light_plan": light_plan(light_current.document) if light_current is not None else None,
    }
    return _page(request, session, "calibration.html", context)


@router.get("/machines", response_class=HTMLResponse)
def machines_page(
    request: Request,
    session: SessionDep,
    edit: Annotated[str | None, Query(max_length=64, description="a machine to edit")] = None,
) -> Response:
    """The roll benders the forming advice knows: their list, a form to add one, and the same form
    filled in to edit one (``?edit=R3-01``; an unknown id is 404)."""
    machines = forming_svc.list_machines(session=session)
    editing = next((m for m in machines if m.id == edit), None) if edit else None
    if edit and editing is None:
        raise HTTPException(404, f"edit: no machine {edit!r}")
    context = {"page": "machines", "machines": machines, "editing": editing}
    return _page(request, session, "machines.html", context)


@router.get("/login", response_class=HTMLResponse)
def login_page(request: Request, session: SessionDep) -> Response:
    """Trade the API token for the dashboard's session cookie (non-demo servers)."""
    return _page(request, session, "login.html", {"page": "login"})
