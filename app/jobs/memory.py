"""The consumer's memory bound: ``PLATE_INSPECT_WORKER_MEMORY_MB`` as ``RLIMIT_AS``.

Set once when the consumer starts (:func:`apply_memory_limit`): an allocation beyond it fails in
the job (``MemoryError`` from numpy, ``Insufficient memory`` from OpenCV, a thread that cannot
start; :func:`is_out_of_memory`) instead of the kernel's OOM killer ending the consumer, so the
job ends ``failed`` with :func:`out_of_memory_message` and the consumer takes the next one. The
limit counts address space, not resident memory.
"""

from __future__ import annotations

import resource
import sys

#: The setting, as operators know it.
SETTING = "PLATE_INSPECT_WORKER_MEMORY_MB"
#: Address space a limit must leave the consumer beyond what it maps before its first job, MiB.
MIN_HEADROOM_MB = 256


class MemoryLimitError(ValueError):
    """The configured limit is too low for the consumer to run at all."""


def mapped_mb() -> float:
    """Address space this process maps now (``VmSize``), MiB."""
    with open("/proc/self/status", encoding="ascii") as fh:
        for line in fh:
            if line.startswith("VmSize:"):
                return int(line.split()[1]) / 1024.0
    raise RuntimeError("/proc/self/status has no VmSize")


def apply_memory_limit(limit_mb: int) -> None:
    """Limit this process's address space to ``limit_mb`` MiB (0: leave it unlimited).

    Raises
    ------
    MemoryLimitError
        The limit does not leave :data:`MIN_HEADROOM_MB` above what the process maps already, or
        exceeds the hard limit the process was started with.
    """
    if limit_mb == 0:
        return
    used = mapped_mb()
    if limit_mb < used + MIN_HEADROOM_MB:
        raise MemoryLimitError(
            f"{SETTING}: expected at least {used + MIN_HEADROOM_MB:.0f} MiB (the consumer maps {used:.0f} MiB "
            f"before its first job), got {limit_mb}"
        )
    _, hard = resource.getrlimit(resource.RLIMIT_AS)
    limit = int(limit_mb) * 1024 * 1024
    if hard != resource.RLIM_INFINITY and limit > hard:
        raise MemoryLimitError(
            f"{SETTING}: expected at most {hard // (1024 * 1024)} MiB (the hard limit of the consumer's "
            f"environment), got {limit_mb}"
        )
    resource.setrlimit(resource.RLIMIT_AS, (limit, hard))


def is_out_of_memory(err: BaseException) -> bool:
    """Whether ``err`` is an allocation that failed: Python/numpy ``MemoryError``, OpenCV ``StsNoMem``,
    or a thread whose stack could not be mapped (``RuntimeError: can't start new thread``)."""
    if isinstance(err, MemoryError):
        return True
    if isinstance(err, RuntimeError) and "can't start new thread" in str(err):
        return True
    cv2 = sys.modules.get("cv2")
    return (
        cv2 is not None
        and isinstance(err, cv2.error)
        and getattr(err, "code", None) == cv2.Error.StsNoMem
    )


def out_of_memory_message(limit_mb: int) -> str:
    """The error stored on a job that ran out of memory."""
    if limit_mb:
        return f"out of memory: the job needed more than {limit_mb} MiB ({SETTING})"
    return f"out of memory: the machine could not give the job the memory it asked for ({SETTING} is 0, no limit)"
