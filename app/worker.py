"""The job consumer process: ``python -m app.worker [--parent-pid PID]`` (``plate-inspect serve`` starts it).

Reads the same ``PLATE_INSPECT_*`` settings as the web process. In order, it:

1. with ``--parent-pid`` (given by ``serve``), arranges to stop when that server dies
   (:func:`app.jobs.guards.exit_with_parent`);
2. bounds its address space to ``PLATE_INSPECT_WORKER_MEMORY_MB`` (:mod:`app.jobs.memory`);
3. takes the data dir's consumer lock, waiting while another consumer holds it
   (:class:`app.jobs.guards.ConsumerLock`);
4. upgrades the database, opens the queue (a corrupt queue file is moved aside and rebuilt),
   reclaims the jobs that were running when a previous consumer died (each counts a worker death;
   the second sets the job aside as failed) and queues every queued row again, oldest first;
5. runs huey's consumer (one worker thread), and a thread that queues again, every 30 s, queued
   rows whose message was lost (:meth:`app.jobs.queue.JobQueue.sweep`).

SIGTERM (also what a dying server sends) stops it at once: the job it was running goes back to
the queue in its place, and that is not counted as a worker death. SIGINT waits for the job.

Exit status: 0 after a stop, :data:`EXIT_CONFIG` for a setting it cannot run with (the
supervisor does not restart it then), 1 when its server was gone before it started.
"""

from __future__ import annotations

import argparse
import logging
import sys
import threading

from app.db import make_engine, make_session_factory, upgrade_database
from app.jobs import JobQueue
from app.jobs.guards import ConsumerLock, exit_with_parent
from app.jobs.memory import MemoryLimitError, apply_memory_limit
from app.services import inspections as svc
from app.settings import Settings
from app.storage import Storage
from pipeline.parallel import configure_process

log = logging.getLogger("app.worker")

#: Exit status for a configuration the consumer cannot run with (``EX_CONFIG`` of sysexits.h).
EXIT_CONFIG = 78


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m app.worker", description="The inspection job consumer."
    )
    parser.add_argument(
        "--parent-pid",
        type=int,
        default=None,
        help="stop when this process (the server that started the consumer) dies",
    )
    args = parser.parse_args(argv)
    configure_process()  # the inspections' thread policy, before any kernel runs
    logging.basicConfig(
        level=logging.INFO,
        format="%(asctime)s %(levelname)s [worker %(process)d] %(name)s: %(message)s",
    )
    if args.parent_pid is not None:
        exit_with_parent(args.parent_pid)
    settings = Settings()
    try:
        apply_memory_limit(settings.worker_memory_mb)
    except MemoryLimitError as err:
        log.error("%s", err)
        return EXIT_CONFIG
    owner = svc.process_lease_owner()
    storage = Storage(settings.data_dir)
    storage.ensure()
    ConsumerLock(storage.data_dir, owner=owner).acquire()  # held until this process ends
    upgrade_database(settings.sqlalchemy_url)
    engine = make_engine(settings.sqlalchemy_url)
    session_factory = make_session_factory(engine)
    queue = JobQueue(settings, session_factory, storage)
    queue.requeue_interrupted(owner=owner)
    stop_sweeping = threading.Event()
    threading.Thread(
        target=queue.sweep_until, args=(stop_sweeping,), name="queue-sweep", daemon=True
    ).start()
    consumer = queue.create_consumer()
    log.info(
        "consumer ready (%s, memory limit %s)",
        owner,
        f"{settings.worker_memory_mb} MiB" if settings.worker_memory_mb else "none",
    )
    consumer.run()
    stop_sweeping.set()
    # Stopped (SIGTERM: the worker thread may still be inside a job): give its job back.
    with session_factory() as session:
        released = svc.release(session=session, owner=owner)
        session.commit()
    if released:
        log.info("inspections %s back in the queue (stopped, not a worker death)", released)
    engine.dispose()
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
