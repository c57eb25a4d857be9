"""Yard tests: a real PostgreSQL and a real Redis (Debian's packages) for the session; each test
gets a fresh migrated database and an empty Redis."""

from __future__ import annotations

import pytest

from app.settings import Settings
from tests.api.helpers import FAKE_INSPECT, TOKEN
from tests.yard import servers


@pytest.fixture(scope="session")
def pg():
    """(server, migrated template database name)."""
    with servers.running_postgres() as server, servers.migrated_template(server) as template:
        yield server, template


@pytest.fixture(scope="session")
def redis_server():
    with servers.running_redis() as server:
        yield server


@pytest.fixture
def pg_url(pg):
    server, template = pg
    name = server.create_database(template=template)
    yield server.url(name)
    server.drop_database(name)


@pytest.fixture
def queue_url(redis_server):
    redis_server.flush()
    yield redis_server.url(0)
    redis_server.flush()


@pytest.fixture
def yard_settings(tmp_path, pg_url, queue_url) -> Settings:
    """PostgreSQL + Redis, the test double of the pipeline, a short lease (reclaims within seconds)."""
    return Settings(
        data_dir=tmp_path / "data",
        database_url=pg_url,
        queue_url=queue_url,
        api_token=TOKEN,
        progress_interval_s=0.05,
        inspect_entry=FAKE_INSPECT,
        job_lease_s=4.0,
    )
