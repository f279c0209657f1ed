"""SQL of aircraft, actuators, their estimators and the fleet board."""

from __future__ import annotations

from dataclasses import dataclass
from datetime import datetime

from sqlalchemy import select
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from app.models import Actuator, Aircraft, EstimatorState, Stream


def aircraft_by_tail(session: Session, operator_id: int, tail: str) -> Aircraft | None:
    return session.scalar(
        select(Aircraft).where(Aircraft.operator_id == operator_id, Aircraft.tail == tail)
    )


def add_aircraft(session: Session, aircraft: Aircraft) -> bool:
    """Insert ``aircraft``; False when its tail exists already (nothing inserted)."""
    try:
        with session.begin_nested():
            session.add(aircraft)
            session.flush()
    except IntegrityError:
        return False
    return True


def list_aircraft(session: Session, operator_id: int) -> list[Aircraft]:
    return list(
        session.scalars(
            select(Aircraft).where(Aircraft.operator_id == operator_id).order_by(Aircraft.tail)
        )
    )


def actuator_of(
    session: Session, operator_id: int, tail: str, actuator_id: str, *, lock: bool = False
) -> Actuator | None:
    """The actuator, optionally locked (``FOR UPDATE`` on PostgreSQL; SQLite writers are
    serialized by ``BEGIN IMMEDIATE``)."""
    stmt = (
        select(Actuator)
        .join(Aircraft, Aircraft.id == Actuator.aircraft_id)
        .where(
            Aircraft.operator_id == operator_id,
            Aircraft.tail == tail,
            Actuator.actuator_id == actuator_id,
        )
    )
    if lock:
        stmt = stmt.with_for_update(of=Actuator)
    return session.scalar(stmt)


def list_actuators(session: Session, aircraft_id: int) -> list[Actuator]:
    return list(
        session.scalars(
            select(Actuator).where(Actuator.aircraft_id == aircraft_id).order_by(Actuator.actuator_id)
        )
    )


def add_actuator(
    session: Session, actuator: Actuator, configs: dict[str, dict[str, object]]
) -> bool:
    """Insert the actuator, its stream and its estimators; False when the actuator id exists."""
    try:
        with session.begin_nested():
            session.add(actuator)
            session.flush()
    except IntegrityError:
        return False
    session.add(Stream(actuator_pk=actuator.id))
    for name, cfg in configs.items():
        session.add(EstimatorState(actuator_pk=actuator.id, estimator=name, config=cfg, reasons=[]))
    session.flush()
    return True


def estimator_configs(session: Session, actuator_pk: int) -> dict[str, dict[str, object]]:
    rows = session.scalars(
        select(EstimatorState)
        .where(EstimatorState.actuator_pk == actuator_pk)
        .order_by(EstimatorState.estimator)
    )
    return {r.estimator: r.config for r in rows}


@dataclass(frozen=True)
class BoardRow:
    """One actuator of the fleet board (or an aircraft without actuators: ``actuator_pk`` None)."""

    tail: str
    actuator_pk: int | None
    actuator_id: str | None
    kind: str | None
    last_logged_seq: int | None
    status: str | None
    failure: str | None
    last_applied_seq: int | None
    t_last_s: float | None
    updated_at: datetime | None
    rul_q05_s: float | None
    rul_q50_s: float | None
    rul_t_s: float | None


def board_rows(session: Session, operator_id: int) -> list[BoardRow]:
    rows = session.execute(
        select(
            Aircraft.tail,
            Actuator.id,
            Actuator.actuator_id,
            Actuator.kind,
            Actuator.last_logged_seq,
            Stream.status,
            Stream.failure,
            Stream.last_applied_seq,
            Stream.last_applied_t_s,
            Stream.updated_at,
            Stream.rul_q05_s,
            Stream.rul_q50_s,
            Stream.rul_t_s,
        )
        .join(Actuator, Actuator.aircraft_id == Aircraft.id, isouter=True)
        .join(Stream, Stream.actuator_pk == Actuator.id, isouter=True)
        .where(Aircraft.operator_id == operator_id)
        .order_by(Aircraft.tail, Actuator.actuator_id)
    ).all()
    return [BoardRow(*tuple(r)) for r in rows]
