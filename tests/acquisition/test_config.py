"""cell-config/1: every bad configuration named by file and field before any device is touched."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest

from pipeline.acquisition import load_cell_config
from pipeline.formats import InputError
from pipeline.io import light_calibration_document
from pipeline.lights.model import Lights
from tests.acquisition.helpers import HEIGHT, WIDTH, ring_lights, write_cell

ARAVIS = {"driver": "aravis", "device_id": "192.168.10.11"}
TCP = {
    "driver": "tcp",
    "address": "192.168.10.20:5000",
    "on": "L{index} ON\n",
    "off": "L{index} OFF\n",
}


def _config(tmp_path, **overrides):
    return write_cell(
        tmp_path / "cell",
        left=ARAVIS,
        right={**ARAVIS, "device_id": "Basler-22334455"},
        lights=TCP,
        **overrides,
    )


def _edit(path, mutate):
    doc = json.loads(path.read_text())
    mutate(doc)
    path.write_text(json.dumps(doc))
    return path


def test_the_formats_example_loads_with_its_axes_normalised(tmp_path):
    config = load_cell_config(_config(tmp_path))
    assert config.cell_id == "cell-test" and config.rig.image_size == (WIDTH, HEIGHT)
    assert config.lights.n == 6 and config.lights.is_point.all()
    np.testing.assert_allclose(
        np.linalg.norm(config.lights.axes, axis=1), 1.0
    )  # [-0.4, 0, 0.92] is 1.003 long
    assert config.light_controller.on == "L{index} ON\n" and config.left.exposure_us is None


def test_lights_from_a_light_calibration_file_beside_the_config(tmp_path):
    path = _config(tmp_path)
    lights = Lights.points(
        [[1000.0 * np.cos(a), 1000.0 * np.sin(a), 300.0] for a in (0, 2, 4)], [1.0, 1.1, 0.9]
    )
    (path.parent / "lights.json").write_text(json.dumps(light_calibration_document(lights, 0.01)))
    _edit(path, lambda d: d["lights"].__setitem__("lights", "lights.json"))
    config = load_cell_config(path)
    np.testing.assert_allclose(config.lights.intensity, [1.0, 1.1, 0.9])


@pytest.mark.parametrize(
    ("mutate", "field", "reason"),
    [
        (lambda d: d.__setitem__("exposure", 1), "exposure", "unknown key"),
        (lambda d: d.pop("working_distance_mm"), "working_distance_mm", "missing required key"),
        (
            lambda d: d["cameras"]["left"].pop("device_id"),
            "cameras.left.device_id",
            "missing required key",
        ),
        (
            lambda d: d["cameras"]["right"].__setitem__("driver", "gige"),
            "cameras.right.driver",
            "expected 'aravis' or 'simulated'",
        ),
        (
            lambda d: d["cameras"]["left"].__setitem__("exposure_us", -5),
            "cameras.left.exposure_us",
            "greater than 0",
        ),
        (lambda d: d["lights"].pop("address"), "lights.address", "missing required key"),
        (
            lambda d: d["lights"].__setitem__("address", "192.168.10.20"),
            "lights.address",
            "expected HOST:PORT",
        ),
        (lambda d: d["lights"].__setitem__("on", "ALL ON\n"), "lights.on", "expected {index}"),
        (
            lambda d: d["lights"].__setitem__("off", "L{index} OFF\nL{index} X\n"),
            "lights.off",
            "expected one line",
        ),
        (lambda d: d["lights"].__setitem__("on", "L{light} ON"), "lights.on", "expected {index}"),
        (
            lambda d: d["lights"].__setitem__("stereo_on", "FLOOD ON\n"),
            "lights.stereo_off",
            "missing required key",
        ),
        (
            lambda d: d["lights"]["lights"][3].__setitem__("axis", [0, 0, 2]),
            "lights.lights[3].axis",
            "expected a unit vector",
        ),
        (
            lambda d: d["lights"].__setitem__("lights", d["lights"]["lights"][:2]),
            "lights.lights",
            "at least 3",
        ),
        (
            lambda d: d["lights"]["lights"][1].__setitem__("position_mm", [30, 0, 0]),
            "lights.lights[1].position_mm",
            "inside the camera head",
        ),
        (
            lambda d: d["lights"]["lights"][0].__setitem__("position_mm", [0, 0, 3500]),
            "lights.lights[0].position_mm",
            "behind the plate",
        ),
        (lambda d: d.__setitem__("calibration", "elsewhere.json"), "calibration", "file not found"),
        (
            lambda d: d["lights"].__setitem__("lights", "lights.json"),
            "lights.lights",
            "file not found",
        ),
        (lambda d: d.__setitem__("format", "cell-config/2"), "format", "unknown format"),
    ],
)
def test_bad_configuration_names_file_and_field(tmp_path, mutate, field, reason):
    path = _edit(_config(tmp_path), mutate)
    with pytest.raises(
        InputError, match=re.escape(f"{path}: {field}: ") + ".*" + re.escape(reason)
    ):
        load_cell_config(path)


def test_bad_calibration_is_named_by_its_own_file(tmp_path):
    path = _config(tmp_path)
    (path.parent / "calibration.json").write_text("{}")
    with pytest.raises(
        InputError,
        match=re.escape(f"{path.parent / 'calibration.json'}: format: missing required key"),
    ):
        load_cell_config(path)


def test_simulated_drivers_need_no_device_id_or_address(tmp_path):
    path = write_cell(
        tmp_path / "cell",
        left={"driver": "simulated"},
        right={"driver": "simulated"},
        lights={"driver": "simulated", "lights": ring_lights(4)},
    )
    config = load_cell_config(path)
    assert (
        config.left.device_id is None
        and config.light_controller.address is None
        and config.lights.n == 4
    )


CONVEYOR = {
    "driver": "tcp",
    "address": "192.168.10.30:5001",
    "direction": [0.0, -0.9986, -0.0523],
    "stations_mm": [0, 2100, 4200],
}


def _conveyor(tmp_path, **changes):
    return _config(tmp_path, conveyor={**CONVEYOR, **changes})


def test_a_conveyor_is_read_with_its_direction_normalised(tmp_path):
    config = load_cell_config(_conveyor(tmp_path))
    assert config.conveyor is not None and config.conveyor.stations_mm == [0, 2100, 4200]
    assert np.linalg.norm(config.conveyor.direction) == pytest.approx(1.0, abs=1e-12)
    np.testing.assert_allclose(config.conveyor.direction, CONVEYOR["direction"], atol=1e-3)
    assert config.conveyor.move_timeout_s == 60.0
    assert load_cell_config(_config(tmp_path / "plain")).conveyor is None


@pytest.mark.parametrize(
    ("changes", "field", "reason"),
    [
        (
            {"direction": [0.0, -0.5, 0.0]},
            "direction",
            "expected a unit vector (the plate's motion), got length 0.5000",
        ),
        ({"direction": [0.0, 0.0, 0.0]}, "direction", "got the zero vector"),
        ({"direction": [0.0, -1.0]}, "direction", "at least 3 items"),
        ({"stations_mm": [100, 2100]}, "stations_mm", "expected station 0 at 0 mm"),
        (
            {"stations_mm": [0, 2100, 1900]},
            "stations_mm",
            "expected strictly increasing positions, got 1900 mm at station 2",
        ),
        ({"stations_mm": [0]}, "stations_mm", "at least 2 items"),
        ({"address": None}, "address", "missing required key (a tcp conveyor needs HOST:PORT)"),
        ({"address": "conveyor"}, "address", "expected HOST:PORT"),
        ({"driver": "serial"}, "driver", "expected 'tcp' or 'simulated'"),
        ({"move_timeout_s": 0}, "move_timeout_s", "greater than 0"),
        ({"speed": 3}, "speed", "unknown key"),
    ],
)
def test_bad_conveyor_names_file_and_field(tmp_path, changes, field, reason):
    path = _conveyor(tmp_path, **changes)
    with pytest.raises(
        InputError, match=re.escape(f"{path}: conveyor.{field}: ") + ".*" + re.escape(reason)
    ):
        load_cell_config(path)
