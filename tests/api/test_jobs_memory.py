"""The consumer's memory bound (PLATE_INSPECT_WORKER_MEMORY_MB): a job beyond it fails, the consumer goes on."""

from __future__ import annotations

import subprocess
import sys

from tests.api.helpers import (
    AUTH,
    ROOT,
    Consumer,
    capture_json_with_plate,
    rezip,
    target_json,
    wait_for,
)

#: The test double asks for 2048 MiB (PLATE_INSPECT_TEST_ALLOCATE_MB's default): the limit leaves less room.
HEADROOM_MB = 1024


def _consumer_baseline_mb() -> float:
    """Address space a consumer process maps before its first job (its modules and the test double's), MiB."""
    code = "import app.worker, tests.api.fake_pipeline; from app.jobs.memory import mapped_mb; print(mapped_mb())"
    out = subprocess.run(
        [sys.executable, "-c", code],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=60,
        check=True,
    )
    return float(out.stdout.strip())


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


def test_a_job_beyond_the_memory_limit_fails_and_the_next_one_runs(client, settings, bundle_zip):
    limit_mb = int(_consumer_baseline_mb()) + HEADROOM_MB
    limited = settings.model_copy(update={"worker_memory_mb": limit_mb})
    consumer = Consumer(limited).start()
    try:
        hog = _post(client, "P-HOG", bundle_zip)
        after = _post(client, "P-101", bundle_zip)
        body = wait_for(client, hog, consumer=consumer)
        assert body["status"] == "error" and body["verdict"] is None, body
        assert body["error"] == (
            f"out of memory: the job needed more than {limit_mb} MiB (PLATE_INSPECT_WORKER_MEMORY_MB)"
        )
        assert wait_for(client, after, consumer=consumer)["status"] == "done"
        assert consumer.proc.poll() is None  # the same consumer: no crash, no restart
    finally:
        consumer.stop()


def test_under_the_default_limit_the_same_job_completes(
    client, settings, consumer_factory, bundle_zip
):
    """The test double's allocation is refused by the limit alone (its pages are never touched)."""
    consumer = consumer_factory().start()
    hog = _post(client, "P-HOG", bundle_zip)
    assert wait_for(client, hog, consumer=consumer)["status"] == "done"


def test_a_limit_too_low_to_start_is_refused_with_the_setting_named(settings):
    env = {**Consumer(settings).env, "PLATE_INSPECT_WORKER_MEMORY_MB": "64"}
    out = subprocess.run(
        [sys.executable, "-m", "app.worker"],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert out.returncode == 78, out.stderr
    assert (
        "PLATE_INSPECT_WORKER_MEMORY_MB: expected at least" in out.stderr and "got 64" in out.stderr
    )
