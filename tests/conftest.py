"""Configuration shared by every test package: the thread policy of a process that runs inspections,
and the fixtures of the cell's fake devices (Aravis' fake GigE Vision camera, the tests' own TCP
light controller), used by the acquisition and the service's acquire tests.

The thread policy is set here, before any test runs a compiled kernel, as the CLI and the job
consumer set it at start (:func:`pipeline.parallel.configure_process`).
"""

import pytest

from pipeline.parallel import configure_process
from tests.acquisition.devices import FakeGigECamera, LightServer

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
def fake_gv():
    """Aravis' fake GigE Vision camera on 127.0.0.1 (a process of its own), stopped after the test."""
    camera = FakeGigECamera()
    yield camera
    camera.stop()
