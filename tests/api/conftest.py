"""Service tests: a real database migrated by Alembic, a real huey consumer process.

Every test that uses ``settings`` runs twice, on the embedded SQLite file (``[sqlite]``) and on a
real PostgreSQL server (``[postgresql]``: one server per test session, a database copied from a
migrated template per test; :mod:`tests.yard.servers`). The job queue is the embedded SQLite one
here; ``tests/yard/`` runs the jobs on Redis."""

from __future__ import annotations

import pytest
from fastapi.testclient import TestClient

from app.main import create_app
from app.settings import Settings
from tests.api.helpers import (
    FAKE_INSPECT,
    TOKEN,
    Consumer,
    render_stations,
    zip_folder,
    zip_stations,
)
from tests.yard import servers


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
def settings(tmp_path, database_url, migrated_sqlite) -> Settings:
    if database_url is None:
        migrated_sqlite(tmp_path / "data")
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


@pytest.fixture(scope="session")
def station_bundles(tmp_path_factory) -> dict:
    """The stations of plate LONG-1 (helpers.render_stations): ``parts`` each station's bundle zipped,
    ``folders`` one zip of the station folders, ``target`` the whole plate's target.json."""
    root = tmp_path_factory.mktemp("stations")
    bundles = render_stations(root)
    return {
        "parts": [zip_folder(b) for b in bundles],
        "folders": zip_stations(bundles),
        "nested": zip_stations(bundles, top="LONG-1/"),
        "target": (root / "target.json").read_bytes(),
    }
