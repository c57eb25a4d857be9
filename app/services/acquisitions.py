"""Acquired inspections: queued by ``POST /plates/{plate_id}/inspections/acquire``, photographed by the job.

The request is checked and queued in the web process (:func:`create_acquired_inspection`); the
consumer photographs the plate with the cell's cameras and lights
(:func:`pipeline.acquisition.acquire`) into the inspection's ``inputs/bundle`` (:func:`capture_for_job`,
called by :mod:`app.jobs.execution`) and then inspects it like any other bundle.
"""

from __future__ import annotations

import json
import logging
import shutil
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from sqlalchemy.orm import Session

from app.limits import DEFAULT_LIMITS, Limits
from app.limits.queue import check_queue
from app.models import Inspection, JobStatus, Target
from app.services.cell import (
    CellLock,
    CellUnavailable,
    cell_message,
    ensure_demo_cell,
    load_cell,
    record_capture,
)
from app.services.errors import UnprocessableError
from app.services.forming import check_process
from app.services.plates import current_target, get_or_create_plate
from app.services.stations import capture_bundles
from app.services.targets import TARGET_FILE, copy_target_files, create_target, validate_target_dir
from app.settings import Settings
from app.storage import Storage
from pipeline.acquisition import (
    CellConfig,
    StreamedFrames,
    acquire,
    acquire_stations,
    last_frame_time,
)
from pipeline.acquisition.stations import StationDone
from pipeline.formats import AcquisitionError, InputError, PipelineError

log = logging.getLogger(__name__)

#: ``Inspection.source`` of an inspection photographed in the cell.
ACQUIRED_SOURCE = "acquired"
#: The request (the cell's id and configuration file), under the inspection's inputs.
ACQUISITION_FILE = "acquisition.json"
#: Folder (under inputs/) the job writes the bundle into.
ACQUIRED_BUNDLE_DIR = "bundle"
#: Stage reported while the cell photographs the plate (before the pipeline's stages).
CAPTURE_STAGE = "capture"
#: Seconds a job waits for the cameras while the web server checks them.
CAMERAS_WAIT_S = 30.0


class AcquisitionFailed(PipelineError):
    """The job could not photograph the plate: a device failed (named with the step), or the cell is
    not usable by this consumer. Its message is stored as the job's error."""


def create_acquired_inspection(
    *,
    session: Session,
    storage: Storage,
    plate_id: str,
    cell: CellConfig,
    process: dict[str, Any] | None = None,
    target_dir: Path | None = None,
    default_target: Path | None = None,
    limits: Limits = DEFAULT_LIMITS,
) -> Inspection:
    """A queued inspection that the job photographs in ``cell``, then inspects.

    The target: the one in ``target_dir`` (``target.json``, validated; it becomes the plate's
    current target), else the plate's current one, else ``default_target`` (a ``target.json``:
    the demo cell's, likewise made the plate's). ``process`` (a validated
    :class:`app.schemas.ProcessIn` as a dict) is the forming pass that produced the shape; its
    machine must be known (:func:`app.services.forming.check_process`). The queue is checked
    against ``limits``. ``inputs/`` gets :data:`ACQUISITION_FILE` and ``target/target.json``; the
    job writes ``bundle/``.

    Raises
    ------
    pipeline.formats.InputError
        A bad target (names the file and the field); nothing was added.
    UnprocessableError
        No target sent and the plate has none (field ``target``); an unknown machine in ``process``
        (field ``process.machine_id``).
    app.limits.queue.QueueFullError
        The plate's queue or the whole queue is full; nothing was added.
    """
    check_process(session=session, process=process)
    new_targets: list[Path] = []
    row = None
    try:
        target = _target(
            session=session,
            storage=storage,
            plate_id=plate_id,
            target_dir=target_dir,
            default_target=default_target,
            created=new_targets,
        )
        row = Inspection(
            plate_id=plate_id,
            target_id=target.id,
            source=ACQUIRED_SOURCE,
            cell_id=cell.cell_id,
            process=process,
            status=JobStatus.QUEUED,
            progress=0.0,
            tolerance_mm=target.tolerance_mm,
            target_radius_mm=target.radius_mm,
        )
        session.add(row)
        session.flush()
        check_queue(session=session, plate_id=plate_id, limits=limits)
        inputs = storage.inputs_dir(row.id)
        inputs.mkdir(parents=True)
        request = {"cell_id": cell.cell_id, "config": cell.path.name}
        (inputs / ACQUISITION_FILE).write_text(json.dumps(request, indent=2), encoding="utf-8")
        copy_target_files(storage=storage, target=target, destination=inputs / "target")
        row.capture_path = storage.relative(inputs / ACQUIRED_BUNDLE_DIR)
        row.target_path = storage.relative(inputs / "target" / TARGET_FILE)
        session.flush()
    except BaseException:
        # The caller rolls the rows back: their files go too.
        for folder in new_targets:
            storage.remove(folder)
        if row is not None and row.id is not None:
            storage.remove(storage.inspection_dir(row.id))
        raise
    return row


def _target(
    *,
    session: Session,
    storage: Storage,
    plate_id: str,
    target_dir: Path | None,
    default_target: Path | None,
    created: list[Path],
) -> Target:
    """The target of a new acquired inspection (see :func:`create_acquired_inspection`); the folders
    of targets it creates are appended to ``created``."""
    if target_dir is not None:
        return _new_target(
            session=session, storage=storage, plate_id=plate_id, folder=target_dir, created=created
        )
    get_or_create_plate(session=session, plate_id=plate_id)
    target = current_target(session=session, plate_id=plate_id)
    if target is not None:
        return target
    if default_target is None:
        raise UnprocessableError(
            f"target: plate {plate_id!r} has no target yet: send a plate-target/1 object as 'target'",
            field="target",
        )
    return _new_target(
        session=session,
        storage=storage,
        plate_id=plate_id,
        folder=default_target.parent,
        created=created,
    )


def _new_target(
    *, session: Session, storage: Storage, plate_id: str, folder: Path, created: list[Path]
) -> Target:
    """A new current target of the plate from ``folder/target.json``, validated where it is (errors
    name that file); the plate's copy is made from it."""
    validated = validate_target_dir(folder)
    staged = storage.new_staging_dir()
    try:
        shutil.copyfile(folder / TARGET_FILE, staged / TARGET_FILE)
        target = create_target(
            session=session,
            storage=storage,
            plate_id=plate_id,
            staging_dir=staged,
            validated=validated,
        )
    except BaseException:
        storage.remove(staged)
        raise
    created.append(storage.absolute(target.path).parent)
    return target


@dataclass(frozen=True)
class JobCapture:
    """What an acquired job photographed (:func:`capture_for_job`)."""

    #: The bundles to measure: ``[bundle_dir]`` for a cell that photographs one view, or a conveyor
    #: cell's stations ``bundle_dir/station_00``, ...
    bundles: list[Path]
    #: One view's frames as the cameras gave them, by file name (empty: read from the bundles).
    frames: dict[str, np.ndarray] = field(default_factory=dict)
    #: ``time.monotonic()`` when the last frame arrived; None for a capture kept from an earlier run.
    last_frame_at: float | None = None


def capture_for_job(
    inspection_id: int,
    *,
    settings: Settings,
    storage: Storage,
    plate_id: str,
    bundle_dir: Path,
    progress: Callable[[str, float], None],
    station_done: StationDone | None = None,
) -> JobCapture:
    """The capture of an acquired job, in the consumer: photograph the plate into ``bundle_dir``; the
    bundles to measure: ``[bundle_dir]`` for a cell that photographs one view, or, for a cell with a
    conveyor, its stations' bundles ``bundle_dir/station_00``, ... (:func:`pipeline.acquisition.acquire_stations`),
    which :func:`app.jobs.execution.measure_bundles` measures as one plate. A view photographed now
    comes with its frames in memory, which the inspection takes instead of decoding the files again.

    A complete capture already there (the job runs again after its worker died or was stopped) is
    kept: the plate photographed then is the one inspected. Progress is reported as stage
    :data:`CAPTURE_STAGE`, its fraction the frames taken (over all stations). The (first) bundle's
    ``capture.json`` (with the acquisition record) is copied into the artifacts. The cameras' state
    and thumbnails are recorded for the dashboard. ``station_done(index, bundle)`` is the hook of
    :func:`pipeline.acquisition.acquire_stations` (a cell with a conveyor, stations photographed
    now): each station as soon as it is photographed, so that it is reconstructed while the next is.

    Raises
    ------
    AcquisitionFailed
        A device failed (``"acquisition failed: <device>: <step>: <reason>"``), the cell is not
        usable here (no cell, a bad configuration, another cell than the job's), or the cameras
        stayed busy.
    pipeline.formats.InputError
        The configuration names settings a camera refuses (an exposure out of its range, a sensor
        smaller than the calibration); the file and field are named relative to its folder.
    """
    request = json.loads(
        (storage.inputs_dir(inspection_id) / ACQUISITION_FILE).read_text(encoding="utf-8")
    )
    progress(CAPTURE_STAGE, 0.0)
    captured = JobCapture(capture_bundles(bundle_dir))
    if not all((bundle / "capture.json").is_file() for bundle in captured.bundles):
        storage.remove(bundle_dir)  # nothing complete: the acquisition writes it anew
        captured = _capture(
            inspection_id,
            settings=settings,
            storage=storage,
            plate_id=plate_id,
            bundle_dir=bundle_dir,
            cell_id=request["cell_id"],
            progress=progress,
            station_done=station_done,
        )
    shutil.copyfile(
        captured.bundles[0] / "capture.json", storage.artifacts_dir(inspection_id) / "capture.json"
    )
    progress(CAPTURE_STAGE, 1.0)
    return captured


def _capture(
    inspection_id: int,
    *,
    settings: Settings,
    storage: Storage,
    plate_id: str,
    bundle_dir: Path,
    cell_id: str,
    progress: Callable[[str, float], None],
    station_done: StationDone | None,
) -> JobCapture:
    """Photograph the plate into ``bundle_dir`` with the cell ``cell_id``, holding the cameras' lock:
    one view (its frames kept in memory too), or each station of a cell with a conveyor."""
    ensure_demo_cell(settings)
    try:
        config = load_cell(settings)
    except CellUnavailable as err:
        raise AcquisitionFailed(err.detail) from None
    if config.cell_id != cell_id:
        raise AcquisitionFailed(
            f"cell_id: the job was queued for cell {cell_id!r}, this consumer's cell ({config.path.name}) is "
            f"{config.cell_id!r}"
        )
    lock = CellLock(storage.data_dir)
    if not lock.acquire(f"inspection {inspection_id} (acquiring)", timeout_s=CAMERAS_WAIT_S):
        raise AcquisitionFailed(
            f"the cameras stayed busy for {CAMERAS_WAIT_S:g} s: {lock.holder() or 'holder unknown'}"
        )

    def report(stage: str, fraction: float) -> None:
        progress(CAPTURE_STAGE, fraction)

    # one view: each frame folded for the inspection as it arrives (pipeline.acquisition.streaming)
    frames: dict[str, np.ndarray] = (
        StreamedFrames.for_cell(config) if config.conveyor is None else {}
    )
    try:
        if config.conveyor is None:
            bundles = [
                acquire(
                    config.path,
                    plate_id,
                    bundle_dir,
                    progress=report,
                    frame_timeout_s=settings.frame_timeout_s,
                    frames=frames,
                )
            ]
        else:
            bundles = acquire_stations(
                config.path,
                plate_id,
                bundle_dir,
                progress=report,
                station_done=station_done,
                frame_timeout_s=settings.frame_timeout_s,
            )
        returned = time.monotonic()  # the bundles are complete: the last frame came its lag before
    except AcquisitionError as err:
        raise AcquisitionFailed(f"acquisition failed: {err}") from None
    except InputError as err:
        raise InputError(
            cell_message(err.file, config.path), err.field, cell_message(err.reason, config.path)
        ) from None
    finally:
        lock.release()
    last_frame_at = last_frame_time(bundles[-1], returned)
    try:
        record_capture(storage.data_dir, bundles[-1], inspection_id=inspection_id, frames=frames)
    except Exception:
        log.warning(
            "inspection %s: the cameras' last frames were not recorded",
            inspection_id,
            exc_info=True,
        )
    return JobCapture(bundles, frames, last_frame_at)
