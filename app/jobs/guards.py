"""Guards of the consumer process: one consumer per data dir, and none outliving its server.

- :class:`ConsumerLock`: an exclusive ``flock`` on ``<data dir>/consumer.lock``, held for the
  consumer's life; the kernel frees it when the holder dies, however it dies. A second consumer
  waits for it (logging who holds it) and takes over when the first is gone. This guards the
  embedded SQLite queue only: a shared queue with many workers (Redis) relies on job leases.
- :func:`exit_with_parent`: the consumer started by ``plate-inspect serve`` stops when its server
  dies, even by SIGKILL: the kernel sends it SIGTERM (``prctl(PR_SET_PDEATHSIG)``), and a thread
  watching the parent pid does the same should the kernel's signal not come (the parent died
  before the ``prctl``, or the thread that started the consumer ended).
"""

from __future__ import annotations

import ctypes
import ctypes.util
import errno
import fcntl
import logging
import os
import signal
import socket
import threading
import time
from datetime import UTC, datetime
from pathlib import Path

log = logging.getLogger(__name__)

#: ``PR_SET_PDEATHSIG`` of ``<sys/prctl.h>``.
PR_SET_PDEATHSIG = 1
#: Seconds between two looks at the lock or the parent pid.
POLL_S = 0.5
#: Seconds between two log lines of a consumer waiting for the lock.
WAIT_LOG_S = 30.0

LOCK_FILE = "consumer.lock"


class ConsumerLock:
    """The single-consumer lock of a data dir (see the module docstring).

    Once taken it is held until the process ends (its descriptor is never closed): a consumer
    stopped by SIGTERM may still be inside a job for a moment, and no other consumer must start
    that job again before it is gone.

    Parameters
    ----------
    data_dir : Path
    owner : str
        Written into the lock file while held, with the pid and the time, for the log of a waiting consumer.
    """

    def __init__(self, data_dir: Path, *, owner: str):
        self.path = Path(data_dir) / LOCK_FILE
        self.owner = owner
        self.held = False

    def try_acquire(self) -> bool:
        """Take the lock if it is free; False if another process holds it."""
        if self.held:
            return True
        self.path.parent.mkdir(parents=True, exist_ok=True)
        fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as err:
            os.close(fd)
            if err.errno in (errno.EAGAIN, errno.EACCES):
                return False
            raise
        since = datetime.now(UTC).isoformat(timespec="seconds")
        os.ftruncate(fd, 0)
        os.pwrite(
            fd,
            f"consumer {self.owner} (pid {os.getpid()} on {socket.gethostname()}) since {since}\n".encode(),
            0,
        )
        self.held = True  # fd stays open: the kernel frees the lock when this process ends
        return True

    def holder(self) -> str:
        """Who holds the lock, as its holder wrote it (empty if unknown)."""
        try:
            return self.path.read_text(encoding="utf-8").strip()
        except OSError:
            return ""

    def acquire(self) -> None:
        """Take the lock, waiting as long as another consumer holds it (logging who, every 30 s)."""
        waited = False
        last_log = float("-inf")
        while not self.try_acquire():
            now = time.monotonic()
            if now - last_log >= WAIT_LOG_S:
                log.warning(
                    "another consumer runs on this data dir (%s); waiting for it to stop",
                    self.holder() or "holder unknown",
                )
                last_log = now
            waited = True
            time.sleep(POLL_S)
        if waited:
            log.info("consumer lock taken: the previous consumer has stopped")


def exit_with_parent(parent_pid: int) -> threading.Thread:
    """Have this process get SIGTERM when ``parent_pid`` (its parent) dies.

    Sets ``PR_SET_PDEATHSIG`` to SIGTERM, then starts :func:`watch_parent`. Exits at once
    (status 1) if the parent is gone already.

    Returns
    -------
    threading.Thread
        The watching thread.
    """
    _set_pdeathsig(signal.SIGTERM)
    if os.getppid() != parent_pid:
        log.error("the server (pid %s) is gone; the consumer exits", parent_pid)
        raise SystemExit(1)
    return watch_parent(parent_pid)


def watch_parent(parent_pid: int) -> threading.Thread:
    """Start a daemon thread that sends SIGTERM to this process once its parent pid is no longer ``parent_pid``."""
    thread = threading.Thread(
        target=_watch_parent, args=(parent_pid,), name="parent-watch", daemon=True
    )
    thread.start()
    return thread


def _set_pdeathsig(signum: int) -> None:
    libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
    if libc.prctl(PR_SET_PDEATHSIG, int(signum), 0, 0, 0) != 0:
        err = ctypes.get_errno()
        log.warning(
            "prctl(PR_SET_PDEATHSIG) failed (%s); the parent watch thread stands in",
            os.strerror(err),
        )


def _watch_parent(parent_pid: int) -> None:
    while os.getppid() == parent_pid:
        time.sleep(POLL_S)
    log.warning("the server (pid %s) is gone; stopping the consumer", parent_pid)
    os.kill(os.getpid(), signal.SIGTERM)
