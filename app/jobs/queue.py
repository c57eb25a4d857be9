"""The huey queue of inspection jobs (SQLite storage under the data dir).

The web process only enqueues ids; the consumer process (:mod:`app.worker`) runs them. The
inspection row is the source of truth: a message only carries the id, and the job claims the
row under a lease before working (:mod:`app.jobs.execution`), so a message delivered twice
changes nothing; at consumer start the queue is rebuilt from the rows.
"""

from __future__ import annotations

import logging

from huey import SqliteHuey
from sqlalchemy.orm import Session, sessionmaker

from app.jobs.execution import execute_inspection
from app.services import inspections as svc
from app.settings import Settings
from app.storage import Storage

log = logging.getLogger(__name__)

TASK_NAME = "run_inspection"


class JobQueue:
    """The huey queue of inspection jobs, shared by the web process (enqueue) and the consumer (run).

    Parameters
    ----------
    settings : Settings
    session_factory : sessionmaker
        Sessions on the service database (each job opens its own).
    storage : Storage
    immediate : bool
        Run tasks in the calling thread (unit tests of the job body only).
    """

    def __init__(self, settings: Settings, session_factory: sessionmaker[Session], storage: Storage, *, immediate=False):
        settings.data_dir.mkdir(parents=True, exist_ok=True)
        self.settings = settings
        self.session_factory = session_factory
        self.storage = storage
        self.huey = SqliteHuey(
            name="plate-inspect", filename=str(settings.huey_path), results=False, immediate=immediate
        )
        self._task = self.huey.task(name=TASK_NAME)(self._run_task)

    # ------------------------------------------------------------ web process and consumer

    def enqueue(self, inspection_id: int) -> None:
        """Queue the job of a committed inspection row."""
        self._task(int(inspection_id))

    def pending_count(self) -> int:
        """Messages waiting in the queue file."""
        return self.huey.pending_count()

    def rebuild(self) -> list[int]:
        """Queue every queued row again, oldest first."""
        with self.session_factory() as session:
            ids = svc.queued_ids(session=session)
        for inspection_id in ids:
            self.enqueue(inspection_id)
        if ids:
            log.info("queued from the database: inspections %s", ids)
        return ids

    # ------------------------------------------------------------ consumer

    def requeue_interrupted(self, *, owner: str) -> list[int]:
        """Consumer start (the only consumer): reclaim jobs of dead consumers, rebuild the queue.

        Jobs left running lost their consumer: each counts a worker death and is queued again at the
        back, or set aside as failed at the second (:func:`app.services.inspections.reclaim_expired`).
        The queue file is then emptied and every queued row queued again in queue order, so the
        database alone decides what runs.

        Returns
        -------
        list of int
            The queued ids, in the order they were queued.
        """
        with self.session_factory() as session:
            reclaimed = svc.requeue_interrupted(session=session, owner=owner)
            session.commit()
        for inspection_id in reclaimed.requeued:
            log.warning("inspection %s: its worker died while running it; queued again (behind the others)",
                        inspection_id)
        for inspection_id in reclaimed.set_aside:
            log.error("inspection %s: set aside as failed: its worker died %d times while running it "
                      "(the reason and last stage are in its error; its inputs are kept)",
                      inspection_id, svc.MAX_WORKER_DEATHS)
        self.huey.storage.flush_queue()
        return self.rebuild()

    def create_consumer(self, **options):
        """A huey consumer of this queue (one worker thread by default; the pipeline uses the cores)."""
        defaults = dict(workers=1, worker_type="thread", periodic=False, max_delay=1.0, initial_delay=0.1)
        defaults.update(options)
        return self.huey.create_consumer(**defaults)

    def _run_task(self, inspection_id: int) -> None:
        execute_inspection(
            inspection_id, settings=self.settings, session_factory=self.session_factory, storage=self.storage
        )

