"""SQL of the telemetry log."""

from __future__ import annotations

from collections.abc import Iterator

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


def actuator_for_update(session: Session, actuator_pk: int) -> Actuator | None:
    """The actuator row, locked for this transaction (SQLite: ``BEGIN IMMEDIATE`` serializes
    writers already and ignores the clause)."""
    return session.get(Actuator, actuator_pk, with_for_update=True)


# ----------------------------------------------------------------------------- read-back
def logged_blocks(
    session: Session,
    actuator_pk: int,
    from_s: float | None,
    to_s: float | None,
    *,
    order: str = "asc",
) -> Iterator[TelemetryBatch]:
    """Logged batches that meet [from_s, to_s], in stream order (or its reverse), read a few at
    a time; each row is let go once the caller moves on, so memory holds a handful of payloads."""
    stmt = select(TelemetryBatch).where(TelemetryBatch.actuator_pk == actuator_pk)
    if from_s is not None:
        stmt = stmt.where(TelemetryBatch.t_last_s >= from_s)
    if to_s is not None:
        stmt = stmt.where(TelemetryBatch.t_first_s <= to_s)
    col = TelemetryBatch.seq
    stmt = stmt.order_by(col.asc() if order == "asc" else col.desc()).execution_options(yield_per=16)
    for row in session.scalars(stmt):
        yield row
        session.expunge(row)


def batch_at(session: Session, actuator_pk: int, seq: int) -> TelemetryBatch | None:
    return session.scalar(
        select(TelemetryBatch).where(TelemetryBatch.actuator_pk == actuator_pk, TelemetryBatch.seq == seq)
    )


def first_kept_batch(session: Session, actuator_pk: int, from_seq: int, upto_seq: int) -> TelemetryBatch | None:
    """The first batch in from_seq..upto_seq whose payload the log still holds."""
    return session.scalar(
        select(TelemetryBatch)
        .where(
            TelemetryBatch.actuator_pk == actuator_pk,
            TelemetryBatch.seq >= from_seq,
            TelemetryBatch.seq <= upto_seq,
            TelemetryBatch.payload.is_not(None),
        )
        .order_by(TelemetryBatch.seq)
        .limit(1)
    )


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
