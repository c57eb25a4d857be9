"""A yard on one machine, as processes: ``plate-inspect serve --no-worker`` and ``plate-inspect
worker`` processes against one PostgreSQL and one Redis (used by the acceptance test and
``benchmarks/bench_yard.py``)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import httpx

from tests.yard.servers import free_port

ROOT = Path(__file__).resolve().parents[2]
TOKEN = "yard-token-0123456789"
CLI = [sys.executable, "-c", "import sys; from pipeline.cli import main; sys.exit(main())"]


class Yard:
    """The service and its workers as child processes (logs in ``data_dir``)."""

    def __init__(self, data_dir: Path, *, database_url: str, queue_url: str, **env: str):
        self.data_dir = Path(data_dir)
        self.data_dir.mkdir(parents=True, exist_ok=True)
        self.env = {
            **os.environ,
            "PLATE_INSPECT_DATA_DIR": str(self.data_dir),
            "PLATE_INSPECT_DATABASE_URL": database_url,
            "PLATE_INSPECT_QUEUE_URL": queue_url,
            "PLATE_INSPECT_API_TOKEN": TOKEN,
            **env,
        }
        self.port = free_port()
        self.base = f"http://127.0.0.1:{self.port}"
        self.server: subprocess.Popen[bytes] | None = None
        self.workers: list[subprocess.Popen[bytes]] = []

    def _spawn(self, args: list[str], log: str) -> subprocess.Popen[bytes]:
        with open(self.data_dir.parent / log, "ab") as fh:
            return subprocess.Popen([*CLI, *args], env=self.env, cwd=ROOT, stdout=fh, stderr=fh)

    def log(self, name: str) -> str:
        path = self.data_dir.parent / name
        return path.read_text(errors="replace") if path.exists() else ""

    def start_server(self, timeout_s: float = 120.0) -> None:
        self.server = self._spawn(["serve", "--no-worker", "--port", str(self.port)], "serve.log")
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                if httpx.get(self.base + "/healthz", timeout=2).status_code == 200:
                    return
            except httpx.HTTPError:
                pass
            if self.server.poll() is not None or time.monotonic() > deadline:
                raise AssertionError(f"serve did not start:\n{self.log('serve.log')}")
            time.sleep(0.2)

    def start_worker(self, timeout_s: float = 120.0) -> subprocess.Popen[bytes]:
        k = len(self.workers)
        proc = self._spawn(["worker"], f"worker{k}.log")
        self.workers.append(proc)
        deadline = time.monotonic() + timeout_s
        while "consumer ready" not in self.log(f"worker{k}.log"):
            if proc.poll() is not None or time.monotonic() > deadline:
                raise AssertionError(f"worker {k} did not start:\n{self.log(f'worker{k}.log')}")
            time.sleep(0.2)
        return proc

    def submit(self, plate_id: str, simulation: dict) -> int:
        r = httpx.post(
            f"{self.base}/api/v1/plates/{plate_id}/inspections/simulated",
            json=simulation,
            headers={"Authorization": f"Bearer {TOKEN}"},
            timeout=30,
        )
        assert r.status_code == 202, r.text
        return int(r.json()["id"])

    def inspection(self, inspection_id: int) -> dict:
        return httpx.get(f"{self.base}/api/v1/inspections/{inspection_id}", timeout=30).json()

    def wait_all(self, ids: list[int], timeout_s: float) -> list[dict]:
        deadline = time.monotonic() + timeout_s
        while True:
            bodies = [self.inspection(i) for i in ids]
            if all(b["status"] in ("done", "error") for b in bodies):
                return bodies
            if time.monotonic() > deadline:
                states = {b["id"]: b["status"] for b in bodies}
                raise AssertionError(f"not finished after {timeout_s} s: {states}")
            time.sleep(0.25)

    def stop(self) -> None:
        for proc in [*self.workers, self.server]:
            if proc is not None and proc.poll() is None:
                proc.send_signal(signal.SIGTERM)
        for proc in [*self.workers, self.server]:
            if proc is not None:
                try:
                    proc.wait(30)
                except subprocess.TimeoutExpired:
                    proc.kill()
                    proc.wait()
