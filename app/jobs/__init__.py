"""Background jobs: the pipeline run on an inspection, in a consumer process apart from the web.

The web process only enqueues ids (huey on SQLite under the data dir); the consumer process
(:mod:`app.worker`) runs them, so the pipeline's CPU work never starves the web server or the 3D
view. The inspection row is the source of truth; the modules, along their seams:

- :mod:`app.jobs.queue`: the huey queue (:class:`JobQueue`), rebuilt from the rows at consumer start;
- :mod:`app.jobs.queue_file`: a corrupt queue file moved aside and recreated;
- :mod:`app.jobs.execution`: one job (:func:`execute_inspection`), claimed under a lease;
- :class:`app.services.leases.LeaseKeeper` (the one lease module): the running job's lease, renewed by a heartbeat;
- :mod:`app.jobs.guards`: one consumer per data dir, none outliving its server;
- :mod:`app.jobs.memory`: the consumer's memory bound.
"""

from app.jobs.execution import (
    SIMULATE_STAGE,
    ProgressWriter,
    execute_inspection,
    render_simulated_bundle,
    warm_up_entry,
)
from app.jobs.queue import TASK_NAME, JobQueue

__all__ = [
    "SIMULATE_STAGE",
    "TASK_NAME",
    "JobQueue",
    "ProgressWriter",
    "execute_inspection",
    "render_simulated_bundle",
    "warm_up_entry",
]
