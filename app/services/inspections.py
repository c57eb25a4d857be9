"""Inspections: created by an upload or the simulated cell, run by the job, read by the API.

The row is the source of truth of its job: ``queued -> running -> done | failed``.
The state changes used by the job (:func:`claim`, :func:`renew_lease`, :func:`record_progress`,
:func:`mark_done`, :func:`mark_failed`, :func:`release`, :func:`reclaim_expired`) are conditional
UPDATEs on the job's lease, so a job delivered twice (at-least-once queue) runs once, and two
consumers never run one job.
"""

from __future__ import annotations

import json
import os
import secrets
import socket
from dataclasses import dataclass
from datetime import datetime, timedelta
from pathlib import Path
from typing import Any

from sqlalchemy import and_, case, func, or_, select, update
from sqlalchemy.orm import Session

from app.limits import DEFAULT_LIMITS, Limits
from app.limits.physical import check_lights
from app.limits.queue import check_queue
from app.limits.work import check_simulation, read_capture_header
from app.models import Inspection, utcnow
from app.services.errors import UnprocessableError
from app.services.forming import check_process
from app.services.light_calibrations import light_calibration_for_capture
from app.services.plates import current_target, get_or_create_plate
from app.services.targets import TARGET_FILE, copy_target_files, create_target, validate_target_dir
from app.storage import Storage
from pipeline.formats import InputError

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
) -> Inspection:
    """A queued inspection of an uploaded bundle.

    ``staging_dir`` holds ``capture.zip`` and, optionally, ``target/target.json`` (+ mesh).
    The bundle is checked without decoding an image (capture.json, calibration, lights, image
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
    capture = read_capture_header(staging_dir / CAPTURE_FILE, limits)
    check_lights(capture.lights, label=capture.label, field="photometric.lights")
    if capture.plate_id != plate_id:
        raise InputError(
            "capture.json",
            "plate_id",
            f"expected {plate_id!r} (the plate of the URL), got {capture.plate_id!r}",
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
        target = current_target(session=session, plate_id=plate_id)
        if target is None:
            raise UnprocessableError(
                f"target: plate {plate_id!r} has no target yet: send a plate-target/1 file as 'target'",
                field="target",
            )
    row = Inspection(
        plate_id=plate_id,
        target_id=target.id,
        source="upload",
        process=process,
        status="queued",
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
        row.capture_path = storage.relative(inputs / CAPTURE_FILE)
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
    row = Inspection(
        plate_id=plate_id,
        target_id=None if target is None else target.id,
        source="simulated",
        simulation=simulation,
        process=process,
        status="queued",
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


def simulation_specs(simulation: dict):
    """The simulator's ``(PlateSpec, CaptureSpec)`` for a simulated inspection's parameters.

    Raises
    ------
    ValueError
        The simulator refuses the described plate or capture.
    """
    from pipeline.simulate import CaptureSpec, Cutout, Dent, Floor, PlateSpec, rail_supports

    floor_mm = simulation.get("floor_mm")
    cutout_mm = simulation.get("cutout_radius_mm")
    plate = PlateSpec(
        shape=simulation["shape"],
        radius_mm=None if simulation.get("radius_mm") is None else float(simulation["radius_mm"]),
        convex=bool(simulation["convex"]),
        dents=tuple(
            Dent(d["x_mm"], d["y_mm"], d["radius_mm"], d["depth_mm"]) for d in simulation["dents"]
        ),
        floor=None
        if floor_mm is None
        else Floor(
            gap_mm=float(floor_mm), supports=rail_supports((3000.0, 3000.0), float(floor_mm), 3)
        ),
        cutouts=() if cutout_mm is None else (Cutout.circle(400.0, -300.0, float(cutout_mm)),),
    )
    near = (
        simulation.get("lights", "distant") == "near-field"
    )  # rows from before point lights were distant
    capture = CaptureSpec(
        n_lights=int(simulation["n_lights"]),
        noise=float(simulation["noise"]),
        bit_depth=int(simulation["bit_depth"]),
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


# ------------------------------------------------------------------ job state
#
# A job is claimed under a lease: ``lease_owner`` (the consumer, "host:pid:nonce") and
# ``lease_expires_at``. The running job renews it; every later write of the job (progress,
# done, failed) is conditional on still holding it, so a consumer that lost its job (its lease
# expired and another claimed the row, or it was released) changes nothing. A lease that ran out
# is taken as its worker's death: the row is claimed again, and the second death sets it aside.


#: A job whose worker died this many times while running it is set aside (``failed``), not run again.
MAX_WORKER_DEATHS = 2
#: Lease of a claim when the caller gives none, s (the consumer passes ``Settings.job_lease_s``).
DEFAULT_LEASE_S = 60.0

_OWNER: dict[int, str] = {}


def process_lease_owner() -> str:
    """This process's lease owner id, ``"host:pid:nonce"`` (the nonce tells a reused pid apart)."""
    pid = os.getpid()
    if pid not in _OWNER:
        _OWNER.clear()  # a forked child gets its own id
        _OWNER[pid] = f"{socket.gethostname()[:80]}:{pid}:{secrets.token_hex(4)}"
    return _OWNER[pid]


def _now(now: datetime | None) -> datetime:
    return utcnow() if now is None else now


def _held_by(inspection_id: int, owner: str):
    return (
        Inspection.id == inspection_id,
        Inspection.status == "running",
        Inspection.lease_owner == owner,
    )


def _claimable(now: datetime):
    """Queued, or running under a lease that ran out below the death limit (the reclaim counts a death)."""
    expired = and_(
        Inspection.status == "running",
        Inspection.lease_expires_at <= now,
        Inspection.deaths + 1 < MAX_WORKER_DEATHS,
    )
    return or_(Inspection.status == "queued", expired)


def claim(
    *,
    session: Session,
    inspection_id: int,
    owner: str | None = None,
    lease_s: float = DEFAULT_LEASE_S,
    now: datetime | None = None,
) -> bool:
    """Take the job under a lease: queued (or running with an expired lease) -> running.

    One conditional UPDATE: of two claims of one row, one wins. Reclaiming an expired lease
    counts a worker death; a row whose next death would reach :data:`MAX_WORKER_DEATHS` is not
    claimed (:func:`reclaim_expired` sets it aside).

    Parameters
    ----------
    session : Session
    inspection_id : int
    owner : str, optional
        The claiming consumer; default :func:`process_lease_owner`.
    lease_s : float
        How long the lease holds unless renewed (:func:`renew_lease`), s.
    now : datetime, optional
        The current time (UTC); tests pass it to step over a lease.

    Returns
    -------
    bool
        False when the row is not claimable (done, failed, or running under a live lease).
    """
    now = _now(now)
    res = session.execute(
        update(Inspection)
        .where(Inspection.id == inspection_id, _claimable(now))
        .values(
            status="running",
            lease_owner=owner or process_lease_owner(),
            lease_expires_at=now + timedelta(seconds=lease_s),
            deaths=case(
                (Inspection.status == "running", Inspection.deaths + 1), else_=Inspection.deaths
            ),
            started_at=now,
            finished_at=None,
            progress=0.0,
            stage=None,
            error=None,
            attempts=Inspection.attempts + 1,
        )
    )
    return res.rowcount == 1


def renew_lease(
    *, session: Session, inspection_id: int, owner: str, lease_s: float, now: datetime | None = None
) -> bool:
    """Extend the lease of a running job; False if ``owner`` no longer holds it."""
    res = session.execute(
        update(Inspection)
        .where(*_held_by(inspection_id, owner))
        .values(lease_expires_at=_now(now) + timedelta(seconds=lease_s))
    )
    return res.rowcount == 1


def record_progress(
    *, session: Session, inspection_id: int, stage: str, progress: float, owner: str | None = None
) -> None:
    """The running job's stage name and overall progress (0..1); a no-op unless ``owner`` holds the lease."""
    if not 0.0 <= progress <= 1.0:
        raise ValueError(f"progress: expected a fraction in [0, 1], got {progress}")
    session.execute(
        update(Inspection)
        .where(*_held_by(inspection_id, owner or process_lease_owner()))
        .values(stage=stage[:32], progress=float(progress))
    )


def mark_done(
    *, session: Session, inspection_id: int, document: dict[str, Any], owner: str | None = None
) -> bool:
    """running -> done with the ``plate-result/1`` document and its summary numbers.

    Only while ``owner`` (default :func:`process_lease_owner`) holds the lease; returns whether it did.
    """
    dev = document.get("deviation_mm") or {}
    res = session.execute(
        update(Inspection)
        .where(*_held_by(inspection_id, owner or process_lease_owner()))
        .values(
            status="done",
            progress=1.0,
            stage="done",
            finished_at=utcnow(),
            lease_owner=None,
            lease_expires_at=None,
            result=document,
            timings_s=document.get("timings_s"),
            radius_mm=document.get("radius_mm"),
            target_radius_mm=document.get("target_radius_mm"),
            radius_error_pct=document.get("radius_error_pct"),
            rms_mm=dev.get("rms"),
            max_abs_mm=dev.get("max_abs"),
            p95_mm=dev.get("p95"),
            within_tolerance_pct=document.get("within_tolerance_pct"),
            tolerance_mm=document.get("tolerance_mm"),
            verdict=document.get("verdict"),
            error=document.get("error"),
        )
    )
    return res.rowcount == 1


def mark_failed(
    *, session: Session, inspection_id: int, error: str, owner: str | None = None
) -> bool:
    """running -> failed with its message (verdict ``error``); the inputs stay on disk.

    Only while ``owner`` (default :func:`process_lease_owner`) holds the lease; returns whether it did.
    """
    res = session.execute(
        update(Inspection)
        .where(*_held_by(inspection_id, owner or process_lease_owner()))
        .values(
            status="failed",
            verdict="error",
            error=error,
            finished_at=utcnow(),
            lease_owner=None,
            lease_expires_at=None,
        )
    )
    return res.rowcount == 1


def release(*, session: Session, owner: str) -> list[int]:
    """A graceful stop: the jobs ``owner`` runs go back to the queue, keeping their place.

    Not a worker death (the job did nothing wrong): ``deaths`` is unchanged. Returns their ids.
    """
    ids = list(
        session.scalars(
            select(Inspection.id).where(
                Inspection.status == "running", Inspection.lease_owner == owner
            )
        )
    )
    for inspection_id in ids:
        session.execute(
            update(Inspection)
            .where(*_held_by(inspection_id, owner))
            .values(
                status="queued", stage=None, progress=0.0, lease_owner=None, lease_expires_at=None
            )
        )
    return ids


def expire_leases(*, session: Session, keep_owner: str, now: datetime | None = None) -> list[int]:
    """End now the leases of running jobs not held by ``keep_owner``: their consumers are known dead.

    The single consumer of an embedded queue calls it once it holds the consumer lock (the lock
    proves that no other consumer lives). Returns the ids whose lease was ended.
    """
    now = _now(now)
    others = or_(Inspection.lease_owner.is_(None), Inspection.lease_owner != keep_owner)
    where = (Inspection.status == "running", others)
    ids = list(session.scalars(select(Inspection.id).where(*where)))
    if ids:
        session.execute(
            update(Inspection).where(Inspection.id.in_(ids), *where).values(lease_expires_at=now)
        )
    return ids


@dataclass(frozen=True)
class Reclaimed:
    """What :func:`reclaim_expired` did: jobs queued again, and jobs set aside as failed."""

    requeued: list[int]
    set_aside: list[int]


def reclaim_expired(*, session: Session, now: datetime | None = None) -> Reclaimed:
    """Running jobs whose lease ran out (``lease_expires_at <= now``: their worker died): one more death each.

    Below :data:`MAX_WORKER_DEATHS` the job is queued again at the back of the queue (so the jobs
    behind it are not held up by a job that may kill its worker); at the limit it is set aside:
    ``failed``, verdict ``error``, with the reason and its last stage. Each row changes in one
    conditional UPDATE on the lease that ran out, so a concurrent claim or renewal wins cleanly.
    """
    now = _now(now)
    rows = session.execute(
        select(Inspection.id, Inspection.lease_owner, Inspection.deaths, Inspection.stage)
        .where(Inspection.status == "running", Inspection.lease_expires_at <= now)
        .order_by(Inspection.queued_at, Inspection.id)
    ).all()
    requeued: list[int] = []
    set_aside: list[int] = []
    for inspection_id, owner, deaths, stage in rows:
        same_lease = (
            Inspection.id == inspection_id,
            Inspection.status == "running",
            Inspection.lease_expires_at <= now,
            Inspection.lease_owner.is_(None) if owner is None else Inspection.lease_owner == owner,
        )
        cleared = dict(lease_owner=None, lease_expires_at=None, deaths=deaths + 1)
        if deaths + 1 >= MAX_WORKER_DEATHS:
            values = dict(
                cleared,
                status="failed",
                verdict="error",
                finished_at=now,
                error=poison_reason(deaths + 1, stage),
            )
            target = set_aside
        else:
            values = dict(cleared, status="queued", queued_at=now, stage=None, progress=0.0)
            target = requeued
        if session.execute(update(Inspection).where(*same_lease).values(**values)).rowcount == 1:
            target.append(inspection_id)
    return Reclaimed(requeued=requeued, set_aside=set_aside)


def poison_reason(deaths: int, stage: str | None) -> str:
    """The error stored on a job set aside after ``deaths`` worker deaths."""
    times = {1: "once", 2: "twice"}.get(deaths, f"{deaths} times")
    last = f"last stage: {stage}" if stage else "no stage reported"
    return (
        f"set aside: the worker died {times} while running this job ({last}); its inputs are kept"
    )


def requeue_interrupted(
    *, session: Session, owner: str | None = None, now: datetime | None = None
) -> Reclaimed:
    """Consumer start: every job left running belongs to a dead consumer; reclaim them.

    Call it only from the single consumer of an embedded queue, holding the consumer lock
    (:func:`expire_leases`). Returns what :func:`reclaim_expired` did.
    """
    now = _now(now)
    expire_leases(session=session, keep_owner=owner or process_lease_owner(), now=now)
    return reclaim_expired(session=session, now=now)


def queued_ids(*, session: Session, queued_before: datetime | None = None) -> list[int]:
    """Every queued job (optionally only those queued before a time), in queue order (oldest first)."""
    where = [Inspection.status == "queued"]
    if queued_before is not None:
        where.append(Inspection.queued_at < queued_before)
    return list(
        session.scalars(
            select(Inspection.id).where(*where).order_by(Inspection.queued_at, Inspection.id)
        )
    )
