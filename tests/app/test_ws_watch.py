"""The process-wide checks of open WebSockets (app.websocket.watch): one reading per interval
for every connection, not one per connection; and the hand-overs a stream connection waits on
instead of a timer of its own (a failed stream wakes it, a frame reaches the log writer from the
parse thread)."""

from __future__ import annotations

import asyncio
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import orjson
import pytest
from fastapi.testclient import TestClient
from sqlalchemy import select
from starlette.websockets import WebSocketDisconnect

from app.auth.service import Principal, authenticate, create_key, revoke_key
from app.db import Database
from app.errors import DomainError, InvalidBatch, Unauthorized
from app.ingest import frame_batch_id
from app.main import create_app
from app.models import Actuator
from app.telemetry.service import prepare_frame
from app.telemetry.validation import DEFAULT_LIMITS
from app.telemetry.writer import LogWriter
from app.websocket import service
from app.websocket.feed import FrameFeed, FrameSource
from app.websocket.hub import Hub, Subscription, inbox
from app.websocket.watch import KeyGuard, ResultSweep
from estimators import fakf
from tests.app.conftest import Api, make_settings

FRAME = {"type": "samples", "client_seq": 1, "t": [0.0, 0.001], "channels": {"current": [0.1, 0.2], "voltage": [1.0, 1.1]}}


def _counting(monkeypatch: pytest.MonkeyPatch, name: str) -> list[Any]:
    """Record each call of ``service.<name>`` (its arguments), calling through."""
    calls: list[Any] = []
    real = getattr(service, name)

    def counted(db: Database, arg: Any) -> Any:
        calls.append(arg)
        return real(db, arg)

    monkeypatch.setattr(service, name, counted)
    return calls


def _actuator_pk(db_url: str, actuator_id: str = "ema1") -> int:
    db = Database(db_url)
    with db.read() as s:
        pk = s.scalar(select(Actuator.id).where(Actuator.actuator_id == actuator_id))
    db.dispose()
    assert pk is not None
    return int(pk)


def _principal(db: Database, key: str) -> Principal:
    with db.read() as s:
        return authenticate(s, f"Bearer {key}")


async def _until(cond: Any, bound: int = 2000) -> None:
    """Let the loop run until ``cond()`` holds (a bounded number of short waits, no fixed sleep)."""
    for _ in range(bound):
        if cond():
            return
        await asyncio.sleep(0.005)
    raise AssertionError("condition not reached")


def test_one_key_reading_per_interval_serves_every_connection_and_a_revocation_reaches_all(
    db_url: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    db = Database(db_url)
    with db.write() as s:
        row, key = create_key(s, "default", ["ingest", "read"], name="stand")
        _, other = create_key(s, "default", ["read"], name="board")
    stand, board = _principal(db, key), _principal(db, other)
    reads = _counting(monkeypatch, "read_keys")

    async def run() -> tuple[list[DomainError | None], list[DomainError | None], bool]:
        guard = KeyGuard(db, 0.02)
        watches = [guard.watch(stand, "ingest") for _ in range(200)] + [guard.watch(board, "read")]
        await _until(lambda: len(reads) >= 3)
        # 201 connections, two (key, scope) pairs: each reading covers both, once.
        assert all(sorted(r) == sorted([(stand.key_id, "ingest"), (board.key_id, "read")]) for r in reads)
        assert not any(w.refused.done() for w in watches)
        with db.write() as s:
            assert revoke_key(s, row.id)
        await _until(lambda: all(w.refused.done() for w in watches[:200]))
        refused = [w.refused.result() if w.refused.done() else None for w in watches]
        for w in watches:
            guard.unwatch(w)
        task = guard._task
        # The last connection gone, no timer is left behind.
        return refused[:200], refused[200:], task is None

    stands, boards, stopped = asyncio.run(run())
    db.dispose()
    assert all(isinstance(r, Unauthorized) and r.detail == "the API key was revoked" for r in stands)
    assert boards == [None] and stopped


def test_the_sweep_wakes_only_connections_whose_result_is_in_the_store(api: Api, db_url: str,
                                                                        monkeypatch: pytest.MonkeyPatch) -> None:
    api.setup_actuator()
    pk = _actuator_pk(db_url)
    r = api.c.post("/v1/aircraft/N1/actuators/ema1/telemetry?wait=60", headers=api.h,
                   json={"batch_id": "b1", "t": [0.0, 0.001], "channels": {"current": [0.1, 0.2], "voltage": [1.0, 1.1]}})
    assert r.status_code == 202, r.text
    assert api.health()["last_applied_seq"] == 1
    db = Database(db_url)
    reads = _counting(monkeypatch, "applied_marks")

    async def run() -> tuple[bool, bool, bool]:
        loop = asyncio.get_running_loop()
        applied, waiting, idle = (Subscription(loop, asyncio.Queue(1)) for _ in range(3))
        sweep = ResultSweep(db, 0.02)
        sweep.add(applied, lambda: (pk, 1))  # its result is in the store, its push was lost
        sweep.add(waiting, lambda: (pk, 2))  # not applied yet: the push will come
        sweep.add(idle, lambda: None)  # waits for nothing
        await _until(lambda: applied.stale)
        await _until(lambda: len(reads) >= 3)
        for sub in (applied, waiting, idle):
            sweep.discard(sub)
        return applied.wakeup.is_set(), waiting.stale or waiting.wakeup.is_set(), idle.stale

    woken, waiting_woken, idle_woken = asyncio.run(run())
    db.dispose()
    assert woken and not waiting_woken and not idle_woken
    assert all(r == [pk] for r in reads)  # one query per round, for every waiting connection


def test_a_failed_stream_wakes_its_stream_connections() -> None:
    async def run() -> tuple[bool, bool, bool]:
        hub = Hub()
        sub = hub.subscribe_stream(7, maxsize=4)
        other = hub.subscribe_stream(8, maxsize=4)
        hub.mark_failed(7, "broken")
        await _until(lambda: sub.stale)
        return sub.stale, sub.wakeup.is_set(), other.stale

    assert asyncio.run(run()) == (True, True, False)


@pytest.fixture
def api_failing(db_url: str) -> Iterator[Api]:
    # No sweep within the test's time: only the failure's own wake-up can tell the connection.
    settings = make_settings(db_url, processor_max_attempts=1, ws_result_poll_s=3600.0)
    with TestClient(create_app(settings)) as client:
        yield Api(client)


def test_a_stream_connection_hears_its_stream_fail_without_polling(api_failing: Api,
                                                                  monkeypatch: pytest.MonkeyPatch) -> None:
    api = api_failing
    api.setup_actuator()
    assert api.app.state.kernels_warm.wait(300)

    def broken_step(cfg, state, batch):  # type: ignore[no-untyped-def]
        raise RuntimeError("kernel exploded")

    monkeypatch.setattr(fakf, "step", broken_step)
    with api.c.websocket_connect("/v1/aircraft/N1/actuators/ema1/stream", headers=api.h) as ws:
        assert ws.receive_json()["type"] == "ready"
        ws.send_json(FRAME)
        assert ws.receive_json()["type"] == "logged"
        err = ws.receive_json()
        assert err["type"] == "error" and err["error"] == "StreamFailed" and "kernel exploded" in err["detail"]
        with pytest.raises(WebSocketDisconnect) as closed:
            ws.receive_json()
    assert closed.value.code == 1011


class _CountingPool(ThreadPoolExecutor):
    """A parse pool that counts its jobs."""

    def __init__(self) -> None:
        super().__init__(max_workers=2)
        self.jobs = 0

    def submit(self, fn: Any, /, *args: Any, **kwargs: Any) -> Any:
        self.jobs += 1
        return super().submit(fn, *args, **kwargs)


def test_frames_of_one_loop_pass_go_to_the_parse_pool_together(db_url: str, api: Api) -> None:
    """Frames put by several connections in one pass of the loop cost one job of the parse pool
    per burst (not one per frame); each is handed to the log writer and answered with its own
    acknowledgement, in order; a bad one is refused with its own error and never reaches the
    writer, without spoiling the others of its burst. (A connection puts its next frame only
    after this one's acknowledgement, so only the frames within one job have an order: the two
    jobs may run at once.)"""
    api.setup_actuator()
    api.setup_actuator(act="ema2")
    api.setup_actuator(act="ema3")
    pk, pk2, pk3 = _actuator_pk(db_url), _actuator_pk(db_url, "ema2"), _actuator_pk(db_url, "ema3")
    db = Database(db_url)
    writer = LogWriter(db)
    writer.start()
    submitted: list[tuple[int, str]] = []
    real_submit = writer.submit

    def submit(actuator_pk: int, batch: Any) -> Any:
        submitted.append((actuator_pk, batch.batch_id))
        return real_submit(actuator_pk, batch)

    pool = _CountingPool()
    chans = ["current", "voltage"]
    settings = api.app.state.settings
    bad = {**FRAME, "client_seq": True}

    async def run() -> list[Any]:
        loop = asyncio.get_running_loop()
        feed = FrameFeed(loop, pool, inbox(loop), prepare_frame, burst=4)
        one = FrameSource(pk, chans, settings.max_batch_samples, DEFAULT_LIMITS, submit)
        two = FrameSource(pk2, chans, settings.max_batch_samples, DEFAULT_LIMITS, submit)
        three = FrameSource(pk3, chans, settings.max_batch_samples, DEFAULT_LIMITS, submit)
        outs = [feed.put(one, orjson.dumps(FRAME).decode()),
                feed.put(two, orjson.dumps(FRAME).decode()),
                feed.put(two, orjson.dumps(bad).decode()),
                feed.put(two, orjson.dumps({**FRAME, "client_seq": 2, "t": [1.0, 1.001]}).decode()),
                feed.put(three, orjson.dumps(FRAME).decode())]
        return await asyncio.gather(*outs, return_exceptions=True)

    try:
        got = asyncio.run(run())
        assert pool.jobs == 2  # five frames, bursts of four
        assert [(c, a.seq) for c, a in (got[0], got[1], got[3], got[4])] == [(1, 1), (1, 1), (2, 2), (1, 1)]
        assert isinstance(got[2], InvalidBatch) and "client_seq" in str(got[2])
        first_job = [(p, b) for p, b in submitted if p != pk3]
        assert first_job == [(pk, frame_batch_id(1)), (pk2, frame_batch_id(1)), (pk2, frame_batch_id(2))]
        assert [(p, b) for p, b in submitted if p == pk3] == [(pk3, frame_batch_id(1))]
        assert api.health()["last_logged_seq"] == 1 and api.health(act="ema2")["last_logged_seq"] == 2
        assert api.health(act="ema3")["last_logged_seq"] == 1
    finally:
        pool.shutdown()
        writer.stop()
        db.dispose()
