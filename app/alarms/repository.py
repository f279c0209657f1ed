"""SQL of alarms: the open alarms of an actuator (locked), one alarm, lists and counts."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from sqlalchemy import func, select
from sqlalchemy.orm import Session

from app.models import Actuator, Aircraft, AlarmRow, ApiKey

OPEN_STATUSES = ("active", "acknowledged")


@dataclass(frozen=True)
class AlarmFilter:
    status: str | None = None  # active, acknowledged, cleared, or "open" (the first two)
    severity: str | None = None
    tail: str | None = None
    actuator_id: str | None = None
    cause: str | None = None


def open_alarms(session: Session, actuator_pk: int) -> list[AlarmRow]:
    """The actuator's open alarms, locked for this transaction (PostgreSQL ``FOR UPDATE``;
    SQLite writers are serialized)."""
    return list(
        session.scalars(
            select(AlarmRow)
            .where(AlarmRow.actuator_pk == actuator_pk, AlarmRow.status.in_(OPEN_STATUSES))
            .order_by(AlarmRow.id)
            .with_for_update()
        )
    )


def add_alarm(session: Session, row: AlarmRow) -> AlarmRow:
    session.add(row)
    session.flush()
    return row


def _named() -> Any:  # a Select of (AlarmRow, tail, actuator id)
    return (
        select(AlarmRow, Aircraft.tail, Actuator.actuator_id)
        .join(Actuator, Actuator.id == AlarmRow.actuator_pk)
        .join(Aircraft, Aircraft.id == Actuator.aircraft_id)
    )


def alarm_of(
    session: Session, operator_id: int, alarm_id: int, *, lock: bool = False
) -> tuple[AlarmRow, str, str] | None:
    """The operator's alarm with its tail and actuator id (None for another operator's)."""
    stmt = _named().where(AlarmRow.id == alarm_id, AlarmRow.operator_id == operator_id)
    if lock:
        stmt = stmt.with_for_update(of=AlarmRow)
    row = session.execute(stmt).first()
    return None if row is None else (row[0], str(row[1]), str(row[2]))


def _filtered(stmt: Any, operator_id: int, f: AlarmFilter, *, with_status: bool) -> Any:
    stmt = stmt.where(AlarmRow.operator_id == operator_id)
    if with_status and f.status is not None:
        if f.status == "open":
            stmt = stmt.where(AlarmRow.status.in_(OPEN_STATUSES))
        else:
            stmt = stmt.where(AlarmRow.status == f.status)
    if f.severity is not None:
        stmt = stmt.where(AlarmRow.severity == f.severity)
    if f.tail is not None:
        stmt = stmt.where(Aircraft.tail == f.tail)
    if f.actuator_id is not None:
        stmt = stmt.where(Actuator.actuator_id == f.actuator_id)
    if f.cause is not None:
        stmt = stmt.where(AlarmRow.cause == f.cause)
    return stmt


def list_alarms(
    session: Session, operator_id: int, f: AlarmFilter, before: int | None, limit: int
) -> list[tuple[AlarmRow, str, str]]:
    """Newest first, ids below ``before`` (the cursor) when given."""
    stmt = _filtered(_named(), operator_id, f, with_status=True)
    if before is not None:
        stmt = stmt.where(AlarmRow.id < before)
    rows = session.execute(stmt.order_by(AlarmRow.id.desc()).limit(limit))
    return [(r[0], str(r[1]), str(r[2])) for r in rows]


def counts(session: Session, operator_id: int, f: AlarmFilter) -> list[tuple[str, str, int]]:
    """(status, severity, count) of the alarms matching every filter but the status."""
    base = (
        select(AlarmRow.status, AlarmRow.severity, func.count())
        .join(Actuator, Actuator.id == AlarmRow.actuator_pk)
        .join(Aircraft, Aircraft.id == Actuator.aircraft_id)
    )
    stmt = _filtered(base, operator_id, f, with_status=False)
    rows = session.execute(stmt.group_by(AlarmRow.status, AlarmRow.severity))
    return [(str(s), str(v), int(n)) for s, v, n in rows]


def open_counts(session: Session, actuator_pks: Sequence[int]) -> dict[int, int]:
    if not actuator_pks:
        return {}
    rows = session.execute(
        select(AlarmRow.actuator_pk, func.count())
        .where(AlarmRow.actuator_pk.in_(list(actuator_pks)), AlarmRow.status.in_(OPEN_STATUSES))
        .group_by(AlarmRow.actuator_pk)
    )
    return {int(pk): int(n) for pk, n in rows}


def key_label(session: Session, key_id: int) -> str:
    """How an API key is named in an alarm's history: its name, else its shown prefix."""
    key = session.get(ApiKey, key_id)
    if key is None:
        return f"key {key_id}"
    return key.name or key.prefix
