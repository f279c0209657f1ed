"""SQL of the fleet event log: give out ids in commit order, append, read after a cursor."""

from __future__ import annotations

from collections.abc import Collection, Sequence
from typing import Any

from sqlalchemy import func, insert, select, update
from sqlalchemy.dialects import postgresql, sqlite
from sqlalchemy.orm import Session

from app.models import Actuator, Aircraft, EventCounter, FleetEventRow


def stream_owner(session: Session, actuator_pk: int) -> tuple[int, str, str]:
    """(operator id, tail, actuator id) of a stream."""
    row = session.execute(
        select(Aircraft.operator_id, Aircraft.tail, Actuator.actuator_id)
        .join(Actuator, Actuator.aircraft_id == Aircraft.id)
        .where(Actuator.id == actuator_pk)
    ).one()
    return int(row[0]), str(row[1]), str(row[2])


def reserve_ids(session: Session, operator_id: int, n: int) -> int:
    """Take the next ``n`` event ids of the operator; returns the first.

    The counter row stays locked until the transaction ends (PostgreSQL row lock; SQLite
    writers are serialized by ``BEGIN IMMEDIATE``), so a later id never commits before an
    earlier one.
    """
    dialect_insert = (
        sqlite.insert if session.get_bind().dialect.name == "sqlite" else postgresql.insert
    )
    session.execute(
        dialect_insert(EventCounter)
        .values(operator_id=operator_id, last_event_id=0)
        .on_conflict_do_nothing(index_elements=["operator_id"])
    )
    last = session.execute(
        update(EventCounter)
        .where(EventCounter.operator_id == operator_id)
        .values(last_event_id=EventCounter.last_event_id + n)
        .returning(EventCounter.last_event_id)
    ).scalar_one()
    return int(last) - n + 1


def insert_events(session: Session, rows: Sequence[dict[str, Any]]) -> None:
    if rows:
        session.execute(insert(FleetEventRow), list(rows))


def events_after(
    session: Session,
    operator_id: int,
    after: int,
    limit: int,
    *,
    types: Collection[str] | None = None,
    tails: Collection[str] | None = None,
    actuator_id: str | None = None,
) -> list[FleetEventRow]:
    stmt = select(FleetEventRow).where(
        FleetEventRow.operator_id == operator_id, FleetEventRow.event_id > after
    )
    if types is not None:
        stmt = stmt.where(FleetEventRow.type.in_(list(types)))
    if tails is not None:
        stmt = stmt.where(FleetEventRow.tail.in_(list(tails)))
    if actuator_id is not None:
        stmt = stmt.where(FleetEventRow.actuator_id == actuator_id)
    return list(session.scalars(stmt.order_by(FleetEventRow.event_id).limit(limit)))


def last_event_id(session: Session, operator_id: int) -> int:
    """The operator's newest committed event id (0 when none)."""
    found = session.scalar(
        select(func.max(FleetEventRow.event_id)).where(FleetEventRow.operator_id == operator_id)
    )
    return int(found or 0)
