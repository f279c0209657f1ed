"""SQL of aircraft, actuators, their estimators and the fleet board."""

from __future__ import annotations

from dataclasses import dataclass
from datetime import datetime

from sqlalchemy import delete, func, or_, select
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from app.models import (
    Actuator,
    Aircraft,
    EstimatorConfigVersion,
    EstimatorState,
    MaintenanceAction,
    Stream,
)
from app.pagination import Order, after_key, order_by


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


def list_aircraft(
    session: Session, operator_id: int, *, after: int | None, order: Order, limit: int
) -> list[Aircraft]:
    """Live aircraft by registration (id), ``limit`` of them after the id ``after``."""
    stmt = select(Aircraft).where(Aircraft.operator_id == operator_id, Aircraft.deleted_at.is_(None))
    if after is not None:
        stmt = stmt.where(after_key([Aircraft.id], [after], order))
    return list(session.scalars(stmt.order_by(*order_by([Aircraft.id], order)).limit(limit)))


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
            Aircraft.deleted_at.is_(None),
        )
    )
    if lock:
        stmt = stmt.with_for_update(of=Actuator)
    return session.scalar(stmt)


def list_actuators(
    session: Session, aircraft_id: int, *, after: int | None, order: Order, limit: int
) -> list[Actuator]:
    """Live actuators of an aircraft by registration (id)."""
    stmt = select(Actuator).where(Actuator.aircraft_id == aircraft_id, Actuator.deleted_at.is_(None))
    if after is not None:
        stmt = stmt.where(after_key([Actuator.id], [after], order))
    return list(session.scalars(stmt.order_by(*order_by([Actuator.id], order)).limit(limit)))


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
        session.add(
            EstimatorConfigVersion(actuator_pk=actuator.id, estimator=name, version=1, config=cfg, from_seq=1)
        )
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
        .where(
            Aircraft.operator_id == operator_id,
            Aircraft.deleted_at.is_(None),
            or_(Actuator.id.is_(None), Actuator.deleted_at.is_(None)),
        )
        .order_by(Aircraft.tail, Actuator.actuator_id)
    ).all()
    return [BoardRow(*tuple(r)) for r in rows]


# ----------------------------------------------------------------------------- lifecycle
def estimator_rows(session: Session, actuator_pk: int) -> list[EstimatorState]:
    return list(
        session.scalars(
            select(EstimatorState)
            .where(EstimatorState.actuator_pk == actuator_pk)
            .order_by(EstimatorState.estimator)
        )
    )


def lock_stream(session: Session, actuator_pk: int) -> Stream:
    """The stream row, locked until the transaction ends: the processor applies no batch of it
    meanwhile (PostgreSQL ``FOR UPDATE``, waiting for an apply in progress; SQLite writers are
    serialized by ``BEGIN IMMEDIATE``)."""
    row = session.scalar(select(Stream).where(Stream.actuator_pk == actuator_pk).with_for_update())
    if row is None:  # created with its actuator, in the same transaction
        raise LookupError(f"actuator {actuator_pk} has no stream row")
    return row


def live_actuators_of(session: Session, aircraft_id: int) -> list[Actuator]:
    return list(
        session.scalars(
            select(Actuator).where(Actuator.aircraft_id == aircraft_id, Actuator.deleted_at.is_(None))
        )
    )


def add(session: Session, row: EstimatorConfigVersion | MaintenanceAction) -> None:
    session.add(row)
    session.flush()


def config_versions(
    session: Session,
    actuator_pk: int,
    estimator: str | None,
    *,
    after: int | None,
    order: Order,
    limit: int,
) -> list[EstimatorConfigVersion]:
    stmt = select(EstimatorConfigVersion).where(EstimatorConfigVersion.actuator_pk == actuator_pk)
    if estimator is not None:
        stmt = stmt.where(EstimatorConfigVersion.estimator == estimator)
    if after is not None:
        stmt = stmt.where(after_key([EstimatorConfigVersion.id], [after], order))
    return list(session.scalars(stmt.order_by(*order_by([EstimatorConfigVersion.id], order)).limit(limit)))


def maintenance_actions(
    session: Session, actuator_pk: int, *, after: int | None, order: Order, limit: int
) -> list[MaintenanceAction]:
    stmt = select(MaintenanceAction).where(MaintenanceAction.actuator_pk == actuator_pk)
    if after is not None:
        stmt = stmt.where(after_key([MaintenanceAction.id], [after], order))
    return list(session.scalars(stmt.order_by(*order_by([MaintenanceAction.id], order)).limit(limit)))


def last_baseline(session: Session, actuator_pk: int) -> int:
    """The highest baseline number any maintenance action started (1: none)."""
    n = session.scalar(
        select(func.max(MaintenanceAction.baseline)).where(MaintenanceAction.actuator_pk == actuator_pk)
    )
    return int(n) if n is not None else 1


def baseline_start(session: Session, actuator_pk: int, baseline: int) -> int:
    """The first batch (seq) of a baseline."""
    if baseline <= 1:
        return 1
    seq = session.scalar(
        select(MaintenanceAction.from_seq).where(
            MaintenanceAction.actuator_pk == actuator_pk,
            MaintenanceAction.baseline == baseline,
            MaintenanceAction.from_seq.is_not(None),
        )
    )
    return int(seq) if seq is not None else 1


def purge_deleted(session: Session, before: datetime) -> tuple[int, int]:
    """Delete, with everything they own, aircraft and actuators soft-deleted before ``before``:
    (aircraft, actuators) removed. The foreign keys cascade to streams, estimators, the log
    and every output table."""
    acts = session.execute(
        delete(Actuator).where(Actuator.deleted_at.is_not(None), Actuator.deleted_at < before)
    )
    acs = session.execute(
        delete(Aircraft).where(Aircraft.deleted_at.is_not(None), Aircraft.deleted_at < before)
    )
    return int(getattr(acs, "rowcount", 0) or 0), int(getattr(acts, "rowcount", 0) or 0)
