"""The processing rules, each inside the caller's transaction: apply a stream's pending
batches, replay one estimator from the log after its state could not be read, and read applied
results back."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from enum import Enum

from sqlalchemy.orm import Session

from app.auth import repository as auth_repository
from app.codec import decode_columns
from app.errors import NotFound
from app.events import service as events
from app.fleet import service as fleet
from app.ingest import TIME_COLUMN
from app.models import (
    EstimatorEventRow,
    EstimatorState,
    HealthWindowRow,
    RulEstimateRow,
    SampleOutputRow,
    Stream,
    TelemetryBatch,
    utcnow,
)
from app.processing import repository
from app.processing.hot import HotStates, runner_of
from app.processing.messages import (
    BatchResult,
    EstimatorResult,
    event_public,
    finite_or_none,
    rul_public,
    window_public,
)
from app.processing.orchestration import (
    LoggedBatch,
    Rows,
    fresh_runner,
    make_runner,
    most_urgent_rul,
    run_estimators,
)
from app.processing.recent import RecentBatches
from estimators.base import Batch, worst_status

# Batches read per query, when applying and when replaying the log.
MAX_BATCHES_PER_QUERY = 256


@dataclass
class ApplyResult:
    """One committed apply of a stream: for metrics, waiters and subscribers."""

    batches: int
    samples: int
    last_applied_seq: int
    actuator_pk: int = 0
    applied: list[BatchResult] = field(default_factory=list)
    # Status before and after this transaction (fleet subscribers hear about changes).
    status_before: str = "learning"
    status_after: str = "learning"
    # More batches were pending than one apply takes (apply the stream again).
    more: bool = False


def decode(
    row: TelemetryBatch | repository.PendingBatch,
    recent: RecentBatches | None = None,
    payload: bytes | None = None,
) -> LoggedBatch:
    """A logged batch, decoded (taken from ``recent`` when this process just logged it; else
    from ``payload``, or the row's own payload when it carries one)."""
    batch = recent.take(row.actuator_pk, row.seq, row.batch_id) if recent is not None else None
    if batch is None:
        if payload is None and isinstance(row, TelemetryBatch):
            payload = row.payload
        if payload is None:
            raise LookupError(f"batch seq {row.seq} has no payload in the log")
        cols = decode_columns(payload)
        t_s = cols.pop(TIME_COLUMN)
        batch = Batch(t_s=t_s, channels=cols, end_of_run=row.end_of_run)
    return LoggedBatch(
        seq=row.seq,
        batch_id=row.batch_id,
        t_first_s=row.t_first_s,
        t_last_s=row.t_last_s,
        n_samples=row.n_samples,
        batch=batch,
    )


def _decode_pending(
    session: Session, pending: Sequence[repository.PendingBatch], recent: RecentBatches | None
) -> list[LoggedBatch]:
    """Decode the batches, reading from the log only the payloads not held in ``recent``."""
    held = {b.seq: recent.take(b.actuator_pk, b.seq, b.batch_id) for b in pending} if recent is not None else {}
    missing = [b.seq for b in pending if held.get(b.seq) is None]
    stored = repository.payloads(session, pending[0].actuator_pk, missing) if missing else {}
    out = []
    for b in pending:
        batch = held.get(b.seq)
        if batch is None:
            out.append(decode(b, None, stored.get(b.seq)))
        else:
            out.append(LoggedBatch(b.seq, b.batch_id, b.t_first_s, b.t_last_s, b.n_samples, batch))
    return out


@dataclass
class GroupLoad:
    """What a group of streams' applies read first, in three queries for the whole group:
    the claimed streams (those another worker holds are missing), their estimator rows and
    their next logged batches (without payloads)."""

    streams: dict[int, repository.StreamRow]
    estimators: dict[int, list[repository.EstimatorRow]]
    candidates: dict[int, list[repository.PendingBatch]]


def load_group(session: Session, actuator_pks: Sequence[int], *, is_sqlite: bool, max_batches: int) -> GroupLoad:
    streams = repository.claim_many(session, actuator_pks, is_sqlite=is_sqlite)
    live = [st for st in streams.values() if st.failure is None]
    return GroupLoad(
        streams=streams,
        estimators=repository.estimators_of(session, [st.actuator_pk for st in live]),
        candidates=repository.pending_of(session, live, max_batches),
    )


def _label(rows: Rows, est_rows: Sequence[EstimatorState | repository.EstimatorRow]) -> None:
    """Stamp every output row with the config version and baseline of its estimator."""
    labels = {er.estimator: (er.config_version, er.baseline) for er in est_rows}
    for items in (rows.health, rows.outputs, rows.events, rows.rul):
        for r in items:
            r["config_version"], r["baseline"] = labels[r["estimator"]]


def _at_baseline_boundary(
    stream: repository.StreamRow, est_rows: Sequence[repository.EstimatorRow], pending: list[repository.PendingBatch]
) -> list[repository.PendingBatch]:
    """The batches of one baseline: a maintenance action recorded while batches were pending
    restarts the estimators at ``reset_at_seq``. Batches before it are applied first (to the
    old baseline); at it, the estimators start the new baseline."""
    boundary = min(
        (er.reset_at_seq for er in est_rows if er.reset_at_seq is not None and er.reset_at_seq > stream.last_applied_seq),
        default=None,
    )
    if boundary is None:
        return pending
    if pending[0].seq < boundary:
        return [b for b in pending if b.seq < boundary]
    for er in est_rows:
        if er.reset_at_seq == boundary and er.reset_baseline is not None:
            fleet.start_baseline(er, er.reset_baseline)
    stream.rul_t_s = stream.rul_q05_s = stream.rul_q50_s = None
    return pending


def _set_rul(stream: Stream | repository.StreamRow, rul_rows: Sequence[dict[str, object]]) -> None:
    best = most_urgent_rul(rul_rows)
    if best is not None:
        stream.rul_t_s = best["t_s"]
        stream.rul_q05_s = best["q05_s"]
        stream.rul_q50_s = best["q50_s"]


@dataclass
class PreparedApply:
    """An apply computed but not stored: the rows to write, the stream's and its estimators'
    rows as they will be, and as they were read (:func:`still_current` compares them with the
    rows at store time)."""

    stream: repository.StreamRow
    est_rows: list[repository.EstimatorRow]
    read_stream: repository.StreamRow
    read_est_rows: list[repository.EstimatorRow]
    rows: Rows
    result: ApplyResult


def prepare_apply(
    session: Session,
    actuator_pk: int,
    *,
    max_samples: int,
    store_outputs: bool,
    is_sqlite: bool,
    max_batches: int = MAX_BATCHES_PER_QUERY,
    recent: RecentBatches | None = None,
    ready_kinds: frozenset[str] | None = None,
    loaded: GroupLoad | None = None,
    hot: HotStates | None = None,
) -> PreparedApply | None:
    """Read a stream's next pending batches and run its estimators over them (pure), writing
    nothing: :func:`store_apply` writes the outcome. :func:`apply_pending` runs both in one
    transaction; the processor on SQLite runs this one in a read transaction, outside the
    database's one write lock, and stores in a short write transaction when the rows read
    are :func:`still_current` there.

    Arguments and the None cases as :func:`apply_pending`. ``hot`` receives the new states
    before they are stored: an entry whose store never commits does not match the row, and is
    not used (:mod:`app.processing.hot`).
    """
    if loaded is None:
        loaded = load_group(session, [actuator_pk], is_sqlite=is_sqlite, max_batches=max_batches)
    stream = loaded.streams.get(actuator_pk)
    if stream is None or stream.failure is not None:
        return None
    est_rows = loaded.estimators.get(actuator_pk, [])
    if ready_kinds is not None and any(er.estimator not in ready_kinds for er in est_rows):
        return None
    taken, more = repository.take_pending(
        stream, loaded.candidates.get(actuator_pk, []), max_samples=max_samples, max_batches=max_batches
    )
    if not taken:
        return None
    read_stream, read_est_rows = stream.copy(), [er.copy() for er in est_rows]
    pending = _at_baseline_boundary(stream, est_rows, taken)
    held = [
        runner_of(hot, actuator_pk, er.estimator, er.config, er.state, er.status, tuple(er.reasons),
                  er.diagnosis_t_s, er.diagnosis)
        for er in est_rows
    ]
    # Whether each state is known to read back: held, or read from the row now.
    verified = [h is not None or er.state is not None for h, er in zip(held, est_rows, strict=True)]
    runners = [
        h or make_runner(er.estimator, er.config, er.state, er.status, er.reasons, er.diagnosis_t_s, er.diagnosis)
        for h, er in zip(held, est_rows, strict=True)
    ]
    batches = _decode_pending(session, pending, recent)
    step = run_estimators(actuator_pk, runners, batches, store_outputs=store_outputs)

    now = utcnow()
    _label(step.rows, est_rows)
    for er, runner, known in zip(est_rows, step.runners, verified, strict=True):
        er.state = runner.kind.dump_state(runner.state)
        if hot is not None:
            hot.put(actuator_pk, er.estimator, er.state, er.config, runner.config, runner.state, verified=known)
        er.applied_seq = pending[-1].seq
        er.status, er.reasons = runner.status, list(runner.reasons)
        er.diagnosis_t_s, er.diagnosis = runner.diagnosis_t_s, runner.diagnosis
    status_before = stream.status
    _set_rul(stream, step.rows.rul)
    stream.last_applied_seq = pending[-1].seq
    stream.last_applied_t_s = pending[-1].t_last_s
    stream.status = step.status
    stream.updated_at = now
    result = ApplyResult(
        batches=len(pending),
        samples=sum(b.n_samples for b in pending),
        last_applied_seq=stream.last_applied_seq,
        actuator_pk=actuator_pk,
        applied=step.results,
        status_before=status_before,
        status_after=stream.status,
        more=more or len(pending) < len(taken),  # the rest starts a new baseline
    )
    return PreparedApply(stream, est_rows, read_stream, read_est_rows, step.rows, result)


def still_current(prepared: PreparedApply, current: GroupLoad) -> bool:
    """Whether the stream's row and its estimators' rows, read again in the transaction that
    stores ``prepared`` (:func:`load_current`), are exactly those it was computed from. Every
    change to them (another apply, an admin rewind, a maintenance action, a config change, a
    replay, a failed mark, a deletion) changes at least one column; logged batches after the
    applied mark never change."""
    pk = prepared.result.actuator_pk
    return (current.streams.get(pk) == prepared.read_stream
            and current.estimators.get(pk, []) == prepared.read_est_rows)


def load_current(session: Session, actuator_pks: Sequence[int], *, is_sqlite: bool) -> GroupLoad:
    """The streams' and estimators' rows as they are now (for :func:`still_current`)."""
    streams = repository.claim_many(session, actuator_pks, is_sqlite=is_sqlite)
    return GroupLoad(streams, repository.estimators_of(session, list(streams)), {})


def store_apply(session: Session, prepared: PreparedApply) -> ApplyResult:
    """Write a prepared apply in the caller's transaction: outputs, states, the applied mark,
    and the fleet events and alarms it logs."""
    return store_group(session, [prepared])[0]


def store_group(session: Session, prepared: Sequence[PreparedApply]) -> list[ApplyResult]:
    """Write prepared applies of several streams in the caller's transaction, with one
    statement per table for all of them (the outputs, the streams' rows, the estimators'
    rows), then each stream's fleet events and alarms in stream order. Either all of it is
    written or the caller rolls it back: a caller that must isolate one stream's error stores
    the streams one by one (:func:`store_apply`), each in its own savepoint."""
    repository.insert_rows(session, [p.rows for p in prepared])
    repository.store_applied(session, [(p.stream, p.est_rows) for p in prepared])
    for p in prepared:
        events.record_apply(session, p.result)  # the fleet event log and alarms, in this transaction
    return [p.result for p in prepared]


def apply_pending(
    session: Session,
    actuator_pk: int,
    *,
    max_samples: int,
    store_outputs: bool,
    is_sqlite: bool,
    max_batches: int = MAX_BATCHES_PER_QUERY,
    recent: RecentBatches | None = None,
    ready_kinds: frozenset[str] | None = None,
    loaded: GroupLoad | None = None,
    hot: HotStates | None = None,
) -> ApplyResult | None:
    """Apply the next pending batches of one stream inside the caller's transaction: claim,
    load, run the estimators (pure), store outputs, states and the applied mark together
    (:func:`prepare_apply`, then :func:`store_apply`).

    ``hot`` holds the states this process stored last (used only when the rows read now
    hold exactly those bytes, :mod:`app.processing.hot`).

    ``loaded`` is what :func:`load_group` read for a group of streams this one belongs to
    (loaded with the same ``max_batches``, in this transaction); without it the stream is
    claimed and loaded alone.

    Returns None when another worker holds the stream, the stream is failed, nothing is
    pending, or an estimator of the stream is of a kind outside ``ready_kinds`` (its kernels
    are still compiling; None means every kind is ready).

    Raises:
        StateUnreadable: an estimator's state has a version this build cannot read (nothing
            is written; the caller replays that estimator or marks the stream failed).
    """
    prepared = prepare_apply(
        session, actuator_pk, max_samples=max_samples, store_outputs=store_outputs, is_sqlite=is_sqlite,
        max_batches=max_batches, recent=recent, ready_kinds=ready_kinds, loaded=loaded, hot=hot,
    )
    return None if prepared is None else store_apply(session, prepared)


class Replay(Enum):
    """How a replay ended."""

    DONE = "done"
    LOG_INCOMPLETE = "log_incomplete"  # retention dropped batches: nothing changed
    BUSY = "busy"  # another worker holds the stream: nothing changed


def replay_estimator(
    session: Session, actuator_pk: int, estimator: str, *, store_outputs: bool, is_sqlite: bool
) -> Replay:
    """Re-initialise one estimator of a stream and replay every applied batch through it, in
    the caller's transaction; its earlier outputs are replaced by the replay's.

    Used when the estimator's stored state has a version this build cannot read: the outputs
    then are those of an uninterrupted run with this build. Nothing changes when the log no
    longer holds every batch from the first (retention dropped payloads), or another worker
    holds the stream.
    """
    stream = repository.claim(session, actuator_pk, is_sqlite=is_sqlite)
    if stream is None:
        return Replay.BUSY
    upto = stream.last_applied_seq
    est_rows = repository.estimators(session, actuator_pk)
    er = next(r for r in est_rows if r.estimator == estimator)
    # Only the current baseline (since the last repair or replacement) is replayed.
    first = fleet.baseline_start(session, actuator_pk, er.baseline)
    if not repository.log_holds_from_first(session, actuator_pk, upto, first_seq=first):
        return Replay.LOG_INCOMPLETE
    repository.delete_outputs(session, actuator_pk, estimator, baseline=er.baseline)
    runner = fresh_runner(estimator, er.config)
    rul_rows: list[dict[str, object]] = []
    for part in repository.logged_batches(session, actuator_pk, upto, MAX_BATCHES_PER_QUERY, first_seq=first):
        step = run_estimators(actuator_pk, [runner], [decode(b) for b in part], store_outputs=store_outputs)
        _label(step.rows, [er])
        repository.insert_rows(session, [step.rows])
        rul_rows.extend(step.rows.rul)
        runner = step.runners[0]
    er.state = runner.kind.dump_state(runner.state)
    er.applied_seq = upto
    er.status, er.reasons = runner.status, list(runner.reasons)
    er.diagnosis_t_s, er.diagnosis = runner.diagnosis_t_s, runner.diagnosis
    _set_rul(stream, rul_rows)
    stream.status = worst_status([r.status for r in est_rows])
    stream.updated_at = utcnow()
    session.flush()
    return Replay.DONE


def applied_results(session: Session, actuator_pk: int, seqs: list[int]) -> list[BatchResult]:
    """What applying each of ``seqs`` produced, read back from the store (when the live push
    was missed: another process applied the batch, or a subscriber queue overflowed).

    The same message as a live result, except that ``status`` is each estimator's status now,
    ``last`` holds the last per-sample outputs only when they are stored, and ``diagnosis`` is
    None (only the latest diagnosis is kept).
    """
    if not seqs:
        return []
    batches = repository.batches_by_seq(session, actuator_pk, seqs)
    if not batches:
        return []
    ests = repository.estimators(session, actuator_pk)
    lo, hi = min(batches), max(batches)
    windows, evs, ruls, outs = (
        repository.outputs_by_seq(session, model, actuator_pk, lo, hi)
        for model in (HealthWindowRow, EstimatorEventRow, RulEstimateRow, SampleOutputRow)
    )
    status = worst_status([er.status for er in ests])
    results = []
    for seq in sorted(batches):
        b = batches[seq]
        per: dict[str, EstimatorResult] = {}
        for er in ests:
            key = (seq, er.estimator)
            last: dict[str, float | None] = {}
            for o in outs.get(key, [])[-1:]:
                cols = decode_columns(o.payload)
                last = {k: finite_or_none(float(v[-1])) for k, v in cols.items() if k != TIME_COLUMN and len(v)}
            per[er.estimator] = EstimatorResult(
                status=er.status,
                reasons=list(er.reasons),
                last=last,
                health=[window_public(w) for w in windows.get(key, [])],
                events=[event_public(e) for e in evs.get(key, [])],
                rul=[rul_public(r) for r in ruls.get(key, [])],
                diagnosis=None,
            )
        results.append(
            BatchResult(
                seq=seq,
                batch_id=b.batch_id,
                t_first_s=b.t_first_s,
                t_last_s=b.t_last_s,
                n_samples=b.n_samples,
                status=status,
                estimators=per,
            )
        )
    return results



def failed_streams(session: Session) -> list[tuple[str, str, str, str]]:
    """(operator, tail, actuator id, reason) of every stream marked failed."""
    return repository.failed_streams(session)


def reset_failed(session: Session, operator: str, tail: str, actuator_id: str) -> bool:
    """Clear the failed mark of a stream (after its cause is fixed): the processor applies it
    again, and marks it again if the cause remains. False when it was not marked."""
    op = auth_repository.operator_by_name(session, operator)
    if op is None:
        raise NotFound(f"operator {operator!r} not found")
    act = fleet.get_actuator(session, op.id, tail, actuator_id)
    status = worst_status([er.status for er in repository.estimators(session, act.id)])
    return repository.clear_failure(session, act.id, status)
