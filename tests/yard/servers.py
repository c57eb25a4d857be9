"""Real PostgreSQL and Redis servers for the tests, from Debian's packages (``postgresql``,
``redis-server``): each started in a temporary directory on a free loopback port, stopped after.

PostgreSQL refuses to run as root: when the tests run as root, ``initdb`` and ``pg_ctl`` run as
the ``postgres`` system user the package creates (``runuser``). Missing binaries fail the test
with what to run (``scripts/setup.sh --with-browser`` installs them), never skip it.
"""

from __future__ import annotations

import glob
import itertools
import os
import shutil
import socket
import subprocess
import tempfile
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest

SETUP_HINT = "run `bash scripts/setup.sh --with-browser` (it installs postgresql and redis-server)"
#: Seconds a server gets to answer after its start.
START_TIMEOUT_S = 60.0


def free_port() -> int:
    """A TCP port free on 127.0.0.1 now."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _postgres_bin() -> Path:
    found = sorted(glob.glob("/usr/lib/postgresql/*/bin/initdb"))
    if not found:
        pytest.fail(
            f"PostgreSQL server binaries not found (/usr/lib/postgresql/*/bin): {SETUP_HINT}"
        )
    return Path(found[-1]).parent


class PostgresServer:
    """A PostgreSQL cluster in ``root`` on ``port`` (superuser ``plate``, trust authentication).

    Parameters
    ----------
    root : Path
        A new empty directory (its parent must be writable by the ``postgres`` user under root).
    durable : bool
        False (tests) turns fsync off; True keeps the server's defaults (benchmarks).
    """

    def __init__(self, root: Path, *, durable: bool = False):
        self.bin = _postgres_bin()
        self.root = Path(root)
        self.data = self.root / "data"
        self.port = free_port()
        self.durable = durable
        self._names = itertools.count()

    def _run(self, *args: str) -> subprocess.CompletedProcess[str]:
        cmd = [str(self.bin / args[0]), *args[1:]]
        if os.geteuid() == 0:
            cmd = ["runuser", "-u", "postgres", "--", *cmd]
        env = {**os.environ, "LC_ALL": "C.UTF-8", "LANG": "C.UTF-8"}
        res = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=self.root)
        if res.returncode != 0:
            raise RuntimeError(
                f"{' '.join(cmd)} failed ({res.returncode}):\n{res.stdout}\n{res.stderr}"
            )
        return res

    def start(self) -> PostgresServer:
        if os.geteuid() == 0:
            shutil.chown(self.root, user="postgres", group="postgres")
        if not self.data.exists():
            self._run(
                "initdb",
                "-D",
                str(self.data),
                "-A",
                "trust",
                "-U",
                "plate",
                "-E",
                "UTF8",
                "--no-sync",
            )
        options = (
            f"-p {self.port} -k {self.root} -c listen_addresses=127.0.0.1 -c max_connections=200"
        )
        if not self.durable:
            options += " -c fsync=off -c synchronous_commit=off -c full_page_writes=off"
        self._run(
            "pg_ctl",
            "-D",
            str(self.data),
            "-w",
            "-t",
            str(int(START_TIMEOUT_S)),
            "-l",
            str(self.root / "server.log"),
            "-o",
            options,
            "start",
        )
        return self

    def stop(self) -> None:
        """Stop the server (fast shutdown: open connections are ended)."""
        if (self.data / "postmaster.pid").exists():
            self._run("pg_ctl", "-D", str(self.data), "-w", "-m", "fast", "stop")

    def url(self, database: str = "postgres") -> str:
        return f"postgresql+psycopg://plate@127.0.0.1:{self.port}/{database}"

    def admin(self, sql: str) -> None:
        """Run one statement outside a transaction on the ``postgres`` database."""
        import psycopg

        with psycopg.connect(
            f"host=127.0.0.1 port={self.port} user=plate dbname=postgres", autocommit=True
        ) as conn:
            conn.execute(sql)

    def create_database(self, *, template: str | None = None, name: str | None = None) -> str:
        """A new database (a copy of ``template`` when given); returns its name."""
        name = name or f"t{os.getpid()}_{next(self._names)}"
        self.admin(f'CREATE DATABASE "{name}"' + (f' TEMPLATE "{template}"' if template else ""))
        return name

    def drop_database(self, name: str) -> None:
        self.admin(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)')


class RedisServer:
    """``redis-server`` on a free loopback port, its files in ``root``, no snapshots."""

    def __init__(self, root: Path):
        binary = shutil.which("redis-server") or "/usr/bin/redis-server"
        if not Path(binary).exists():
            pytest.fail(f"redis-server not found: {SETUP_HINT}")
        self.binary = binary
        self.root = Path(root)
        self.port = free_port()
        self.proc: subprocess.Popen[bytes] | None = None

    def start(self) -> RedisServer:
        with open(self.root / "redis.log", "ab") as log:
            self.proc = subprocess.Popen(
                [
                    self.binary,
                    "--port",
                    str(self.port),
                    "--bind",
                    "127.0.0.1",
                    "--dir",
                    str(self.root),
                    "--save",
                    "",
                    "--appendonly",
                    "no",
                ],
                stdout=log,
                stderr=log,
            )
        deadline = time.monotonic() + START_TIMEOUT_S
        while not self.ping():
            if self.proc.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError(
                    f"redis-server did not start:\n{(self.root / 'redis.log').read_text()}"
                )
            time.sleep(0.05)
        return self

    def ping(self) -> bool:
        import redis

        try:
            return bool(redis.Redis(host="127.0.0.1", port=self.port, socket_timeout=1).ping())
        except redis.exceptions.ConnectionError:
            return False

    def url(self, db: int = 0) -> str:
        return f"redis://127.0.0.1:{self.port}/{db}"

    def flush(self) -> None:
        import redis

        redis.Redis(host="127.0.0.1", port=self.port).flushall()

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.terminate()
            self.proc.wait(30)


@contextmanager
def running_postgres(*, durable: bool = False) -> Iterator[PostgresServer]:
    """A started :class:`PostgresServer` in a new temporary directory; stopped and removed after."""
    root = Path(tempfile.mkdtemp(prefix="plate-pg-"))
    server = PostgresServer(root, durable=durable)
    try:
        yield server.start()
    finally:
        server.stop()
        shutil.rmtree(root, ignore_errors=True)


@contextmanager
def running_redis() -> Iterator[RedisServer]:
    """A started :class:`RedisServer` in a new temporary directory; stopped and removed after."""
    root = Path(tempfile.mkdtemp(prefix="plate-redis-"))
    server = RedisServer(root)
    try:
        yield server.start()
    finally:
        server.stop()
        shutil.rmtree(root, ignore_errors=True)


@contextmanager
def migrated_template(server: PostgresServer) -> Iterator[str]:
    """A database migrated to the newest schema, to copy per test (``CREATE DATABASE ... TEMPLATE``)."""
    from app.db import upgrade_database

    name = server.create_database(name=f"migrated_{os.getpid()}")
    upgrade_database(server.url(name))
    try:
        yield name
    finally:
        server.drop_database(name)
