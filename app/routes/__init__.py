"""Thin routers, one per resource, gathered under ``/api/v1``."""

from fastapi import APIRouter, Depends

from app.routes import (
    calibrations,
    forming,
    inspections,
    light_calibrations,
    plate_maps,
    plates,
    session,
)
from app.routes.common import API_PREFIX, request_fingerprint

api_router = APIRouter(prefix=API_PREFIX, dependencies=[Depends(request_fingerprint)])
api_router.include_router(inspections.router)
api_router.include_router(plates.router)
api_router.include_router(calibrations.router)
api_router.include_router(light_calibrations.router)
api_router.include_router(session.router)
api_router.include_router(forming.router)
api_router.include_router(plate_maps.router)

__all__ = ["api_router"]
