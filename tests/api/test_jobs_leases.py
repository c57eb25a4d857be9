"""Job leases on a real SQLite file migrated by Alembic: atomic claims, expiry, worker deaths, poison."""

from __future__ import annotations

import threading
from datetime import timedelta

from alembic.autogenerate import compare_metadata
from alembic.migration import MigrationContext
from alembic.script import ScriptDirectory
from sqlalchemy import create_engine, text

from app.db import alembic_config, make_engine, make_session_factory
from app.models import Base, Inspection, utcnow
from app.services import leases as svc
from tests.api.helpers import AUTH

SIM = {"n_lights": 3, "width": 160, "height": 128}


def _submit(client, n: int = 1) -> list[int]:
    ids = []
    for i in range(n):
        r = client.post(f"/api/v1/plates/L-{i}/inspections/simulated", json=SIM, headers=AUTH)
        assert r.status_code == 202, r.text
        ids.append(r.json()["id"])
    return ids


def _row(client, inspection_id: int) -> Inspection:
    with client.app.state.session_factory() as s:
        return s.get(Inspection, inspection_id)


def _claim(client, inspection_id: int, owner: str, *, now=None, lease_s: float = 30.0) -> bool:
    with client.app.state.session_factory() as s:
        won = svc.claim(
            session=s, inspection_id=inspection_id, owner=owner, lease_s=lease_s, now=now
        )
        s.commit()
    return won


def test_migration_0003_is_the_head_and_matches_the_models(client):
    script = ScriptDirectory.from_config(alembic_config("sqlite://"))
    heads = script.get_heads()
    assert "0003" in {rev.revision for rev in script.walk_revisions()}
    with client.app.state.engine.connect() as connection:
        context = MigrationContext.configure(connection)
        assert context.get_current_revision() in heads
        assert compare_metadata(context, Base.metadata) == []


def test_two_claims_of_one_row_race_and_one_wins(client, settings):
    ids = _submit(client, 8)
    # Two processes' worth of connections: one engine per claimant, each claim in its own transaction.
    engines = [make_engine(settings.sqlalchemy_url) for _ in range(2)]
    factories = [make_session_factory(e) for e in engines]
    for inspection_id in ids:
        barrier = threading.Barrier(2)
        results: dict[str, bool] = {}

        def claim(owner: str, factory) -> None:
            with factory() as s:
                barrier.wait()
                results[owner] = svc.claim(session=s, inspection_id=inspection_id, owner=owner)
                s.commit()

        threads = [
            threading.Thread(target=claim, args=(f"host:{n}:aa", f))
            for n, f in enumerate(factories)
        ]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        assert sorted(results.values()) == [False, True], results
        winner = next(owner for owner, won in results.items() if won)
        row = _row(client, inspection_id)
        assert (row.status, row.lease_owner, row.attempts, row.deaths) == ("running", winner, 1, 0)
    for e in engines:
        e.dispose()


def test_a_live_lease_is_not_claimed_an_expired_one_is_and_counts_a_death(client):
    (inspection_id,) = _submit(client)
    t0 = utcnow()
    assert _claim(client, inspection_id, "a:1:x", now=t0, lease_s=30)
    assert not _claim(client, inspection_id, "b:2:y", now=t0 + timedelta(seconds=29))
    assert _claim(client, inspection_id, "b:2:y", now=t0 + timedelta(seconds=31))
    row = _row(client, inspection_id)
    assert (row.status, row.lease_owner, row.attempts, row.deaths) == ("running", "b:2:y", 2, 1)

    # The first owner's late writes change nothing: it lost the lease.
    with client.app.state.session_factory() as s:
        assert not svc.renew_lease(
            session=s, inspection_id=inspection_id, owner="a:1:x", lease_s=30
        )
        svc.record_progress(
            session=s, inspection_id=inspection_id, stage="depth", progress=0.5, owner="a:1:x"
        )
        assert not svc.mark_done(
            session=s, inspection_id=inspection_id, document={"verdict": "pass"}, owner="a:1:x"
        )
        assert not svc.mark_error(
            session=s, inspection_id=inspection_id, error="late", owner="a:1:x"
        )
        s.commit()
    row = _row(client, inspection_id)
    assert (row.status, row.stage, row.error) == ("running", None, None)

    # The holder renews, reports progress and finishes.
    with client.app.state.session_factory() as s:
        assert svc.renew_lease(session=s, inspection_id=inspection_id, owner="b:2:y", lease_s=30)
        svc.record_progress(
            session=s, inspection_id=inspection_id, stage="depth", progress=0.5, owner="b:2:y"
        )
        assert svc.mark_done(
            session=s, inspection_id=inspection_id, document={"verdict": "pass"}, owner="b:2:y"
        )
        s.commit()
    row = _row(client, inspection_id)
    assert (row.status, row.verdict, row.lease_owner, row.lease_expires_at) == (
        "done",
        "pass",
        None,
        None,
    )


def test_a_second_expired_lease_sets_the_job_aside_with_its_last_stage(client):
    (inspection_id,) = _submit(client)
    t0 = utcnow()
    assert _claim(client, inspection_id, "a:1:x", now=t0, lease_s=10)
    with client.app.state.session_factory() as s:
        reclaimed = svc.reclaim_expired(session=s, now=t0 + timedelta(seconds=11))
        s.commit()
    assert reclaimed == svc.Reclaimed(requeued=[inspection_id], set_aside=[])
    row = _row(client, inspection_id)
    assert (row.status, row.deaths, row.lease_owner) == ("queued", 1, None)
    assert row.queued_at >= t0 + timedelta(seconds=11)  # at the back of the queue

    t1 = t0 + timedelta(seconds=20)
    assert _claim(client, inspection_id, "b:2:y", now=t1, lease_s=10)
    with client.app.state.session_factory() as s:
        svc.record_progress(
            session=s, inspection_id=inspection_id, stage="stereo", progress=0.4, owner="b:2:y"
        )
        s.commit()
    # At the limit the expired lease is not claimed again: it is set aside.
    assert not _claim(client, inspection_id, "c:3:z", now=t1 + timedelta(seconds=11))
    with client.app.state.session_factory() as s:
        reclaimed = svc.reclaim_expired(session=s, now=t1 + timedelta(seconds=11))
        s.commit()
    assert reclaimed == svc.Reclaimed(requeued=[], set_aside=[inspection_id])
    body = client.get(f"/api/v1/inspections/{inspection_id}").json()
    assert body["status"] == "error" and body["verdict"] is None
    assert body["error"] == (
        "set aside: the worker died twice while running this job (last stage: stereo); its inputs are kept"
    )
    assert _row(client, inspection_id).deaths == 2


def test_a_graceful_release_keeps_the_place_and_is_no_death(client):
    first, second = _submit(client, 2)
    queued_at = _row(client, first).queued_at
    assert _claim(client, first, "a:1:x")
    with client.app.state.session_factory() as s:
        assert svc.release(session=s, owner="a:1:x") == [first]
        s.commit()
        assert svc.queued_ids(session=s) == [first, second]
    row = _row(client, first)
    assert (row.status, row.deaths, row.lease_owner, row.queued_at) == (
        "queued",
        0,
        None,
        queued_at,
    )


def test_consumer_start_reclaims_rows_of_dead_consumers_in_queue_order(client):
    a, b, c = _submit(client, 3)
    assert _claim(
        client, a, "dead:1:x", lease_s=600
    )  # a live-looking lease of a consumer that is gone
    with client.app.state.session_factory() as s:
        reclaimed = svc.requeue_interrupted(session=s, owner="me:2:y")
        s.commit()
        order = svc.queued_ids(session=s)
    assert reclaimed.requeued == [a]
    assert order == [
        b,
        c,
        a,
    ]  # the job that was running when its worker died goes behind the others
    assert _row(client, a).deaths == 1


def test_a_row_of_the_previous_schema_left_running_is_reclaimed(client, settings):
    (inspection_id,) = _submit(client)
    engine = create_engine(settings.sqlalchemy_url)
    with engine.begin() as conn:  # as revision 0002 left it: running, no lease
        conn.execute(
            text("UPDATE inspections SET status='running' WHERE id=:id"), {"id": inspection_id}
        )
    engine.dispose()
    with client.app.state.session_factory() as s:
        assert svc.requeue_interrupted(session=s, owner="me:2:y").requeued == [inspection_id]
        s.commit()
    assert _row(client, inspection_id).status == "queued"
