"""No orphaned or second consumer: the consumer dies with its server, and one consumer runs per data dir."""

from __future__ import annotations

import os
import re
import signal
import socket
import subprocess
import sys
from collections import Counter
from pathlib import Path

from tests.api.helpers import (
    AUTH,
    ROOT,
    Consumer,
    child_env,
    invocations,
    pid_alive,
    wait_for,
    wait_until,
)

PLATE_INSPECT = Path(sys.executable).parent / "plate-inspect"
SIM = {"n_lights": 3, "width": 160, "height": 128}


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Server:
    """``plate-inspect serve`` in a child process (its own session, so a signal to it reaches it alone)."""

    def __init__(self, settings, *, calls: Path, stage_delay_s: float, log: Path):
        self.env = child_env(
            settings,
            PLATE_INSPECT_TEST_INVOCATIONS=str(calls),
            PLATE_INSPECT_TEST_STAGE_DELAY_S=str(stage_delay_s),
        )
        self.log = log
        self.proc: subprocess.Popen | None = None

    def start(self) -> Server:
        with open(self.log, "ab") as fh:
            self.proc = subprocess.Popen(
                [str(PLATE_INSPECT), "serve", "--port", str(_free_port())],
                env=self.env,
                cwd=ROOT,
                stdout=fh,
                stderr=fh,
                start_new_session=True,
            )
        return self

    def output(self) -> str:
        return self.log.read_text(errors="replace") if self.log.exists() else ""

    def consumer_pids(self) -> list[int]:
        return [
            int(pid) for pid in re.findall(r"job consumer started \(pid (\d+)\)", self.output())
        ]

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            self.proc.wait(30)


def _submit(client, n: int) -> list[int]:
    ids = []
    for i in range(n):
        r = client.post(f"/api/v1/plates/O-{i}/inspections/simulated", json=SIM, headers=AUTH)
        assert r.status_code == 202, r.text
        ids.append(r.json()["id"])
    return ids


def test_server_killed_alone_takes_its_consumer_along_and_a_restart_runs_each_job_once(
    client, settings, tmp_path
):
    calls = tmp_path / "invocations.txt"
    ids = _submit(client, 4)
    first = Server(settings, calls=calls, stage_delay_s=0.3, log=tmp_path / "serve-1.log").start()
    second = None
    try:
        wait_until(lambda: invocations(calls), 60, first.output)  # a job is running
        (orphan,) = first.consumer_pids()
        first.proc.send_signal(signal.SIGKILL)  # the server process alone, not its group
        first.proc.wait(10)
        # Restarted at once (as a service manager would): its consumer waits for the orphan's lock.
        second = Server(
            settings, calls=calls, stage_delay_s=0.0, log=tmp_path / "serve-2.log"
        ).start()
        wait_until(
            lambda: not pid_alive(orphan), 10, lambda: f"consumer {orphan} outlived its server"
        )
        for inspection_id in ids:
            body = wait_for(client, inspection_id, timeout_s=90)
            assert body["status"] == "done", f"{body}\n{second.output()}"
        (consumer,) = second.consumer_pids()  # one consumer, never restarted
        assert {pid for _, _, pid in invocations(calls)} <= {orphan, consumer}
    finally:
        first.stop()
        if second is not None:
            second.stop()
        for pid in first.consumer_pids():
            if pid_alive(pid):  # an orphan left by a failure: not left running after the test
                os.kill(pid, signal.SIGKILL)
    ends = Counter(i for event, i, _ in invocations(calls) if event == "end")
    assert ends == Counter(ids), invocations(calls)  # each job completed exactly once
    starts = Counter(i for event, i, _ in invocations(calls) if event == "start")
    assert max(starts.values()) <= 2  # the job interrupted by the kill ran again, no other did
    # The interrupted job was given back by its stopping consumer: not a worker death.
    assert "back in the queue (stopped, not a worker death)" in first.output()
    with client.app.state.session_factory() as s:
        from app.models import Inspection

        assert {s.get(Inspection, i).deaths for i in ids} == {0}


def test_a_second_consumer_waits_for_the_lock_and_takes_over_when_the_first_dies(
    client, settings, tmp_path
):
    calls = tmp_path / "invocations.txt"
    first = Consumer(settings, invocations=calls, stage_delay_s=0.3).start().wait_ready()
    second = Consumer(settings, invocations=calls, log_name="consumer-2.log").start()
    try:
        wait_until(lambda: "waiting for it to stop" in second.output(), 30, second.output)
        assert f"pid {first.proc.pid}" in second.output()  # it names the holder
        (a,) = _submit(client, 1)
        wait_until(lambda: invocations(calls), 30, first.output)
        first.kill()  # mid-job
        second.wait_ready()
        (b,) = _submit(client, 1)
        for inspection_id in (a, b):
            assert (
                wait_for(client, inspection_id, timeout_s=60, consumer=second)["status"] == "done"
            )
    finally:
        first.stop()
        second.stop()
    runs = invocations(calls)
    assert [(e, i, p) for e, i, p in runs if p == first.proc.pid] == [("start", a, first.proc.pid)]
    assert [(e, i) for e, i, p in runs if p == second.proc.pid] == [
        ("start", a),
        ("end", a),
        ("start", b),
        ("end", b),
    ]


def test_the_parent_watch_alone_stops_a_child_whose_parent_died(tmp_path):
    """The fallback of PR_SET_PDEATHSIG: a thread watching the parent pid (no prctl here)."""
    child_code = (
        "import os, time; from app.jobs.guards import watch_parent; "
        "watch_parent(os.getppid()); print(os.getpid(), flush=True); time.sleep(60)"
    )
    parent_code = (
        "import subprocess, sys; p = subprocess.Popen([sys.executable, '-c', sys.argv[1]], stdout=subprocess.PIPE, stderr=subprocess.DEVNULL); "
        "print(p.stdout.readline().decode().strip(), flush=True)"  # then exits, leaving the child behind
    )
    out = subprocess.run(
        [sys.executable, "-c", parent_code, child_code],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=60,
    )
    child = int(out.stdout.strip())
    try:
        wait_until(lambda: not pid_alive(child), 10, lambda: f"child {child} outlived its parent")
    finally:
        if pid_alive(child):
            os.kill(child, signal.SIGKILL)
