"""The API contract: error bodies as documented, 405's Allow, no server paths."""

from __future__ import annotations

import re

import jsonschema_rs
import pytest
from fastapi.testclient import TestClient

from app.errors import scrub_paths
from pipeline.formats import InputError
from tests.api.conftest import AUTH

API = "/api/v1"


@pytest.fixture
def document(client) -> dict:
    return client.get("/openapi.json").json()


def _validator(document: dict, operation: dict, status: str):
    """A JSON Schema validator of the body the document gives for ``status`` of ``operation``."""
    schema = operation["responses"][status]["content"]["application/json"]["schema"]
    return jsonschema_rs.Draft202012Validator({**schema, "components": document["components"]})


def _operations(document: dict):
    for path, operations in document["paths"].items():
        for method, operation in operations.items():
            yield f"{method.upper()} {path}", operation


# ------------------------------------------------------------------ documented error bodies


def test_every_operation_documents_the_errors_it_can_send_as_one_error_model(document):
    assert "HTTPValidationError" not in document["components"]["schemas"]
    for name, operation in _operations(document):
        responses = operation["responses"]
        expected = set()
        if operation.get("parameters") or operation.get("requestBody"):
            expected.add("422")
        if operation.get("requestBody"):
            expected |= {"400", "413"}
        if operation.get("security"):
            expected |= {"401", "403", "429"}
        assert expected <= set(responses), (name, sorted(responses))
        for status, response in responses.items():
            if status.startswith("4"):
                schema = response["content"]["application/json"]["schema"]
                assert schema == {"$ref": "#/components/schemas/ErrorOut"}, (name, status)


def test_writes_declare_their_security(document):
    schemes = document["components"]["securitySchemes"]
    assert schemes["HTTPBearer"]["scheme"] == "bearer"
    assert schemes["APIKeyCookie"] == {**schemes["APIKeyCookie"], "in": "cookie", "name": "plate_inspect_session"}
    writes = [name for name, op in _operations(document) if op.get("security")]
    assert "POST /api/v1/plates/{plate_id}/inspections" in writes and "PUT /api/v1/plates/{plate_id}/target" in writes
    assert not any(name.startswith("GET ") for name in writes)


@pytest.mark.parametrize(
    ("method", "path", "kwargs"),
    [
        ("GET", f"{API}/inspections", {"params": {"limit": "many"}}),
        ("GET", f"{API}/inspections/x", {}),
        ("POST", f"{API}/plates/P-1/inspections/simulated", {"json": {"n_lights": 1}, "headers": AUTH}),
        ("POST", f"{API}/plates/P-1/inspections/simulated", {"content": b"{not json", "headers": {**AUTH, "Content-Type": "application/json"}}),
        ("POST", f"{API}/session", {"json": {}}),
    ],
)
def test_422_bodies_match_the_documented_schema(client, document, method, path, kwargs):
    r = client.request(method, path, **kwargs)
    assert r.status_code == 422, r.text
    template = next(
        p for p in document["paths"]
        if re.fullmatch(re.sub(r"\{[^}]+\}", "[^/]+", p), path)
        and method.lower() in document["paths"][p]
    )
    _validator(document, document["paths"][template][method.lower()], "422").validate(r.json())
    body = r.json()
    assert isinstance(body["detail"], str) and body["errors"] and all({"type", "loc", "msg"} <= set(e) for e in body["errors"])


def test_a_broken_multipart_body_is_a_documented_400(client, document):
    r = client.post(
        f"{API}/calibrations", content=b"--x\r\nbroken", headers={**AUTH, "Content-Type": "multipart/form-data"}
    )
    assert r.status_code == 400, r.text
    _validator(document, document["paths"][f"{API}/calibrations"]["post"], "400").validate(r.json())


# ------------------------------------------------------------------ 405


@pytest.mark.parametrize(
    ("method", "path", "allow"),
    [
        ("PATCH", f"{API}/plates/P-1/target", "GET, PUT"),
        ("DELETE", f"{API}/plates/P-1/inspections", "GET, POST"),
        ("PUT", f"{API}/session", "POST, DELETE"),
        ("POST", f"{API}/inspections/1", "GET"),
        ("POST", "/cell", "GET"),
        ("POST", "/static/css/app.css", "GET, HEAD"),
    ],
)
def test_405_allow_lists_every_method_of_the_path(client, method, path, allow):
    r = client.request(method, path)
    assert r.status_code == 405
    assert r.headers["allow"] == allow
    if path.startswith(API):
        assert r.json()["field"] == "method" and allow in r.json()["detail"]


# ------------------------------------------------------------------ no server paths


def test_messages_built_from_exceptions_carry_no_server_path(client, settings):
    secret = str(settings.data_dir.resolve() / "inspections" / "7" / "inputs")

    def broken_input():
        raise InputError(f"{secret}/capture.zip", "capture.json", f"cannot read {secret}/capture.json")

    def bug():
        raise OSError(2, "No such file or directory", f"{secret}/result.json")

    client.app.add_api_route("/test-only/input", broken_input)
    client.app.add_api_route("/test-only/bug", bug)
    r = client.get("/test-only/input")
    assert r.status_code == 422 and "/" not in r.json()["file"] and secret not in r.text
    assert r.json()["detail"] == "capture.zip: capture.json: cannot read capture.json"
    with TestClient(client.app, raise_server_exceptions=False) as quiet:
        r = quiet.get("/test-only/bug")
    assert r.status_code == 500 and r.json() == {"detail": "internal error: FileNotFoundError", "field": None}


@pytest.mark.parametrize(
    ("text", "scrubbed"),
    [
        ("[Errno 2] No such file or directory: '/srv/cell/var/a/result.json'", "[Errno 2] No such file or directory: 'result.json'"),
        ("/tmp/staging/x1/capture.zip: capture.json: bad", "capture.zip: capture.json: bad"),
        ("sections (/home/op/venv/lib/x.py)", "sections (x.py)"),
        ("Origin: cross-site write refused (origin http://evil.example/a/b)", "Origin: cross-site write refused (origin http://evil.example/a/b)"),
        ("Content-Type: expected application/json or multipart/form-data", "Content-Type: expected application/json or multipart/form-data"),
    ],
)
def test_scrub_paths_keeps_file_names_only(text, scrubbed):
    assert scrub_paths(text) == scrubbed
