"""WebSocket streaming against a real server: results pushed back, resume, crash recovery,
malformed frames, back-pressure, fleet events, slow subscribers and many connections."""

from __future__ import annotations

import asyncio
import socket
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import orjson
import pytest
from fleethealth_client import FleetHealthClient
from fleethealth_client.streaming import (
    FrameStreamer,
    StreamRefused,
    encode_frame,
    frames_of,
    ws_url,
)
from websockets.asyncio.client import connect
from websockets.exceptions import ConnectionClosed

from app.auth.service import create_key
from app.db import Database
from tests.conftest import make_series
from tests.e2e.conftest import LiveServer

pytestmark = pytest.mark.e2e

FAKF = {"fakf": {"identification_samples": 300, "health_window_samples": 250}}
TAIL = "WS1"
FRAME = 100


def _setup(server: LiveServer, *actuators: str, tail: str = TAIL) -> None:
    with FleetHealthClient(server.url, server.api_key) as client:
        client.create_aircraft(tail)
        for act in actuators:
            client.create_actuator(tail, act, estimators=FAKF)


def _outputs(server: LiveServer, act: str, tail: str = TAIL) -> dict[str, Any]:
    r = httpx.get(
        f"{server.url}/v1/aircraft/{tail}/actuators/{act}/outputs?estimator=fakf&max_samples=1000000&order=asc",
        headers=server.headers,
        timeout=30,
    )
    assert r.status_code == 200, r.text
    return r.json()  # type: ignore[no-any-return]


def _health(server: LiveServer, act: str, tail: str = TAIL) -> dict[str, Any]:
    r = httpx.get(f"{server.url}/v1/aircraft/{tail}/actuators/{act}/health", headers=server.headers, timeout=30)
    assert r.status_code == 200, r.text
    return r.json()  # type: ignore[no-any-return]


def _reference(server: LiveServer, act: str, series: Any) -> dict[str, Any]:
    """The same series posted as one REST batch: the outputs streaming must reproduce."""
    with FleetHealthClient(server.url, server.api_key) as client:
        client.post_batch(
            TAIL, act, "all", {"current": series.current, "voltage": series.voltage},
            t_s=series.t_s, fmt="arrow", wait_s=60,
        )
    return _outputs(server, act)


def _frames(series: Any) -> list[tuple[np.ndarray, dict[str, np.ndarray]]]:
    return frames_of(series.t_s, {"current": series.current, "voltage": series.voltage}, FRAME)


@pytest.mark.parametrize("binary", [False, True], ids=["json", "arrow"])
def test_streamed_frames_get_results_and_match_one_rest_batch(live_server: LiveServer, binary: bool) -> None:
    server = live_server
    _setup(server, "ref", "ws")
    series = make_series(3000, seed=5)
    ref = _reference(server, "ref", series)

    async def run() -> FrameStreamer:
        async with FrameStreamer(server.url, server.api_key, TAIL, "ws", binary=binary) as fs:
            assert fs.ready["last_client_seq"] is None and fs.ready["channels"] == ["current", "voltage"]
            for t, chans in _frames(series):
                await fs.send(chans, t_s=t)
            await fs.drain(60)
            return fs

    fs = asyncio.run(run())
    results = fs.stats.results
    assert [r["client_seq"] for r in results] == list(range(1, 31))
    assert [r["seq"] for r in results] == list(range(1, 31))
    last = results[-1]
    assert last["t_last_s"] == pytest.approx(series.t_s[-1])
    est = last["estimators"]["fakf"]
    out = _outputs(server, "ws")
    assert est["last"]["voltage_estimate"] == pytest.approx(out["series"]["voltage_estimate"][-1], rel=0, abs=0)
    # Health windows are pushed with the frame that completes them: 3000 samples / 250.
    assert sum(len(r["estimators"]["fakf"]["health"]) for r in results) == 12
    # Exactly once, in order: the stored outputs equal those of the single REST batch.
    assert out["t_s"] == ref["t_s"]
    assert out["series"] == ref["series"]


def test_auth_by_first_message_and_refusals(live_server: LiveServer, tmp_path: Path) -> None:
    server = live_server
    _setup(server, "a")
    db = Database(server.db_url)
    with db.write() as s:
        _, read_only = create_key(s, "default", ["read"])
    db.dispose()
    url = ws_url(server.url, f"/v1/aircraft/{TAIL}/actuators/a/stream")

    async def run() -> None:
        # A browser cannot set headers: the key comes in the first message.
        fs = FrameStreamer(server.url, server.api_key, TAIL, "a", auth_message=True)
        await fs.open()
        assert fs.ready["type"] == "ready"
        await fs.close()
        for headers, first in (
            ({"Authorization": "Bearer fh_nonsense"}, None),
            ({"Authorization": f"Bearer {read_only}"}, None),  # lacks the ingest scope
            (None, {"type": "hello"}),
        ):
            async with connect(url, additional_headers=headers) as ws:
                if first is not None:
                    await ws.send(orjson.dumps(first).decode())
                msg = orjson.loads(await ws.recv())
                assert msg["type"] == "error"
                with pytest.raises(ConnectionClosed):
                    await ws.recv()
                assert ws.close_code == 1008
        # Another tail or actuator: refused the same way.
        async with connect(ws_url(server.url, f"/v1/aircraft/{TAIL}/actuators/nope/stream"),
                           additional_headers=server.headers) as ws:
            assert orjson.loads(await ws.recv())["error"] == "NotFound"
            with pytest.raises(ConnectionClosed):
                await ws.recv()
            assert ws.close_code == 1008

    asyncio.run(run())


def test_malformed_frames_are_refused_with_a_close_code_and_nothing_is_stored(live_server: LiveServer) -> None:
    server = live_server
    _setup(server, "m")
    url = ws_url(server.url, f"/v1/aircraft/{TAIL}/actuators/m/stream")
    t = np.arange(10) * 0.001
    good = encode_frame(1, {"current": np.ones(10), "voltage": np.ones(10)}, t_s=t)
    cases: list[tuple[str | bytes, int, str]] = [
        ("{not json", 1007, "InvalidBatch"),
        (orjson.dumps({"type": "telemetry", "client_seq": 1}).decode(), 1003, "UnsupportedFrame"),
        (orjson.dumps({"type": "samples", "client_seq": 0, "t": [0.0], "channels": {"current": [1], "voltage": [1]}}).decode(),
         1007, "InvalidBatch"),
        (encode_frame(1, {"current": np.ones(10)}, t_s=t), 1007, "InvalidBatch"),  # a channel missing
        (encode_frame(1, {"current": np.ones(10), "voltage": np.ones(10)}, t_s=t[::-1].copy()), 1007, "InvalidBatch"),
        (b"not an arrow stream", 1007, "InvalidBatch"),
    ]

    async def run() -> None:
        for frame, code, error in cases:
            async with connect(url, additional_headers=server.headers) as ws:
                assert orjson.loads(await ws.recv())["type"] == "ready"
                await ws.send(frame)
                msg = orjson.loads(await ws.recv())
                assert msg["type"] == "error" and msg["error"] == error, msg
                with pytest.raises(ConnectionClosed):
                    await ws.recv()
                assert ws.close_code == code, (frame, ws.close_code)
        assert _health(server, "m")["last_logged_seq"] == 0
        # A valid frame, then one whose client_seq goes back: 1008, the first stays logged once.
        async with connect(url, additional_headers=server.headers) as ws:
            await ws.recv()
            await ws.send(good)
            assert orjson.loads(await ws.recv())["type"] == "logged"
            await ws.send(good)  # the same frame again: a duplicate, not a second batch
            msgs = [orjson.loads(await ws.recv()) for _ in range(2)]
            assert {m["type"] for m in msgs} == {"duplicate", "result"}
            late = encode_frame(2, {"current": np.ones(10), "voltage": np.ones(10)}, t_s=t)  # t not after
            await ws.send(late)
            msg = orjson.loads(await ws.recv())
            assert msg["error"] == "StaleBatch"
            with pytest.raises(ConnectionClosed):
                await ws.recv()
            assert ws.close_code == 1008
        assert _health(server, "m")["last_logged_seq"] == 1
        # The client helper raises the refusal instead of retrying it.
        fs = FrameStreamer(server.url, server.api_key, TAIL, "m")
        await fs.open()
        await fs.send({"current": np.ones(10), "volts": np.ones(10)}, t_s=t + 1.0)
        with pytest.raises(StreamRefused) as refused:
            await fs.drain(30)
        assert refused.value.code == 1007 and "volts" in refused.value.detail
        await fs.close()

    asyncio.run(run())


def test_resume_after_dropped_connections_loses_nothing_and_logs_nothing_twice(live_server: LiveServer) -> None:
    server = live_server
    _setup(server, "ref", "ws")
    series = make_series(4000, seed=8)
    ref = _reference(server, "ref", series)
    frames = _frames(series)

    async def run() -> FrameStreamer:
        fs = FrameStreamer(server.url, server.api_key, TAIL, "ws", binary=True)
        await fs.open()
        for k, (t, chans) in enumerate(frames):
            await fs.send(chans, t_s=t)
            if k in (7, 21, 33):
                await fs.drop()  # abrupt: frames in flight may or may not be logged
        await fs.drain(60)
        await fs.close()
        return fs

    fs = asyncio.run(run())
    assert fs.stats.connects == 4
    h = _health(server, "ws")
    assert h["last_logged_seq"] == len(frames) == h["last_applied_seq"]
    out = _outputs(server, "ws")
    assert out["t_s"] == ref["t_s"] and out["series"] == ref["series"]

    # A new client continues the numbering from what the server announces.
    async def again() -> dict[str, Any]:
        async with FrameStreamer(server.url, server.api_key, TAIL, "ws") as fs2:
            return fs2.ready

    ready = asyncio.run(again())
    assert ready["last_client_seq"] == len(frames) == ready["last_applied_client_seq"]


def test_streaming_survives_a_server_crash(live_server: LiveServer) -> None:
    server = live_server
    _setup(server, "ref", "ws")
    series = make_series(3000, seed=9)
    ref = _reference(server, "ref", series)
    frames = _frames(series)

    async def run() -> None:
        fs = FrameStreamer(server.url, server.api_key, TAIL, "ws", max_reconnects=200)
        await fs.open()
        for t, chans in frames[:12]:
            await fs.send(chans, t_s=t)
        await asyncio.sleep(0.3)
        server.kill()  # SIGKILL: whatever was acked as logged must survive
        restart = asyncio.get_running_loop().run_in_executor(None, server.start)
        for t, chans in frames[12:]:
            await fs.send(chans, t_s=t)  # reconnects (with backoff) once the server is back
        await restart
        await fs.drain(120)
        await fs.close()

    asyncio.run(run())
    h = _health(server, "ws")
    assert h["last_logged_seq"] == len(frames) == h["last_applied_seq"]
    out = _outputs(server, "ws")
    assert out["t_s"] == ref["t_s"] and out["series"] == ref["series"]


@pytest.fixture
def paused_server(tmp_path: Path) -> Any:
    """A server whose processor is off: frames are logged, never applied."""
    from app.migrate import upgrade

    url = f"sqlite:///{tmp_path / 'bp.db'}"
    upgrade(url)
    server = LiveServer(url, tmp_path / "server.log",
                        {"FLEETHEALTH_PROCESSOR_ENABLED": "false", "FLEETHEALTH_WS_MAX_INFLIGHT": "5",
                         "FLEETHEALTH_WS_SLOW_DOWN_FRAMES": "6", "FLEETHEALTH_WS_MAX_QUEUED_FRAMES": "8",
                         "FLEETHEALTH_SHUTDOWN_TIMEOUT_S": "1"})
    server.start()
    yield server
    server.stop()


def test_throttled_stream_keeps_answering_keepalive_and_drops_nothing(paused_server: LiveServer) -> None:
    server = paused_server
    _setup(server, "bp")
    series = make_series(40 * 50, seed=3)
    frames = frames_of(series.t_s, {"current": series.current, "voltage": series.voltage}, 50)
    url = ws_url(server.url, f"/v1/aircraft/{TAIL}/actuators/bp/stream")

    async def until_slow_down() -> list[dict[str, Any]]:
        async with connect(url, additional_headers=server.headers, ping_interval=None) as ws:
            assert orjson.loads(await ws.recv())["max_inflight"] == 5
            msgs: list[dict[str, Any]] = []
            for k, (t, c) in enumerate(frames):
                await ws.send(encode_frame(k + 1, c, t_s=t))
                # The server reads on: every frame gets an answer or a slow_down before long.
                while len(msgs) < k + 1 and not any(m["type"] == "slow_down" for m in msgs):
                    try:
                        msgs.append(orjson.loads(await asyncio.wait_for(ws.recv(), 2.0)))
                    except TimeoutError:
                        break  # queued behind the full window: not logged, no answer yet
                if any(m["type"] == "slow_down" for m in msgs):
                    break
            # Throttled, not stalled: the server still reads the socket, so a keepalive ping
            # is answered (the old back-pressure stopped reading and pings timed out).
            for _ in range(3):
                await asyncio.wait_for(await ws.ping(), 10.0)
            ws.transport.abort()
            return msgs

    msgs = asyncio.run(until_slow_down())
    logged = [m["client_seq"] for m in msgs if m["type"] == "logged"]
    slow = [m for m in msgs if m["type"] == "slow_down"]
    assert logged == [1, 2, 3, 4, 5] and len(slow) == 1, msgs
    assert slow[0]["inflight"] == 5 and slow[0]["queued"] == 1 and "rate_hz" in slow[0]
    assert _health(server, "bp")["last_logged_seq"] == 5  # the queued frame was never acknowledged

    # Nothing was silently dropped: with processing back, a resuming client finishes the stream.
    server.stop()
    server.extra_env["FLEETHEALTH_PROCESSOR_ENABLED"] = "true"
    server.start()

    async def finish() -> FrameStreamer:
        async with FrameStreamer(server.url, server.api_key, TAIL, "bp") as fs:
            assert fs.ready["last_client_seq"] == 5
            for t, c in frames[5:]:
                await fs.send(c, t_s=t)
            await fs.drain(60)
            return fs

    fs = asyncio.run(finish())
    # Frames 1-5 were logged before; their results are pushed unless recovery applied them
    # before this client connected (then they are in the store).
    first = (fs.ready["last_applied_client_seq"] or 0) + 1
    assert [r["client_seq"] for r in fs.stats.results] == list(range(first, 41))
    assert _health(server, "bp")["last_applied_seq"] == 40
    assert fs.stats.connects == 1


@pytest.fixture
def throttling_server(tmp_path: Path) -> Any:
    from app.migrate import upgrade

    url = f"sqlite:///{tmp_path / 'th.db'}"
    upgrade(url)
    server = LiveServer(url, tmp_path / "server.log",
                        {"FLEETHEALTH_WS_MAX_INFLIGHT": "2", "FLEETHEALTH_WS_SLOW_DOWN_FRAMES": "4",
                         "FLEETHEALTH_WS_MAX_QUEUED_FRAMES": "8"})
    server.start()
    yield server
    server.stop()


def test_a_fast_sender_is_slowed_down_and_resumed_not_dropped(throttling_server: LiveServer) -> None:
    server = throttling_server
    _setup(server, "fast")
    series = make_series(60 * 200, seed=4)
    frames = frames_of(series.t_s, {"current": series.current, "voltage": series.voltage}, 200)

    async def run() -> FrameStreamer:
        async with FrameStreamer(server.url, server.api_key, TAIL, "fast") as fs:
            for t, c in frames:
                await fs.send(c, t_s=t)
            await fs.drain(120)
            return fs

    fs = asyncio.run(run())
    assert fs.stats.connects == 1  # backed off, never reconnected
    assert fs.stats.slow_downs >= 1 and fs.stats.resumes >= 1
    assert [r["client_seq"] for r in fs.stats.results] == list(range(1, 61))
    assert _health(server, "fast")["last_applied_seq"] == 60


def _status_flip_batch(n: int = 800) -> dict[str, Any]:
    """Constant current: identification cannot succeed, so the status turns unknown."""
    t = np.arange(n) * 0.001
    return {"t_s": t, "channels": {"current": np.ones(n), "voltage": np.ones(n)}}


def test_fleet_events_are_filtered_by_operator_and_tail(live_server: LiveServer) -> None:
    server = live_server
    _setup(server, "x", tail="FA")
    _setup(server, "x", tail="FB")
    db = Database(server.db_url)
    with db.write() as s:
        _, other = create_key(s, "other-operator", ["read"])
    db.dispose()
    base = ws_url(server.url, "/v1/fleet/events")

    async def run() -> tuple[list[dict[str, Any]], list[dict[str, Any]], list[dict[str, Any]]]:
        async with (
            connect(base + "?tail=FA", additional_headers=server.headers) as only_a,
            connect(base, additional_headers=server.headers) as everything,
            connect(base, additional_headers={"Authorization": f"Bearer {other}"}) as stranger,
        ):
            for ws in (only_a, everything, stranger):
                assert orjson.loads(await ws.recv())["type"] == "ready"
            with FleetHealthClient(server.url, server.api_key) as client:
                for tail in ("FA", "FB"):
                    b = _status_flip_batch()
                    client.post_batch(tail, "x", "b1", b["channels"], t_s=b["t_s"], wait_s=30)

            async def collect(ws: Any, want: int) -> list[dict[str, Any]]:
                got: list[dict[str, Any]] = []
                with pytest.raises(TimeoutError):
                    while len(got) < want + 1:  # bounded: one more than expected, or 2 s silence
                        got.append(orjson.loads(await asyncio.wait_for(ws.recv(), 2.0)))
                return got

            return await collect(only_a, 1), await collect(everything, 2), await collect(stranger, 0)

    a, both, none = asyncio.run(run())
    assert [(e["type"], e["tail"], e["from"], e["to"]) for e in a] == [("status_changed", "FA", "learning", "unknown")]
    assert sorted(e["tail"] for e in both) == ["FA", "FB"]
    assert all(e["type"] == "status_changed" and e["reasons"] for e in both)
    assert none == []

    async def bad_filter() -> int | None:
        async with connect(base + "?types=gossip", additional_headers=server.headers) as ws:
            assert orjson.loads(await ws.recv())["type"] == "error"
            with pytest.raises(ConnectionClosed):
                await ws.recv()
            return ws.close_code

    assert asyncio.run(bad_filter()) == 1008


@pytest.fixture
def small_queue_server(tmp_path: Path) -> Any:
    from app.migrate import upgrade

    url = f"sqlite:///{tmp_path / 'sq.db'}"
    upgrade(url)
    server = LiveServer(
        url,
        tmp_path / "server.log",
        # One frame per apply transaction: events come one by one, not in bursts above the queue.
        # The queue still leaves the fast subscriber, which shares a busy event loop with the
        # sender, room to fall behind by a hundred events; the stalled one overflows it anyway
        # (it never reads, and 2000 events are far more than its buffers and queue hold).
        # A small kernel send buffer, so that a subscriber that reads nothing stalls the server's
        # sends after tens of kilobytes rather than megabytes.
        {
            "FLEETHEALTH_WS_SUBSCRIBER_QUEUE": "100",
            "FLEETHEALTH_PROCESSOR_MAX_SAMPLES_PER_TXN": "5",
            "FLEETHEALTH_SOCKET_SEND_BUFFER_BYTES": "8192",
            # The stalled subscriber reads nothing (not even pings) until ingest has finished,
            # which takes longer than the defaults on a busy machine: the 1013 close frame must
            # wait in the send queue behind the unread events for as long as the test runs,
            # rather than the connection being dropped first by keepalive or the close timeout.
            "FLEETHEALTH_WS_CLOSE_TIMEOUT_S": "600",
            "FLEETHEALTH_WS_PING_INTERVAL_S": "600",
            "FLEETHEALTH_WS_PING_TIMEOUT_S": "600",
        },
    )
    server.start()
    yield server
    server.stop()


def test_a_slow_subscriber_is_dropped_and_does_not_slow_ingest(small_queue_server: LiveServer) -> None:
    server = small_queue_server
    _setup(server, "s")
    n_frames = 2000
    series = make_series(n_frames * 5, seed=4)
    frames = frames_of(series.t_s, {"current": series.current, "voltage": series.voltage}, 5)
    url = ws_url(server.url, "/v1/fleet/events?types=applied")
    port = int(server.url.rsplit(":", 1)[1])

    async def run() -> tuple[int, int | None, int]:
        # The slow subscriber reads nothing, through a tiny receive buffer.
        sock = socket.socket()
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        sock.connect(("127.0.0.1", port))
        # Its own keepalive is off as well: it reads nothing (not even pongs) for as long as
        # ingest takes, and must not give up before the server's 1013.
        slow = await connect(url, additional_headers=server.headers, sock=sock, max_queue=1, ping_interval=None)
        fast = await connect(url, additional_headers=server.headers)
        fast_seen = 0

        async def read_fast() -> None:
            nonlocal fast_seen
            async for raw in fast:
                if orjson.loads(raw)["type"] == "applied":
                    fast_seen += 1
                    if fast_seen == n_frames:
                        return

        reader = asyncio.create_task(read_fast())
        async with FrameStreamer(server.url, server.api_key, TAIL, "s") as fs:
            for t, c in frames:
                await fs.send(c, t_s=t)
            await fs.drain(300)
            streamed = len(fs.stats.results)
        await asyncio.wait_for(reader, 120)
        await fast.close()
        # Now the slow one reads: what was buffered, then the close.
        slow_seen = 0
        with pytest.raises(ConnectionClosed):
            while True:
                msg = orjson.loads(await asyncio.wait_for(slow.recv(), 30))
                slow_seen += msg["type"] == "applied"
        return streamed, slow.close_code, slow_seen

    streamed, code, slow_seen = asyncio.run(run())
    assert streamed == n_frames  # ingest finished every frame while the subscriber stalled
    assert code == 1013
    assert slow_seen < n_frames
    assert _health(server, "s")["last_applied_seq"] == n_frames


def test_hundreds_of_concurrent_streams(live_server: LiveServer) -> None:
    server = live_server
    n_streams, n_frames = 200, 3
    with FleetHealthClient(server.url, server.api_key) as client:
        client.create_aircraft("MANY")
        for k in range(n_streams):
            client.create_actuator("MANY", f"a{k:03d}", estimators=FAKF)
    series = make_series(n_frames * 50, seed=1)
    frames = frames_of(series.t_s, {"current": series.current, "voltage": series.voltage}, 50)

    async def one(k: int) -> list[int]:
        async with FrameStreamer(server.url, server.api_key, "MANY", f"a{k:03d}", binary=k % 2 == 1) as fs:
            for t, c in frames:
                await fs.send(c, t_s=t)
            await fs.drain(240)
            return [r["client_seq"] for r in fs.stats.results]

    async def run() -> list[list[int]]:
        return await asyncio.wait_for(asyncio.gather(*(one(k) for k in range(n_streams))), 300)

    seen = asyncio.run(run())
    assert all(s == [1, 2, 3] for s in seen)
    fleet = httpx.get(f"{server.url}/v1/fleet/health", headers=server.headers, timeout=30).json()
    many = next(a for a in fleet["aircraft"] if a["tail"] == "MANY")
    assert {a["last_applied_seq"] for a in many["actuators"]} == {n_frames}


def test_permessage_deflate_is_off_unless_configured(live_server: LiveServer) -> None:
    """The client offers permessage-deflate (websockets does by default); the server takes it
    only when ``FLEETHEALTH_WS_PER_MESSAGE_DEFLATE`` is on, and streams alike either way."""
    server = live_server
    _setup(server, "defl")
    series = make_series(2 * FRAME, seed=9)
    frames = _frames(series)
    url = ws_url(server.url, f"/v1/aircraft/{TAIL}/actuators/defl/stream")

    async def one_frame(client_seq: int) -> tuple[str | None, list[str]]:
        async with connect(url, additional_headers=server.headers) as ws:
            extensions = ws.response.headers.get("Sec-WebSocket-Extensions")
            assert orjson.loads(await asyncio.wait_for(ws.recv(), 30))["type"] == "ready"
            t, c = frames[client_seq - 1]
            await ws.send(encode_frame(client_seq, c, t_s=t, binary=True))
            kinds: list[str] = []
            while "result" not in kinds:
                kinds.append(orjson.loads(await asyncio.wait_for(ws.recv(), 60))["type"])
            return extensions, kinds

    extensions, kinds = asyncio.run(one_frame(1))
    assert extensions is None and kinds == ["logged", "result"]

    server.stop()
    server.extra_env["FLEETHEALTH_WS_PER_MESSAGE_DEFLATE"] = "true"
    server.start()
    extensions, kinds = asyncio.run(one_frame(2))
    assert extensions is not None and "permessage-deflate" in extensions
    assert kinds == ["logged", "result"]
