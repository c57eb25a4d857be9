"""The running job's lease, renewed by a heartbeat thread while the pipeline works.

A claim gives the consumer the job for ``Settings.job_lease_s`` seconds
(:func:`app.services.leases.claim`); :class:`LeaseKeeper` renews it every third of that,
so only a consumer that died or hung for a whole lease loses its job. A renewal the database
refuses means the lease was lost (another consumer reclaimed the job): it is logged, and the
job's later writes (progress, done, failed) are no-ops.
"""

from __future__ import annotations

import logging
import threading

from sqlalchemy.orm import Session, sessionmaker

from app.services import leases as svc

log = logging.getLogger(__name__)


class LeaseKeeper:
    """Renew the lease of one running job until :meth:`stop` (a context manager).

    Parameters
    ----------
    session_factory : sessionmaker
    inspection_id : int
    owner : str
        The lease owner (:func:`app.services.leases.process_lease_owner` in the consumer).
    lease_s : float
        Lease length, s; renewed every ``lease_s / 3``.
    """

    def __init__(
        self,
        session_factory: sessionmaker[Session],
        inspection_id: int,
        *,
        owner: str,
        lease_s: float,
    ):
        self.session_factory = session_factory
        self.inspection_id = inspection_id
        self.owner = owner
        self.lease_s = lease_s
        self._stop = threading.Event()
        self._thread = threading.Thread(
            target=self._run, name=f"lease-{inspection_id}", daemon=True
        )
        #: Set when the database refused a renewal: another consumer holds the job now.
        self.lost = threading.Event()

    def __enter__(self) -> LeaseKeeper:
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self.stop()

    def stop(self) -> None:
        """Stop renewing (the job finished, or failed)."""
        self._stop.set()
        self._thread.join()

    def _run(self) -> None:
        while not self._stop.wait(self.lease_s / 3.0):
            try:
                with self.session_factory() as session:
                    held = svc.renew_lease(
                        session=session,
                        inspection_id=self.inspection_id,
                        owner=self.owner,
                        lease_s=self.lease_s,
                    )
                    session.commit()
            except Exception:
                log.warning(
                    "inspection %s: lease renewal failed; retrying",
                    self.inspection_id,
                    exc_info=True,
                )
                continue
            if not held:
                if not self._stop.is_set():
                    self.lost.set()
                    log.error(
                        "inspection %s: lease lost (the job was reclaimed or released); its result "
                        "will not be stored by this consumer",
                        self.inspection_id,
                    )
                return
