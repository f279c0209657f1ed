"""RUL estimates, estimator diagnoses, streamed-frame client sequence numbers

Revision ID: 001befd59ade
Revises: 4fa009bedd2e
Create Date: 2026-11-22 01:25:44.916700
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "001befd59ade"
down_revision: str | None = "4fa009bedd2e"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    op.create_table(
        "rul_estimates",
        sa.Column("id", sa.BigInteger().with_variant(sa.Integer(), "sqlite"), nullable=False),
        sa.Column("actuator_pk", sa.Integer(), nullable=False),
        sa.Column("estimator", sa.String(length=32), nullable=False),
        sa.Column("seq", sa.BigInteger(), nullable=False),
        sa.Column("t_s", sa.Float(), nullable=False),
        sa.Column("mean_s", sa.Float(), nullable=True),
        sa.Column("std_s", sa.Float(), nullable=True),
        sa.Column("q05_s", sa.Float(), nullable=True),
        sa.Column("q50_s", sa.Float(), nullable=True),
        sa.Column("q95_s", sa.Float(), nullable=True),
        sa.Column("optimistic_s", sa.Float(), nullable=True),
        sa.Column("pessimistic_s", sa.Float(), nullable=True),
        sa.Column("threshold", sa.Float(), nullable=False),
        sa.Column("health", sa.JSON(), nullable=False),
        sa.Column("assumption", sa.JSON(), nullable=False),
        sa.Column("status", sa.String(length=8), nullable=False),
        sa.Column("reasons", sa.JSON(), nullable=False),
        sa.ForeignKeyConstraint(
            ["actuator_pk"],
            ["actuators.id"],
            name=op.f("fk_rul_estimates_actuator_pk_actuators"),
            ondelete="CASCADE",
        ),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_rul_estimates")),
    )
    with op.batch_alter_table("rul_estimates", schema=None) as batch_op:
        batch_op.create_index(
            "ix_rul_estimates_stream_time", ["actuator_pk", "estimator", "t_s"], unique=False
        )

    with op.batch_alter_table("estimator_states", schema=None) as batch_op:
        batch_op.add_column(sa.Column("diagnosis_t_s", sa.Float(), nullable=True))
        batch_op.add_column(sa.Column("diagnosis", sa.JSON(), nullable=True))

    with op.batch_alter_table("actuators", schema=None) as batch_op:
        batch_op.add_column(sa.Column("last_client_seq", sa.BigInteger(), nullable=True))

    with op.batch_alter_table("streams", schema=None) as batch_op:
        batch_op.add_column(sa.Column("rul_t_s", sa.Float(), nullable=True))
        batch_op.add_column(sa.Column("rul_q05_s", sa.Float(), nullable=True))
        batch_op.add_column(sa.Column("rul_q50_s", sa.Float(), nullable=True))


def downgrade() -> None:
    with op.batch_alter_table("streams", schema=None) as batch_op:
        batch_op.drop_column("rul_q50_s")
        batch_op.drop_column("rul_q05_s")
        batch_op.drop_column("rul_t_s")

    with op.batch_alter_table("actuators", schema=None) as batch_op:
        batch_op.drop_column("last_client_seq")

    with op.batch_alter_table("estimator_states", schema=None) as batch_op:
        batch_op.drop_column("diagnosis")
        batch_op.drop_column("diagnosis_t_s")

    with op.batch_alter_table("rul_estimates", schema=None) as batch_op:
        batch_op.drop_index("ix_rul_estimates_stream_time")

    op.drop_table("rul_estimates")
