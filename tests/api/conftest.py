"""Service tests: a real database migrated by Alembic, a real huey consumer process.

Every test that uses ``settings`` runs twice, on the embedded SQLite file (``[sqlite]``) and on a
real PostgreSQL server (``[postgresql]``: one server per test session, a database copied from a
migrated template per test; :mod:`tests.yard.servers`). The job queue is the embedded SQLite one
here; ``tests/yard/`` runs the jobs on Redis.
"""

from __future__ import annotations

import io
import os
import shutil
import signal
import subprocess
import sys
import time
import zipfile
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from app.main import create_app
from app.settings import Settings
from tests.acquisition.conftest import fake_gv, light_server  # noqa: F401 (fixtures of test_acquire.py)
from tests.yard import servers

ROOT = Path(__file__).resolve().parents[2]
TOKEN = "test-token-0123456789"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
FAKE_INSPECT = "tests.api.fake_pipeline:inspect"


@pytest.fixture(scope="session")
def pg_template():
    """A PostgreSQL server for the session and the name of a database migrated to the head."""
    with servers.running_postgres() as server, servers.migrated_template(server) as template:
        yield server, template


@pytest.fixture(params=["sqlite", "postgresql"])
def database_url(request) -> str | None:
    """None (the SQLite file under the data dir), or a fresh migrated PostgreSQL database."""
    if request.param == "sqlite":
        yield None
        return
    server, template = request.getfixturevalue("pg_template")
    name = server.create_database(template=template)
    yield server.url(name)
    server.drop_database(name)


@pytest.fixture
def settings(tmp_path, database_url) -> Settings:
    return Settings(
        data_dir=tmp_path / "data",
        database_url=database_url,
        api_token=TOKEN,
        max_upload_mb=8.0,
        progress_interval_s=0.05,
        inspect_entry=FAKE_INSPECT,
    )


@pytest.fixture
def client(settings):
    app = create_app(settings)
    with TestClient(app) as c:
        yield c
    app.state.engine.dispose()


class Consumer:
    """``python -m app.worker`` in a child process, with the test's settings.

    ``invocations`` (a file) is where the test double of the pipeline records its calls
    (:func:`invocations`); ``args`` are extra command-line arguments (e.g. ``--parent-pid``).
    """

    def __init__(
        self,
        settings: Settings,
        *,
        stage_delay_s: float = 0.0,
        invocations: Path | None = None,
        args: tuple[str, ...] = (),
        log_name: str = "consumer.log",
    ):
        self.env = {
            **os.environ,
            **settings.to_env(),
            "PLATE_INSPECT_TEST_STAGE_DELAY_S": str(stage_delay_s),
        }
        if invocations is not None:
            self.env["PLATE_INSPECT_TEST_INVOCATIONS"] = str(invocations)
        self.args = tuple(args)
        self.log = settings.data_dir / log_name
        self.proc: subprocess.Popen | None = None

    def start(self) -> Consumer:
        self.log.parent.mkdir(parents=True, exist_ok=True)
        fh = open(self.log, "ab")  # noqa: SIM115 (the consumer process holds it)
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "app.worker", *self.args],
            env=self.env,
            cwd=ROOT,
            stdout=fh,
            stderr=fh,
        )
        fh.close()
        return self

    def wait_ready(self, timeout_s: float = 60.0) -> Consumer:
        """Wait until the consumer logs that it runs its queue (it holds the consumer lock)."""
        wait_until(
            lambda: "consumer ready" in self.output(),
            timeout_s,
            lambda: f"consumer not ready\n{self.output()}",
        )
        return self

    def kill(self) -> None:
        self.proc.send_signal(signal.SIGKILL)
        self.proc.wait(10)

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()

    def output(self) -> str:
        return self.log.read_text(errors="replace") if self.log.exists() else ""


def wait_until(condition, timeout_s: float, message=lambda: "condition not met"):
    """Poll ``condition()`` every 50 ms until it is truthy (returned); AssertionError with ``message()`` after the timeout."""
    deadline = time.monotonic() + timeout_s
    while True:
        value = condition()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f"after {timeout_s} s: {message()}")
        time.sleep(0.05)


def invocations(path: Path) -> list[tuple[str, int, int]]:
    """The test double's calls recorded in ``path``: ``(event, inspection id, pid)``, event ``start`` or ``end``."""
    if not path.exists():
        return []
    rows = []
    for line in path.read_text(encoding="ascii").splitlines():
        event, inspection_id, pid = line.split()
        rows.append((event, int(inspection_id), int(pid)))
    return rows


def pid_alive(pid: int) -> bool:
    """Whether process ``pid`` exists and is not a zombie."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return False
    return stat.rsplit(")", 1)[1].split()[0] != "Z"


@pytest.fixture
def consumer_factory(settings):
    started: list[Consumer] = []

    def make(**kw) -> Consumer:
        c = Consumer(settings, **kw)
        started.append(c)
        return c

    yield make
    for c in started:
        c.stop()


def wait_for(
    client,
    inspection_id: int,
    *,
    statuses=("done", "error"),
    timeout_s: float = 60.0,
    consumer=None,
) -> dict:
    """Poll GET /api/v1/inspections/{id} until its status is one of ``statuses``."""
    deadline = time.monotonic() + timeout_s
    while True:
        body = client.get(f"/api/v1/inspections/{inspection_id}").json()
        if body["status"] in statuses:
            return body
        if time.monotonic() > deadline:
            log = consumer.output() if consumer is not None else ""
            raise AssertionError(
                f"inspection {inspection_id} still {body['status']} after {timeout_s} s\n{log}"
            )
        time.sleep(0.05)


@pytest.fixture(scope="session")
def bundle_zip(tmp_path_factory) -> bytes:
    """A small simulated capture bundle (320x256, 6 lights) of plate P-100, zipped."""
    from pipeline.simulate import CaptureSpec, PlateSpec, simulate_capture

    folder = tmp_path_factory.mktemp("bundle") / "P-100"
    simulate_capture(
        folder,
        plate=PlateSpec(),
        capture=CaptureSpec(width=320, height=256, n_lights=6),
        plate_id="P-100",
        seed=1,
    )
    return zip_folder(folder)


def zip_folder(folder: Path, *, skip=()) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_STORED) as zf:
        for path in sorted(folder.iterdir()):
            if path.is_file() and path.name not in skip and path.name != "truth.npz":
                zf.write(path, path.name)
    return buf.getvalue()


def rezip(data: bytes, *, replace: dict[str, bytes] | None = None, drop=()) -> bytes:
    """A copy of a zip with some members replaced or dropped."""
    replace = replace or {}
    out = io.BytesIO()
    with zipfile.ZipFile(io.BytesIO(data)) as src, zipfile.ZipFile(out, "w") as dst:
        for info in src.infolist():
            if info.filename in drop:
                continue
            dst.writestr(info.filename, replace.get(info.filename, src.read(info.filename)))
    return out.getvalue()


def target_json(**over) -> bytes:
    import json

    doc = {
        "format": "plate-target/1",
        "shape": {"type": "cylinder", "radius_mm": 5000.0},
        "size_mm": [3000.0, 3000.0],
        "tolerance_mm": 2.0,
    }
    doc.update(over)
    return json.dumps(doc).encode()


def stored_files(data_dir: Path) -> list[str]:
    """Every file under the data dir except the database and queue files."""
    skip = ("plate_inspect.db", "huey.db", "consumer.")
    return sorted(
        str(p.relative_to(data_dir))
        for p in data_dir.rglob("*")
        if p.is_file() and not p.name.startswith(skip)
    )


__all__ = [
    "AUTH",
    "TOKEN",
    "rezip",
    "shutil",
    "stored_files",
    "target_json",
    "wait_for",
    "zip_folder",
]
