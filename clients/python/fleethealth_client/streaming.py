"""Streaming client: send frames over WebSocket, with results pushed back and resume.

    async with FrameStreamer(url, key, "N101FH", "ema-left") as fs:
        for t, chans in blocks:
            await fs.send(chans, t_s=t)
        results = await fs.drain()

Every frame gets the next client sequence number and stays in memory until the server says it is
logged (durable). When the connection drops, :meth:`FrameStreamer.send` and
:meth:`FrameStreamer.drain` reconnect (with backoff), read the server's ``last_client_seq`` and
send again only the frames after it, so nothing is lost and nothing is logged twice. A frame the
server refuses (invalid samples, out of order) raises :class:`StreamRefused`; it is not retried.

JSON frames need numpy and orjson only; binary (Arrow) frames need pyarrow (the ``arrow`` extra).
"""

from __future__ import annotations

import asyncio
import contextlib
from collections import OrderedDict
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import orjson
from numpy.typing import ArrayLike
from websockets.asyncio.client import ClientConnection, connect
from websockets.exceptions import ConnectionClosed, InvalidHandshake

from fleethealth_client.arrow import ipc_stream
from fleethealth_client.columns import TIME_COLUMN, FloatArray, as_float_columns, time_params
from fleethealth_client.errors import StreamRefused
from fleethealth_client.paths import actuator_path, ws_url

__all__ = [
    "REFUSAL_CODES",
    "FrameStreamer",
    "StreamRefused",
    "StreamStats",
    "encode_frame",
    "frames_of",
    "ws_url",
]

# Close codes after which sending the same frame again cannot succeed.
REFUSAL_CODES = frozenset({1003, 1007, 1008, 1009})
#: Delays between reconnection attempts (seconds); the last one repeats.
RECONNECT_DELAYS_S = (0.1, 0.25, 0.5, 1.0, 2.0, 5.0)
#: Failures of a connection attempt that another attempt may not meet: refused or reset TCP,
#: a handshake cut short or garbled (``InvalidMessage``, e.g. a server dying mid-handshake), an
#: HTTP status instead of the upgrade (``InvalidStatus``, e.g. a proxy's 502), a timeout.
RECONNECTABLE: tuple[type[BaseException], ...] = (OSError, EOFError, ConnectionClosed, InvalidHandshake, TimeoutError)
#: Reconnection attempts before giving up.
MAX_RECONNECTS = 20
#: Seconds to open a connection and receive the server's ``ready``.
OPEN_TIMEOUT_S = 10.0
#: Default limit of :meth:`FrameStreamer.drain` (seconds).
DRAIN_TIMEOUT_S = 60.0


def encode_frame(
    client_seq: int,
    channels: Mapping[str, ArrayLike],
    *,
    t_s: ArrayLike | None = None,
    t0: float | None = None,
    sample_rate_hz: float | None = None,
    binary: bool = False,
) -> str | bytes:
    """One frame: JSON text, or an Arrow IPC stream with ``client_seq`` in the schema metadata.

    Raises:
        ValueError: an invalid batch (see :func:`fleethealth_client.columns.as_float_columns`).
        ImportError: ``binary`` without pyarrow installed.
    """
    t_arr, columns = as_float_columns(channels, t_s)
    timing = time_params(t_arr, t0, sample_rate_hz)
    if not binary:
        doc: dict[str, Any] = {"type": "samples", "client_seq": client_seq}
        if t_arr is not None:
            doc["t"] = t_arr
        doc.update(timing)
        doc["channels"] = columns
        return orjson.dumps(doc, option=orjson.OPT_SERIALIZE_NUMPY).decode()
    names = ([TIME_COLUMN] if t_arr is not None else []) + list(columns)
    arrays = ([t_arr] if t_arr is not None else []) + list(columns.values())
    meta = {"client_seq": str(client_seq), **{k: repr(v) for k, v in timing.items()}}
    return ipc_stream(names, arrays, meta, what="binary frame")


@dataclass
class StreamStats:
    """What a :class:`FrameStreamer` saw.

    Attributes:
        connects: connections opened (1 plus the reconnections).
        frames_sent: frames handed to :meth:`FrameStreamer.send` (each sent again after a
            reconnection is counted once).
        duplicates: frames the server answered as already logged.
        slow_downs: ``slow_down`` notices received (the server's queue for this connection,
            or its process-wide one, filled up).
        resumes: ``resume`` notices received.
        throttled_s: seconds :meth:`FrameStreamer.send` waited because of them.
        results: the ``result`` messages pushed back, in order of arrival.
    """

    connects: int = 0
    frames_sent: int = 0
    duplicates: int = 0
    slow_downs: int = 0
    resumes: int = 0
    throttled_s: float = 0.0
    results: list[dict[str, Any]] = field(default_factory=list)


class FrameStreamer:
    """Streams frames into one actuator and collects the results pushed back.

    Args:
        base_url: the server's HTTP(S) address, e.g. ``"http://127.0.0.1:8000"``.
        api_key: key with the ``ingest`` scope.
        tail: aircraft tail.
        actuator_id: actuator of that aircraft.
        binary: send Arrow frames (needs pyarrow) instead of JSON text.
        samples: ask for every per-sample output in the results (``?samples=true``).
        auth_message: authenticate with a first message instead of a header (as browsers must).
        reconnect_delays_s: waits between reconnection attempts; the last one repeats.
        max_reconnects: attempts before :meth:`open` gives up with ``ConnectionError``.
        open_timeout_s: limit on opening a connection and receiving ``ready``.
    """

    def __init__(
        self,
        base_url: str,
        api_key: str,
        tail: str,
        actuator_id: str,
        *,
        binary: bool = False,
        samples: bool = False,
        auth_message: bool = False,
        reconnect_delays_s: Sequence[float] = RECONNECT_DELAYS_S,
        max_reconnects: int = MAX_RECONNECTS,
        open_timeout_s: float = OPEN_TIMEOUT_S,
    ) -> None:
        query = "?samples=true" if samples else ""
        self.url = ws_url(base_url, f"{actuator_path(tail, actuator_id)}/stream{query}")
        self.api_key = api_key
        self.binary = binary
        self.auth_message = auth_message
        self.delays = tuple(reconnect_delays_s)
        self.max_reconnects = max_reconnects
        self.open_timeout_s = open_timeout_s
        self.stats = StreamStats()
        self.ready: dict[str, Any] = {}
        self._ws: ClientConnection | None = None
        self._unlogged: OrderedDict[int, str | bytes] = OrderedDict()  # client_seq -> frame
        self._awaiting: set[int] = set()  # logged, result not seen
        self._next_seq = 1
        self._reader: asyncio.Task[None] | None = None
        self._changed = asyncio.Event()
        self._failure: BaseException | None = None
        # Between the server's slow_down and resume: send at most advised_rate_hz frames/s
        # (no frame at all when the server could not say a rate) instead of reconnecting.
        self._paused = False
        self._advised_rate_hz: float | None = None
        self._last_send = 0.0
        # Frames sent and not logged yet are at most what the server reads ahead
        # (ready.max_queued_frames / max_queued_bytes): it then never has to stop reading,
        # so keepalive pings keep flowing however far the stream is throttled.
        self._max_unlogged: int | None = None
        self._max_unlogged_bytes: int | None = None

    # ------------------------------------------------------------------ connection
    async def __aenter__(self) -> FrameStreamer:
        await self.open()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    async def open(self) -> dict[str, Any]:
        """Connect (retrying with backoff) and resend what the server has not logged."""
        attempt = 0
        while True:
            try:
                return await self._connect()
            except StreamRefused:
                raise
            except RECONNECTABLE as exc:
                if attempt >= self.max_reconnects:
                    raise ConnectionError(f"could not connect to {self.url}: {exc}") from exc
                await asyncio.sleep(self.delays[min(attempt, len(self.delays) - 1)])
                attempt += 1

    async def _connect(self) -> dict[str, Any]:
        headers = None if self.auth_message else {"Authorization": f"Bearer {self.api_key}"}
        ws = await connect(
            self.url, additional_headers=headers, open_timeout=self.open_timeout_s, max_size=None
        )
        try:
            if self.auth_message:
                await ws.send(orjson.dumps({"type": "auth", "key": self.api_key}).decode())
            ready = self._decode(await asyncio.wait_for(ws.recv(), self.open_timeout_s))
            if ready.get("type") == "error":
                raise StreamRefused(None, ready.get("error", "Error"), ready.get("detail", ""))
        except BaseException:
            await ws.close()
            raise
        self._ws = ws
        self.ready = ready
        self.stats.connects += 1
        last_logged = ready.get("last_client_seq") or 0
        last_applied = ready.get("last_applied_client_seq") or 0
        self._next_seq = max(self._next_seq, last_logged + 1)
        for seq in [s for s in self._unlogged if s <= last_logged]:
            del self._unlogged[seq]  # durable already
            self._awaiting.add(seq)
        # Results of frames applied while disconnected are in the store, not pushed again.
        self._awaiting = {s for s in self._awaiting if s > last_applied}
        self._failure = None
        self._paused = False
        self._max_unlogged = ready.get("max_queued_frames")
        self._max_unlogged_bytes = ready.get("max_queued_bytes")
        self._reader = asyncio.create_task(self._read(ws))
        for frame in list(self._unlogged.values()):
            await ws.send(frame)
        return ready

    async def close(self) -> None:
        if self._reader is not None:
            self._reader.cancel()
        if self._ws is not None:
            await self._ws.close()
            self._ws = None

    async def drop(self) -> None:
        """Cut the connection abruptly (tests of resume)."""
        if self._ws is not None:
            self._ws.transport.abort()

    # ------------------------------------------------------------------ messages
    @staticmethod
    def _decode(raw: str | bytes) -> dict[str, Any]:
        doc = orjson.loads(raw)
        if not isinstance(doc, dict):
            raise ValueError(f"unexpected message {doc!r}")
        return doc

    async def _read(self, ws: ClientConnection) -> None:
        error: dict[str, Any] | None = None
        # A closed connection ends the loop; its close code (below) says why.
        with contextlib.suppress(ConnectionClosed):
            async for raw in ws:
                msg = self._decode(raw)
                kind = msg.get("type")
                if kind == "logged":
                    self._unlogged.pop(msg["client_seq"], None)
                    self._awaiting.add(msg["client_seq"])
                elif kind == "duplicate":
                    self.stats.duplicates += 1
                    self._unlogged.pop(msg["client_seq"], None)
                elif kind == "result":
                    if msg.get("client_seq") is not None:
                        self._awaiting.discard(msg["client_seq"])
                    self.stats.results.append(msg)
                elif kind == "slow_down":
                    self.stats.slow_downs += 1
                    self._paused = True
                    self._advised_rate_hz = msg.get("rate_hz")
                elif kind == "resume":
                    self.stats.resumes += 1
                    self._paused = False
                elif kind == "error":
                    error = msg
                self._changed.set()
        code = ws.close_code
        if error is not None or code in REFUSAL_CODES:
            err = error or {}
            self._failure = StreamRefused(
                code, err.get("error", "Closed"), err.get("detail", ws.close_reason or "")
            )
        else:
            self._failure = ConnectionError(f"connection closed ({code})")
        self._changed.set()

    async def _ensure_open(self) -> ClientConnection:
        if isinstance(self._failure, StreamRefused):
            raise self._failure
        if self._ws is None or self._failure is not None:
            if self._ws is not None:
                with contextlib.suppress(Exception):
                    await self._ws.close()
                self._ws = None
            await self.open()
        assert self._ws is not None
        return self._ws

    # ------------------------------------------------------------------ sending
    async def send(
        self,
        channels: Mapping[str, ArrayLike],
        *,
        t_s: ArrayLike | None = None,
        t0: float | None = None,
        sample_rate_hz: float | None = None,
    ) -> int:
        """Send the next frame; returns its client sequence number. After the server's
        ``slow_down`` it paces frames at the advised rate until ``resume``; it blocks, too,
        when the server stops reading (a queue bound reached)."""
        await self._throttle()
        seq = self._next_seq
        frame = encode_frame(
            seq, channels, t_s=t_s, t0=t0, sample_rate_hz=sample_rate_hz, binary=self.binary
        )
        await self._room_for(len(frame))
        self._next_seq += 1
        self._unlogged[seq] = frame
        self.stats.frames_sent += 1
        while True:
            ws = await self._ensure_open()
            try:
                await ws.send(frame)
                self._last_send = asyncio.get_running_loop().time()
                return seq
            except ConnectionClosed:
                await asyncio.sleep(0)  # the reader records why; _ensure_open reconnects
                if self._failure is None:
                    self._failure = ConnectionError("connection closed while sending")

    async def _room_for(self, n_bytes: int) -> None:
        """Wait until one more unlogged frame stays within the server's read-ahead bounds."""
        while self._failure is None and self._unlogged and (
            (self._max_unlogged is not None and len(self._unlogged) >= self._max_unlogged)
            or (
                self._max_unlogged_bytes is not None
                and sum(len(f) for f in self._unlogged.values()) + n_bytes > self._max_unlogged_bytes
            )
        ):
            self._changed.clear()
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self._changed.wait(), 1.0)

    async def _throttle(self) -> None:
        """While the server says ``slow_down``: wait until the next frame is due at its advised
        rate, or until it says ``resume`` (or the connection drops: reconnecting resets it)."""
        loop = asyncio.get_running_loop()
        start = loop.time()
        while self._paused and self._failure is None:
            rate = self._advised_rate_hz
            wait_s = 1.0
            if rate:
                due = self._last_send + 1.0 / rate
                if loop.time() >= due:
                    break
                wait_s = due - loop.time()
            self._changed.clear()
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self._changed.wait(), wait_s)
        self.stats.throttled_s += loop.time() - start

    async def drain(self, timeout_s: float = DRAIN_TIMEOUT_S) -> list[dict[str, Any]]:
        """Wait until every frame sent is logged and its result pushed (reconnecting as
        needed); returns all results received so far, in order."""
        loop = asyncio.get_running_loop()
        deadline = loop.time() + timeout_s
        while self._unlogged or self._awaiting:
            await self._ensure_open()
            left = deadline - loop.time()
            if left <= 0:
                raise TimeoutError(
                    f"{len(self._unlogged)} frames not logged and {len(self._awaiting)} results "
                    f"missing after {timeout_s} s"
                )
            self._changed.clear()
            if not (self._unlogged or self._awaiting) or self._failure is not None:
                continue
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self._changed.wait(), left)
        return self.stats.results


def frames_of(
    t_s: FloatArray, channels: Mapping[str, FloatArray], frame_samples: int
) -> list[tuple[FloatArray, dict[str, FloatArray]]]:
    """Cut a series into frames of ``frame_samples`` samples (the last may be shorter)."""
    return [
        (t_s[i : i + frame_samples], {k: v[i : i + frame_samples] for k, v in channels.items()})
        for i in range(0, len(t_s), frame_samples)
    ]
