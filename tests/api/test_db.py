"""The database's migrations: concurrent upgrades of one new SQLite file (web process and consumer)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import sqlalchemy as sa

ROOT = Path(__file__).resolve().parents[2]

UPGRADE = "import sys; from app.db import upgrade_database; upgrade_database(sys.argv[1])"


def _heads() -> set[str]:
    from alembic.script import ScriptDirectory

    from app.db import alembic_config

    return set(ScriptDirectory.from_config(alembic_config("sqlite://")).get_heads())


def test_processes_upgrading_one_new_file_at_once_all_succeed(tmp_path):
    # `serve` starts the web process and the consumer together; both upgrade on start.
    for trial in range(3):
        url = f"sqlite:///{tmp_path / f'trial{trial}' / 'plate_inspect.db'}"
        procs = [
            subprocess.Popen(
                [sys.executable, "-c", UPGRADE, url], cwd=ROOT, stderr=subprocess.PIPE, text=True
            )
            for _ in range(3)
        ]
        errors = [p.communicate(timeout=120)[1] for p in procs]
        assert [p.returncode for p in procs] == [0, 0, 0], "\n".join(errors)
        engine = sa.create_engine(url)
        with engine.connect() as conn:
            versions = {
                row[0] for row in conn.execute(sa.text("SELECT version_num FROM alembic_version"))
            }
            tables = set(sa.inspect(conn).get_table_names())
        engine.dispose()
        assert versions == _heads()
        assert {"inspections", "light_calibrations"} <= tables


def test_migrated_database_is_at_the_single_head_and_matches_the_models(client):
    """One Alembic head, the database migrated to it, and no difference left for autogenerate."""
    from alembic.autogenerate import compare_metadata
    from alembic.migration import MigrationContext

    from app.models import Base

    heads = _heads()
    assert len(heads) == 1, f"migrations have several heads: {sorted(heads)}"
    with client.app.state.engine.connect() as connection:
        context = MigrationContext.configure(connection)
        assert {context.get_current_revision()} == heads
        assert compare_metadata(context, Base.metadata) == []


def test_job_status_vocabulary_migrates_both_ways(tmp_path):
    """0008: a job that could not measure was ``failed`` with verdict ``error``; it is ``error`` without
    a verdict, and a downgrade gives the old pair back. Done jobs keep their verdict."""
    from alembic import command
    from sqlalchemy.orm import Session

    from app.db import alembic_config
    from app.models import Inspection, JobStatus, Plate

    url = f"sqlite:///{tmp_path / 'plate_inspect.db'}"
    cfg = alembic_config(url)
    command.upgrade(cfg, "head")
    engine = sa.create_engine(url)
    with Session(engine) as session:
        session.add(Plate(id="P1"))
        session.add_all(
            [
                Inspection(plate_id="P1", source="upload", status=JobStatus.ERROR, error="bad"),
                Inspection(plate_id="P1", source="upload", status=JobStatus.DONE, verdict="fail"),
            ]
        )
        session.commit()

    def rows() -> list[tuple[str, str | None]]:
        with engine.connect() as conn:
            q = sa.text("SELECT status, verdict FROM inspections ORDER BY id")
            return [tuple(r) for r in conn.execute(q)]

    command.downgrade(cfg, "0007")
    assert rows() == [("failed", "error"), ("done", "fail")]
    command.upgrade(cfg, "head")
    assert rows() == [("error", None), ("done", "fail")]
    engine.dispose()


def test_idempotency_fingerprints_migrate_both_ways(tmp_path):
    """0010: a claimed key records its request's fingerprint; keys stored before it have none
    (and replay for any body); a downgrade drops the column and keeps the keys."""
    from alembic import command

    from app.db import alembic_config

    url = f"sqlite:///{tmp_path / 'plate_inspect.db'}"
    cfg = alembic_config(url)
    command.upgrade(cfg, "0009")
    engine = sa.create_engine(url)
    with engine.begin() as conn:
        conn.execute(
            sa.text(
                "INSERT INTO idempotency_keys (key, scope, token_hash, state, created_at) "
                "VALUES ('k', 'POST /x', 't', 'done', '2026-11-26 09:00:00')"
            )
        )

    def columns() -> set[str]:
        with engine.connect() as conn:
            return {c["name"] for c in sa.inspect(conn).get_columns("idempotency_keys")}

    command.upgrade(cfg, "head")
    assert "request_sha256" in columns()
    with engine.connect() as conn:
        q = sa.text("SELECT key, request_sha256 FROM idempotency_keys")
        assert [tuple(r) for r in conn.execute(q)] == [("k", None)]
    command.downgrade(cfg, "0009")
    assert "request_sha256" not in columns()
    with engine.connect() as conn:
        assert conn.execute(sa.text("SELECT count(*) FROM idempotency_keys")).scalar() == 1
    engine.dispose()
