"""The cell configuration (``cell-config/1``, docs/formats.md): read, checked and resolved.

Everything a configuration names is read and checked here, before any device is touched: the
calibration it names (relative to the configuration file), the photometric lights (inline, or a
``light-calibration/1`` file beside it), and the lights' positions against the calibrated head and
the working distance, as a capture bundle's would be.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

from pipeline.camera import StereoRig
from pipeline.formats import (
    CELL_CONFIG_FORMAT,
    CellCamera,
    CellConfigFile,
    CellConveyor,
    CellLights,
    InputError,
)
from pipeline.io import load_calibration, load_light_calibration, read_json
from pipeline.io.capture import _check_light_positions
from pipeline.io.validation import _validate
from pipeline.lights.model import Lights


@dataclass(frozen=True)
class CellConfig:
    """A checked ``cell-config/1`` with the files it names read.

    Attributes
    ----------
    path : Path
        The configuration file.
    cell_id : str
    left, right : pipeline.formats.CellCamera
        The cameras as configured (driver, device id, optional exposure and gain).
    light_controller : pipeline.formats.CellLights
        The light controller as configured (driver, address, command templates).
    lights : pipeline.lights.model.Lights
        The N photometric lights in image order (left-camera frame, mm).
    rig : StereoRig
        The calibration; images are taken at ``rig.image_size``.
    calibration_path : Path
    working_distance_mm : float
    conveyor : pipeline.formats.CellConveyor or None
        The conveyor that carries a long plate station by station (driver, address, unit
        ``direction``, ``stations_mm``); None: the cell photographs one view.
    """

    path: Path
    cell_id: str
    left: CellCamera
    right: CellCamera
    light_controller: CellLights
    lights: Lights
    rig: StereoRig
    calibration_path: Path
    working_distance_mm: float
    conveyor: CellConveyor | None = None

    @property
    def label(self) -> str:
        """How error messages name the configuration file."""
        return str(self.path)


def load_cell_config(path: str | os.PathLike[str]) -> CellConfig:
    """Read a ``cell-config/1`` file and the calibration and light calibration it names.

    Parameters
    ----------
    path : str or Path
        The configuration file; ``calibration`` and a ``lights.lights`` file name are relative to
        its folder.

    Returns
    -------
    CellConfig

    Raises
    ------
    InputError
        Naming the file and the field: an unreadable or malformed configuration (unknown or missing
        keys, a tcp controller without address or commands, a command that is not one line or lacks
        ``{index}``, fewer than 3 lights, a conveyor's direction that is not a unit vector or stations
        that do not start at 0 and increase), a missing or malformed calibration or light calibration,
        a light inside the camera head or behind the plate.
    """
    path = Path(path)
    label = str(path)
    doc = read_json(path, label=label)
    cfg = _validate(CellConfigFile, doc, label=label, expected_format=CELL_CONFIG_FORMAT)
    base = path.parent

    calibration_path = base / cfg.calibration
    if not calibration_path.is_file():
        raise InputError(label, "calibration", f"{cfg.calibration!r}: file not found in {base}")
    rig = load_calibration(calibration_path)

    if isinstance(cfg.lights.lights, str):
        light_file = base / cfg.lights.lights
        if not light_file.is_file():
            raise InputError(
                label, "lights.lights", f"{cfg.lights.lights!r}: file not found in {base}"
            )
        lights, _ = load_light_calibration(light_file)
        lights_label, lights_field = str(light_file), "lights"
    else:
        lights = Lights.from_documents(cfg.lights.lights)
        lights_label, lights_field = label, "lights.lights"
    try:
        _check_light_positions(lights, rig, cfg.working_distance_mm, label=lights_label)
    except InputError as err:  # the check names a capture's field
        raise InputError(
            lights_label, err.field.replace("photometric.lights", lights_field), err.reason
        ) from None

    return CellConfig(
        path=path,
        cell_id=cfg.cell_id,
        left=cfg.cameras.left,
        right=cfg.cameras.right,
        light_controller=cfg.lights,
        lights=lights,
        rig=rig,
        calibration_path=calibration_path,
        working_distance_mm=float(cfg.working_distance_mm),
        conveyor=cfg.conveyor,
    )
