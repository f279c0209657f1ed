"""Registration, authentication, tenancy, bad input and the read side of the API."""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import orjson
import pytest
from fastapi.testclient import TestClient
from sqlalchemy import select

from app.auth.service import create_key
from app.cli import openapi_document
from app.db import Database
from app.main import create_app
from app.models import ApiKey
from tests.app.conftest import ADMIN_KEY, Api, arrow_bytes, make_settings
from tests.conftest import make_series

ROOT = Path(__file__).resolve().parents[2]
TEL = "/v1/aircraft/N1/actuators/ema1/telemetry"


def _key(db_url: str, operator: str, scopes: list[str]) -> str:
    db = Database(db_url)
    with db.write() as s:
        _, key = create_key(s, operator, scopes)
    db.dispose()
    return key


def test_auth_required_and_keys_hashed(api: Api, db_url: str) -> None:
    assert api.c.get("/v1/aircraft").status_code == 401
    r = api.c.get("/v1/aircraft", headers={"Authorization": "Bearer nope"})
    assert r.status_code == 401 and r.json()["error"] == "Unauthorized"
    db = Database(db_url)
    with db.read() as s:
        stored = [k.key_hash for k in s.scalars(select(ApiKey))]
    db.dispose()
    assert stored and ADMIN_KEY not in stored and all(len(h) == 64 for h in stored)


def test_scopes(api: Api, db_url: str) -> None:
    api.setup_actuator()
    reader = Api(api.c, _key(db_url, "default", ["read"]))
    ingester = Api(api.c, _key(db_url, "default", ["ingest"]))
    s = make_series(10)
    assert reader.send_json("N1", "ema1", "x", s.t_s, {"current": s.current, "voltage": s.voltage}).status_code == 403
    assert reader.get("/v1/aircraft").status_code == 200
    assert ingester.get("/v1/aircraft").status_code == 403
    assert ingester.post("/v1/aircraft", json={"tail": "N2"}).status_code == 403
    r = ingester.send_json("N1", "ema1", "x", s.t_s, {"current": s.current, "voltage": s.voltage}, wait=0)
    assert r.status_code == 202


def test_other_operator_sees_nothing(api: Api, db_url: str) -> None:
    api.setup_actuator()
    other = Api(api.c, _key(db_url, "other-airline", ["read", "ingest", "admin"]))
    s = make_series(10)
    for path in ["/v1/aircraft/N1", "/v1/aircraft/N1/actuators", "/v1/aircraft/N1/actuators/ema1",
                 "/v1/aircraft/N1/actuators/ema1/health", "/v1/aircraft/N1/actuators/ema1/health/history",
                 "/v1/aircraft/N1/actuators/ema1/events"]:
        r = other.get(path)
        assert r.status_code == 404 and r.json()["error"] == "NotFound", path
    assert other.send_json("N1", "ema1", "x", s.t_s, {"current": s.current, "voltage": s.voltage}).status_code == 404
    assert other.get("/v1/aircraft").json() == {"items": [], "next_cursor": None}
    assert other.get("/v1/fleet/health").json() == {"aircraft": [], "next_cursor": None}
    # The other operator may use the same tail for its own aircraft.
    assert other.post("/v1/aircraft", json={"tail": "N1"}).status_code == 201
    assert api.health()["last_logged_seq"] == 0


def test_registration_errors(api: Api) -> None:
    assert api.post("/v1/aircraft", json={"tail": "N1"}).status_code == 201
    r = api.post("/v1/aircraft", json={"tail": "N1"})
    assert r.status_code == 409 and r.json()["error"] == "AlreadyExists"
    assert api.post("/v1/aircraft", json={"tail": "bad tail!"}).status_code == 422
    A = "/v1/aircraft/N1/actuators"
    r = api.post(A, json={"actuator_id": "a", "kind": "warp_drive"})
    assert r.status_code == 422 and "warp_drive" in r.json()["detail"]
    r = api.post(A, json={"actuator_id": "a", "kind": "ema_voltage", "estimators": {"fakf": {"q": -1}}})
    assert r.status_code == 422 and r.json()["error"] == "InvalidConfig" and "q" in r.json()["detail"]
    r = api.post(A, json={"actuator_id": "a", "kind": "ema_voltage", "estimators": {"fakf": {"no_such": 1}}})
    assert r.status_code == 422 and "no_such" in r.json()["detail"]
    r = api.post(A, json={"actuator_id": "a", "kind": "ema_voltage", "channels": ["current", "volts"]})
    assert r.status_code == 422 and "voltage" in r.json()["detail"]
    r = api.post(A, json={"actuator_id": "a", "kind": "ema_voltage", "estimators": {"nope": {}}})
    assert r.status_code == 422
    assert api.post("/v1/aircraft/NX/actuators", json={"actuator_id": "a", "kind": "ema_voltage"}).status_code == 404
    r = api.post(A, json={"actuator_id": "a", "kind": "ema_voltage",
                          "channels": ["i", "v"], "estimators": {"fakf": {"current_channel": "i", "voltage_channel": "v"}}})
    assert r.status_code == 201, r.text
    assert r.json()["estimators"]["fakf"]["current_channel"] == "i"
    assert api.post(A, json={"actuator_id": "a", "kind": "ema_voltage"}).status_code == 409
    assert api.get("/v1/aircraft/N1/actuators/zzz").status_code == 404


def _bad(api: Api, content: bytes, ctype: str = "application/json", query: str = "") -> dict:  # type: ignore[type-arg]
    before = api.health()["last_logged_seq"]
    r = api.post(TEL + query, content=content, headers={"content-type": ctype})
    assert 400 <= r.status_code < 500, r.text
    body = r.json()
    assert set(body) == {"error", "detail"} and body["detail"]
    assert api.health()["last_logged_seq"] == before  # nothing changed
    return {"status": r.status_code, **body}


def _json(**kw: object) -> bytes:
    base: dict[str, object] = {"batch_id": "b", "t": [0.0, 0.001, 0.002],
                               "channels": {"current": [1.0, 2.0, 3.0], "voltage": [1.0, None, 2.0]}}
    base.update(kw)
    return orjson.dumps({k: v for k, v in base.items() if v is not None})


def test_bad_input_is_refused_and_changes_nothing(api: Api) -> None:
    api.setup_actuator()
    ok = api.post(TEL, content=_json(), headers={"content-type": "application/json"})
    assert ok.status_code == 202
    ch = lambda c, v: {"current": c, "voltage": v}  # noqa: E731
    cases = [
        (_json(batch_id="b2", t=[1.0, 1.001, 1.002], channels=ch([1, 2, "x"], [1, 2, 3])), 400, "not a number"),
        (_json(batch_id="b2", t=[1.0, 1.001, 1.002], channels=ch([1, 2, True], [1, 2, 3])), 400, "current"),
        (b'{"batch_id":"b2","t":[1,2,3],"channels":{"current":[1,2,3],"voltage":[1,Infinity,3]}}', 400, "JSON"),
        (b'{"batch_id":"b2","t":[1,2,3],"channels":{"current":[1,2,3],"voltage":[1,1e999,3]}}', 400, "infinity"),
        (_json(batch_id="b2", t=[1.0, 1.001], channels=ch([1, 2, 3], [1, 2, 3])), 400, "samples"),
        (_json(batch_id="b2", t=[1.0, 1.001, 1.002], channels={**ch([1, 2, 3], [1, 2, 3]), "temp": [1, 2, 3]}), 400, "unknown channels: temp"),
        (_json(batch_id="b2", t=[1.0, 1.001, 1.002], channels={"current": [1, 2, 3]}), 400, "missing channels: voltage"),
        (_json(batch_id="b2", t=[1.0, 1.002, 1.001], channels=ch([1, 2, 3], [1, 2, 3])), 400, "increase"),
        (_json(batch_id="b2", t=[1.0, 1.0, 1.001], channels=ch([1, 2, 3], [1, 2, 3])), 400, "increase"),
        (_json(batch_id="b2", t=[0.001, 0.5, 1.0], channels=ch([1, 2, 3], [1, 2, 3])), 409, "StaleBatch"),
        (_json(batch_id="b2", t=[], channels=ch([], [])), 400, "empty"),
        (_json(batch_id=None), 400, "batch_id"),
        (_json(batch_id="b2", t=None, channels=ch([1, 2], [1, 2])), 400, "timestamps"),
        (_json(batch_id="b2", t=None, t0=5.0, sample_rate_hz=-1.0, channels=ch([1, 2], [1, 2])), 400, "sample_rate_hz"),
        (b"[1,2,3]", 400, "object"),
        (b"{not json", 400, "JSON"),
        (b"", 400, "empty"),
    ]
    for content, status, needle in cases:
        got = _bad(api, content)
        assert got["status"] == status, (content, got)
        assert needle in got["detail"] or needle == got["error"], (needle, got)
    got = _bad(api, b"t,current,voltage\n2,1,inf\n", "text/csv", "?batch_id=c1")
    assert got["status"] == 400 and "infinite" in got["detail"]
    got = _bad(api, b"t,current,voltage\n2,1,abc\n", "text/csv", "?batch_id=c1")
    assert got["status"] == 400 and "voltage" in got["detail"]
    got = _bad(api, b"current,voltage\n1,1\n", "text/csv", "?batch_id=c1")
    assert "timestamps" in got["detail"]
    got = _bad(api, b"not arrow at all", "application/vnd.apache.arrow.stream", "?batch_id=a1")
    assert "Arrow" in got["detail"]
    got = _bad(api, b"<xml/>", "application/xml")
    assert got["status"] == 415 and got["error"] == "UnsupportedMediaType"
    got = _bad(api, b"{}", "")
    assert got["status"] == 415
    r = api.post("/v1/aircraft/N1/actuators/nope/telemetry", content=_json(), headers={"content-type": "application/json"})
    assert r.status_code == 404
    r = api.post("/v1/aircraft/NOPE/actuators/ema1/telemetry", content=_json(), headers={"content-type": "application/json"})
    assert r.status_code == 404


def test_oversize_body_is_413(db_url: str) -> None:
    with TestClient(create_app(make_settings(db_url, max_body_bytes=10_000))) as client:
        api = Api(client)
        api.setup_actuator()
        s = make_series(2000)
        r = api.send_arrow("N1", "ema1", "big", s.t_s, {"current": s.current, "voltage": s.voltage})
        assert r.status_code == 413 and r.json()["error"] == "PayloadTooLarge"
        # Also when the client sends no Content-Length (chunked upload).
        body = arrow_bytes({"t": s.t_s, "current": s.current, "voltage": s.voltage})
        r = api.post(TEL + "?batch_id=big", content=iter([body[:5000], body[5000:]]),
                     headers={"content-type": "application/vnd.apache.arrow.stream"})
        assert r.status_code == 413
        assert api.health()["last_logged_seq"] == 0


def test_three_formats_give_the_same_outputs(api: Api) -> None:
    s = make_series(1000, seed=11)
    for act in ("j", "c", "a"):
        api.setup_actuator("N1", act)
    api.send_json("N1", "j", "b", s.t_s, {"current": s.current, "voltage": s.voltage})
    csv = "t,current,voltage\n" + "\n".join(
        f"{float(t)!r},{float(i)!r},{float(v)!r}" for t, i, v in zip(s.t_s, s.current, s.voltage, strict=True))
    r = api.post("/v1/aircraft/N1/actuators/c/telemetry?batch_id=b&wait=30", content=csv.encode(),
                 headers={"content-type": "text/csv; charset=utf-8"})
    assert r.status_code == 202, r.text
    api.send_arrow("N1", "a", "b", s.t_s, {"current": s.current, "voltage": s.voltage})
    outs = [api.outputs("N1", a)["series"]["voltage_estimate"] for a in ("j", "c", "a")]
    assert outs[0] == outs[1] == outs[2] and len(outs[0]) == 1000


def test_regular_time_from_t0_and_rate(api: Api) -> None:
    api.setup_actuator()
    body = {"batch_id": "r", "t0": 100.0, "sample_rate_hz": 1000.0,
            "channels": {"current": [1.0] * 5, "voltage": [2.0] * 5}}
    r = api.post(TEL, json=body)
    assert r.status_code == 202 and r.json()["t_first_s"] == 100.0
    assert r.json()["t_last_s"] == pytest.approx(100.004)
    r = api.post(TEL + "?batch_id=r2&t0=200&sample_rate_hz=100", content=b"current,voltage\n1,2\n1,2\n",
                 headers={"content-type": "text/csv"})
    assert r.status_code == 202 and r.json()["t_last_s"] == pytest.approx(200.01)


def test_fleet_overview_and_history_range(api: Api) -> None:
    api.setup_actuator("A1", "x")
    api.setup_actuator("B2", "y")
    s = make_series(1000, seed=12)
    api.send_arrow("B2", "y", "b", s.t_s, {"current": s.current, "voltage": s.voltage})
    fleet = api.get("/v1/fleet/health?sort=tail").json()["aircraft"]
    assert [a["tail"] for a in fleet] == ["A1", "B2"]
    assert fleet[1]["actuators"][0]["last_applied_seq"] == 1
    assert api.get("/v1/fleet/health?sort=updated").json()["aircraft"][0]["tail"] == "B2"
    assert api.get("/v1/fleet/health?sort=bogus").status_code == 422
    hist = api.get("/v1/aircraft/B2/actuators/y/health/history?from_s=0.3&to_s=0.6").json()["items"]
    assert hist and all(w["t_end_s"] >= 0.3 and w["t_start_s"] <= 0.6 for w in hist)
    assert len(hist) < len(api.history("B2", "y"))
    assert api.get("/v1/aircraft/B2/actuators/y/health/history?estimator=nope").status_code == 404
    ev = api.get("/v1/aircraft/B2/actuators/y/events").json()["items"]
    assert [e["kind"] for e in ev] == ["identified"]


def test_fleet_status_follows_worst_window(api: Api, db_url: str) -> None:
    """An actuator whose voltage stops following its current model turns alert on the board."""
    api.setup_actuator("OK1", "x")
    api.setup_actuator("BAD1", "x")
    s = make_series(2000, seed=13)
    api.send_arrow("OK1", "x", "b", s.t_s, {"current": s.current, "voltage": s.voltage})
    v = s.voltage.copy()
    v[1000:] = 0.3 * v[1000:] + 8.0 * np.sin(2 * np.pi * 11 * s.t_s[1000:])  # model broken after 1 s
    api.send_arrow("BAD1", "x", "b", s.t_s, {"current": s.current, "voltage": v})
    board = api.get("/v1/fleet/health").json()["aircraft"]
    assert [a["tail"] for a in board] == ["BAD1", "OK1"]
    assert board[0]["status"] == "alert" and board[1]["status"] == "ok"
    h = api.health("BAD1", "x")
    assert h["status"] == "alert" and h["estimators"]["fakf"]["reasons"]


def test_metrics_and_probes(api: Api) -> None:
    api.setup_actuator()
    s = make_series(300)
    api.send_arrow("N1", "ema1", "m", s.t_s, {"current": s.current, "voltage": s.voltage})
    assert api.c.get("/healthz").json() == {"status": "ok"}
    # Ready once every kind's kernels are (minutes on a cold numba cache: they compile).
    deadline = time.monotonic() + 280
    while (r := api.c.get("/readyz")).status_code == 503 and time.monotonic() < deadline:
        assert r.json()["checks"]["schema"] == "ok" and r.json()["checks"]["kernels"] != "ok"
        time.sleep(0.2)
    assert r.status_code == 200 and r.json()["checks"]["schema"] == "ok"
    assert {k["status"] for k in r.json()["kernels"].values()} == {"ready"}
    # Default FLEETHEALTH_METRICS_ACCESS=key: a key with the read scope is needed.
    assert api.c.get("/metrics").status_code == 401
    text = api.get("/metrics").text
    assert "fleethealth_batches_logged_total" in text and "fleethealth_samples_applied_total" in text


@pytest.mark.parametrize("access", ["off", "open"])
def test_metrics_access_setting(db_url: str, access: str) -> None:
    with TestClient(create_app(make_settings(db_url, metrics_access=access, warm_kernels=False))) as c:
        anonymous = c.get("/metrics")
        keyed = c.get("/metrics", headers={"Authorization": f"Bearer {ADMIN_KEY}"})
    if access == "off":
        assert anonymous.status_code == keyed.status_code == 404
        assert keyed.json()["error"] == "NotFound"
    else:
        assert anonymous.status_code == keyed.status_code == 200
        assert "fleethealth_batches_logged_total" in anonymous.text


def test_key_creation_endpoint(api: Api) -> None:
    r = api.post("/v1/keys", json={"scopes": ["read"], "name": "dashboard"})
    assert r.status_code == 201
    key = r.json()["key"]
    reader = Api(api.c, key)
    assert reader.get("/v1/aircraft").status_code == 200
    assert reader.post("/v1/keys", json={"scopes": ["admin"]}).status_code == 403


def test_openapi_file_is_current() -> None:
    committed = json.loads((ROOT / "openapi" / "openapi.json").read_text())
    assert committed == json.loads(json.dumps(openapi_document())), (
        "openapi/openapi.json is stale: run `fleethealth export-openapi`"
    )
