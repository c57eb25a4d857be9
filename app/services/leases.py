"""The job state of an inspection row: claims under a lease, progress, done / error, reclaiming, and
the running job's lease renewed by a heartbeat (:class:`LeaseKeeper`): the one lease module.

The database row is the truth of a job; the queue only carries its id (see app/jobs/). A claim gives
the consumer the job for ``Settings.job_lease_s`` seconds (:func:`claim`); :class:`LeaseKeeper`
renews it every third of that, so only a consumer that died or hung for a whole lease loses its job.
A renewal the database refuses means the lease was lost (another consumer reclaimed the job): it is
logged, and the job's later writes (progress, done, failed) are no-ops.
"""

from __future__ import annotations

import logging
import os
import secrets
import socket
import threading
from dataclasses import dataclass
from datetime import datetime, timedelta
from typing import Any, cast

from sqlalchemy import ColumnElement, CursorResult, Executable, and_, case, or_, select, update
from sqlalchemy.orm import Session, sessionmaker

from app.models import Inspection, JobStatus, utcnow

log = logging.getLogger(__name__)

# A job is claimed under a lease: ``lease_owner`` (the consumer, "host:pid:nonce") and
# ``lease_expires_at``. The running job renews it; every later write of the job (progress,
# done, error) is conditional on still holding it, so a consumer that lost its job (its lease
# expired and another claimed the row, or it was released) changes nothing. A lease that ran out
# is taken as its worker's death: the row is claimed again, and the second death sets it aside.


#: A job whose worker died this many times while running it is set aside (``error``), not run again.
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


def _changed(session: Session, statement: Executable) -> int:
    """Rows an UPDATE changed (an UPDATE's result is a cursor result, which counts them)."""
    result = cast("CursorResult[Any]", session.execute(statement))
    return result.rowcount


def _now(now: datetime | None) -> datetime:
    return utcnow() if now is None else now


def _held_by(inspection_id: int, owner: str) -> tuple[ColumnElement[bool], ...]:
    return (
        Inspection.id == inspection_id,
        Inspection.status == JobStatus.RUNNING,
        Inspection.lease_owner == owner,
    )


def _claimable(now: datetime) -> ColumnElement[bool]:
    """Queued, or running under a lease that ran out below the death limit (the reclaim counts a death)."""
    expired = and_(
        Inspection.status == JobStatus.RUNNING,
        Inspection.lease_expires_at <= now,
        Inspection.deaths + 1 < MAX_WORKER_DEATHS,
    )
    return or_(Inspection.status == JobStatus.QUEUED, expired)


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
        False when the row is not claimable (done, error, or running under a live lease).
    """
    now = _now(now)
    changed = _changed(
        session,
        update(Inspection)
        .where(Inspection.id == inspection_id, _claimable(now))
        .values(
            status=JobStatus.RUNNING,
            lease_owner=owner or process_lease_owner(),
            lease_expires_at=now + timedelta(seconds=lease_s),
            deaths=case(
                (Inspection.status == JobStatus.RUNNING, Inspection.deaths + 1),
                else_=Inspection.deaths,
            ),
            started_at=now,
            finished_at=None,
            progress=0.0,
            stage=None,
            error=None,
            attempts=Inspection.attempts + 1,
        ),
    )
    return changed == 1


def renew_lease(
    *, session: Session, inspection_id: int, owner: str, lease_s: float, now: datetime | None = None
) -> bool:
    """Extend the lease of a running job; False if ``owner`` no longer holds it."""
    changed = _changed(
        session,
        update(Inspection)
        .where(*_held_by(inspection_id, owner))
        .values(lease_expires_at=_now(now) + timedelta(seconds=lease_s)),
    )
    return changed == 1


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
    changed = _changed(
        session,
        update(Inspection)
        .where(*_held_by(inspection_id, owner or process_lease_owner()))
        .values(
            status=JobStatus.DONE,
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
        ),
    )
    return changed == 1


def mark_error(
    *, session: Session, inspection_id: int, error: str, owner: str | None = None
) -> bool:
    """running -> error with its message (no verdict: nothing was measured); the inputs stay on disk.

    Only while ``owner`` (default :func:`process_lease_owner`) holds the lease; returns whether it did.
    """
    changed = _changed(
        session,
        update(Inspection)
        .where(*_held_by(inspection_id, owner or process_lease_owner()))
        .values(
            status=JobStatus.ERROR,
            verdict=None,
            error=error,
            finished_at=utcnow(),
            lease_owner=None,
            lease_expires_at=None,
        ),
    )
    return changed == 1


def release(*, session: Session, owner: str) -> list[int]:
    """A graceful stop: the jobs ``owner`` runs go back to the queue, keeping their place.

    Not a worker death (the job did nothing wrong): ``deaths`` is unchanged. Returns their ids.
    """
    ids = list(
        session.scalars(
            select(Inspection.id).where(
                Inspection.status == JobStatus.RUNNING, Inspection.lease_owner == owner
            )
        )
    )
    for inspection_id in ids:
        session.execute(
            update(Inspection)
            .where(*_held_by(inspection_id, owner))
            .values(
                status=JobStatus.QUEUED,
                stage=None,
                progress=0.0,
                lease_owner=None,
                lease_expires_at=None,
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
    where = (Inspection.status == JobStatus.RUNNING, others)
    ids = list(session.scalars(select(Inspection.id).where(*where)))
    if ids:
        session.execute(
            update(Inspection).where(Inspection.id.in_(ids), *where).values(lease_expires_at=now)
        )
    return ids


@dataclass(frozen=True)
class Reclaimed:
    """What :func:`reclaim_expired` did: jobs queued again, and jobs set aside as errors."""

    requeued: list[int]
    set_aside: list[int]


def reclaim_expired(*, session: Session, now: datetime | None = None) -> Reclaimed:
    """Running jobs whose lease ran out (``lease_expires_at <= now``: their worker died): one more death each.

    Below :data:`MAX_WORKER_DEATHS` the job is queued again at the back of the queue (so the jobs
    behind it are not held up by a job that may kill its worker); at the limit it is set aside:
    ``error``, without a verdict, with the reason and its last stage. Each row changes in one
    conditional UPDATE on the lease that ran out, so a concurrent claim or renewal wins cleanly.
    """
    now = _now(now)
    rows = session.execute(
        select(Inspection.id, Inspection.lease_owner, Inspection.deaths, Inspection.stage)
        .where(Inspection.status == JobStatus.RUNNING, Inspection.lease_expires_at <= now)
        .order_by(Inspection.queued_at, Inspection.id)
    ).all()
    requeued: list[int] = []
    set_aside: list[int] = []
    for inspection_id, owner, deaths, stage in rows:
        same_lease = (
            Inspection.id == inspection_id,
            Inspection.status == JobStatus.RUNNING,
            Inspection.lease_expires_at <= now,
            Inspection.lease_owner.is_(None) if owner is None else Inspection.lease_owner == owner,
        )
        cleared: dict[str, Any] = dict(lease_owner=None, lease_expires_at=None, deaths=deaths + 1)
        if deaths + 1 >= MAX_WORKER_DEATHS:
            values = dict(
                cleared,
                status=JobStatus.ERROR,
                verdict=None,
                finished_at=now,
                error=poison_reason(deaths + 1, stage),
            )
            target = set_aside
        else:
            values = dict(cleared, status=JobStatus.QUEUED, queued_at=now, stage=None, progress=0.0)
            target = requeued
        if _changed(session, update(Inspection).where(*same_lease).values(**values)) == 1:
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
    where = [Inspection.status == JobStatus.QUEUED]
    if queued_before is not None:
        where.append(Inspection.queued_at < queued_before)
    return list(
        session.scalars(
            select(Inspection.id).where(*where).order_by(Inspection.queued_at, Inspection.id)
        )
    )


# --------------------------------------------------------------------------- the running job's heartbeat


class LeaseKeeper:
    """Renew the lease of one running job until :meth:`stop` (a context manager).

    Parameters
    ----------
    session_factory : sessionmaker
    inspection_id : int
    owner : str
        The lease owner (:func:`app.services.leases.process_lease_owner` in the consumer).
    lease_s : float
        Lease length, s; renewed every ``lease_s / 3``.
    """

    def __init__(
        self,
        session_factory: sessionmaker[Session],
        inspection_id: int,
        *,
        owner: str,
        lease_s: float,
    ):
        self.session_factory = session_factory
        self.inspection_id = inspection_id
        self.owner = owner
        self.lease_s = lease_s
        self._stop = threading.Event()
        self._thread = threading.Thread(
            target=self._run, name=f"lease-{inspection_id}", daemon=True
        )
        #: Set when the database refused a renewal: another consumer holds the job now.
        self.lost = threading.Event()

    def __enter__(self) -> LeaseKeeper:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def stop(self) -> None:
        """Stop renewing (the job finished, or failed)."""
        self._stop.set()
        self._thread.join()

    def _run(self) -> None:
        while not self._stop.wait(self.lease_s / 3.0):
            try:
                with self.session_factory() as session:
                    held = renew_lease(
                        session=session,
                        inspection_id=self.inspection_id,
                        owner=self.owner,
                        lease_s=self.lease_s,
                    )
                    session.commit()
            except Exception:
                log.warning(
                    "inspection %s: lease renewal failed; retrying",
                    self.inspection_id,
                    exc_info=True,
                )
                continue
            if not held:
                if not self._stop.is_set():
                    self.lost.set()
                    log.error(
                        "inspection %s: lease lost (the job was reclaimed or released); its result "
                        "will not be stored by this consumer",
                        self.inspection_id,
                    )
                return
