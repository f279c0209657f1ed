"""The clients against loopback servers that misbehave: a WebSocket handshake cut short (the
streamer retries with back-off and loses nothing), and 503 answers with ``Retry-After`` (the
REST client waits as told and retries)."""

from __future__ import annotations

import asyncio
import contextlib
import threading
import time
from collections.abc import Iterator
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Any

import numpy as np
import orjson
import pytest
from fleethealth_client import FleetHealthClient
from fleethealth_client.retry import RetryPolicy, parse_retry_after
from fleethealth_client.streaming import FrameStreamer
from websockets.asyncio.server import ServerConnection, serve


class CuttingFront:
    """127.0.0.1 front of a WebSocket server: the next ``cuts`` connections are closed once the
    client's handshake request has arrived (no response, as when a server dies mid-handshake);
    the others are forwarded."""

    def __init__(self, backend_port: int) -> None:
        self.backend_port = backend_port
        self.cuts = 0
        self.cut_done = 0
        self.server: asyncio.Server | None = None

    async def start(self) -> int:
        self.server = await asyncio.start_server(self._handle, "127.0.0.1", 0)
        return int(self.server.sockets[0].getsockname()[1])

    async def _handle(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        head = await reader.readuntil(b"\r\n\r\n")
        if self.cuts > 0:
            self.cuts -= 1
            self.cut_done += 1
            writer.write(b"HTTP/1.1 101 Swi")  # a response cut in the middle
            await writer.drain()
            writer.transport.abort()
            return
        up_r, up_w = await asyncio.open_connection("127.0.0.1", self.backend_port)
        up_w.write(head)

        async def pipe(src: asyncio.StreamReader, dst: asyncio.StreamWriter) -> None:
            with contextlib.suppress(OSError, asyncio.IncompleteReadError):
                while data := await src.read(65536):
                    dst.write(data)
                    await dst.drain()
            dst.close()

        await asyncio.gather(pipe(reader, up_w), pipe(up_r, writer))


class FakeStreamServer:
    """The server side of the stream protocol, enough for the client: ready with resume
    positions, logged then result per frame."""

    def __init__(self) -> None:
        self.logged: list[int] = []

    async def handler(self, ws: ServerConnection) -> None:
        last = self.logged[-1] if self.logged else None
        await ws.send(orjson.dumps({"type": "ready", "last_client_seq": last,
                                    "last_applied_client_seq": last, "max_inflight": 16}).decode())
        async for raw in ws:
            seq = orjson.loads(raw)["client_seq"]
            if self.logged and seq <= self.logged[-1]:
                await ws.send(orjson.dumps({"type": "duplicate", "client_seq": seq, "seq": seq}).decode())
                continue
            self.logged.append(seq)
            await ws.send(orjson.dumps({"type": "logged", "client_seq": seq, "seq": seq}).decode())
            await ws.send(orjson.dumps({"type": "result", "client_seq": seq, "seq": seq}).decode())


def test_streamer_survives_cut_handshakes_and_loses_nothing() -> None:
    async def run() -> None:
        fake = FakeStreamServer()
        async with serve(fake.handler, "127.0.0.1", 0) as backend:
            front = CuttingFront(int(next(iter(backend.sockets)).getsockname()[1]))
            port = await front.start()
            front.cuts = 3
            fs = FrameStreamer(f"http://127.0.0.1:{port}", "k", "N1", "a", reconnect_delays_s=(0.05, 0.1))
            await fs.open()
            assert front.cut_done == 3 and fs.stats.connects == 1
            for i in range(3):
                await fs.send({"x": np.array([1.0, 2.0])}, t_s=np.array([2.0 * i, 2.0 * i + 1]))
            await fs.drain(timeout_s=30)
            # The connection drops and the server dies again during the next handshakes.
            front.cuts = 2
            await fs.drop()
            for i in range(3, 6):
                await fs.send({"x": np.array([1.0, 2.0])}, t_s=np.array([2.0 * i, 2.0 * i + 1]))
            results = await fs.drain(timeout_s=30)
            await fs.close()
            assert front.cut_done == 5 and fs.stats.connects == 2
            assert fake.logged == [1, 2, 3, 4, 5, 6]
            assert sorted({r["client_seq"] for r in results}) == [1, 2, 3, 4, 5, 6]
            assert front.server is not None
            front.server.close()

    asyncio.run(asyncio.wait_for(run(), 120))


# ----------------------------------------------------------------------------- 503 Retry-After
class _Handler(BaseHTTPRequestHandler):
    unavailable = 2
    seen: list[float] = []

    def do_GET(self) -> None:  # noqa: N802 (http.server's naming)
        type(self).seen.append(time.monotonic())
        if type(self).unavailable > 0:
            type(self).unavailable -= 1
            body = b'{"error": "StorageUnavailable", "detail": "disk full"}'
            self.send_response(503)
            self.send_header("Retry-After", "1")
        else:
            body = b'{"status": "ok"}'
            self.send_response(200)
        self.send_header("Content-Type", "application/json")
        self.send_header("Content-Length", str(len(body)))
        self.end_headers()
        self.wfile.write(body)

    def log_message(self, *args: Any) -> None:
        pass


@pytest.fixture
def unavailable_twice() -> Iterator[str]:
    _Handler.unavailable, _Handler.seen = 2, []
    server = ThreadingHTTPServer(("127.0.0.1", 0), _Handler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    yield f"http://127.0.0.1:{server.server_address[1]}"
    server.shutdown()


def test_rest_client_retries_503_after_retry_after(unavailable_twice: str) -> None:
    # The computed back-off would be ~1 ms: the waits seen are the server's 1 s.
    policy = RetryPolicy(max_retries=3, backoff_s=0.001, max_backoff_s=0.001)
    with FleetHealthClient(unavailable_twice, "k", retry=policy) as c:
        assert c.healthz() == {"status": "ok"}
    gaps = np.diff(_Handler.seen)
    assert len(_Handler.seen) == 3 and (gaps >= 0.99).all(), gaps


def test_retry_after_forms() -> None:
    assert parse_retry_after("7") == 7.0
    assert parse_retry_after(None) is None and parse_retry_after("soon") is None
    assert 0.0 <= (parse_retry_after("Wed, 21 Oct 2015 07:28:00 GMT") or 0.0) == 0.0
    assert RetryPolicy(max_retry_after_s=2.0).delay_s(0, "30") <= 2.2
