"""Acquired inspections: the cell an inspection is photographed in.

Revision ID: 0005
Revises: 0004
Create Date: 2026-11-25 09:00:00

"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

# revision identifiers, used by Alembic.
revision: str = "0005"
down_revision: str | Sequence[str] | None = "0004"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    """Upgrade schema: ``inspections.cell_id`` (null for uploaded and simulated inspections)."""
    with op.batch_alter_table("inspections", schema=None) as batch_op:
        batch_op.add_column(sa.Column("cell_id", sa.String(length=64), nullable=True))
        batch_op.create_index(batch_op.f("ix_inspections_cell_id"), ["cell_id"], unique=False)


def downgrade() -> None:
    """Downgrade schema."""
    with op.batch_alter_table("inspections", schema=None) as batch_op:
        batch_op.drop_index(batch_op.f("ix_inspections_cell_id"))
        batch_op.drop_column("cell_id")
