"""SQL of the processor: claim a stream, load its pending batches and estimators, store what
applying them produced, mark a stream failed, and read applied results back."""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from datetime import UTC, datetime
from typing import Any

from sqlalchemy import delete, func, insert, select, text, update
from sqlalchemy.orm import Session

from app.models import (
    Actuator,
    Aircraft,
    EstimatorEventRow,
    EstimatorState,
    HealthWindowRow,
    Operator,
    RulEstimateRow,
    SampleOutputRow,
    Stream,
    TelemetryBatch,
    utcnow,
)
from app.processing.orchestration import Rows

OUTPUT_MODELS: tuple[Any, ...] = (HealthWindowRow, SampleOutputRow, EstimatorEventRow, RulEstimateRow)


def claim(session: Session, actuator_pk: int, *, is_sqlite: bool) -> Stream | None:
    """Lock the stream for this transaction. None when another worker holds it (PostgreSQL:
    ``FOR UPDATE SKIP LOCKED``; on SQLite ``BEGIN IMMEDIATE`` already serializes writers)."""
    stmt = select(Stream).where(Stream.actuator_pk == actuator_pk)
    if not is_sqlite:
        stmt = stmt.with_for_update(skip_locked=True)
    return session.scalar(stmt)


def pending_batches(
    session: Session, stream: Stream, *, max_samples: int, max_batches: int
) -> tuple[list[TelemetryBatch], bool]:
    """The next logged batches after the applied mark, without a gap (a seq not committed yet
    ends the run), up to ``max_samples`` samples (at least one batch) and ``max_batches``; and
    whether more contiguous batches follow them (a limit stopped the run)."""
    pending: list[TelemetryBatch] = []
    total = 0
    for row in session.scalars(
        select(TelemetryBatch)
        .where(TelemetryBatch.actuator_pk == stream.actuator_pk, TelemetryBatch.seq > stream.last_applied_seq)
        .order_by(TelemetryBatch.seq)
        .limit(max_batches + 1)
    ):
        if row.seq != stream.last_applied_seq + len(pending) + 1:
            break
        if len(pending) == max_batches or (pending and total + row.n_samples > max_samples):
            return pending, True
        pending.append(row)
        total += row.n_samples
    return pending, False


def streams_pending(session: Session, actuator_pks: Sequence[int]) -> list[int]:
    """Those of the streams with logged batches not applied yet (and not failed)."""
    if not actuator_pks:
        return []
    return list(
        session.scalars(
            select(Actuator.id)
            .join(Stream, Stream.actuator_pk == Actuator.id)
            .where(
                Actuator.id.in_(actuator_pks),
                Actuator.last_logged_seq > Stream.last_applied_seq,
                Stream.failure.is_(None),
            )
        )
    )


def notify(session: Session, channel: str, payload: str) -> None:
    """PostgreSQL ``NOTIFY``, delivered when (and only if) this transaction commits."""
    session.execute(text("SELECT pg_notify(:channel, :payload)"), {"channel": channel, "payload": payload})


def notification_scope(session: Session) -> str:
    """The database and schema this session works in (notification channels are per database,
    not per schema: two schemas on one server must not hear each other)."""
    return str(session.execute(text("SELECT current_database() || '.' || current_schema()")).scalar_one())


def listen(connection: Any, channels: Sequence[str]) -> None:
    """``LISTEN`` on a raw psycopg connection in autocommit mode."""
    for ch in channels:
        connection.execute(f'LISTEN "{ch}"')


def estimators(session: Session, actuator_pk: int) -> list[EstimatorState]:
    return list(
        session.scalars(
            select(EstimatorState)
            .where(EstimatorState.actuator_pk == actuator_pk)
            .order_by(EstimatorState.estimator)
        )
    )


def insert_rows(session: Session, rows: Rows) -> None:
    for items, model in zip(
        (rows.health, rows.outputs, rows.events, rows.rul), OUTPUT_MODELS, strict=True
    ):
        if items:
            session.execute(insert(model), items)


def delete_outputs(session: Session, actuator_pk: int, estimator: str, baseline: int | None = None) -> None:
    """Forget everything one estimator of a stream produced (before it replays the stream), or
    only what it produced in one baseline."""
    for model in OUTPUT_MODELS:
        stmt = delete(model).where(model.actuator_pk == actuator_pk, model.estimator == estimator)
        if baseline is not None:
            stmt = stmt.where(model.baseline == baseline)
        session.execute(stmt)


def log_holds_from_first(session: Session, actuator_pk: int, upto_seq: int, first_seq: int = 1) -> bool:
    """Whether the log still holds the payload of every batch first_seq..upto_seq (retention
    may have dropped the oldest)."""
    if upto_seq < first_seq:
        return True
    kept = session.scalar(
        select(func.count())
        .select_from(TelemetryBatch)
        .where(
            TelemetryBatch.actuator_pk == actuator_pk,
            TelemetryBatch.seq >= first_seq,
            TelemetryBatch.seq <= upto_seq,
            TelemetryBatch.payload.is_not(None),
        )
    )
    return int(kept or 0) == upto_seq - first_seq + 1


def logged_batches(
    session: Session, actuator_pk: int, upto_seq: int, chunk: int, first_seq: int = 1
) -> Iterator[list[TelemetryBatch]]:
    """Batches first_seq..upto_seq in stream order, ``chunk`` at a time (memory stays bounded)."""
    after = first_seq - 1
    while after < upto_seq:
        part = list(
            session.scalars(
                select(TelemetryBatch)
                .where(
                    TelemetryBatch.actuator_pk == actuator_pk,
                    TelemetryBatch.seq > after,
                    TelemetryBatch.seq <= upto_seq,
                )
                .order_by(TelemetryBatch.seq)
                .limit(chunk)
            )
        )
        if not part:
            return
        yield part
        after = part[-1].seq
        for row in part:
            session.expunge(row)  # let the payloads go


FAILURE_MAX_CHARS = 2000  # the column's length


def mark_failed(session: Session, actuator_pk: int, reason: str) -> None:
    session.execute(
        update(Stream)
        .where(Stream.actuator_pk == actuator_pk)
        .values(status="failed", failure=reason[:FAILURE_MAX_CHARS], updated_at=utcnow())
    )


def applied_mark(session: Session, actuator_pk: int) -> tuple[int, str | None]:
    """The stream's last applied seq and, when it is failed, why."""
    row = session.execute(
        select(Stream.last_applied_seq, Stream.failure).where(Stream.actuator_pk == actuator_pk)
    ).first()
    return (0, None) if row is None else (int(row[0]), row[1])


def pending_streams(session: Session) -> list[int]:
    """Streams with logged batches not applied yet, except failed ones (they wait for an
    operator: retrying them forever would only repeat the failure)."""
    return list(
        session.scalars(
            select(Actuator.id)
            .join(Stream, Stream.actuator_pk == Actuator.id)
            .where(Actuator.last_logged_seq > Stream.last_applied_seq, Stream.failure.is_(None))
        )
    )


def count_failed(session: Session) -> int:
    return int(
        session.scalar(select(func.count()).select_from(Stream).where(Stream.failure.is_not(None))) or 0
    )


def drop_applied_payloads(session: Session, older_than_s: float) -> int:
    """Retention: forget raw payloads of batches applied more than ``older_than_s`` ago."""
    cutoff = datetime.fromtimestamp(utcnow().timestamp() - older_than_s, UTC)
    res = session.execute(
        update(TelemetryBatch)
        .where(
            TelemetryBatch.applied_at.is_not(None),
            TelemetryBatch.applied_at < cutoff,
            TelemetryBatch.payload.is_not(None),
        )
        .values(payload=None)
    )
    return int(getattr(res, "rowcount", 0) or 0)


def drop_old_sample_outputs(session: Session, keep_s: float) -> int:
    """Retention: forget the per-sample outputs that end more than ``keep_s`` seconds of stream
    time before the stream's last applied sample (health windows, events and RUL are kept)."""
    newest = (
        select(Stream.last_applied_t_s)
        .where(Stream.actuator_pk == SampleOutputRow.actuator_pk)
        .scalar_subquery()
    )
    res = session.execute(delete(SampleOutputRow).where(SampleOutputRow.t_last_s < newest - keep_s))
    return int(getattr(res, "rowcount", 0) or 0)


def stream_owner(session: Session, actuator_pk: int) -> tuple[int, str, str]:
    """(operator id, tail, actuator id) of a stream."""
    row = session.execute(
        select(Aircraft.operator_id, Aircraft.tail, Actuator.actuator_id)
        .join(Actuator, Actuator.aircraft_id == Aircraft.id)
        .where(Actuator.id == actuator_pk)
    ).one()
    return int(row[0]), str(row[1]), str(row[2])


# ----------------------------------------------------------------------------- read-back
def batches_by_seq(session: Session, actuator_pk: int, seqs: Sequence[int]) -> dict[int, TelemetryBatch]:
    lo, hi = min(seqs), max(seqs)
    wanted = set(seqs)
    return {
        b.seq: b
        for b in session.scalars(
            select(TelemetryBatch).where(
                TelemetryBatch.actuator_pk == actuator_pk, TelemetryBatch.seq.between(lo, hi)
            )
        )
        if b.seq in wanted
    }


def outputs_by_seq(
    session: Session, model: Any, actuator_pk: int, lo: int, hi: int
) -> dict[tuple[int, str], list[Any]]:
    """Rows of one output table for seqs lo..hi, keyed by (seq, estimator), in insert order."""
    out: dict[tuple[int, str], list[Any]] = {}
    for r in session.scalars(
        select(model).where(model.actuator_pk == actuator_pk, model.seq.between(lo, hi)).order_by(model.id)
    ):
        out.setdefault((r.seq, r.estimator), []).append(r)
    return out


def failed_streams(session: Session) -> list[tuple[str, str, str, str]]:
    """(operator, tail, actuator id, reason) of every stream marked failed."""
    rows = session.execute(
        select(Operator.name, Aircraft.tail, Actuator.actuator_id, Stream.failure)
        .join(Aircraft, Aircraft.operator_id == Operator.id)
        .join(Actuator, Actuator.aircraft_id == Aircraft.id)
        .join(Stream, Stream.actuator_pk == Actuator.id)
        .where(Stream.failure.is_not(None))
        .order_by(Operator.name, Aircraft.tail, Actuator.actuator_id)
    )
    return [(str(o), str(t), str(a), str(f)) for o, t, a, f in rows]


def clear_failure(session: Session, actuator_pk: int, status: str) -> bool:
    """Clear a stream's failed mark; False when it was not marked."""
    res = session.execute(
        update(Stream)
        .where(Stream.actuator_pk == actuator_pk, Stream.failure.is_not(None))
        .values(failure=None, status=status, updated_at=utcnow())
    )
    return bool(getattr(res, "rowcount", 0))
