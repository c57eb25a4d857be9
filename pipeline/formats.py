"""The JSON file formats (docs/formats.md) as pydantic models.

Unknown keys are an error, missing required keys are an error. A format
change is a new format version, never a silent edit. Reading files (and
turning validation failures into :class:`InputError` naming the file and the
field) lives in :mod:`pipeline.io`.
"""

from __future__ import annotations

import math
from typing import Annotated, Any, Final, Literal, Self

from pydantic import (
    AfterValidator,
    BaseModel,
    ConfigDict,
    Discriminator,
    Field,
    Tag,
    field_validator,
    model_validator,
)

CALIBRATION_FORMAT = "stereo-calibration/1"
CAPTURE_FORMAT = "plate-capture/1"
TARGET_FORMAT = "plate-target/1"
RESULT_FORMAT: Final = "plate-result/1"
LIGHT_CALIBRATION_FORMAT = "light-calibration/1"
CELL_CONFIG_FORMAT = "cell-config/1"

#: Tolerance on |l| - 1 for a light direction to count as a unit vector.
UNIT_TOLERANCE = 1e-3


class InputError(ValueError):
    """Bad input: names the file and the field that is wrong.

    ``str(err)`` is one line: ``"<file>: <field>: <reason>"``; the CLI prints
    it and exits 2, the service answers 422 with it.
    """

    def __init__(self, file: str, field: str, reason: str) -> None:
        self.file = str(file)
        self.field = field
        self.reason = reason
        where = f"{self.file}: {field}" if field else self.file
        super().__init__(f"{where}: {reason}")


class PipelineError(Exception):
    """Valid input that cannot be processed (a domain error, not a bad file)."""


class CalibrationError(PipelineError):
    """The calibration images cannot give a calibration (too few usable views, ...)."""


class CaptureError(PipelineError):
    """A well-formed capture that cannot be measured (no plate found, too few lit pixels, ...)."""


class AcquisitionError(Exception):
    """A device of the cell failed while acquiring: names the device and the step.

    ``str(err)`` is one line: ``"<device>: <step>: <reason>"`` (``"left camera 192.168.10.11:
    photometric image 3: no frame within 2.0 s"``); the CLI prints it and exits 4.
    """

    def __init__(self, device: str, step: str, reason: str) -> None:
        self.device = device
        self.step = step
        self.reason = reason
        super().__init__(f"{device}: {step}: {reason}")


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


Vec3 = Annotated[list[float], Field(min_length=3, max_length=3)]
Mat3 = Annotated[list[Vec3], Field(min_length=3, max_length=3)]


def _finite(values: float | list[float] | list[list[float]] | None) -> bool:
    if isinstance(values, (list, tuple)):
        return all(_finite(v) for v in values)
    return values is None or math.isfinite(values)


# --------------------------------------------------------------------------- calibration


class CameraIntrinsics(_Strict):
    K: Mat3
    dist: Annotated[list[float], Field(min_length=5, max_length=5)]

    @field_validator("K", "dist")
    @classmethod
    def _check_finite(cls, v: list[float] | list[list[float]]) -> list[float] | list[list[float]]:
        if not _finite(v):
            raise ValueError("expected finite numbers")
        return v


class BoardSpec(_Strict):
    inner_corners: Annotated[list[int], Field(min_length=2, max_length=2)]
    square_mm: float = Field(gt=0)


class StereoCalibrationFile(_Strict):
    format: Literal["stereo-calibration/1"]
    image_size: Annotated[list[int], Field(min_length=2, max_length=2)]
    left: CameraIntrinsics
    right: CameraIntrinsics
    R: Mat3
    T: Vec3
    rms_px: float | None = None
    board: BoardSpec | None = None

    @field_validator("image_size")
    @classmethod
    def _positive_size(cls, v: list[int]) -> list[int]:
        if any(x <= 0 for x in v):
            raise ValueError(f"expected positive [width, height], got {v}")
        return v


# --------------------------------------------------------------------------- capture


def _unit_vector(
    v: list[float], what: str = "a unit vector", tolerance: float = UNIT_TOLERANCE
) -> list[float]:
    if not _finite(v):
        raise ValueError(f"expected finite numbers, got {v}")
    norm = math.sqrt(sum(x * x for x in v))
    if norm == 0:
        raise ValueError(f"expected {what}, got the zero vector")
    if abs(norm - 1.0) > tolerance:
        raise ValueError(f"expected {what}, got length {norm:.4f}")
    return v


class Light(_Strict):
    """One photometric light: distant (``direction``) or a point light (``position_mm``).

    A point light's irradiance on a surface point X is ``intensity * (1000 / |P - X|)^2 *
    max(0, cos theta_axis)^mu * max(0, n . (P - X) / |P - X|)`` (docs/formats.md, capture bundle).
    """

    direction: Vec3 | None = None
    position_mm: Vec3 | None = None
    axis: Vec3 | None = None
    mu: float | None = Field(default=None, ge=0)
    intensity: float = Field(default=1.0, gt=0)

    @field_validator("direction", "axis")
    @classmethod
    def _unit(cls, v: list[float] | None) -> list[float] | None:
        return None if v is None else _unit_vector(v)

    @field_validator("position_mm")
    @classmethod
    def _finite_position(cls, v: list[float] | None) -> list[float] | None:
        if v is not None and not _finite(v):
            raise ValueError(f"expected finite numbers, got {v}")
        return v

    @field_validator("intensity", "mu")
    @classmethod
    def _finite_intensity(cls, v: float | None) -> float | None:
        if v is not None and not math.isfinite(v):
            raise ValueError(f"expected a finite number, got {v}")
        return v

    @model_validator(mode="after")
    def _one_kind(self) -> Self:
        if (self.direction is None) == (self.position_mm is None):
            raise ValueError(
                "direction, position_mm: expected exactly one of them (a distant light or a point light), got "
                + ("both" if self.direction is not None else "neither")
            )
        if self.direction is not None and (self.axis is not None or self.mu is not None):
            raise ValueError(
                "axis, mu: only a point light (position_mm) has an LED axis and profile, got a distant light"
            )
        return self


class Photometric(_Strict):
    lights: list[Light]
    images: list[str]
    dark: str | None = None

    @model_validator(mode="after")
    def _counts(self) -> Self:
        if len(self.lights) < 3:
            raise ValueError(f"lights: expected at least 3 lights, got {len(self.lights)}")
        if len(self.lights) != len(self.images):
            raise ValueError(
                f"lights: expected {len(self.images)} lights to match {len(self.images)} images, got {len(self.lights)}"
            )
        return self


class StereoPair(_Strict):
    left: str
    right: str


class Station(_Strict):
    """Where a capture of a long plate was taken on the conveyor (optional; docs/stations.md).

    ``index``: the station's place in the sequence (0 first); ``travel_mm``: the conveyor's travel
    since station 0 as its encoder reads it, mm; ``direction``: the unit direction of the plate's
    motion in the left camera frame.
    """

    index: int = Field(ge=0, le=999, strict=True)
    travel_mm: float = Field(allow_inf_nan=False)
    direction: Vec3

    @field_validator("direction")
    @classmethod
    def _unit_direction(cls, v: list[float]) -> list[float]:
        return _unit_vector(v)


class CaptureFile(_Strict):
    format: Literal["plate-capture/1"]
    plate_id: str = Field(min_length=1)
    captured_at: str | None = None
    calibration: str | StereoCalibrationFile
    bit_depth: Literal[8, 10, 12, 14, 16]
    photometric: Photometric
    stereo: StereoPair | None = None
    working_distance_mm: float | None = Field(default=None, gt=0)
    acquisition: dict[str, Any] | None = None
    #: A station of a plate longer than the view (conveyor stations, docs/stations.md).
    station: Station | None = None


class CalibratedLight(_Strict):
    """A light measured by ``calibrate-lights``: always a point light."""

    position_mm: Vec3
    axis: Vec3
    mu: float = Field(ge=0)
    intensity: float = Field(gt=0)

    @field_validator("axis")
    @classmethod
    def _unit(cls, v: list[float]) -> list[float]:
        return _unit_vector(v)

    @field_validator("position_mm")
    @classmethod
    def _finite_position(cls, v: list[float]) -> list[float]:
        if not _finite(v):
            raise ValueError(f"expected finite numbers, got {v}")
        return v


class LightCalibrationFile(_Strict):
    format: Literal["light-calibration/1"]
    lights: Annotated[list[CalibratedLight], Field(min_length=3)]
    rms: float | None = Field(default=None, ge=0)


# --------------------------------------------------------------------------- cell configuration


class CellCamera(_Strict):
    """One camera of the cell: ``aravis`` (GenICam through Aravis) or ``simulated`` (the simulator)."""

    driver: Literal["aravis", "simulated"]
    device_id: str | None = Field(default=None, min_length=1)
    exposure_us: float | None = Field(default=None, gt=0)
    gain_db: float | None = None

    @field_validator("exposure_us", "gain_db")
    @classmethod
    def _finite(cls, v: float | None) -> float | None:
        if v is not None and not math.isfinite(v):
            raise ValueError(f"expected a finite number, got {v}")
        return v

    @model_validator(mode="after")
    def _device(self) -> Self:
        if self.driver == "aravis" and self.device_id is None:
            raise ValueError(
                "device_id: missing required key (an aravis camera is opened by its device id)"
            )
        return self


class CellCameras(_Strict):
    left: CellCamera
    right: CellCamera


def _one_line_command(v: str | None, *, per_light: bool) -> str | None:
    """A light controller command: one text line (a line break only at its end).

    Per-light commands are ``str.format`` templates whose only field is ``{index}``; the stereo
    light's commands are sent as they are.
    """
    if v is None:
        return None
    body = v.removesuffix("\n").removesuffix("\r")
    if not body.strip():
        raise ValueError(f"expected a command, got {v!r}")
    if "\n" in body or "\r" in body:
        raise ValueError(f"expected one line (a line break only at the end), got {v!r}")
    if not per_light:
        if "{index}" in body:
            raise ValueError(
                f"expected a command without {{index}} (it switches the stereo light), got {v!r}"
            )
        return v
    if "{index}" not in body:
        raise ValueError(f"expected {{index}} (the 0-based light index) in the command, got {v!r}")
    try:
        body.format(index=0)
    except (KeyError, IndexError, ValueError) as exc:
        raise ValueError(
            f"expected text whose only field is {{index}}, got {v!r} ({exc})"
        ) from None
    return v


def _host_port(v: str | None) -> str | None:
    """A device's ``HOST:PORT`` (a tcp light controller's or conveyor's)."""
    if v is None:
        return v
    host, sep, port = v.rpartition(":")
    if not sep or not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise ValueError(f"expected HOST:PORT (port 1-65535), got {v!r}")
    return v


#: Tolerance on |l| - 1 for a cell configuration's light axis or direction; it is then normalised.
CELL_UNIT_TOLERANCE = 0.01


class CellLight(Light):
    """A capture light as a cell configuration gives it: an axis or direction within
    :data:`CELL_UNIT_TOLERANCE` of unit length (``[-0.4, 0, 0.92]``, rounded by hand) is normalised."""

    @field_validator("direction", "axis")
    @classmethod
    def _unit(cls, v: list[float] | None) -> list[float] | None:
        if v is None:
            return None
        _unit_vector(v, tolerance=CELL_UNIT_TOLERANCE)
        norm = math.sqrt(sum(x * x for x in v))
        return [x / norm for x in v]


_LightList = Annotated[list[CellLight], Field(min_length=3)]


def _lights_kind(v: object) -> str:
    return "file" if isinstance(v, str) else "list"


class CellLights(_Strict):
    """The light controller and the photometric lights it switches (in image order)."""

    driver: Literal["tcp", "simulated"]
    address: str | None = None
    on: str | None = None
    off: str | None = None
    stereo_on: str | None = None
    stereo_off: str | None = None
    lights: Annotated[
        Annotated[_LightList, Tag("list")] | Annotated[str, Tag("file"), Field(min_length=1)],
        Discriminator(_lights_kind),
    ]

    @field_validator("address")
    @classmethod
    def _address(cls, v: str | None) -> str | None:
        return _host_port(v)

    @field_validator("on", "off")
    @classmethod
    def _per_light(cls, v: str | None) -> str | None:
        return _one_line_command(v, per_light=True)

    @field_validator("stereo_on", "stereo_off")
    @classmethod
    def _stereo(cls, v: str | None) -> str | None:
        return _one_line_command(v, per_light=False)

    @model_validator(mode="after")
    def _complete(self) -> Self:
        if self.driver == "tcp":
            for key in ("address", "on", "off"):
                if getattr(self, key) is None:
                    raise ValueError(
                        f"{key}: missing required key (a tcp light controller needs address, on and off)"
                    )
        if (self.stereo_on is None) != (self.stereo_off is None):
            missing = "stereo_off" if self.stereo_off is None else "stereo_on"
            raise ValueError(
                f"{missing}: missing required key (stereo_on and stereo_off go together)"
            )
        return self


class CellConveyor(_Strict):
    """The conveyor that carries a plate longer than the view under the head (docs/stations.md).

    ``driver`` ``tcp`` (``address`` ``HOST:PORT``; ``MOVE <mm>`` lines, docs/acquisition.md) or
    ``simulated``; ``direction``: the unit direction of the plate's motion in the left camera frame
    (within :data:`CELL_UNIT_TOLERANCE` of unit length, then normalised); ``stations_mm``: where the
    plate is photographed, its travel since station 0 (mm; 0 first, strictly increasing, at least 2);
    ``move_timeout_s``: how long one move may take before the conveyor counts as stalled.
    """

    driver: Literal["tcp", "simulated"]
    address: str | None = None
    direction: Vec3
    stations_mm: Annotated[list[float], Field(min_length=2, max_length=1000)]
    move_timeout_s: float = Field(default=60.0, gt=0, allow_inf_nan=False)

    @field_validator("address")
    @classmethod
    def _address(cls, v: str | None) -> str | None:
        return _host_port(v)

    @field_validator("direction")
    @classmethod
    def _unit(cls, v: list[float]) -> list[float]:
        _unit_vector(v, "a unit vector (the plate's motion)", tolerance=CELL_UNIT_TOLERANCE)
        norm = math.sqrt(sum(x * x for x in v))
        return [x / norm for x in v]

    @field_validator("stations_mm")
    @classmethod
    def _stations(cls, v: list[float]) -> list[float]:
        if not _finite(v):
            raise ValueError(f"expected finite positions (mm), got {v}")
        if v[0] != 0:
            raise ValueError(f"expected station 0 at 0 mm (travel since station 0), got {v[0]:g}")
        for k in range(1, len(v)):
            if not v[k] > v[k - 1]:
                raise ValueError(
                    f"expected strictly increasing positions, got {v[k]:g} mm at station {k} "
                    f"after {v[k - 1]:g} mm"
                )
        return v

    @model_validator(mode="after")
    def _complete(self) -> Self:
        if self.driver == "tcp" and self.address is None:
            raise ValueError("address: missing required key (a tcp conveyor needs HOST:PORT)")
        return self


class CellConfigFile(_Strict):
    format: Literal["cell-config/1"]
    cell_id: str = Field(min_length=1)
    cameras: CellCameras
    lights: CellLights
    calibration: str = Field(min_length=1)
    working_distance_mm: float = Field(gt=0)
    #: A conveyor that carries a long plate station by station (docs/stations.md); None: one view.
    conveyor: CellConveyor | None = None


# --------------------------------------------------------------------------- target


class PlaneShape(_Strict):
    type: Literal["plane"]


class CylinderShape(_Strict):
    type: Literal["cylinder"]
    radius_mm: float = Field(gt=0)


class SphereShape(_Strict):
    type: Literal["sphere"]
    radius_mm: float = Field(gt=0)


class MeshShape(_Strict):
    type: Literal["mesh"]
    file: str = Field(min_length=1)


TargetShape = Annotated[
    PlaneShape | CylinderShape | SphereShape | MeshShape, Field(discriminator="type")
]


class TargetMaterial(_Strict):
    """The plate's nominal material (optional; roll-bending advice needs it, see docs/forming.md)."""

    grade: str = Field(min_length=1, max_length=32)
    thickness_mm: float = Field(gt=0, allow_inf_nan=False)
    yield_mpa: float = Field(gt=0, allow_inf_nan=False)
    youngs_mpa: float = Field(default=206000.0, gt=0, allow_inf_nan=False)
    poisson: float = Field(default=0.3, ge=0, lt=0.5)

    @model_validator(mode="after")
    def _yield_below_modulus(self) -> Self:
        if self.yield_mpa >= self.youngs_mpa:
            raise ValueError(
                f"yield_mpa: expected less than youngs_mpa ({self.youngs_mpa:g}), got {self.yield_mpa:g}"
            )
        return self


def _printable(text: str) -> str:
    if not text.strip() or not text.isprintable():
        raise ValueError(f"expected printable text, not blank, got {text[:70]!r}")
    return text


#: A traceability string of a target (drawing number, revision, hull, block): 1-64 printable characters.
TraceText = Annotated[str, Field(min_length=1, max_length=64), AfterValidator(_printable)]


class TargetDrawing(_Strict):
    """The plate's drawing (optional traceability, printed on the report)."""

    number: TraceText
    revision: TraceText


class TargetFile(_Strict):
    format: Literal["plate-target/1"]
    shape: TargetShape
    size_mm: Annotated[list[float], Field(min_length=2, max_length=2)]
    tolerance_mm: float = Field(gt=0)
    material: TargetMaterial | None = None
    #: Optional traceability (printed on the report): the drawing, hull (ship) and block.
    drawing: TargetDrawing | None = None
    hull: TraceText | None = None
    block: TraceText | None = None

    @field_validator("size_mm")
    @classmethod
    def _positive(cls, v: list[float]) -> list[float]:
        if any(not math.isfinite(x) or x <= 0 for x in v):
            raise ValueError(f"expected two positive sizes in mm, got {v}")
        return v


# --------------------------------------------------------------------------- result


class DeviationStats(_Strict):
    rms: float
    max_abs: float
    p95: float


class ResultUncertainty(_Strict):
    """Expanded uncertainties (GUM, coverage factor ``k``) of the radius and the deviation, mm."""

    k: float = 2.0
    radius_mm: float | None
    deviation_mm: float


class ResultFile(_Strict):
    format: Literal["plate-result/1"] = RESULT_FORMAT
    plate_id: str
    radius_mm: float | None
    principal_radii_mm: Annotated[list[float | None], Field(min_length=2, max_length=2)]
    target_radius_mm: float | None
    radius_error_pct: float | None
    deviation_mm: DeviationStats | None
    tolerance_mm: float
    within_tolerance_pct: float | None
    verdict: Literal["pass", "fail", "error"]
    error: str | None = None
    warnings: list[str] | None = None
    uncertainty: ResultUncertainty | None = None
    timings_s: dict[str, float]
    artifacts: dict[str, str]
