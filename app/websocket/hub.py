"""In-process publish/subscribe of applied results and fleet events, and the applied marks
that ``?wait=`` awaits.

The processor thread publishes after each committed apply; WebSocket handlers in the event loop
subscribe. When the processor runs in other processes (``fleethealth worker`` on PostgreSQL), the
wake-up listener (:mod:`app.processing.wakeups`) feeds the same hub from their notifications:
:meth:`Hub.wake_stream` tells a stream's connections to read their results back from the store,
:meth:`Hub.publish_fleet` relays the fleet events the worker computed, and
:meth:`Hub.mark_applied` resolves waiters. Publishing never blocks the processor: each subscriber has a bounded queue, filled
with ``loop.call_soon_threadsafe``; a subscriber whose queue is full is marked ``overflowed``
and its connection closes it (a slow consumer is dropped, never waited for). Every hand-over to a
loop goes through that loop's :class:`Inbox`: one ``call_soon_threadsafe`` (one wake-up of the
loop) per burst, however many subscribers and results it carries.

Fleet events (JSON objects with a ``type``):

* ``status_changed``: an actuator's worst status changed (``from``, ``to``, ``reasons``);
* estimator events of the kinds in :data:`FLEET_EVENT_KINDS` (fault detections and clearances,
  RUL and deterioration thresholds crossed), with the estimator's ``detail``;
* ``applied`` (only when asked for): one per applied batch, with the status and the last value
  of each per-sample output, for live boards.
"""

from __future__ import annotations

import asyncio
import logging
import threading
import weakref
from collections.abc import Callable, Iterable, Sequence
from concurrent.futures import Future
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, TypeVar

if TYPE_CHECKING:
    from app.processing.service import ApplyResult

FLEET_EVENT_KINDS = frozenset(
    {"fault_detected", "fault_cleared", "rul_threshold_crossed", "dn_threshold_crossed"}
)
DEFAULT_FLEET_TYPES = frozenset({"status_changed", *FLEET_EVENT_KINDS})
ALL_FLEET_TYPES = frozenset({*DEFAULT_FLEET_TYPES, "applied"})


log = logging.getLogger("fleethealth.hub")
T = TypeVar("T")


class Inbox:
    """Calls handed to one event loop from other threads, run there in batches.

    ``loop.call_soon_threadsafe`` writes to the loop's self-pipe and wakes it once per call; a
    group commit of 200 frames, or a group apply of 200 streams, would wake it 200 times, each
    wake-up a hand-over of the GIL. :meth:`put` queues the call and schedules one run of the
    queue only when none is pending: the calls of a burst are run together, in order.
    """

    def __init__(self, loop: asyncio.AbstractEventLoop) -> None:
        self.loop = loop
        self._calls: list[tuple[Callable[..., None], tuple[Any, ...]]] = []
        self._lock = threading.Lock()
        self._scheduled = False

    def put(self, fn: Callable[..., None], *args: Any) -> None:
        """Call ``fn(*args)`` in the loop soon (any thread; never blocks on the loop)."""
        with self._lock:
            self._calls.append((fn, args))
            if self._scheduled:
                return
            self._scheduled = True
        try:
            self.loop.call_soon_threadsafe(self._run)
        except RuntimeError:  # the loop is closed: its subscribers and waiters are gone
            with self._lock:
                self._calls.clear()
                self._scheduled = False

    def wrap(self, fut: Future[T]) -> asyncio.Future[T]:
        """An awaitable of a thread's future, as ``asyncio.wrap_future`` but resolved through
        this inbox (call it in the loop). Cancelling the awaitable leaves ``fut`` alone: what it
        stands for (an append being committed) completes anyway."""
        out: asyncio.Future[T] = self.loop.create_future()
        fut.add_done_callback(lambda done: self.put(_copy_outcome, done, out))
        return out

    def _run(self) -> None:
        with self._lock:
            calls, self._calls = self._calls, []
            self._scheduled = False
        for fn, args in calls:
            try:
                fn(*args)
            except Exception:  # one bad call must not lose the others of its burst
                log.exception("a call handed to the event loop failed")


def _copy_outcome(src: Future[T], dst: asyncio.Future[T]) -> None:
    if dst.done():  # cancelled: its awaiter is gone
        return
    if src.cancelled():
        dst.cancel()
        return
    exc = src.exception()
    if exc is not None:
        dst.set_exception(exc)
    else:
        dst.set_result(src.result())


_inboxes: weakref.WeakKeyDictionary[asyncio.AbstractEventLoop, Inbox] = weakref.WeakKeyDictionary()
_inboxes_lock = threading.Lock()


def inbox(loop: asyncio.AbstractEventLoop) -> Inbox:
    """The :class:`Inbox` of ``loop`` (one per loop, made on first use)."""
    box = _inboxes.get(loop)
    if box is None:
        with _inboxes_lock:
            box = _inboxes.get(loop)
            if box is None:
                box = _inboxes[loop] = Inbox(loop)
    return box


@dataclass(frozen=True)
class StreamMeta:
    """Who owns a stream: fleet events carry the tail and actuator id, filtered by operator."""

    operator_id: int
    tail: str
    actuator_id: str


@dataclass(eq=False)
class Subscription:
    """One subscriber's bounded queue, owned by an event loop."""

    loop: asyncio.AbstractEventLoop
    queue: asyncio.Queue[Any]
    accept: Callable[[Any], bool] = field(default=lambda _item: True)
    overflowed: bool = False
    wakeup: asyncio.Event = field(default_factory=asyncio.Event)
    # Only wake the subscriber up (it reads what happened from the durable event log).
    wake_only: bool = False
    # Results of the stream were committed where they could not be pushed from (another
    # process): the subscriber reads them back from the store.
    stale: bool = False

    def mark_stale(self) -> None:
        """Tell the subscriber to read its results back from the store (in its loop)."""
        self.stale = True
        self.wakeup.set()

    def _offer(self, item: Any) -> None:  # runs in the subscriber's loop
        if self.wake_only:
            self.wakeup.set()
            return
        if self.overflowed:
            return
        try:
            self.queue.put_nowait(item)
        except asyncio.QueueFull:
            self.overflowed = True
        self.wakeup.set()

    def offer(self, item: Any) -> None:
        """Called from any thread; never blocks."""
        if self.accept(item):
            inbox(self.loop).put(self._offer, item)


@dataclass(eq=False)
class Waiter:
    """One ``?wait=``: resolved with ``(applied, failure)``."""

    seq: int
    future: asyncio.Future[tuple[bool, str | None]]


def _set_once(fut: asyncio.Future[tuple[bool, str | None]], outcome: tuple[bool, str | None]) -> None:
    if not fut.done():
        fut.set_result(outcome)


class Hub:
    """Routes applied results to the connections streaming into an actuator, and fleet events
    to fleet subscribers."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._streams: dict[int, set[Subscription]] = {}
        self._fleet: set[Subscription] = set()
        # ?wait=: stream -> waiters (seq, future) resolved when an apply commits or it fails.
        self._waiters: dict[int, set[Waiter]] = {}
        #: Called (stream, True) when a stream gets its first connection, (stream, False) when it
        #: loses its last (SQLite's apply process pushes the results of such streams here).
        self.on_watch: Callable[[int, bool], None] | None = None

    # ------------------------------------------------------------------ applied marks
    def watch_applied(self, actuator_pk: int, seq: int) -> Waiter:
        """A waiter for batch ``seq`` of the stream, resolved by :meth:`mark_applied` or
        :meth:`mark_failed` (register it before reading the mark from the store: no commit is
        missed in between)."""
        w = Waiter(seq, asyncio.get_running_loop().create_future())
        with self._lock:
            self._waiters.setdefault(actuator_pk, set()).add(w)
        return w

    def unwatch(self, actuator_pk: int, waiter: Waiter) -> None:
        with self._lock:
            ws = self._waiters.get(actuator_pk)
            if ws is not None:
                ws.discard(waiter)
                if not ws:
                    del self._waiters[actuator_pk]

    def mark_applied(self, actuator_pk: int, applied_seq: int) -> None:
        """Batches up to ``applied_seq`` of the stream are committed as applied (any thread)."""
        self._resolve(actuator_pk, lambda w: (True, None) if w.seq <= applied_seq else None)

    def mark_failed(self, actuator_pk: int, reason: str) -> None:
        """The stream is failed: its waiters and its connections hear it at once (any
        thread; the connections read the failure back from the store)."""
        self._resolve(actuator_pk, lambda _w: (False, reason))
        self.wake_stream(actuator_pk)

    def _resolve(self, actuator_pk: int, outcome: Callable[[Waiter], tuple[bool, str | None] | None]) -> None:
        with self._lock:
            ws = self._waiters.get(actuator_pk)
            if not ws:
                return
            done = [(w, o) for w in ws if (o := outcome(w)) is not None]
            for w, _ in done:
                ws.discard(w)
            if not ws:
                del self._waiters[actuator_pk]
        for w, o in done:
            inbox(w.future.get_loop()).put(_set_once, w.future, o)

    def watched_streams(self) -> list[int]:
        with self._lock:
            return list(self._waiters)

    def streams(self) -> list[int]:
        """Streams with at least one connection here."""
        with self._lock:
            return list(self._streams)

    def wake_all_streams(self) -> None:
        for pk in self.streams():
            self.wake_stream(pk)

    def wake_stream(self, actuator_pk: int) -> None:
        """Batches of the stream were applied elsewhere: its connections read their results
        back from the store (any thread)."""
        with self._lock:
            subs = list(self._streams.get(actuator_pk, ()))
        for sub in subs:
            inbox(sub.loop).put(sub.mark_stale)

    # ------------------------------------------------------------------ subscriptions
    def subscribe_stream(self, actuator_pk: int, maxsize: int) -> Subscription:
        sub = Subscription(asyncio.get_running_loop(), asyncio.Queue(maxsize))
        with self._lock:
            first = actuator_pk not in self._streams
            self._streams.setdefault(actuator_pk, set()).add(sub)
        if first and self.on_watch is not None:
            self.on_watch(actuator_pk, True)
        return sub

    def subscribe_fleet(
        self, operator_id: int, tails: Iterable[str] | None, types: Iterable[str], maxsize: int
    ) -> Subscription:
        tail_set = frozenset(tails) if tails else None
        type_set = frozenset(types)

        def accept(ev: dict[str, Any]) -> bool:
            return (
                ev["_operator_id"] == operator_id
                and ev["type"] in type_set
                and (tail_set is None or ev["tail"] in tail_set)
            )

        sub = Subscription(asyncio.get_running_loop(), asyncio.Queue(maxsize), accept)
        with self._lock:
            self._fleet.add(sub)
        return sub

    def subscribe_fleet_wakeup(self, operator_id: int) -> Subscription:
        """Woken when this process applied a batch that produced fleet events of the operator
        (other processes' are found by re-reading the log)."""

        def accept(ev: dict[str, Any]) -> bool:
            return bool(ev["_operator_id"] == operator_id and ev["type"] != "applied")

        sub = Subscription(asyncio.get_running_loop(), asyncio.Queue(1), accept, wake_only=True)
        with self._lock:
            self._fleet.add(sub)
        return sub

    def unsubscribe(self, sub: Subscription) -> None:
        with self._lock:
            self._fleet.discard(sub)
            for subs in self._streams.values():
                subs.discard(sub)
            gone = [pk for pk, subs in self._streams.items() if not subs]
            for pk in gone:
                del self._streams[pk]
        if self.on_watch is not None:
            for pk in gone:
                self.on_watch(pk, False)

    # ------------------------------------------------------------------ publishing
    def has_fleet_subscribers(self) -> bool:
        return bool(self._fleet)

    def publish_applied(self, actuator_pk: int, items: Sequence[Any]) -> None:
        with self._lock:
            subs = list(self._streams.get(actuator_pk, ()))
        for sub in subs:
            for item in items:
                sub.offer(item)

    def publish_fleet(self, events: list[dict[str, Any]]) -> None:
        with self._lock:
            subs = list(self._fleet)
        for sub in subs:
            for ev in events:
                sub.offer(ev)


def fleet_events(meta: StreamMeta, result: ApplyResult) -> list[dict[str, Any]]:
    """Fleet events of one committed apply."""
    base = {"_operator_id": meta.operator_id, "tail": meta.tail, "actuator_id": meta.actuator_id}
    out: list[dict[str, Any]] = []
    status = result.status_before
    for ab in result.applied:
        for name, est in ab.estimators.items():
            for ev in est.events:
                if ev["kind"] in FLEET_EVENT_KINDS:
                    out.append(
                        {
                            **base,
                            "type": ev["kind"],
                            "estimator": name,
                            "seq": ab.seq,
                            "t_s": ev["t_s"],
                            "detail": ev["detail"],
                        }
                    )
        if ab.status != status:
            reasons = [r for est in ab.estimators.values() for r in est.reasons]
            out.append(
                {
                    **base,
                    "type": "status_changed",
                    "seq": ab.seq,
                    "t_s": ab.t_last_s,
                    "from": status,
                    "to": ab.status,
                    "reasons": reasons,
                }
            )
            status = ab.status
        out.append(
            {
                **base,
                "type": "applied",
                "seq": ab.seq,
                "t_s": ab.t_last_s,
                "n_samples": ab.n_samples,
                "status": ab.status,
                "last": {name: est.last for name, est in ab.estimators.items()},
            }
        )
    return out


def public(event: dict[str, Any]) -> dict[str, Any]:
    """An event as sent to subscribers (without routing keys)."""
    return {k: v for k, v in event.items() if not k.startswith("_")}
