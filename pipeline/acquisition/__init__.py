"""Acquisition: the cell's cameras and lights take a capture bundle (``plate-inspect acquire``).

A ``cell-config/1`` file (docs/formats.md) names the cameras (GenICam through Aravis, or the
simulator), the light controller (tcp or simulated), the lights, the calibration and optionally a
conveyor (tcp or simulated); :func:`acquire` runs the sequence and writes a ``plate-capture/1``
bundle, :func:`acquire_stations` carries a long plate station by station and writes one bundle per
station (docs/stations.md); :class:`StreamedFrames` folds each frame for the inspection that follows
as it is taken. Setting up a real cell: docs/acquisition.md.
"""

from ..formats import AcquisitionError
from .acquire import (
    acquire,
    add_after_last_frame,
    auto_exposure,
    last_frame_lag_s,
    last_frame_time,
)
from .cameras import Camera, Frame, SimulatedCamera, SimulatedCell, open_camera
from .config import CellConfig, load_cell_config
from .conveyor import Conveyor, SimulatedConveyor, TcpConveyor, open_conveyor
from .demo import write_demo_cell
from .lights import (
    LightController,
    SimulatedLightController,
    TcpLightController,
    open_light_controller,
)
from .stations import acquire_stations
from .streaming import StreamedFrames

__all__ = [
    "AcquisitionError",
    "Camera",
    "CellConfig",
    "Conveyor",
    "Frame",
    "LightController",
    "SimulatedCamera",
    "SimulatedCell",
    "SimulatedConveyor",
    "SimulatedLightController",
    "StreamedFrames",
    "TcpConveyor",
    "TcpLightController",
    "acquire",
    "acquire_stations",
    "add_after_last_frame",
    "auto_exposure",
    "last_frame_lag_s",
    "last_frame_time",
    "load_cell_config",
    "open_camera",
    "open_conveyor",
    "open_light_controller",
    "write_demo_cell",
]
