"""The deviation map of an inspection in the plate's own frame (mm axes): JSON for reading values,
PNG for drawing (:mod:`app.services.plate_maps`)."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter
from fastapi.responses import Response
from sqlalchemy.orm import Session

from app.deps import SessionDep, StorageDep
from app.errors import ApiError
from app.models import Inspection
from app.routes.common import InspectionIdPath, defects_and_reasons
from app.schemas import ErrorOut, PlateMapOut
from app.services import inspections as svc
from app.services.plate_maps import NoPlateMap, plate_map_document, plate_map_of, plate_map_png
from app.services.stations import read_stations
from app.storage import Storage
from pipeline.judge.plate_map import PlateMap

router = APIRouter(tags=["inspections"])

_ERRORS: dict[int | str, dict[str, Any]] = {404: {"model": ErrorOut}, 409: {"model": ErrorOut}}


def _map_of(session: Session, storage: Storage, inspection_id: int) -> tuple[Inspection, PlateMap]:
    row = svc.get_inspection(session=session, inspection_id=inspection_id)
    if row is None:
        raise ApiError(404, f"inspection_id: no inspection {inspection_id}", field="inspection_id")
    try:
        return row, plate_map_of(storage, row)
    except NoPlateMap as err:
        raise ApiError(409, f"inspection_id: {err}", field="inspection_id") from None


def _tolerance(row: Inspection) -> float:
    """The tolerance a done inspection was judged with (every done inspection records one)."""
    if row.tolerance_mm is None:
        raise ApiError(
            409, f"inspection_id: inspection {row.id} records no tolerance", field="inspection_id"
        )
    return float(row.tolerance_mm)


@router.get("/inspections/{inspection_id}/plate-map", response_model=PlateMapOut, responses=_ERRORS)
def get_plate_map(
    inspection_id: InspectionIdPath, session: SessionDep, storage: StorageDep
) -> dict[str, Any]:
    """The deviation map in the target's own frame: mean deviation in square cells of its x and y,
    mm, the defects at their places, and a plate measured at stations' stations with their outlines.
    Only a done inspection has one (409 otherwise)."""
    row, plate = _map_of(session, storage, inspection_id)
    defects = defects_and_reasons(storage, row, ["details.json"])["defects"]
    stations = read_stations(storage.artifacts_dir(row.id))
    return plate_map_document(
        plate, tolerance_mm=_tolerance(row), defects=defects, stations=stations
    )


@router.get(
    "/inspections/{inspection_id}/plate-map.png",
    response_class=Response,
    responses={200: {"content": {"image/png": {}}, "description": "one pixel per cell"}, **_ERRORS},
)
def get_plate_map_png(
    inspection_id: InspectionIdPath, session: SessionDep, storage: StorageDep
) -> Response:
    """The map coloured by tolerance band (within: one calm green; beyond: orange to red above the
    target, light to dark blue below), one pixel per cell, x to the right and y up."""
    row, plate = _map_of(session, storage, inspection_id)
    png = plate_map_png(plate, tolerance_mm=_tolerance(row))
    return Response(png, media_type="image/png", headers={"Cache-Control": "private, max-age=300"})
