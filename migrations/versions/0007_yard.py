"""A yard's PostgreSQL: timezone-aware timestamps and 64-bit ids there, indexes for the history and the queue.

On PostgreSQL every ``timestamp`` column of the service's tables becomes ``timestamp with time
zone`` (the values were stored as UTC: they are read as UTC), and the numeric row ids (and the
foreign keys to them) ``bigint``, as the API's ids go up to 2^63 - 1. SQLite has no such type: nothing
changes there but the indexes. New datetime columns in later revisions: ``sa.DateTime(timezone=True)``.

Revision ID: 0007
Revises: 0006
Create Date: 2026-11-26 09:00:00

"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

# revision identifiers, used by Alembic.
revision: str = "0007"
down_revision: str | Sequence[str] | None = "0006"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

#: Numeric ids made bigint on PostgreSQL: (table, column, its sequence or None for a foreign key).
BIGINT_IDS = [
    ("targets", "id", "targets_id_seq"),
    ("calibrations", "id", "calibrations_id_seq"),
    ("light_calibrations", "id", "light_calibrations_id_seq"),
    ("inspections", "id", "inspections_id_seq"),
    ("idempotency_keys", "id", "idempotency_keys_id_seq"),
    ("inspections", "target_id", None),
    ("inspections", "light_calibration_id", None),
]
INDEXES = {
    "ix_inspections_plate_id_id": ["plate_id", "id"],
    "ix_inspections_status_queued_at": ["status", "queued_at"],
}


def _timestamp_columns(timezone: bool) -> list[tuple[str, str]]:
    """(table, column) of every timestamp column with (or without) a time zone, public schema."""
    rows = op.get_bind().execute(
        sa.text(
            "SELECT table_name, column_name FROM information_schema.columns "
            "WHERE table_schema = current_schema() AND data_type = :type "
            "AND table_name <> 'alembic_version' ORDER BY table_name, column_name"
        ),
        {"type": "timestamp with time zone" if timezone else "timestamp without time zone"},
    )
    return [(table, column) for table, column in rows]


def _id_types(sql_type: str) -> None:
    for table, column, sequence in BIGINT_IDS:
        op.execute(f'ALTER TABLE "{table}" ALTER COLUMN "{column}" TYPE {sql_type}')
        if sequence is not None:
            op.execute(f'ALTER SEQUENCE "{sequence}" AS {sql_type}')


def upgrade() -> None:
    """Upgrade schema."""
    if op.get_bind().dialect.name == "postgresql":
        for table, column in _timestamp_columns(timezone=False):
            op.execute(
                f'ALTER TABLE "{table}" ALTER COLUMN "{column}" TYPE timestamp with time zone '
                f"USING \"{column}\" AT TIME ZONE 'UTC'"
            )
        _id_types("bigint")
    with op.batch_alter_table("inspections", schema=None) as batch_op:
        for name, columns in INDEXES.items():
            batch_op.create_index(name, columns, unique=False)


def downgrade() -> None:
    """Downgrade schema."""
    with op.batch_alter_table("inspections", schema=None) as batch_op:
        for name in INDEXES:
            batch_op.drop_index(name)
    if op.get_bind().dialect.name == "postgresql":
        _id_types("integer")
        for table, column in _timestamp_columns(timezone=True):
            op.execute(
                f'ALTER TABLE "{table}" ALTER COLUMN "{column}" TYPE timestamp without time zone '
                f"USING \"{column}\" AT TIME ZONE 'UTC'"
            )
