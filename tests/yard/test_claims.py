"""The job claim and the reclaim of expired leases under real PostgreSQL concurrency: of many
workers racing for the same rows, each row goes to exactly one."""

from __future__ import annotations

import random
import threading
from datetime import timedelta

from sqlalchemy import select

from app.db import make_engine, make_session_factory
from app.models import Inspection, Plate, utcnow
from app.services import leases as svc

N_ROWS, N_WORKERS = 40, 8


def _queued_rows(session_factory, n: int) -> list[int]:
    with session_factory() as s:
        s.add(Plate(id="P-1"))
        rows = [Inspection(plate_id="P-1", source="simulated", status="queued") for _ in range(n)]
        s.add_all(rows)
        s.commit()
        return [r.id for r in rows]


def _race(n_workers: int, work) -> None:
    start = threading.Barrier(n_workers)
    errors: list[BaseException] = []

    def run(k: int) -> None:
        try:
            start.wait()
            work(k)
        except BaseException as err:  # surfaced below
            errors.append(err)

    threads = [threading.Thread(target=run, args=(k,)) for k in range(n_workers)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors, errors


def test_concurrent_claims_give_each_row_to_exactly_one_worker(pg_url):
    engine = make_engine(pg_url)
    factory = make_session_factory(engine)
    ids = _queued_rows(factory, N_ROWS)
    won: dict[int, list[str]] = {i: [] for i in ids}
    lock = threading.Lock()

    def worker(k: int) -> None:
        owner = f"host:{k}:x"
        order = ids[:]
        random.Random(k).shuffle(order)
        for inspection_id in order:
            with factory() as s:
                ok = svc.claim(session=s, inspection_id=inspection_id, owner=owner, lease_s=30)
                s.commit()
            if ok:
                with lock:
                    won[inspection_id].append(owner)

    _race(N_WORKERS, worker)
    assert all(len(owners) == 1 for owners in won.values()), won
    with factory() as s:
        rows = s.scalars(select(Inspection)).all()
        assert {r.status for r in rows} == {"running"}
        assert all(r.lease_owner == won[r.id][0] and r.attempts == 1 for r in rows)
        assert all(r.lease_expires_at.tzinfo is not None for r in rows)
    engine.dispose()


def test_concurrent_reclaims_requeue_each_expired_job_once(pg_url):
    engine = make_engine(pg_url)
    factory = make_session_factory(engine)
    ids = _queued_rows(factory, N_ROWS)
    past = utcnow() - timedelta(seconds=120)
    with factory() as s:
        for inspection_id in ids:
            assert svc.claim(session=s, inspection_id=inspection_id, owner="dead:1:x", now=past)
        s.commit()
    requeued: list[int] = []
    lock = threading.Lock()

    def worker(k: int) -> None:
        with factory() as s:
            got = svc.reclaim_expired(session=s)
            s.commit()
        with lock:
            requeued.extend(got.requeued)

    _race(N_WORKERS, worker)
    assert sorted(requeued) == ids
    with factory() as s:
        rows = s.scalars(select(Inspection)).all()
        assert {(r.status, r.deaths, r.lease_owner) for r in rows} == {("queued", 1, None)}
    engine.dispose()


def test_a_lease_renewed_by_its_heartbeat_is_not_reclaimed(pg_url):
    engine = make_engine(pg_url)
    factory = make_session_factory(engine)
    (inspection_id,) = _queued_rows(factory, 1)
    t0 = utcnow()
    with factory() as s:
        assert svc.claim(session=s, inspection_id=inspection_id, owner="a:1:x", lease_s=5, now=t0)
        s.commit()
    with factory() as s:  # the heartbeat renews before the lease runs out
        later = t0 + timedelta(seconds=4)
        assert svc.renew_lease(
            session=s, inspection_id=inspection_id, owner="a:1:x", lease_s=5, now=later
        )
        s.commit()
    with factory() as s:
        assert svc.reclaim_expired(session=s, now=t0 + timedelta(seconds=6)).requeued == []
        assert not svc.claim(session=s, inspection_id=inspection_id, owner="b:2:y")
        assert svc.reclaim_expired(session=s, now=t0 + timedelta(seconds=10)).requeued == [
            inspection_id
        ]
        s.commit()
    engine.dispose()
