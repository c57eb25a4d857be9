"""Process policy: how many worker threads the pipeline uses, and how OpenMP's threads wait.

The library sets nothing process-wide on import. Its functions that run work beside their main
line take a ``workers`` count whose default comes from :func:`default_workers`; the entry points
(``plate-inspect``'s :func:`pipeline.cli.main`, the service's job consumer) call
:func:`configure_process` once at start, before any compiled kernel runs.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import sys

#: Environment variable that overrides the number of worker threads (an integer >= 1).
WORKERS_ENV = "PLATE_INSPECT_WORKERS"

#: glibc malloc: blocks up to this many bytes come from the heap, where a freed block is reused,
#: instead of a fresh mapping that the kernel zeroes page by page on first touch (glibc's
#: largest allowed value, 32 MiB on 64-bit: an image of 1224x1024 float64 is 10 MB).
MALLOC_MMAP_THRESHOLD_BYTES = 32 * 2**20
#: glibc malloc: free memory at the top of the heap is given back to the system only beyond this.
MALLOC_TRIM_THRESHOLD_BYTES = 2**30
#: mallopt parameters (glibc's malloc.h).
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3


def default_workers() -> int:
    """The number of worker threads for work that runs beside the pipeline's main line.

    Returns
    -------
    int
        ``$PLATE_INSPECT_WORKERS`` when set, else the number of CPUs this process may run on.

    Raises
    ------
    ValueError
        ``PLATE_INSPECT_WORKERS`` is set but not an integer >= 1.
    """
    text = os.environ.get(WORKERS_ENV, "").strip()
    if text:
        try:
            workers = int(text)
        except ValueError:
            workers = 0
        if workers < 1:
            raise ValueError(f"{WORKERS_ENV}: expected an integer >= 1, got {text!r}")
        return workers
    if hasattr(os, "sched_getaffinity"):
        return len(os.sched_getaffinity(0))
    return os.cpu_count() or 1


def configure_process() -> None:
    """Set the process-wide thread policy of a process that runs inspections; call it once at start.

    The parallel numba kernels (OpenMP layer) leave their worker threads spinning after each
    parallel region unless told otherwise; on the cell's 2-core computer that spinning takes the
    second core from the work beside it (stereo, artifact writing; measured in docs/figures.md,
    *Speed, end to end*). ``OMP_WAIT_POLICY=PASSIVE`` is read by libgomp when it starts, so this
    must run before the first kernel; a value already set in the environment wins.

    An inspection allocates and frees images of several MB many times over: with glibc's default
    policy most of them are fresh mappings, and zeroing their pages took ~0.3 of the ~1.4
    core-seconds of an inspection at 1224x1024 (measured with ``perf``). :func:`keep_freed_memory`
    keeps freed blocks for reuse.
    """
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    keep_freed_memory()


def keep_freed_memory() -> bool:
    """Have glibc's malloc keep freed memory for reuse (see :data:`MALLOC_MMAP_THRESHOLD_BYTES`).

    The process then holds its peak of heap memory (up to :data:`MALLOC_TRIM_THRESHOLD_BYTES` of it
    free) instead of giving it back after each inspection. Nothing is changed when either setting
    is already given in the environment (``MALLOC_MMAP_THRESHOLD_``, ``MALLOC_TRIM_THRESHOLD_``),
    or off glibc.

    Returns
    -------
    bool
        Whether the policy was set.
    """
    if not sys.platform.startswith("linux") or any(
        name in os.environ for name in ("MALLOC_MMAP_THRESHOLD_", "MALLOC_TRIM_THRESHOLD_")
    ):
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):  # not glibc
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    return bool(
        mallopt(_M_MMAP_THRESHOLD, MALLOC_MMAP_THRESHOLD_BYTES)
        and mallopt(_M_TRIM_THRESHOLD, MALLOC_TRIM_THRESHOLD_BYTES)
    )
