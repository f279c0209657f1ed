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

Applies are group-committed: the loop takes every stream woken since its last round and applies
their pending batches in one transaction (up to ``processor_max_streams_per_txn`` streams and
``processor_max_samples_per_txn`` samples): each stream's estimators run (a stream whose run
raises writes nothing), then one statement per table stores the whole group; should that store
raise, it is rolled back to a savepoint and the streams are stored one by one, each inside its
own savepoint, so that one stream's error rolls back only that stream. Subscribers and ``?wait=`` hear of each apply after the
commit. On PostgreSQL the transaction also carries a ``NOTIFY`` per stream (its applied mark and its
fleet events), delivered to API processes when it commits (:mod:`app.processing.wakeups`); in
SQLite's apply process the same payloads go to ``serve`` after the commit
(:mod:`app.processing.apply_process`). On
SQLite the estimators run in a read transaction, outside the one write lock, and a short write
transaction stores them; a small apply while nobody holds or waits for that lock is one write
transaction (``_apply_in_lock``).

A failed stream keeps logging batches (they are durable) but is not applied; ``.../health``, the
fleet board and ``/metrics`` show it, and a ``?wait`` on one of its batches answers at once.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import queue
import threading
import time
from collections import OrderedDict
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from typing import Any

import orjson
from prometheus_client import Counter, Gauge, Histogram
from sqlalchemy.orm import Session
from starlette.concurrency import run_in_threadpool

from app.config import Settings
from app.db import Database
from app.errors import STORAGE_FAULTS
from app.fleet import service as fleet
from app.processing import repository, service
from app.processing.hot import HotStates
from app.processing.orchestration import StateUnreadable
from app.processing.recent import RecentBatches
from app.processing.service import ApplyResult
from app.telemetry.body import release_memory
from app.websocket.hub import Hub, StreamMeta, fleet_events

log = logging.getLogger("fleethealth.processor")

BATCHES_APPLIED = Counter("fleethealth_batches_applied_total", "Batches applied to estimators")
#: An apply of at least this many samples hands the memory it freed back to the OS afterwards.
RELEASE_AFTER_SAMPLES = 250_000
SAMPLES_APPLIED = Counter("fleethealth_samples_applied_total", "Samples applied to estimators")
APPLY_ERRORS = Counter("fleethealth_apply_errors_total", "Failed apply transactions")
STATE_REPLAYS = Counter(
    "fleethealth_state_replays_total", "Estimators re-initialised and replayed from the log"
)
STREAM_FAILURES = Counter(
    "fleethealth_stream_failures_total", "Streams marked failed", ["cause"]
)
STREAMS_FAILED = Gauge("fleethealth_streams_failed", "Streams marked failed (not applied)")
APPLY_GROUPS = Counter(
    "fleethealth_apply_groups_total",
    "Apply transactions that stored something, by how they ran: one_transaction (SQLite, small, "
    "the lock free; PostgreSQL always), computed_outside (SQLite: a read transaction, then the store)",
    ["path"],
)
GROUP_STORE_SPLITS = Counter(
    "fleethealth_apply_group_splits_total",
    "Apply groups whose common store raised and were stored stream by stream instead",
)
APPLY_SECONDS = Histogram(
    "fleethealth_apply_seconds",
    "Duration of one apply transaction",
    buckets=(0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1, 2.5, 5, 10),
)

# PostgreSQL: a woken stream that another worker held is looked at again after this long.
BUSY_RECHECK_S = 0.02
# NOTIFY payloads must stay under 8000 bytes; fleet events are split to fit.
NOTIFY_MAX_BYTES = 7000
# Owners (operator, tail, actuator id) of the streams applied lately, for fleet events.
STREAM_META_CACHE = 4096
# Applied marks remembered for ?wait= without a read.
APPLIED_MARKS_CACHE = 4096
# Streams of a group whose rows are read in one query each (a time budget may end the group
# before all are applied: they are read some at a time, not all at once). The three queries'
# fixed cost was a fifth of a small apply with chunks of 8 in groups of 20-30 streams.
LOAD_CHUNK = 32
# SQLite: an apply of at most this many samples, of at most IN_LOCK_MAX_STREAMS streams, runs
# inside the write lock in one transaction when no other writer holds or waits for it.
IN_LOCK_MAX_SAMPLES = 64
IN_LOCK_MAX_STREAMS = 8
# PostgreSQL: a group whose applies so far average at least this many samples per stream is
# bounded by PROCESSOR_COMPUTE_BUDGET_S instead of PROCESSOR_TXN_BUDGET_S (Processor._bound_s).
LARGE_APPLY_SAMPLES = 1000
# Per-sample output retention runs at most this often (it scans the table).
SAMPLE_OUTPUT_PRUNE_EVERY_S = 60.0


class _StreamFailed(Exception):
    """Rolls back the transaction of a group of one stream whose apply raised."""


@dataclass(frozen=True)
class WaitOutcome:
    """What a wait for a batch ended with: applied, still pending, or the stream failed."""

    applied: bool
    failure: str | None = None


class Processor:
    """A background thread that applies pending batches, woken by ingest (in this process, or by
    ``NOTIFY`` from others) and by a periodic scan."""

    def __init__(
        self,
        db: Database,
        settings: Settings,
        hub: Hub | None = None,
        *,
        applied_channel: str | None = None,
        origin: str = "",
        ready_kinds: Callable[[], frozenset[str] | None] = lambda: None,
        announce: Callable[[list[str]], None] | None = None,
        forward: Callable[[Sequence[int]], None] | None = None,
        push_results: Callable[[ApplyResult], bool] | None = None,
        in_lock_applies: bool = True,
    ) -> None:
        self.db = db
        # Batches this process logged, decoded (the log writer fills it when this process applies).
        self.recent = RecentBatches() if settings.processor_enabled else None
        # Estimator states this process stored last, parsed (checked against each row read).
        self.hot = HotStates()
        self.settings = settings
        self.hub = hub or Hub()
        # PostgreSQL: the channel on which applies are announced to other processes.
        self.applied_channel = applied_channel
        self.origin = origin
        # SQLite apply process: sends the applied channel's payloads to the serving process
        # after each commit (app/processing/apply_process.py).
        self.announce = announce
        # ... and, before, the results of a stream whose connections are there (True when sent).
        self.push_results = push_results
        # A process that does not apply (processor_enabled false) and whose wake-ups reach the
        # applying process directly (SQLite apply process): where notify() sends them.
        self.forward = forward
        # SQLite: whether a small apply may run inside the write lock when it is free
        # (_apply_in_lock). An apply process computes outside it: the serving process's log
        # commits would wait for its computation, and the CPU the second read costs is its own.
        self.in_lock_applies = in_lock_applies
        # Estimator kinds whose kernels are ready (None: all); other streams wait, and are
        # woken by recover() when their kind becomes ready.
        self.ready_kinds = ready_kinds
        self._meta: OrderedDict[int, StreamMeta] = OrderedDict()
        self._queue: queue.SimpleQueue[int | None] = queue.SimpleQueue()
        # Latest applied marks seen here, so that a ?wait= on a batch already applied needs no
        # read; bounded (the store has the rest).
        self._applied: OrderedDict[int, int] = OrderedDict()
        self._applied_lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._attempts: dict[int, int] = {}
        self._retry_at: dict[int, float] = {}
        self._recheck_at: dict[int, float] = {}
        # Samples of each stream's last apply (SQLite: whether to apply it inside the write lock).
        self._sizes: OrderedDict[int, int] = OrderedDict()

    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, name="fleethealth-processor", daemon=True)
        self._thread.start()

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def stop(self, timeout: float = 10.0) -> None:
        self._stop.set()
        self._queue.put(None)
        if self._thread is not None:
            self._thread.join(timeout)

    def notify(self, actuator_pk: int) -> None:
        self.notify_many((actuator_pk,))

    def notify_many(self, actuator_pks: Sequence[int]) -> None:
        if self.settings.processor_enabled:  # else nobody would ever take it off the queue
            for pk in actuator_pks:
                self._queue.put(pk)
        elif self.forward is not None:
            self.forward(actuator_pks)

    def forget(self, actuator_pk: int) -> None:
        """Drop what this process remembers of a stream (after an admin rewind committed: its
        applied mark went back), and look at it again."""
        with self._applied_lock:
            self._applied.pop(actuator_pk, None)
        self.hot.forget(actuator_pk)  # would not match the rewound rows anyway: free it now
        self._attempts.pop(actuator_pk, None)
        self._retry_at.pop(actuator_pk, None)
        self.notify(actuator_pk)

    # ------------------------------------------------------------------ waiting
    async def wait_applied(self, actuator_pk: int, seq: int, timeout_s: float) -> WaitOutcome:
        """Wait until batch ``seq`` of the stream is applied, the stream is failed, or the
        time runs out: an awaitable resolved when the apply commits (here, or in another
        process through its notification), never a poll."""
        if self._applied.get(actuator_pk, 0) >= seq:
            return WaitOutcome(True)
        waiter = self.hub.watch_applied(actuator_pk, seq)
        try:
            applied, failure = await run_in_threadpool(self._read_mark, actuator_pk)
            if applied >= seq:
                return WaitOutcome(True)
            if failure is not None:
                return WaitOutcome(False, failure)
            try:
                ok, failure = await asyncio.wait_for(waiter.future, timeout_s)
            except TimeoutError:
                return WaitOutcome(False)
            return WaitOutcome(ok, failure)
        finally:
            self.hub.unwatch(actuator_pk, waiter)

    def known_applied(self, actuator_pk: int) -> int | None:
        """The stream's applied mark as last seen here (applied here or announced by another
        process), None when not remembered."""
        return self._applied.get(actuator_pk)

    def _remember_applied(self, actuator_pk: int, applied_seq: int) -> None:
        with self._applied_lock:  # the processor and the notification listener both call this
            if applied_seq > self._applied.get(actuator_pk, 0):
                self._applied[actuator_pk] = applied_seq
            self._applied.move_to_end(actuator_pk)
            while len(self._applied) > APPLIED_MARKS_CACHE:
                self._applied.popitem(last=False)

    def _read_mark(self, actuator_pk: int) -> tuple[int, str | None]:
        with self.db.read() as s:
            return repository.applied_mark(s, actuator_pk)

    def applied_elsewhere(
        self, actuator_pk: int, applied_seq: int, events: list[dict[str, Any]], wake: bool = True
    ) -> None:
        """Another process committed an apply of the stream (its notification): waiters and
        stream connections hear of it (``wake``: they read their results back; not when the
        results were pushed, :meth:`results_elsewhere`), fleet subscribers get its events."""
        self._remember_applied(actuator_pk, applied_seq)
        self.hub.mark_applied(actuator_pk, applied_seq)
        if wake:
            self.hub.wake_stream(actuator_pk)
        if events and self.hub.has_fleet_subscribers():
            self.hub.publish_fleet(events)

    def results_elsewhere(self, actuator_pk: int, items: list[Any]) -> None:
        """Results another process applied and sent (SQLite's apply process): pushed to the
        stream's connections, as this process's own are."""
        self.hub.publish_applied(actuator_pk, items)

    def resync(self) -> None:
        """Notifications may have been missed (the listener reconnected): every waiter and
        stream connection looks at the store again."""
        for pk in self.hub.watched_streams():
            applied, failure = self._read_mark(pk)
            self.hub.mark_applied(pk, applied)
            if failure is not None:
                self.hub.mark_failed(pk, failure)
        self.hub.wake_all_streams()

    # ------------------------------------------------------------------ applying
    def recover(self) -> int:
        """Wake every stream with pending batches (at start-up and on each scan)."""
        with self.db.read() as s:
            pks = repository.pending_streams(s)
            STREAMS_FAILED.set(repository.count_failed(s))
        for pk in pks:
            self.notify(pk)
        return len(pks)

    def apply_streams(self, actuator_pks: Sequence[int]) -> int:
        """Apply every pending batch of the streams, several streams per transaction; the
        number of batches applied."""
        applied = 0
        replayed: dict[int, set[str]] = {}
        waiting = sorted(set(actuator_pks))
        cap = self.settings.processor_max_streams_per_txn
        while waiting and not self._stop.is_set():
            part, waiting = waiting[:cap], waiting[cap:]
            again, n = self._apply_group(part, replayed)
            applied += n
            waiting = sorted(set(waiting) | set(again))
        return applied

    def _apply_group(self, pks: list[int], replayed: dict[int, set[str]]) -> tuple[list[int], int]:
        """One transaction over some streams: the streams to apply again, and the batches
        applied.

        On SQLite the streams are read and their estimators run in a read transaction first,
        outside the database's one write lock (which the log writer's acknowledgements wait
        for); the write transaction then only checks that each stream's rows are as read
        and stores the outcome (a stream whose rows changed meanwhile is applied again under
        the lock). On PostgreSQL one transaction holds the streams' row locks throughout.
        """
        t0 = time.perf_counter()
        results: list[ApplyResult] = []
        errors: list[tuple[int, Exception]] = []
        idle: list[int] = []
        left: list[int] = []
        # One stream alone needs no savepoint: its error rolls the whole transaction back.
        alone = len(pks) == 1
        try:
            in_lock = self._apply_in_lock(pks, t0, errors, idle, alone) if self._small(pks) else None
            path = "one_transaction"
            if in_lock is not None:
                results, left = in_lock
            elif self.db.is_sqlite:
                path = "computed_outside"
                with self.db.read() as rs:
                    prepared, left = self._prepare(rs, pks, t0, errors, idle)
                if prepared:
                    # Not waiting for the disk: an apply lost in a power cut is redone from the log.
                    with self.db.write(durable=False) as s:
                        current = service.load_current(s, [p.result.actuator_pk for p in prepared], is_sqlite=True)
                        results = self._store(s, prepared, errors, alone, current)
            else:
                with self.db.write(durable=False) as s:
                    results, left = self._apply_locked(s, pks, t0, errors, idle, alone)
                    if self.applied_channel is not None and results:
                        # One statement for the group's notifications (one per stream, in order).
                        repository.notify_many(s, self.applied_channel,
                                               [p for res in results for p in self._announcements(s, res)])
        except _StreamFailed:  # the one stream's error (in errors): its transaction is rolled back
            results.clear()
        except Exception as commit_exc:  # the commit failed: no stream of the group was applied
            for pk in pks:
                self._attempt_failed(pk, commit_exc)
            return [], 0
        if results:
            APPLY_GROUPS.labels(path).inc()
            APPLY_SECONDS.observe(time.perf_counter() - t0)
            if sum(r.samples for r in results) >= RELEASE_AFTER_SAMPLES:
                release_memory()  # the freed batches' heap back to the OS (docs/operations.md)
        again = list(left)
        for res in results:
            self._remember_size(res)
            self._attempts.pop(res.actuator_pk, None)
            self._retry_at.pop(res.actuator_pk, None)
            BATCHES_APPLIED.inc(res.batches)
            SAMPLES_APPLIED.inc(res.samples)
            self._remember_applied(res.actuator_pk, res.last_applied_seq)
            self.hub.mark_applied(res.actuator_pk, res.last_applied_seq)
            self._publish(res)
            if res.more:
                again.append(res.actuator_pk)
        if self.announce is not None and results:
            self._announce(results)
        for pk, err in errors:
            if isinstance(err, StateUnreadable):
                done = replayed.setdefault(pk, set())
                if err.estimator in done:
                    # A state the estimator just wrote cannot be read back: a bug, not an upgrade.
                    self._attempt_failed(pk, err)
                elif self._replay(pk, err):
                    done.add(err.estimator)
                    again.append(pk)
            else:
                self._attempt_failed(pk, err)
        if idle and not self.db.is_sqlite:
            self._recheck_busy(idle)
        return again, sum(r.batches for r in results)

    def _small(self, pks: list[int]) -> bool:
        """SQLite: whether the streams' last applies were all small (the likely size of this
        one): a few streams, each of at most ``IN_LOCK_MAX_SAMPLES`` samples last time."""
        return (self.db.is_sqlite and self.in_lock_applies and len(pks) <= IN_LOCK_MAX_STREAMS
                and all(self._sizes.get(pk, IN_LOCK_MAX_SAMPLES + 1) <= IN_LOCK_MAX_SAMPLES for pk in pks))

    def _remember_size(self, res: ApplyResult) -> None:
        self._sizes[res.actuator_pk] = res.samples
        self._sizes.move_to_end(res.actuator_pk)
        while len(self._sizes) > APPLIED_MARKS_CACHE:
            self._sizes.popitem(last=False)

    def _apply_in_lock(
        self, pks: list[int], t0: float, errors: list[tuple[int, Exception]], idle: list[int], alone: bool
    ) -> tuple[list[ApplyResult], list[int]] | None:
        """SQLite, a small apply while no other writer holds or waits for the write lock: the
        whole apply in one write transaction, as on PostgreSQL, without the read transaction
        and the second read of the rows that computing outside the lock costs (about a sixth
        of a one-sample apply). A writer that comes meanwhile waits for the computation too,
        which for at most ``IN_LOCK_MAX_SAMPLES`` samples is short. None, with nothing
        written, when the lock is taken or waited for, or the pending batches turn out larger
        (the caller then computes outside the lock)."""
        with self.db.write_if_free(durable=False) as s:
            if s is None:
                return None
            loaded = self._load(s, pks, 0, service.GroupLoad({}, {}, {}))
            if sum(b.n_samples for c in loaded.candidates.values() for b in c) > IN_LOCK_MAX_SAMPLES:
                return None  # an empty transaction: the batches are computed outside the lock
            return self._apply_locked(s, pks, t0, errors, idle, alone, first=loaded)

    def _limits(self) -> dict[str, Any]:
        return {
            "max_batches": self.settings.processor_max_batches_per_txn,
            "store_outputs": self.settings.store_sample_outputs,
            "is_sqlite": self.db.is_sqlite,
            "ready_kinds": self.ready_kinds(),
            "hot": self.hot,
        }

    def _load(self, session: Session, pks: list[int], i: int, loaded: service.GroupLoad) -> service.GroupLoad:
        """The rows of the group's streams from the i-th on, read a few streams at a time."""
        if i % LOAD_CHUNK:
            return loaded
        return service.load_group(session, pks[i : i + LOAD_CHUNK], is_sqlite=self.db.is_sqlite,
                                  max_batches=self.settings.processor_max_batches_per_txn)

    def _over(self, i: int, t0: float, budget: int, seconds: float) -> bool:
        # Bound the group's length: every stream of it waits for its commit, and a write
        # transaction holds the database's write lock (SQLite) or the streams' locks (PostgreSQL).
        return budget <= 0 or (i > 0 and time.perf_counter() - t0 > seconds)

    def _bound_s(self, samples: int, streams: int) -> float:
        """How long a transaction that holds its streams (PostgreSQL's row locks; SQLite's write
        lock for its small in-lock applies) may run before no further stream joins it: the
        short ``processor_txn_budget_s``, unless the group's applies so far (``samples`` over
        ``streams``) average ``LARGE_APPLY_SAMPLES`` samples or more per stream; then
        ``processor_compute_budget_s``.
        A large apply alone outlasts the short bound, so under it every group held one stream
        and paid the group's fixed cost per stream (docs/benchmarks.md, "PostgreSQL: apply
        groups of large batches"); small applies keep the short bound, as their results wait
        for the commit."""
        if streams and samples >= LARGE_APPLY_SAMPLES * streams:
            return self.settings.processor_compute_budget_s
        return self.settings.processor_txn_budget_s

    def _prepare(
        self, session: Session, pks: list[int], t0: float, errors: list[tuple[int, Exception]], idle: list[int]
    ) -> tuple[list[service.PreparedApply], list[int]]:
        """Compute the applies of the streams (nothing written): the prepared ones, and the
        streams left for the next group by the limits."""
        prepared: list[service.PreparedApply] = []
        budget = self.settings.processor_max_samples_per_txn
        limits = self._limits()
        loaded = service.GroupLoad({}, {}, {})
        for i, pk in enumerate(pks):
            if self._over(i, t0, budget, self.settings.processor_compute_budget_s):
                return prepared, pks[i:]
            loaded = self._load(session, pks, i, loaded)
            try:
                prep = service.prepare_apply(session, pk, max_samples=budget, recent=self.recent, loaded=loaded,
                                             **limits)
            except Exception as exc:  # nothing of it was written
                errors.append((pk, exc))
                continue
            if prep is None:
                idle.append(pk)
                continue
            budget -= prep.result.samples
            prepared.append(prep)
        return prepared, []

    def _apply_locked(
        self, session: Session, pks: list[int], t0: float, errors: list[tuple[int, Exception]], idle: list[int],
        alone: bool, first: service.GroupLoad | None = None,
    ) -> tuple[list[ApplyResult], list[int]]:
        """Apply the streams in this transaction, which holds their row locks (PostgreSQL) or
        the write lock (SQLite): each stream's estimators run (a stream whose run raises is
        left out, nothing of it written), then the group is stored (:meth:`_store_group`);
        the results and the streams left by the limits. ``first``: the rows of the first
        streams, already read here."""
        prepared: list[service.PreparedApply] = []
        left: list[int] = []
        budget = self.settings.processor_max_samples_per_txn
        limits = self._limits()
        loaded = first or service.GroupLoad({}, {}, {})
        for i, pk in enumerate(pks):
            bound = self._bound_s(self.settings.processor_max_samples_per_txn - budget, len(prepared))
            if self._over(i, t0, budget, bound):
                left = pks[i:]
                break
            if i or first is None:
                loaded = self._load(session, pks, i, loaded)
            try:
                prep = service.prepare_apply(session, pk, max_samples=budget, recent=self.recent, loaded=loaded,
                                             **limits)
            except Exception as exc:  # nothing of it was written
                errors.append((pk, exc))
                if alone:
                    raise _StreamFailed from exc
                continue
            if prep is None:
                idle.append(pk)
                continue
            budget -= prep.result.samples
            prepared.append(prep)
        return self._store_group(session, prepared, errors, alone), left

    def _store(
        self,
        session: Session,
        prepared: list[service.PreparedApply],
        errors: list[tuple[int, Exception]],
        alone: bool,
        current: service.GroupLoad,
    ) -> list[ApplyResult]:
        """Store applies prepared outside this transaction (SQLite) as a group
        (:meth:`_store_group`); a stream whose rows are no longer those it was computed from
        is applied again here, under the write lock, in its own savepoint."""
        fresh = [p for p in prepared if service.still_current(p, current)]
        results = self._store_group(session, fresh, errors, alone)
        stored = {id(p) for p in fresh}
        for prep in prepared:
            if id(prep) in stored:
                continue
            pk = prep.result.actuator_pk
            try:
                with contextlib.nullcontext() if alone else session.begin_nested():
                    res = service.apply_pending(session, pk, max_samples=prep.result.samples or 1, **self._limits())
            except Exception as exc:  # this stream's savepoint is rolled back
                errors.append((pk, exc))
                if alone:
                    raise _StreamFailed from exc
                continue
            if res is not None:
                results.append(res)
        return results

    def _store_group(
        self, session: Session, prepared: list[service.PreparedApply], errors: list[tuple[int, Exception]],
        alone: bool,
    ) -> list[ApplyResult]:
        """Store the prepared applies of a group: all of them with one statement per table,
        inside one savepoint; if that raises, the savepoint is rolled back and the streams are
        stored one by one, each in its own savepoint, so that only the stream at fault is left
        out (its error in ``errors``). One stream alone needs no savepoint: its error rolls the
        whole transaction back."""
        if not prepared:
            return []
        if alone:
            try:
                return service.store_group(session, prepared)
            except Exception as exc:
                errors.append((prepared[0].result.actuator_pk, exc))
                raise _StreamFailed from exc
        try:
            with session.begin_nested():
                return service.store_group(session, prepared)
        except Exception:
            GROUP_STORE_SPLITS.inc()
            log.warning("storing a group of %d streams failed; storing them one by one", len(prepared),
                        exc_info=True)
        results: list[ApplyResult] = []
        for prep in prepared:
            try:
                with session.begin_nested():
                    results.append(service.store_apply(session, prep))
            except Exception as exc:  # this stream's savepoint is rolled back
                errors.append((prep.result.actuator_pk, exc))
        return results

    def _recheck_busy(self, pks: list[int]) -> None:
        """PostgreSQL: a stream found idle may have been held by another worker (``SKIP
        LOCKED``) while a batch was logged; look again shortly rather than wait for the scan."""
        try:
            with self.db.read() as s:
                pending = repository.streams_pending(s, pks)
        except Exception:
            log.exception("re-checking streams %s failed; the scan will", pks)
            return
        due = time.monotonic() + BUSY_RECHECK_S
        for pk in pending:
            self._recheck_at[pk] = due

    def _announce(self, results: list[ApplyResult]) -> None:
        """Send the applies to the serving process after their commit (apply process): the
        results of watched streams, then the applied channel's payloads. A lost one delays a
        waiter until the serving process re-reads (it does when the process restarts)."""
        assert self.announce is not None
        try:
            payloads: list[str] = []
            for res in results:
                pushed = self.push_results is not None and self.push_results(res)
                payloads.extend(self._announcements(None, res, pushed=pushed))
            self.announce(payloads)
        except Exception:
            log.exception("announcing %d applies failed", len(results))

    def _announcements(self, session: Session | None, res: ApplyResult, *, pushed: bool = False) -> list[str]:
        """The NOTIFY payloads of an apply: its mark and its fleet events, split to fit
        (``"r": 1``: its results were sent ahead)."""
        meta = self._stream_meta(res.actuator_pk, session)
        events = fleet_events(meta, res)
        extra = {"r": 1} if pushed else {}
        return [
            orjson.dumps({"o": self.origin, "pk": res.actuator_pk, "seq": res.last_applied_seq, "ev": chunk, **extra},
                         option=orjson.OPT_SERIALIZE_NUMPY).decode()
            for chunk in _chunks(events, NOTIFY_MAX_BYTES)
        ]

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
        if isinstance(exc, STORAGE_FAULTS):
            # The database is unreachable or full, the stream is not broken: retry (without a
            # limit) once it is back; nothing of the attempt was committed.
            self._retry_at[actuator_pk] = time.monotonic() + self.settings.processor_retry_backoff_s
            log.warning("applying stream %s: storage unavailable (%s); retrying", actuator_pk, exc)
            return
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
        if self.applied_channel is not None:
            payload = {"o": self.origin, "pk": actuator_pk, "failure": reason[: NOTIFY_MAX_BYTES // 2]}
            repository.notify(session, self.applied_channel, orjson.dumps(payload).decode())

    def _after_failed(self, actuator_pk: int) -> None:
        self._attempts.pop(actuator_pk, None)
        self._retry_at.pop(actuator_pk, None)
        with self.db.read() as s:
            STREAMS_FAILED.set(repository.count_failed(s))
            _, failure = repository.applied_mark(s, actuator_pk)
        if failure is not None:
            self.hub.mark_failed(actuator_pk, failure)
            if self.announce is not None:
                payload = {"o": self.origin, "pk": actuator_pk, "failure": failure[: NOTIFY_MAX_BYTES // 2]}
                try:
                    self.announce([orjson.dumps(payload).decode()])
                except Exception:
                    log.exception("announcing the failure of stream %s failed", actuator_pk)

    # ------------------------------------------------------------------ publishing
    def _publish(self, res: ApplyResult) -> None:
        """Tell this process's subscribers what was committed (never blocks; a failure only
        loses pushes)."""
        try:
            self.hub.publish_applied(res.actuator_pk, res.applied)
            if self.hub.has_fleet_subscribers():
                self.hub.publish_fleet(fleet_events(self._stream_meta(res.actuator_pk), res))
        except Exception:
            log.exception("publishing results of stream %s failed", res.actuator_pk)

    def _stream_meta(self, actuator_pk: int, session: Session | None = None) -> StreamMeta:
        meta = self._meta.get(actuator_pk)
        if meta is not None:
            self._meta.move_to_end(actuator_pk)
            return meta
        if session is not None:
            meta = StreamMeta(*repository.stream_owner(session, actuator_pk))
        else:
            with self.db.read() as s:
                meta = StreamMeta(*repository.stream_owner(s, actuator_pk))
        self._meta[actuator_pk] = meta
        while len(self._meta) > STREAM_META_CACHE:
            self._meta.popitem(last=False)
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
                    with self.db.write() as s:
                        fleet.purge_deleted(s, self.settings.deleted_retention_s)
                    if self.settings.sample_output_retention_s is not None and now >= next_prune:
                        next_prune = now + SAMPLE_OUTPUT_PRUNE_EVERY_S
                        with self.db.write() as s:
                            repository.drop_old_sample_outputs(s, self.settings.sample_output_retention_s)
                except Exception:
                    log.exception("periodic scan failed")
                next_scan = now + self.settings.processor_scan_interval_s
            wake_at = min([next_scan, *self._recheck_at.values()])
            woken: set[int] = set()
            try:
                pk = self._queue.get(timeout=max(0.0, wake_at - time.monotonic()))
                if pk is not None:
                    woken.add(pk)
            except queue.Empty:
                pass
            # Coalesce: every stream woken meanwhile joins this round.
            while True:
                try:
                    more = self._queue.get_nowait()
                except queue.Empty:
                    break
                if more is not None:
                    woken.add(more)
            now = time.monotonic()
            for p, at in list(self._recheck_at.items()):
                if at <= now:
                    woken.add(p)
                    del self._recheck_at[p]
            ready = [p for p in woken if now >= self._retry_at.get(p, 0.0)]  # others back off
            if ready:
                self.apply_streams(ready)


def _chunks(events: list[dict[str, Any]], max_bytes: int) -> Iterator[list[dict[str, Any]]]:
    """The events in lists whose JSON stays under ``max_bytes`` (at least one list, maybe
    empty; an event larger than the bound travels alone)."""
    chunk: list[dict[str, Any]] = []
    size = 0
    for ev in events:
        n = len(orjson.dumps(ev, option=orjson.OPT_SERIALIZE_NUMPY)) + 1
        if chunk and size + n > max_bytes:
            yield chunk
            chunk, size = [], 0
        chunk.append(ev)
        size += n
    yield chunk
