"""SQL of the telemetry log."""

from __future__ import annotations

from sqlalchemy import select
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from app.models import Actuator, TelemetryBatch


def batch_by_id(session: Session, actuator_pk: int, batch_id: str) -> TelemetryBatch | None:
    return session.scalar(
        select(TelemetryBatch).where(
            TelemetryBatch.actuator_pk == actuator_pk, TelemetryBatch.batch_id == batch_id
        )
    )


def add_batch(session: Session, row: TelemetryBatch) -> bool:
    """Insert a log row; False when its batch id (or seq) is taken meanwhile."""
    try:
        with session.begin_nested():
            session.add(row)
            session.flush()
    except IntegrityError:
        return False
    return True


def actuator_for_update(session: Session, actuator_pk: int) -> Actuator | None:
    """The actuator row, locked for this transaction (SQLite: ``BEGIN IMMEDIATE`` serializes
    writers already and ignores the clause)."""
    return session.get(Actuator, actuator_pk, with_for_update=True)
