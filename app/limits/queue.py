"""Caps on the job queue: inspections waiting per plate and in all (429 with ``Retry-After``).

:func:`check_queue` runs in the write transaction of a new inspection, after its row is flushed,
and counts that row too. On SQLite the flush holds the database's write lock until the commit,
so two submissions at once are counted one after the other and the caps are exact; on a server
database under READ COMMITTED they can overshoot by the submissions in flight.
"""

from __future__ import annotations

import statistics

from sqlalchemy import ColumnElement, func, select
from sqlalchemy.orm import Session

from app.limits import Limits, setting_name
from app.models import FINISHED, Inspection, JobStatus
from app.services.errors import ServiceError

#: A job's run time assumed before any job has finished, s.
DEFAULT_JOB_S = 60.0
#: Finished jobs whose run times estimate the next one's.
RECENT_JOBS = 20
#: Bounds of the Retry-After advice, s.
RETRY_AFTER_S = (1, 3600)


class QueueFullError(ServiceError):
    """The queue is at a cap: answer 429 with ``Retry-After: retry_after_s`` (not remembered as final).

    Attributes
    ----------
    retry_after_s : int
        When a place is likely to be free, s (from the run times of recent jobs).
    """

    def __init__(self, detail: str, *, field: str | None, retry_after_s: int):
        super().__init__(detail, field=field)
        self.retry_after_s = retry_after_s


def check_queue(*, session: Session, plate_id: str, limits: Limits) -> None:
    """Refuse the inspection just flushed if it puts its plate's queue or the whole queue over its cap.

    Raises
    ------
    QueueFullError
        Over ``max_queued_per_plate`` (field ``plate_id``) or ``max_queued`` (no field).
    """
    queued = Inspection.status == JobStatus.QUEUED
    per_plate = _count(session, queued, Inspection.plate_id == plate_id)
    if per_plate > limits.max_queued_per_plate:
        oldest = session.scalar(
            select(func.min(Inspection.id)).where(queued, Inspection.plate_id == plate_id)
        )
        ahead = _count(
            session, queued, Inspection.id <= oldest
        )  # jobs to start before this plate's next one
        raise QueueFullError(
            f"plate_id: plate {plate_id!r} has {per_plate - 1} inspections waiting already, the limit per plate is "
            f"{limits.max_queued_per_plate} (the server setting {setting_name('max_queued_per_plate')} raises it); "
            "retry when one of them has started",
            field="plate_id",
            retry_after_s=_retry_after(session, jobs_ahead=ahead),
        )
    total = _count(session, queued)
    if total > limits.max_queued:
        raise QueueFullError(
            f"queue: {total - 1} inspections are waiting already, the limit is {limits.max_queued} "
            f"(the server setting {setting_name('max_queued')} raises it); retry when one of them has started",
            field=None,
            retry_after_s=_retry_after(session, jobs_ahead=1),
        )


def _count(session: Session, *where: ColumnElement[bool]) -> int:
    return int(session.scalar(select(func.count()).select_from(Inspection).where(*where)) or 0)


def _retry_after(session: Session, *, jobs_ahead: int) -> int:
    """Seconds until ``jobs_ahead`` more jobs have started: that many median run times of recent jobs."""
    rows = session.execute(
        select(Inspection.started_at, Inspection.finished_at)
        .where(
            Inspection.status.in_(FINISHED),
            Inspection.started_at.is_not(None),
            Inspection.finished_at.is_not(None),
        )
        .order_by(Inspection.finished_at.desc())
        .limit(RECENT_JOBS)
    ).all()
    runs = [
        (finished - started).total_seconds()
        for started, finished in rows
        if started is not None and finished is not None and finished >= started  # as selected
    ]
    typical = statistics.median(runs) if runs else DEFAULT_JOB_S
    lo, hi = RETRY_AFTER_S
    return int(min(max(round(typical * max(jobs_ahead, 1)), lo), hi))
