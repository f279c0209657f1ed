"""Group commit of the telemetry log: one thread appends whatever is queued in one transaction.

Every append (a REST batch or a WebSocket frame, of any stream) is handed to :class:`LogWriter`
as an already parsed and checked batch. The writer thread takes the first queued append and
every other one queued behind it (up to ``max_group``), locks their actuator rows in primary-key
order (two API processes on one PostgreSQL never deadlock), runs the log's rules
(:func:`app.telemetry.service.log_batch`) for each in arrival order, and commits them together.
The group costs a fixed number of Core statements (lock the heads, find the retries, insert the
rows, advance the heads), not a round of ORM work per append.
Each append's future is resolved only after that commit: an acknowledgement still means the batch
is durable (invariant 1), but one fsync (SQLite) or one commit round trip (PostgreSQL) now covers
every batch that arrived while the previous group was being written.

An append refused by the rules (a stale or conflicting batch, a deleted actuator) gets its own
error and writes nothing, so it never spoils the rest of its group. Any other error rolls the group
back, and each of its appends is then tried alone, so that only the faulty one fails.

After each commit ``on_logged`` is called with the streams that received new batches (the
in-process processor's wake-up); on PostgreSQL the same wake-up is also sent by ``NOTIFY`` inside
the transaction, so it reaches worker processes exactly when the batches become visible.
"""

from __future__ import annotations

import contextlib
import logging
import queue
import threading
from collections.abc import Callable, Sequence
from concurrent.futures import Future, InvalidStateError
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from prometheus_client import Histogram
from sqlalchemy.exc import IntegrityError

from app.db import Database
from app.errors import ActuatorDeleted, DomainError, IdempotencyConflict
from app.ingest import ParsedBatch
from app.models import utcnow
from app.processing.recent import RecentBatches
from app.telemetry import repository
from app.telemetry.repository import LoggedBatch

if TYPE_CHECKING:
    from app.telemetry.service import Ack

log = logging.getLogger("fleethealth.log_writer")

GROUP_SIZE = Histogram(
    "fleethealth_log_group_appends",
    "Appends committed per telemetry log transaction",
    buckets=(1, 2, 4, 8, 16, 32, 64, 128, 256, 512),
)

@dataclass(eq=False)
class _Append:
    actuator_pk: int
    batch: ParsedBatch
    future: Future[Ack] = field(default_factory=Future)


class LogWriter:
    """The one writer of the telemetry log in this process (start it before submitting)."""

    def __init__(
        self,
        db: Database,
        *,
        max_group: int = 256,
        on_logged: Callable[[Sequence[int]], None] | None = None,
        notify_channel: str | None = None,
        origin: str = "",
        recent: RecentBatches | None = None,
    ) -> None:
        self.db = db
        self.max_group = max_group
        self.on_logged = on_logged
        # PostgreSQL: NOTIFY channel for the wake-ups of worker processes (None on SQLite).
        self.notify_channel = notify_channel
        self.origin = origin
        # The in-process processor's shortcut: committed batches, already decoded.
        self.recent = recent
        self._queue: queue.SimpleQueue[_Append | None] = queue.SimpleQueue()
        self._thread: threading.Thread | None = None
        self._stopping = False

    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, name="fleethealth-log-writer", daemon=True)
        self._thread.start()

    def stop(self, timeout: float = 10.0) -> None:
        """Commit what is queued, then stop."""
        self._stopping = True
        self._queue.put(None)
        if self._thread is not None:
            self._thread.join(timeout)

    def submit(self, actuator_pk: int, batch: ParsedBatch) -> Future[Ack]:
        """Queue an append; the future resolves to its :class:`~app.telemetry.service.Ack` once
        committed (or to the error that refused it)."""
        item = _Append(actuator_pk, batch)
        if self._thread is None or not self._thread.is_alive():
            item.future.set_exception(RuntimeError("the telemetry log writer is not running"))
            return item.future
        self._queue.put(item)
        return item.future

    # ------------------------------------------------------------------ the thread
    def _run(self) -> None:
        while True:
            first = self._queue.get()
            if first is None:
                if self._stopping and self._queue.empty():
                    return
                continue
            group = [first]
            while len(group) < self.max_group:
                try:
                    nxt = self._queue.get_nowait()
                except queue.Empty:
                    break
                if nxt is None:
                    self._queue.put(None)  # keep the stop request for after this group
                    break
                group.append(nxt)
            try:
                self._write(group)
            except Exception as exc:  # the thread must outlive any one group
                log.exception("the log writer failed on a group of %d appends", len(group))
                for item in group:
                    _settle(item.future, exc)
            # Nothing of a committed group (its decoded batches) stays referenced until the next.
            del first, group
            nxt = None

    def _write(self, group: list[_Append]) -> None:
        GROUP_SIZE.observe(len(group))
        try:
            outcomes = self._commit(group)
        except Exception as exc:
            if len(group) == 1:
                if isinstance(exc, IntegrityError):
                    # Only if a writer appended without the actuator's row lock.
                    exc = IdempotencyConflict(
                        f"batch_id {group[0].batch.batch_id!r} is being logged concurrently; retry")
                _settle(group[0].future, exc)
                return
            log.warning("a group of %d appends failed (%s); committing them one by one", len(group), exc)
            for item in group:
                self._write([item])
            return
        logged: list[int] = []
        for item, outcome in zip(group, outcomes, strict=True):
            if isinstance(outcome, DomainError):
                _settle(item.future, outcome)
            else:
                if not outcome.replayed:
                    logged.append(item.actuator_pk)
                _settle(item.future, outcome)
        if logged and self.on_logged is not None:
            try:
                self.on_logged(sorted(set(logged)))
            except Exception:  # a lost wake-up is caught up by the processor's scan
                log.exception("waking the processor failed")

    def _commit(self, group: list[_Append]) -> list[Ack | DomainError]:
        outcomes: list[Ack | DomainError] = []
        held: list[tuple[int, int]] = []  # the batches put in ``recent`` for this commit
        try:
            self._transaction(group, outcomes, held)
        except BaseException:
            if self.recent is not None:
                self.recent.drop(held)
            raise
        if self.recent is not None:
            self.recent.confirm(held)
        return outcomes

    def _transaction(self, group: list[_Append], outcomes: list[Ack | DomainError],
                     held: list[tuple[int, int]]) -> None:
        """Append the group in one transaction. Each new batch is put, decoded, in ``recent``
        before the commit (the commit's NOTIFY may wake a processor at once); the caller
        confirms them after the commit, or drops them if it failed."""
        from app.telemetry.service import log_batch

        received_at = utcnow()
        with self.db.write() as s:
            heads = repository.lock_log_heads(s, sorted({i.actuator_pk for i in group}))
            priors = repository.logged_by_ids(s, [(i.actuator_pk, i.batch.batch_id) for i in group])
            rows: list[dict[str, object]] = []
            for item in group:
                key = (item.actuator_pk, item.batch.batch_id)
                head = heads.get(item.actuator_pk)
                try:
                    if head is None:
                        # Refused like a stale frame (a WebSocket closes with a policy code and this detail).
                        raise ActuatorDeleted("the actuator was deleted; its stream takes no more frames")
                    ack, row = log_batch(head, item.batch, priors.get(key), received_at)
                except DomainError as exc:
                    outcomes.append(exc)
                    continue
                if row is not None:
                    rows.append(row)
                    if self.recent is not None:
                        b = item.batch
                        put = self.recent.put(item.actuator_pk, ack.seq, b.batch_id, b.t_s, b.channels, b.end_of_run)
                        if put is not None:
                            held.append(put)
                    # The same batch id again later in this group is a retry of this one.
                    priors[key] = LoggedBatch(ack.seq, ack.batch_id, str(row["content_hash"]), ack.n_samples,
                                              ack.t_first_s, ack.t_last_s, ack.received_at, ack.end_of_run)
                outcomes.append(ack)
            repository.insert_batches(s, rows)
            advanced = {a.actuator_pk for a in outcomes if not isinstance(a, DomainError) and not a.replayed}
            repository.advance_heads(s, [heads[pk] for pk in sorted(advanced)])
            if self.notify_channel is not None and advanced:
                repository.notify(s, self.notify_channel, f"{self.origin} " + ",".join(map(str, sorted(advanced))))


def _settle(future: Future[Ack], outcome: Ack | BaseException) -> None:
    """Resolve an append's future unless it is already done: its waiter may have gone (a
    WebSocket dropped mid-frame cancels it). The append itself stays committed; a sender that
    never saw the ack resends it and gets the first answer (idempotent)."""
    if future.done():
        return
    with contextlib.suppress(InvalidStateError):  # cancelled between the check and here
        if isinstance(outcome, BaseException):
            future.set_exception(outcome)
        else:
            future.set_result(outcome)
