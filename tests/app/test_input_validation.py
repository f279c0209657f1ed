"""Input validation at the edge: huge integers and magnitudes, out-of-window times and control
characters are refused with 400/422 (WebSocket 1007/1008) on every backend, never stored."""

from __future__ import annotations

import time
from collections.abc import Iterator
from typing import Any

import numpy as np
import orjson
import pyarrow as pa
import pytest
from fastapi.testclient import TestClient
from starlette.websockets import WebSocketDisconnect

from app.errors import InvalidBatch
from app.ingest import ParsedBatch
from app.main import create_app
from app.telemetry.validation import BatchLimits, check_batch
from tests.app.conftest import Api, make_settings

URL = "/v1/aircraft/N1/actuators/ema1/telemetry"
STREAM = "/v1/aircraft/N1/actuators/ema1/stream"


@pytest.fixture
def api(db_url: str) -> Iterator[Api]:
    with TestClient(create_app(make_settings(db_url, processor_enabled=False))) as client:
        a = Api(client)
        a.setup_actuator()
        yield a


def _json(api: Api, doc: dict[str, Any], raw: bytes | None = None) -> Any:
    return api.post(URL, content=raw if raw is not None else orjson.dumps(doc),
                    headers={"content-type": "application/json"})


def _arrow(api: Api, table: pa.Table, batch_id: str = "a1") -> Any:
    sink = pa.BufferOutputStream()
    with pa.ipc.new_stream(sink, table.schema) as w:
        w.write_table(table)
    return api.post(f"{URL}?batch_id={batch_id}", content=sink.getvalue().to_pybytes(),
                    headers={"content-type": "application/vnd.apache.arrow.stream"})


def _logged(api: Api) -> int:
    return int(api.health()["last_logged_seq"])


def _ok_then_nothing_logged(api: Api, r: Any, status: int, needle: str) -> None:
    assert r.status_code == status, r.text
    body = r.json()
    assert body["error"] in ("InvalidBatch", "ValidationError"), body
    assert needle in body["detail"], body
    assert _logged(api) == 0


# ----------------------------------------------------------------------------- integers, magnitudes
def test_json_integer_above_2_53_refused(api: Api) -> None:
    raw = b'{"batch_id":"b1","t":[0,1],"channels":{"current":[9007199254740993,1],"voltage":[1,2]}}'
    _ok_then_nothing_logged(api, _json(api, {}, raw), 400, "2**53")


def test_json_integer_beyond_64_bits_refused(api: Api) -> None:
    raw = b'{"batch_id":"b1","t":[0,1],"channels":{"current":[18446744073709551615,1],"voltage":[1,2]}}'
    r = _json(api, {}, raw)
    assert r.status_code == 400, r.text
    assert r.json()["error"] == "InvalidBatch"
    assert _logged(api) == 0


def test_json_huge_float_magnitude_refused(api: Api) -> None:
    doc = {"batch_id": "b1", "t": [0, 1], "channels": {"current": [1e300, 1], "voltage": [1, 2]}}
    _ok_then_nothing_logged(api, _json(api, doc), 400, "FLEETHEALTH_MAX_ABS_VALUE")


def test_csv_integer_above_2_53_refused(api: Api) -> None:
    body = b"t,current,voltage\n0,9007199254740993,1\n1,2,3\n"
    r = api.post(f"{URL}?batch_id=c1", content=body, headers={"content-type": "text/csv"})
    _ok_then_nothing_logged(api, r, 400, "2**53")


def test_arrow_uint64_max_refused(api: Api) -> None:
    table = pa.table({
        "t": pa.array([0.0, 1.0]),
        "current": pa.array([2**64 - 1, 1], type=pa.uint64()),
        "voltage": pa.array([1.0, 2.0]),
    })
    _ok_then_nothing_logged(api, _arrow(api, table), 400, "2**53")


def test_arrow_int64_time_above_2_53_refused(api: Api) -> None:
    table = pa.table({
        "t": pa.array([0, 2**62], type=pa.int64()),
        "current": pa.array([1.0, 2.0]),
        "voltage": pa.array([1.0, 2.0]),
    })
    r = _arrow(api, table)
    assert r.status_code == 400, r.text
    assert _logged(api) == 0


def test_exact_integers_and_normal_values_accepted(api: Api) -> None:
    raw = b'{"batch_id":"b1","t":[0,1],"channels":{"current":[123456789,-5],"voltage":[1,null]}}'
    r = _json(api, {}, raw)
    assert r.status_code == 202, r.text
    assert _logged(api) == 1


def test_ws_huge_integer_closes_1007(api: Api) -> None:
    with api.c.websocket_connect(STREAM, headers=api.h) as ws:
        assert ws.receive_json()["type"] == "ready"
        ws.send_text('{"type":"samples","client_seq":1,"t":[0,1],'
                     '"channels":{"current":[9007199254740993,1],"voltage":[1,2]}}')
        err = ws.receive_json()
        assert err["type"] == "error" and err["error"] == "InvalidBatch" and "2**53" in err["detail"]
        with pytest.raises(WebSocketDisconnect) as closed:
            ws.receive_json()
    assert closed.value.code == 1007
    assert _logged(api) == 0


def test_ws_arrow_uint64_max_closes_1007(api: Api) -> None:
    table = pa.table({
        "current": pa.array([2**64 - 1, 1], type=pa.uint64()),
        "voltage": pa.array([1.0, 2.0]),
    }).replace_schema_metadata({"client_seq": "1", "t0": "0", "sample_rate_hz": "10"})
    sink = pa.BufferOutputStream()
    with pa.ipc.new_stream(sink, table.schema) as w:
        w.write_table(table)
    with api.c.websocket_connect(STREAM, headers=api.h) as ws:
        assert ws.receive_json()["type"] == "ready"
        ws.send_bytes(sink.getvalue().to_pybytes())
        assert ws.receive_json()["error"] == "InvalidBatch"
        with pytest.raises(WebSocketDisconnect) as closed:
            ws.receive_json()
    assert closed.value.code == 1007


# ----------------------------------------------------------------------------- time window
def test_far_future_time_refused_and_stream_not_poisoned(api: Api) -> None:
    doc = {"batch_id": "b1", "t": [1e300, 2e300], "channels": {"current": [1, 2], "voltage": [1, 2]}}
    _ok_then_nothing_logged(api, _json(api, doc), 400, "FLEETHEALTH_MAX_TIME_S")
    ok = {"batch_id": "b2", "t": [0, 1], "channels": {"current": [1, 2], "voltage": [1, 2]}}
    assert _json(api, ok).status_code == 202
    assert _logged(api) == 1


@pytest.mark.parametrize(("scale", "unit"), [(1e3, "milliseconds"), (1e6, "microseconds"), (1e9, "nanoseconds")])
def test_epoch_in_wrong_unit_named(api: Api, scale: float, unit: str) -> None:
    now = time.time()
    doc = {"batch_id": "b1", "t": [now * scale, (now + 1) * scale],
           "channels": {"current": [1, 2], "voltage": [1, 2]}}
    _ok_then_nothing_logged(api, _json(api, doc), 400, unit)


def test_epoch_seconds_now_accepted_future_refused(api: Api) -> None:
    now = time.time()
    ahead = {"batch_id": "b1", "t": [now + 30 * 86400, now + 30 * 86400 + 1],
             "channels": {"current": [1, 2], "voltage": [1, 2]}}
    _ok_then_nothing_logged(api, _json(api, ahead), 400, "FLEETHEALTH_MAX_FUTURE_S")
    ok = {"batch_id": "b2", "t": [now - 10, now - 9], "channels": {"current": [1, 2], "voltage": [1, 2]}}
    assert _json(api, ok).status_code == 202
    assert _logged(api) == 1


def test_regular_time_with_tiny_rate_refused(api: Api) -> None:
    doc = {"batch_id": "b1", "t0": 0, "sample_rate_hz": 1e-300,
           "channels": {"current": [1, 2], "voltage": [1, 2]}}
    _ok_then_nothing_logged(api, _json(api, doc), 400, "FLEETHEALTH_MAX_TIME_S")


def test_ws_far_future_closes_1007(api: Api) -> None:
    with api.c.websocket_connect(STREAM, headers=api.h) as ws:
        assert ws.receive_json()["type"] == "ready"
        ws.send_json({"type": "samples", "client_seq": 1, "t": [1e300, 2e300],
                      "channels": {"current": [1, 2], "voltage": [1, 2]}})
        err = ws.receive_json()
        assert err["error"] == "InvalidBatch" and "FLEETHEALTH_MAX_TIME_S" in err["detail"]
        with pytest.raises(WebSocketDisconnect) as closed:
            ws.receive_json()
    assert closed.value.code == 1007
    assert _logged(api) == 0


def test_limits_are_settings(db_url: str) -> None:
    settings = make_settings(db_url, processor_enabled=False, max_time_s=100.0, max_abs_value=10.0)
    with TestClient(create_app(settings)) as client:
        a = Api(client)
        a.setup_actuator()
        late = {"batch_id": "b1", "t": [0, 101], "channels": {"current": [1, 2], "voltage": [1, 2]}}
        assert _json(a, late).status_code == 400
        big = {"batch_id": "b2", "t": [0, 1], "channels": {"current": [11, 2], "voltage": [1, 2]}}
        assert _json(a, big).status_code == 400
        ok = {"batch_id": "b3", "t": [0, 100], "channels": {"current": [10, -10], "voltage": [1, 2]}}
        assert _json(a, ok).status_code == 202


def test_check_batch_pure() -> None:
    b = ParsedBatch("x", np.array([0.0, 1.0]), {"c": np.array([np.nan, 5.0])})
    check_batch(b, BatchLimits(max_abs_value=5.0), now_s=2e9)
    with pytest.raises(InvalidBatch, match="index 1"):
        check_batch(b, BatchLimits(max_abs_value=4.0), now_s=2e9)
    epoch = ParsedBatch("x", np.array([2e9, 2e9 + 100]), {"c": np.array([1.0, 2.0])})
    check_batch(epoch, BatchLimits(max_future_s=100.0), now_s=2e9)
    with pytest.raises(InvalidBatch, match="t\\[1\\]"):
        check_batch(epoch, BatchLimits(max_future_s=99.0), now_s=2e9)


# ----------------------------------------------------------------------------- control characters
@pytest.mark.parametrize("path", [
    "/v1/aircraft/N%001/actuators/ema1/health",
    "/v1/aircraft/N1/actuators/ema%001/health",
    "/v1/aircraft/N%0A1",
])
def test_nul_in_path_422(api: Api, path: str) -> None:
    r = api.get(path)
    assert r.status_code == 422, r.text
    assert r.json()["error"] == "ValidationError"


def test_nul_in_query_batch_id_422(api: Api) -> None:
    r = api.post(f"{URL}?batch_id=a%00b", content=b"t,current,voltage\n0,1,2\n",
                 headers={"content-type": "text/csv"})
    assert r.status_code == 422, r.text
    assert _logged(api) == 0


def test_nul_in_json_batch_id_refused(api: Api) -> None:
    doc = {"batch_id": "a\x00b", "t": [0, 1], "channels": {"current": [1, 2], "voltage": [1, 2]}}
    _ok_then_nothing_logged(api, _json(api, doc), 400, "control characters")


def test_nul_in_idempotency_key_refused(api: Api) -> None:
    r = api.post(URL, content=b"t,current,voltage\n0,1,2\n",
                 headers={"content-type": "text/csv", "Idempotency-Key": "a\x01b"})
    assert r.status_code == 400, r.text
    assert _logged(api) == 0


@pytest.mark.parametrize(("path", "doc"), [
    ("/v1/aircraft", {"tail": "N\x002"}),
    ("/v1/aircraft", {"tail": "N2", "description": "a\x00b"}),
    ("/v1/aircraft/N1/actuators", {"actuator_id": "e\x00", "kind": "ema_voltage"}),
    ("/v1/aircraft/N1/actuators", {"actuator_id": "e2", "kind": "ema_voltage", "channels": ["cur\x00rent"]}),
    ("/v1/keys", {"name": "k\x00", "scopes": ["read"]}),
    ("/v1/keys", {"name": "k\x1b[31m", "scopes": ["read"]}),
])
def test_nul_in_body_identifiers_422(api: Api, path: str, doc: dict[str, Any]) -> None:
    r = api.post(path, json=doc)
    assert r.status_code == 422, r.text
    assert r.json()["error"] in ("ValidationError", "InvalidConfig")


def test_nul_in_channel_name_of_batch_refused(api: Api) -> None:
    doc = {"batch_id": "b1", "t": [0, 1], "channels": {"cur\x00rent": [1, 2], "voltage": [1, 2]}}
    r = _json(api, doc)
    assert r.status_code == 400, r.text
    assert _logged(api) == 0


def test_ws_nul_in_path_closes_1008(api: Api) -> None:
    path = "/v1/aircraft/N%001/actuators/ema1/stream"
    with pytest.raises(WebSocketDisconnect) as closed, api.c.websocket_connect(path, headers=api.h) as ws:
        ws.receive_json()
    assert closed.value.code == 1008
