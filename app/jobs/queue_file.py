"""The huey queue's SQLite file: checked when a process opens it, moved aside and rebuilt if corrupt.

The queue holds nothing the database does not: each message is an inspection id whose row says
``queued``. A corrupt ``huey.db`` ("database disk image is malformed", junk written over it, a
truncated copy) is therefore moved aside as ``huey.db.corrupt-<UTC timestamp>`` (kept for a
post-mortem), a new file is created, and the caller re-queues the queued rows. The web process
and the consumer both check, whichever opens the file first; an exclusive ``flock`` on
``huey.db.lock`` makes the check, the move and the new file's creation one step, so two processes
never both move it (the second finds the new file sound).
"""

from __future__ import annotations

import logging
import os
import sqlite3
from collections.abc import Iterator
from contextlib import contextmanager
from datetime import UTC, datetime
from pathlib import Path

from app.locks import file_lock

log = logging.getLogger(__name__)

#: Seconds a check waits for another process's write lock on the queue file.
CHECK_TIMEOUT_S = 10.0


@contextmanager
def queue_file_lock(path: Path) -> Iterator[None]:
    """Hold the exclusive lock of the queue file ``path`` (``<path>.lock``; freed by the kernel if the holder dies)."""
    path = Path(path)
    with file_lock(path.with_name(path.name + ".lock")):
        yield


def queue_file_problem(path: Path) -> str | None:
    """Why the SQLite file ``path`` cannot be used, or None when it is sound (or absent: it will be created).

    Runs SQLite's ``PRAGMA quick_check`` (structure of every page and index, not the contents).
    """
    path = Path(path)
    if not path.exists():
        return None
    try:
        conn = sqlite3.connect(f"file:{path}?mode=rw", uri=True, timeout=CHECK_TIMEOUT_S)
    except sqlite3.Error as err:
        return str(err)
    try:
        rows = [row[0] for row in conn.execute("PRAGMA quick_check").fetchall()]
    except sqlite3.OperationalError as err:
        if "locked" in str(err) or "busy" in str(err):
            return None  # another process writes to it: readable enough to be in use
        return str(err)
    except sqlite3.DatabaseError as err:
        return str(err)
    finally:
        conn.close()
    if rows != ["ok"]:
        return "; ".join(str(r) for r in rows[:3])
    return None


def move_aside(path: Path, *, now: datetime | None = None) -> Path:
    """Rename ``path`` (and its ``-wal``/``-shm`` companions) to ``<name>.corrupt-<UTC timestamp>``.

    Returns the new path of the main file; an existing name gets a ``-2``, ``-3``... suffix.
    """
    path = Path(path)
    stamp = (now or datetime.now(UTC)).strftime("%Y%m%dT%H%M%SZ")
    aside = path.with_name(f"{path.name}.corrupt-{stamp}")
    n = 1
    while aside.exists():
        n += 1
        aside = path.with_name(f"{path.name}.corrupt-{stamp}-{n}")
    os.replace(path, aside)
    for suffix in ("-wal", "-shm"):
        companion = path.with_name(path.name + suffix)
        if companion.exists():
            os.replace(companion, aside.with_name(aside.name + suffix))
    return aside


def repair_if_corrupt(path: Path) -> Path | None:
    """Move a corrupt queue file aside (call it holding :func:`queue_file_lock`).

    Returns the path it was moved to, or None when the file is sound or absent. Logs at ERROR:
    the operator should know that the disk or a process damaged the queue.
    """
    path = Path(path)
    problem = queue_file_problem(path)
    if problem is None:
        return None
    aside = move_aside(path)
    log.error(
        "job queue file %s is unusable (%s): moved aside as %s; a new queue is rebuilt from the inspections "
        "in the database (queued jobs are queued again, nothing is lost)",
        path.name,
        problem,
        aside.name,
    )
    return aside
