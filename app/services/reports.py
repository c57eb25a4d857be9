"""The data of an inspection's report (:mod:`app.report`): its target, capture record,
calibrations and templates.

The route gives the inspection's API document; this gathers what else the report shows from the
database, the inspection's inputs and its artifact folder, and never fails for want of the
optional parts (no templates when the meshes cannot be cut, no camera serials for a bundle that
records none: the report says "not recorded", it is still printed).
"""

from __future__ import annotations

import hashlib
import json
import logging
import zipfile
from collections.abc import Callable
from datetime import UTC, datetime
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path
from typing import Any

from sqlalchemy import select
from sqlalchemy.orm import Session

from app.models import Calibration, Inspection, LightCalibration, Target
from app.plate_frame import frame_places
from app.report import ReportData, build_report
from app.services.plate_maps import NoPlateMap, plate_map_of
from app.services.stations import capture_bundles, read_stations
from app.storage import Storage
from pipeline.judge.plate_map import PlateMap
from pipeline.judge.sections import Section, load_sections

log = logging.getLogger(__name__)

#: Frame spacing of the report's virtual templates, mm (the dashboard's default).
REPORT_SPACING_MM = 700.0


#: Most uploaded calibrations compared with a bundle's to name it.
CALIBRATIONS_COMPARED = 200


def inspection_report(
    *,
    session: Session,
    storage: Storage,
    row: Inspection,
    document: dict[str, Any],
    yard: str | None = None,
) -> bytes:
    """The PDF report of a done inspection (``document``: its API document as JSON; ``yard``: the
    yard's name, printed in every page's header)."""
    capture, calibration = _capture_and_calibration(storage, row)
    details = _json_file(storage.artifacts_dir(row.id) / "details.json")
    sections, places = _sections(storage, row.id)
    light = (
        session.get(LightCalibration, row.light_calibration_id)
        if row.light_calibration_id is not None
        else None
    )
    data = ReportData(
        inspection=document,
        artifacts_dir=storage.artifacts_dir(row.id),
        target=_target(session, storage, row),
        light_calibration=None
        if light is None
        else {"id": light.id, "rms": light.rms, "file_name": light.file_name},
        software_version=_software_version(),
        printed_at=datetime.now(UTC),
        sections=sections,
        template_places=places,
        template_spacing_mm=REPORT_SPACING_MM,
        plate_map=_plate_map(storage, row),
        yard=yard,
        capture=capture,
        stereo_calibration=_stereo_calibration(session, calibration),
        details=details,
        stations=read_stations(storage.artifacts_dir(row.id), details),
    )
    return build_report(data)


def _json_file(path: Path) -> dict[str, Any] | None:
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    return doc if isinstance(doc, dict) else None


def _target(session: Session, storage: Storage, row: Inspection) -> dict[str, Any] | None:
    """The target document the inspection was judged against: its inputs' target.json, else the
    plate's target row it names."""
    if row.target_path:
        doc = _json_file(storage.absolute(row.target_path))
        if doc is not None:
            return doc
    target = session.get(Target, row.target_id) if row.target_id is not None else None
    return target.document if target is not None else None


def _capture_and_calibration(
    storage: Storage, row: Inspection
) -> tuple[dict[str, Any] | None, dict[str, Any] | None]:
    """The bundle's capture.json (for its acquisition record) and its stereo calibration document,
    from the bundle folder or .zip of the inspection's inputs (station 0's of a plate measured at
    stations); None where unreadable."""
    if not row.capture_path:
        return None, None
    bundles = capture_bundles(storage.absolute(row.capture_path))
    if not bundles:
        return None, None
    bundle = bundles[0]
    try:
        if bundle.is_dir():
            capture = _json_file(bundle / "capture.json")
            return capture, _calibration_doc(capture, lambda name: (bundle / name).read_bytes())
        with zipfile.ZipFile(bundle) as zf:
            names = [n for n in zf.namelist() if n.rsplit("/", 1)[-1] == "capture.json"]
            if not names:
                return None, None
            name = min(names, key=lambda n: n.count("/"))
            prefix = name[: -len("capture.json")]
            capture = json.loads(zf.read(name))
            return capture, _calibration_doc(capture, lambda n: zf.read(prefix + n))
    except (OSError, ValueError, KeyError, zipfile.BadZipFile) as err:
        log.warning("inspection %s: report without the bundle's record: %s", row.id, err)
        return None, None


def _calibration_doc(
    capture: dict[str, Any] | None, read: Callable[[str], bytes]
) -> dict[str, Any] | None:
    """The capture's calibration: given inline, or the bundle's file it names (``read`` reads a
    file of the bundle by its relative name)."""
    value = (capture or {}).get("calibration")
    if isinstance(value, dict):
        return value
    if isinstance(value, str) and not value.startswith("/") and ".." not in value.split("/"):
        doc = json.loads(read(value))
        return doc if isinstance(doc, dict) else None
    return None


def _digest(doc: dict[str, Any]) -> str:
    return hashlib.sha256(json.dumps(doc, sort_keys=True).encode()).hexdigest()


def _stereo_calibration(session: Session, document: dict[str, Any] | None) -> dict[str, Any] | None:
    """``{"id", "created_at", "rms_px", "sha256"}`` of the bundle's calibration: the id and
    upload time of the uploaded calibration with the same content, if any."""
    if document is None:
        return None
    digest = _digest(document)
    rows = session.scalars(
        select(Calibration).order_by(Calibration.id.desc()).limit(CALIBRATIONS_COMPARED)
    )
    match = next((r for r in rows if _digest(r.document) == digest), None)
    return {
        "id": None if match is None else match.id,
        "created_at": None if match is None else match.created_at,
        "rms_px": document.get("rms_px"),
        "sha256": digest,
    }


def _sections(storage: Storage, inspection_id: int) -> tuple[list[Section], list[str]]:
    """The virtual templates at the report's spacing (and through every defect) with each one's
    place in the target's frame ("x = −803 mm, 697 mm from edge D"; none without a registration);
    no templates when the meshes cannot be cut (the report says less, it is still printed)."""
    folder = storage.artifacts_dir(inspection_id)
    try:
        frame, sections, _tol = load_sections(folder, spacing_mm=REPORT_SPACING_MM)
    except (OSError, ValueError, KeyError) as err:
        log.warning("inspection %s: report without templates: %s", inspection_id, err)
        return [], []
    places = frame_places(folder, frame, sections)
    # the report's Helvetica has no U+2212: an ASCII minus, as in its other tables
    return sections, [] if places is None else [p.where.replace("\u2212", "-") for p in places]


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
