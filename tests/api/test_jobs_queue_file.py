"""A corrupt huey.db neither stops the web process nor the consumer: moved aside, recreated, rebuilt."""

from __future__ import annotations

import logging
import os
import subprocess
import sys

import pytest
from fastapi.testclient import TestClient

from app.main import create_app
from tests.api.helpers import AUTH, ROOT, child_env, wait_for

SIM = {"n_lights": 3, "width": 160, "height": 128}


def _submit(client, plate_id: str) -> int:
    r = client.post(f"/api/v1/plates/{plate_id}/inspections/simulated", json=SIM, headers=AUTH)
    assert r.status_code == 202, r.text
    return r.json()["id"]


def _queued_then_corrupt(settings, how: str) -> list[int]:
    """Two jobs queued by a web process with no consumer, then the queue file damaged."""
    app = create_app(settings)
    with TestClient(app) as client:
        ids = [_submit(client, "Q-1"), _submit(client, "Q-2")]
    app.state.jobs.huey.storage.close()
    app.state.engine.dispose()
    path = settings.huey_path
    if how == "junk":
        path.write_bytes(os.urandom(3000) + b"not a database" * 500)
    else:  # truncated: the header survives, the pages it announces do not
        data = path.read_bytes()
        path.write_bytes(data[:1024])
        for suffix in ("-wal", "-shm"):
            path.with_name(path.name + suffix).unlink(missing_ok=True)
    return ids


def _aside(settings) -> list[str]:
    return sorted(
        p.name
        for p in settings.data_dir.glob("huey.db.corrupt-*")
        if not p.name.endswith(("-wal", "-shm"))
    )


@pytest.mark.parametrize("how", ["junk", "truncated"])
def test_web_process_starts_on_a_corrupt_queue_and_its_jobs_complete(
    settings, consumer_factory, caplog, how
):
    ids = _queued_then_corrupt(settings, how)
    caplog.set_level(logging.INFO, logger="app.jobs")
    app = create_app(settings)
    try:
        errors = [
            r
            for r in caplog.records
            if r.levelno == logging.ERROR and "moved aside" in r.getMessage()
        ]
        assert len(errors) == 1, caplog.text
        (aside,) = _aside(settings)
        assert aside in errors[0].getMessage() and "nothing is lost" in errors[0].getMessage()
        assert (
            app.state.jobs.repaired and app.state.jobs.pending_count() == 2
        )  # rebuilt from the rows
        consumer = consumer_factory().start()
        with TestClient(app) as client:
            ids.append(_submit(client, "Q-3"))
            for inspection_id in ids:
                assert wait_for(client, inspection_id, consumer=consumer)["status"] == "done"
        assert "moved aside" not in consumer.output()  # the web process repaired it first
        assert _aside(settings) == [aside]  # kept for a post-mortem
    finally:
        app.state.engine.dispose()


def test_consumer_starts_on_a_corrupt_queue_and_runs_the_queued_jobs(settings, consumer_factory):
    ids = _queued_then_corrupt(settings, "junk")
    consumer = consumer_factory().start().wait_ready()
    assert "ERROR" in consumer.output() and "moved aside" in consumer.output()
    assert len(_aside(settings)) == 1
    app = create_app(settings)
    try:
        assert not app.state.jobs.repaired
        with TestClient(app) as client:
            ids.append(_submit(client, "Q-3"))
            for inspection_id in ids:
                assert wait_for(client, inspection_id, consumer=consumer)["status"] == "done"
    finally:
        app.state.engine.dispose()


OPEN_QUEUE = """
import sys
from app.db import make_engine, make_session_factory
from app.jobs import JobQueue
from app.settings import Settings
from app.storage import Storage
settings = Settings()
queue = JobQueue(settings, make_session_factory(make_engine(settings.sqlalchemy_url)), Storage(settings.data_dir))
print("repaired" if queue.repaired else "sound", queue.pending_count())
"""


def test_processes_opening_one_corrupt_queue_at_once_move_it_aside_once(settings):
    _queued_then_corrupt(settings, "junk")
    env = child_env(settings)
    procs = [
        subprocess.Popen(
            [sys.executable, "-c", OPEN_QUEUE],
            cwd=ROOT,
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        for _ in range(3)
    ]
    outputs = [p.communicate(timeout=120) for p in procs]
    assert [p.returncode for p in procs] == [0, 0, 0], outputs
    verdicts = sorted(out.split()[0] for out, _ in outputs)
    assert verdicts == ["repaired", "sound", "sound"], outputs
    assert len(_aside(settings)) == 1


def test_the_sweep_queues_again_rows_whose_message_was_lost(client):
    jobs = client.app.state.jobs
    ids = [_submit(client, "Q-1"), _submit(client, "Q-2")]
    jobs.huey.storage.flush_queue()  # messages lost (a failed write, a replaced file)
    assert jobs.sweep(min_age_s=3600) == []  # too young: their web process may be writing them
    assert jobs.sweep(min_age_s=0) == ids
    assert jobs.pending_count() == 2
    assert jobs.sweep(min_age_s=0) == []  # no duplicates


def test_a_queue_file_that_fails_under_a_running_server_is_repaired_and_followed(settings, caplog):
    caplog.set_level(logging.INFO, logger="app.jobs")
    app = create_app(settings)
    other = None
    try:
        with TestClient(app) as client:
            first = _submit(client, "Q-1")
            # Another process's queue (the consumer's), open on the same file.
            other = type(app.state.jobs)(settings, app.state.session_factory, app.state.storage)
            settings.huey_path.write_bytes(os.urandom(8192))  # damaged under both
            # SQLite reports damage when it reads the file anew: the web process's next connection.
            app.state.jobs.huey.storage.close()
            second = _submit(client, "Q-2")  # the web process meets the failure and repairs
        assert app.state.jobs.repaired
        assert len(_aside(settings)) == 1
        assert any(
            r.levelno == logging.ERROR and "moved aside" in r.getMessage() for r in caplog.records
        )
        pending = {task.args[0] for task in app.state.jobs.huey.pending()}
        assert pending == {first, second}  # rebuilt from the rows
        assert (
            other.sweep(min_age_s=0) == []
        )  # the other process follows the new file: nothing missing
        assert other.pending_count() == 2
    finally:
        if other is not None:
            other.huey.storage.close()
        app.state.engine.dispose()
