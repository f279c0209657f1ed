"""The per-stream processor: telemetry log -> estimators -> results, one transaction.

For a stream, the processor takes the next logged batches after the stream's applied mark, loads
each attached estimator's config and state, steps the estimators over the batches in order, and
commits outputs, health windows, events, new states and the new applied mark in ONE transaction
(``app.processing.service.apply_pending``). A crash before the commit leaves the mark where it
was, so the batches are applied again, once, after restart; a crash after it leaves nothing to
redo. The row lock on ``streams`` (``FOR UPDATE SKIP LOCKED`` on PostgreSQL; ``BEGIN IMMEDIATE``
on SQLite) makes one worker apply a stream at a time, so any number of processes can share a
database.

A stream that cannot be applied is never retried forever:

* an estimator state this build cannot read (a new ``STATE_VERSION``) is re-initialised and the
  stream replayed from its telemetry log, when the log still holds every batch from the first;
  otherwise the stream is marked ``failed`` with the reason;
* any other error is retried ``processor_max_attempts`` times with a doubling back-off, then the
  stream is marked ``failed`` with the last error.

A failed stream keeps logging batches (they are durable) but is not applied; ``.../health``, the
fleet board and ``/metrics`` show it, and a ``?wait`` on one of its batches answers at once.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

from prometheus_client import Counter, Gauge, Histogram
from sqlalchemy.orm import Session

from app.config import Settings
from app.db import Database
from app.processing import repository, service
from app.processing.orchestration import StateUnreadable
from app.processing.service import ApplyResult
from app.websocket.hub import Hub, StreamMeta, fleet_events

log = logging.getLogger("fleethealth.processor")

BATCHES_APPLIED = Counter("fleethealth_batches_applied_total", "Batches applied to estimators")
SAMPLES_APPLIED = Counter("fleethealth_samples_applied_total", "Samples applied to estimators")
APPLY_ERRORS = Counter("fleethealth_apply_errors_total", "Failed apply transactions")
STATE_REPLAYS = Counter(
    "fleethealth_state_replays_total", "Estimators re-initialised and replayed from the log"
)
STREAM_FAILURES = Counter(
    "fleethealth_stream_failures_total", "Streams marked failed", ["cause"]
)
STREAMS_FAILED = Gauge("fleethealth_streams_failed", "Streams marked failed (not applied)")
APPLY_SECONDS = Histogram(
    "fleethealth_apply_seconds",
    "Duration of one apply transaction",
    buckets=(0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1, 2.5, 5, 10),
)

# A waiter re-reads the applied mark this often: another process may have applied the batch.
WAIT_POLL_S = 0.5
# Per-sample output retention runs at most this often (it scans the table).
SAMPLE_OUTPUT_PRUNE_EVERY_S = 60.0
# Shortest sleep of the loop between scans (wake-ups arrive through the queue anyway).
MIN_LOOP_SLEEP_S = 0.05


@dataclass(frozen=True)
class WaitOutcome:
    """What a wait for a batch ended with: applied, still pending, or the stream failed."""

    applied: bool
    failure: str | None = None


class Processor:
    """A background thread that applies pending batches, woken by ingest and by a periodic scan."""

    def __init__(
        self,
        db: Database,
        settings: Settings,
        hub: Hub | None = None,
        ready_kinds: Callable[[], frozenset[str] | None] = lambda: None,
    ) -> None:
        self.db = db
        self.settings = settings
        self.hub = hub or Hub()
        # Estimator kinds whose kernels are ready (None: all); other streams wait, and are
        # woken by recover() when their kind becomes ready.
        self.ready_kinds = ready_kinds
        self._meta: dict[int, StreamMeta] = {}
        self._queue: queue.SimpleQueue[int | None] = queue.SimpleQueue()
        self._applied: dict[int, int] = {}
        self._failed: dict[int, str] = {}
        self._cond = threading.Condition()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._attempts: dict[int, int] = {}
        self._retry_at: dict[int, float] = {}

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

    # ------------------------------------------------------------------ waiting
    def wait_applied(self, actuator_pk: int, seq: int, timeout_s: float) -> WaitOutcome:
        """Wait until batch ``seq`` of the stream is applied, the stream is failed, or the
        time runs out."""
        deadline = time.monotonic() + timeout_s
        if self._applied.get(actuator_pk, 0) >= seq:
            return WaitOutcome(True)
        self._refresh(actuator_pk)
        with self._cond:
            while self._applied.get(actuator_pk, 0) < seq and actuator_pk not in self._failed:
                left = deadline - time.monotonic()
                if left <= 0:
                    break
                self._cond.wait(min(left, WAIT_POLL_S))
                if self._applied.get(actuator_pk, 0) < seq:
                    self._refresh(actuator_pk)
        applied = self._applied.get(actuator_pk, 0) >= seq
        return WaitOutcome(applied, None if applied else self._failed.get(actuator_pk))

    def _refresh(self, actuator_pk: int) -> None:
        with self.db.read() as s:
            applied, failure = repository.applied_mark(s, actuator_pk)
        if applied > self._applied.get(actuator_pk, 0):
            self._applied[actuator_pk] = applied
        if failure is not None:
            self._failed[actuator_pk] = failure
        else:
            self._failed.pop(actuator_pk, None)

    # ------------------------------------------------------------------ applying
    def recover(self) -> int:
        """Wake every stream with pending batches (at start-up and on each scan)."""
        with self.db.read() as s:
            pks = repository.pending_streams(s)
            STREAMS_FAILED.set(repository.count_failed(s))
        for pk in pks:
            self.notify(pk)
        return len(pks)

    def _apply_stream(self, actuator_pk: int) -> int:
        applied = 0
        replayed: set[str] = set()
        while not self._stop.is_set():
            t0 = time.perf_counter()
            try:
                with self.db.write() as s:
                    res = service.apply_pending(
                        s,
                        actuator_pk,
                        max_samples=self.settings.processor_max_samples_per_txn,
                        max_batches=self.settings.processor_max_batches_per_txn,
                        store_outputs=self.settings.store_sample_outputs,
                        is_sqlite=self.db.is_sqlite,
                        ready_kinds=self.ready_kinds(),
                    )
            except StateUnreadable as exc:
                if exc.estimator in replayed:
                    # A state the estimator just wrote cannot be read back: a bug, not an upgrade.
                    self._attempt_failed(actuator_pk, exc)
                    return applied
                if self._replay(actuator_pk, exc):
                    replayed.add(exc.estimator)
                    continue
                return applied
            except Exception as exc:
                self._attempt_failed(actuator_pk, exc)
                return applied
            self._attempts.pop(actuator_pk, None)
            self._retry_at.pop(actuator_pk, None)
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

    def _replay(self, actuator_pk: int, exc: StateUnreadable) -> bool:
        """Replay the estimator whose state is unreadable; True when done (apply again)."""
        log.warning("stream %s: %s; replaying it from the telemetry log", actuator_pk, exc)
        try:
            with self.db.write() as s:
                outcome = service.replay_estimator(
                    s,
                    actuator_pk,
                    exc.estimator,
                    store_outputs=self.settings.store_sample_outputs,
                    is_sqlite=self.db.is_sqlite,
                )
                if outcome is service.Replay.LOG_INCOMPLETE:
                    self._mark_failed(
                        s,
                        actuator_pk,
                        f"estimator {exc.estimator!r} cannot read its stored state ({exc.detail}) "
                        "and the telemetry log no longer holds every batch from the first to "
                        "replay the stream",
                        cause="state_unreadable",
                    )
        except Exception as replay_exc:
            self._attempt_failed(actuator_pk, replay_exc)
            return False
        if outcome is service.Replay.DONE:
            STATE_REPLAYS.inc()
            return True
        if outcome is service.Replay.LOG_INCOMPLETE:
            self._after_failed(actuator_pk)
        return False  # failed, or another worker holds the stream and replays it

    def _attempt_failed(self, actuator_pk: int, exc: BaseException) -> None:
        """Back off a stream whose apply raised; mark it failed after the last attempt."""
        APPLY_ERRORS.inc()
        n = self._attempts.get(actuator_pk, 0) + 1
        self._attempts[actuator_pk] = n
        if n < self.settings.processor_max_attempts:
            delay = min(
                self.settings.processor_retry_backoff_s * 2 ** (n - 1),
                self.settings.processor_retry_backoff_max_s,
            )
            self._retry_at[actuator_pk] = time.monotonic() + delay
            log.exception("applying stream %s failed (attempt %d); retry in %.1f s", actuator_pk, n, delay,
                          exc_info=exc)
            return
        log.error("applying stream %s failed %d times; marking it failed", actuator_pk, n, exc_info=exc)
        try:
            with self.db.write() as s:
                self._mark_failed(
                    s,
                    actuator_pk,
                    f"applying failed {n} times; last error: {type(exc).__name__}: {exc}",
                    cause="apply_error",
                )
        except Exception:
            log.exception("marking stream %s failed did not commit; it will be retried", actuator_pk)
            self._retry_at[actuator_pk] = time.monotonic() + self.settings.processor_retry_backoff_max_s
            return
        self._after_failed(actuator_pk)

    def _mark_failed(self, session: Session, actuator_pk: int, reason: str, *, cause: str) -> None:
        repository.mark_failed(session, actuator_pk, reason)
        STREAM_FAILURES.labels(cause).inc()
        with self._cond:
            self._failed[actuator_pk] = reason

    def _after_failed(self, actuator_pk: int) -> None:
        self._attempts.pop(actuator_pk, None)
        self._retry_at.pop(actuator_pk, None)
        with self.db.read() as s:
            STREAMS_FAILED.set(repository.count_failed(s))
        with self._cond:
            self._cond.notify_all()

    # ------------------------------------------------------------------ publishing
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
                meta = self._meta[actuator_pk] = StreamMeta(*repository.stream_owner(s, actuator_pk))
        return meta

    # ------------------------------------------------------------------ loop
    def _run(self) -> None:
        next_scan = 0.0
        next_prune = 0.0
        while not self._stop.is_set():
            now = time.monotonic()
            if now >= next_scan:
                try:
                    self.recover()
                    if self.settings.log_retention_s is not None:
                        with self.db.write() as s:
                            repository.drop_applied_payloads(s, self.settings.log_retention_s)
                    if self.settings.sample_output_retention_s is not None and now >= next_prune:
                        next_prune = now + SAMPLE_OUTPUT_PRUNE_EVERY_S
                        with self.db.write() as s:
                            repository.drop_old_sample_outputs(s, self.settings.sample_output_retention_s)
                except Exception:
                    log.exception("periodic scan failed")
                next_scan = now + self.settings.processor_scan_interval_s
            try:
                pk = self._queue.get(timeout=max(MIN_LOOP_SLEEP_S, next_scan - time.monotonic()))
            except queue.Empty:
                continue
            if pk is None:
                continue
            # Coalesce repeated wake-ups for the same stream.
            woken = {pk}
            while True:
                try:
                    more = self._queue.get_nowait()
                except queue.Empty:
                    break
                if more is not None:
                    woken.add(more)
            for p in sorted(woken):
                if time.monotonic() < self._retry_at.get(p, 0.0):
                    continue  # backing off; the periodic scan wakes it again
                self._apply_stream(p)
