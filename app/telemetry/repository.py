"""SQL of the telemetry log."""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from datetime import datetime
from typing import cast

from sqlalchemy import Table, bindparam, insert, select, text, update
from sqlalchemy.orm import Session

from app.models import Actuator, TelemetryBatch

_BATCHES = cast(Table, TelemetryBatch.__table__)
_ACTUATORS = cast(Table, Actuator.__table__)


@dataclass
class LogHead:
    """Where an actuator's log stands: the columns of its row the log writer locks and advances."""

    actuator_pk: int
    last_logged_seq: int
    last_logged_t_s: float | None
    last_client_seq: int | None


@dataclass(frozen=True)
class LoggedBatch:
    """What the log keeps of a batch to recognize and answer a retry of it."""

    seq: int
    batch_id: str
    content_hash: str
    n_samples: int
    t_first_s: float
    t_last_s: float
    received_at: datetime
    end_of_run: bool


# The log writer's SQL: Core statements built once (only their parameters change), on the
# session's connection, one of each per group whatever the number of appends (no ORM unit of
# work, no statement construction per call).
_A, _B = _ACTUATORS.c, _BATCHES.c
_LOCK_HEADS = (
    select(_A.id, _A.last_logged_seq, _A.last_logged_t_s, _A.last_client_seq, _A.deleted_at)
    .where(_A.id.in_(bindparam("pks", expanding=True)))
    .order_by(_A.id)
    .with_for_update()
)
_LOGGED_BY_IDS = select(
    _B.actuator_pk, _B.seq, _B.batch_id, _B.content_hash, _B.n_samples, _B.t_first_s, _B.t_last_s,
    _B.received_at, _B.end_of_run,
).where(_B.actuator_pk.in_(bindparam("pks", expanding=True)), _B.batch_id.in_(bindparam("ids", expanding=True)))
_INSERT_BATCHES = insert(_BATCHES)
_ADVANCE_HEADS = (
    update(_ACTUATORS)
    .where(_A.id == bindparam("pk"))
    .values(last_logged_seq=bindparam("seq"), last_logged_t_s=bindparam("t_s"),
            last_client_seq=bindparam("client_seq"))
)


def lock_log_heads(session: Session, actuator_pks: Sequence[int]) -> dict[int, LogHead]:
    """The log heads of the live (not deleted) actuators among ``actuator_pks``, their rows
    locked for this transaction in primary-key order (two writers that lock overlapping sets in
    the same order cannot deadlock; SQLite: ``BEGIN IMMEDIATE`` serializes writers already)."""
    if not actuator_pks:
        return {}
    rows = session.connection().execute(_LOCK_HEADS, {"pks": sorted(actuator_pks)})
    return {r.id: LogHead(r.id, r.last_logged_seq, r.last_logged_t_s, r.last_client_seq)
            for r in rows if r.deleted_at is None}


def logged_by_ids(session: Session, keys: Sequence[tuple[int, str]]) -> dict[tuple[int, str], LoggedBatch]:
    """The logged batches among ``(actuator_pk, batch_id)`` keys."""
    if not keys:
        return {}
    rows = session.connection().execute(
        _LOGGED_BY_IDS, {"pks": sorted({pk for pk, _ in keys}), "ids": sorted({b for _, b in keys})}
    )
    wanted = set(keys)
    return {
        (r.actuator_pk, r.batch_id): LoggedBatch(r.seq, r.batch_id, r.content_hash, r.n_samples, r.t_first_s,
                                                 r.t_last_s, r.received_at, r.end_of_run)
        for r in rows if (r.actuator_pk, r.batch_id) in wanted
    }


def insert_batches(session: Session, rows: Sequence[dict[str, object]]) -> None:
    """Insert log rows (one executemany). A taken batch id or seq raises ``IntegrityError``:
    it cannot happen while every append holds its actuator's row lock."""
    if rows:
        session.connection().execute(_INSERT_BATCHES, list(rows))


def advance_heads(session: Session, heads: Sequence[LogHead]) -> None:
    """Write the advanced log heads back to their (locked) actuator rows."""
    if heads:
        session.connection().execute(
            _ADVANCE_HEADS,
            [{"pk": h.actuator_pk, "seq": h.last_logged_seq, "t_s": h.last_logged_t_s,
              "client_seq": h.last_client_seq} for h in heads],
        )


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


def notify(session: Session, channel: str, payload: str) -> None:
    """PostgreSQL ``NOTIFY``, delivered when (and only if) this transaction commits."""
    session.execute(text("SELECT pg_notify(:channel, :payload)"), {"channel": channel, "payload": payload})
