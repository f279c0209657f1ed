"""WebSocket streaming: live ingest with results pushed back, and fleet event subscriptions.

Frames enter the same telemetry log as REST batches (``app.telemetry.service.log_batch`` under the
actuator row lock, committed before the ``logged`` acknowledgement), so every invariant of the
log holds for them: durable before ack, exactly once, in order, applied after a crash. The
protocol is documented in docs/api.md ("Streaming").

Close codes: 1003 a message that is not a frame; 1007 a frame whose samples are invalid; 1008
authentication, authorization (also a key revoked or stripped of the scope while the connection
is open, seen within ``ws_auth_recheck_s``) or a frame the log refuses (client_seq or time not after the last,
same client_seq with other samples); 1009 a frame above ``ws_max_frame_bytes`` (by the server);
1011 the stream is marked failed (its frames are logged but not applied); 1013 a fleet
subscriber too slow for its bounded queue, or the database unavailable (the frame was not logged;
reconnect and send it again).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections import OrderedDict, deque
from dataclasses import dataclass, field
from typing import Any

import orjson
from fastapi import APIRouter, WebSocket, WebSocketDisconnect
from prometheus_client import Counter, Gauge
from starlette.concurrency import run_in_threadpool
from starlette.websockets import WebSocketState

from app.auth.service import Principal
from app.config import Settings
from app.db import Database
from app.errors import STORAGE_FAULTS, DomainError, IdempotencyConflict, InvalidBatch, StaleBatch
from app.events import service as events
from app.events.service import LOGGED_TYPES
from app.ingest import UnsupportedFrame
from app.processing.processor import Processor
from app.telemetry.validation import BatchLimits
from app.telemetry.writer import LogWriter
from app.websocket import service
from app.websocket.feed import FrameFeed, FrameSource, frame_feed
from app.websocket.hub import (
    ALL_FLEET_TYPES,
    DEFAULT_FLEET_TYPES,
    Hub,
    Subscription,
    public,
)
from app.websocket.watch import KeyGuard, ResultSweep, per_loop

log = logging.getLogger("fleethealth.stream")
router = APIRouter(prefix="/v1")

WS_CONNECTIONS = Gauge("fleethealth_ws_connections", "Open WebSocket connections", ["endpoint"])
WS_FRAMES = Counter("fleethealth_ws_frames_total", "Streamed frames by outcome", ["outcome"])
WS_DROPPED = Counter("fleethealth_ws_subscribers_dropped_total", "Fleet subscribers dropped as too slow")
WS_FLOW = Counter("fleethealth_ws_flow_total", "slow_down and resume messages sent to stream clients", ["message"])
WS_QUEUED = Gauge("fleethealth_ws_queued_frames", "Frames read from stream connections, not logged yet")
# Bound once: ``labels()`` per frame costs a lock and a dict look-up.
FRAMES_LOGGED = WS_FRAMES.labels("logged")
WS_KEY_CLOSES = Counter(
    "fleethealth_ws_key_closes_total", "WebSockets closed because their key was revoked or lost its scope", ["error"]
)

CLOSE_UNSUPPORTED = 1003
CLOSE_INVALID = 1007
CLOSE_POLICY = 1008
CLOSE_INTERNAL = 1011
CLOSE_TRY_LATER = 1013
# Logged events read per query by a fleet subscriber.
LOG_PAGE = 500


def _dumps(obj: Any) -> str:
    return orjson.dumps(obj, option=orjson.OPT_SERIALIZE_NUMPY).decode()


async def _send(ws: WebSocket, lock: asyncio.Lock, obj: dict[str, Any]) -> None:
    async with lock:
        await ws.send_text(_dumps(obj))


async def _refuse(ws: WebSocket, code: int, error: str, detail: str, **extra: Any) -> None:
    """Send an error message and close; a peer already gone is not an error."""
    with contextlib.suppress(Exception):
        await ws.send_text(_dumps({"type": "error", "error": error, "detail": detail, **extra}))
        await ws.close(code=code, reason=error[:120])


async def _authenticate(ws: WebSocket, db: Database, settings: Settings, scope: str) -> Principal | None:
    """The key from the Authorization header or, for browsers, a first ``{"type": "auth",
    "key": ...}`` message. Refuses (1008) and returns None when it fails."""
    header = ws.headers.get("authorization")
    if header is None:
        try:
            first = await asyncio.wait_for(ws.receive_text(), settings.ws_auth_timeout_s)
            doc = orjson.loads(first)
        except TimeoutError:
            await _refuse(ws, CLOSE_POLICY, "Unauthorized", "no Authorization header and no auth message in time")
            return None
        except (orjson.JSONDecodeError, KeyError, RuntimeError, WebSocketDisconnect):
            await _refuse(ws, CLOSE_POLICY, "Unauthorized", 'first message must be {"type": "auth", "key": "..."}')
            return None
        if not isinstance(doc, dict) or doc.get("type") != "auth" or not isinstance(doc.get("key"), str):
            await _refuse(ws, CLOSE_POLICY, "Unauthorized", 'first message must be {"type": "auth", "key": "..."}')
            return None
        header = f"Bearer {doc['key']}"

    try:
        principal = await run_in_threadpool(service.authenticate_key, db, header)
        principal.require(scope)
    except DomainError as exc:
        await _refuse(ws, CLOSE_POLICY, exc.name, exc.detail)
        return None
    return principal


async def _close_on_refusal(ws: WebSocket, db: Database, settings: Settings, principal: Principal, scope: str,
                            lock: asyncio.Lock) -> None:
    """Once the process-wide :class:`~app.websocket.watch.KeyGuard` finds the connection's key
    revoked or without ``scope`` (within ``ws_auth_recheck_s``), close with 1008 and return.
    Nothing runs here until then: no timer, no reading of its own."""
    guard = per_loop(ws.app.state, "ws_key_guard", lambda: KeyGuard(db, settings.ws_auth_recheck_s / 2))
    watch = guard.watch(principal, scope)
    try:
        refusal = await watch.refused
    finally:
        guard.unwatch(watch)
    WS_KEY_CLOSES.labels(refusal.name).inc()

    async def close() -> None:
        async with lock:  # never in the middle of another message
            await _refuse(ws, CLOSE_POLICY, refusal.name, refusal.detail)

    with contextlib.suppress(TimeoutError):
        await asyncio.wait_for(close(), settings.ws_close_timeout_s)


# ----------------------------------------------------------------------------- ingest stream
class FrameBudget:
    """Frames (and their bytes) read from every stream connection of the process and not
    logged yet, against ``ws_max_queued_frames_total`` and ``ws_max_queued_bytes_total``: at
    half of either every connection is told to slow down, at the bound they stop reading until
    the loggers catch up. One event loop owns it."""

    def __init__(self, limit: int, limit_bytes: int) -> None:
        self.limit = limit
        self.limit_bytes = limit_bytes
        self.used = 0
        self.used_bytes = 0

    def take(self, n_bytes: int) -> None:
        self.used += 1
        self.used_bytes += n_bytes
        WS_QUEUED.set(self.used)

    def give(self, n: int, n_bytes: int) -> None:
        self.used = max(0, self.used - n)
        self.used_bytes = max(0, self.used_bytes - n_bytes)
        WS_QUEUED.set(self.used)

    def pressed(self) -> bool:
        return self.used * 2 >= self.limit or self.used_bytes * 2 >= self.limit_bytes

    def full(self) -> bool:
        return self.used >= self.limit or self.used_bytes >= self.limit_bytes


class RateMeter:
    """Events per second over the last ``window`` events (the rate a connection's results come
    back at: what the server can sustain for this stream now)."""

    def __init__(self, window: int = 32) -> None:
        self.times: deque[float] = deque(maxlen=window)

    def tick(self) -> None:
        self.times.append(time.monotonic())

    def rate_hz(self) -> float | None:
        if len(self.times) < 2:
            return None
        span = time.monotonic() - self.times[0]
        return round((len(self.times) - 1) / span, 3) if span > 0 else None


def _frame_budget(ws: WebSocket, settings: Settings) -> FrameBudget:
    budget: FrameBudget | None = getattr(ws.app.state, "ws_frame_budget", None)
    if budget is None:
        budget = ws.app.state.ws_frame_budget = FrameBudget(
            settings.ws_max_queued_frames_total, settings.ws_max_queued_bytes_total
        )
    return budget


@dataclass
class _StreamConn:
    """One ingest connection: frames logged and waiting for their results, in stream order."""

    ws: WebSocket
    db: Database
    settings: Settings
    processor: Processor
    actuator_pk: int
    channels: list[str]
    with_samples: bool
    sub: Subscription
    feed: FrameFeed
    source: FrameSource
    lock: asyncio.Lock = field(default_factory=asyncio.Lock)
    inflight: OrderedDict[int, int | None] = field(default_factory=OrderedDict)  # seq -> client_seq
    ready: dict[int, dict[str, Any]] = field(default_factory=dict)  # seq -> result message
    window_free: asyncio.Event = field(default_factory=asyncio.Event)
    inflight_added: asyncio.Event = field(default_factory=asyncio.Event)
    failure: str | None = None  # why the stream is no longer applied, once read back
    budget: FrameBudget = field(default_factory=lambda: FrameBudget(1, 1))
    queue: deque[str | bytes] = field(default_factory=deque)  # read, not logged yet
    queued_bytes: int = 0
    frame_added: asyncio.Event = field(default_factory=asyncio.Event)
    space_free: asyncio.Event = field(default_factory=asyncio.Event)
    paused: bool = False  # slow_down sent, resume not yet
    results_rate: RateMeter = field(default_factory=lambda: RateMeter())
    sent_seq: int = 0  # the last result sent (older pushes are stale)

    # ------------------------------------------------------------------ results
    def _take_pushed(self) -> None:
        """Keep the results pushed for this stream. One may come before its frame is in
        ``inflight``: the processor can apply a frame between its commit to the log and the
        moment this connection reads the acknowledgement. It is kept (not read back from the
        store later), so are results of frames of another connection to the same actuator;
        those never become in flight, so only the newest few are kept."""
        while True:
            try:
                ab = self.sub.queue.get_nowait()
            except asyncio.QueueEmpty:
                break
            if ab.seq > self.sent_seq and ab.seq not in self.ready:
                self.ready[ab.seq] = ab.message(with_samples=self.with_samples)
        spare = len(self.ready) - len(self.inflight) - self.sub.queue.maxsize
        if spare > 0:
            for seq in sorted(q for q in self.ready if q not in self.inflight)[:spare]:
                del self.ready[seq]

    async def _read_back(self) -> None:
        """Results of in-flight batches already applied but not pushed here (applied by another
        process, or pushed while the results queue was full)."""
        missing = [seq for seq in self.inflight if seq not in self.ready]
        if not missing:
            return
        messages, failure = await run_in_threadpool(service.missed_results, self.db, self.actuator_pk, missing)
        for msg in messages:
            self.ready[msg["seq"]] = msg
        self.failure = failure

    def _should_read_back(self, head: int) -> bool:
        """Whether the head's result may be in the store without having been pushed here:
        pushes were lost (queue overflow), the stream was applied elsewhere or failed (a
        notification, or the process-wide :class:`~app.websocket.watch.ResultSweep` that
        finds wake-ups lost), or this process knows the head is applied. Otherwise the
        connection waits for the push: a thousand connections waiting for a busy processor do
        not read the store, nor wake up, until something happened to their stream."""
        if self.sub.overflowed or self.sub.stale:
            self.sub.overflowed = self.sub.stale = False
            return True
        known = self.processor.known_applied(self.actuator_pk)
        return known is not None and known >= head

    def waiting_for(self) -> tuple[int, int] | None:
        """(stream, seq) of the result this connection waits for, None when it waits for none."""
        if not self.inflight:
            return None
        head = next(iter(self.inflight))
        return None if head in self.ready else (self.actuator_pk, head)

    async def push_results(self) -> None:
        while True:
            if not self.inflight:
                self.inflight_added.clear()
                await self.inflight_added.wait()
                continue
            # Woken by a push, a notification, the sweep, or a frame acknowledged after its
            # result had come: no timer of its own.
            await self.sub.wakeup.wait()
            self.sub.wakeup.clear()
            self._take_pushed()
            head = next(iter(self.inflight))
            if head not in self.ready and self._should_read_back(head):
                await self._read_back()
            while self.inflight:
                head = next(iter(self.inflight))
                msg = self.ready.pop(head, None)
                if msg is None:
                    break
                self.inflight.pop(head)
                self.sent_seq = head
                await _send(self.ws, self.lock, msg)
                self.results_rate.tick()
                self.window_free.set()
            if self._flow_due():
                await self._flow()
            if self.inflight and self.failure is not None:
                # Frames logged but never to be applied: say so instead of a silent wait.
                await _refuse(
                    self.ws, CLOSE_INTERNAL, "StreamFailed",
                    f"frames are logged but the stream is no longer applied: {self.failure}",
                )
                return

    # ------------------------------------------------------------------ frames
    # Three tasks share a connection: ``read_frames`` keeps reading the socket (so keepalive
    # pings and pongs are answered even while the stream is throttled) into a bounded queue;
    # ``log_frames`` logs queued frames in order while fewer than ``ws_max_inflight`` await
    # their results; ``push_results`` sends results. ``_flow`` tells the client to slow down
    # (with the rate its results come back at) and to resume; only a client that ignores
    # ``slow_down`` until the queue's hard bound is full meets TCP back-pressure.
    def _queue_full(self) -> bool:
        return (
            len(self.queue) >= self.settings.ws_max_queued_frames
            or self.queued_bytes >= self.settings.ws_max_queued_bytes
            or self.budget.full()
        )

    def _flow_due(self) -> bool:
        """Whether :meth:`_flow` has a ``slow_down`` or ``resume`` to send."""
        waiting = len(self.queue) + len(self.inflight)
        high = self.settings.ws_slow_down_frames
        if self.paused:
            return waiting <= high // 2 and not self.budget.pressed()
        return waiting >= high or self.budget.pressed()

    async def _flow(self) -> None:
        """Send ``slow_down`` when the frames waiting here (queued and in flight) reach
        ``ws_slow_down_frames`` or the process-wide queue is half full; ``resume`` once they
        are back to half of it. Callers check :meth:`_flow_due` first (it runs for every frame
        read, logged and answered; most of the time there is nothing to send)."""
        waiting = len(self.queue) + len(self.inflight)
        high = self.settings.ws_slow_down_frames
        if not self.paused and (waiting >= high or self.budget.pressed()):
            self.paused = True
            WS_FLOW.labels("slow_down").inc()
            await _send(self.ws, self.lock, {
                "type": "slow_down", "queued": len(self.queue), "inflight": len(self.inflight),
                "rate_hz": self.results_rate.rate_hz(),
            })
        elif self.paused and waiting <= high // 2 and not self.budget.pressed():
            self.paused = False
            WS_FLOW.labels("resume").inc()
            await _send(self.ws, self.lock, {"type": "resume", "rate_hz": self.results_rate.rate_hz()})

    async def read_frames(self) -> None:
        while True:
            while self._queue_full():
                self.space_free.clear()
                if not self._queue_full():
                    break
                await self.space_free.wait()
            msg = await self.ws.receive()
            if msg["type"] == "websocket.disconnect":
                return
            data = msg.get("text") if msg.get("text") is not None else msg.get("bytes")
            if data is None:
                continue
            self.queue.append(data)
            self.queued_bytes += len(data)
            self.budget.take(len(data))
            self.frame_added.set()
            if self._flow_due():
                await self._flow()

    async def log_frames(self) -> None:
        window = self.settings.ws_max_inflight
        while True:
            while not self.queue:
                self.frame_added.clear()
                await self.frame_added.wait()
            while len(self.inflight) >= window:
                self.window_free.clear()
                if len(self.inflight) < window:
                    break
                await self.window_free.wait()
            data = self.queue.popleft()
            self.queued_bytes -= len(data)
            self.budget.give(1, len(data))
            self.space_free.set()
            if not await self._take_frame(data):
                return
            if self._flow_due():
                await self._flow()

    def release(self) -> None:
        """Give the frames still queued back to the process-wide budget (the connection ends;
        they were never acknowledged, so the client sends them again)."""
        self.budget.give(len(self.queue), self.queued_bytes)
        self.queue.clear()
        self.queued_bytes = 0

    async def _take_frame(self, data: str | bytes) -> bool:
        """Log one frame and acknowledge it; False when it was refused (connection closed)."""
        try:
            # Parsed in a parse thread, handed from there to the log writer; acknowledged once
            # committed (durable), by the writer's group commit.
            client_seq, ack = await self.feed.put(self.source, data)
        except UnsupportedFrame as exc:
            WS_FRAMES.labels("unsupported").inc()
            await _refuse(self.ws, CLOSE_UNSUPPORTED, exc.name, exc.detail)
            return False
        except InvalidBatch as exc:
            WS_FRAMES.labels("invalid").inc()
            await _refuse(self.ws, CLOSE_INVALID, exc.name, exc.detail)
            return False
        except (StaleBatch, IdempotencyConflict) as exc:
            WS_FRAMES.labels("refused").inc()
            await _refuse(self.ws, CLOSE_POLICY, exc.name, exc.detail)
            return False
        except STORAGE_FAULTS as exc:
            # Nothing of the frame was stored; the client reconnects (1013) and sends it again.
            WS_FRAMES.labels("storage_unavailable").inc()
            await _refuse(
                self.ws, CLOSE_TRY_LATER, "StorageUnavailable",
                f"the database is unavailable ({type(exc).__name__}); the frame was not logged, retry later",
                retry_after_s=self.settings.storage_retry_after_s,
            )
            return False
        if ack.replayed:
            WS_FRAMES.labels("duplicate").inc()
            await _send(self.ws, self.lock, {"type": "duplicate", "client_seq": client_seq, "seq": ack.seq})
            return True
        FRAMES_LOGGED.inc()
        self.inflight[ack.seq] = client_seq
        self.inflight_added.set()
        if ack.seq in self.ready:  # applied and pushed before this acknowledgement was read
            self.sub.wakeup.set()
        # No processor wake-up here: the log writer wakes it for every stream of each commit.
        await _send(
            self.ws,
            self.lock,
            {
                "type": "logged",
                "client_seq": client_seq,
                "seq": ack.seq,
                "n_samples": ack.n_samples,
                "t_first_s": ack.t_first_s,
                "t_last_s": ack.t_last_s,
            },
        )
        return True


@router.websocket("/aircraft/{tail}/actuators/{actuator_id}/stream")
async def stream(ws: WebSocket, tail: str, actuator_id: str) -> None:
    """Live ingest: frames in, ``logged`` and ``result`` messages out (docs/api.md)."""
    db: Database = ws.app.state.db
    settings: Settings = ws.app.state.settings
    processor: Processor = ws.app.state.processor
    hub: Hub = processor.hub
    await ws.accept()
    principal = await _authenticate(ws, db, settings, "ingest")
    if principal is None:
        return
    try:
        start = await run_in_threadpool(service.stream_start, db, principal, tail, actuator_id)
    except DomainError as exc:
        await _refuse(ws, CLOSE_POLICY, exc.name, exc.detail)
        return
    pk = start.actuator_pk
    writer: LogWriter = ws.app.state.log_writer
    sub = hub.subscribe_stream(pk, maxsize=4 * settings.ws_max_inflight)
    conn = _StreamConn(
        ws=ws,
        db=db,
        settings=settings,
        processor=processor,
        actuator_pk=pk,
        channels=start.channels,
        with_samples=ws.query_params.get("samples", "false").lower() in ("1", "true", "yes"),
        sub=sub,
        budget=_frame_budget(ws, settings),
        sent_seq=start.last_applied_seq,
        feed=frame_feed(asyncio.get_running_loop()),
        source=FrameSource(pk, start.channels, settings.max_batch_samples, BatchLimits.from_settings(settings),
                           writer.submit),
    )
    # Frames logged before a dropped connection and not applied yet: their results come here.
    for seq, client_seq in start.pending:
        if client_seq is not None:
            conn.inflight[seq] = client_seq
    WS_CONNECTIONS.labels("stream").inc()
    sweep = per_loop(ws.app.state, "ws_result_sweep", lambda: ResultSweep(db, settings.ws_result_poll_s))
    pusher = asyncio.create_task(conn.push_results())
    tasks = {pusher}
    try:
        await _send(
            ws,
            conn.lock,
            {
                "type": "ready",
                "tail": tail,
                "actuator_id": actuator_id,
                "channels": start.channels,
                "last_client_seq": start.last_client_seq,
                "last_applied_client_seq": start.last_applied_client_seq,
                "last_logged_seq": start.last_logged_seq,
                "last_applied_seq": start.last_applied_seq,
                "failure": start.failure,
                "max_inflight": settings.ws_max_inflight,
                "max_queued_frames": settings.ws_max_queued_frames,
                "max_queued_bytes": settings.ws_max_queued_bytes,
            },
        )
        if conn.inflight:
            # Some may have been applied between the start's reading and the subscription
            # (their pushes missed): read back once, the rest are pushed.
            sub.mark_stale()
            conn.inflight_added.set()
            processor.notify(pk)
        sweep.add(sub, conn.waiting_for)
        tasks = {
            pusher,
            asyncio.create_task(conn.read_frames()),
            asyncio.create_task(conn.log_frames()),
            asyncio.create_task(_close_on_refusal(ws, db, settings, principal, "ingest", conn.lock)),
        }
        done, _ = await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
        for task in done:
            if task.exception() is not None and not isinstance(task.exception(), WebSocketDisconnect):
                log.error("stream connection failed", exc_info=task.exception())
    except WebSocketDisconnect:
        log.debug("stream peer left during the handshake messages")
    finally:
        for task in tasks:
            task.cancel()
        # Awaited, so that no task outlives its connection ("Task was destroyed but it is
        # pending"); a frame being logged finishes its transaction in the thread pool anyway.
        await asyncio.gather(*tasks, return_exceptions=True)
        conn.release()
        sweep.discard(sub)
        hub.unsubscribe(sub)
        WS_CONNECTIONS.labels("stream").dec()
        if ws.application_state == WebSocketState.CONNECTED:
            with contextlib.suppress(Exception):
                await asyncio.wait_for(ws.close(), settings.ws_close_timeout_s)


# ----------------------------------------------------------------------------- fleet events
@router.websocket("/fleet/events")
async def fleet_events(ws: WebSocket) -> None:
    """Fleet events of the key's operator: status changes, fault detections and clearances,
    RUL and deterioration thresholds crossed, alarms (and, on request, every applied batch).

    Logged events come from the durable event log, after ``?after=<id>`` when given (resume
    without loss), else from the newest; the process's own applies wake the reader up and a
    poll every ``events_poll_s`` finds those of other processes. ``applied`` events are pushed
    live only.
    """
    db: Database = ws.app.state.db
    settings: Settings = ws.app.state.settings
    hub: Hub = ws.app.state.processor.hub
    await ws.accept()
    principal = await _authenticate(ws, db, settings, "read")
    if principal is None:
        return
    tails = [t for v in ws.query_params.getlist("tail") for t in v.split(",") if t]
    raw_types = ws.query_params.get("types")
    types = [t for t in raw_types.split(",") if t] if raw_types else sorted(DEFAULT_FLEET_TYPES)
    known = {*LOGGED_TYPES, *ALL_FLEET_TYPES}
    bad = sorted(set(types) - known)
    if bad:
        await _refuse(ws, CLOSE_POLICY, "InvalidConfig", f"unknown event types {bad}; known: {sorted(known)}")
        return
    raw_after = ws.query_params.get("after")
    if raw_after is not None and not (raw_after.isdigit() and int(raw_after) <= 2**53):
        await _refuse(ws, CLOSE_POLICY, "InvalidConfig", f"after must be an event id (0 or more), got {raw_after!r}")
        return
    operator_id = principal.operator_id
    logged = sorted(set(types) & LOGGED_TYPES)
    cursor = int(raw_after) if raw_after is not None else await run_in_threadpool(events.head, db, operator_id)
    live = hub.subscribe_fleet(operator_id, tails or None, ["applied"], settings.ws_subscriber_queue) if "applied" in types else None
    wake = hub.subscribe_fleet_wakeup(operator_id) if logged else None
    lock = asyncio.Lock()
    WS_CONNECTIONS.labels("fleet").inc()

    async def send_live() -> None:
        assert live is not None
        while True:
            ev = await live.queue.get()
            await _send(ws, lock, public(ev))

    async def follow_log() -> None:
        nonlocal cursor
        assert wake is not None
        while True:
            wake.wakeup.clear()
            batch = await run_in_threadpool(
                events.read_after, db, operator_id, cursor, LOG_PAGE, logged, tails or None
            )
            for ev in batch:
                await _send(ws, lock, ev)
                cursor = ev["id"]
            if len(batch) < LOG_PAGE:
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(wake.wakeup.wait(), settings.events_poll_s)

    async def watch_overflow() -> None:
        assert live is not None
        while not live.overflowed:
            live.wakeup.clear()
            await live.wakeup.wait()

    async def watch_peer() -> None:
        while (await ws.receive())["type"] != "websocket.disconnect":
            pass  # subscribers have nothing to say; anything they send is ignored

    tasks: list[asyncio.Task[None]] = []

    async def guard() -> None:
        await _close_on_refusal(ws, db, settings, principal, "read", lock)

    try:
        await _send(ws, lock, {"type": "ready", "tails": tails or None, "types": sorted(types), "after": cursor})
        tasks += [asyncio.create_task(watch_peer()), asyncio.create_task(guard())]
        if live is not None:
            tasks += [asyncio.create_task(send_live()), asyncio.create_task(watch_overflow())]
        if wake is not None:
            tasks.append(asyncio.create_task(follow_log()))
        done, _ = await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
        for task in done:
            exc = task.exception()
            if exc is not None and not isinstance(exc, WebSocketDisconnect):
                log.error("fleet event subscription failed", exc_info=exc)
    except WebSocketDisconnect:
        log.debug("fleet subscriber left before ready")
    finally:
        for t in tasks:
            t.cancel()
        for sub in (live, wake):
            if sub is not None:
                hub.unsubscribe(sub)
        WS_CONNECTIONS.labels("fleet").dec()
    if live is not None and live.overflowed:
        WS_DROPPED.inc()
        # The close frame waits behind whatever the slow peer has not read yet; give up after
        # ws_close_timeout_s and let the server drop the socket.
        with contextlib.suppress(Exception):
            await asyncio.wait_for(
                ws.close(code=CLOSE_TRY_LATER, reason="subscriber too slow: event queue full"),
                settings.ws_close_timeout_s,
            )
    elif ws.application_state == WebSocketState.CONNECTED:
        with contextlib.suppress(Exception):
            await asyncio.wait_for(ws.close(), settings.ws_close_timeout_s)
