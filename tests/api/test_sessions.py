"""Dashboard sessions (random, stored hashed, expiring, revocable) and the throttle of wrong tokens."""

from __future__ import annotations

import asyncio
import hashlib
import sqlite3
from concurrent.futures import ThreadPoolExecutor
from datetime import timedelta

import pytest
from fastapi.testclient import TestClient
from pydantic import SecretStr
from sqlalchemy import select

from app.deps import SESSION_COOKIE
from app.main import create_app
from app.models import DashboardSession, utcnow
from app.throttle import FIRST_DELAY_S, TokenThrottle, client_key
from tests.api.helpers import AUTH, TOKEN

SIMULATED = "/api/v1/plates/P-1/inspections/simulated"


def _login(client, token: str = TOKEN):
    return client.post("/api/v1/session", json={"token": token})


def _write(client, **headers):
    return client.post(SIMULATED, json={"width": 320, "height": 256}, headers=headers)


def _rows(app) -> list[DashboardSession]:
    with app.state.session_factory() as session:
        return list(session.scalars(select(DashboardSession)))


def _with_cookie(app, value: str | bytes) -> TestClient:
    """A client of ``app`` that sends ``value`` as the session cookie (raw header, any bytes)."""
    raw = value if isinstance(value, bytes) else value.encode("ascii")
    return TestClient(app, headers={"Cookie": SESSION_COOKIE.encode() + b"=" + raw})


@pytest.fixture
def demo_app(settings):
    """The app in demo mode (its pages open sessions themselves)."""
    app = create_app(settings.model_copy(update={"demo": True}))
    yield app
    app.state.engine.dispose()


# ------------------------------------------------------------------ sessions


def test_each_login_is_a_new_random_session_stored_only_as_its_hash(client, settings):
    first = _login(client)
    assert first.status_code == 204, first.text
    cookie = first.headers["set-cookie"].lower()
    assert "httponly" in cookie and "samesite=strict" in cookie and "path=/" in cookie
    assert f"max-age={12 * 3600}" in cookie  # PLATE_INSPECT_SESSION_HOURS: a shift by default
    values = [first.cookies[SESSION_COOKIE]] + [
        _login(client).cookies[SESSION_COOKIE] for _ in range(2)
    ]
    assert len(set(values)) == 3 and all(len(v) == 43 for v in values)

    rows = _rows(client.app)
    assert {r.id_hash for r in rows} == {hashlib.sha256(v.encode()).hexdigest() for v in values}
    assert all(
        r.expires_at - r.created_at == timedelta(hours=12) and r.revoked_at is None for r in rows
    )
    # Neither the session ids nor the token are in the database file.
    client.app.state.engine.dispose()
    dump = "\n".join(sqlite3.connect(settings.data_dir / "plate_inspect.db").iterdump())
    assert not any(v in dump for v in values) and TOKEN not in dump


def test_logout_revokes_the_session_on_the_server(client):
    value = _login(client).cookies[SESSION_COOKIE]
    assert _write(client).status_code == 202
    assert client.delete("/api/v1/session").status_code == 204
    # The browser dropped the cookie; a copy of its value kept elsewhere is refused too.
    replay = _with_cookie(client.app, value)
    r = _write(replay)
    assert r.status_code == 401 and r.json()["field"] == SESSION_COOKIE, r.text
    (row,) = _rows(client.app)
    assert row.revoked_at is not None
    # Another login is another session; logging out without one is harmless.
    assert _login(client).status_code == 204 and _write(client).status_code == 202
    assert TestClient(client.app).delete("/api/v1/session").status_code == 204


def test_an_expired_session_no_longer_writes(client):
    value = _login(client).cookies[SESSION_COOKIE]
    with client.app.state.session_factory() as session:
        row = session.get(DashboardSession, hashlib.sha256(value.encode()).hexdigest())
        row.expires_at = utcnow() - timedelta(seconds=1)
        session.commit()
    r = _write(client)
    assert r.status_code == 401 and "log in again" in r.json()["detail"]


def test_session_lifetime_is_a_setting(settings):
    app = create_app(settings.model_copy(update={"session_hours": 0.5}))
    with TestClient(app) as c:
        assert "max-age=1800" in _login(c).headers["set-cookie"].lower()
        (row,) = _rows(app)
        assert row.expires_at - row.created_at == timedelta(minutes=30)
    app.state.engine.dispose()


def test_a_new_api_token_ends_the_sessions_of_the_old_one(client, settings):
    value = _login(client).cookies[SESSION_COOKIE]
    client.app.state.engine.dispose()
    rotated = create_app(
        settings.model_copy(update={"api_token": SecretStr("another-token-98765")})
    )
    r = _write(_with_cookie(rotated, value))
    assert r.status_code == 401 and r.json()["field"] == SESSION_COOKIE
    rotated.state.engine.dispose()


@pytest.mark.parametrize(
    "value",
    ["é".encode(), "\u00ff\u00fe".encode("latin-1"), b"x" * 43, b"../../etc/passwd", b""],
)
def test_a_bad_cookie_is_no_session(demo_app, value):
    with _with_cookie(demo_app, value) as c:
        page = c.get("/cell")
        assert page.status_code == 200
        assert SESSION_COOKIE in page.headers.get("set-cookie", "")  # demo: a fresh session instead
        r = c.post(SIMULATED, json={})
        assert r.status_code == 401, r.text
        assert "internal error" not in r.text


def test_a_bad_cookie_is_no_session_outside_demo_mode(client):
    with _with_cookie(client.app, "é".encode()) as c:
        page = c.get("/cell")
        assert page.status_code == 200 and "operator session" not in page.text
        assert c.get("/login").status_code == 200


def test_demo_pages_open_a_session_that_writes(demo_app):
    with TestClient(demo_app) as c:
        first = c.get("/cell")
        value = first.cookies[SESSION_COOKIE]
        assert "operator session" in first.text
        # The browser holds a valid session now: no new one per page.
        assert SESSION_COOKIE not in c.get("/calibration").headers.get("set-cookie", "")
        assert c.post(SIMULATED, json={"width": 320, "height": 256}).status_code == 202
        # A browser without the cookie gets a session of its own.
        other = TestClient(demo_app).get("/cell").cookies[SESSION_COOKIE]
        assert other != value
        assert len(_rows(demo_app)) == 2


# ------------------------------------------------------------------ throttle of wrong tokens


@pytest.fixture
def throttled(settings):
    """An app whose throttle allows 3 free failures and spaces checks at most 0.05 s (quick tests)."""
    app = create_app(
        settings.model_copy(update={"login_free_failures": 3, "login_max_delay_s": 0.05})
    )
    yield app
    app.state.engine.dispose()


def test_wrong_tokens_get_429_with_retry_after_but_the_right_one_always_logs_in(throttled):
    with TestClient(throttled) as c:
        codes = [_login(c, "wrong").status_code for _ in range(6)]
        assert codes == [401, 401, 401, 429, 429, 429]
        r = _login(c, "wrong")
        assert r.status_code == 429 and int(r.headers["retry-after"]) >= 1
        assert r.json()["field"] == "token" and "wrong token" in r.json()["detail"]
        assert _login(c).status_code == 204  # the right token, from the throttled address
        assert _login(c, "wrong").status_code == 401  # and that address starts afresh


def test_bearer_guesses_count_and_other_addresses_are_not_slowed(throttled):
    with TestClient(throttled) as c, TestClient(throttled, client=("10.1.2.3", 5000)) as other:
        for _ in range(3):
            assert _write(c, Authorization="Bearer wrong").status_code == 401
        r = _write(c, Authorization="Bearer wrong")
        assert (
            r.status_code == 429
            and r.headers["retry-after"]
            and r.headers["www-authenticate"] == "Bearer"
        )
        assert (
            _login(c, "wrong").status_code == 429
        )  # one count for both ways of presenting a token
        # Malformed headers guess nothing and do not count.
        assert _write(other, Authorization="Basic dGVzdA==").status_code == 401
        assert throttled.state.token_throttle.failures(client_key("10.1.2.3")) == 0
        assert _login(other, "wrong").status_code == 401
        assert _write(c, **AUTH).status_code == 202


def test_a_flood_of_wrong_tokens_never_refuses_the_right_one(throttled):
    """Concurrent wrong tokens from one address and the right one among them: the right one logs in."""
    with TestClient(throttled) as c:
        tokens = ["wrong"] * 12 + [TOKEN] + ["wrong"] * 12
        with ThreadPoolExecutor(8) as pool:
            codes = list(pool.map(lambda t: _login(c, t).status_code, tokens))
        assert codes[12] == 204
        assert set(codes[:12] + codes[13:]) <= {401, 429} and 429 in codes
        assert _login(c).status_code == 204


def test_throttled_checks_are_spaced_out_one_at_a_time():
    """After the free failures, every check of the address waits its turn: growing, capped spacing."""
    now = [0.0]

    async def sleep(seconds: float) -> None:
        pass  # the turn is what is checked here; the clock is stepped by hand

    throttle = TokenThrottle(
        free_failures=2, window_s=60.0, max_delay_s=2.0, clock=lambda: now[0], sleep=sleep
    )
    assert throttle.failed("a") is None and throttle.failed("a") is None
    # Two failures: the next check waits FIRST_DELAY_S; four concurrent ones queue behind each other.
    waits = asyncio.run(_gather(throttle, "a", 4))
    assert waits == pytest.approx([FIRST_DELAY_S * k for k in (1, 2, 3, 4)])
    assert asyncio.run(throttle.wait_turn("b")) == 0.0  # another address is not slowed
    # Every further failure doubles the spacing up to max_delay_s.
    now[0] = 100.0  # the failures above are forgotten after the window
    spacings = []
    for _ in range(6):
        retry = throttle.failed("c")
        spacings.append(retry)
    assert spacings[:2] == [None, None]
    assert spacings[2:] == pytest.approx([1.0, 2.0, 2.0, 2.0])
    throttle.succeeded("c")
    assert throttle.failures("c") == 0 and asyncio.run(throttle.wait_turn("c")) == 0.0


async def _gather(throttle: TokenThrottle, client: str, n: int) -> list[float]:
    return list(await asyncio.gather(*(throttle.wait_turn(client) for _ in range(n))))


def test_ipv6_clients_are_counted_per_64_block():
    assert client_key("2001:db8::1") == client_key("2001:db8::ffff:1") == "2001:db8::/64"
    assert client_key("::ffff:10.0.0.7") == "10.0.0.7"
    assert client_key("10.0.0.7") == "10.0.0.7" and client_key(None) == "unknown"
