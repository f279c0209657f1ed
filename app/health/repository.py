"""SQL of the read side: streams, estimators, health windows, outputs, events, RUL."""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from typing import Any

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
from app.pagination import Order, after_key, order_by


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


def latest_window(session: Session, actuator_pk: int, estimator: str, baseline: int) -> HealthWindowRow | None:
    """The estimator's latest window in ``baseline`` (a replaced part's windows are history)."""
    return session.scalar(
        select(HealthWindowRow)
        .where(
            HealthWindowRow.actuator_pk == actuator_pk,
            HealthWindowRow.estimator == estimator,
            HealthWindowRow.baseline == baseline,
        )
        .order_by(HealthWindowRow.t_end_s.desc())
        .limit(1)
    )


def _page(stmt: Any, cols: Sequence[Any], after: Sequence[Any] | None, order: Order, limit: int | None) -> Any:
    if after is not None:
        stmt = stmt.where(after_key(cols, after, order))
    stmt = stmt.order_by(*order_by(cols, order))
    return stmt if limit is None else stmt.limit(limit)


def windows(
    session: Session,
    actuator_pk: int,
    estimator: str | None,
    from_s: float | None,
    to_s: float | None,
    *,
    after: Sequence[Any] | None = None,
    order: Order = "asc",
    limit: int | None,
) -> list[HealthWindowRow]:
    """Windows whose span meets [from_s, to_s], by (t_end_s, id) in ``order``, after ``after``
    (at most ``limit``; None: all)."""
    stmt = select(HealthWindowRow).where(HealthWindowRow.actuator_pk == actuator_pk)
    if estimator is not None:
        stmt = stmt.where(HealthWindowRow.estimator == estimator)
    if from_s is not None:
        stmt = stmt.where(HealthWindowRow.t_end_s >= from_s)
    if to_s is not None:
        stmt = stmt.where(HealthWindowRow.t_start_s <= to_s)
    return list(session.scalars(_page(stmt, [HealthWindowRow.t_end_s, HealthWindowRow.id], after, order, limit)))


def sample_outputs(
    session: Session,
    actuator_pk: int,
    estimator: str,
    from_s: float | None,
    to_s: float | None,
    order: Order = "asc",
) -> Iterator[SampleOutputRow]:
    """Output blocks that meet [from_s, to_s], in stream order or its reverse, read a few at
    a time (each block's payload is let go once the caller moves on)."""
    stmt = select(SampleOutputRow).where(
        SampleOutputRow.actuator_pk == actuator_pk, SampleOutputRow.estimator == estimator
    )
    if from_s is not None:
        stmt = stmt.where(SampleOutputRow.t_last_s >= from_s)
    if to_s is not None:
        stmt = stmt.where(SampleOutputRow.t_first_s <= to_s)
    stmt = stmt.order_by(*order_by([SampleOutputRow.seq], order)).execution_options(yield_per=16)
    for row in session.scalars(stmt):
        yield row
        session.expunge(row)


def events(
    session: Session,
    actuator_pk: int,
    from_s: float | None,
    to_s: float | None,
    *,
    after: Sequence[Any] | None,
    order: Order,
    limit: int,
) -> list[EstimatorEventRow]:
    stmt = select(EstimatorEventRow).where(EstimatorEventRow.actuator_pk == actuator_pk)
    if from_s is not None:
        stmt = stmt.where(EstimatorEventRow.t_s >= from_s)
    if to_s is not None:
        stmt = stmt.where(EstimatorEventRow.t_s <= to_s)
    return list(session.scalars(_page(stmt, [EstimatorEventRow.t_s, EstimatorEventRow.id], after, order, limit)))


def latest_rul(session: Session, actuator_pk: int, estimator: str, baseline: int) -> RulEstimateRow | None:
    """The estimator's latest prognosis in ``baseline``."""
    return session.scalar(
        select(RulEstimateRow)
        .where(
            RulEstimateRow.actuator_pk == actuator_pk,
            RulEstimateRow.estimator == estimator,
            RulEstimateRow.baseline == baseline,
        )
        .order_by(RulEstimateRow.t_s.desc())
        .limit(1)
    )


def ruls(
    session: Session,
    actuator_pk: int,
    estimator: str | None,
    from_s: float | None,
    to_s: float | None,
    *,
    after: Sequence[Any] | None,
    order: Order,
    limit: int,
) -> list[RulEstimateRow]:
    stmt = select(RulEstimateRow).where(RulEstimateRow.actuator_pk == actuator_pk)
    if estimator is not None:
        stmt = stmt.where(RulEstimateRow.estimator == estimator)
    if from_s is not None:
        stmt = stmt.where(RulEstimateRow.t_s >= from_s)
    if to_s is not None:
        stmt = stmt.where(RulEstimateRow.t_s <= to_s)
    return list(session.scalars(_page(stmt, [RulEstimateRow.t_s, RulEstimateRow.id], after, order, limit)))


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
