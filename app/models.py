"""Database models (SQLAlchemy 2, typed ``Mapped[...]``).

Plates are named by the yard (the MES's plate id). Targets, calibrations and light calibrations
are versioned: a new upload is a new row, the newest row is the current one. An inspection row is the source
of truth for its job: ``queued -> running -> done | error`` (:class:`JobStatus`).
"""

from __future__ import annotations

from datetime import UTC, datetime
from enum import StrEnum
from typing import Any

from sqlalchemy import (
    JSON,
    BigInteger,
    DateTime,
    Float,
    ForeignKey,
    Index,
    Integer,
    String,
    Text,
    TypeDecorator,
    UniqueConstraint,
)
from sqlalchemy.engine import Dialect
from sqlalchemy.orm import DeclarativeBase, Mapped, mapped_column, relationship
from sqlalchemy.types import TypeEngine


class JobStatus(StrEnum):
    """An inspection job's state: ``queued -> running -> done | error``.

    ``error``: the job could not measure the plate (a bad bundle, a device, a crash); its inputs are
    kept and ``error`` says why. It has no verdict: a verdict is the plate's (:class:`Verdict`).
    """

    QUEUED = "queued"
    RUNNING = "running"
    DONE = "done"
    ERROR = "error"


#: States of a job that will not change again (its folder is complete).
FINISHED = (JobStatus.DONE, JobStatus.ERROR)
#: States of a job still to run or running.
ACTIVE = (JobStatus.QUEUED, JobStatus.RUNNING)


class Verdict(StrEnum):
    """A measured plate's verdict (a done job's)."""

    PASS = "pass"
    FAIL = "fail"


#: Numeric row ids: 64-bit on PostgreSQL (the API takes ids up to 2^63 - 1; migration 0007),
#: SQLite's INTEGER (its rowid, 64-bit already).
RowId = Integer().with_variant(BigInteger(), "postgresql")


def utcnow() -> datetime:
    return datetime.now(UTC)


class UTCDateTime(TypeDecorator[datetime]):
    """A timezone-aware UTC datetime on every backend.

    PostgreSQL stores ``timestamp with time zone`` (migration 0007); SQLite has no such type and
    stores the naive UTC value. Reads are always aware, in UTC.
    """

    impl = DateTime
    cache_ok = True

    def load_dialect_impl(self, dialect: Dialect) -> TypeEngine[Any]:
        return dialect.type_descriptor(DateTime(timezone=dialect.name == "postgresql"))

    def process_bind_param(self, value: datetime | None, dialect: Dialect) -> datetime | None:
        if value is None:
            return None
        if value.tzinfo is None:
            raise ValueError(f"datetime: expected a timezone-aware value, got naive {value!r}")
        value = value.astimezone(UTC)
        return value if dialect.name == "postgresql" else value.replace(tzinfo=None)

    def process_result_value(self, value: datetime | None, dialect: Dialect) -> datetime | None:
        if value is None:
            return None
        return value.replace(tzinfo=UTC) if value.tzinfo is None else value.astimezone(UTC)


class Base(DeclarativeBase):
    type_annotation_map = {  # noqa: RUF012 (SQLAlchemy reads this class attribute)
        datetime: UTCDateTime(),
        dict[str, Any]: JSON,
    }


class Plate(Base):
    __tablename__ = "plates"

    id: Mapped[str] = mapped_column(String(64), primary_key=True)
    created_at: Mapped[datetime] = mapped_column(default=utcnow)

    targets: Mapped[list[Target]] = relationship(back_populates="plate", order_by="Target.id")
    inspections: Mapped[list[Inspection]] = relationship(
        back_populates="plate", order_by="Inspection.id"
    )


class Target(Base):
    """One version of a plate's CAD target (``plate-target/1``); files under the storage dir."""

    __tablename__ = "targets"

    id: Mapped[int] = mapped_column(RowId, primary_key=True)
    plate_id: Mapped[str] = mapped_column(ForeignKey("plates.id"), index=True)
    shape: Mapped[str] = mapped_column(String(16))
    radius_mm: Mapped[float | None] = mapped_column(Float)
    tolerance_mm: Mapped[float] = mapped_column(Float)
    document: Mapped[dict[str, Any]]
    #: target.json path, relative to the data dir.
    path: Mapped[str] = mapped_column(String(512))
    created_at: Mapped[datetime] = mapped_column(default=utcnow)

    plate: Mapped[Plate] = relationship(back_populates="targets")


class Calibration(Base):
    """One uploaded ``stereo-calibration/1``; the newest is the cell's current calibration."""

    __tablename__ = "calibrations"

    id: Mapped[int] = mapped_column(RowId, primary_key=True)
    image_width: Mapped[int] = mapped_column(Integer)
    image_height: Mapped[int] = mapped_column(Integer)
    rms_px: Mapped[float | None] = mapped_column(Float)
    document: Mapped[dict[str, Any]]
    path: Mapped[str] = mapped_column(String(512))
    created_at: Mapped[datetime] = mapped_column(default=utcnow)


class LightCalibration(Base):
    """One uploaded ``light-calibration/1`` (the cell's measured lights); the newest is the current one."""

    __tablename__ = "light_calibrations"

    id: Mapped[int] = mapped_column(RowId, primary_key=True)
    #: The uploaded file's name as the client sent it (None for a JSON body).
    file_name: Mapped[str | None] = mapped_column(String(255))
    n_lights: Mapped[int] = mapped_column(Integer)
    #: The fit's residual as the file gives it (None when it gives none).
    rms: Mapped[float | None] = mapped_column(Float)
    document: Mapped[dict[str, Any]]
    #: lights.json path, relative to the data dir.
    path: Mapped[str] = mapped_column(String(512))
    created_at: Mapped[datetime] = mapped_column(default=utcnow)


class Inspection(Base):
    """One inspection job and its summary result."""

    __tablename__ = "inspections"
    __table_args__ = (
        # A plate's history, newest first (GET /plates/{id}/inspections), and the queue in order.
        Index("ix_inspections_plate_id_id", "plate_id", "id"),
        Index("ix_inspections_status_queued_at", "status", "queued_at"),
    )

    id: Mapped[int] = mapped_column(RowId, primary_key=True)
    plate_id: Mapped[str] = mapped_column(ForeignKey("plates.id"), index=True)
    target_id: Mapped[int | None] = mapped_column(ForeignKey("targets.id"))
    #: The light calibration passed to the pipeline: the current one when an uploaded capture
    #: with nominal (direction-only) lights was submitted; None otherwise. Fixed at submission,
    #: so a re-run (or a job queued before a new upload) measures with the same lights.
    light_calibration_id: Mapped[int | None] = mapped_column(ForeignKey("light_calibrations.id"))
    #: "upload" (a bundle .zip), "simulated" (rendered by the job from ``simulation``) or
    #: "acquired" (photographed by the job with the cell's cameras and lights).
    source: Mapped[str] = mapped_column(String(16))
    simulation: Mapped[dict[str, Any] | None]
    #: The forming pass that produced the inspected shape (issue 14), e.g. ``{"method": "roll-bending",
    #: "machine_id": "R3-01", "top_roll_displacement_mm": 97.0}``; None when not given.
    process: Mapped[dict[str, Any] | None] = mapped_column(JSON(none_as_null=True))
    #: Who started the inspection (the name typed at the cell or sent by the MES); None when not given.
    operator: Mapped[str | None] = mapped_column(String(80))
    #: The cell (its configuration's ``cell_id``) an acquired inspection is photographed in; None otherwise.
    cell_id: Mapped[str | None] = mapped_column(String(64), index=True)

    status: Mapped[str] = mapped_column(String(16), default=JobStatus.QUEUED, index=True)
    progress: Mapped[float] = mapped_column(Float, default=0.0)
    stage: Mapped[str | None] = mapped_column(String(32))
    #: Runs started (claims), whatever their end.
    attempts: Mapped[int] = mapped_column(Integer, default=0)
    error: Mapped[str | None] = mapped_column(Text)
    #: When the job (last) entered the queue: jobs are claimed oldest first. A job queued again
    #: after its worker died goes to the back; one released by a graceful stop keeps its place.
    queued_at: Mapped[datetime] = mapped_column(default=utcnow, index=True)
    #: The consumer running the job (``host:pid:nonce``) and when its lease ends unless renewed;
    #: both set while ``running`` only (see :mod:`app.services.leases`).
    lease_owner: Mapped[str | None] = mapped_column(String(128))
    lease_expires_at: Mapped[datetime | None]
    #: Times a worker died (or lost its lease) while running this job; the second sets it aside.
    deaths: Mapped[int] = mapped_column(Integer, default=0)

    #: Input paths relative to the data dir: the bundle (.zip or folder) and the target.json used.
    capture_path: Mapped[str | None] = mapped_column(String(512))
    target_path: Mapped[str | None] = mapped_column(String(512))

    result: Mapped[dict[str, Any] | None]
    timings_s: Mapped[dict[str, Any] | None]
    radius_mm: Mapped[float | None] = mapped_column(Float)
    target_radius_mm: Mapped[float | None] = mapped_column(Float)
    radius_error_pct: Mapped[float | None] = mapped_column(Float)
    rms_mm: Mapped[float | None] = mapped_column(Float)
    max_abs_mm: Mapped[float | None] = mapped_column(Float)
    p95_mm: Mapped[float | None] = mapped_column(Float)
    within_tolerance_pct: Mapped[float | None] = mapped_column(Float)
    tolerance_mm: Mapped[float | None] = mapped_column(Float)
    verdict: Mapped[str | None] = mapped_column(String(8))

    created_at: Mapped[datetime] = mapped_column(default=utcnow, index=True)
    started_at: Mapped[datetime | None]
    finished_at: Mapped[datetime | None]

    plate: Mapped[Plate] = relationship(back_populates="inspections")
    target: Mapped[Target | None] = relationship()
    light_calibration: Mapped[LightCalibration | None] = relationship()


class Machine(Base):
    """A roll bender the forming advice knows (issue 14); ``PUT /machines/{id}`` replaces its geometry."""

    __tablename__ = "machines"

    id: Mapped[str] = mapped_column(String(64), primary_key=True)
    #: Only ``"three-roll-pyramid"`` (:data:`pipeline.forming.records.MACHINE_KIND`).
    kind: Mapped[str] = mapped_column(String(32))
    bottom_roll_spacing_mm: Mapped[float] = mapped_column(Float)
    bottom_roll_diameter_mm: Mapped[float] = mapped_column(Float)
    top_roll_diameter_mm: Mapped[float] = mapped_column(Float)
    created_at: Mapped[datetime] = mapped_column(default=utcnow)
    updated_at: Mapped[datetime] = mapped_column(default=utcnow)


class IdempotencyKey(Base):
    """The first answer to a write sent with an ``Idempotency-Key`` (per route and token)."""

    __tablename__ = "idempotency_keys"
    __table_args__ = (
        UniqueConstraint("key", "scope", "token_hash", name="uq_idempotency_key_scope_token"),
    )

    id: Mapped[int] = mapped_column(RowId, primary_key=True)
    key: Mapped[str] = mapped_column(String(255))
    #: "METHOD /path" of the request.
    scope: Mapped[str] = mapped_column(String(512))
    #: sha256 hex of the bearer token.
    token_hash: Mapped[str] = mapped_column(String(64))
    #: "pending" while the first request runs, then "done".
    state: Mapped[str] = mapped_column(String(8), default="pending")
    status_code: Mapped[int | None] = mapped_column(Integer)
    body: Mapped[dict[str, Any] | None]
    #: sha256 hex of the request's body as fields and contents
    #: (:func:`app.services.idempotency.fingerprint`); null for keys stored before 0010.
    request_sha256: Mapped[str | None] = mapped_column(String(64))
    created_at: Mapped[datetime] = mapped_column(default=utcnow)


class DashboardSession(Base):
    """A dashboard login: the browser holds a random session id, the server only its sha256.

    A session authorises writes until ``expires_at``, unless revoked (logout) first, and only
    while the API token it was opened with is still the server's (``token_hash``).
    """

    __tablename__ = "sessions"

    #: sha256 hex of the session id in the cookie (the id itself is never stored).
    id_hash: Mapped[str] = mapped_column(String(64), primary_key=True)
    #: sha256 hex of the API token the session was opened under (a new token ends it).
    token_hash: Mapped[str] = mapped_column(String(64))
    created_at: Mapped[datetime] = mapped_column(default=utcnow)
    expires_at: Mapped[datetime] = mapped_column(index=True)
    revoked_at: Mapped[datetime | None]
