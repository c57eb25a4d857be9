"""Acquisition: the cell's cameras and lights take a capture bundle (``plate-inspect acquire``).

A ``cell-config/1`` file (docs/formats.md) names the cameras (GenICam through Aravis, or the
simulator), the light controller (tcp or simulated), the lights and the calibration;
:func:`acquire` runs the sequence and writes a ``plate-capture/1`` bundle. Setting up a real cell:
docs/acquisition.md.
"""

from ..formats import AcquisitionError
from .acquire import acquire, auto_exposure, last_frame_lag_s
from .cameras import Camera, Frame, SimulatedCamera, SimulatedCell, open_camera
from .config import CellConfig, load_cell_config
from .demo import write_demo_cell
from .lights import (
    LightController,
    SimulatedLightController,
    TcpLightController,
    open_light_controller,
)

__all__ = [
    "AcquisitionError",
    "Camera",
    "CellConfig",
    "Frame",
    "LightController",
    "SimulatedCamera",
    "SimulatedCell",
    "SimulatedLightController",
    "TcpLightController",
    "acquire",
    "auto_exposure",
    "last_frame_lag_s",
    "load_cell_config",
    "open_camera",
    "open_light_controller",
    "write_demo_cell",
]
