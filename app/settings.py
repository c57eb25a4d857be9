"""The service's settings: one pydantic-settings class, environment prefix ``PLATE_INSPECT_``.

``PLATE_INSPECT_DATA_DIR``, ``PLATE_INSPECT_DATABASE_URL``, ``PLATE_INSPECT_API_TOKEN``,
``PLATE_INSPECT_MAX_UPLOAD_MB``, ``PLATE_INSPECT_DEMO``, ``PLATE_INSPECT_PROGRESS_INTERVAL_S``,
``PLATE_INSPECT_INSPECT_ENTRY``, ``PLATE_INSPECT_VIEWER_IDLE_S``, ``PLATE_INSPECT_VIEWER_MAX_SERVERS``,
``PLATE_INSPECT_VIEWER_MAX_SOCKETS_PER_CLIENT``, ``PLATE_INSPECT_VIEWER_RESERVED_SERVERS``,
``PLATE_INSPECT_SESSION_HOURS``, ``PLATE_INSPECT_LOGIN_FREE_FAILURES``, ``PLATE_INSPECT_LOGIN_WINDOW_S``,
``PLATE_INSPECT_LOGIN_MAX_DELAY_S``; request and queue limits: ``PLATE_INSPECT_MAX_IMAGE_PIXELS``, ``PLATE_INSPECT_MAX_LIGHTS``,
``PLATE_INSPECT_MAX_SIMULATED_PIXELS``, ``PLATE_INSPECT_MAX_QUEUED_PER_PLATE``, ``PLATE_INSPECT_MAX_QUEUED``;
job consumer: ``PLATE_INSPECT_WORKER_MEMORY_MB``, ``PLATE_INSPECT_JOB_LEASE_S``; a yard:
``PLATE_INSPECT_QUEUE_URL``; the cell:
``PLATE_INSPECT_CELL_CONFIG``; the report: ``PLATE_INSPECT_YARD``.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

from pydantic import Field, ImportString, SecretStr, field_validator, model_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

#: Environment variable prefix of every setting.
ENV_PREFIX = "PLATE_INSPECT_"
#: Default job lease on the embedded SQLite queue, s.
EMBEDDED_JOB_LEASE_S = 60.0
#: Default job lease on a shared (Redis) queue, s: a dead worker's job is queued again within
#: about this plus the reclaim interval (a quarter of it), well under a minute.
YARD_JOB_LEASE_S = 15.0


#: The pipeline's entry a job calls: ``inspect(capture, target, *, out_dir, progress,
#: light_calibration)``, answering a result whose ``document`` is the plate-result/1 object.
InspectFunction = Callable[..., Any]


def pipeline_inspect() -> InspectFunction:
    """The service's handover to the pipeline: :func:`pipeline.run.inspect`.

    Imported when settings are made without another entry (its module loads the pipeline, which
    the ``plate-inspect`` commands that only register ``serve`` never need).
    """
    from pipeline.run import inspect

    return inspect


def entry_name(function: InspectFunction) -> str:
    """``module:function`` naming ``function`` for another process (:meth:`Settings.to_env`)."""
    return f"{function.__module__}:{function.__qualname__}"


class Settings(BaseSettings):
    """Configuration of the web process and the job consumer (both read the same environment).

    Attributes
    ----------
    data_dir : Path
        Root of everything stored on disk: the SQLite database (by default), the huey queue,
        uploads and artifacts (layout in :mod:`app.storage`).
    database_url : str or None
        SQLAlchemy URL; None means ``sqlite:///<data_dir>/plate_inspect.db``. A yard's central
        database: ``postgresql+psycopg://user:password@host:5432/name`` (the ``yard`` extra).
    queue_url : str or None
        The job queue: None is the embedded SQLite queue under ``data_dir`` (one consumer per data
        dir); ``redis://host:port/db`` is huey's Redis storage, shared by any number of workers.
    api_token : SecretStr or None
        Bearer token required by every write. Without one the server refuses to start unless
        ``demo`` is set, in which case a random token is generated and printed at start.
    max_upload_mb : float
        Largest request body accepted, in MiB (413 beyond it).
    demo : bool
        Demo cell: a generated token, and dashboard pages get a write session without a login.
    progress_interval_s : float
        Shortest interval between two progress writes of a running job to the database, s.
    inspect_entry : callable
        The function a job calls to inspect (:data:`InspectFunction`): :func:`pipeline.run.inspect`
        by default. From the environment (and to the consumer process, :meth:`to_env`) it is named
        ``module:function`` and imported when the settings are made; tests point it at a test
        double to control timing.
    viewer_idle_s : float
        A 3D view's viser server stops this long after its last browser left, s.
    viewer_max_servers : int
        Most 3D views (one viser server each, on loopback) running at once.
    viewer_max_sockets_per_client : int
        Most 3D-view websockets one client address without a dashboard session holds at once.
    viewer_reserved_servers : int
        3D-view servers kept for the operator: clients with a valid dashboard session, or on
        loopback (the cell's own screen). Other clients start servers only while fewer than
        ``viewer_max_servers - viewer_reserved_servers`` have a browser (at most all of them).
    session_hours : float
        Lifetime of a dashboard session from its login, h (a shift by default).
    login_free_failures : int
        Wrong tokens one client address may send within ``login_window_s`` before its token
        checks are spaced out (growing delay, then 429 with ``Retry-After`` for a wrong one).
    login_window_s : float
        Failed token checks older than this are forgotten, s.
    login_max_delay_s : float
        Longest spacing between two token checks of a throttled address, s.
    max_image_pixels : int
        Most pixels (width x height) of one image of an uploaded capture, and of a stereo
        calibration's ``image_size`` (422 beyond it; read from the image headers).
    max_lights : int
        Most lights (= photometric images) of an uploaded capture, a light calibration or a
        simulated inspection (422 beyond it).
    max_simulated_pixels : int
        Most pixels (width x height) of a simulated inspection's images (422 beyond it); the
        simulator needs about 0.6 KB of memory per pixel.
    max_queued_per_plate : int
        Most inspections of one plate waiting in the queue (429 with Retry-After beyond it).
    max_queued : int
        Most inspections waiting in the queue in all (429 with Retry-After beyond it).
    worker_memory_mb : int
        Address space the job consumer may use, MiB (``RLIMIT_AS``, set when it starts; 0: no
        limit). A job that needs more ends ``failed`` ("out of memory: ..."); the consumer goes on.
        It counts virtual memory (libraries, thread stacks and heap arenas included), not only the
        resident pages. Measured on a simulated real capture (2448x2048, 38 point lights, 16-bit,
        41 images with the stereo pair and dark frame; 2-core machine): ``pipeline.run.inspect``
        peaks at 2931 MiB resident and 3872 MiB of address space; the consumer running the same
        capture as a simulated job (rendered, then inspected, in the one process) at 3505 MiB
        resident and 4596 MiB of address space. The default, 8192, is 1.8 times that; thread stacks
        and malloc arenas grow with the cores, so a machine with many cores may need more.
    job_lease_s : float
        A running job's lease, s: its consumer renews it every third of this; a job whose lease ran
        out (its consumer hung or died on another host) may be claimed again, which counts as a
        worker death (the second sets the job aside as failed). Default: 60 on the embedded queue
        (its one consumer is known dead when the next starts), :data:`YARD_JOB_LEASE_S` on a
        shared queue (the other workers reclaim a dead worker's job when its lease ran out).
    cell_config : Path or None
        The cell's ``cell-config/1`` file (docs/acquisition.md): acquisition jobs
        (``POST /plates/{plate_id}/inspections/acquire``) photograph the plate with the cameras and
        lights it names. None: in demo mode, the demo cell of simulated cameras and lights, written
        under the data dir (:mod:`app.services.cell`); otherwise the server acquires nothing.
    frame_timeout_s : float
        Seconds a camera's frame may take beyond its exposure before an acquisition job takes the
        camera to be gone and fails (``plate-inspect acquire --frame-timeout``; default 2, as there).
    yard : str or None
        The shipyard's name, printed in the header of every report page ("not recorded" when unset).
    """

    model_config = SettingsConfigDict(env_prefix=ENV_PREFIX, extra="ignore")

    data_dir: Path = Path("var")
    database_url: str | None = None
    queue_url: str | None = None
    api_token: SecretStr | None = None
    max_upload_mb: float = Field(default=512.0, gt=0)
    demo: bool = False
    progress_interval_s: float = Field(default=0.5, ge=0)
    inspect_entry: ImportString[InspectFunction] = Field(default_factory=pipeline_inspect)
    viewer_idle_s: float = Field(default=300.0, ge=0)
    viewer_max_servers: int = Field(default=8, ge=1, le=64)
    viewer_max_sockets_per_client: int = Field(default=4, ge=1, le=64)
    viewer_reserved_servers: int = Field(default=2, ge=0, le=64)
    session_hours: float = Field(default=12.0, gt=0, le=24 * 31)
    login_free_failures: int = Field(default=5, ge=1)
    login_window_s: float = Field(default=900.0, gt=0)
    login_max_delay_s: float = Field(default=5.0, ge=0, le=600)
    # Request and queue limits (app.limits): 422 for too big a request, 429 for a full queue.
    max_image_pixels: int = Field(default=4096 * 3072, ge=64 * 64, le=100_000_000)
    max_lights: int = Field(default=48, ge=3, le=1024)
    max_simulated_pixels: int = Field(default=2048 * 1024, ge=64 * 64, le=4096 * 4096)
    max_queued_per_plate: int = Field(default=8, ge=1)
    max_queued: int = Field(default=100, ge=1)
    # -- job consumer (app.worker): memory bound and job leases
    worker_memory_mb: int = Field(default=8192, ge=0)
    job_lease_s: float | None = Field(default=None, ge=3.0)  # None: set by _default_lease
    # -- the cell (app.services.cell)
    cell_config: Path | None = None
    frame_timeout_s: float = Field(default=2.0, gt=0.0, le=600.0)
    # -- the report (app.report)
    yard: str | None = Field(default=None, min_length=1, max_length=64)

    @field_validator("inspect_entry", mode="before")
    @classmethod
    def _entry_shape(cls, v: object) -> object:
        if isinstance(v, str) and (v.count(":") != 1 or not all(v.split(":"))):
            raise ValueError(f"expected 'module:function', got {v!r}")
        return v

    @field_validator("cell_config", mode="before")
    @classmethod
    def _unset_when_empty(cls, v: object) -> object:
        """``PLATE_INSPECT_CELL_CONFIG=`` (empty) is no cell config, not the current folder."""
        return None if isinstance(v, str) and not v.strip() else v

    @field_validator("database_url", "queue_url", mode="before")
    @classmethod
    def _none_when_empty(cls, v: object) -> object:
        """An empty ``PLATE_INSPECT_DATABASE_URL=`` or ``QUEUE_URL=`` is the embedded default."""
        return None if isinstance(v, str) and not v.strip() else v

    @field_validator("queue_url")
    @classmethod
    def _redis_only(cls, v: str | None) -> str | None:
        if v is not None and not v.startswith(("redis://", "rediss://", "unix://")):
            raise ValueError(f"expected redis://host:port/db (or rediss://, unix://), got {v!r}")
        return v

    @model_validator(mode="after")
    def _default_lease(self) -> Settings:
        if self.job_lease_s is None:
            self.job_lease_s = self.lease_s
        return self

    @property
    def lease_s(self) -> float:
        """The job lease in force, s: ``job_lease_s``, or its default for the queue when unset."""
        if self.job_lease_s is not None:
            return self.job_lease_s
        return YARD_JOB_LEASE_S if self.queue_url else EMBEDDED_JOB_LEASE_S

    @property
    def sqlalchemy_url(self) -> str:
        """The database URL in use (the explicit one, or the SQLite file under ``data_dir``)."""
        if self.database_url:
            return self.database_url
        return f"sqlite:///{(self.data_dir / 'plate_inspect.db').resolve()}"

    @property
    def huey_path(self) -> Path:
        """The huey queue's SQLite file."""
        return self.data_dir / "huey.db"

    @property
    def max_upload_bytes(self) -> int:
        return int(self.max_upload_mb * 1024 * 1024)

    def to_env(self) -> dict[str, str]:
        """These settings as ``PLATE_INSPECT_*`` environment variables (for the consumer process)."""
        env = {
            f"{ENV_PREFIX}DATA_DIR": str(self.data_dir.resolve()),
            f"{ENV_PREFIX}DATABASE_URL": self.sqlalchemy_url,
            f"{ENV_PREFIX}MAX_UPLOAD_MB": repr(self.max_upload_mb),
            f"{ENV_PREFIX}DEMO": "1" if self.demo else "0",
            f"{ENV_PREFIX}PROGRESS_INTERVAL_S": repr(self.progress_interval_s),
            f"{ENV_PREFIX}INSPECT_ENTRY": entry_name(self.inspect_entry),
            f"{ENV_PREFIX}WORKER_MEMORY_MB": str(self.worker_memory_mb),
            f"{ENV_PREFIX}JOB_LEASE_S": repr(self.job_lease_s),
            f"{ENV_PREFIX}FRAME_TIMEOUT_S": repr(self.frame_timeout_s),
        }
        if self.queue_url is not None:
            env[f"{ENV_PREFIX}QUEUE_URL"] = self.queue_url
        if self.cell_config is not None:
            env[f"{ENV_PREFIX}CELL_CONFIG"] = str(self.cell_config.resolve())
        if self.api_token is not None:
            env[f"{ENV_PREFIX}API_TOKEN"] = self.api_token.get_secret_value()
        return env
