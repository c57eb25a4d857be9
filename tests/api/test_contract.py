"""The API contract: error bodies as documented, 405's Allow, no server paths, security headers."""

from __future__ import annotations

import base64
import hashlib
import re

import jsonschema_rs
import pytest
from fastapi.testclient import TestClient

from app.errors import scrub_paths
from pipeline.formats import InputError
from tests.api.helpers import AUTH

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
    assert schemes["APIKeyCookie"] == {
        **schemes["APIKeyCookie"],
        "in": "cookie",
        "name": "plate_inspect_session",
    }
    writes = [name for name, op in _operations(document) if op.get("security")]
    assert (
        "POST /api/v1/plates/{plate_id}/inspections" in writes
        and "PUT /api/v1/plates/{plate_id}/target" in writes
    )
    assert not any(name.startswith("GET ") for name in writes)


@pytest.mark.parametrize(
    ("method", "path", "kwargs"),
    [
        ("GET", f"{API}/inspections", {"params": {"limit": "many"}}),
        ("GET", f"{API}/inspections/x", {}),
        (
            "POST",
            f"{API}/plates/P-1/inspections/simulated",
            {"json": {"n_lights": 1}, "headers": AUTH},
        ),
        ("POST", f"{API}/session", {"json": {}}),
    ],
)
def test_422_bodies_match_the_documented_schema(client, document, method, path, kwargs):
    r = client.request(method, path, **kwargs)
    assert r.status_code == 422, r.text
    template = next(
        p
        for p in document["paths"]
        if re.fullmatch(re.sub(r"\{[^}]+\}", "[^/]+", p), path)
        and method.lower() in document["paths"][p]
    )
    _validator(document, document["paths"][template][method.lower()], "422").validate(r.json())
    body = r.json()
    assert (
        isinstance(body["detail"], str)
        and body["errors"]
        and all({"type", "loc", "msg"} <= set(e) for e in body["errors"])
    )


def test_a_broken_multipart_body_is_a_documented_400(client, document):
    r = client.post(
        f"{API}/calibrations",
        content=b"--x\r\nbroken",
        headers={**AUTH, "Content-Type": "multipart/form-data"},
    )
    assert r.status_code == 400, r.text
    _validator(document, document["paths"][f"{API}/calibrations"]["post"], "400").validate(r.json())
    path = f"{API}/plates/P-1/inspections/simulated"
    r = client.post(
        path, content=b"{not json", headers={**AUTH, "Content-Type": "application/json"}
    )
    assert r.status_code == 400 and r.json()["field"] == "body", r.text
    template = f"{API}/plates/{{plate_id}}/inspections/simulated"
    _validator(document, document["paths"][template]["post"], "400").validate(r.json())


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
        raise InputError(
            f"{secret}/capture.zip", "capture.json", f"cannot read {secret}/capture.json"
        )

    def bug():
        raise OSError(2, "No such file or directory", f"{secret}/result.json")

    client.app.add_api_route("/test-only/input", broken_input)
    client.app.add_api_route("/test-only/bug", bug)
    r = client.get("/test-only/input")
    assert r.status_code == 422 and "/" not in r.json()["file"] and secret not in r.text
    assert r.json()["detail"] == "capture.zip: capture.json: cannot read capture.json"
    with TestClient(client.app, raise_server_exceptions=False) as quiet:
        r = quiet.get("/test-only/bug")
    assert r.status_code == 500 and r.json() == {
        "detail": "internal error: FileNotFoundError",
        "field": None,
    }
    assert r.headers["x-content-type-options"] == "nosniff"  # the 500 answer has the headers too


@pytest.mark.parametrize(
    ("text", "scrubbed"),
    [
        (
            "[Errno 2] No such file or directory: '/srv/cell/var/a/result.json'",
            "[Errno 2] No such file or directory: 'result.json'",
        ),
        ("/tmp/staging/x1/capture.zip: capture.json: bad", "capture.zip: capture.json: bad"),
        ("sections (/home/op/venv/lib/x.py)", "sections (x.py)"),
        (
            "Origin: cross-site write refused (origin http://evil.example/a/b)",
            "Origin: cross-site write refused (origin http://evil.example/a/b)",
        ),
        (
            "Content-Type: expected application/json or multipart/form-data",
            "Content-Type: expected application/json or multipart/form-data",
        ),
    ],
)
def test_scrub_paths_keeps_file_names_only(text, scrubbed):
    assert scrub_paths(text) == scrubbed


# ------------------------------------------------------------------ security headers


def test_every_response_has_the_security_headers(client):
    answers = [
        client.get("/healthz"),
        client.get(f"{API}/plates"),
        client.get(f"{API}/inspections/12345"),
        client.get("/no/such/page"),
        client.get("/cell"),
        client.get("/static/css/app.css"),
        client.post(f"{API}/session", json={"token": "wrong"}),
    ]
    for r in answers:
        assert r.headers["x-content-type-options"] == "nosniff", r.url
        assert r.headers["referrer-policy"] == "same-origin", r.url
        assert r.headers["x-frame-options"] == "DENY", r.url
        policy = r.headers["content-security-policy"]
        assert (
            "script-src 'self';" in policy
            and "frame-ancestors 'none'" in policy
            and "'unsafe-inline'" not in policy
        )


def test_dashboard_pages_have_no_inline_script_or_style(client):
    """The dashboard's CSP allows no inline script or style: its pages must not need any."""
    for page in ("/cell", "/calibration", "/login"):
        html = client.get(page).text
        assert not re.search(r"<script(?![^>]*\bsrc=)[^>]*>", html), page
        assert " style=" not in html and "<style" not in html, page
        assert (
            "frame-src 'self'" in client.get(page).headers["content-security-policy"]
        )  # the 3D view's frame


def test_docs_page_allows_its_start_script_by_hash(client):
    r = client.get("/docs")
    (script,) = re.findall(rb"<script>(.*?)</script>", r.content, re.DOTALL)
    digest = base64.b64encode(hashlib.sha256(script).digest()).decode()
    assert f"'sha256-{digest}'" in r.headers["content-security-policy"]
    assert r.headers["x-frame-options"] == "DENY"
    assert client.get("/static-docs/swagger-ui-bundle.js").status_code == 200
