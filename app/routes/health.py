"""Liveness: ``GET /healthz``."""

from __future__ import annotations

from fastapi import APIRouter
from sqlalchemy import text

from app.deps import SessionDep
from app.schemas import Health
from app.services.inspections import count_by_status

router = APIRouter(tags=["health"])


@router.get("/healthz", response_model=Health)
def healthz(session: SessionDep):
    session.execute(text("SELECT 1"))
    counts = count_by_status(session=session)
    return Health(status="ok", database="ok", queued=counts.get("queued", 0), running=counts.get("running", 0))
