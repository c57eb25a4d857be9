"""Test devices: a TCP light controller and a TCP conveyor of the tests' own, and Aravis' fake GigE
Vision camera.

:class:`LightServer` is a real TCP server on loopback that speaks the tcp driver's protocol (one
command per line, an ``OK`` line per command unless told otherwise) and records every command; it
can refuse a command, stop answering, or call back on a command (to pull a camera away mid-way).
:class:`ConveyorServer` is one that speaks the tcp conveyor's (``MOVE <mm>`` answered ``OK
<encoder_mm>``), with a conveyor's positioning errors; it can refuse a move or stop answering.
:class:`FakeGigECamera` runs ``arv-fake-gv-camera-0.8 -i 127.0.0.1`` (Debian's aravis-tools), a
separate process that speaks GigE Vision over loopback.
"""

from __future__ import annotations

import fcntl
import shutil
import socketserver
import subprocess
import tempfile
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path

FAKE_GV_CAMERA = "arv-fake-gv-camera-0.8"
FAKE_GV_ADDRESS = "127.0.0.1"
#: The file the test processes' fake GigE cameras take turns on (see :class:`FakeGigECamera`).
FAKE_GV_LOCK = Path(tempfile.gettempdir()) / "plate-inspect-fake-gv.lock"


class _Server(socketserver.ThreadingTCPServer):
    daemon_threads = True
    allow_reuse_address = True


def _serve(handler: type[socketserver.StreamRequestHandler]) -> _Server:
    """A TCP server on ``127.0.0.1:<free port>`` serving ``handler`` in a daemon thread, started."""
    server = _Server(("127.0.0.1", 0), handler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    return server


class LightServer:
    """A light controller on ``127.0.0.1:<free port>``.

    Parameters
    ----------
    reply : str or None
        The line sent after each accepted command (None: a silent controller).
    echo : bool
        Send each command back first.
    refuse : str or None
        A command (without its line break) answered with ``ERR refused`` instead.
    stall_after : int or None
        After this many commands, read but never answer again.
    on_command : callable, optional
        ``on_command(command)`` before the answer, in the server's thread.
    """

    def __init__(
        self,
        *,
        reply: str | None = "OK",
        echo: bool = False,
        refuse: str | None = None,
        stall_after: int | None = None,
        on_command: Callable[[str], None] | None = None,
    ):
        self.commands: list[str] = []
        self.connections = 0
        self._reading = 0  # connections whose commands are still being read
        self._read = threading.Condition()
        server = self

        class Handler(socketserver.StreamRequestHandler):
            def handle(self) -> None:
                with server._read:
                    server.connections += 1
                    server._reading += 1
                try:
                    self._commands()
                finally:
                    with server._read:
                        server._reading -= 1
                        server._read.notify_all()

            def _commands(self) -> None:
                for raw in self.rfile:
                    command = raw.decode().rstrip("\r\n")
                    server.commands.append(command)
                    if on_command is not None:
                        on_command(command)
                    if stall_after is not None and len(server.commands) > stall_after:
                        continue
                    if echo:
                        self.wfile.write(raw)
                    if command == refuse:
                        self.wfile.write(b"ERR refused\n")
                    elif reply is not None:
                        self.wfile.write(reply.encode() + b"\n")

        self._server = _serve(Handler)
        self.address = f"127.0.0.1:{self._server.server_address[1]}"

    def settled(self, connections: int = 1, timeout_s: float = 10.0) -> list[str]:
        """The commands once ``connections`` connections have been read to their end (the client closed
        them). A client of a silent controller does not wait for its commands to be read: they may
        still be in the socket when it returns."""
        with self._read:
            self._read.wait_for(
                lambda: self.connections >= connections and self._reading == 0, timeout_s
            )
        return self.commands

    def close(self) -> None:
        self._server.shutdown()
        self._server.server_close()


class ConveyorServer:
    """A conveyor controller on ``127.0.0.1:<free port>``.

    ``MOVE <mm>`` moves the plate by that much plus the move's positioning error and answers ``OK
    <position>`` (the encoder's reading, 2 decimals, from the controller's own zero).

    Parameters
    ----------
    start_mm : float
        The encoder's reading before the first move.
    errors_mm : sequence of float
        The positioning error of each move in turn (0 after the last).
    refuse : int or None
        The move (0-based count of ``MOVE`` commands) answered ``ERR blocked`` instead.
    stall : int or None
        From this move on, read but never answer.
    reply : str or None
        Answer every move with this line instead of ``OK <position>``.
    echo : bool
        Send each command back first.
    on_command : callable, optional
        ``on_command(command)`` when a command arrives, in the server's thread.
    """

    def __init__(
        self,
        *,
        start_mm: float = 1000.0,
        errors_mm: Sequence[float] = (),
        refuse: int | None = None,
        stall: int | None = None,
        reply: str | None = None,
        echo: bool = False,
        on_command: Callable[[str], None] | None = None,
    ):
        self.commands: list[str] = []
        self.position_mm = start_mm
        server = self

        class Handler(socketserver.StreamRequestHandler):
            def handle(self) -> None:
                for raw in self.rfile:
                    command = raw.decode().rstrip("\r\n")
                    move = len(server.commands)
                    server.commands.append(command)
                    if on_command is not None:
                        on_command(command)
                    if stall is not None and move >= stall:
                        continue
                    if echo:
                        self.wfile.write(raw)
                    verb, _, amount = command.partition(" ")
                    if verb != "MOVE":
                        self.wfile.write(b"ERR unknown command\n")
                    elif move == refuse:
                        self.wfile.write(b"ERR blocked\n")
                    else:
                        error = errors_mm[move] if move < len(errors_mm) else 0.0
                        server.position_mm += float(amount) + error
                        line = reply if reply is not None else f"OK {server.position_mm:.2f}"
                        self.wfile.write(line.encode() + b"\n")

        self._server = _serve(Handler)
        self.address = f"127.0.0.1:{self._server.server_address[1]}"

    def close(self) -> None:
        self._server.shutdown()
        self._server.server_close()


class FakeGigECamera:
    """``arv-fake-gv-camera-0.8 -i 127.0.0.1 -s SERIAL [-r LOST]`` running until :meth:`stop`.

    Waits until Aravis opens the camera at 127.0.0.1 and checks that it is this one (its serial):
    only one fake GigE camera can answer on the loopback address. So the test processes (pytest-xdist's
    workers) take turns: each camera holds :data:`FAKE_GV_LOCK` from its start to :meth:`close`, after
    the test (a camera stopped mid-test, one that vanishes, keeps the address free of another's until
    then).
    """

    def __init__(self, serial: str = "PITEST", *, lost_packets_per_thousand: int = 0):
        if shutil.which(FAKE_GV_CAMERA) is None:
            raise RuntimeError(
                f"{FAKE_GV_CAMERA} not found: scripts/setup.sh installs Debian's aravis-tools"
            )
        self._lock = open(FAKE_GV_LOCK, "a")  # noqa: SIM115 - held until close()
        fcntl.flock(self._lock, fcntl.LOCK_EX)
        import gi

        gi.require_version("Aravis", "0.8")
        from gi.repository import Aravis, GLib

        self.serial = serial
        self.device_id = FAKE_GV_ADDRESS
        command = [
            FAKE_GV_CAMERA,
            "-i",
            FAKE_GV_ADDRESS,
            "-s",
            serial,
            "-r",
            str(lost_packets_per_thousand),
        ]
        try:
            self._process = subprocess.Popen(
                command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT
            )
            deadline = time.monotonic() + 15
            while True:
                if self._process.poll() is not None:
                    raise RuntimeError(
                        f"{FAKE_GV_CAMERA} exited: {self._process.stdout.read().decode().strip()}"
                    )
                try:
                    found = Aravis.Camera.new(FAKE_GV_ADDRESS).get_device_serial_number()
                except GLib.Error:
                    found = None
                if found == serial:
                    return
                if found is not None or time.monotonic() > deadline:
                    self.stop()  # (the lock is released below)
                    raise RuntimeError(
                        f"the fake GigE camera at {FAKE_GV_ADDRESS} is {found!r}, not this test's {serial!r}"
                    )
                time.sleep(0.2)
        except BaseException:
            self._release()
            raise

    def stop(self) -> None:
        """Stop the camera (it vanishes from the network)."""
        if self._process.poll() is None:
            self._process.terminate()
            self._process.wait(timeout=10)

    def close(self) -> None:
        """Stop the camera and let another test process start one."""
        self.stop()
        self._release()

    def _release(self) -> None:
        if not self._lock.closed:
            fcntl.flock(self._lock, fcntl.LOCK_UN)
            self._lock.close()
