"""The memory a batch request may hold: the process-wide budget (FLEETHEALTH_INGEST_MEMORY_BYTES)
and the body reader (spool past FLEETHEALTH_BODY_SPOOL_BYTES, no copies)."""

from __future__ import annotations

import threading

import numpy as np
import pytest
from fastapi.testclient import TestClient

from app.errors import IngestBusy, PayloadTooLarge
from app.ingest import ARROW_TYPES, JSON_TYPES, TimeParams, parse_body
from app.main import create_app
from app.telemetry.body import IngestMemory
from tests.app.conftest import Api, arrow_bytes, make_settings

TEL = "/v1/aircraft/N1/actuators/ema1/telemetry"
CHANNELS = ["current", "voltage"]


def _cols(n: int) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(7)
    return {"t": np.arange(n) * 1e-3, "current": rng.normal(size=n), "voltage": rng.normal(size=n)}


def test_the_budget_is_shared_waited_for_and_refuses_what_cannot_fit() -> None:
    budget = IngestMemory(1000, wait_s=0.05)
    assert budget.try_take(600)
    assert not budget.try_take(600)
    with pytest.raises(IngestBusy, match="INGEST_MEMORY_BYTES"):
        budget.take(600)  # waits 50 ms, nobody gives back
    with pytest.raises(PayloadTooLarge, match="INGEST_MEMORY_BYTES"):
        budget.take(1001)  # could never fit
    # A waiter gets its share as soon as another request gives its own back.
    got = threading.Event()
    waiter_budget = IngestMemory(1000, wait_s=30.0)
    waiter_budget.take(600)
    t = threading.Thread(target=lambda: (waiter_budget.take(600), got.set()))
    t.start()
    assert not got.wait(0.05)
    waiter_budget.give(600)
    t.join(10)
    assert got.is_set() and waiter_budget.held == 600 and waiter_budget.peak_held == 600


@pytest.mark.parametrize("mt", [JSON_TYPES[0], ARROW_TYPES[0]])
def test_decoders_reserve_their_memory_before_they_allocate(mt: str) -> None:
    import orjson

    cols = _cols(20_000)
    if mt == JSON_TYPES[0]:
        body = orjson.dumps({"batch_id": "b", "t": cols["t"], "channels": {c: cols[c] for c in CHANNELS}},
                            option=orjson.OPT_SERIALIZE_NUMPY)
    else:
        body = arrow_bytes(cols)
    reserved: list[int] = []
    parsed = parse_body(body, mt, TimeParams("b", None, None), CHANNELS, 100_000, reserve=reserved.append)
    # One reservation for the whole request (a request that waited holding part of its share
    # could wait on another doing the same), at least the decoded columns and their log encoding,
    # taken before decoding (a refusal stops it).
    assert len(reserved) == 1 and reserved[0] >= 2 * parsed.nbytes

    def refuse(n: int) -> None:
        raise IngestBusy("full")

    with pytest.raises(IngestBusy):
        parse_body(body, mt, TimeParams("b", None, None), CHANNELS, 100_000, reserve=refuse)


def test_a_batch_larger_than_the_process_budget_is_refused_and_a_small_one_passes(db_url: str) -> None:
    # 200,000 samples of t + 2 channels decode to 4.8 MB: more than a 4 MB budget can hold.
    settings = make_settings(db_url, ingest_memory_bytes=4_000_000, body_spool_bytes=1_000_000)
    with TestClient(create_app(settings)) as client:
        api = Api(client)
        api.setup_actuator()
        big = arrow_bytes(_cols(200_000))
        r = api.post(TEL + "?batch_id=big", content=big, headers={"content-type": ARROW_TYPES[0]})
        assert r.status_code == 413 and "INGEST_MEMORY_BYTES" in r.json()["detail"], r.text
        small = arrow_bytes(_cols(1000))
        r = api.post(TEL + "?batch_id=small", content=small, headers={"content-type": ARROW_TYPES[0]})
        assert r.status_code == 202, r.text
        # Every share was given back: the refused one too.
        assert client.app.state.ingest_memory.held == 0  # type: ignore[attr-defined]


def test_spooled_and_in_memory_bodies_log_the_same_samples(db_url: str) -> None:
    # The same batch under and over the spool threshold (JSON and Arrow) gives one digest:
    # the second post of each is an idempotent replay, not a conflict.
    settings = make_settings(db_url, body_spool_bytes=50_000)
    with TestClient(create_app(settings)) as client:
        api = Api(client)
        api.setup_actuator()
        import orjson

        cols = _cols(5000)
        js = orjson.dumps({"batch_id": "j", "t": cols["t"], "channels": {c: cols[c] for c in CHANNELS}},
                          option=orjson.OPT_SERIALIZE_NUMPY)
        assert len(js) > 50_000
        first = api.post(TEL, content=js, headers={"content-type": JSON_TYPES[0]})
        assert first.status_code == 202, first.text

        def chunks() -> object:
            for i in range(0, len(js), 4096):
                yield js[i:i + 4096]

        # Without Content-Length (chunked): grows in memory, then moves to the spool file.
        again = api.post(TEL, content=chunks(), headers={"content-type": JSON_TYPES[0]})
        assert again.status_code == 202 and again.headers.get("Idempotent-Replayed") == "true", again.text
        assert again.json()["seq"] == first.json()["seq"]
