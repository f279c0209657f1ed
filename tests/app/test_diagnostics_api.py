"""Fault isolation and remaining useful life through the service: estimators' diagnoses, fault
events, RUL prognoses stored with history, statuses and the fleet board."""

from __future__ import annotations

from typing import Any

import numpy as np
import orjson

from estimators.simulators.uav_closed_loop import SurfaceFault, simulate_flight


def _post(api: Any, tail: str, act: str, batch_id: str, t: np.ndarray, chans: dict[str, np.ndarray]) -> None:
    body = {"batch_id": batch_id, "t": t.tolist(), "channels": {k: v.tolist() for k, v in chans.items()}}
    r = api.post(
        f"/v1/aircraft/{tail}/actuators/{act}/telemetry?wait=60",
        content=orjson.dumps(body),
        headers={"content-type": "application/json"},
    )
    assert r.status_code == 202, r.text


def test_rul_is_stored_with_history_and_orders_the_fleet_board(api: Any) -> None:
    from estimators.simulators.friction_drive import simulate_friction_drive

    api.post("/v1/aircraft", json={"tail": "FD1"})
    cfg = {"deterioration_ekf": {"rul_every_s": 5.0, "health_window_samples": 5000, "rul_trajectories": 200}}
    for act in ("slow", "fast"):
        r = api.post("/v1/aircraft/FD1/actuators", json={"actuator_id": act, "kind": "friction_drive", "estimators": cfg})
        assert r.status_code == 201, r.text
    runs = {act: simulate_friction_drive(20.0, 1000.0, m=m, seed=2) for act, m in (("slow", 0.01), ("fast", 0.05))}
    for act, (t, chans, _truth) in runs.items():
        for k in range(4):
            sl = slice(k * 5000, (k + 1) * 5000)
            _post(api, "FD1", act, f"b{k}", t[sl], {c: v[sl] for c, v in chans.items()})

    rul = {act: api.get(f"/v1/aircraft/FD1/actuators/{act}/rul?order=asc").json() for act in runs}
    for act, body in rul.items():
        items = body["items"]
        # One prognosis per 5 s of stream time, stored with history.
        assert [round(i["t_s"]) for i in items] == [5, 10, 15], (act, [i["t_s"] for i in items])
        latest = body["latest"]["deterioration_ekf"]
        assert latest == items[-1]
        assert latest["threshold"] == 0.9 and latest["assumption"]
        # Early in life m is uncertain: slow-wear trajectories may not fail within the horizon
        # (then the upper quantile is null), but the lower ones are defined.
        assert latest["q05_s"] <= latest["q50_s"]
        assert latest["q95_s"] is None or latest["q50_s"] <= latest["q95_s"]
        assert latest["health"]["dn_lower"] <= latest["health"]["dn"] <= latest["health"]["dn_upper"]
        truth_dn = runs[act][2]["dn"][runs[act][0] <= latest["t_s"]][-1]
        assert abs(latest["health"]["dn"] - truth_dn) < 0.01
    # The faster wear has the shorter life, and the board sorted by RUL lists it first.
    assert rul["fast"]["latest"]["deterioration_ekf"]["q50_s"] < rul["slow"]["latest"]["deterioration_ekf"]["q50_s"]
    board = api.get("/v1/fleet/health?sort=rul").json()["aircraft"]
    fd1 = next(a for a in board if a["tail"] == "FD1")
    assert [a["actuator_id"] for a in fd1["actuators"]] == ["fast", "slow"]
    assert fd1["actuators"][0]["rul_q05_s"] == rul["fast"]["latest"]["deterioration_ekf"]["q05_s"]
    window = api.get("/v1/aircraft/FD1/actuators/fast/rul?from_s=9&to_s=16&order=asc").json()
    assert [round(i["t_s"]) for i in window["items"]] == [10, 15]


def test_surface_fault_is_served_by_faults_and_on_the_fleet_board(api: Any) -> None:
    api.post("/v1/aircraft", json={"tail": "UAV1"})
    r = api.post("/v1/aircraft/UAV1/actuators", json={"actuator_id": "fcu", "kind": "flight_controls"})
    assert r.status_code == 201, r.text
    fault = SurfaceFault("elevator_left", 20.0, 35.0, "stuck", position_deg=6.0)
    t, chans, _ = simulate_flight(60.0, faults=(fault,), seed=11)
    base = "/v1/aircraft/UAV1/actuators/fcu"

    def send(lo: float, hi: float) -> None:
        sel = (t >= lo) & (t < hi)
        for k, start in enumerate(np.arange(lo, hi, 5.0)):
            part = sel & (t >= start) & (t < start + 5.0)
            _post(api, "UAV1", "fcu", f"b{lo:.0f}-{k}", t[part], {c: v[part] for c, v in chans.items()})

    send(0.0, 30.0)  # into the fault
    faults = api.get(f"{base}/faults").json()
    assert faults["status"] == "alert"
    assert [f["detail"]["component"] for f in faults["active_faults"]] == ["elevator_left"]
    detected = faults["active_faults"][0]
    # Detected after the onset, within a few seconds (the estimator's own tests bound it tighter).
    assert 20.0 <= detected["detail"]["detected_s"] <= 23.0
    diag = faults["estimators"]["stmmae"]["diagnosis"]
    assert diag["probabilities"]["elevator_left"] > 0.9
    assert faults["estimators"]["stmmae"]["t_s"] == t[t < 30.0][-1]
    fleet = api.get("/v1/fleet/health").json()["aircraft"]
    fcu = next(a for ac in fleet if ac["tail"] == "UAV1" for a in ac["actuators"])
    assert fcu["status"] == "alert" and fcu["active_faults"] == ["elevator_left"]

    send(30.0, 60.0)  # the surface works again from 35 s
    faults = api.get(f"{base}/faults").json()
    assert faults["active_faults"] == []
    half = [e for e in faults["events"] if e["detail"]["component"] == "elevator_left"]
    assert [e["kind"] for e in half[:2]] == ["fault_detected", "fault_cleared"]
    assert half[1]["detail"]["cleared_s"] > 35.0
    # "one of the two elevators" was raised first and handed to the left half
    group = [e for e in faults["events"] if e["detail"]["component"] == "elevator"]
    assert [e["kind"] for e in group] == ["fault_detected", "fault_cleared"]
    assert group[1]["detail"]["isolated_as"] == "elevator_left"
    fleet = api.get("/v1/fleet/health").json()["aircraft"]
    fcu = next(a for ac in fleet if ac["tail"] == "UAV1" for a in ac["actuators"])
    assert fcu["active_faults"] == []
    assert api.get("/v1/aircraft/UAV1/actuators/nope/faults").status_code == 404


def test_sha_ema_residual_isolation_is_served_by_faults(api: Any) -> None:
    from app.ingest import TIME_COLUMN  # noqa: F401  (the Arrow body carries a t column)
    from estimators.simulators.sha_ema import PAPER_SCENARIO, simulate_sha_ema

    api.post("/v1/aircraft", json={"tail": "RA1"})
    r = api.post("/v1/aircraft/RA1/actuators", json={"actuator_id": "aileron", "kind": "sha_ema"})
    assert r.status_code == 201, r.text
    t, chans, _truth = simulate_sha_ema(7.0, faults=PAPER_SCENARIO, seed=4)
    step = 10_000  # 1 s of stream time per batch
    for k in range(0, len(t), step):
        r = api.send_arrow("RA1", "aileron", f"b{k}", t[k : k + step], {c: v[k : k + step] for c, v in chans.items()})
        assert r.status_code == 202, r.text
    faults = api.get("/v1/aircraft/RA1/actuators/aileron/faults").json()
    assert faults["status"] == "alert"
    diag = faults["estimators"]["darr_fekf"]["diagnosis"]
    # The seed paper's scenario (A_h and B_h drop at 4 s): residuals 6 and 7 only.
    assert diag["coherence_vector"] == [0, 0, 0, 0, 0, 1, 1]
    assert any(set(c) == {"a_h", "b_h"} for c in diag["candidates"]), diag["candidates"][:5]
    detected = [e for e in faults["events"] if e["kind"] == "fault_detected"]
    assert detected and 4.0 <= detected[0]["detail"]["detected_s"] < 5.0
    assert [f["detail"]["component"] for f in faults["active_faults"]] == [detected[-1]["detail"]["component"]]
    b_h = diag["parameters"]["b_h"]
    assert b_h["lower"] <= b_h["estimate"] <= b_h["upper"]
    board = api.get("/v1/fleet/health").json()["aircraft"]
    ra1 = next(a for a in board if a["tail"] == "RA1")
    assert ra1["status"] == "alert" and ra1["actuators"][0]["active_faults"]
