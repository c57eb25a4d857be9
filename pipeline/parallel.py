"""Process policy: how many worker threads the pipeline uses, and how OpenMP's threads wait.

The library sets nothing process-wide on import. Its functions that run work beside their main
line take a ``workers`` count whose default comes from :func:`default_workers`; the entry points
(``plate-inspect``'s :func:`pipeline.cli.main`, the service's job consumer) call
:func:`configure_process` once at start, before any compiled kernel runs.
"""

from __future__ import annotations

import os

#: Environment variable that overrides the number of worker threads (an integer >= 1).
WORKERS_ENV = "PLATE_INSPECT_WORKERS"


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
    """
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
