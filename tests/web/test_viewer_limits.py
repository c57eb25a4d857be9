"""Room for the operator in the 3D view: websockets per anonymous address, servers kept for sessions and loopback.

A real app (create_app, SQLite migrated by Alembic) with seeded inspections; the bridges reach
real viser servers on loopback. TestClient's peer address is chosen per client.
"""

from __future__ import annotations

from contextlib import ExitStack

import pytest
from fastapi.testclient import TestClient
from starlette.websockets import WebSocketDisconnect

from app.viewer import CLOSE_TRY_AGAIN_LATER, VISER_SUBPROTOCOL
from tests.web.helpers import seed_done_inspection

TOKEN = "viewer-limits-token-0123"


@pytest.fixture
def app(tmp_path):
    """At most 3 viewer servers, 1 kept for the operator, 2 websockets per anonymous address."""
    from app.main import create_app
    from app.settings import Settings

    app = create_app(
        Settings(
            data_dir=tmp_path / "data",
            api_token=TOKEN,
            viewer_max_servers=3,
            viewer_reserved_servers=1,
            viewer_max_sockets_per_client=2,
        )
    )
    app.state.test_ids = [seed_done_inspection(app, plate_id=f"H9-P{i}") for i in range(4)]
    yield app
    app.state.engine.dispose()


def _open(stack: ExitStack, client: TestClient, inspection_id: int):
    """A connected bridge (viser's first message relayed), kept open until ``stack`` closes."""
    ws = stack.enter_context(
        client.websocket_connect(f"/viewer/{inspection_id}", subprotocols=[VISER_SUBPROTOCOL])
    )
    assert len(ws.receive_bytes()) > 0
    return ws


def _refused(client: TestClient, inspection_id: int) -> WebSocketDisconnect:
    with (
        pytest.raises(WebSocketDisconnect) as closed,
        client.websocket_connect(
            f"/viewer/{inspection_id}", subprotocols=[VISER_SUBPROTOCOL]
        ) as ws,
    ):
        ws.receive_bytes()
    return closed.value


def _client(app, host: str) -> TestClient:
    return TestClient(app, client=(host, 40000))


def test_an_anonymous_address_holds_at_most_its_websockets(app):
    first, second, *_ = app.state.test_ids
    anonymous = _client(app, "10.0.0.5")
    with TestClient(app) as main:
        with ExitStack() as stack:
            _open(stack, anonymous, first)
            _open(stack, anonymous, second)
            refused = _refused(anonymous, first)
            assert (
                refused.code == CLOSE_TRY_AGAIN_LATER
                and "already has 2 3D views open" in refused.reason
            )
            page = anonymous.get(f"/viewer/{first}/")
            assert page.status_code == 503 and "already has 2 3D views open" in page.text
            assert (
                page.headers["x-frame-options"] == "SAMEORIGIN"
            )  # shown inside the dashboard's frame
            # Another address is not affected.
            _open(stack, _client(app, "10.0.0.6"), first)
            assert main.app.state.viewer.running() == sorted([first, second])
        with ExitStack() as stack:  # closed sockets are given back
            _open(stack, anonymous, first)
            _open(stack, anonymous, second)


def test_anonymous_clients_leave_the_reserved_servers_to_the_operator(app):
    ids = app.state.test_ids
    with TestClient(app) as main, ExitStack() as stack:
        # Two anonymous addresses start two servers: all those not kept for the operator.
        _open(stack, _client(app, "10.0.0.1"), ids[0])
        _open(stack, _client(app, "10.0.0.2"), ids[1])
        third = _client(app, "10.0.0.3")
        refused = _refused(third, ids[2])
        assert refused.code == CLOSE_TRY_AGAIN_LATER and "kept for the operator" in refused.reason
        assert third.get(f"/viewer/{ids[2]}/").status_code == 503
        _open(stack, third, ids[0])  # a running view is open to anyone
        assert main.app.state.viewer.running() == sorted(ids[:2])

        # The operator with a dashboard session gets the reserved server.
        operator = _client(app, "10.0.0.9")
        assert operator.post("/api/v1/session", json={"token": TOKEN}).status_code == 204
        page = operator.get(f"/viewer/{ids[2]}/")
        assert page.status_code == 200 and page.headers["x-frame-options"] == "SAMEORIGIN"
        policy = page.headers["content-security-policy"]
        assert (
            "'strict-dynamic'" in policy
            and "'sha256-" in policy
            and "frame-ancestors 'self'" in policy
        )
        _open(stack, operator, ids[2])
        assert main.app.state.viewer.running() == sorted(ids[:3])
        # Every server has a browser now: even the operator is told so.
        refused = _refused(operator, ids[3])
        assert (
            refused.code == CLOSE_TRY_AGAIN_LATER
            and "3 inspections are already being viewed" in refused.reason
        )


def test_the_cells_own_screen_on_loopback_is_the_operator(app):
    ids = app.state.test_ids
    with TestClient(app), ExitStack() as stack:
        _open(stack, _client(app, "10.0.0.1"), ids[0])
        _open(stack, _client(app, "10.0.0.2"), ids[1])
        assert _refused(_client(app, "10.0.0.3"), ids[2]).code == CLOSE_TRY_AGAIN_LATER
        cell_screen = _client(app, "127.0.0.1")
        _open(stack, cell_screen, ids[2])
        # Loopback is not held to the per-address limit either.
        _open(stack, cell_screen, ids[2])
        _open(stack, cell_screen, ids[0])


def test_a_revoked_session_is_anonymous_again(app):
    ids = app.state.test_ids
    with TestClient(app), ExitStack() as stack:
        _open(stack, _client(app, "10.0.0.1"), ids[0])
        _open(stack, _client(app, "10.0.0.2"), ids[1])
        operator = _client(app, "10.0.0.9")
        assert operator.post("/api/v1/session", json={"token": TOKEN}).status_code == 204
        cookie = operator.cookies.get("plate_inspect_session")
        assert operator.delete("/api/v1/session").status_code == 204
        operator.cookies.set("plate_inspect_session", cookie)  # a copy kept after logout
        assert "kept for the operator" in _refused(operator, ids[2]).reason
