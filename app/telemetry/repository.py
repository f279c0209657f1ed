"""SQL of the telemetry log."""

from __future__ import annotations

from sqlalchemy import select, text
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


def actuators_for_update(session: Session, actuator_pks: list[int]) -> dict[int, Actuator]:
    """The actuator rows, locked for this transaction in primary-key order (two writers that
    lock overlapping sets in the same order cannot deadlock)."""
    if not actuator_pks:
        return {}
    rows = session.scalars(
        select(Actuator).where(Actuator.id.in_(actuator_pks)).order_by(Actuator.id).with_for_update()
    )
    return {a.id: a for a in rows}


def notify(session: Session, channel: str, payload: str) -> None:
    """PostgreSQL ``NOTIFY``, delivered when (and only if) this transaction commits."""
    session.execute(text("SELECT pg_notify(:channel, :payload)"), {"channel": channel, "payload": payload})
