"""Light controllers: what switches the photometric lights (and a flood or pattern light) on and off.

One small interface, :class:`LightController`, and two drivers: ``tcp`` (one text line per
command over a TCP connection) and ``simulated`` (no hardware: the simulated cameras read which
lights are on from it). A serial or fieldbus controller is another subclass implementing
:meth:`LightController._send`, :meth:`LightController.describe` and :meth:`LightController._disconnect`.

The tcp protocol (docs/acquisition.md): the configuration's ``on``/``off`` templates with
``{index}`` (0-based light index) replaced, and its ``stereo_on``/``stereo_off`` lines, each sent
as one line ending in ``\\n``. A controller may answer each command with a line: if it answers the
first command within :data:`FIRST_REPLY_S`, every command must be answered within the command
timeout by a line beginning with ``OK`` or ``ACK`` (any other line is a refusal); a controller that
does not answer the first one is taken to be silent, and whatever it sends later is still read and
checked before each command.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import Any, Literal

from ..formats import AcquisitionError, CellLights
from .tcp import ACCEPTED, CONNECT_TIMEOUT_S, LineConnection

#: Seconds a controller that answers has to answer each command.
COMMAND_TIMEOUT_S = 2.0
#: Seconds to wait for an answer to the first command before taking the controller to be silent.
FIRST_REPLY_S = 0.5

Command = Literal["on", "off", "stereo_on", "stereo_off"]


class LightController(ABC):
    """Switches N photometric lights, and a stereo (flood or pattern) light when there is one.

    Tracks which lights it has switched on (:attr:`lit`, :attr:`stereo_lit`); :meth:`close`
    switches off whatever is still on (best effort), then disconnects. Every failure is an
    :class:`~pipeline.formats.AcquisitionError` naming :attr:`device` and the step.

    Parameters
    ----------
    n_lights : int
        Number of photometric lights.
    has_stereo_light : bool
        The configuration names ``stereo_on``/``stereo_off`` commands.
    """

    #: How error messages name the controller.
    device: str = "light controller"

    def __init__(self, n_lights: int, has_stereo_light: bool) -> None:
        self.n_lights = n_lights
        self.has_stereo_light = has_stereo_light
        self._lit: set[int] = set()
        self._stereo_lit = False

    @property
    def lit(self) -> frozenset[int]:
        """Indices of the photometric lights switched on."""
        return frozenset(self._lit)

    @property
    def stereo_lit(self) -> bool:
        """The stereo light is switched on."""
        return self._stereo_lit

    def on(self, index: int, *, step: str) -> None:
        """Switch photometric light ``index`` on; ``step`` names the step in an error."""
        self._check_index(index, step)
        self._lit.add(index)  # before sending: a command that failed may still have switched it on
        self._send("on", index, step=step)

    def off(self, index: int, *, step: str) -> None:
        """Switch photometric light ``index`` off."""
        self._check_index(index, step)
        self._send("off", index, step=step)
        self._lit.discard(index)

    def stereo_on(self, *, step: str) -> None:
        """Switch the stereo light on (the configuration's ``stereo_on``)."""
        self._check_stereo(step)
        self._stereo_lit = True
        self._send("stereo_on", None, step=step)

    def stereo_off(self, *, step: str) -> None:
        """Switch the stereo light off."""
        self._check_stereo(step)
        self._send("stereo_off", None, step=step)
        self._stereo_lit = False

    def close(self) -> None:
        """Switch off what is still on (errors ignored: the controller may be what failed), then disconnect."""
        try:
            for index in sorted(self._lit):
                self.off(index, step=f"switching light {index} off after a failure")
            if self._stereo_lit:
                self.stereo_off(step="switching the stereo light off after a failure")
        except AcquisitionError:
            pass
        finally:
            self._disconnect()

    @abstractmethod
    def describe(self) -> dict[str, Any]:
        """The controller for the acquisition record: ``{"driver": ..., ...}`` (JSON-ready)."""

    @abstractmethod
    def _send(self, command: Command, index: int | None, *, step: str) -> None:
        """Send one command (``index`` for ``on``/``off``); raise :class:`AcquisitionError` on failure."""

    @abstractmethod
    def _disconnect(self) -> None:
        """Release the connection (never raises)."""

    def _check_index(self, index: int, step: str) -> None:
        if not 0 <= index < self.n_lights:
            raise AcquisitionError(
                self.device, step, f"no light {index}: the cell has lights 0-{self.n_lights - 1}"
            )

    def _check_stereo(self, step: str) -> None:
        if not self.has_stereo_light:
            raise AcquisitionError(
                self.device, step, "the configuration names no stereo_on/stereo_off commands"
            )


class SimulatedLightController(LightController):
    """The demo cell's lights: no hardware, only the state the simulated cameras render."""

    device = "simulated light controller"

    def describe(self) -> dict[str, Any]:
        return {"driver": "simulated", "n_lights": self.n_lights}

    def _send(self, command: Command, index: int | None, *, step: str) -> None:
        return None

    def _disconnect(self) -> None:
        return None


class TcpLightController(LightController):
    """A controller that takes one text line per command over TCP (see the module docstring).

    Parameters
    ----------
    config : pipeline.formats.CellLights
        ``address`` (``HOST:PORT``), ``on``/``off`` templates, optional ``stereo_on``/``stereo_off``.
    n_lights : int
    connect_timeout_s, command_timeout_s, first_reply_s : float
        See :data:`CONNECT_TIMEOUT_S`, :data:`COMMAND_TIMEOUT_S`, :data:`FIRST_REPLY_S`.

    Raises
    ------
    AcquisitionError
        The controller cannot be reached (refused, unknown host, no answer within the timeout).
    """

    def __init__(
        self,
        config: CellLights,
        n_lights: int,
        *,
        connect_timeout_s: float = CONNECT_TIMEOUT_S,
        command_timeout_s: float = COMMAND_TIMEOUT_S,
        first_reply_s: float = FIRST_REPLY_S,
    ) -> None:
        super().__init__(n_lights, config.stereo_on is not None)
        address = config.address
        if address is None:  # impossible: CellLights requires it of a tcp controller
            raise ValueError("config.address: a tcp light controller needs HOST:PORT")
        self.address = address
        self.device = f"light controller {config.address}"
        self._templates: dict[Command, str | None] = {
            "on": config.on,
            "off": config.off,
            "stereo_on": config.stereo_on,
            "stereo_off": config.stereo_off,
        }
        self._command_timeout_s = command_timeout_s
        self._first_reply_s = first_reply_s
        self._replies: bool | None = None  # unknown until the first command
        self._sent: set[str] = set()  # commands sent: a line that repeats one is an echo
        self._connection = LineConnection(address, self.device, connect_timeout_s=connect_timeout_s)

    def describe(self) -> dict[str, Any]:
        return {
            "driver": "tcp",
            "address": self.address,
            "n_lights": self.n_lights,
            "replies": self._replies,
            "stereo_light": self.has_stereo_light,
        }

    def _send(self, command: Command, index: int | None, *, step: str) -> None:
        text = self._templates[command]
        if text is None:  # impossible: CellLights requires on/off, _check_stereo the stereo pair
            raise AcquisitionError(
                self.device, step, f"the configuration names no {command} command"
            )
        line = text.format(index=index) if index is not None else text
        sent = line.strip()
        while (late := self._answer(0.0, step)) is not None:  # late answers to earlier commands
            self._check_reply(late, None, step)
        self._connection.send(line, step=step, timeout_s=self._command_timeout_s)
        self._sent.add(sent)
        if self._replies is False:
            return
        wait = self._first_reply_s if self._replies is None else self._command_timeout_s
        reply = self._answer(wait, step)
        if reply is None:
            if self._replies is None:
                self._replies = False  # a silent controller
                return
            raise AcquisitionError(self.device, step, f"no answer to {sent!r} within {wait:g} s")
        self._replies = True
        self._check_reply(reply, sent, step)

    def _check_reply(self, reply: str, sent: str | None, step: str) -> None:
        """Accept a line beginning with ``OK``/``ACK``; anything else refuses ``sent`` (None: an earlier command)."""
        if not reply.split()[0].upper().startswith(ACCEPTED):
            what = repr(sent) if sent is not None else "an earlier command"
            raise AcquisitionError(self.device, step, f"refused {what}: answered {reply!r}")

    def _answer(self, timeout_s: float, step: str) -> str | None:
        """The next line received within ``timeout_s`` (0: only what has arrived) that is not empty and
        not a command echoed back; None if none."""
        return self._connection.read_line(timeout_s, step=step, skip=self._sent)

    def _disconnect(self) -> None:
        self._connection.close()


def open_light_controller(config: CellLights, n_lights: int) -> LightController:
    """The light controller a configuration names, connected.

    Parameters
    ----------
    config : pipeline.formats.CellLights
    n_lights : int
        Number of photometric lights (the configuration's lights, or its light calibration's).

    Raises
    ------
    AcquisitionError
        A tcp controller that cannot be reached.
    """
    if config.driver == "tcp":
        return TcpLightController(config, n_lights)
    return SimulatedLightController(n_lights, config.stereo_on is not None)
