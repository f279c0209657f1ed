"""SQL of the processor: claim a stream, load its pending batches and estimators, store what
applying them produced, mark a stream failed, and read applied results back."""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass, fields
from datetime import UTC, datetime
from typing import Any, TypeVar, cast

from sqlalchemy import Table, bindparam, delete, func, insert, select, text, update
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

_R = TypeVar("_R")

OUTPUT_MODELS: tuple[Any, ...] = (HealthWindowRow, SampleOutputRow, EstimatorEventRow, RulEstimateRow)


@dataclass(frozen=True)
class PendingBatch:
    """A logged batch not applied yet, without its payload (read only when the batch is not
    already decoded in memory, :class:`~app.processing.recent.RecentBatches`)."""

    actuator_pk: int
    seq: int
    batch_id: str
    n_samples: int
    t_first_s: float
    t_last_s: float
    end_of_run: bool


@dataclass
class StreamRow:
    """The columns of a stream's row that an apply reads and writes (read and written with Core
    statements: the ORM's loading, identity map and flush were a third of a small apply)."""

    actuator_pk: int
    last_applied_seq: int
    last_applied_t_s: float | None
    status: str
    failure: str | None
    rul_t_s: float | None
    rul_q05_s: float | None
    rul_q50_s: float | None
    updated_at: datetime | None = None

    def copy(self) -> StreamRow:
        """A shallow copy (the row as read, kept to compare with the store's later)."""
        return _shallow_copy(self)


@dataclass
class EstimatorRow:
    """An estimator row of a stream as an apply reads and writes it (attribute names as on
    :class:`~app.models.EstimatorState`, so that the fleet's baseline rules apply to either)."""

    actuator_pk: int
    estimator: str
    config: dict[str, Any]
    state: bytes | None
    applied_seq: int
    status: str
    reasons: list[str]
    diagnosis_t_s: float | None
    diagnosis: dict[str, Any] | None
    config_version: int
    baseline: int
    reset_at_seq: int | None
    reset_baseline: int | None

    def copy(self) -> EstimatorRow:
        """A shallow copy (the row as read, kept to compare with the store's later)."""
        return _shallow_copy(self)


def _shallow_copy(row: _R) -> _R:
    # What ``dataclasses.replace`` gives for these rows, without a call of ``__init__`` through
    # every field by name (a fifth of the cost).
    new = object.__new__(type(row))
    new.__dict__.update(row.__dict__)
    return new


_STREAMS = cast(Table, Stream.__table__)
_ESTIMATOR_STATES = cast(Table, EstimatorState.__table__)
_BATCHES = cast(Table, TelemetryBatch.__table__)
_S, _E, _T = _STREAMS.c, _ESTIMATOR_STATES.c, _BATCHES.c
_STREAM_FIELDS = tuple(f.name for f in fields(StreamRow))
_ESTIMATOR_FIELDS = tuple(f.name for f in fields(EstimatorRow))

# The statements of every apply, built once: building a statement costs more than running it
# on SQLite (and their compiled forms are cached by these very objects). Core statements on
# the session's connection: no ORM compile, loading or unit of work per apply.
_CLAIM = (
    select(*(_S[name] for name in _STREAM_FIELDS))
    .where(_S.actuator_pk.in_(bindparam("pks", expanding=True)))
    .order_by(_S.actuator_pk)
)
_CLAIM_SKIP_LOCKED = _CLAIM.with_for_update(skip_locked=True)
_ESTIMATORS = (
    select(*(_E[name] for name in _ESTIMATOR_FIELDS))
    .where(_E.actuator_pk.in_(bindparam("pks", expanding=True)))
    .order_by(_E.actuator_pk, _E.estimator)
)
_PENDING = (
    select(_T.actuator_pk, _T.seq, _T.batch_id, _T.n_samples, _T.t_first_s, _T.t_last_s, _T.end_of_run)
    .join(_STREAMS, _S.actuator_pk == _T.actuator_pk)
    .where(
        _T.actuator_pk.in_(bindparam("pks", expanding=True)),
        _T.seq > _S.last_applied_seq,
        _T.seq <= _S.last_applied_seq + bindparam("window"),
    )
    .order_by(_T.actuator_pk, _T.seq)
)
_PAYLOADS = select(_T.seq, _T.payload).where(
    _T.actuator_pk == bindparam("pk"), _T.seq.between(bindparam("lo"), bindparam("hi"))
)
_STREAM_WRITTEN = ("last_applied_seq", "last_applied_t_s", "status", "updated_at", "rul_t_s", "rul_q05_s",
                   "rul_q50_s")
_UPDATE_STREAM = (
    update(_STREAMS)
    .where(_S.actuator_pk == bindparam("k_pk"))
    .values({name: bindparam(f"v_{name}", type_=_S[name].type) for name in _STREAM_WRITTEN})
)
_ESTIMATOR_WRITTEN = ("state", "applied_seq", "status", "reasons", "diagnosis_t_s", "diagnosis", "baseline",
                      "reset_at_seq", "reset_baseline")
_UPDATE_ESTIMATOR = (
    update(_ESTIMATOR_STATES)
    .where(_E.actuator_pk == bindparam("k_pk"), _E.estimator == bindparam("k_estimator"))
    .values({name: bindparam(f"v_{name}", type_=_E[name].type) for name in _ESTIMATOR_WRITTEN})
)


def claim_many(session: Session, actuator_pks: Sequence[int], *, is_sqlite: bool) -> dict[int, StreamRow]:
    """Lock the streams for this transaction, in one query; those another worker holds are
    left out (PostgreSQL: ``FOR UPDATE SKIP LOCKED``, which never waits, so no lock order can
    deadlock; on SQLite ``BEGIN IMMEDIATE`` already serializes writers)."""
    stmt = _CLAIM if is_sqlite else _CLAIM_SKIP_LOCKED
    rows = session.connection().execute(stmt, {"pks": list(actuator_pks)})
    return {int(r[0]): StreamRow(*r) for r in rows}


def estimators_of(session: Session, actuator_pks: Sequence[int]) -> dict[int, list[EstimatorRow]]:
    """Each stream's estimator rows, by estimator name, in one query."""
    out: dict[int, list[EstimatorRow]] = {pk: [] for pk in actuator_pks}
    if out:
        for r in session.connection().execute(_ESTIMATORS, {"pks": list(out)}):
            er = EstimatorRow(*r)
            er.reasons = list(er.reasons or [])
            out[er.actuator_pk].append(er)
    return out


def store_applied(session: Session, applies: Sequence[tuple[StreamRow, Sequence[EstimatorRow]]]) -> None:
    """Write back what applies changed: each stream's row and its estimators' rows, in one
    statement for the streams and one for the estimators, however many streams."""
    conn = session.connection()
    conn.execute(_UPDATE_STREAM, [
        {"k_pk": stream.actuator_pk, **{f"v_{name}": getattr(stream, name) for name in _STREAM_WRITTEN}}
        for stream, _ in applies
    ])
    est_params = [
        {"k_pk": er.actuator_pk, "k_estimator": er.estimator,
         **{f"v_{name}": getattr(er, name) for name in _ESTIMATOR_WRITTEN}}
        for _, est_rows in applies for er in est_rows
    ]
    if est_params:
        conn.execute(_UPDATE_ESTIMATOR, est_params)


def pending_of(
    session: Session, streams: Sequence[StreamRow], max_batches: int
) -> dict[int, list[PendingBatch]]:
    """Each stream's next logged batches after its applied mark, in stream order, at most
    ``max_batches + 1`` (the one more tells whether a limit stops the run), in one query.
    Seqs are given out one by one, so the window ``mark < seq <= mark + max_batches + 1``
    holds them; a seq not committed yet is a gap, found by :func:`take_pending`."""
    out: dict[int, list[PendingBatch]] = {st.actuator_pk: [] for st in streams}
    if not out:
        return out
    for pk, seq, batch_id, n, t_first, t_last, eor in session.connection().execute(
        _PENDING, {"pks": list(out), "window": max_batches + 1}
    ):
        out[pk].append(PendingBatch(pk, seq, batch_id, n, t_first, t_last, bool(eor)))
    return out


def take_pending(
    stream: StreamRow, candidates: Sequence[PendingBatch], *, max_samples: int, max_batches: int
) -> tuple[list[PendingBatch], bool]:
    """The batches of ``candidates`` (:func:`pending_of`) that follow the applied mark without
    a gap, up to ``max_samples`` samples (at least one batch) and ``max_batches``; and whether
    more contiguous batches follow them (a limit stopped the run)."""
    pending: list[PendingBatch] = []
    total = 0
    for row in candidates:
        if row.seq != stream.last_applied_seq + len(pending) + 1:
            break
        if len(pending) == max_batches or (pending and total + row.n_samples > max_samples):
            return pending, True
        pending.append(row)
        total += row.n_samples
    return pending, False


def payloads(session: Session, actuator_pk: int, seqs: Sequence[int]) -> dict[int, bytes | None]:
    """The stored payloads of some of a stream's batches, by seq."""
    if not seqs:
        return {}
    wanted = set(seqs)
    rows = session.connection().execute(_PAYLOADS, {"pk": actuator_pk, "lo": min(seqs), "hi": max(seqs)})
    return {int(seq): payload for seq, payload in rows if seq in wanted}


def claim(session: Session, actuator_pk: int, *, is_sqlite: bool) -> Stream | None:
    """Lock the stream for this transaction. None when another worker holds it (PostgreSQL:
    ``FOR UPDATE SKIP LOCKED``; on SQLite ``BEGIN IMMEDIATE`` already serializes writers)."""
    stmt = select(Stream).where(Stream.actuator_pk == actuator_pk)
    if not is_sqlite:
        stmt = stmt.with_for_update(skip_locked=True)
    return session.scalar(stmt)


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


def notify_many(session: Session, channel: str, payloads: Sequence[str]) -> None:
    """PostgreSQL ``NOTIFY`` of several payloads on one channel, in this order, in one statement
    (delivered when, and only if, this transaction commits)."""
    if payloads:
        session.execute(_NOTIFY_MANY, {"channel": channel, "payloads": list(payloads)})


_NOTIFY_MANY = text(
    "SELECT pg_notify(:channel, p) FROM unnest(CAST(:payloads AS text[])) WITH ORDINALITY AS t(p, i) ORDER BY i"
)


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


# Core inserts on the tables (not the ORM's bulk insert of the models: the same rows and column
# defaults, without its per-statement bookkeeping, which was most of an insert of a few rows).
_INSERTS = tuple(insert(cast(Table, model.__table__)) for model in OUTPUT_MODELS)


def insert_rows(session: Session, rows: Sequence[Rows]) -> None:
    """Insert the output rows of one or more applies, one statement per table (rows of a
    table keep their order: apply by apply, each in its own order)."""
    conn = session.connection()
    for i, stmt in enumerate(_INSERTS):
        items = [r for part in rows for r in (part.health, part.outputs, part.events, part.rul)[i]]
        if items:
            conn.execute(stmt, items)


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
    """Retention: forget the raw payloads of applied batches (seq at or before their stream's
    applied mark) received more than ``older_than_s`` ago. A batch not applied yet keeps its
    payload however old it is."""
    cutoff = datetime.fromtimestamp(utcnow().timestamp() - older_than_s, UTC)
    applied_mark = (
        select(Stream.last_applied_seq).where(Stream.actuator_pk == TelemetryBatch.actuator_pk).scalar_subquery()
    )
    res = session.execute(
        update(TelemetryBatch)
        .where(
            TelemetryBatch.received_at < cutoff,
            TelemetryBatch.payload.is_not(None),
            TelemetryBatch.seq <= applied_mark,
        )
        .values(payload=None)
        .execution_options(synchronize_session=False)
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
