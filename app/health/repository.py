"""SQL of the read side: streams, estimators, health windows, outputs, events, RUL."""

from __future__ import annotations

from collections.abc import Iterator

from sqlalchemy import select
from sqlalchemy.orm import Session

from app.models import (
    EstimatorEventRow,
    EstimatorState,
    HealthWindowRow,
    RulEstimateRow,
    SampleOutputRow,
    Stream,
    TelemetryBatch,
)


def stream(session: Session, actuator_pk: int) -> Stream:
    row = session.get(Stream, actuator_pk)
    if row is None:  # created with its actuator, in the same transaction
        raise LookupError(f"actuator {actuator_pk} has no stream row")
    return row


def estimators(session: Session, actuator_pk: int) -> list[EstimatorState]:
    return list(
        session.scalars(
            select(EstimatorState)
            .where(EstimatorState.actuator_pk == actuator_pk)
            .order_by(EstimatorState.estimator)
        )
    )


def has_estimator(session: Session, actuator_pk: int, estimator: str) -> bool:
    return session.get(EstimatorState, (actuator_pk, estimator)) is not None


def latest_window(session: Session, actuator_pk: int, estimator: str) -> HealthWindowRow | None:
    return session.scalar(
        select(HealthWindowRow)
        .where(HealthWindowRow.actuator_pk == actuator_pk, HealthWindowRow.estimator == estimator)
        .order_by(HealthWindowRow.t_end_s.desc())
        .limit(1)
    )


def windows(
    session: Session,
    actuator_pk: int,
    estimator: str | None,
    from_s: float | None,
    to_s: float | None,
    limit: int | None,
) -> list[HealthWindowRow]:
    """Windows whose span meets [from_s, to_s], oldest first (at most ``limit``; None: all)."""
    stmt = select(HealthWindowRow).where(HealthWindowRow.actuator_pk == actuator_pk)
    if estimator is not None:
        stmt = stmt.where(HealthWindowRow.estimator == estimator)
    if from_s is not None:
        stmt = stmt.where(HealthWindowRow.t_end_s >= from_s)
    if to_s is not None:
        stmt = stmt.where(HealthWindowRow.t_start_s <= to_s)
    stmt = stmt.order_by(HealthWindowRow.t_end_s, HealthWindowRow.estimator)
    return list(session.scalars(stmt if limit is None else stmt.limit(limit)))


def sample_outputs(
    session: Session, actuator_pk: int, estimator: str, from_s: float | None, to_s: float | None
) -> Iterator[SampleOutputRow]:
    """Output blocks that meet [from_s, to_s], in stream order (read lazily)."""
    stmt = select(SampleOutputRow).where(
        SampleOutputRow.actuator_pk == actuator_pk, SampleOutputRow.estimator == estimator
    )
    if from_s is not None:
        stmt = stmt.where(SampleOutputRow.t_last_s >= from_s)
    if to_s is not None:
        stmt = stmt.where(SampleOutputRow.t_first_s <= to_s)
    return iter(session.scalars(stmt.order_by(SampleOutputRow.seq)))


def events(
    session: Session, actuator_pk: int, from_s: float | None, to_s: float | None, limit: int
) -> list[EstimatorEventRow]:
    stmt = select(EstimatorEventRow).where(EstimatorEventRow.actuator_pk == actuator_pk)
    if from_s is not None:
        stmt = stmt.where(EstimatorEventRow.t_s >= from_s)
    if to_s is not None:
        stmt = stmt.where(EstimatorEventRow.t_s <= to_s)
    return list(session.scalars(stmt.order_by(EstimatorEventRow.t_s, EstimatorEventRow.id).limit(limit)))


def latest_rul(session: Session, actuator_pk: int, estimator: str) -> RulEstimateRow | None:
    return session.scalar(
        select(RulEstimateRow)
        .where(RulEstimateRow.actuator_pk == actuator_pk, RulEstimateRow.estimator == estimator)
        .order_by(RulEstimateRow.t_s.desc())
        .limit(1)
    )


def ruls(
    session: Session,
    actuator_pk: int,
    estimator: str | None,
    from_s: float | None,
    to_s: float | None,
    limit: int,
) -> list[RulEstimateRow]:
    stmt = select(RulEstimateRow).where(RulEstimateRow.actuator_pk == actuator_pk)
    if estimator is not None:
        stmt = stmt.where(RulEstimateRow.estimator == estimator)
    if from_s is not None:
        stmt = stmt.where(RulEstimateRow.t_s >= from_s)
    if to_s is not None:
        stmt = stmt.where(RulEstimateRow.t_s <= to_s)
    return list(session.scalars(stmt.order_by(RulEstimateRow.t_s, RulEstimateRow.id).limit(limit)))


def telemetry_batches(
    session: Session, actuator_pk: int, from_s: float | None, to_s: float | None
) -> Iterator[TelemetryBatch]:
    """Logged batches still holding their samples that meet [from_s, to_s], in stream order."""
    stmt = select(TelemetryBatch).where(
        TelemetryBatch.actuator_pk == actuator_pk, TelemetryBatch.payload.is_not(None)
    )
    if from_s is not None:
        stmt = stmt.where(TelemetryBatch.t_last_s >= from_s)
    if to_s is not None:
        stmt = stmt.where(TelemetryBatch.t_first_s <= to_s)
    return iter(session.scalars(stmt.order_by(TelemetryBatch.seq)))
