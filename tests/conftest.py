"""Configuration shared by every test package: the thread policy of a process that runs inspections,
the fixtures of the cell's fake devices (Aravis' fake GigE Vision camera, the tests' own TCP
light controller and conveyor), used by the acquisition and the service's acquire tests, and the SQLite database
migrated once per session that the service and dashboard tests start from.

The thread policy is set here, before any test runs a compiled kernel, as the CLI and the job
consumer set it at start (:func:`pipeline.parallel.configure_process`).
"""

import sqlite3
from collections.abc import Callable
from pathlib import Path

import pytest

from pipeline.parallel import configure_process
from tests.acquisition.devices import ConveyorServer, FakeGigECamera, LightServer

configure_process()


@pytest.fixture
def light_server():
    """A factory of :class:`LightServer` (keyword arguments as its own); all closed after the test."""
    servers = []

    def make(**kwargs) -> LightServer:
        servers.append(LightServer(**kwargs))
        return servers[-1]

    yield make
    for server in servers:
        server.close()


@pytest.fixture
def conveyor_server():
    """A factory of :class:`ConveyorServer` (keyword arguments as its own); all closed after the test."""
    servers = []

    def make(**kwargs) -> ConveyorServer:
        servers.append(ConveyorServer(**kwargs))
        return servers[-1]

    yield make
    for server in servers:
        server.close()


@pytest.fixture
def fake_gv():
    """Aravis' fake GigE Vision camera on 127.0.0.1 (a process of its own), stopped after the test."""
    camera = FakeGigECamera()
    yield camera
    camera.close()


@pytest.fixture(scope="session")
def migrated_sqlite(tmp_path_factory) -> Callable[[Path], None]:
    """Puts a copy of a SQLite database migrated to the head by Alembic (once per session) in a data
    dir, where the app's SQLite file goes (as the PostgreSQL tests copy a migrated template):
    ``create_app`` and the consumer still upgrade on start and find it current. The migrations from
    an empty file are tested in tests/api/test_db.py."""
    from app.db import upgrade_database

    template = tmp_path_factory.mktemp("sqlite-template") / "plate_inspect.db"
    upgrade_database(f"sqlite:///{template}")

    def put(data_dir: Path) -> None:
        data_dir.mkdir(parents=True, exist_ok=True)
        src, dst = sqlite3.connect(template), sqlite3.connect(data_dir / "plate_inspect.db")
        try:
            src.backup(dst)
        finally:
            dst.close()
            src.close()

    return put
