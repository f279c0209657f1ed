"""The in-process hub: fleet events derived from an apply, filtering, bounded queues; frame
parsing."""

from __future__ import annotations

import asyncio
import threading
from concurrent.futures import Future

import numpy as np
import pytest
from fleethealth_client.streaming import encode_frame

from app.errors import InvalidBatch
from app.ingest import UnsupportedFrame, client_seq_of, frame_batch_id, parse_frame
from app.processing import ApplyResult
from app.processing.messages import BatchResult, EstimatorResult
from app.websocket.hub import Hub, Inbox, StreamMeta, fleet_events, inbox, public


def _applied(seq: int, status: str, events: list[dict] | None = None) -> BatchResult:  # type: ignore[type-arg]
    return BatchResult(
        seq=seq,
        batch_id=f"b{seq}",
        t_first_s=float(seq),
        t_last_s=seq + 0.5,
        n_samples=10,
        status=status,
        estimators={
            "est": EstimatorResult(status=status, reasons=[f"r{seq}"] if status != "ok" else [], last={"x": 1.0},
                                   health=[], events=events or [], rul=[], diagnosis=None)
        },
    )


def test_fleet_events_report_status_changes_and_fleet_kinds_only() -> None:
    meta = StreamMeta(operator_id=7, tail="N1", actuator_id="a")
    res = ApplyResult(
        batches=3, samples=30, last_applied_seq=3, actuator_pk=1,
        applied=[
            _applied(1, "ok", [{"kind": "identified", "t_s": 1.0, "detail": {}}]),
            _applied(2, "alert", [{"kind": "fault_detected", "t_s": 2.2, "detail": {"component": "rudder"}}]),
            _applied(3, "alert"),
        ],
        status_before="ok", status_after="alert",
    )
    evs = fleet_events(meta, res)
    kinds = [(e["type"], e["seq"]) for e in evs if e["type"] != "applied"]
    assert kinds == [("fault_detected", 2), ("status_changed", 2)]  # "identified" is not a fleet event
    change = next(e for e in evs if e["type"] == "status_changed")
    assert (change["from"], change["to"], change["reasons"]) == ("ok", "alert", ["r2"])
    assert [e["seq"] for e in evs if e["type"] == "applied"] == [1, 2, 3]
    assert "_operator_id" not in public(change) and public(change)["tail"] == "N1"


def test_hub_filters_by_operator_tail_and_type_and_drops_an_overflowing_subscriber() -> None:
    hub = Hub()

    async def run() -> tuple[list[dict], bool, list[dict], bool]:  # type: ignore[type-arg]
        mine = hub.subscribe_fleet(7, ["N1"], ["status_changed"], maxsize=3)
        small = hub.subscribe_fleet(7, None, ["applied"], maxsize=2)
        ev = {"_operator_id": 7, "tail": "N1", "type": "status_changed"}
        batch = [
            ev,
            {**ev, "tail": "N2"},  # other tail
            {**ev, "_operator_id": 8},  # other operator
            {**ev, "type": "applied"},
            {**ev, "type": "applied"},
            {**ev, "type": "applied"},  # third one overflows `small`
        ]
        # Published from another thread, as the processor does; publishing never blocks.
        t = threading.Thread(target=hub.publish_fleet, args=(batch,))
        t.start()
        t.join()
        await asyncio.sleep(0.05)
        got_mine = [mine.queue.get_nowait() for _ in range(mine.queue.qsize())]
        got_small = [small.queue.get_nowait() for _ in range(small.queue.qsize())]
        hub.unsubscribe(mine)
        hub.unsubscribe(small)
        return got_mine, mine.overflowed, got_small, small.overflowed

    got_mine, mine_over, got_small, small_over = asyncio.run(run())
    assert got_mine == [{"_operator_id": 7, "tail": "N1", "type": "status_changed"}]
    assert not mine_over
    assert len(got_small) == 2 and small_over
    assert not hub.has_fleet_subscribers()


def test_frames_parse_in_both_encodings_to_the_same_batch() -> None:
    t = np.arange(5) * 0.01 + 3.0
    chans = {"current": np.array([1.0, np.nan, 2.0, 3.0, 4.0]), "voltage": np.arange(5.0)}
    seq_j, bj = parse_frame(encode_frame(12, chans, t_s=t), ["current", "voltage"], 100)
    seq_a, ba = parse_frame(encode_frame(12, chans, t_s=t, binary=True), ["current", "voltage"], 100)
    seq_r, br = parse_frame(encode_frame(12, chans, t0=3.0, sample_rate_hz=100.0, binary=True),
                            ["current", "voltage"], 100)
    assert seq_j == seq_a == seq_r == 12
    assert bj.batch_id == ba.batch_id == frame_batch_id(12) and client_seq_of(bj.batch_id) == 12
    assert bj.content_hash() == ba.content_hash() == br.content_hash()


@pytest.mark.parametrize(
    ("frame", "error", "match"),
    [
        ('{"type": "hello"}', UnsupportedFrame, "unexpected message type"),
        ('{"type": "samples", "client_seq": true, "t": [0], "channels": {"a": [1]}}', InvalidBatch, "client_seq"),
        ('{"type": "samples", "client_seq": 1, "batch_id": "x", "t": [0], "channels": {"a": [1]}}', InvalidBatch,
         "not batch_id"),
        ('[1, 2]', InvalidBatch, "JSON object"),
        (b"\x00\x01", InvalidBatch, "Arrow"),
    ],
)
def test_bad_frames_are_refused_with_a_reason(frame: str | bytes, error: type, match: str) -> None:
    with pytest.raises(error, match=match):
        parse_frame(frame, ["a"], 100)


def test_rest_batch_ids_cannot_take_the_frame_prefix(api) -> None:  # type: ignore[no-untyped-def]
    api.setup_actuator()
    r = api.send_json("N1", "ema1", "ws-1", np.arange(3.0), {"current": np.ones(3), "voltage": np.ones(3)})
    assert r.status_code == 400 and "reserved" in r.json()["detail"]


def test_a_wake_only_subscription_is_woken_by_its_operators_logged_events_only() -> None:
    hub = Hub()

    async def run() -> list[tuple[bool, int]]:
        sub = hub.subscribe_fleet_wakeup(7)
        out = []
        for ev in (
            {"_operator_id": 8, "type": "status_changed", "tail": "N1"},  # another operator
            {"_operator_id": 7, "type": "applied", "tail": "N1"},  # live only, not logged
            {"_operator_id": 7, "type": "fault_detected", "tail": "N1"},
        ):
            sub.wakeup.clear()
            t = threading.Thread(target=hub.publish_fleet, args=([ev],))
            t.start()
            t.join()
            await asyncio.sleep(0.05)
            out.append((sub.wakeup.is_set(), sub.queue.qsize()))
        hub.unsubscribe(sub)
        return out

    assert asyncio.run(run()) == [(False, 0), (False, 0), (True, 0)]


def test_an_inbox_wakes_its_loop_once_per_burst_and_runs_every_call_in_order() -> None:
    loop = asyncio.new_event_loop()
    try:
        wakeups = []
        real = loop.call_soon_threadsafe

        def counting(*args):  # type: ignore[no-untyped-def]
            wakeups.append(args)
            return real(*args)

        loop.call_soon_threadsafe = counting  # type: ignore[method-assign]
        box = Inbox(loop)
        ran: list[int] = []

        def burst(first: int) -> None:
            for k in range(first, first + 100):
                box.put(ran.append, k)

        # A burst from another thread while the loop runs nothing: one wake-up for all of it.
        t = threading.Thread(target=burst, args=(0,))
        t.start()
        t.join()
        assert len(wakeups) == 1
        loop.run_until_complete(asyncio.sleep(0))
        assert ran == list(range(100))
        # Once run, the next burst schedules a new run.
        burst(100)
        loop.run_until_complete(asyncio.sleep(0))
        assert len(wakeups) == 2 and ran == list(range(200))
    finally:
        loop.close()
    # A closed loop (its subscribers are gone) takes calls without raising, and drops them.
    box.put(ran.append, -1)
    assert ran == list(range(200))


def test_a_failing_call_does_not_lose_the_rest_of_its_burst() -> None:
    async def run() -> list[int]:
        box = inbox(asyncio.get_running_loop())
        assert inbox(asyncio.get_running_loop()) is box  # one per loop
        ran: list[int] = []
        done = asyncio.Event()
        box.put(ran.append, 1)
        box.put(lambda: 1 / 0)
        box.put(ran.append, 2)
        box.put(done.set)
        await asyncio.wait_for(done.wait(), 30)
        return ran

    assert asyncio.run(run()) == [1, 2]


def test_inbox_wrap_hands_over_results_and_errors_of_other_threads_futures() -> None:
    async def run() -> tuple[int, str, bool]:
        box = inbox(asyncio.get_running_loop())
        ok: Future[int] = Future()
        bad: Future[int] = Future()
        left: Future[int] = Future()
        got_ok, got_bad, got_left = box.wrap(ok), box.wrap(bad), box.wrap(left)
        got_left.cancel()  # its awaiter went away: the thread's future is left alone
        t = threading.Thread(target=lambda: (ok.set_result(7), bad.set_exception(InvalidBatch("no")),
                                             left.set_result(1)))
        t.start()
        t.join()
        value = await asyncio.wait_for(got_ok, 30)
        with pytest.raises(InvalidBatch) as err:
            await asyncio.wait_for(got_bad, 30)
        await asyncio.sleep(0)
        return value, err.value.detail, left.result() == 1 and got_left.cancelled()

    assert asyncio.run(run()) == (7, "no", True)
