"""The telemetry log loses its per-batch applied stamp: a batch is applied when its seq is at or
before its stream's applied mark (``streams.last_applied_seq``). Stamping each batch rewrote
its whole row on SQLite (the payload included) once more per apply.

Revision ID: c81d5f3e2a70
Revises: 5e1f0c7a9b3d
Create Date: 2026-12-02 14:00:00.000000
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "c81d5f3e2a70"
down_revision: str | None = "5e1f0c7a9b3d"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    with op.batch_alter_table("telemetry_batches") as batch:
        batch.drop_column("applied_at")


def downgrade() -> None:
    with op.batch_alter_table("telemetry_batches") as batch:
        batch.add_column(sa.Column("applied_at", sa.DateTime(timezone=True), nullable=True))
    # The time of the apply is not known any more: the time of receipt stands in for it.
    op.execute(
        sa.text(
            "UPDATE telemetry_batches SET applied_at = received_at WHERE seq <= "
            "(SELECT last_applied_seq FROM streams WHERE streams.actuator_pk = telemetry_batches.actuator_pk)"
        )
    )
