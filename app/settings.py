"""The service's settings: one pydantic-settings class, environment prefix ``PLATE_INSPECT_``.

``PLATE_INSPECT_DATA_DIR``, ``PLATE_INSPECT_DATABASE_URL``, ``PLATE_INSPECT_API_TOKEN``,
``PLATE_INSPECT_MAX_UPLOAD_MB``, ``PLATE_INSPECT_DEMO``, ``PLATE_INSPECT_PROGRESS_INTERVAL_S``,
``PLATE_INSPECT_INSPECT_ENTRY``, ``PLATE_INSPECT_VIEWER_IDLE_S``, ``PLATE_INSPECT_VIEWER_MAX_SERVERS``,
``PLATE_INSPECT_WORKER_MEMORY_MB``, ``PLATE_INSPECT_JOB_LEASE_S``.
"""

from __future__ import annotations

from pathlib import Path

from pydantic import Field, SecretStr, field_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

#: Environment variable prefix of every setting.
ENV_PREFIX = "PLATE_INSPECT_"


class Settings(BaseSettings):
    """Configuration of the web process and the job consumer (both read the same environment).

    Attributes
    ----------
    data_dir : Path
        Root of everything stored on disk: the SQLite database (by default), the huey queue,
        uploads and artifacts (layout in :mod:`app.storage`).
    database_url : str or None
        SQLAlchemy URL; None means ``sqlite:///<data_dir>/plate_inspect.db``.
    api_token : SecretStr or None
        Bearer token required by every write. Without one the server refuses to start unless
        ``demo`` is set, in which case a random token is generated and printed at start.
    max_upload_mb : float
        Largest request body accepted, in MiB (413 beyond it).
    demo : bool
        Demo cell: a generated token, and dashboard pages get a write session without a login.
    progress_interval_s : float
        Shortest interval between two progress writes of a running job to the database, s.
    inspect_entry : str
        ``module:function`` the job calls to inspect; ``pipeline.run:inspect`` in production
        (tests point it at a test double to control timing).
    viewer_idle_s : float
        A 3D view's viser server stops this long after its last browser left, s.
    viewer_max_servers : int
        Most 3D views (one viser server each, on loopback) running at once.
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
        worker death (the second sets the job aside as failed).
    """

    model_config = SettingsConfigDict(env_prefix=ENV_PREFIX, extra="ignore")

    data_dir: Path = Path("var")
    database_url: str | None = None
    api_token: SecretStr | None = None
    max_upload_mb: float = Field(default=512.0, gt=0)
    demo: bool = False
    progress_interval_s: float = Field(default=0.5, ge=0)
    inspect_entry: str = "pipeline.run:inspect"
    viewer_idle_s: float = Field(default=300.0, ge=0)
    viewer_max_servers: int = Field(default=8, ge=1, le=64)
    # -- job consumer (app.worker): memory bound and job leases
    worker_memory_mb: int = Field(default=8192, ge=0)
    job_lease_s: float = Field(default=60.0, ge=3.0)

    @field_validator("inspect_entry")
    @classmethod
    def _entry_shape(cls, v: str) -> str:
        if v.count(":") != 1 or not all(v.split(":")):
            raise ValueError(f"expected 'module:function', got {v!r}")
        return v

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
            f"{ENV_PREFIX}INSPECT_ENTRY": self.inspect_entry,
            f"{ENV_PREFIX}WORKER_MEMORY_MB": str(self.worker_memory_mb),
            f"{ENV_PREFIX}JOB_LEASE_S": repr(self.job_lease_s),
        }
        if self.api_token is not None:
            env[f"{ENV_PREFIX}API_TOKEN"] = self.api_token.get_secret_value()
        return env
