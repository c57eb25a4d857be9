"""Inspections: created by an upload or the simulated cell, run by the job, read by the API.

The row is the source of truth of its job: ``queued -> running -> done | failed``.
The state changes used by the job (:func:`claim`, :func:`renew_lease`, :func:`record_progress`,
:func:`mark_done`, :func:`mark_error`, :func:`release`, :func:`reclaim_expired`) are conditional
UPDATEs on the job's lease, so a job delivered twice (at-least-once queue) runs once, and two
consumers never run one job.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal, cast

from sqlalchemy import func, select
from sqlalchemy.orm import Session

from app.limits import DEFAULT_LIMITS, Limits
from app.limits.physical import check_lights
from app.limits.queue import check_queue
from app.limits.work import check_simulation, read_capture_header
from app.models import Inspection, JobStatus
from app.services.errors import UnprocessableError
from app.services.forming import check_process
from app.services.light_calibrations import light_calibration_for_capture
from app.services.plates import current_target, get_or_create_plate
from app.services.stations import STATIONS_DIR, stage_stations
from app.services.targets import TARGET_FILE, copy_target_files, create_target, validate_target_dir
from app.storage import Storage
from pipeline.formats import InputError
from pipeline.io import CaptureHeader

if TYPE_CHECKING:
    from pipeline.simulate import CaptureSpec, PlateSpec

CAPTURE_FILE = "capture.zip"
SIMULATION_FILE = "simulation.json"
#: Folder (under inputs/) of a simulated inspection's rendered bundle.
SIMULATED_BUNDLE_DIR = "bundle"


# ------------------------------------------------------------------ creation


def create_uploaded_inspection(
    *,
    session: Session,
    storage: Storage,
    plate_id: str,
    staging_dir: Path,
    limits: Limits = DEFAULT_LIMITS,
    process: dict[str, Any] | None = None,
    sent_names: list[str] | None = None,
) -> Inspection:
    """A queued inspection of an uploaded bundle, or of the bundles of a plate's conveyor stations.

    ``staging_dir`` holds ``capture.zip`` and, optionally, ``target/target.json`` (+ mesh). A plate
    measured at stations (:mod:`app.services.stations`): ``parts/0.zip``, ``1.zip``, ... (the
    multipart parts as sent, named ``sent_names`` in errors), or a ``capture.zip`` of station
    folders; each bundle is checked as one bundle is, the set as the pipeline checks it, and the
    stations are kept in ``inputs/stations/`` (``capture_path``). The bundle is checked without decoding an image (capture.json, calibration, lights, image
    headers; :func:`app.limits.work.read_capture_header`) and within ``limits`` (default:
    :data:`app.limits.DEFAULT_LIMITS`), as is the queue; the target is
    validated with the pipeline's loader. A target sent with the inspection becomes the plate's
    current target. A capture whose lights are nominal directions is run with the cell's current
    light calibration, recorded in the row now (see
    :func:`app.services.light_calibrations.light_calibration_for_capture`). Once the row has an
    id, the staging folder becomes the inspection's ``inputs/`` folder. ``process`` (a validated
    :class:`app.schemas.ProcessIn` as a dict) is the forming pass that produced the shape; its
    machine must be known (:func:`app.services.forming.check_process`).

    Raises
    ------
    pipeline.formats.InputError
        A bad bundle or target, or one over ``limits`` (names the file and field); nothing was added.
    UnprocessableError
        No target sent and the plate has none (field ``target``); an unknown machine in ``process``
        (field ``process.machine_id``).
    app.limits.queue.QueueFullError
        The plate's queue or the whole queue is full; nothing was added.
    """
    check_process(session=session, process=process)
    staging_dir = Path(staging_dir)
    capture, label, kept_as = _uploaded_capture(staging_dir, limits, sent_names or [CAPTURE_FILE])
    if capture.plate_id != plate_id:
        raise InputError(
            label,
            "plate_id",
            f"the bundle is of plate {capture.plate_id!r}, not of {plate_id!r}, the plate this "
            "inspection was started for",
        )
    target_staging = staging_dir / "target"
    new_target_dir = None
    if (target_staging / TARGET_FILE).is_file():
        # Validated where it was uploaded (errors name target/target.json of the upload), then the
        # target keeps its own copy under the plate and the inspection keeps the one it used.
        validated = validate_target_dir(target_staging)
        plate_copy = storage.staging_copy(target_staging)
        try:
            target = create_target(
                session=session,
                storage=storage,
                plate_id=plate_id,
                staging_dir=plate_copy,
                validated=validated,
            )
        except BaseException:
            storage.remove(plate_copy)
            raise
        new_target_dir = storage.absolute(target.path).parent
    else:
        get_or_create_plate(session=session, plate_id=plate_id)
        current = current_target(session=session, plate_id=plate_id)
        if current is None:
            raise UnprocessableError(
                f"target: plate {plate_id!r} has no target yet: send a plate-target/1 file as 'target'",
                field="target",
            )
        target = current
    row = Inspection(
        plate_id=plate_id,
        target_id=target.id,
        source="upload",
        process=process,
        status=JobStatus.QUEUED,
        progress=0.0,
    )
    try:
        light_calibration = light_calibration_for_capture(session=session, capture=capture)
        row.light_calibration_id = None if light_calibration is None else light_calibration.id
        session.add(row)
        session.flush()
        check_queue(session=session, plate_id=plate_id, limits=limits)
        inputs = storage.adopt(staging_dir, storage.inputs_dir(row.id))
        if not (inputs / "target" / TARGET_FILE).is_file():
            copy_target_files(storage=storage, target=target, destination=inputs / "target")
        row.capture_path = storage.relative(inputs / kept_as)
        row.target_path = storage.relative(inputs / "target" / TARGET_FILE)
        row.tolerance_mm = target.tolerance_mm
        row.target_radius_mm = target.radius_mm
        session.flush()
    except BaseException:
        # The caller rolls the rows back: their files go too (the staging folder is the caller's).
        storage.remove(new_target_dir)
        if row.id is not None:
            storage.remove(storage.inspection_dir(row.id))
        raise
    return row


def _uploaded_capture(
    staging_dir: Path, limits: Limits, sent_names: list[str]
) -> tuple[CaptureHeader, str, str]:
    """The upload's capture checked: its header, how errors name its capture.json and what it is
    kept as under the inputs. One bundle: ``capture.json``, :data:`CAPTURE_FILE`; a plate at
    stations: station 0's header and capture.json as sent,
    :data:`app.services.stations.STATIONS_DIR`."""
    stations = stage_stations(staging_dir, CAPTURE_FILE, limits=limits, sent_names=sent_names)
    if stations is not None:
        return stations.headers[0], stations.labels[0], STATIONS_DIR
    capture = read_capture_header(staging_dir / CAPTURE_FILE, limits)
    check_lights(capture.lights, label=capture.label, field="photometric.lights")
    return capture, "capture.json", CAPTURE_FILE


def create_simulated_inspection(
    *,
    session: Session,
    storage: Storage,
    plate_id: str,
    simulation: dict[str, Any],
    limits: Limits = DEFAULT_LIMITS,
) -> Inspection:
    """A queued simulated inspection: the job renders the capture from ``simulation`` then inspects it.

    ``simulation`` is a validated :class:`app.schemas.SimulatedInspectionIn` as a dict; it is kept
    in the row and in ``inputs/simulation.json``. The simulator writes the lights it rendered
    with, so no light calibration is applied. The request and the queue are checked against
    ``limits`` (default: :data:`app.limits.DEFAULT_LIMITS`).

    The inspection is judged against the plate's current target, copied to ``inputs/target/``
    (the rendered shape is then what the pass formed: an under-bent plate fails); a plate without
    a target is judged against the rendered shape (the simulator's ``target.json`` in the bundle).
    ``simulation["process"]``, when given, is stored as the inspection's ``process``; its machine
    must be known (:func:`app.services.forming.check_process`).

    Raises
    ------
    UnprocessableError
        Over ``limits`` (lights, simulated pixels), a plate or capture the simulator refuses, or an
        unknown machine in ``process`` (field ``process.machine_id``).
    app.limits.queue.QueueFullError
        The plate's queue or the whole queue is full; nothing was added.
    """
    check_simulation(simulation, limits)
    try:
        simulation_specs(simulation)
    except ValueError as err:
        raise UnprocessableError(f"simulation: {err}", field="body") from None
    process = simulation.get("process")
    check_process(session=session, process=process)
    get_or_create_plate(session=session, plate_id=plate_id)
    target = current_target(session=session, plate_id=plate_id)
    if target is not None and "size_mm" not in simulation:
        simulation = {**simulation, "size_mm": _simulated_size(target.document)}
    row = Inspection(
        plate_id=plate_id,
        target_id=None if target is None else target.id,
        source="simulated",
        simulation=simulation,
        process=process,
        status=JobStatus.QUEUED,
        progress=0.0,
    )
    if target is None:
        row.tolerance_mm = float(simulation["tolerance_mm"])
        row.target_radius_mm = (
            None if simulation["shape"] == "plane" else simulation.get("radius_mm")
        )
    else:
        row.tolerance_mm, row.target_radius_mm = target.tolerance_mm, target.radius_mm
    session.add(row)
    session.flush()
    check_queue(session=session, plate_id=plate_id, limits=limits)
    inputs = storage.inputs_dir(row.id)
    try:
        inputs.mkdir(parents=True)
        (inputs / SIMULATION_FILE).write_text(json.dumps(simulation, indent=2), encoding="utf-8")
        bundle = inputs / SIMULATED_BUNDLE_DIR
        row.capture_path = storage.relative(bundle)
        if target is None:
            row.target_path = storage.relative(bundle / TARGET_FILE)
        else:
            row.target_path = storage.relative(
                copy_target_files(storage=storage, target=target, destination=inputs / "target")
            )
        session.flush()
    except BaseException:
        storage.remove(storage.inspection_dir(row.id))
        raise
    return row


#: The demo cell's field of view takes a plate up to this size a side, mm.
SIMULATED_MAX_SIDE_MM = 3000.0


def _simulated_size(target_document: dict[str, Any] | None) -> list[float]:
    """The size the demo cell renders a plate with a target at: the target's, each side at most
    :data:`SIMULATED_MAX_SIDE_MM` (what the simulated cameras see); 3000 x 3000 mm without one."""
    size = (target_document or {}).get("size_mm") or [SIMULATED_MAX_SIDE_MM] * 2
    return [min(float(v), SIMULATED_MAX_SIDE_MM) for v in size]


def simulation_specs(simulation: dict[str, Any]) -> tuple[PlateSpec, CaptureSpec]:
    """The simulator's ``(PlateSpec, CaptureSpec)`` for a simulated inspection's parameters.

    Raises
    ------
    ValueError
        The simulator refuses the described plate or capture.
    """
    from pipeline.simulate import CaptureSpec, Cutout, Dent, Floor, PlateSpec, rail_supports

    floor_mm = simulation.get("floor_mm")
    cutout_mm = simulation.get("cutout_radius_mm")
    size_x, size_y = (float(v) for v in simulation.get("size_mm", (3000.0, 3000.0)))
    size = (size_x, size_y)
    plate = PlateSpec(
        size_mm=size,
        shape=simulation["shape"],
        radius_mm=None if simulation.get("radius_mm") is None else float(simulation["radius_mm"]),
        convex=bool(simulation["convex"]),
        dents=tuple(
            Dent(d["x_mm"], d["y_mm"], d["radius_mm"], d["depth_mm"]) for d in simulation["dents"]
        ),
        floor=None
        if floor_mm is None
        else Floor(gap_mm=float(floor_mm), supports=rail_supports(size, float(floor_mm), 3)),
        cutouts=() if cutout_mm is None else (Cutout.circle(400.0, -300.0, float(cutout_mm)),),
    )
    near = (
        simulation.get("lights", "distant") == "near-field"
    )  # rows from before point lights were distant
    capture = CaptureSpec(
        n_lights=int(simulation["n_lights"]),
        noise=float(simulation["noise"]),
        # 8, 12 or 16 (SimulatedInspectionIn); CaptureSpec refuses any other.
        bit_depth=cast("Literal[8, 12, 16]", int(simulation["bit_depth"])),
        specular=float(simulation["specular"]),
        width=int(simulation["width"]),
        height=int(simulation["height"]),
        light_elevation_deg=float(simulation.get("light_elevation_deg", 45.0)),
        near_field_mm=float(simulation.get("light_height_mm", 2800.0)) if near else None,
        led_mu=float(simulation.get("led_mu", 0.0)) if near else 0.0,
        manifest_lights=simulation.get("light_manifest", "exact"),
        light_error_deg=float(simulation.get("light_error_deg", 0.0)),
    )
    return plate, capture


# ------------------------------------------------------------------ reading


def get_inspection(*, session: Session, inspection_id: int) -> Inspection | None:
    return session.get(Inspection, inspection_id)


def list_inspections(
    *,
    session: Session,
    plate_id: str | None = None,
    statuses: tuple[str, ...] | None = None,
    limit: int = 20,
    offset: int = 0,
) -> tuple[list[Inspection], int]:
    """Inspections newest first, optionally of one plate and/or in some statuses.

    Returns
    -------
    (inspections, total)
    """
    if limit < 1 or offset < 0:
        raise ValueError(
            f"paging: expected limit >= 1 and offset >= 0, got limit={limit}, offset={offset}"
        )
    where = []
    if plate_id is not None:
        where.append(Inspection.plate_id == plate_id)
    if statuses:
        where.append(Inspection.status.in_(statuses))
    total = int(session.scalar(select(func.count()).select_from(Inspection).where(*where)) or 0)
    items = list(
        session.scalars(
            select(Inspection)
            .where(*where)
            .order_by(Inspection.id.desc())
            .limit(limit)
            .offset(offset)
        )
    )
    return items, total


def plate_history(*, session: Session, plate_id: str) -> list[Inspection]:
    """Every inspection of a plate, oldest first."""
    return list(
        session.scalars(
            select(Inspection).where(Inspection.plate_id == plate_id).order_by(Inspection.id)
        )
    )


def artifact_names(*, storage: Storage, inspection: Inspection) -> list[str]:
    """Names of the files in the inspection's artifacts folder (sorted)."""
    folder = storage.artifacts_dir(inspection.id)
    if not folder.is_dir():
        return []
    return sorted(p.name for p in folder.iterdir() if p.is_file())


def count_by_status(*, session: Session) -> dict[str, int]:
    rows = session.execute(
        select(Inspection.status, func.count()).group_by(Inspection.status)
    ).all()
    return {status: int(n) for status, n in rows}
