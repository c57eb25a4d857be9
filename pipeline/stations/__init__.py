"""A plate longer than the view, measured from its conveyor stations as one plate (docs/stations.md).

Modules, one job each:

- :mod:`~pipeline.stations.plan`: the stations' bundles checked as a set, in station order;
- :mod:`~pipeline.stations.register`: the stations registered to one another (texture-matched
  overlaps, one pose-graph least squares, the overlaps' residuals);
- :mod:`~pipeline.stations.mosaic`: the registered stations resampled onto one grid;
- :mod:`~pipeline.stations.inspect`: each station reconstructed, the whole plate judged
  (:func:`pipeline.run.inspect` calls it for several bundles);
- :mod:`~pipeline.stations.early`: the stations reconstructed as they arrive, during the acquisition.
"""

from .early import EarlyStations
from .inspect import (
    StationResult,
    StitchedPlate,
    measure_stations,
    reconstruct_station,
    stitched_details,
)
from .mosaic import Mosaic, build_mosaic
from .plan import MIN_OVERLAP, StationRef, plan_stations, station_ref, view_length_mm
from .register import (
    ENCODER_LIMIT_MM,
    StationPoses,
    StationView,
    register_stations,
)

__all__ = [
    "ENCODER_LIMIT_MM",
    "MIN_OVERLAP",
    "EarlyStations",
    "Mosaic",
    "StationPoses",
    "StationRef",
    "StationResult",
    "StationView",
    "StitchedPlate",
    "build_mosaic",
    "measure_stations",
    "plan_stations",
    "reconstruct_station",
    "register_stations",
    "station_ref",
    "stitched_details",
    "view_length_mm",
]
