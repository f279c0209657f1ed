"""Asset lifecycle: soft deletion, estimator config versions, maintenance actions and
baselines; output rows say which config version and baseline produced them

Revision ID: b7e2d4f1a9c3
Revises: 7c3e9a41d2b5
Create Date: 2026-12-02 00:40:00.000000
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "b7e2d4f1a9c3"
down_revision: str | None = "7c3e9a41d2b5"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

OUTPUT_TABLES = ("health_windows", "sample_outputs", "estimator_events", "rul_estimates")


def upgrade() -> None:
    for table in ("aircraft", "actuators"):
        with op.batch_alter_table(table) as batch:
            batch.add_column(sa.Column("deleted_at", sa.DateTime(timezone=True), nullable=True))
    with op.batch_alter_table("estimator_states") as batch:
        batch.add_column(sa.Column("config_version", sa.Integer(), server_default="1", nullable=False))
        batch.add_column(sa.Column("baseline", sa.Integer(), server_default="1", nullable=False))
        batch.add_column(sa.Column("reset_at_seq", sa.BigInteger(), nullable=True))
        batch.add_column(sa.Column("reset_baseline", sa.Integer(), nullable=True))
    for table in OUTPUT_TABLES:
        with op.batch_alter_table(table) as batch:
            batch.add_column(sa.Column("config_version", sa.Integer(), server_default="1", nullable=False))
            batch.add_column(sa.Column("baseline", sa.Integer(), server_default="1", nullable=False))
    op.create_table(
        "estimator_config_versions",
        sa.Column("id", sa.BigInteger().with_variant(sa.Integer(), "sqlite"), nullable=False),
        sa.Column("actuator_pk", sa.Integer(), nullable=False),
        sa.Column("estimator", sa.String(length=32), nullable=False),
        sa.Column("version", sa.Integer(), nullable=False),
        sa.Column("config", sa.JSON(), nullable=False),
        sa.Column("from_seq", sa.BigInteger(), nullable=False),
        sa.Column("state", sa.String(length=8), nullable=False),
        sa.Column("comment", sa.String(length=2000), nullable=True),
        sa.Column("created_at", sa.DateTime(timezone=True), nullable=False),
        sa.Column("created_by_key_id", sa.Integer(), nullable=True),
        sa.ForeignKeyConstraint(
            ["actuator_pk"],
            ["actuators.id"],
            name=op.f("fk_estimator_config_versions_actuator_pk_actuators"),
            ondelete="CASCADE",
        ),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_estimator_config_versions")),
        sa.UniqueConstraint(
            "actuator_pk", "estimator", "version",
            name=op.f("uq_estimator_config_versions_actuator_pk_estimator_version"),
        ),
    )
    op.create_table(
        "maintenance_actions",
        sa.Column("id", sa.BigInteger().with_variant(sa.Integer(), "sqlite"), nullable=False),
        sa.Column("actuator_pk", sa.Integer(), nullable=False),
        sa.Column("action", sa.String(length=16), nullable=False),
        sa.Column("performed_by", sa.String(length=200), nullable=False),
        sa.Column("performed_at", sa.DateTime(timezone=True), nullable=False),
        sa.Column("comment", sa.String(length=2000), nullable=True),
        sa.Column("baseline", sa.Integer(), nullable=False),
        sa.Column("from_seq", sa.BigInteger(), nullable=True),
        sa.Column("status_before", sa.String(length=8), nullable=False),
        sa.Column("recorded_at", sa.DateTime(timezone=True), nullable=False),
        sa.Column("recorded_by_key_id", sa.Integer(), nullable=True),
        sa.ForeignKeyConstraint(
            ["actuator_pk"],
            ["actuators.id"],
            name=op.f("fk_maintenance_actions_actuator_pk_actuators"),
            ondelete="CASCADE",
        ),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_maintenance_actions")),
    )
    op.create_index("ix_maintenance_actions_actuator", "maintenance_actions", ["actuator_pk", "id"])
    # Every existing estimator has had one configuration, from the stream's first batch.
    op.execute(
        sa.text(
            "INSERT INTO estimator_config_versions "
            "(actuator_pk, estimator, version, config, from_seq, state, created_at) "
            "SELECT e.actuator_pk, e.estimator, 1, e.config, 1, 'kept', a.created_at "
            "FROM estimator_states e JOIN actuators a ON a.id = e.actuator_pk"
        )
    )


def downgrade() -> None:
    op.drop_index("ix_maintenance_actions_actuator", table_name="maintenance_actions")
    op.drop_table("maintenance_actions")
    op.drop_table("estimator_config_versions")
    for table in OUTPUT_TABLES:
        with op.batch_alter_table(table) as batch:
            batch.drop_column("baseline")
            batch.drop_column("config_version")
    with op.batch_alter_table("estimator_states") as batch:
        for col in ("reset_baseline", "reset_at_seq", "baseline", "config_version"):
            batch.drop_column(col)
    for table in ("aircraft", "actuators"):
        with op.batch_alter_table(table) as batch:
            batch.drop_column("deleted_at")
