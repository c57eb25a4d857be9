"""Database engine, sessions and migrations (SQLAlchemy 2, Alembic).

The web process and the job consumer share one database (a SQLite file by default):
SQLite runs in WAL mode with a busy timeout so the two processes can write in turn.
The schema is created and upgraded by Alembic only (never ``create_all``).
"""

from __future__ import annotations

from contextlib import contextmanager
from pathlib import Path

from alembic import command
from alembic.config import Config
from sqlalchemy import Engine, create_engine, event
from sqlalchemy.orm import Session, sessionmaker

from app.locks import file_lock

MIGRATIONS_DIR = Path(__file__).resolve().parents[1] / "migrations"

#: Seconds a SQLite connection waits for the other process's write lock.
SQLITE_BUSY_TIMEOUT_S = 30.0


def make_engine(url: str) -> Engine:
    """An engine for ``url``; SQLite connections get WAL, foreign keys and a busy timeout."""
    if not url:
        raise ValueError("database url: expected a SQLAlchemy URL, got an empty string")
    is_sqlite = url.startswith("sqlite")
    engine = create_engine(
        url,
        connect_args={"timeout": SQLITE_BUSY_TIMEOUT_S, "check_same_thread": False}
        if is_sqlite
        else {},
    )
    if is_sqlite:

        @event.listens_for(engine, "connect")
        def _sqlite_pragmas(dbapi_conn, _record):
            cur = dbapi_conn.cursor()
            cur.execute("PRAGMA journal_mode=WAL")
            cur.execute("PRAGMA foreign_keys=ON")
            cur.execute("PRAGMA synchronous=NORMAL")
            cur.close()

    return engine


def make_session_factory(engine: Engine) -> sessionmaker[Session]:
    """Sessions that keep loaded attributes after commit (routes build responses after it)."""
    return sessionmaker(bind=engine, expire_on_commit=False)


def alembic_config(url: str) -> Config:
    """Alembic configuration for ``url`` (script location: the project's ``migrations/``)."""
    cfg = Config(str(MIGRATIONS_DIR / "alembic.ini"))
    cfg.set_main_option("script_location", str(MIGRATIONS_DIR))
    # ConfigParser interpolation: '%' in the URL must be doubled.
    cfg.set_main_option("sqlalchemy.url", url.replace("%", "%%"))
    # The server's logging is configured already: env.py must not reset it from the .ini.
    cfg.attributes["configure_logging"] = False
    return cfg


def upgrade_database(url: str) -> None:
    """Bring the database at ``url`` to the newest migration (creates a SQLite file if missing).

    The web process and the consumer both upgrade on start, at the same moment under
    ``serve``; for a SQLite file the upgrade holds an exclusive lock on ``<file>.migrate.lock``
    so that the second one waits and then finds the schema current (two concurrent
    upgrades of a new file otherwise both create the tables and one fails).
    """
    with _migration_lock(url):
        command.upgrade(alembic_config(url), "head")


@contextmanager
def _migration_lock(url: str):
    """An exclusive flock beside a SQLite database file (the kernel frees it if its holder dies)."""
    if not url.startswith("sqlite:///") or url.removeprefix("sqlite:///") in ("", ":memory:"):
        yield
        return
    path = Path(url.removeprefix("sqlite:///"))
    with file_lock(path.with_name(path.name + ".migrate.lock")):
        yield
