"""WebSocket streaming: live ingest with results pushed back, and fleet event subscriptions.

Frames enter the same telemetry log as REST batches (``app.telemetry.service.log_batch`` under the
actuator row lock, committed before the ``logged`` acknowledgement), so every invariant of the
log holds for them: durable before ack, exactly once, in order, applied after a crash. The
protocol is documented in docs/api.md ("Streaming").

Close codes: 1003 a message that is not a frame; 1007 a frame whose samples are invalid; 1008
authentication, authorization or a frame the log refuses (client_seq or time not after the last,
same client_seq with other samples); 1009 a frame above ``ws_max_frame_bytes`` (by the server);
1011 the stream is marked failed (its frames are logged but not applied); 1013 a fleet
subscriber too slow for its bounded queue.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections import OrderedDict
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
from app.errors import DomainError, IdempotencyConflict, InvalidBatch, StaleBatch
from app.ingest import UnsupportedFrame
from app.processing.processor import Processor
from app.telemetry import service as telemetry
from app.telemetry.validation import BatchLimits
from app.websocket import service
from app.websocket.hub import ALL_FLEET_TYPES, DEFAULT_FLEET_TYPES, Hub, Subscription, public

log = logging.getLogger("fleethealth.stream")
router = APIRouter(prefix="/v1")

WS_CONNECTIONS = Gauge("fleethealth_ws_connections", "Open WebSocket connections", ["endpoint"])
WS_FRAMES = Counter("fleethealth_ws_frames_total", "Streamed frames by outcome", ["outcome"])
WS_DROPPED = Counter("fleethealth_ws_subscribers_dropped_total", "Fleet subscribers dropped as too slow")

CLOSE_UNSUPPORTED = 1003
CLOSE_INVALID = 1007
CLOSE_POLICY = 1008
CLOSE_INTERNAL = 1011
CLOSE_TRY_LATER = 1013


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


# ----------------------------------------------------------------------------- ingest stream
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
    lock: asyncio.Lock = field(default_factory=asyncio.Lock)
    inflight: OrderedDict[int, int | None] = field(default_factory=OrderedDict)  # seq -> client_seq
    ready: dict[int, dict[str, Any]] = field(default_factory=dict)  # seq -> result message
    window_free: asyncio.Event = field(default_factory=asyncio.Event)
    inflight_added: asyncio.Event = field(default_factory=asyncio.Event)
    failure: str | None = None  # why the stream is no longer applied, once read back

    # ------------------------------------------------------------------ results
    def _take_pushed(self) -> None:
        while True:
            try:
                ab = self.sub.queue.get_nowait()
            except asyncio.QueueEmpty:
                break
            if ab.seq in self.inflight and ab.seq not in self.ready:
                self.ready[ab.seq] = ab.message(with_samples=self.with_samples)

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

    async def push_results(self) -> None:
        poll = self.settings.ws_result_poll_s
        while True:
            if not self.inflight:
                self.inflight_added.clear()
                await self.inflight_added.wait()
                continue
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self.sub.wakeup.wait(), poll)
            self.sub.wakeup.clear()
            self._take_pushed()
            head = next(iter(self.inflight))
            if head not in self.ready:
                if self.sub.overflowed:
                    self.sub.overflowed = False  # pushes were lost: read them back
                await self._read_back()
            while self.inflight:
                head = next(iter(self.inflight))
                msg = self.ready.pop(head, None)
                if msg is None:
                    break
                self.inflight.pop(head)
                await _send(self.ws, self.lock, msg)
                self.window_free.set()
            if self.inflight and self.failure is not None:
                # Frames logged but never to be applied: say so instead of a silent wait.
                await _refuse(
                    self.ws, CLOSE_INTERNAL, "StreamFailed",
                    f"frames are logged but the stream is no longer applied: {self.failure}",
                )
                return

    # ------------------------------------------------------------------ frames
    async def _window_slot(self, nxt: asyncio.Future[Any]) -> bool:
        """Wait until fewer than ``ws_max_inflight`` frames await their results. Meanwhile the
        next message may be read ahead (one frame at most, so TCP still pushes back on the
        sender) to notice a peer that leaves. False when the peer left."""
        window = self.settings.ws_max_inflight
        told = False
        while len(self.inflight) >= window:
            if not told:
                await _send(self.ws, self.lock, {"type": "slow_down", "inflight": len(self.inflight)})
                told = True
            self.window_free.clear()
            if len(self.inflight) < window:
                break
            free = asyncio.ensure_future(self.window_free.wait())
            watch = {free} if nxt.done() else {free, nxt}
            await asyncio.wait(watch, return_when=asyncio.FIRST_COMPLETED)
            free.cancel()
            if nxt.done() and nxt.result()["type"] == "websocket.disconnect":
                return False
        return True

    async def read_frames(self) -> None:
        nxt: asyncio.Future[Any] = asyncio.ensure_future(self.ws.receive())
        try:
            while True:
                msg = await nxt
                if msg["type"] == "websocket.disconnect":
                    return
                nxt = asyncio.ensure_future(self.ws.receive())
                if not await self._window_slot(nxt):
                    return
                data = msg.get("text") if msg.get("text") is not None else msg.get("bytes")
                if data is not None and not await self._take_frame(data):
                    return
        finally:
            nxt.cancel()

    async def _take_frame(self, data: str | bytes) -> bool:
        """Log one frame and acknowledge it; False when it was refused (connection closed)."""
        try:
            client_seq, ack = await telemetry.ingest_frame(
                self.ws.app.state.log_writer, self.actuator_pk, self.channels, data,
                self.settings.max_batch_samples, BatchLimits.from_settings(self.settings),
            )
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
        if ack.replayed:
            WS_FRAMES.labels("duplicate").inc()
            await _send(self.ws, self.lock, {"type": "duplicate", "client_seq": client_seq, "seq": ack.seq})
            return True
        WS_FRAMES.labels("logged").inc()
        self.inflight[ack.seq] = client_seq
        self.inflight_added.set()
        self.processor.notify(self.actuator_pk)
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
    )
    # Frames logged before a dropped connection and not applied yet: their results come here.
    for seq, client_seq in start.pending:
        if client_seq is not None:
            conn.inflight[seq] = client_seq
    WS_CONNECTIONS.labels("stream").inc()
    pusher = asyncio.create_task(conn.push_results())
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
            },
        )
        if conn.inflight:
            conn.inflight_added.set()
            processor.notify(pk)
        reader = asyncio.create_task(conn.read_frames())
        done, _ = await asyncio.wait({reader, pusher}, return_when=asyncio.FIRST_COMPLETED)
        for task in done:
            if task.exception() is not None and not isinstance(task.exception(), WebSocketDisconnect):
                log.error("stream connection failed", exc_info=task.exception())
        reader.cancel()
    except WebSocketDisconnect:
        log.debug("stream peer left during the handshake messages")
    finally:
        pusher.cancel()
        hub.unsubscribe(sub)
        WS_CONNECTIONS.labels("stream").dec()
        if ws.application_state == WebSocketState.CONNECTED:
            with contextlib.suppress(Exception):
                await asyncio.wait_for(ws.close(), settings.ws_close_timeout_s)


# ----------------------------------------------------------------------------- fleet events
@router.websocket("/fleet/events")
async def fleet_events(ws: WebSocket) -> None:
    """Fleet events of the key's operator: status changes, fault detections and clearances,
    RUL and deterioration thresholds crossed (and, on request, every applied batch)."""
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
    bad = sorted(set(types) - ALL_FLEET_TYPES)
    if bad:
        await _refuse(
            ws, CLOSE_POLICY, "InvalidConfig", f"unknown event types {bad}; known: {sorted(ALL_FLEET_TYPES)}"
        )
        return
    sub = hub.subscribe_fleet(principal.operator_id, tails or None, types, settings.ws_subscriber_queue)
    WS_CONNECTIONS.labels("fleet").inc()

    async def sender() -> None:
        await ws.send_text(_dumps({"type": "ready", "tails": tails or None, "types": sorted(types)}))
        while True:
            ev = await sub.queue.get()
            await ws.send_text(_dumps(public(ev)))

    async def watch_overflow() -> None:
        while not sub.overflowed:
            sub.wakeup.clear()
            await sub.wakeup.wait()

    async def watch_peer() -> None:
        while (await ws.receive())["type"] != "websocket.disconnect":
            pass  # subscribers have nothing to say; anything they send is ignored

    tasks = [asyncio.create_task(c()) for c in (sender, watch_overflow, watch_peer)]
    try:
        await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
    finally:
        for t in tasks:
            t.cancel()
        hub.unsubscribe(sub)
        WS_CONNECTIONS.labels("fleet").dec()
    if sub.overflowed:
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
