"""The huey queue of inspection jobs (SQLite storage under the data dir).

The web process only enqueues ids; the consumer process (:mod:`app.worker`) runs them. The
inspection row is the source of truth: a message only carries the id, and the job claims the
row under a lease before working (:mod:`app.jobs.execution`), so a message delivered twice
changes nothing, and a message lost (a failed write, a corrupt queue file moved aside) is queued
again from the rows: at consumer start, by the process that repairs the file, and by the
consumer's periodic :meth:`JobQueue.sweep`.
"""

from __future__ import annotations

import logging
import os
import sqlite3
import threading
from datetime import timedelta
from pathlib import Path

from huey import SqliteHuey
from sqlalchemy.orm import Session, sessionmaker

from app.jobs.execution import execute_inspection
from app.jobs.queue_file import queue_file_lock, repair_if_corrupt
from app.models import utcnow
from app.services import inspections as svc
from app.settings import Settings
from app.storage import Storage

log = logging.getLogger(__name__)

TASK_NAME = "run_inspection"
#: Seconds between two sweeps of the consumer (:meth:`JobQueue.sweep_until`).
SWEEP_S = 30.0
#: A queued row younger than this (s) may still be on its way into the queue: not swept.
SWEEP_MIN_AGE_S = 10.0


class JobQueue:
    """The huey queue of inspection jobs, shared by the web process (enqueue) and the consumer (run).

    Opening it checks the queue file: a corrupt one is moved aside, recreated, and the queued rows
    are queued again (:mod:`app.jobs.queue_file`). A queue file that fails later is repaired the
    same way by the process that meets the failure; the others follow the new file when they
    next use the queue.

    Parameters
    ----------
    settings : Settings
    session_factory : sessionmaker
        Sessions on the service database (each job opens its own).
    storage : Storage
    immediate : bool
        Run tasks in the calling thread (unit tests of the job body only).
    """

    def __init__(
        self,
        settings: Settings,
        session_factory: sessionmaker[Session],
        storage: Storage,
        *,
        immediate=False,
    ):
        settings.data_dir.mkdir(parents=True, exist_ok=True)
        self.settings = settings
        self.session_factory = session_factory
        self.storage = storage
        self.path = Path(settings.huey_path)
        with queue_file_lock(self.path):
            aside = repair_if_corrupt(self.path)
            # huey creates the file and its tables here, still under the lock.
            self.huey = SqliteHuey(
                name="plate-inspect", filename=str(self.path), results=False, immediate=immediate
            )
            self._inode = _inode(self.path)
        self._task = self.huey.task(name=TASK_NAME)(self._run_task)
        #: This process moved a corrupt queue file aside (and rebuilt the queue from the rows).
        self.repaired = aside is not None
        if self.repaired:
            self.rebuild()

    # ------------------------------------------------------------ web process and consumer

    def enqueue(self, inspection_id: int) -> None:
        """Queue the job of a committed inspection row.

        A queue file that fails is repaired (:meth:`repair`) and the message written again; if the
        write still fails it is logged at ERROR, not raised: the row stays queued in the database
        and the consumer's sweep queues it again.
        """
        self._follow_replaced_file()
        try:
            self._task(int(inspection_id))
            return
        except sqlite3.DatabaseError:
            log.exception("inspection %s: the job queue file failed", inspection_id)
        if not self.repair():  # a file moved aside: the rebuild queued this row too
            self._put(int(inspection_id))

    def pending_count(self) -> int:
        """Messages waiting in the queue file."""
        return self.huey.pending_count()

    def repair(self) -> bool:
        """Check the queue file now: a corrupt one is moved aside, recreated and rebuilt from the rows.

        Returns
        -------
        bool
            Whether the file was moved aside.
        """
        with queue_file_lock(self.path):
            aside = repair_if_corrupt(self.path)
            self._reopen()
        if aside is not None:
            self.repaired = True
            self.rebuild()
        return aside is not None

    def rebuild(self) -> list[int]:
        """Queue every queued row again, oldest first (after the queue file was recreated)."""
        with self.session_factory() as session:
            ids = svc.queued_ids(session=session)
        for inspection_id in ids:
            self._put(inspection_id)
        if ids:
            log.info("queued from the database: inspections %s", ids)
        return ids

    # ------------------------------------------------------------ consumer

    def requeue_interrupted(self, *, owner: str) -> list[int]:
        """Consumer start (holding the consumer lock): reclaim jobs of dead consumers, rebuild the queue.

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
            log.warning(
                "inspection %s: its worker died while running it; queued again (behind the others)",
                inspection_id,
            )
        for inspection_id in reclaimed.set_aside:
            log.error(
                "inspection %s: set aside as failed: its worker died %d times while running it "
                "(the reason and last stage are in its error; its inputs are kept)",
                inspection_id,
                svc.MAX_WORKER_DEATHS,
            )
        self.huey.storage.flush_queue()
        return self.rebuild()

    def sweep(self, *, min_age_s: float = SWEEP_MIN_AGE_S) -> list[int]:
        """Queue again the queued rows that have no message in the queue (lost), oldest first.

        Rows queued less than ``min_age_s`` ago are left alone (their web process may be writing
        their message). A queue file that fails is repaired. Returns the ids queued again.
        """
        self._follow_replaced_file()
        try:
            pending = {task.args[0] for task in self.huey.pending() if task.args}
        except sqlite3.DatabaseError:
            log.exception("the job queue file failed")
            self.repair()
            return []
        with self.session_factory() as session:
            ids = svc.queued_ids(
                session=session, queued_before=utcnow() - timedelta(seconds=min_age_s)
            )
        missing = [inspection_id for inspection_id in ids if inspection_id not in pending]
        for inspection_id in missing:
            self._put(inspection_id)
        if missing:
            log.warning(
                "inspections %s were queued in the database but not in the job queue: queued again",
                missing,
            )
        return missing

    def sweep_until(self, stop: threading.Event, *, interval_s: float = SWEEP_S) -> None:
        """Run :meth:`sweep` every ``interval_s`` until ``stop`` is set (the consumer's sweeper thread)."""
        while not stop.wait(interval_s):
            try:
                self.sweep()
            except Exception:
                log.exception("job queue sweep failed")

    def create_consumer(self, **options):
        """A huey consumer of this queue (one worker thread by default; the pipeline uses the cores)."""
        defaults = dict(
            workers=1, worker_type="thread", periodic=False, max_delay=1.0, initial_delay=0.1
        )
        defaults.update(options)
        return self.huey.create_consumer(**defaults)

    # ------------------------------------------------------------ internals

    def _put(self, inspection_id: int) -> bool:
        try:
            self._task(int(inspection_id))
        except sqlite3.DatabaseError:
            log.exception(
                "inspection %s: could not be written to the job queue; it stays queued in the database "
                "and the consumer's sweep queues it again",
                inspection_id,
            )
            return False
        return True

    def _follow_replaced_file(self) -> None:
        """Reopen the queue file if another process replaced it (moved a corrupt one aside)."""
        if _inode(self.path) != self._inode:
            with queue_file_lock(self.path):
                self._reopen()

    def _reopen(self) -> None:
        """Close the connection and open the file at the queue's path (creating its tables); hold the lock."""
        storage = self.huey.storage
        storage.close()
        storage.initialize_schema()
        self._inode = _inode(self.path)

    def _run_task(self, inspection_id: int) -> None:
        execute_inspection(
            inspection_id,
            settings=self.settings,
            session_factory=self.session_factory,
            storage=self.storage,
        )


def _inode(path: Path) -> int | None:
    try:
        return os.stat(path).st_ino
    except FileNotFoundError:
        return None
