"""The job consumer process: ``python -m app.worker`` (``plate-inspect serve`` starts it as a child).

Reads the same ``PLATE_INSPECT_*`` settings as the web process, upgrades the database, re-queues
jobs that were running when a previous consumer died, then runs huey's consumer (one worker).
SIGTERM stops it at once (a job it was running is re-queued at the next start); SIGINT waits
for the running job.
"""

from __future__ import annotations

import logging
import sys

from app.db import make_engine, make_session_factory, upgrade_database
from app.jobs import JobQueue
from app.settings import Settings
from app.storage import Storage

log = logging.getLogger("app.worker")


def main(argv: list[str] | None = None) -> int:
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s [worker %(process)d] %(name)s: %(message)s")
    settings = Settings()
    storage = Storage(settings.data_dir)
    storage.ensure()
    upgrade_database(settings.sqlalchemy_url)
    engine = make_engine(settings.sqlalchemy_url)
    queue = JobQueue(settings, make_session_factory(engine), storage)
    queue.requeue_interrupted()
    consumer = queue.create_consumer()
    log.info("consumer ready (data dir %s)", storage.data_dir)
    consumer.run()
    engine.dispose()
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
