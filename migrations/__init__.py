"""Alembic migrations of the service database (``app.db.upgrade_database`` runs them)."""
