"""Database engine, sessions and migrations (SQLAlchemy 2, Alembic).

The web process and the job consumer share one database (a SQLite file by default):
SQLite runs in WAL mode with a busy timeout so the two processes can write in turn. A yard's
central PostgreSQL (``postgresql+psycopg://...``) is reached through a connection pool whose
connections are checked before use (``pool_pre_ping``): after the server was restarted or
unreachable, the next request gets a fresh connection instead of an error.
The schema is created and upgraded by Alembic only (never ``create_all``); concurrent upgrades
(``serve`` and workers starting together) take turns under a lock (a file lock beside a SQLite
file, a PostgreSQL advisory lock).
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from alembic import command
from alembic.config import Config
from sqlalchemy import Engine, create_engine, event, text
from sqlalchemy.engine.interfaces import DBAPIConnection
from sqlalchemy.exc import DBAPIError, OperationalError
from sqlalchemy.orm import Session, sessionmaker
from sqlalchemy.pool import NullPool

from app.locks import file_lock

MIGRATIONS_DIR = Path(__file__).resolve().parents[1] / "migrations"

#: Seconds a SQLite connection waits for the other process's write lock.
SQLITE_BUSY_TIMEOUT_S = 30.0
#: Seconds a PostgreSQL connection attempt waits for the server (then the request answers 503).
CONNECT_TIMEOUT_S = 5
#: Pooled connections per process beyond which a request waits (plus the overflow), and how long.
POOL_SIZE, POOL_MAX_OVERFLOW, POOL_TIMEOUT_S = 5, 10, 10.0
#: Pooled connections older than this are replaced (a firewall between cell and server may drop idle ones), s.
POOL_RECYCLE_S = 1800
#: Key of the PostgreSQL advisory lock held while the schema is upgraded.
MIGRATION_LOCK_KEY = 0x706C617465  # "plate"


def make_engine(url: str) -> Engine:
    """An engine for ``url``.

    SQLite connections get WAL, foreign keys and a busy timeout. A server database gets a pool
    (:data:`POOL_SIZE` + :data:`POOL_MAX_OVERFLOW` connections), connections checked before use
    and recycled after :data:`POOL_RECYCLE_S`, and a connect timeout of :data:`CONNECT_TIMEOUT_S`.
    """
    if not url:
        raise ValueError("database url: expected a SQLAlchemy URL, got an empty string")
    is_sqlite = url.startswith("sqlite")
    if is_sqlite:
        engine = create_engine(
            url, connect_args={"timeout": SQLITE_BUSY_TIMEOUT_S, "check_same_thread": False}
        )
    else:
        engine = create_engine(
            url,
            pool_pre_ping=True,
            pool_size=POOL_SIZE,
            max_overflow=POOL_MAX_OVERFLOW,
            pool_timeout=POOL_TIMEOUT_S,
            pool_recycle=POOL_RECYCLE_S,
            connect_args={"connect_timeout": CONNECT_TIMEOUT_S}
            if url.startswith("postgresql")
            else {},
        )
    if is_sqlite:

        @event.listens_for(engine, "connect")
        def _sqlite_pragmas(dbapi_conn: DBAPIConnection, _record: object) -> None:
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
    upgrades of a new file otherwise both create the tables and one fails); on PostgreSQL
    (``serve`` on N cells and M workers starting together) an advisory lock does the same.
    """
    with _migration_lock(url):
        command.upgrade(alembic_config(url), "head")


def database_unavailable(exc: BaseException) -> bool:
    """Whether ``exc`` says the database cannot be reached or used now (not a bad statement).

    A connection refused or dropped, a server shutting down, a SQLite file locked beyond the busy
    timeout: the request may succeed later (the service answers 503).
    """
    if isinstance(exc, OperationalError):
        return True
    return isinstance(exc, DBAPIError) and bool(exc.connection_invalidated)


@contextmanager
def _migration_lock(url: str) -> Iterator[None]:
    """An exclusive lock for a schema upgrade: a flock beside a SQLite database file (the kernel
    frees it if its holder dies), a session-level advisory lock on PostgreSQL (freed when its
    connection closes, however the process ends)."""
    if url.startswith("postgresql"):
        engine = create_engine(
            url, poolclass=NullPool, connect_args={"connect_timeout": CONNECT_TIMEOUT_S}
        )
        try:
            with engine.connect() as conn:
                conn.execute(text("SELECT pg_advisory_lock(:key)"), {"key": MIGRATION_LOCK_KEY})
                conn.commit()
                try:
                    yield
                finally:
                    conn.execute(
                        text("SELECT pg_advisory_unlock(:key)"), {"key": MIGRATION_LOCK_KEY}
                    )
                    conn.commit()
        finally:
            engine.dispose()
        return
    if not url.startswith("sqlite:///") or url.removeprefix("sqlite:///") in ("", ":memory:"):
        yield
        return
    path = Path(url.removeprefix("sqlite:///"))
    with file_lock(path.with_name(path.name + ".migrate.lock")):
        yield
