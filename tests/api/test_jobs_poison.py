"""A job that kills its consumer: set aside at the second death, never blocking the queue.

(A job whose consumer died once runs again and completes: ``test_jobs.py``.)
"""

from __future__ import annotations

from collections import Counter

from sqlalchemy import select

from app.cli import ConsumerProcess
from app.models import Inspection
from tests.api.helpers import (
    AUTH,
    capture_json_with_plate,
    invocations,
    rezip,
    target_json,
    wait_for,
)


def _post(client, plate_id: str, bundle_zip: bytes) -> int:
    bundle = rezip(
        bundle_zip, replace={"capture.json": capture_json_with_plate(bundle_zip, plate_id)}
    )
    files = {
        "capture": ("bundle.zip", bundle, "application/zip"),
        "target": ("target.json", target_json(), "application/json"),
    }
    r = client.post(f"/api/v1/plates/{plate_id}/inspections", files=files, headers=AUTH)
    assert r.status_code == 202, r.text
    return r.json()["id"]


def test_a_job_that_kills_its_consumer_is_set_aside_and_the_queue_goes_on(
    client, settings, bundle_zip, tmp_path
):
    calls = tmp_path / "invocations.txt"
    poison = _post(client, "P-KILLSELF", bundle_zip)  # first in the queue
    behind = [_post(client, f"P-{n}", bundle_zip) for n in range(4)]

    supervisor = ConsumerProcess(
        settings
    )  # the supervisor of `plate-inspect serve`: restarts a consumer that exits
    supervisor.env.update(
        PLATE_INSPECT_TEST_INVOCATIONS=str(calls), PLATE_INSPECT_TEST_STAGE_DELAY_S="0"
    )
    supervisor.start()
    try:
        body = wait_for(client, poison, timeout_s=120)
        for inspection_id in behind:
            assert wait_for(client, inspection_id, timeout_s=120)["status"] == "done"
    finally:
        supervisor.stop()

    assert body["status"] == "error" and body["verdict"] is None, body
    assert body["error"] == (
        "set aside: the worker died twice while running this job (last stage: normals); its inputs are kept"
    )
    inputs = settings.data_dir / "inspections" / str(poison) / "inputs"
    assert (inputs / "capture.zip").is_file()
    runs = Counter((event, i) for event, i, _ in invocations(calls))
    assert runs[("start", poison)] == 2 and runs[("end", poison)] == 0  # run twice, never again
    assert all(runs[("end", i)] == 1 for i in behind), runs
    # After its first death the poison job went behind the jobs waiting then.
    order = [i for event, i, _ in invocations(calls) if event == "start"]
    assert order[0] == poison and order.index(behind[0]) < order.index(poison, 1)
    with client.app.state.session_factory() as s:
        assert s.scalar(select(Inspection.deaths).where(Inspection.id == poison)) == 2
