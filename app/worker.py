"""The job consumer process: ``python -m app.worker [--parent-pid PID] [--cell ID]``.

``plate-inspect serve`` starts it (unless ``--no-worker``); ``plate-inspect worker`` is it alone.

Reads the same ``PLATE_INSPECT_*`` settings as the web process. In order, it:

1. with ``--parent-pid`` (given by ``serve``), arranges to stop when that server dies
   (:func:`app.jobs.guards.exit_with_parent`);
2. bounds its address space to ``PLATE_INSPECT_WORKER_MEMORY_MB`` (:mod:`app.jobs.memory`);
3. on the embedded queue, takes the data dir's consumer lock, waiting while another consumer
   holds it (:class:`app.jobs.guards.ConsumerLock`); a shared (Redis) queue has many workers;
4. upgrades the database (waiting while it is unreachable), opens the queue (a corrupt queue
   file is moved aside and rebuilt); on the embedded queue it reclaims the jobs that were
   running when a previous consumer died (each counts a worker death; the second sets the job
   aside as failed) and queues every queued row again, oldest first; on a shared queue it
   reclaims only jobs whose lease ran out and queues rows whose message is missing;
5. runs huey's consumer (one worker thread; with ``--cell`` one more for that cell's
   acquisition queue, one job at a time), and a thread that reclaims expired leases every
   quarter of the lease and queues again, every 30 s, queued rows whose message was lost
   (:meth:`app.jobs.queue.JobQueue.sweep_until`).

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
import time

from app.db import database_unavailable, make_engine, make_session_factory, upgrade_database
from app.jobs import JobQueue, warm_up_entry
from app.jobs.guards import ConsumerLock, exit_with_parent
from app.jobs.memory import MemoryLimitError, apply_memory_limit
from app.services import leases as svc
from app.settings import Settings
from app.storage import Storage
from pipeline.parallel import configure_process

log = logging.getLogger("app.worker")

#: Exit status for a configuration the consumer cannot run with (``EX_CONFIG`` of sysexits.h).
EXIT_CONFIG = 78
#: Seconds between two attempts to reach the database at start.
DB_RETRY_S = 5.0


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        prog="python -m app.worker", description="The inspection job consumer."
    )
    parser.add_argument(
        "--parent-pid",
        type=int,
        default=None,
        help="stop when this process (the server that started the consumer) dies",
    )
    parser.add_argument(
        "--cell",
        default=None,
        metavar="ID",
        help="also run the acquisition jobs of cell ID (shared queue only; PLATE_INSPECT_CELL_CONFIG "
        "must name that cell)",
    )
    return parser.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    configure_process()  # the inspections' thread policy, before any kernel runs
    logging.basicConfig(
        level=logging.INFO,
        format="%(asctime)s %(levelname)s [worker %(process)d] %(name)s: %(message)s",
        force=True,  # under `plate-inspect worker` the CLI configured logging already
    )
    if args.parent_pid is not None:
        exit_with_parent(args.parent_pid)
    settings = Settings()
    try:
        apply_memory_limit(settings.worker_memory_mb)
        check_cell(settings, args.cell)
    except (MemoryLimitError, ValueError) as err:
        log.error("%s", err)
        return EXIT_CONFIG
    owner = svc.process_lease_owner()
    storage = Storage(settings.data_dir)
    storage.ensure()
    if settings.queue_url is None:
        ConsumerLock(storage.data_dir, owner=owner).acquire()  # held until this process ends
    wait_for_database(settings.sqlalchemy_url)
    engine = make_engine(settings.sqlalchemy_url)
    session_factory = make_session_factory(engine)
    queue = JobQueue(settings, session_factory, storage)
    # the compiled kernels loaded (and, on a fresh install, compiled) before the first job is claimed
    loaded = warm_up_entry(settings.inspect_entry)
    if loaded is not None:
        log.info("kernels loaded (%.1f s)", loaded)
    if queue.shared:
        queue.start_shared()
    else:
        queue.requeue_interrupted(owner=owner)
    run_consumers(queue, settings, owner=owner, cell_id=args.cell)
    # Stopped (SIGTERM: the worker thread may still be inside a job): give its job back.
    with session_factory() as session:
        released = svc.release(session=session, owner=owner)
        session.commit()
    if released:
        log.info("inspections %s back in the queue (stopped, not a worker death)", released)
    engine.dispose()
    return 0


def run_consumers(queue: JobQueue, settings: Settings, *, owner: str, cell_id: str | None) -> None:
    """Run huey's consumer until a signal stops it, with the sweeper thread; with ``cell_id``
    also a consumer of that cell's acquisition queue (threads; one job at a time)."""
    stop_sweeping = threading.Event()
    threading.Thread(
        target=queue.sweep_until, args=(stop_sweeping,), name="queue-sweep", daemon=True
    ).start()
    cell_consumer = None
    if cell_id is not None:
        cell_consumer = queue.create_consumer(cell_id=cell_id)
        cell_consumer.start()  # its signal handlers are replaced by the main consumer's below
    consumer = queue.create_consumer()
    log.info(
        "consumer ready (%s, queue %s%s, lease %.0f s, memory limit %s)",
        owner,
        "redis (shared)" if queue.shared else "sqlite (embedded)",
        f", cell {cell_id}" if cell_id else "",
        settings.job_lease_s,
        f"{settings.worker_memory_mb} MiB" if settings.worker_memory_mb else "none",
    )
    consumer.run()
    if cell_consumer is not None:
        cell_consumer.stop()
    stop_sweeping.set()


def check_cell(settings: Settings, cell_id: str | None) -> None:
    """``--cell`` needs a shared queue and the cell's config; ValueError naming the setting otherwise."""
    if cell_id is None:
        return
    if settings.queue_url is None:
        raise ValueError(
            "--cell: the embedded queue has one consumer that runs every job; set "
            "PLATE_INSPECT_QUEUE_URL for workers of a shared queue"
        )
    from app.services.cell import CellUnavailable, load_cell

    try:
        configured = load_cell(settings).cell_id
    except CellUnavailable as err:
        raise ValueError(f"--cell {cell_id}: {err}") from None
    if configured != cell_id:
        raise ValueError(
            f"--cell {cell_id}: PLATE_INSPECT_CELL_CONFIG names cell {configured!r}; a worker runs "
            "the acquisitions of the cell whose cameras it reaches"
        )


def wait_for_database(url: str, *, retry_s: float = DB_RETRY_S) -> None:
    """Upgrade the database to the current schema, retrying while it cannot be reached (logged)."""
    while True:
        try:
            upgrade_database(url)
            return
        except Exception as err:
            if not database_unavailable(err):
                raise
            log.warning(
                "database unreachable (%s); retrying in %.0f s", str(err).splitlines()[0], retry_s
            )
            time.sleep(retry_s)


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
