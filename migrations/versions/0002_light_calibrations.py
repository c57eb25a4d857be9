"""Light calibrations (light-calibration/1) and the one each inspection was run with.

Revision ID: 0002
Revises: 0001
Create Date: 2026-11-23 19:00:00

"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

# revision identifiers, used by Alembic.
revision: str = "0002"
down_revision: str | Sequence[str] | None = "0001"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

#: SQLite has no ALTER TABLE ADD CONSTRAINT: batch mode recreates the table and needs the name.
FK_NAME = "fk_inspections_light_calibration_id_light_calibrations"


def upgrade() -> None:
    """Upgrade schema."""
    op.create_table(
        "light_calibrations",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("file_name", sa.String(length=255), nullable=True),
        sa.Column("n_lights", sa.Integer(), nullable=False),
        sa.Column("rms", sa.Float(), nullable=True),
        sa.Column("document", sa.JSON(), nullable=False),
        sa.Column("path", sa.String(length=512), nullable=False),
        sa.Column("created_at", sa.DateTime(), nullable=False),
        sa.PrimaryKeyConstraint("id"),
    )
    with op.batch_alter_table("inspections", schema=None) as batch_op:
        batch_op.add_column(sa.Column("light_calibration_id", sa.Integer(), nullable=True))
        batch_op.create_foreign_key(FK_NAME, "light_calibrations", ["light_calibration_id"], ["id"])


def downgrade() -> None:
    """Downgrade schema."""
    with op.batch_alter_table("inspections", schema=None) as batch_op:
        batch_op.drop_constraint(FK_NAME, type_="foreignkey")
        batch_op.drop_column("light_calibration_id")

    op.drop_table("light_calibrations")
