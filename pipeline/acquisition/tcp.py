"""One TCP connection to a device of the cell that takes one text line per command and may answer
with lines: the tcp light controller (:mod:`~pipeline.acquisition.lights`) and the tcp conveyor
(:mod:`~pipeline.acquisition.conveyor`). Every failure is an :class:`AcquisitionError` naming the
device and the step.
"""

from __future__ import annotations

import socket
import time
from collections.abc import Container

from ..formats import AcquisitionError

#: Seconds to wait for the connection to a device (the light controller, the conveyor).
CONNECT_TIMEOUT_S = 3.0
#: First words of a line that accepts a command (case-insensitive).
ACCEPTED = ("OK", "ACK")


class LineConnection:
    """A connected TCP socket that sends lines and reads the lines that come back.

    Parameters
    ----------
    address : str
        ``HOST:PORT`` (an IPv6 host in brackets).
    device : str
        How errors name the device (``"light controller 192.168.10.20:5000"``).
    connect_timeout_s : float
        Seconds to wait for the connection.

    Raises
    ------
    AcquisitionError
        The device cannot be reached (refused, unknown host, no connection within the timeout), at
        step ``connecting``.
    """

    def __init__(self, address: str, device: str, *, connect_timeout_s: float) -> None:
        self.device = device
        self._pending = b""
        host, _, port = address.rpartition(":")
        try:
            self._sock = socket.create_connection(
                (host.strip("[]"), int(port)), timeout=connect_timeout_s
            )
        except TimeoutError:
            raise AcquisitionError(
                device, "connecting", f"no connection within {connect_timeout_s:g} s"
            ) from None
        except OSError as exc:
            raise AcquisitionError(device, "connecting", exc.strerror or str(exc)) from None
        self._sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)

    def send(self, line: str, *, step: str, timeout_s: float) -> None:
        """Send ``line`` (a ``\\n`` is added unless it ends in one) within ``timeout_s`` seconds."""
        if not line.endswith("\n"):
            line += "\n"
        sent = line.strip()
        try:
            self._sock.settimeout(timeout_s)
            self._sock.sendall(line.encode())
        except TimeoutError:
            raise AcquisitionError(
                self.device, step, f"{sent!r} not taken within {timeout_s:g} s"
            ) from None
        except OSError as exc:
            raise AcquisitionError(
                self.device, step, f"sending {sent!r}: {exc.strerror or exc}"
            ) from None

    def read_line(self, timeout_s: float, *, step: str, skip: Container[str] = ()) -> str | None:
        """The next line received within ``timeout_s`` seconds (0: only what has arrived), stripped,
        that is not empty and not in ``skip`` (commands echoed back); None if none came."""
        deadline = time.monotonic() + timeout_s
        while True:
            while b"\n" not in self._pending:
                left = deadline - time.monotonic()
                try:
                    if left <= 0:
                        self._sock.setblocking(False)
                    else:
                        self._sock.settimeout(left)
                    chunk = self._sock.recv(4096)
                except (BlockingIOError, TimeoutError):
                    return None
                except OSError as exc:
                    raise AcquisitionError(
                        self.device, step, f"reading the answer: {exc.strerror or exc}"
                    ) from None
                if not chunk:
                    raise AcquisitionError(self.device, step, "the device closed the connection")
                self._pending += chunk
            raw, self._pending = self._pending.split(b"\n", 1)
            line = raw.decode(errors="replace").strip()
            if line and line not in skip:
                return line

    def close(self) -> None:
        """Close the connection (never raises)."""
        self._sock.close()
