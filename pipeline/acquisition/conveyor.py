"""Conveyors: what carries a plate longer than the view under the head, station by station.

One small interface, :class:`Conveyor`, and two drivers: ``tcp`` (one text line per move over a TCP
connection) and ``simulated`` (no hardware: the simulated cameras render the plate where it has
carried it). Every failure is an :class:`~pipeline.formats.AcquisitionError` naming the conveyor
(``conveyor HOST:PORT``) and the step (the station and its position).

The tcp protocol (docs/acquisition.md): ``MOVE <mm>`` moves the plate by that many millimetres along
the travel (relative, positive along the configuration's ``direction``; ``MOVE 0.000`` only reads
the encoder), one line ending in ``\\n``. The controller answers when the plate is at rest with one
line ``OK <encoder_mm>`` (or ``ACK <encoder_mm>``): the encoder's reading of the plate's position, mm,
from the controller's own zero. Any other answer (``ERR blocked``) is a refusal; no answer within
the move timeout is a stalled conveyor. A command echoed back is skipped. Each move is commanded from
the last reading, so a station's error does not carry over to the next: station ``k`` is
``MOVE (reading_0 + stations_mm[k]) - reading_(k-1)``.
"""

from __future__ import annotations

import math
import zlib
from abc import ABC, abstractmethod
from typing import Any

import numpy as np

from ..formats import AcquisitionError, CellConveyor
from .tcp import ACCEPTED, CONNECT_TIMEOUT_S, LineConnection

#: The simulated conveyor's encoder reads the plate's position off by a uniform error within +- this, mm.
SIMULATED_ENCODER_ERROR_MM = 4.0
#: The simulated plate turns about its normal by a uniform yaw within +- this at each station (but
#: the first), degrees.
SIMULATED_YAW_DEG = 0.3
#: The simulated conveyor's random stream (with the plate's seed).
_STREAM = 7927


class Conveyor(ABC):
    """Moves the plate along the travel and reads the encoder.

    Parameters
    ----------
    config : pipeline.formats.CellConveyor
    """

    #: How error messages name the conveyor.
    device: str = "conveyor"

    def __init__(self, config: CellConveyor) -> None:
        self.config = config
        self.direction = np.asarray(config.direction, np.float64)
        self._readings: list[float] = []  # the encoder's reading after each move, mm

    @property
    def readings_mm(self) -> list[float]:
        """The encoder's reading after each move so far (mm, the controller's own zero)."""
        return list(self._readings)

    def go_to_station(self, index: int) -> float:
        """Carry the plate to station ``index`` (0 first, in order) and read the encoder.

        Station 0 is where the plate lies when the acquisition starts (a move of 0 mm reads the
        encoder there); station ``k`` is ``stations_mm[k]`` further along the travel.

        Returns
        -------
        float
            The encoder's travel since station 0, mm (0 at station 0).

        Raises
        ------
        AcquisitionError
            The conveyor refuses, stalls, is gone, or the plate is not where the move should have
            brought it: nearer another station's position than its own (the step names the station).
        """
        stations = self.config.stations_mm
        if index != len(self._readings) or index >= len(stations):
            raise ValueError(
                f"index: expected station {len(self._readings)} next, of {len(stations)}, got {index}"
            )
        target = stations[index]
        step = f"station {index} (moving to {target:g} mm)"
        delta = 0.0 if index == 0 else self._readings[0] + target - self._readings[-1]
        reading = self._move(delta, step=step)
        travel = 0.0 if index == 0 else reading - self._readings[0]
        self._readings.append(reading)
        gaps = np.diff(stations)
        half = 0.5 * float(min(gaps[max(index - 1, 0) : index + 1]))
        if abs(travel - target) > half:
            raise AcquisitionError(
                self.device,
                step,
                f"the encoder reads {travel:.1f} mm of travel after the move, more than half the "
                f"step between stations ({half:g} mm) from {target:g} mm: a blocked or slipping plate?",
            )
        return travel

    @abstractmethod
    def describe(self) -> dict[str, Any]:
        """The conveyor for the acquisition record: ``{"driver": ..., ...}`` (JSON-ready)."""

    @abstractmethod
    def _move(self, delta_mm: float, *, step: str) -> float:
        """Move by ``delta_mm`` along the travel; the encoder's reading at rest (mm)."""

    @abstractmethod
    def close(self) -> None:
        """Release the conveyor (never raises)."""


class SimulatedConveyor(Conveyor):
    """The demo cell's conveyor: the plate goes exactly where it is sent, the encoder reads that
    position off by up to :data:`SIMULATED_ENCODER_ERROR_MM`, and the plate yaws by up to
    :data:`SIMULATED_YAW_DEG` about its normal at each station but the first (a plate that shifts
    on the rollers). The errors are drawn from a stream seeded by the plate id: the same plate id
    gives the same readings.

    Parameters
    ----------
    config : pipeline.formats.CellConveyor
    plate_id : str
    """

    device = "simulated conveyor"

    def __init__(self, config: CellConveyor, plate_id: str) -> None:
        super().__init__(config)
        self._rng = np.random.default_rng([zlib.crc32(plate_id.encode()), _STREAM])
        #: The plate's true travel since station 0 (mm) and its yaw (deg): what the cell renders.
        self.true_travel_mm = 0.0
        self.yaw_deg = 0.0

    def describe(self) -> dict[str, Any]:
        return {
            "driver": "simulated",
            "encoder_error_mm": SIMULATED_ENCODER_ERROR_MM,
            "yaw_deg": SIMULATED_YAW_DEG,
        }

    def _move(self, delta_mm: float, *, step: str) -> float:
        if self._readings:  # the plate goes to the station's position, whatever the encoder read
            self.true_travel_mm = self.config.stations_mm[len(self._readings)]
            self.yaw_deg = float(self._rng.uniform(-SIMULATED_YAW_DEG, SIMULATED_YAW_DEG))
        error = float(self._rng.uniform(-SIMULATED_ENCODER_ERROR_MM, SIMULATED_ENCODER_ERROR_MM))
        reading0 = self._readings[0] if self._readings else 0.0
        return round(reading0 + self.true_travel_mm + error, 3)

    def close(self) -> None:
        return None


class TcpConveyor(Conveyor):
    """A conveyor controller that takes ``MOVE <mm>`` lines over TCP (see the module docstring).

    Parameters
    ----------
    config : pipeline.formats.CellConveyor
        ``address`` (``HOST:PORT``), ``move_timeout_s``.
    connect_timeout_s : float
        See :data:`~pipeline.acquisition.tcp.CONNECT_TIMEOUT_S`.

    Raises
    ------
    AcquisitionError
        The controller cannot be reached (refused, unknown host, no connection within the timeout).
    """

    def __init__(self, config: CellConveyor, *, connect_timeout_s: float = CONNECT_TIMEOUT_S):
        super().__init__(config)
        if config.address is None:  # impossible: CellConveyor requires it of a tcp conveyor
            raise ValueError("config.address: a tcp conveyor needs HOST:PORT")
        self.address = config.address
        self.device = f"conveyor {config.address}"
        self._connection = LineConnection(
            config.address, self.device, connect_timeout_s=connect_timeout_s
        )
        self._last_sent = ""

    def describe(self) -> dict[str, Any]:
        return {
            "driver": "tcp",
            "address": self.address,
            "move_timeout_s": self.config.move_timeout_s,
        }

    def _move(self, delta_mm: float, *, step: str) -> float:
        sent = f"MOVE {delta_mm:.3f}"
        timeout_s = self.config.move_timeout_s
        # every move is answered before the next: a line now was not asked for (but a late echo of
        # the move before, which the light controller's driver skips too)
        late = self._connection.read_line(0.0, step=step, skip=(self._last_sent,))
        if late is not None:
            raise AcquisitionError(self.device, step, f"unexpected line {late!r} before {sent!r}")
        self._connection.send(sent, step=step, timeout_s=timeout_s)
        self._last_sent = sent
        reply = self._connection.read_line(timeout_s, step=step, skip=(sent,))
        if reply is None:
            raise AcquisitionError(
                self.device, step, f"no answer to {sent!r} within {timeout_s:g} s"
            )
        words = reply.split()
        if not words[0].upper().startswith(ACCEPTED):
            raise AcquisitionError(self.device, step, f"refused {sent!r}: answered {reply!r}")
        try:
            reading = float(words[1]) if len(words) == 2 else math.nan
        except ValueError:
            reading = math.nan
        if not math.isfinite(reading):
            raise AcquisitionError(
                self.device,
                step,
                f"answered {reply!r} to {sent!r}: expected 'OK <encoder_mm>' (one finite number)",
            )
        return reading

    def close(self) -> None:
        self._connection.close()


def open_conveyor(config: CellConveyor, *, plate_id: str) -> Conveyor:
    """The conveyor a configuration names, connected.

    Parameters
    ----------
    config : pipeline.formats.CellConveyor
    plate_id : str
        Seeds a simulated conveyor's errors.

    Raises
    ------
    AcquisitionError
        A tcp conveyor that cannot be reached.
    """
    if config.driver == "tcp":
        return TcpConveyor(config)
    return SimulatedConveyor(config, plate_id)
