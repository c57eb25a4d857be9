"""The issue's acceptance run: ``serve --no-worker`` on PostgreSQL + Redis, two ``worker``
processes, 8 inspections through the real pipeline, one worker killed with SIGKILL mid-job."""

from __future__ import annotations

import collections
import re
import signal

import pytest
from sqlalchemy import create_engine, select

from app.models import Inspection
from pipeline.artifacts import ARTIFACT_FILES
from tests.api.helpers import wait_until
from tests.yard.cluster import Yard

#: Large enough that a job lasts about a second in a warmed-up worker: the kill below must land
#: inside one (at 320x256 a job takes 0.6 s and the eight are done before a poll sees one run).
SIM = {"n_lights": 12, "width": 800, "height": 640}
N = 8


@pytest.mark.slow
def test_eight_inspections_two_workers_one_killed_all_complete_once(tmp_path, pg_url, queue_url):
    yard = Yard(
        tmp_path / "data", database_url=pg_url, queue_url=queue_url, PLATE_INSPECT_JOB_LEASE_S="6"
    )
    try:
        yard.start_server()
        victim, survivor = yard.start_worker(), yard.start_worker()
        ids = [yard.submit(f"ACC-{i}", SIM) for i in range(N)]
        # Kill the first worker the moment its log shows a job started and not finished: the
        # look and the signal are a few milliseconds apart, a job lasts about a second.
        running = wait_until(
            lambda: _in_flight(yard.log("worker0.log")),
            180,
            lambda: "the first worker never ran a job",
        )
        victim.send_signal(signal.SIGKILL)
        victim.wait(30)
        # The job it was running when it died: started in its log and never finished there (the
        # job seen running above may have ended between that look and the signal).
        victim_log = yard.log("worker0.log")
        killed_mid_job = _in_flight(victim_log)
        bodies = yard.wait_all(ids, timeout_s=600)
    finally:
        yard.stop()
    assert [b["status"] for b in bodies] == ["done"] * N, [b["error"] for b in bodies]
    assert all(b["verdict"] in ("pass", "fail") for b in bodies), [b["error"] for b in bodies]
    for b in bodies:
        assert set(ARTIFACT_FILES.values()) <= set(b["artifacts"]), b["artifacts"]
        assert (
            yard.data_dir / "inspections" / str(b["id"]) / "artifacts" / "result.json"
        ).is_file()
    assert running and len(killed_mid_job) == 1, (running, killed_mid_job)
    (killed,) = killed_mid_job
    done_lines = collections.Counter(
        int(m.group(1))
        for k in (0, 1)
        for m in re.finditer(r"inspection (\d+): done, verdict", yard.log(f"worker{k}.log"))
    )
    assert done_lines == dict.fromkeys(ids, 1), done_lines  # each completed exactly once
    assert f"inspection {killed}: its worker died while running it" in yard.log("worker1.log")
    engine = create_engine(pg_url)
    with engine.connect() as conn:
        rows = conn.execute(select(Inspection.id, Inspection.status, Inspection.deaths)).all()
    engine.dispose()
    assert sorted(r.id for r in rows) == sorted(ids)
    assert {r.id: r.deaths for r in rows}[killed] == 1
    assert not [
        p
        for p in yard.data_dir.rglob("*")
        if p.suffix in (".db", ".sqlite", ".lock") and "cell" not in p.parts
    ]
    assert survivor.returncode is not None


def _in_flight(log: str) -> set[int]:
    """The inspections a worker's log shows started and not (yet) finished."""
    return _ids(r"inspection (\d+): running", log) - _ids(r"inspection (\d+): done, verdict", log)


def _ids(pattern: str, text: str) -> set[int]:
    """The inspection ids that ``pattern`` (one group) finds in a worker's log."""
    return {int(m.group(1)) for m in re.finditer(pattern, text)}
