"""Acquisition tests: Aravis' fake cameras, a TCP light controller of the tests' own, cell configs."""

from __future__ import annotations

import pytest

from tests.acquisition.devices import FakeGigECamera, LightServer


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
def fake_gv():
    """Aravis' fake GigE Vision camera on 127.0.0.1 (a process of its own), stopped after the test."""
    camera = FakeGigECamera()
    yield camera
    camera.stop()
