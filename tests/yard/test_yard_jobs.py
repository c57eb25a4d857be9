"""Jobs on a yard's setup: PostgreSQL rows, a Redis queue, several ``worker`` processes.

The pipeline is the test double (:mod:`tests.api.fake_pipeline`), slowed per stage so that a
worker can be killed mid-job; ``test_acceptance.py`` runs the real pipeline.
"""

from __future__ import annotations

import collections

from fastapi.testclient import TestClient
from sqlalchemy import create_engine, select

from app.db import make_engine, make_session_factory
from app.jobs import JobQueue
from app.main import create_app
from app.models import Inspection, Plate
from app.storage import Storage
from tests.api.helpers import AUTH, Consumer, invocations, wait_for, wait_until

SIM = {"n_lights": 3, "width": 160, "height": 128}


def _submit(client, n: int) -> list[int]:
    ids = []
    for i in range(n):
        r = client.post(f"/api/v1/plates/Y-{i}/inspections/simulated", json=SIM, headers=AUTH)
        assert r.status_code == 202, r.text
        ids.append(r.json()["id"])
    return ids


def test_two_workers_on_redis_share_the_jobs_and_a_killed_one_loses_none(yard_settings, tmp_path):
    calls = tmp_path / "calls.txt"
    workers = [
        Consumer(yard_settings, stage_delay_s=0.3, invocations=calls, log_name=f"w{k}.log")
        for k in range(2)
    ]
    app = create_app(yard_settings)
    try:
        with TestClient(app) as client:
            for w in workers:
                w.start().wait_ready()
            ids = _submit(client, 6)
            # Wait until both workers run a job, then kill one of them mid-job.
            running = wait_until(
                lambda: (
                    {pid for ev, _, pid in invocations(calls) if ev == "start"}
                    >= {w.proc.pid for w in workers}
                    and [
                        i
                        for ev, i, pid in invocations(calls)
                        if ev == "start" and pid == workers[0].proc.pid
                    ]
                ),
                60,
                lambda: "both workers did not start a job",
            )
            workers[0].kill()
            bodies = [wait_for(client, i, timeout_s=120, consumer=workers[1]) for i in ids]
    finally:
        for w in workers:
            w.stop()
        app.state.engine.dispose()
    assert [b["status"] for b in bodies] == ["done"] * len(ids), [b["error"] for b in bodies]
    ends = collections.Counter(i for ev, i, _ in invocations(calls) if ev == "end")
    assert ends == dict.fromkeys(ids, 1), ends  # each completed exactly once
    killed = running[-1]
    assert f"inspection {killed}: its worker died while running it" in workers[1].output()
    engine = create_engine(yard_settings.sqlalchemy_url)
    with engine.connect() as conn:
        deaths = dict(conn.execute(select(Inspection.id, Inspection.deaths)).all())
    engine.dispose()
    assert deaths[killed] == 1
    data = yard_settings.data_dir
    assert not list(data.rglob("*.db")) and not (data / "consumer.lock").exists()


def test_acquisition_jobs_go_to_their_cells_queue_on_redis(yard_settings):
    engine = make_engine(yard_settings.sqlalchemy_url)
    factory = make_session_factory(engine)
    with factory() as s:
        s.add(Plate(id="C-1"))
        rows = [
            Inspection(plate_id="C-1", source="acquired", status="queued", cell_id="cell-7"),
            Inspection(plate_id="C-1", source="simulated", status="queued"),
        ]
        s.add_all(rows)
        s.commit()
        acquired, simulated = (r.id for r in rows)
    queue = JobQueue(yard_settings, factory, Storage(yard_settings.data_dir))
    queue.enqueue(acquired)
    queue.enqueue(simulated)
    general = [t.args[0] for t in queue.huey.pending()]
    cell = [t.args[0] for t in queue._huey_for("cell-7")[0].pending()]
    assert (general, cell) == ([simulated], [acquired])
    assert queue.sweep(min_age_s=0) == []  # both have their message
    queue.huey.storage.flush_queue()
    queue._huey_for("cell-7")[0].storage.flush_queue()
    assert queue.sweep(min_age_s=0) == [acquired, simulated]
    assert [t.args[0] for t in queue._huey_for("cell-7")[0].pending()] == [acquired]
    engine.dispose()


def test_a_cell_worker_needs_a_shared_queue_and_its_cells_config(yard_settings, tmp_path):
    from app.worker import EXIT_CONFIG

    for settings, expected in (
        (yard_settings.model_copy(update={"queue_url": None}), "PLATE_INSPECT_QUEUE_URL"),
        (yard_settings, "PLATE_INSPECT_CELL_CONFIG"),
    ):
        w = Consumer(settings, args=("--cell", "cell-7"), log_name=f"cell{expected}.log").start()
        assert w.proc.wait(60) == EXIT_CONFIG
        assert expected in w.output()
