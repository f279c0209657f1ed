"""Stream failure reason; end-of-run marker on logged batches

Revision ID: 7c3e9a41d2b5
Revises: 001befd59ade
Create Date: 2026-12-01 20:40:00.000000
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "7c3e9a41d2b5"
down_revision: str | None = "001befd59ade"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    # Why a stream is no longer applied (status "failed"); NULL while it is applied.
    op.add_column("streams", sa.Column("failure", sa.String(length=2000), nullable=True))
    # Existing batches did not end a run; the marker is part of a batch's identity.
    op.add_column(
        "telemetry_batches",
        sa.Column("end_of_run", sa.Boolean(), server_default=sa.false(), nullable=False),
    )
    # New streams start "learning" (the ORM's default); a stream that never applied a batch
    # reported "ok" without evidence, so it says "learning" now too.
    op.execute(sa.text("UPDATE streams SET status = 'learning' WHERE last_applied_seq = 0"))
    op.execute(sa.text("UPDATE estimator_states SET status = 'learning' WHERE applied_seq = 0"))


def downgrade() -> None:
    op.execute(sa.text("UPDATE streams SET status = 'ok' WHERE status = 'learning'"))
    op.execute(sa.text("UPDATE estimator_states SET status = 'ok' WHERE status = 'learning'"))
    with op.batch_alter_table("telemetry_batches") as batch:
        batch.drop_column("end_of_run")
    with op.batch_alter_table("streams") as batch:
        batch.drop_column("failure")
