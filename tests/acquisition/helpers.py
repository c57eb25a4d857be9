"""Helpers of the acquisition tests: the simulated cell's files and light controllers; the fixtures
are in conftest.py.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from pipeline.io import calibration_document
from pipeline.simulate import default_rig
from tests.acquisition.devices import LightServer

#: Image size of the test cells (the calibration's image_size), width x height.
WIDTH, HEIGHT = 612, 512


def ring_lights(n: int) -> list[dict]:
    """``n`` LEDs on a ring 1650 mm around the left camera, 210 mm in front of it, aimed inwards."""
    lights = []
    for k in range(n):
        phi = 2 * np.pi * k / n
        axis = np.array([-0.4 * np.cos(phi), -0.4 * np.sin(phi), 0.92])
        lights.append(
            {
                "position_mm": [1650 * np.cos(phi), 1650 * np.sin(phi), 210.0],
                "axis": [round(float(v), 2) for v in axis],
                "mu": 1.3,
                "intensity": 9.8,
            }
        )
    return lights


def write_cell(
    folder: Path,
    *,
    left: dict,
    right: dict,
    lights: dict,
    n_lights: int = 6,
    size: tuple[int, int] = (WIDTH, HEIGHT),
    **overrides,
) -> Path:
    """A ``cell-config/1`` file and its calibration in ``folder``; ``lights`` without its ``lights`` list."""
    folder.mkdir(parents=True, exist_ok=True)
    rig = default_rig(width=size[0], height=size[1])
    (folder / "calibration.json").write_text(json.dumps(calibration_document(rig)))
    doc = {
        "format": "cell-config/1",
        "cell_id": "cell-test",
        "cameras": {"left": left, "right": right},
        "lights": {**lights, "lights": ring_lights(n_lights)} if "lights" not in lights else lights,
        "calibration": "calibration.json",
        "working_distance_mm": 3000.0,
    }
    doc.update(overrides)
    path = folder / "cell.json"
    path.write_text(json.dumps(doc))
    return path


def tcp_lights(server: LightServer, **extra) -> dict:
    return {
        "driver": "tcp",
        "address": server.address,
        "on": "L{index} ON\n",
        "off": "L{index} OFF\n",
        **extra,
    }
