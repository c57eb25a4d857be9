"""While PostgreSQL is down the service answers 503 with a clear message, and recovers by itself."""

from __future__ import annotations

from fastapi.testclient import TestClient

from app.main import create_app
from app.settings import Settings
from tests.api.helpers import TOKEN
from tests.yard import servers


def test_a_stopped_database_is_503_and_the_service_recovers_when_it_is_back(tmp_path):
    with servers.running_postgres() as server:
        settings = Settings(
            data_dir=tmp_path / "data", database_url=server.url("postgres"), api_token=TOKEN
        )
        app = create_app(settings)  # brings the empty database to the current schema
        with TestClient(app) as client:
            assert client.get("/api/v1/inspections").status_code == 200
            server.stop()
            for path in ("/api/v1/inspections", "/api/v1/plates", "/healthz"):
                r = client.get(path)
                assert r.status_code == 503, (path, r.text)
                assert r.json()["detail"].startswith("database unavailable:"), r.text
                assert r.headers["Retry-After"] == "5"
            server.start()
            r = client.get("/api/v1/inspections")
            assert r.status_code == 200, r.text  # the pool's pre-ping replaced the dead connections
            assert client.get("/healthz").json()["database"] == "ok"
        app.state.engine.dispose()
    assert "503" in app.openapi()["paths"]["/api/v1/inspections"]["get"]["responses"]
