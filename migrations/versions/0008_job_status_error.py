"""One vocabulary: a job that could not measure its plate ends ``error``, and verdicts are pass or fail.

Until now such a job was ``status = 'failed'`` with ``verdict = 'error'``: "failed" beside a plate's
FAIL read as one more failed plate. The job's state says it (``error``); the verdict is the plate's and
stays empty when nothing was measured.

Revision ID: 0008
Revises: 0007
Create Date: 2026-11-24 16:00:00

"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

# revision identifiers, used by Alembic.
revision: str = "0008"
down_revision: str | Sequence[str] | None = "0007"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    op.execute(sa.text("UPDATE inspections SET verdict = NULL WHERE verdict = 'error'"))
    op.execute(sa.text("UPDATE inspections SET status = 'error' WHERE status = 'failed'"))


def downgrade() -> None:
    op.execute(
        sa.text(
            "UPDATE inspections SET status = 'failed', verdict = 'error' WHERE status = 'error'"
        )
    )
