"""Fixtures: a real app (SQLite migrated by Alembic) in a temp data dir, with inspections seeded."""

from __future__ import annotations

import pytest


@pytest.fixture
def demo_app(tmp_path, monkeypatch, migrated_sqlite):
    """create_app() in demo mode on a temp data dir (no consumer; rows are seeded directly)."""
    from app.main import create_app
    from app.settings import Settings

    migrated_sqlite(tmp_path / "data")
    settings = Settings(data_dir=tmp_path / "data", demo=True)
    return create_app(settings)
