"""The data of an inspection's report (:mod:`app.report`): its target, light calibration and templates.

The route gives the inspection's API document; this gathers what else the report shows from the
database and the artifact folder, and never fails for want of the optional parts (no templates when
the meshes cannot be cut: the report says less, it is still printed).
"""

from __future__ import annotations

import logging
from datetime import UTC, datetime
from importlib.metadata import PackageNotFoundError, version
from typing import Any

from sqlalchemy.orm import Session

from app.models import Inspection, LightCalibration, Target
from app.report import ReportData, build_report
from app.services.plate_maps import NoPlateMap, plate_map_of
from app.storage import Storage
from pipeline.plate_map import PlateMap
from pipeline.sections import Section, load_sections

log = logging.getLogger(__name__)

#: Frame spacing of the report's virtual templates, mm (the dashboard's default).
REPORT_SPACING_MM = 700.0


def inspection_report(
    *, session: Session, storage: Storage, row: Inspection, document: dict[str, Any]
) -> bytes:
    """The PDF report of a done inspection (``document``: its API document as JSON)."""
    target = session.get(Target, row.target_id) if row.target_id is not None else None
    light = (
        session.get(LightCalibration, row.light_calibration_id)
        if row.light_calibration_id is not None
        else None
    )
    data = ReportData(
        inspection=document,
        artifacts_dir=storage.artifacts_dir(row.id),
        target=target.document if target is not None else None,
        light_calibration=None
        if light is None
        else {"id": light.id, "rms": light.rms, "file_name": light.file_name},
        software_version=_software_version(),
        printed_at=datetime.now(UTC),
        sections=_sections(storage, row.id),
        plate_map=_plate_map(storage, row),
    )
    return build_report(data)


def _sections(storage: Storage, inspection_id: int) -> list[Section]:
    """The virtual templates at the report's spacing (and through every defect); none when the
    meshes cannot be cut (the report says less, it is still printed)."""
    try:
        _frame, sections, _tol = load_sections(
            storage.artifacts_dir(inspection_id), spacing_mm=REPORT_SPACING_MM
        )
    except (OSError, ValueError, KeyError) as err:
        log.warning("inspection %s: report without templates: %s", inspection_id, err)
        return []
    return sections


def _plate_map(storage: Storage, row: Inspection) -> PlateMap | None:
    """The deviation map in the target's frame; None (the camera's map is printed) when the
    artifacts cannot give one."""
    try:
        return plate_map_of(storage, row)
    except NoPlateMap as err:
        log.warning("inspection %s: report with the camera's map: %s", row.id, err)
        return None


def _software_version() -> str:
    try:
        return version("plate-inspect")
    except PackageNotFoundError:
        return "unknown"
