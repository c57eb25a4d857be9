"""Liveness: ``GET /healthz`` (the database, the queue, the cell's cameras)."""

from __future__ import annotations

from dataclasses import asdict

from fastapi import APIRouter, Request
from sqlalchemy import text

from app.deps import SessionDep
from app.schemas import CameraHealth, CellHealth, Health
from app.services.camera_monitor import CellState
from app.services.inspections import count_by_status

router = APIRouter(tags=["health"])


@router.get("/healthz", response_model=Health)
def healthz(request: Request, session: SessionDep) -> Health:
    """The database answers; jobs queued and running; the cell and its cameras (null without a cell).

    The cameras are checked at most every few seconds, in a thread that is waited for a few seconds
    at most (a camera that does not answer by then is reported unreachable); during a capture they
    are not checked and their last known state is reported.
    """
    session.execute(text("SELECT 1"))
    counts = count_by_status(session=session)
    cell = request.app.state.cell.state()
    return Health(
        status="ok",
        database="ok",
        queued=counts.get("queued", 0),
        running=counts.get("running", 0),
        cell=cell_health(cell) if cell.configured else None,
    )


def cell_health(cell: CellState) -> CellHealth:
    """The cell as ``/healthz`` reports it."""
    return CellHealth(
        ready=cell.ready,
        reason=cell.reason,
        cell_id=cell.cell_id,
        demo=cell.demo,
        in_use=cell.in_use,
        cameras=[CameraHealth(**asdict(camera)) for camera in cell.cameras],
    )
