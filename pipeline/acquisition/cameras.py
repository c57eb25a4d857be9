"""Cameras of the cell: one interface, :class:`Camera`, for the ``aravis`` and ``simulated`` drivers.

A camera is set up once (pixel format, region, gain, exposure), started, and then takes frames
by :meth:`Camera.trigger` + :meth:`Camera.fetch`: triggering both cameras before fetching either
takes a stereo pair together (as close in time as software triggers allow). A camera that has no
software trigger takes each frame as a single-frame acquisition started by :meth:`Camera.trigger`.

The ``simulated`` driver is the demo cell: it renders the plate with the simulator
(:func:`pipeline.simulate.render_radiance`) under the lights its light controller has switched on,
through the same sequence as a real cell.
"""

from __future__ import annotations

import zlib
from abc import ABC, abstractmethod
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Any, Literal

import numpy as np

from pipeline.acquisition.conveyor import Conveyor, SimulatedConveyor
from pipeline.acquisition.lights import LightController
from pipeline.camera import StereoRig
from pipeline.formats import AcquisitionError, CellCamera
from pipeline.lights.model import Lights

if TYPE_CHECKING:
    from pipeline.simulate import PlateSpec

Side = Literal["left", "right"]

#: Pixel formats in order of preference and the bit depth each gives (unpacked: one 16-bit word
#: per pixel above 8 bits).
PIXEL_FORMATS = {"Mono16": 16, "Mono14": 14, "Mono12": 12, "Mono10": 10, "Mono8": 8}


@dataclass(frozen=True)
class Frame:
    """One image from a camera.

    Attributes
    ----------
    image : (H, W) uint8 or uint16
        Raw counts as the camera gave them.
    device_timestamp_ns : int or None
        The camera's own time stamp (its clock), None where the camera has none.
    frame_id : int or None
    """

    image: np.ndarray
    device_timestamp_ns: int | None
    frame_id: int | None


class Camera(ABC):
    """A camera of the cell. Every failure is an :class:`AcquisitionError` naming :attr:`device`.

    Parameters
    ----------
    side : {"left", "right"}
    config : pipeline.formats.CellCamera
    """

    def __init__(self, side: Side, config: CellCamera) -> None:
        self.side = side
        self.config = config
        self.device = f"{side} camera {config.device_id or config.driver}"

    @property
    @abstractmethod
    def can_trigger(self) -> bool:
        """The camera takes a frame on a software trigger (else: a single-frame acquisition per frame)."""

    @abstractmethod
    def sensor_size(self) -> tuple[int, int]:
        """``(width, height)`` of the whole sensor, px."""

    @abstractmethod
    def pixel_formats(self) -> list[str]:
        """The pixel formats the camera offers (GenICam names)."""

    @abstractmethod
    def configure(self, *, pixel_format: str, width: int, height: int) -> None:
        """Set the pixel format and a ``width`` x ``height`` region centred on the sensor."""

    @abstractmethod
    def exposure_bounds_us(self) -> tuple[float, float]:
        """``(min, max)`` exposure time, microseconds."""

    @abstractmethod
    def set_exposure(self, exposure_us: float, *, step: str) -> float:
        """Set the exposure time; returns the one the camera took (microseconds)."""

    @abstractmethod
    def gain_bounds_db(self) -> tuple[float, float] | None:
        """``(min, max)`` gain, dB; None when the camera has no gain control."""

    @abstractmethod
    def set_gain(self, gain_db: float) -> float:
        """Set the gain; returns the one the camera took (dB)."""

    @abstractmethod
    def start(self) -> None:
        """Get ready to take frames (buffers, acquisition started when the camera can be triggered)."""

    @abstractmethod
    def trigger(self, *, step: str) -> None:
        """Start exposing one frame; ``step`` names the step in an error."""

    @abstractmethod
    def fetch(self, *, step: str, timeout_s: float) -> Frame:
        """The frame the last :meth:`trigger` started; an error after ``timeout_s`` seconds."""

    @abstractmethod
    def describe(self) -> dict[str, Any]:
        """The camera for the acquisition record (JSON-ready): driver, device_id, vendor, model, serial,
        pixel_format, bit_depth, region ``[x, y, width, height]``, gain_db, trigger."""

    @abstractmethod
    def close(self) -> None:
        """Stop and release the camera (never raises)."""

    def grab(self, *, step: str, timeout_s: float) -> Frame:
        """Trigger and fetch one frame."""
        self.trigger(step=step)
        return self.fetch(step=step, timeout_s=timeout_s)


def choose_pixel_format(left: Camera, right: Camera) -> str:
    """The first of :data:`PIXEL_FORMATS` that both cameras offer (one bit depth for the bundle).

    Raises
    ------
    AcquisitionError
        No monochrome format common to both cameras.
    """
    offered = set(left.pixel_formats()) & set(right.pixel_formats())
    for name in PIXEL_FORMATS:
        if name in offered:
            return name
    raise AcquisitionError(
        f"{left.device} and {right.device}",
        "choosing the pixel format",
        f"no monochrome format both offer (expected one of {', '.join(PIXEL_FORMATS)}; left offers "
        f"{', '.join(left.pixel_formats())}, right {', '.join(right.pixel_formats())})",
    )


# --------------------------------------------------------------------------- simulated


#: Exposure (microseconds) at which the simulated cameras see what the simulator renders.
SIMULATED_NOMINAL_EXPOSURE_US = 10_000.0


def simulated_plate(
    working_distance_mm: float, stations_mm: Sequence[float] | None = None
) -> PlateSpec:
    """The plate of the simulated cell: the simulator's default plate at the working distance, made
    longer by the conveyor's last station position when there is one (so that every station sees as
    much plate as the one view does).

    Parameters
    ----------
    working_distance_mm : float
    stations_mm : sequence of float, optional
        The conveyor's station positions (0 first), mm.

    Returns
    -------
    pipeline.simulate.PlateSpec
    """
    from pipeline.simulate import PlateSpec

    plate = PlateSpec(distance_mm=working_distance_mm)
    if stations_mm is None:
        return plate
    width, length = plate.size_mm
    return replace(plate, size_mm=(width, length + float(stations_mm[-1])))


class SimulatedCell:
    """The demo cell's scene: the simulator's default plate at the working distance, its lights.

    Both simulated cameras render from one cell, under the lights its controller has switched on
    (the stereo light counts as all the lights). The radiance of each light is rendered once per
    camera and station, on its first frame there; a frame adds the sensor's dark level, noise and
    quantisation.

    With a conveyor, the plate is longer (:func:`simulated_plate`) and its middle lies under the
    head halfway along the stations; the cameras render it where the conveyor has carried it
    (:func:`pipeline.simulate.carried_pose`): a simulated conveyor's true travel and yaw, or another
    conveyor's encoder reading.

    Parameters
    ----------
    rig : StereoRig
    lights : pipeline.lights.model.Lights
        The configuration's lights (the ones written into the bundle).
    working_distance_mm : float
        The plate's centre lies this far along the left camera's axis.
    controller : LightController
        Which lights are on.
    plate_id : str
        Seeds the plate's texture and the noise (the same plate id renders the same plate).
    conveyor : Conveyor, optional
        Where the plate is.
    """

    def __init__(
        self,
        rig: StereoRig,
        lights: Lights,
        working_distance_mm: float,
        controller: LightController,
        plate_id: str,
        conveyor: Conveyor | None = None,
    ) -> None:
        from pipeline.simulate import CaptureSpec

        self.rig = rig
        self.lights = lights
        self.controller = controller
        self.conveyor = conveyor
        self.plate = simulated_plate(
            working_distance_mm, None if conveyor is None else conveyor.config.stations_mm
        )
        self.spec = CaptureSpec()
        self.seed = zlib.crc32(plate_id.encode())
        self._rng = np.random.default_rng(self.seed)
        self._radiance: dict[str, np.ndarray] = {}
        self._radiance_at: tuple[float, float] | None = None
        w, h = rig.image_size
        self._dark = {
            side: (
                self.spec.dark_level
                + 0.001 * np.random.default_rng([self.seed, k]).standard_normal((h, w))
            ).astype(np.float32)
            for k, side in enumerate(("left", "right"))
        }

    def station(self) -> tuple[float, float]:
        """``(travel_mm, yaw_deg)``: where the conveyor has carried the plate since station 0."""
        conveyor = self.conveyor
        if conveyor is None:
            return 0.0, 0.0
        if isinstance(conveyor, SimulatedConveyor):
            return conveyor.true_travel_mm, conveyor.yaw_deg
        readings = conveyor.readings_mm
        return (readings[-1] - readings[0] if readings else 0.0), 0.0

    def pose(self) -> np.ndarray | None:
        """``T_cam_plate`` (4, 4) of the plate where it is now; None: the simulator's own pose."""
        if self.conveyor is None:
            return None
        from pipeline.simulate import carried_pose

        travel_mm, yaw_deg = self.station()
        return carried_pose(
            self.plate,
            first_centre_y_mm=-0.5 * self.conveyor.config.stations_mm[-1],
            travel_mm=travel_mm,
            direction=self.conveyor.direction,
            yaw_deg=yaw_deg,
        )

    def radiance(self, side: Side) -> np.ndarray:
        """(N, H, W) float32: each light alone as camera ``side`` sees it at the nominal exposure."""
        if self.station() != self._radiance_at:  # the conveyor moved the plate
            self._radiance.clear()
            self._radiance_at = self.station()
        if side not in self._radiance:
            from pipeline.simulate import render_radiance

            self._radiance[side] = render_radiance(
                self.plate,
                self.rig,
                self.lights,
                side=side,
                capture=self.spec,
                seed=self.seed,
                pose=self.pose(),
            )
        return self._radiance[side]

    def render(
        self, side: Side, lit: frozenset[int], *, exposure_us: float, gain_db: float, bit_depth: int
    ) -> np.ndarray:
        """A frame of camera ``side`` with lights ``lit`` on: (H, W) uint8 (``bit_depth`` 8) or uint16."""
        radiance = self.radiance(side)
        signal = (
            radiance[sorted(lit)].sum(axis=0) if lit else np.zeros(radiance.shape[1:], np.float32)
        )
        scale = np.float32(exposure_us / SIMULATED_NOMINAL_EXPOSURE_US * 10 ** (gain_db / 20))
        noise = np.float32(self.spec.noise) * self._rng.standard_normal(signal.shape, np.float32)
        full = float(2**bit_depth - 1)
        counts = np.clip(np.rint((self._dark[side] + scale * signal + noise) * full), 0.0, full)
        frame: np.ndarray = counts.astype(np.uint8 if bit_depth == 8 else np.uint16)
        return frame


class SimulatedCamera(Camera):
    """A camera of the demo cell (driver ``simulated``): its sensor is the calibration's image size.

    Parameters
    ----------
    side : {"left", "right"}
    config : pipeline.formats.CellCamera
    cell : SimulatedCell
    """

    def __init__(self, side: Side, config: CellCamera, cell: SimulatedCell) -> None:
        super().__init__(side, config)
        self.cell = cell
        self._format = "Mono16"
        self._exposure_us = SIMULATED_NOMINAL_EXPOSURE_US
        self._gain_db = 0.0
        self._lit: frozenset[int] | None = None
        self._frames = 0

    @property
    def can_trigger(self) -> bool:
        return True

    def sensor_size(self) -> tuple[int, int]:
        return self.cell.rig.image_size

    def pixel_formats(self) -> list[str]:
        return ["Mono8", "Mono12", "Mono16"]

    def configure(self, *, pixel_format: str, width: int, height: int) -> None:
        self._format = pixel_format

    def exposure_bounds_us(self) -> tuple[float, float]:
        return 10.0, 1_000_000.0

    def set_exposure(self, exposure_us: float, *, step: str) -> float:
        lo, hi = self.exposure_bounds_us()
        self._exposure_us = float(np.clip(exposure_us, lo, hi))
        return self._exposure_us

    def gain_bounds_db(self) -> tuple[float, float] | None:
        return 0.0, 24.0

    def set_gain(self, gain_db: float) -> float:
        self._gain_db = float(gain_db)
        return self._gain_db

    def start(self) -> None:
        return None

    def trigger(self, *, step: str) -> None:
        controller = self.cell.controller
        self._lit = (
            frozenset(range(self.cell.lights.n)) if controller.stereo_lit else controller.lit
        )

    def fetch(self, *, step: str, timeout_s: float) -> Frame:
        if self._lit is None:
            raise AcquisitionError(self.device, step, "fetched a frame that was not triggered")
        image = self.cell.render(
            self.side,
            self._lit,
            exposure_us=self._exposure_us,
            gain_db=self._gain_db,
            bit_depth=PIXEL_FORMATS[self._format],
        )
        self._lit = None
        self._frames += 1
        return Frame(image=image, device_timestamp_ns=None, frame_id=self._frames)

    def describe(self) -> dict[str, Any]:
        w, h = self.cell.rig.image_size
        return {
            "driver": "simulated",
            "device_id": self.config.device_id,
            "vendor": "plate-inspect",
            "model": "simulated camera",
            "serial": f"SIM-{self.side.upper()}",
            "pixel_format": self._format,
            "bit_depth": PIXEL_FORMATS[self._format],
            "region": [0, 0, w, h],
            "gain_db": self._gain_db,
            "trigger": "software",
        }

    def close(self) -> None:
        return None


def open_camera(side: Side, config: CellCamera, *, cell: SimulatedCell | None) -> Camera:
    """Open the camera a configuration names.

    Parameters
    ----------
    side : {"left", "right"}
    config : pipeline.formats.CellCamera
    cell : SimulatedCell or None
        The scene of the ``simulated`` driver (required for it).

    Raises
    ------
    AcquisitionError
        The camera is not found or cannot be opened, or Aravis is not installed.
    """
    if config.driver == "simulated":
        if cell is None:
            raise ValueError("cell: a simulated camera needs the simulated cell")
        return SimulatedCamera(side, config, cell)
    from pipeline.acquisition.aravis import AravisCamera

    return AravisCamera(side, config)
