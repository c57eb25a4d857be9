"""Property-based API tests (schemathesis): every operation, as documented, answers as documented.

The app is the real one (create_app on a temp data dir, SQLite migrated by Alembic, the test
double of the pipeline as the job's entry; no consumer runs, jobs stay queued), called in-process
over ASGI with the API token. For every operation of /openapi.json schemathesis generates
requests from the document (valid ones and ones that break it) and checks that no answer is a
5xx, that every status code and content type is documented, and that every body matches its
documented schema. Examples are few and derandomized (the same ones every run) so that the
whole file runs in about a minute on two cores.
"""

from __future__ import annotations

import pytest
import schemathesis
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from schemathesis import GenerationMode
from schemathesis.checks import (
    content_type_conformance,
    not_a_server_error,
    response_schema_conformance,
    status_code_conformance,
)

from app.main import create_app
from app.settings import Settings
from tests.api.helpers import AUTH, FAKE_INSPECT, TOKEN

#: Generated requests per operation (valid and invalid ones together).
MAX_EXAMPLES = 25
CHECKS = [
    not_a_server_error,
    status_code_conformance,
    content_type_conformance,
    response_schema_conformance,
]


@pytest.fixture(scope="module")
def api_schema(tmp_path_factory):
    settings = Settings(
        data_dir=tmp_path_factory.mktemp("schemathesis") / "data",
        api_token=TOKEN,
        max_upload_mb=8.0,
        inspect_entry=FAKE_INSPECT,
        # Generated bodies of POST /session carry wrong tokens: unthrottled here, so that the
        # test's requests from one address are not spaced out (tests/api/test_sessions.py covers it).
        login_free_failures=1_000_000,
    )
    app = create_app(settings)
    yield schemathesis.openapi.from_asgi("/openapi.json", app)
    app.state.engine.dispose()


def test_every_operation_answers_as_documented(api_schema, subtests):
    # One subtest per operation (schemathesis' own pytest loader for fixtures does not run on pytest 9).
    operations = [result.ok() for result in api_schema.get_all_operations()]
    assert len(operations) >= 20
    for operation in operations:
        with subtests.test(operation=operation.label):
            _fuzz(operation)


def _fuzz(operation) -> None:
    cases = st.one_of(
        operation.as_strategy(generation_mode=GenerationMode.POSITIVE),
        operation.as_strategy(generation_mode=GenerationMode.NEGATIVE),
    )

    @given(case=cases)
    @settings(
        max_examples=MAX_EXAMPLES,
        deadline=None,
        derandomize=True,
        database=None,
        suppress_health_check=list(HealthCheck),
    )
    def check(case) -> None:
        response = case.call_and_validate(headers=AUTH, checks=CHECKS)
        assert response.status_code < 500

    check()
