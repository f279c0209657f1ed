"""The per-stream processor: telemetry log -> estimators -> results, one transaction.

For a stream, the processor takes the next logged batches after the stream's applied mark, loads
each attached estimator's config and state, steps the estimators over the batches in order, and
commits outputs, health windows, events, new states and the new applied mark in ONE transaction.
A crash before the commit leaves the mark where it was, so the batches are applied again, once,
after restart; a crash after it leaves nothing to redo. The row lock on ``streams`` (``FOR UPDATE
SKIP LOCKED`` on PostgreSQL; ``BEGIN IMMEDIATE`` on SQLite) makes one worker apply a stream at a
time, so any number of processes can share a database.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from prometheus_client import Counter, Histogram
from sqlalchemy import insert, select, update
from sqlalchemy.orm import Session

from app.codec import decode_columns, encode_columns
from app.config import Settings
from app.db import Database
from app.hub import Hub, StreamMeta, fleet_events
from app.ingest import TIME_COLUMN
from app.models import (
    Actuator,
    Aircraft,
    EstimatorEventRow,
    EstimatorState,
    HealthWindowRow,
    RulEstimateRow,
    SampleOutputRow,
    Stream,
    TelemetryBatch,
    utcnow,
)
from estimators.base import Batch, RulEstimate, worst_status
from estimators.registry import ESTIMATORS

log = logging.getLogger("fleethealth.processor")

BATCHES_APPLIED = Counter("fleethealth_batches_applied_total", "Batches applied to estimators")
SAMPLES_APPLIED = Counter("fleethealth_samples_applied_total", "Samples applied to estimators")
APPLY_ERRORS = Counter("fleethealth_apply_errors_total", "Failed apply transactions")
APPLY_SECONDS = Histogram(
    "fleethealth_apply_seconds",
    "Duration of one apply transaction",
    buckets=(0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1, 2.5, 5, 10),
)


def _clean(value: Any) -> Any:
    """JSON-safe indicator values: NaN and inf become None."""
    if isinstance(value, float | np.floating):
        v = float(value)
        return v if np.isfinite(v) else None
    return value


def _clean_json(value: Any) -> Any:
    """A JSON-safe deep copy: non-finite floats become None, numpy scalars plain numbers."""
    if isinstance(value, dict):
        return {str(k): _clean_json(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_clean_json(v) for v in value]
    if isinstance(value, np.ndarray):
        return [_clean_json(v) for v in value.tolist()]
    if isinstance(value, np.integer):
        return int(value)
    if isinstance(value, np.bool_):
        return bool(value)
    return _clean(value)


def _window_row(base: dict[str, Any], w: Any) -> dict[str, Any]:
    return dict(
        base,
        t_start_s=float(w.t_start_s),
        t_end_s=float(w.t_end_s),
        n_samples=int(w.n_samples),
        indicators={k: _clean(v) for k, v in w.indicators.items()},
        status=w.status,
        reasons=list(w.reasons),
    )


def _opt(x: float | None) -> float | None:
    return None if x is None else _clean(float(x))


def _rul_row(base: dict[str, Any], r: RulEstimate) -> dict[str, Any]:
    return dict(
        base,
        t_s=float(r.t_s),
        mean_s=_opt(r.mean_s),
        std_s=_opt(r.std_s),
        q05_s=_opt(r.q05_s),
        q50_s=_opt(r.q50_s),
        q95_s=_opt(r.q95_s),
        optimistic_s=_opt(r.optimistic_s),
        pessimistic_s=_opt(r.pessimistic_s),
        threshold=float(r.threshold),
        health=_clean_json(r.health),
        assumption=_clean_json(r.assumption),
        status=r.status,
        reasons=list(r.reasons),
    )


def _public(row: dict[str, Any]) -> dict[str, Any]:
    """A stored row as subscribers see it (no internal keys, no blobs)."""
    return {k: v for k, v in row.items() if k not in ("actuator_pk", "payload")}


def _update_stream_rul(stream: Stream, rul_rows: list[dict[str, Any]]) -> None:
    """Keep the fleet board's RUL: per estimator the latest prognosis, across estimators the most
    urgent (smallest 5 % quantile)."""
    latest: dict[str, dict[str, Any]] = {}
    for r in rul_rows:
        latest[r["estimator"]] = r
    best = min(
        latest.values(),
        key=lambda r: (r["q05_s"] is None, r["q05_s"] if r["q05_s"] is not None else 0.0),
    )
    stream.rul_t_s = best["t_s"]
    stream.rul_q05_s = best["q05_s"]
    stream.rul_q50_s = best["q50_s"]


@dataclass
class AppliedBatch:
    """What applying one logged batch produced, for subscribers (JSON-safe)."""

    seq: int
    batch_id: str
    t_first_s: float
    t_last_s: float
    n_samples: int
    status: str
    estimators: dict[str, dict[str, Any]]
    # Per-sample outputs (estimator -> name -> array) and their times, for subscribers asking.
    t_s: np.ndarray | None = None
    samples: dict[str, dict[str, np.ndarray]] = field(default_factory=dict)


@dataclass
class ApplyResult:
    batches: int
    samples: int
    last_applied_seq: int
    actuator_pk: int = 0
    applied: list[AppliedBatch] = field(default_factory=list)
    # Status before and after this transaction (fleet subscribers hear about changes).
    status_before: str = "ok"
    status_after: str = "ok"


def apply_pending(
    session: Session, actuator_pk: int, *, max_samples: int, store_outputs: bool, is_sqlite: bool
) -> ApplyResult | None:
    """Apply the next pending batches of one stream inside the caller's transaction.

    Returns None when another worker holds the stream (PostgreSQL) or nothing is pending.
    """
    lock = select(Stream).where(Stream.actuator_pk == actuator_pk)
    if not is_sqlite:
        lock = lock.with_for_update(skip_locked=True)
    stream = session.scalar(lock)
    if stream is None:
        return None
    pending: list[TelemetryBatch] = []
    total = 0
    for row in session.scalars(
        select(TelemetryBatch)
        .where(TelemetryBatch.actuator_pk == actuator_pk, TelemetryBatch.seq > stream.last_applied_seq)
        .order_by(TelemetryBatch.seq)
        .limit(256)
    ):
        if row.seq != stream.last_applied_seq + len(pending) + 1:
            break  # a gap: the earlier seq is not committed yet
        if pending and total + row.n_samples > max_samples:
            break
        pending.append(row)
        total += row.n_samples
    if not pending:
        return None

    est_rows = list(
        session.scalars(select(EstimatorState).where(EstimatorState.actuator_pk == actuator_pk))
    )
    runners = []
    for er in est_rows:
        module = ESTIMATORS[er.estimator]
        cfg = module.parse_config(er.config)
        state = module.load_state(er.state) if er.state is not None else module.initial_state(cfg)
        runners.append([er, module, cfg, state])

    health_rows: list[dict[str, Any]] = []
    output_rows: list[dict[str, Any]] = []
    event_rows: list[dict[str, Any]] = []
    rul_rows: list[dict[str, Any]] = []
    applied: list[AppliedBatch] = []
    status_before = stream.status
    now = utcnow()
    for row in pending:
        assert row.payload is not None, "a pending batch lost its payload"
        cols = decode_columns(row.payload)
        t_s = cols.pop(TIME_COLUMN)
        batch = Batch(t_s=t_s, channels=cols)
        per_est: dict[str, dict[str, Any]] = {}
        per_samples: dict[str, dict[str, np.ndarray]] = {}
        for runner in runners:
            er, module, cfg, state = runner
            state, out = module.step(cfg, state, batch)
            runner[3] = state
            base = dict(actuator_pk=actuator_pk, estimator=er.estimator, seq=row.seq)
            windows = [_window_row(base, w) for w in out.health]
            health_rows.extend(windows)
            for w in out.health:
                er.status, er.reasons = w.status, list(w.reasons)
            events = [
                dict(base, t_s=float(ev.t_s), kind=ev.kind, detail=_clean_json(ev.detail)) for ev in out.events
            ]
            event_rows.extend(events)
            ruls = [_rul_row(base, r) for r in out.rul]
            rul_rows.extend(ruls)
            for r in out.rul:
                er.status, er.reasons = r.status, list(r.reasons)
            if out.status is not None:
                er.status, er.reasons = out.status.status, list(out.status.reasons)
            if out.diagnosis is not None:
                er.diagnosis_t_s = float(out.diagnosis.t_s)
                er.diagnosis = _clean_json(out.diagnosis.detail)
            if store_outputs and out.samples:
                output_rows.append(
                    dict(
                        base,
                        t_first_s=row.t_first_s,
                        t_last_s=row.t_last_s,
                        n_samples=row.n_samples,
                        payload=encode_columns({TIME_COLUMN: t_s, **out.samples}),
                    )
                )
            per_samples[er.estimator] = out.samples
            per_est[er.estimator] = {
                "status": er.status,
                "reasons": list(er.reasons),
                "last": {k: _clean(v[-1]) for k, v in out.samples.items() if len(v)},
                "health": [_public(w) for w in windows],
                "events": [_public(e) for e in events],
                "rul": [_public(r) for r in ruls],
                "diagnosis": _clean_json(out.diagnosis.detail) if out.diagnosis is not None else None,
            }
        row.applied_at = now
        applied.append(
            AppliedBatch(
                seq=row.seq,
                batch_id=row.batch_id,
                t_first_s=row.t_first_s,
                t_last_s=row.t_last_s,
                n_samples=row.n_samples,
                status=worst_status([er.status for er in est_rows]),
                estimators=per_est,
                t_s=t_s,
                samples=per_samples,
            )
        )

    for rows, model in (
        (health_rows, HealthWindowRow),
        (output_rows, SampleOutputRow),
        (event_rows, EstimatorEventRow),
        (rul_rows, RulEstimateRow),
    ):
        if rows:
            session.execute(insert(model), rows)
    for er, module, _cfg, state in runners:
        er.state = module.dump_state(state)
        er.applied_seq = pending[-1].seq
    if rul_rows:
        _update_stream_rul(stream, rul_rows)
    stream.last_applied_seq = pending[-1].seq
    stream.last_applied_t_s = pending[-1].t_last_s
    stream.status = worst_status([er.status for er in est_rows])
    stream.updated_at = now
    session.flush()
    return ApplyResult(
        batches=len(pending),
        samples=total,
        last_applied_seq=stream.last_applied_seq,
        actuator_pk=actuator_pk,
        applied=applied,
        status_before=status_before,
        status_after=stream.status,
    )


def pending_streams(session: Session) -> list[int]:
    return list(
        session.scalars(
            select(Actuator.id)
            .join(Stream, Stream.actuator_pk == Actuator.id)
            .where(Actuator.last_logged_seq > Stream.last_applied_seq)
        )
    )


def drop_applied_payloads(session: Session, older_than_s: float) -> int:
    """Retention: forget raw payloads of batches applied more than ``older_than_s`` ago."""
    cutoff = utcnow().timestamp() - older_than_s
    from datetime import UTC, datetime

    res = session.execute(
        update(TelemetryBatch)
        .where(
            TelemetryBatch.applied_at.is_not(None),
            TelemetryBatch.applied_at < datetime.fromtimestamp(cutoff, UTC),
            TelemetryBatch.payload.is_not(None),
        )
        .values(payload=None)
    )
    return int(res.rowcount or 0)  # type: ignore[attr-defined]


class Processor:
    """A background thread that applies pending batches, woken by ingest and by a periodic scan."""

    def __init__(self, db: Database, settings: Settings, hub: Hub | None = None) -> None:
        self.db = db
        self.settings = settings
        self.hub = hub or Hub()
        self._meta: dict[int, StreamMeta] = {}
        self._queue: queue.SimpleQueue[int | None] = queue.SimpleQueue()
        self._applied: dict[int, int] = {}
        self._cond = threading.Condition()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._failures: dict[int, float] = {}

    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, name="fleethealth-processor", daemon=True)
        self._thread.start()

    def stop(self, timeout: float = 10.0) -> None:
        self._stop.set()
        self._queue.put(None)
        if self._thread is not None:
            self._thread.join(timeout)

    def notify(self, actuator_pk: int) -> None:
        self._queue.put(actuator_pk)

    def wait_applied(self, actuator_pk: int, seq: int, timeout_s: float) -> bool:
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while self._applied.get(actuator_pk, 0) < seq:
                left = deadline - time.monotonic()
                if left <= 0:
                    break
                self._cond.wait(min(left, 0.5))
                if self._applied.get(actuator_pk, 0) < seq:
                    self._refresh(actuator_pk)  # another process may have applied it
        return self._applied.get(actuator_pk, 0) >= seq

    def _refresh(self, actuator_pk: int) -> None:
        with self.db.read() as s:
            v = s.scalar(select(Stream.last_applied_seq).where(Stream.actuator_pk == actuator_pk))
        if v is not None and v > self._applied.get(actuator_pk, 0):
            self._applied[actuator_pk] = v

    def drain(self, actuator_pks: Iterable[int]) -> int:
        """Apply everything pending for these streams now, in the calling thread."""
        n = 0
        for pk in actuator_pks:
            n += self._apply_stream(pk)
        return n

    def recover(self) -> int:
        with self.db.read() as s:
            pks = pending_streams(s)
        if pks:
            log.info("recovering %d streams with pending batches", len(pks))
        for pk in pks:
            self.notify(pk)
        return len(pks)

    def _apply_stream(self, actuator_pk: int) -> int:
        applied = 0
        while not self._stop.is_set():
            t0 = time.perf_counter()
            try:
                with self.db.write() as s:
                    res = apply_pending(
                        s,
                        actuator_pk,
                        max_samples=self.settings.processor_max_samples_per_txn,
                        store_outputs=self.settings.store_sample_outputs,
                        is_sqlite=self.db.is_sqlite,
                    )
            except Exception:
                APPLY_ERRORS.inc()
                self._failures[actuator_pk] = time.monotonic()
                log.exception("applying stream %s failed; it will be retried", actuator_pk)
                return applied
            if res is None:
                return applied
            APPLY_SECONDS.observe(time.perf_counter() - t0)
            BATCHES_APPLIED.inc(res.batches)
            SAMPLES_APPLIED.inc(res.samples)
            applied += res.batches
            with self._cond:
                self._applied[actuator_pk] = res.last_applied_seq
                self._cond.notify_all()
            self._publish(res)
        return applied

    def _publish(self, res: ApplyResult) -> None:
        """Tell subscribers what was committed (never blocks; a failure only loses pushes)."""
        try:
            self.hub.publish_applied(res.actuator_pk, res.applied)
            if self.hub.has_fleet_subscribers():
                self.hub.publish_fleet(fleet_events(self._stream_meta(res.actuator_pk), res))
        except Exception:
            log.exception("publishing results of stream %s failed", res.actuator_pk)

    def _stream_meta(self, actuator_pk: int) -> StreamMeta:
        meta = self._meta.get(actuator_pk)
        if meta is None:
            with self.db.read() as s:
                row = s.execute(
                    select(Aircraft.operator_id, Aircraft.tail, Actuator.actuator_id)
                    .join(Actuator, Actuator.aircraft_id == Aircraft.id)
                    .where(Actuator.id == actuator_pk)
                ).one()
            meta = self._meta[actuator_pk] = StreamMeta(row[0], row[1], row[2])
        return meta

    def _run(self) -> None:
        next_scan = 0.0
        while not self._stop.is_set():
            now = time.monotonic()
            if now >= next_scan:
                try:
                    self.recover()
                    if self.settings.log_retention_s is not None:
                        with self.db.write() as s:
                            drop_applied_payloads(s, self.settings.log_retention_s)
                except Exception:
                    log.exception("periodic scan failed")
                next_scan = now + self.settings.processor_scan_interval_s
            try:
                pk = self._queue.get(timeout=max(0.05, next_scan - time.monotonic()))
            except queue.Empty:
                continue
            if pk is None:
                continue
            # Coalesce repeated wake-ups for the same stream.
            batch = {pk}
            while True:
                try:
                    more = self._queue.get_nowait()
                except queue.Empty:
                    break
                if more is not None:
                    batch.add(more)
            for p in sorted(batch):
                if time.monotonic() - self._failures.get(p, -1e9) < 5.0:
                    continue  # back off a stream whose last apply failed
                self._apply_stream(p)
