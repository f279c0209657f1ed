"""Stream rewinds: the record of every admin rewind of a stream

Revision ID: 5e1f0c7a9b3d
Revises: 7c3e9a41d2b5
Create Date: 2026-12-02 01:00:00.000000
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "5e1f0c7a9b3d"
down_revision: str | None = "b4e7d2a9c316"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    op.create_table(
        "stream_rewinds",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("actuator_pk", sa.Integer(), nullable=False),
        sa.Column("at", sa.DateTime(timezone=True), nullable=False),
        sa.Column("actor", sa.String(length=200), nullable=False),
        sa.Column("key_id", sa.Integer(), nullable=True),
        sa.Column("reason", sa.String(length=500), nullable=False),
        sa.Column("to_seq", sa.BigInteger(), nullable=False),
        sa.Column("from_logged_seq", sa.BigInteger(), nullable=False),
        sa.Column("from_applied_seq", sa.BigInteger(), nullable=False),
        sa.Column("estimators_reset", sa.Boolean(), nullable=False),
        sa.Column("discarded", sa.JSON(), nullable=False),
        sa.ForeignKeyConstraint(
            ["actuator_pk"], ["actuators.id"],
            name=op.f("fk_stream_rewinds_actuator_pk_actuators"), ondelete="CASCADE",
        ),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_stream_rewinds")),
    )
    op.create_index(op.f("ix_stream_rewinds_actuator_pk"), "stream_rewinds", ["actuator_pk"])


def downgrade() -> None:
    op.drop_index(op.f("ix_stream_rewinds_actuator_pk"), table_name="stream_rewinds")
    op.drop_table("stream_rewinds")
