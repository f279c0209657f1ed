"""The lean path of a telemetry POST (:class:`app.telemetry.router.LeanIngest`) answers exactly
as the route does: each request here is sent once as the lean path takes it (no query string)
and once with ``?wait=0``, which the lean path leaves to the route; status, body and headers
must be the same. Requests the lean path must not take go to the route."""

from __future__ import annotations

from collections.abc import Iterator
from concurrent.futures import Future
from typing import Any

import orjson
import pytest
from fastapi.testclient import TestClient
from sqlalchemy.exc import OperationalError

from app.auth.service import create_key
from app.telemetry.router import LeanIngest
from tests.app.conftest import ADMIN_KEY, Api, make_settings

TEL = "/v1/aircraft/N1/actuators/ema1/telemetry"
JSON = {"content-type": "application/json"}
T0 = 1_700_000_000.0


@pytest.fixture
def taken(monkeypatch: pytest.MonkeyPatch) -> list[bool]:
    """One entry per telemetry POST that reached the lean path: whether it took it."""
    seen: list[bool] = []
    original = LeanIngest._take

    def spy(*args: Any) -> Any:
        got = original(*args)
        seen.append(got is not None)
        return got

    monkeypatch.setattr(LeanIngest, "_take", staticmethod(spy))
    return seen


def _api(db_url: str, **settings: Any) -> Iterator[Api]:
    with TestClient(create_app_for(db_url, **settings)) as client:
        api = Api(client)
        api.setup_actuator()
        # The route's first answer remembers the key and the actuator: the lean path may take
        # every later request.
        r = api.post(f"{TEL}?wait=0", content=_body("warm", T0), headers=JSON)
        assert r.status_code == 202, r.text
        yield api


def create_app_for(db_url: str, **settings: Any) -> Any:
    from app.main import create_app

    return create_app(make_settings(db_url, processor_enabled=False, **settings))


@pytest.fixture
def api(db_url: str) -> Iterator[Api]:
    yield from _api(db_url)


def _body(batch_id: str, t: float, **fields: Any) -> bytes:
    doc: dict[str, Any] = {"batch_id": batch_id, "t": [t], "channels": {"current": [0.3], "voltage": [-8.0]}}
    doc.update(fields)
    return orjson.dumps(doc)


def _answer(r: Any) -> tuple[int, Any, dict[str, str]]:
    headers = {k: v for k, v in r.headers.items() if k not in ("date",)}
    return r.status_code, r.json(), headers


def _both(api: Api, taken: list[bool], content: bytes, headers: dict[str, str] | None = None) -> Any:
    """The lean path's answer and the route's, asserted equal; the answer."""
    headers = headers or JSON
    taken.clear()
    lean = api.post(TEL, content=content, headers=headers)
    assert taken == [True], "the lean path did not take the request"
    route = api.post(f"{TEL}?wait=0", content=content, headers=headers)
    assert taken == [True], "the request with a query string reached the lean path's checks"
    assert _answer(lean) == _answer(route)
    return lean


@pytest.mark.parametrize(
    ("content", "error"),
    [
        (b"{not json", "InvalidBatch"),
        (b"", "InvalidBatch"),
        (b"[1, 2]", "InvalidBatch"),
        (_body("x1", T0 + 1, extra=1), "InvalidBatch"),
        (orjson.dumps({"t": [T0 + 1], "channels": {"current": [0.3], "voltage": [-8.0]}}), "InvalidBatch"),
        (orjson.dumps({"batch_id": "x2", "t": [T0 + 1], "channels": {"current": [0.3]}}), "InvalidBatch"),
        (orjson.dumps({"batch_id": "x3", "t": [T0 + 1], "channels": {"current": [0.3], "voltage": [-8.0],
                                                                     "other": [1.0]}}), "InvalidBatch"),
        (orjson.dumps({"batch_id": "x4", "t": [T0 + 1], "channels": {"current": [1e300], "voltage": [1.0]}}),
         "InvalidBatch"),
        (orjson.dumps({"batch_id": "x5", "t": [T0 + 1], "channels": {"current": [2**53 + 1], "voltage": [1]}}),
         "InvalidBatch"),
        (orjson.dumps({"batch_id": "x6", "t": [T0 + 1], "channels": {"current": [True], "voltage": [1.0]}}),
         "InvalidBatch"),
        (orjson.dumps({"batch_id": "x7", "t": [T0 + 1], "channels": {"current": ["1"], "voltage": [1.0]}}),
         "InvalidBatch"),
        (orjson.dumps({"batch_id": "x8", "t": [T0 + 1, T0 + 1], "channels": {"current": [1, 2],
                                                                           "voltage": [1, 2]}}), "InvalidBatch"),
        (_body("x9", 1e11), "InvalidBatch"),
        (_body("ws-7", T0 + 1), "InvalidBatch"),
        (_body("x10", T0 - 1), "StaleBatch"),
    ],
)
def test_refusals_are_the_routes(api: Api, taken: list[bool], content: bytes, error: str) -> None:
    status, body, headers = _answer(_both(api, taken, content))
    assert body["error"] == error, body
    assert status == (409 if error == "StaleBatch" else 400)
    assert headers["content-type"] == "application/json"


def test_appends_replays_and_conflicts_are_the_routes(api: Api, taken: list[bool]) -> None:
    taken.clear()
    lean = api.post(TEL, content=_body("a1", T0 + 1), headers=JSON)
    route = api.post(f"{TEL}?wait=0", content=_body("a2", T0 + 2), headers=JSON)
    assert taken == [True]
    assert lean.status_code == route.status_code == 202
    assert set(lean.headers) == set(route.headers)
    assert "idempotent-replayed" not in lean.headers
    first, second = lean.json(), route.json()
    assert set(first) == set(second)
    assert (first["batch_id"], first["seq"], first["n_samples"], first["t_first_s"]) == ("a1", 2, 1, T0 + 1)
    assert (second["batch_id"], second["seq"]) == ("a2", 3)
    # A retry of either answers its first acknowledgement, marked replayed, both ways.
    for batch_id, t, ack in (("a1", T0 + 1, first), ("a2", T0 + 2, second)):
        replay = _both(api, taken, _body(batch_id, t))
        assert replay.status_code == 202
        assert replay.headers["idempotent-replayed"] == "true"
        assert replay.json() == ack
    conflict = _both(api, taken, _body("a1", T0 + 1, end_of_run=True))
    assert conflict.status_code == 409 and conflict.json()["error"] == "IdempotencyConflict"


def test_csv_with_an_idempotency_key(api: Api, taken: list[bool]) -> None:
    taken.clear()
    csv = {"content-type": "text/csv"}
    r = api.post(TEL, content=f"t,current,voltage\n{T0 + 5},0.3,-8.0\n".encode(),
                 headers={**csv, "Idempotency-Key": "c1"})
    assert taken == [True]
    assert r.status_code == 202, r.text
    assert r.json()["batch_id"] == "c1"
    refused = _both(api, taken, b"t,current\n1,2,3\n", {**csv, "Idempotency-Key": "c2"})
    assert refused.status_code == 400


def test_requests_it_does_not_take_go_to_the_route(api: Api, taken: list[bool], db_url: str) -> None:
    body = _body("r1", T0 + 10)
    taken.clear()
    assert api.c.post(TEL, content=body, headers=JSON).status_code == 401  # no key
    assert api.c.post(TEL, content=body, headers={**JSON, "Authorization": "Basic abc"}).status_code == 401
    unknown = {**JSON, "Authorization": "Bearer fh_unknown-key-0123456789abcdef"}
    assert api.c.post(TEL, content=body, headers=unknown).status_code == 401
    with api.app.state.db.write() as s:
        _, read_key = create_key(s, "default", ["read"], name="reader")
    reader = {**JSON, "Authorization": f"Bearer {read_key}"}
    assert api.c.get("/v1/aircraft", headers=reader).status_code == 200  # remembered now
    assert api.c.post(TEL, content=body, headers=reader).status_code == 403
    assert api.post(TEL, content=body, headers={"content-type": "text/plain"}).status_code == 415
    big = orjson.dumps({"batch_id": "r2", "t": [T0 + 11 + k for k in range(2000)],
                        "channels": {"current": [0.5] * 2000, "voltage": [1.0] * 2000}})
    assert len(big) > 16 * 1024
    assert api.post(TEL, content=big, headers=JSON).status_code == 202
    later = _body("r5", T0 + 3000)
    chunked = api.post(TEL, content=iter([later[:10], later[10:]]), headers=JSON)
    assert chunked.status_code == 202, chunked.text
    # Not remembered yet: the route looks the actuator up (and remembers it).
    api.setup_actuator(act="ema2")
    other = TEL.replace("ema1", "ema2")
    assert api.post(other, content=_body("r3", T0), headers=JSON).status_code == 202
    assert taken == [False] * 8
    assert api.post(other, content=_body("r4", T0 + 1), headers=JSON).status_code == 202
    assert taken[-1] is True


def test_a_storage_fault_is_the_routes(api: Api, taken: list[bool], monkeypatch: pytest.MonkeyPatch) -> None:
    def failing(actuator_pk: int, batch: Any) -> Future[Any]:
        future: Future[Any] = Future()
        future.set_exception(OperationalError("INSERT", {}, Exception("database or disk is full")))
        return future

    monkeypatch.setattr(api.app.state.log_writer, "submit", failing)
    r = _both(api, taken, _body("s1", T0 + 1))
    assert r.status_code == 503
    assert r.json()["error"] == "StorageUnavailable"
    assert int(r.headers["retry-after"]) > 0


def test_the_memory_budget_is_the_routes(db_url: str, taken: list[bool]) -> None:
    for api in _api(db_url, ingest_memory_bytes=2000, ingest_memory_wait_s=0.0):
        ts = [T0 + 1 + k for k in range(30)]
        body = orjson.dumps({"batch_id": "m1", "t": ts, "channels": {"current": [0.5] * 30, "voltage": [1.0] * 30}})
        assert len(body) < 2000  # the body fits, its decoding does not
        r = _both(api, taken, body)
        assert r.status_code == 413 and r.json()["error"] == "PayloadTooLarge", r.text


def test_the_key_is_read_from_the_header_as_the_route_reads_it(api: Api, taken: list[bool]) -> None:
    taken.clear()
    spaced = {**JSON, "Authorization": f"bearer   {ADMIN_KEY}  "}
    r = api.c.post(TEL, content=_body("k1", T0 + 1), headers=spaced)
    assert taken == [True]
    assert r.status_code == 202, r.text
    assert api.c.post(f"{TEL}?wait=0", content=_body("k2", T0 + 2), headers=spaced).status_code == 202
