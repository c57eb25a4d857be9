"""A stand-in inspection entry for the acquire job's tests: the real pipeline (``inspect``,
``warm_up``, ``EarlyStations``), except that station 1's reconstruction fails as the plate goes on to
station 2 (as a station whose plate the stereo pair does not find), in the consumer that imports it
(the consumer imports the entry by its module, this one)."""

from __future__ import annotations

from typing import Any

from pipeline import run
from pipeline.formats import CaptureError
from pipeline.run import EarlyStations, warm_up
from pipeline.stations import early

__all__ = ["EarlyStations", "inspect", "warm_up"]

_reconstruct_station = early.reconstruct_station


def _failing(ref: Any, *args: Any, **kwargs: Any) -> Any:
    if ref.station.index == 1:
        raise CaptureError(f"{ref.label}: stereo: no plate found")
    return _reconstruct_station(ref, *args, **kwargs)


early.reconstruct_station = _failing


def inspect(*args: Any, **kwargs: Any) -> run.InspectionResult:
    """:func:`pipeline.run.inspect`."""
    return run.inspect(*args, **kwargs)
