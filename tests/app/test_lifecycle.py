"""The actuator's life: estimator config versions, soft deletion and purge, maintenance
actions with baselines (a replacement resets RUL), on SQLite and PostgreSQL."""

from __future__ import annotations

import time
from typing import Any

import numpy as np
import orjson
import pytest
from fastapi.testclient import TestClient
from sqlalchemy import func, select

from app.db import Database
from app.main import create_app
from app.models import Actuator, Aircraft, HealthWindowRow, SampleOutputRow, TelemetryBatch
from app.processing import service as processing
from tests.app.conftest import FAKF_SMALL, Api, make_settings
from tests.conftest import make_series

A = "/v1/aircraft/N1/actuators/ema1"


def wait_applied(api: Api, path: str, seq: int, timeout_s: float = 300.0) -> None:
    """Until the stream has applied batch ``seq`` (a cold start compiles kernels first)."""
    deadline = time.monotonic() + timeout_s
    while api.get(f"{path}/health").json()["last_applied_seq"] < seq:
        assert time.monotonic() < deadline, f"batch {seq} of {path} not applied in {timeout_s} s"
        time.sleep(0.1)


def _send(api: Api, batch_id: str, lo: int, hi: int, n: int = 2000) -> None:
    s = make_series(n, seed=3)
    r = api.send_json("N1", "ema1", batch_id, s.t_s[lo:hi], {"current": s.current[lo:hi], "voltage": s.voltage[lo:hi]})
    assert r.status_code == 202, r.text
    wait_applied(api, A, r.json()["seq"])


def test_config_patch_makes_a_version_applied_from_the_next_batch(api: Api) -> None:
    api.setup_actuator()
    _send(api, "b1", 0, 1000)
    r = api.c.patch(A, headers=api.h, json={"estimators": {"fakf": {"thresholds": {"innovation_ratio_watch": 1.7}}},
                                            "comment": "tighter watch level"})
    assert r.status_code == 200, r.text
    body = r.json()
    assert body["actuator"]["config_versions"] == {"fakf": 2}
    fakf = body["actuator"]["estimators"]["fakf"]
    assert fakf["thresholds"]["innovation_ratio_watch"] == 1.7
    # Settings not named stay as they were (merged member by member, not replaced).
    assert fakf["health_window_samples"] == FAKF_SMALL["health_window_samples"]
    assert fakf["thresholds"]["innovation_ratio_alert"] == 2.0
    assert body["versions"] == [
        {**body["versions"][0], "estimator": "fakf", "version": 2, "from_seq": 2, "state": "kept",
         "comment": "tighter watch level"}
    ]
    _send(api, "b2", 1000, 2000)
    hist = api.history()
    assert {(w["seq"], w["config_version"]) for w in hist} == {(1, 1), (2, 2)}
    # The estimator carried its state over: the identified model is not re-identified.
    kinds = [e["kind"] for e in api.get(f"{A}/events?order=asc").json()["items"]]
    assert kinds == ["identified"], kinds
    versions = api.get(f"{A}/configs").json()["items"]
    assert [(v["version"], v["from_seq"]) for v in versions] == [(2, 2), (1, 1)]
    assert versions[1]["config"]["thresholds"]["innovation_ratio_watch"] == 1.5


def test_config_patch_errors(api: Api) -> None:
    api.setup_actuator()
    for body, code, err in [
        ({"estimators": {"fakf": {"health_window_samples": -3}}}, 422, "InvalidConfig"),
        ({"estimators": {"fakf": {"no_such_setting": 1}}}, 422, "InvalidConfig"),
        ({"estimators": {"stmmae": {}}}, 422, "InvalidConfig"),
        ({"estimators": {}}, 422, "InvalidConfig"),
        ({"estimators": {"fakf": {}}, "bogus": 1}, 422, "ValidationError"),
    ]:
        r = api.c.patch(A, headers=api.h, json=body)
        assert r.status_code == code and r.json()["error"] == err, (body, r.text)
    assert api.get(A).json()["config_versions"] == {"fakf": 1}


def test_a_config_change_of_the_state_layout_needs_a_reset(api: Api) -> None:
    from estimators.simulators.friction_drive import simulate_friction_drive

    api.post("/v1/aircraft", json={"tail": "FD"})
    cfg = {"deterioration_ekf": {"health_window_samples": 2000, "rul_every_s": 1.0, "rul_trajectories": 50}}
    assert api.post("/v1/aircraft/FD/actuators", json={"actuator_id": "d", "kind": "friction_drive",
                                                       "estimators": cfg}).status_code == 201
    t, chans, _ = simulate_friction_drive(2.0, 1000.0, m=0.01, seed=1)
    body = {"batch_id": "b1", "t": t.tolist(), "channels": {k: v.tolist() for k, v in chans.items()}}
    r = api.post("/v1/aircraft/FD/actuators/d/telemetry?wait=60", content=orjson.dumps(body),
                 headers={"content-type": "application/json"})
    assert r.status_code == 202, r.text
    wait_applied(api, "/v1/aircraft/FD/actuators/d", 1)
    change = {"deterioration_ekf": {"rul_load": {"kind": "observed", "bins": 7}}}
    r = api.c.patch("/v1/aircraft/FD/actuators/d", headers=api.h, json={"estimators": change})
    assert r.status_code == 422 and "reset_state" in r.json()["detail"], r.text
    r = api.c.patch("/v1/aircraft/FD/actuators/d", headers=api.h, json={"estimators": change, "reset_state": True})
    assert r.status_code == 200, r.text
    assert r.json()["versions"][0]["state"] == "reset"
    assert api.get("/v1/aircraft/FD/actuators/d/health").json()["estimators"]["deterioration_ekf"]["status"] == "learning"


def test_aircraft_patch_and_soft_delete(api: Api) -> None:
    api.setup_actuator()
    api.setup_actuator(act="ema2")
    r = api.c.patch("/v1/aircraft/N1", headers=api.h, json={"description": "A320 MSN 4711"})
    assert r.status_code == 200 and r.json()["description"] == "A320 MSN 4711"
    assert api.c.patch("/v1/aircraft/N1", headers=api.h, json={"tail": "N2"}).status_code == 422
    _send(api, "b1", 0, 500)

    r = api.c.delete(A, headers=api.h)
    assert r.status_code == 200, r.text
    assert r.json()["purge_after"] > r.json()["deleted_at"]
    for path in [A, f"{A}/health", f"{A}/rul", f"{A}/telemetry", f"{A}/outputs?estimator=fakf"]:
        r = api.get(path)
        assert r.status_code == 410 and r.json()["error"] == "Gone", (path, r.text)
    s = make_series(10, t0=100.0)
    r = api.send_json("N1", "ema1", "late", s.t_s, {"current": s.current, "voltage": s.voltage})
    assert r.status_code == 410 and "deleted" in r.json()["detail"]
    assert [a["actuator_id"] for a in api.get("/v1/aircraft/N1/actuators").json()["items"]] == ["ema2"]
    board = api.get("/v1/fleet/health").json()["aircraft"]
    assert [a["actuator_id"] for a in board[0]["actuators"]] == ["ema2"]
    r = api.post("/v1/aircraft/N1/actuators", json={"actuator_id": "ema1", "kind": "ema_voltage"})
    assert r.status_code == 409 and "deleted" in r.json()["detail"]

    assert api.c.delete("/v1/aircraft/N1", headers=api.h).status_code == 200
    assert api.get("/v1/aircraft/N1").status_code == 410
    assert api.get("/v1/aircraft/N1/actuators/ema2").status_code == 410
    assert api.get("/v1/aircraft").json()["items"] == []
    assert api.get("/v1/fleet/health").json()["aircraft"] == []


def _count(db: Database, model: Any, **where: Any) -> int:
    with db.read() as s:
        stmt = select(func.count()).select_from(model)
        for k, v in where.items():
            stmt = stmt.where(getattr(model, k) == v)
        return int(s.scalar(stmt) or 0)


def test_deleted_data_is_kept_then_purged(db_url: str) -> None:
    settings = make_settings(db_url, deleted_retention_s=1.0)
    with TestClient(create_app(settings)) as client:
        api = Api(client)
        api.setup_actuator()
        api.setup_actuator(tail="N2", act="keep")
        _send(api, "b1", 0, 500)
        db = Database(db_url)
        try:
            with db.read() as s:
                pk = s.scalar(select(Actuator.id).where(Actuator.actuator_id == "ema1"))
            assert _count(db, TelemetryBatch, actuator_pk=pk) == 1
            assert api.c.delete("/v1/aircraft/N1", headers=api.h).status_code == 200
            # Kept (hidden) right after the deletion ...
            assert _count(db, TelemetryBatch, actuator_pk=pk) == 1
            # ... and purged by the processor's periodic scan once the retention has passed.
            deadline = time.monotonic() + 60
            while _count(db, Aircraft, tail="N1") and time.monotonic() < deadline:
                time.sleep(0.2)
            assert _count(db, Aircraft, tail="N1") == 0
            for model in (Actuator, TelemetryBatch, HealthWindowRow, SampleOutputRow):
                field = "id" if model is Actuator else "actuator_pk"
                assert _count(db, model, **{field: pk}) == 0, model
            assert _count(db, Aircraft, tail="N2") == 1
            # The tail is free again.
            assert api.post("/v1/aircraft", json={"tail": "N1"}).status_code == 201
        finally:
            db.dispose()


def _post_fd(api: Api, batch_id: str, t: np.ndarray, chans: dict[str, np.ndarray], wait: float = 60) -> Any:
    body = {"batch_id": batch_id, "t": t.tolist(), "channels": {k: v.tolist() for k, v in chans.items()}}
    r = api.post(f"/v1/aircraft/FD/actuators/d/telemetry?wait={wait}", content=orjson.dumps(body),
                 headers={"content-type": "application/json"})
    assert r.status_code == 202, r.text
    wait_applied(api, "/v1/aircraft/FD/actuators/d", r.json()["seq"])
    return r.json()


def test_replacement_starts_a_new_baseline_and_rul_again(api: Api) -> None:
    from estimators.simulators.friction_drive import simulate_friction_drive

    api.post("/v1/aircraft", json={"tail": "FD"})
    cfg = {"deterioration_ekf": {"rul_every_s": 5.0, "health_window_samples": 5000, "rul_trajectories": 200}}
    assert api.post("/v1/aircraft/FD/actuators", json={"actuator_id": "d", "kind": "friction_drive",
                                                       "estimators": cfg}).status_code == 201
    # A fast-wearing part: past the failure threshold within 20 s.
    t, chans, _ = simulate_friction_drive(25.0, 1000.0, m=0.1, seed=2)
    for k in range(5):
        sl = slice(k * 5000, (k + 1) * 5000)
        _post_fd(api, f"old{k}", t[sl], {c: v[sl] for c, v in chans.items()})
    D = "/v1/aircraft/FD/actuators/d"
    assert api.get(f"{D}/health").json()["status"] == "failed"
    old_latest = api.get(f"{D}/rul").json()["latest"]["deterioration_ekf"]
    assert old_latest["q50_s"] == 0.0 and old_latest["baseline"] == 1
    assert old_latest["threshold_met"] is True and old_latest["event_state"] == 0.0

    r = api.post(f"{D}/maintenance", json={"action": "inspection", "performed_by": "J. Doe", "comment": "worn"})
    assert r.status_code == 201 and r.json()["baseline"] == 1 and r.json()["from_seq"] is None
    assert api.get(f"{D}/health").json()["status"] == "failed"  # an inspection changes nothing

    r = api.post(f"{D}/maintenance", json={"action": "replacement", "performed_by": "J. Doe",
                                           "performed_at": "2026-12-02T08:00:00Z", "comment": "new roller"})
    assert r.status_code == 201, r.text
    m = r.json()
    assert (m["baseline"], m["from_seq"], m["status_before"]) == (2, 6, "failed")
    health = api.get(f"{D}/health").json()
    assert health["status"] == "learning"  # failed is cleared; the new part has no model yet
    assert health["estimators"]["deterioration_ekf"]["baseline"] == 2
    assert api.get(f"{D}/rul").json()["latest"] == {}  # the old part's RUL is history
    assert api.get("/v1/fleet/health").json()["aircraft"][0]["actuators"][0]["rul_q05_s"] is None

    # The new part wears slowly; it is monitored from its own start.
    t2, chans2, _ = simulate_friction_drive(20.0, 1000.0, m=0.01, seed=5, t0_s=30.0)
    for k in range(4):
        sl = slice(k * 5000, (k + 1) * 5000)
        _post_fd(api, f"new{k}", t2[sl], {c: v[sl] for c, v in chans2.items()})
    body = api.get(f"{D}/rul?order=asc").json()
    new_latest = body["latest"]["deterioration_ekf"]
    assert new_latest["baseline"] == 2 and new_latest["q50_s"] > 5.0
    assert new_latest["threshold_met"] is False and new_latest["event_state"] > 0.5
    assert api.get(f"{D}/health").json()["status"] != "failed"
    # History before and after is kept, each labelled with its baseline.
    labels = [(round(i["t_s"]), i["baseline"]) for i in body["items"]]
    assert labels == [(5, 1), (10, 1), (15, 1), (20, 1), (35, 2), (40, 2), (45, 2)], labels
    acts = api.get(f"{D}/maintenance").json()["items"]
    assert [a["action"] for a in acts] == ["replacement", "inspection"]
    assert acts[0]["performed_at"].startswith("2026-12-02T08:00:00")
    bad = api.post(f"{D}/maintenance", json={"action": "overhaul", "performed_by": "x"})
    assert bad.status_code == 422
    naive = api.post(f"{D}/maintenance", json={"action": "repair", "performed_by": "x", "performed_at": "2026-12-02T08:00:00"})
    assert naive.status_code == 422


def _apply_all(db: Database) -> None:
    with db.read() as s:
        pks = list(s.scalars(select(Actuator.id)))
    for pk in pks:
        for _ in range(100):
            with db.write() as s:
                res = processing.apply_pending(s, pk, max_samples=10**6, store_outputs=True, is_sqlite=db.is_sqlite)
            if res is None:
                break


def test_a_replacement_with_batches_pending_applies_them_to_the_old_baseline(api_noproc: Api, db_url: str) -> None:
    api = api_noproc
    api.setup_actuator()
    api.setup_actuator(act="fresh")
    s = make_series(3000, seed=4)
    ch = {"current": s.current, "voltage": s.voltage}

    def send(act: str, bid: str, lo: int, hi: int) -> None:
        r = api.send_json("N1", act, bid, s.t_s[lo:hi], {k: v[lo:hi] for k, v in ch.items()}, wait=0)
        assert r.status_code == 202, r.text

    send("ema1", "b1", 0, 1000)
    send("ema1", "b2", 1000, 1500)
    r = api.post(f"{A}/maintenance", json={"action": "replacement", "performed_by": "MRO"})
    assert r.status_code == 201 and r.json()["from_seq"] == 3
    # A second restart cannot wait behind the first (it would drop the first's baseline).
    r = api.post(f"{A}/maintenance", json={"action": "repair", "performed_by": "MRO"})
    assert r.status_code == 409 and r.json()["error"] == "MaintenancePending", r.text
    assert api.post(f"{A}/maintenance", json={"action": "inspection", "performed_by": "MRO"}).status_code == 201
    send("ema1", "b3", 1500, 2200)
    send("ema1", "b4", 2200, 3000)
    # The same samples of the new part, fed to a new actuator from its start.
    send("fresh", "c1", 1500, 2200)
    send("fresh", "c2", 2200, 3000)
    db = Database(db_url)
    try:
        _apply_all(db)
    finally:
        db.dispose()
    hist = api.history()
    assert {(w["seq"], w["baseline"]) for w in hist} == {(1, 1), (2, 1), (3, 2), (4, 2)}
    new = [w for w in hist if w["baseline"] == 2]
    fresh = api.history("N1", "fresh")
    strip = ("seq", "baseline")
    assert [{k: v for k, v in w.items() if k not in strip} for w in new] == [
        {k: v for k, v in w.items() if k not in strip} for w in fresh
    ]
    out = api.outputs()
    fresh_out = api.outputs("N1", "fresh")
    k = np.searchsorted(np.asarray(out["t_s"]), s.t_s[1500])
    assert out["t_s"][k:] == fresh_out["t_s"]
    assert out["series"].keys() == fresh_out["series"].keys()
    assert all(v[k:] == fresh_out["series"][n] for n, v in out["series"].items())


def test_a_state_replay_after_a_replacement_recomputes_only_the_new_baseline(
    api: Api, monkeypatch: pytest.MonkeyPatch
) -> None:
    from estimators import fakf

    n = 500
    s = make_series(4 * n, seed=23)

    def send(act: str, k: int) -> None:
        sl = slice(n * k, n * (k + 1))
        r = api.send_arrow("N1", act, f"b{k}", s.t_s[sl], {"current": s.current[sl], "voltage": s.voltage[sl]})
        assert r.status_code == 202, r.text
        wait_applied(api, f"/v1/aircraft/N1/actuators/{act}", r.json()["seq"])

    api.setup_actuator("N1", "up")
    send("up", 0)
    send("up", 1)
    before = api.history("N1", "up")
    assert api.post("/v1/aircraft/N1/actuators/up/maintenance",
                    json={"action": "replacement", "performed_by": "MRO"}).json()["from_seq"] == 3
    send("up", 2)
    # An upgrade makes the stored state unreadable: the processor replays the new baseline.
    monkeypatch.setattr(fakf, "STATE_VERSION", fakf.STATE_VERSION + 1)
    send("up", 3)
    h = api.health("N1", "up")
    assert h["failure"] is None and h["last_applied_seq"] == 4
    hist = api.history("N1", "up")
    assert [w for w in hist if w["baseline"] == 1] == before  # the old part's history is untouched
    api.setup_actuator("N1", "fresh")
    for k in (2, 3):
        send("fresh", k)
    new = [w for w in hist if w["baseline"] == 2]
    fresh = api.history("N1", "fresh")
    assert len(new) == len(fresh) == 4
    for a, b in zip(new, fresh, strict=True):
        assert (a["t_start_s"], a["t_end_s"], a["status"]) == (b["t_start_s"], b["t_end_s"], b["status"])
        assert a["indicators"] == pytest.approx(b["indicators"], rel=1e-12, abs=1e-12)
