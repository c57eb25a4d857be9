"""A stand-in inspection entry for the acquire job's tests: the real pipeline (``inspect``,
``warm_up``), whose ``EarlyStations`` loses station 1's ``capture.json`` from its own links of the
bundle (the bundle written for the inspection keeps it) as the plate goes on to station 2: that
station's reconstruction fails there, as a bundle that cannot be read. Importing it changes nothing
else (the tests' own process imports it too)."""

from __future__ import annotations

from pathlib import Path

from pipeline import run
from pipeline.run import warm_up
from pipeline.stations import StationResult

__all__ = ["EarlyStations", "inspect", "warm_up"]


class EarlyStations(run.EarlyStations):
    def _reconstruct(self, index: int, linked: Path, final: Path) -> StationResult | None:
        if index == 1:
            (linked / "capture.json").unlink()  # a link: the written bundle keeps its file
        return super()._reconstruct(index, linked, final)


def inspect(*args: object, **kwargs: object) -> run.InspectionResult:
    """:func:`pipeline.run.inspect`."""
    return run.inspect(*args, **kwargs)  # type: ignore[arg-type]
