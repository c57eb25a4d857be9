"""Request and response bodies of the REST API (pydantic)."""

from __future__ import annotations

from datetime import datetime
from typing import Annotated, Any, Generic, Literal, Self, TypeVar

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    SerializerFunctionWrapHandler,
    StringConstraints,
    ValidationInfo,
    field_validator,
    model_serializer,
    model_validator,
)

from app.limits.physical import (
    MAX_DENT_DEPTH_MM,
    MAX_DENT_RADIUS_MM,
    MAX_TOLERANCE_MM,
    RADIUS_MM,
    SIZE_MM,
    radius_reason,
)

# Re-exported: the plate id's rules belong with the schemas that use them.
from app.storage import PLATE_ID_MAX_LENGTH as PLATE_ID_MAX_LENGTH
from app.storage import PLATE_ID_REGEX as PLATE_ID_REGEX

T = TypeVar("T")


#: Request bodies: unknown keys refused, integers and booleans strict (``false`` is not 0, ``1``
#: is not true, ``"5"`` is not a number), finite numbers only (no NaN, no Infinity).
STRICT_BODY = ConfigDict(extra="forbid", strict=True, allow_inf_nan=False)

Status = Literal["queued", "running", "done", "error"]
#: An operator's name as typed at the cell: 1-80 printable characters, spaces around it dropped.
OperatorName = Annotated[
    str,
    StringConstraints(
        strip_whitespace=True, min_length=1, max_length=80, pattern=r"^[^\x00-\x1f\x7f]+$"
    ),
]
Verdict = Literal["pass", "fail"]


class ErrorOut(BaseModel):
    """Every error answer: a message, and the request field it is about (or null)."""

    detail: str
    field: str | None = None


class Page(BaseModel, Generic[T]):
    """One page of a list, newest first."""

    items: list[T]
    total: int
    limit: int
    offset: int


# ------------------------------------------------------------------ forming (issue 14)

#: A machine id: the same characters as a plate id.
MACHINE_ID_REGEX = PLATE_ID_REGEX
MACHINE_ID_MAX_LENGTH = 64


class MachineIn(BaseModel):
    """A three-roll pyramid bender's geometry (mm); ``PUT /machines/{machine_id}``."""

    model_config = STRICT_BODY

    kind: Literal["three-roll-pyramid"]
    bottom_roll_spacing_mm: float = Field(
        gt=0, le=SIZE_MM[1], description="between the bottom rolls' axes"
    )
    bottom_roll_diameter_mm: float = Field(gt=0, le=SIZE_MM[1])
    top_roll_diameter_mm: float = Field(gt=0, le=SIZE_MM[1])


class MachineOut(MachineIn):
    model_config = ConfigDict(extra="forbid")

    id: str
    created_at: datetime
    updated_at: datetime


class ProcessIn(BaseModel):
    """The forming pass that produced the inspected shape: a roll-bending pass on a known machine."""

    model_config = STRICT_BODY

    method: Literal["roll-bending"]
    machine_id: str = Field(
        min_length=1, max_length=MACHINE_ID_MAX_LENGTH, pattern=MACHINE_ID_REGEX
    )
    flipped: bool = Field(
        default=False,
        description="a reverse pass: the plate turned over and rolled to open it (stored only when true)",
    )
    top_roll_displacement_mm: float = Field(
        ge=-SIZE_MM[1],
        le=SIZE_MM[1],
        description="down from touching the flat plate; a flipped pass may be negative (the top roll "
        "stops above that point, pressing the flipped plate's arch flatter)",
    )

    @field_validator("top_roll_displacement_mm")
    @classmethod
    def _positive_unless_flipped(cls, value: float, info: ValidationInfo) -> float:
        if value <= 0 and not info.data.get("flipped", False):
            raise ValueError(
                "expected more than 0 mm for a bending pass (only a flipped pass may be <= 0)"
            )
        return value

    @model_serializer(mode="wrap")
    def _without_default_flip(self, handler: SerializerFunctionWrapHandler) -> dict[str, Any]:
        """A bending pass is stored as before: ``flipped`` only when true."""
        data: dict[str, Any] = handler(self)
        if not self.flipped:
            data.pop("flipped", None)
        return data


class AdviceOut(BaseModel):
    """The next forming step of a plate (see docs/forming.md, "Actions and aim")."""

    action: Literal["bend", "done", "reverse"]
    machine_id: str
    top_roll_displacement_mm: float | None
    expected_radius_mm: float | None
    expected_radius_range_mm: tuple[float | None, float | None] | None = Field(
        description="central 95 % interval; null for an open end (the plate may stay flat)"
    )
    basis: dict[str, Any]


# ------------------------------------------------------------------ inspections


class DentIn(BaseModel):
    """A dent pressed into the simulated plate (plate frame, mm; depth > 0 is away from the cameras)."""

    model_config = STRICT_BODY

    x_mm: float = Field(ge=-SIZE_MM[1] / 2, le=SIZE_MM[1] / 2)
    y_mm: float = Field(ge=-SIZE_MM[1] / 2, le=SIZE_MM[1] / 2)
    radius_mm: float = Field(gt=0, le=MAX_DENT_RADIUS_MM)
    depth_mm: float = Field(ge=-MAX_DENT_DEPTH_MM, le=MAX_DENT_DEPTH_MM)


class SimulatedInspectionIn(BaseModel):
    """The demo cell: a formed plate to render with the simulator and inspect.

    A plate with a current target is judged against it (``radius_mm`` is then the formed radius,
    and the target's tolerance applies); a plate without one against the rendered shape.
    """

    model_config = STRICT_BODY

    shape: Literal["plane", "cylinder", "sphere", "saddle"] = "cylinder"
    radius_mm: float | None = Field(
        default=5000.0,
        description="formed radius, mm (ignored for a plane)",
        json_schema_extra={"minimum": RADIUS_MM[0], "maximum": RADIUS_MM[1]},
    )
    convex: bool = True
    n_lights: int = Field(default=12, ge=3, le=64)
    noise: float = Field(
        default=0.004, ge=0, le=0.5, description="image noise, fraction of full scale"
    )
    bit_depth: Literal[8, 12, 16] = 16
    specular: float = Field(default=0.0, ge=0, le=1)
    lights: Literal["near-field", "distant"] = Field(
        default="near-field",
        description="LED point lights above the plate (a real cell), or distant lights",
    )
    light_height_mm: float = Field(
        default=2800.0, gt=100, le=20000, description="near-field: LEDs above the plate, mm"
    )
    light_elevation_deg: float = Field(
        default=30.0, gt=0, lt=80, description="lights' angle from the optical axis"
    )
    led_mu: float = Field(
        default=1.5, ge=0, le=20, description="near-field: LED beam profile exponent cos^mu"
    )
    light_manifest: Literal["exact", "nominal"] = Field(
        default="exact",
        description="near-field: the bundle gives positions (exact) or only directions (nominal)",
    )
    light_error_deg: float = Field(
        default=0.0, ge=0, lt=30, description="lights written off by this angle"
    )
    floor_mm: float | None = Field(
        default=None,
        gt=50,
        le=2000,
        description="a lit shop floor this far below the plate, on 3 rails (null: dark)",
    )
    cutout_radius_mm: float | None = Field(
        default=None,
        gt=10,
        le=1000,
        description="a round opening this big, 400 mm right and 300 mm up of the centre",
    )
    dents: list[DentIn] = Field(default_factory=list, max_length=32)
    seed: int = Field(default=0, ge=0, le=2**31 - 1)
    width: int = Field(default=1224, ge=64, le=4096, description="image width, px")
    height: int = Field(default=1024, ge=64, le=4096, description="image height, px")
    tolerance_mm: float = Field(
        default=2.0, gt=0, le=MAX_TOLERANCE_MM, description="used when the plate has no target"
    )
    process: ProcessIn | None = Field(
        default=None, description="the forming pass that produced this shape"
    )
    operator: OperatorName | None = Field(
        default=None, description="who starts the inspection (printed on the signed report)"
    )

    @field_validator("radius_mm")
    @classmethod
    def _hull_plate_radius(cls, v: float | None) -> float | None:
        if v is not None and not RADIUS_MM[0] <= v <= RADIUS_MM[1]:
            raise ValueError(radius_reason(v))
        return v

    @model_validator(mode="after")
    def _radius_needed(self) -> Self:
        if self.shape != "plane" and self.radius_mm is None:
            raise ValueError(f"radius_mm: expected a radius for a {self.shape} plate, got null")
        return self


class AcquireInspectionIn(BaseModel):
    """The cell photographs the plate, then the bundle is inspected."""

    model_config = STRICT_BODY

    target: dict[str, Any] | None = Field(
        default=None,
        description="a plate-target/1 object (plane, cylinder or sphere) that becomes the plate's target; "
        "default: the plate's current target",
    )
    process: ProcessIn | None = Field(
        default=None, description="the forming pass that produced this shape"
    )
    operator: OperatorName | None = Field(
        default=None, description="who starts the inspection (printed on the signed report)"
    )


class InspectionCreated(BaseModel):
    id: int
    status: Status


class DefectOut(BaseModel):
    """A region out of tolerance that fails the plate (largest first; ``id`` is its rank)."""

    id: int
    #: Centroid (x, y) in the target's own frame (that of target.json), mm; null if unknown.
    centroid_mm: list[float] | None
    #: Centroid (column, row) in the left image, px.
    centroid_px: list[float]
    area_mm2: float
    #: Signed deviation of largest magnitude, mm (positive: the plate stands proud of its target,
    #: towards the cameras).
    peak_mm: float
    #: Area-weighted mean deviation, mm; null for inspections measured before it was recorded.
    mean_mm: float | None


class StationOut(BaseModel):
    """One conveyor station of a plate measured at stations (details.json ``stations``, docs/stations.md)."""

    index: int
    #: The travel since station 0 the registration found, and the conveyor encoder's, mm.
    travel_mm: float
    travel_encoder_mm: float
    #: Where the station looked: the corners of its image frame at its plate's depth, in the target's
    #: frame (x, y), mm; null when details.json has none.
    outline_mm: list[list[float]] | None
    #: The overlap with the station before (none for station 0): texture matches the registration used,
    #: and the distance between the two registered surfaces there, RMS and max, mm.
    overlap_matches: int | None
    overlap_rms_mm: float | None
    overlap_max_mm: float | None


class PlateMapOut(BaseModel):
    """The deviation map in the target's own frame (x along its first side, y along its second, mm):
    the mean deviation in square cells, as the dashboard's map draws and reads it."""

    frame: Literal["target"]
    #: Corner of cell [0][0] (its smallest x and y), mm.
    x0_mm: float
    y0_mm: float
    cell_mm: float
    #: [x_min, x_max, y_min, y_max] of the grid, mm.
    extent_mm: list[float]
    nx: int
    ny: int
    tolerance_mm: float
    #: ny rows of nx cells, row 0 at the smallest y; mean signed deviation, mm; null where no data.
    deviation_mm: list[list[float | None]]
    defects: list[DefectOut]
    #: The conveyor stations of a plate measured at stations, each with its outline; empty for one view.
    stations: list[StationOut] = []


class InspectionOut(BaseModel):
    """An inspection: its job state and, once done, its ``plate-result/1`` document."""

    id: int
    plate_id: str
    status: Status
    progress: float
    stage: str | None
    result: dict[str, Any] | None
    error: str | None
    source: str
    verdict: Verdict | None
    #: The forming pass that produced the inspected shape (``process`` of the request), or null.
    process: dict[str, Any] | None
    #: Who started the inspection, or null.
    operator: str | None = None
    #: The light calibration the inspection is run with (see GET /light-calibrations/{id}), or null.
    light_calibration_id: int | None
    #: The cell an acquired inspection is photographed in (its configuration's cell_id), or null.
    cell_id: str | None
    created_at: datetime
    started_at: datetime | None
    finished_at: datetime | None
    #: artifact name -> URL, for the files present on disk.
    artifacts: dict[str, str]
    #: Once done: the regions that fail the plate, largest first (empty for a pass).
    defects: list[DefectOut] = []
    #: Once done: why the plate failed (empty for a pass).
    reasons: list[str] = []


class InspectionSummary(BaseModel):
    """One row of a plate's history."""

    id: int
    plate_id: str
    status: Status
    progress: float
    stage: str | None
    source: str
    verdict: Verdict | None
    radius_mm: float | None
    target_radius_mm: float | None
    radius_error_pct: float | None
    rms_mm: float | None
    max_abs_mm: float | None
    p95_mm: float | None
    within_tolerance_pct: float | None
    tolerance_mm: float | None
    process: dict[str, Any] | None
    operator: str | None = None
    error: str | None
    created_at: datetime
    started_at: datetime | None
    finished_at: datetime | None


# ------------------------------------------------------------------ plates, targets, calibrations


class TargetOut(BaseModel):
    id: int
    plate_id: str
    shape: str
    radius_mm: float | None
    tolerance_mm: float
    document: dict[str, Any]
    created_at: datetime


class PlateOut(BaseModel):
    id: str
    created_at: datetime
    inspection_count: int
    latest_verdict: Verdict | None
    latest_inspection: InspectionSummary | None
    target: TargetOut | None


class CalibrationOut(BaseModel):
    id: int
    image_size: tuple[int, int]
    rms_px: float | None
    document: dict[str, Any]
    created_at: datetime


class LightCalibrationOut(BaseModel):
    """A stored ``light-calibration/1``: the cell's point lights in image order (left-camera frame, mm)."""

    id: int
    file_name: str | None = Field(description="the uploaded file's name (null for a JSON body)")
    n_lights: int
    rms: float | None = Field(description="the calibration fit's residual, as the file gives it")
    document: dict[str, Any]
    created_at: datetime


class CameraHealth(BaseModel):
    """One camera of the cell: connected (opened and described), unreachable, error, or unknown (not checked yet)."""

    side: Literal["left", "right"]
    driver: str
    device_id: str | None
    state: Literal["connected", "unreachable", "error", "unknown"]
    vendor: str | None
    model: str | None
    serial: str | None
    detail: str | None = Field(
        description="why not connected, or where a state that is not of now comes from"
    )


class CellHealth(BaseModel):
    """The cell: whether acquisitions can be queued, and its cameras (checked at most every few seconds)."""

    ready: bool
    reason: str | None = Field(description="why acquisitions cannot be queued")
    cell_id: str | None
    demo: bool
    in_use: str | None = Field(
        description="who holds the cameras now (the cameras' state is then the last known)"
    )
    cameras: list[CameraHealth]


class Health(BaseModel):
    status: Literal["ok"]
    database: Literal["ok"]
    queued: int
    running: int
    cell: CellHealth | None = Field(
        description="null: no cell on this server (PLATE_INSPECT_CELL_CONFIG unset)"
    )
