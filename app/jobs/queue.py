"""The huey queue of inspection jobs: SQLite storage under the data dir, or Redis in a yard.

The web process only enqueues ids; the consumer processes (:mod:`app.worker`) run them. The
inspection row is the source of truth: a message only carries the id, and the job claims the
row under a lease before working (:mod:`app.jobs.execution`), so a message delivered twice
changes nothing, and a message lost (a failed write, a corrupt queue file moved aside) is queued
again from the rows: at consumer start, by the process that repairs the file, and by the
consumer's periodic :meth:`JobQueue.sweep`.

On Redis (``PLATE_INSPECT_QUEUE_URL``) any number of workers share the queue: none holds a lock,
each reclaims (:meth:`JobQueue.reclaim`) the jobs whose lease ran out (a worker that died) and
queues them again. An acquisition job (its row has a ``cell_id``) goes to its cell's own queue
(``plate-inspect.cell.<id>``), consumed only by a worker started with ``--cell <id>``; the
embedded queue has one consumer, the cell's own, and one queue.
"""

from __future__ import annotations

import logging
import os
import sqlite3
import threading
import time
from datetime import timedelta
from pathlib import Path
from typing import Any

from huey import RedisHuey, SqliteHuey
from huey.api import Huey, TaskWrapper
from huey.consumer import Consumer
from sqlalchemy import select
from sqlalchemy.orm import Session, sessionmaker

from app.jobs.execution import execute_inspection
from app.jobs.queue_file import queue_file_lock, repair_if_corrupt
from app.models import Inspection, utcnow
from app.services import leases as svc
from app.settings import Settings
from app.storage import Storage

log = logging.getLogger(__name__)

TASK_NAME = "run_inspection"
#: Seconds between two sweeps of the consumer (:meth:`JobQueue.sweep_until`).
SWEEP_S = 30.0
#: A queued row younger than this (s) may still be on its way into the queue: not swept.
SWEEP_MIN_AGE_S = 10.0
#: Name of the general queue; a cell's acquisition queue is ``<name>.cell.<cell id>`` (Redis).
QUEUE_NAME = "plate-inspect"
try:  # the `yard` extra; without it only the embedded queue is usable
    from redis.exceptions import RedisError
except ImportError:  # pragma: no cover - the tests install the extra

    class RedisError(Exception):  # type: ignore[no-redef]
        """Stands in for redis' error when the client is not installed (never raised)."""


#: What a failing queue storage raises (a damaged SQLite file, an unreachable Redis).
QUEUE_ERRORS = (sqlite3.DatabaseError, RedisError)


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
        immediate: bool = False,
    ) -> None:
        settings.data_dir.mkdir(parents=True, exist_ok=True)
        self.settings = settings
        self.session_factory = session_factory
        self.storage = storage
        self.immediate = immediate
        #: A queue shared by many workers (Redis): no queue file, cell queues, leases reclaimed.
        self.shared = settings.queue_url is not None
        self.path = Path(settings.huey_path)
        self._cells: dict[str, tuple[Huey, TaskWrapper]] = {}
        self._one_job = threading.Lock()
        aside = None
        if self.shared:
            self.huey: Huey = RedisHuey(
                name=QUEUE_NAME, url=settings.queue_url, results=False, immediate=immediate
            )
        else:
            with queue_file_lock(self.path):
                aside = repair_if_corrupt(self.path)
                # huey creates the file and its tables here, still under the lock.
                self.huey = SqliteHuey(
                    name=QUEUE_NAME, filename=str(self.path), results=False, immediate=immediate
                )
                self._inode = _inode(self.path)
        self._task: TaskWrapper = self.huey.task(name=TASK_NAME)(self._run_task)
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
            self._task_for(self._cell_of(inspection_id))(int(inspection_id))
            return
        except QUEUE_ERRORS:
            log.exception("inspection %s: the job queue failed", inspection_id)
        if not self.repair():  # a file moved aside: the rebuild queued this row too
            self._put(int(inspection_id))

    def pending_count(self) -> int:
        """Messages waiting in the queue file."""
        return int(self.huey.pending_count())

    def repair(self) -> bool:
        """Check the queue file now: a corrupt one is moved aside, recreated and rebuilt from the rows.

        Returns
        -------
        bool
            Whether the file was moved aside (always False on Redis: nothing to repair).
        """
        if self.shared:
            return False
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
        cells = self._cells_of(ids)
        for inspection_id in ids:
            self._put(inspection_id, cells.get(inspection_id))
        if ids:
            log.info("queued from the database: inspections %s", ids)
        return ids

    # ------------------------------------------------------------ consumer

    def requeue_interrupted(self, *, owner: str) -> list[int]:
        """Consumer start (holding the consumer lock): reclaim jobs of dead consumers, rebuild the queue.

        Jobs left running lost their consumer: each counts a worker death and is queued again at the
        back, or set aside (error) at the second (:func:`app.services.leases.reclaim_expired`).
        The queue file is then emptied and every queued row queued again in queue order, so the
        database alone decides what runs.

        Returns
        -------
        list of int
            The queued ids, in the order they were queued.
        """
        if self.shared:
            raise RuntimeError("requeue_interrupted: only the embedded queue's one consumer may")
        with self.session_factory() as session:
            reclaimed = svc.requeue_interrupted(session=session, owner=owner)
            session.commit()
        self._log_reclaimed(reclaimed)
        self.huey.storage.flush_queue()
        return self.rebuild()

    def start_shared(self) -> list[int]:
        """A worker's start on a shared queue: reclaim expired leases, queue rows whose message is missing.

        Jobs running under a live lease belong to other workers and are left alone.
        """
        return self.reclaim() + self.sweep(min_age_s=SWEEP_MIN_AGE_S)

    def sweep(self, *, min_age_s: float = SWEEP_MIN_AGE_S) -> list[int]:
        """Queue again the queued rows that have no message in the queue (lost), oldest first.

        Rows queued less than ``min_age_s`` ago are left alone (their web process may be writing
        their message). A queue file that fails is repaired. Returns the ids queued again.
        """
        self._follow_replaced_file()
        with self.session_factory() as session:
            ids = svc.queued_ids(
                session=session, queued_before=utcnow() - timedelta(seconds=min_age_s)
            )
        cells = self._cells_of(ids)
        try:
            pending = self._pending_ids(set(cells.values()))
        except QUEUE_ERRORS:
            log.exception("the job queue failed")
            self.repair()
            return []
        missing = [inspection_id for inspection_id in ids if inspection_id not in pending]
        for inspection_id in missing:
            self._put(inspection_id, cells.get(inspection_id))
        if missing:
            log.warning(
                "inspections %s were queued in the database but not in the job queue: queued again",
                missing,
            )
        return missing

    def reclaim(self) -> list[int]:
        """Queue again the jobs whose lease ran out (their worker died); set aside the poison ones.

        Any worker may call it at any time: each row changes in one conditional UPDATE
        (:func:`app.services.leases.reclaim_expired`), so a job is reclaimed once. Returns
        the ids queued again.
        """
        with self.session_factory() as session:
            reclaimed = svc.reclaim_expired(session=session)
            session.commit()
        self._log_reclaimed(reclaimed)
        cells = self._cells_of(reclaimed.requeued)
        for inspection_id in reclaimed.requeued:
            self._put(inspection_id, cells.get(inspection_id))
        return reclaimed.requeued

    def sweep_until(self, stop: threading.Event, *, interval_s: float = SWEEP_S) -> None:
        """Until ``stop`` is set (the consumer's sweeper thread): :meth:`reclaim` every quarter of
        the job lease (at most every ``interval_s``), :meth:`sweep` every ``interval_s``."""
        tick_s = min(interval_s, self.settings.lease_s / 4.0)
        last_sweep = time.monotonic()
        while not stop.wait(tick_s):
            try:
                self.reclaim()
                if time.monotonic() - last_sweep >= interval_s:
                    last_sweep = time.monotonic()
                    self.sweep()
            except Exception:
                log.exception("job queue sweep failed (retried at the next tick)")

    def create_consumer(self, *, cell_id: str | None = None, **options: Any) -> Consumer:
        """A huey consumer of this queue (one worker thread by default; the pipeline uses the cores).

        With ``cell_id`` (shared queue only), a consumer of that cell's acquisition queue; a
        process running both runs one job at a time.
        """
        if cell_id is not None and not self.shared:
            raise ValueError(
                "--cell: only a shared queue (PLATE_INSPECT_QUEUE_URL) has cell queues"
            )
        defaults = {
            "workers": 1,
            "worker_type": "thread",
            "periodic": False,
            "max_delay": 1.0,
            "initial_delay": 0.1,
        }
        defaults.update(options)
        huey = self.huey if cell_id is None else self._huey_for(cell_id)[0]
        return huey.create_consumer(**defaults)

    # ------------------------------------------------------------ internals

    def _log_reclaimed(self, reclaimed: svc.Reclaimed) -> None:
        for inspection_id in reclaimed.requeued:
            log.warning(
                "inspection %s: its worker died while running it; queued again (behind the others)",
                inspection_id,
            )
        for inspection_id in reclaimed.set_aside:
            log.error(
                "inspection %s: set aside (error): its worker died %d times while running it "
                "(the reason and last stage are in its error; its inputs are kept)",
                inspection_id,
                svc.MAX_WORKER_DEATHS,
            )

    def _huey_for(self, cell_id: str) -> tuple[Huey, TaskWrapper]:
        """The huey and task of a cell's acquisition queue (Redis), created once."""
        if cell_id not in self._cells:
            huey = RedisHuey(
                name=f"{QUEUE_NAME}.cell.{cell_id}",
                url=self.settings.queue_url,
                results=False,
                immediate=self.immediate,
            )
            self._cells[cell_id] = (huey, huey.task(name=TASK_NAME)(self._run_task))
        return self._cells[cell_id]

    def _task_for(self, cell_id: str | None) -> TaskWrapper:
        return self._task if cell_id is None or not self.shared else self._huey_for(cell_id)[1]

    def _cell_of(self, inspection_id: int) -> str | None:
        return self._cells_of([inspection_id]).get(inspection_id) if self.shared else None

    def _cells_of(self, ids: list[int]) -> dict[int, str]:
        """The cell of each acquisition job among ``ids`` (shared queue only; others go to the general queue)."""
        if not self.shared or not ids:
            return {}
        with self.session_factory() as session:
            rows = session.execute(
                select(Inspection.id, Inspection.cell_id).where(
                    Inspection.id.in_(ids), Inspection.cell_id.is_not(None)
                )
            ).all()
        return {int(i): str(c) for i, c in rows}

    def _pending_ids(self, cells: set[str]) -> set[int]:
        """Inspection ids with a message waiting in the general queue or the given cells' queues."""
        hueys = [self.huey, *(self._huey_for(c)[0] for c in sorted(cells) if self.shared)]
        return {task.args[0] for huey in hueys for task in huey.pending() if task.args}

    def _put(self, inspection_id: int, cell_id: str | None = None) -> bool:
        try:
            self._task_for(cell_id)(int(inspection_id))
        except QUEUE_ERRORS:
            log.exception(
                "inspection %s: could not be written to the job queue; it stays queued in the database "
                "and the consumer's sweep queues it again",
                inspection_id,
            )
            return False
        return True

    def _follow_replaced_file(self) -> None:
        """Reopen the queue file if another process replaced it (moved a corrupt one aside)."""
        if self.shared:
            return
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
        with self._one_job:  # a worker consuming its cell's queue too still runs one job at a time
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
