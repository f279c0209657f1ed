"""RUL in prognostics' words: event_state, time_of_event (absolute on an epoch clock), and
RUL in operating hours / cycles from a counter channel."""

from __future__ import annotations

from datetime import UTC, datetime

import numpy as np
import orjson
import pytest

from app.health import vocabulary
from tests.app.conftest import Api
from tests.app.test_lifecycle import wait_applied


def test_event_state_is_normalized_health() -> None:
    es = vocabulary.event_state("deterioration_ekf", {"dn": 0.45, "dn_lower": 0.4, "dn_upper": 0.5}, 0.9)
    assert es["event_state"] == pytest.approx(0.5)
    assert es["event_state_lower"] == pytest.approx(1 - 0.5 / 0.9)
    assert es["event_state_upper"] == pytest.approx(1 - 0.4 / 0.9)
    assert es["threshold_met"] is False
    assert vocabulary.event_state("deterioration_ekf", {"dn": 1.2, "dn_lower": None, "dn_upper": None}, 0.9) == {
        "event_state": 0.0, "event_state_lower": None, "event_state_upper": None, "threshold_met": True}
    assert vocabulary.event_state("deterioration_ekf", {"dn": -0.1}, 0.9)["event_state"] == 1.0
    assert vocabulary.event_state("fakf", {"x": 1.0}, 1.0)["event_state"] is None


def test_time_of_event_is_absolute_only_on_an_epoch_clock() -> None:
    epoch = vocabulary.time_of_event(1.7e9, {"q50_s": 3600.0, "q05_s": 60.0, "q95_s": None})
    assert epoch["time_basis"] == "epoch"
    assert epoch["time_of_event"] == datetime.fromtimestamp(1.7e9 + 3600.0, UTC)
    assert epoch["time_of_event_q05"] == datetime.fromtimestamp(1.7e9 + 60.0, UTC)
    assert epoch["time_of_event_q95"] is None and epoch["time_of_event_q95_t_s"] is None
    stream = vocabulary.time_of_event(100.0, {"q50_s": 50.0, "q05_s": 10.0, "q95_s": 90.0})
    assert stream["time_basis"] == "stream" and stream["time_of_event"] is None
    assert stream["time_of_event_t_s"] == 150.0 and stream["time_of_event_q95_t_s"] == 190.0


def test_usage_rate_and_conversion() -> None:
    assert vocabulary.usage_rate((0.0, 100.0), (3600.0, 101.0)) == pytest.approx(1 / 3600)
    assert vocabulary.usage_rate((0.0, 100.0), (3600.0, 100.0)) is None  # the counter did not move
    assert vocabulary.usage_rate(None, (1.0, 2.0)) is None
    assert vocabulary.usage_rate((5.0, 1.0), (5.0, 2.0)) is None
    assert vocabulary.rul_in_usage({"mean_s": 7200.0, "q05_s": None, "q50_s": 3600.0, "q95_s": 0.0}, 0.5 / 3600) == {
        "mean": 1.0, "q05": None, "q50": 0.5, "q95": 0.0}
    assert vocabulary.rul_in_usage({"mean_s": 1.0}, None) is None


def test_rul_on_an_epoch_clock_with_an_hours_counter(api: Api) -> None:
    from estimators.simulators.friction_drive import simulate_friction_drive

    t0 = 1.7e9
    api.post("/v1/aircraft", json={"tail": "FD"})
    cfg = {"deterioration_ekf": {"rul_every_s": 5.0, "health_window_samples": 5000, "rul_trajectories": 200}}
    r = api.post("/v1/aircraft/FD/actuators", json={
        "actuator_id": "d", "kind": "friction_drive", "estimators": cfg,
        "channels": ["current", "motor_speed", "wheel_speed", "operating_hours", "cycles"]})
    assert r.status_code == 201, r.text
    t, chans, _ = simulate_friction_drive(15.0, 1000.0, m=0.05, seed=2, t0_s=t0)
    # The hour meter runs at half the stream clock (the drive works half the time); one cycle
    # every 2 s.
    hours = 1234.0 + 0.5 * (t - t0) / 3600.0
    cycles = np.floor((t - t0) / 2.0)
    D = "/v1/aircraft/FD/actuators/d"
    for k in range(3):
        sl = slice(k * 5000, (k + 1) * 5000)
        body = {"batch_id": f"b{k}", "t": t[sl].tolist(),
                "channels": {**{c: v[sl].tolist() for c, v in chans.items()},
                             "operating_hours": hours[sl].tolist(), "cycles": cycles[sl].tolist()}}
        r = api.post(f"{D}/telemetry", content=orjson.dumps(body), headers={"content-type": "application/json"})
        assert r.status_code == 202, r.text
    wait_applied(api, D, 3)
    body = api.get(f"{D}/rul?order=asc").json()
    items = body["items"]
    assert [round(i["t_s"] - t0) for i in items] == [5, 10]
    for it in items:
        assert it["time_basis"] == "epoch"
        q50 = it["q50_s"]
        assert datetime.fromisoformat(it["time_of_event"]) == datetime.fromtimestamp(it["t_s"] + q50, UTC)
        assert it["event_state"] == pytest.approx(1 - it["health"]["dn"] / it["threshold"])
        assert it["event_state_lower"] <= it["event_state"] <= it["event_state_upper"]
        assert it["threshold_met"] is (it["health"]["dn"] >= it["threshold"])
        # Hours: RUL seconds x the meter's rate (0.5 h per 3600 s); cycles: 1 per 2 s (the
        # counter's rate is measured from its first sample to its last one before t_s).
        assert it["rul_operating_hours"]["q50"] == pytest.approx(q50 * 0.5 / 3600.0, rel=1e-9)
        dt = np.flatnonzero(t <= it["t_s"])[-1]
        rate = cycles[dt] / (t[dt] - t0)
        assert it["rul_cycles"]["q50"] == pytest.approx(q50 * rate, rel=1e-9)
    assert body["latest"]["deterioration_ekf"] == items[-1]
    # Health declines over life: event_state falls.
    assert items[1]["event_state"] < items[0]["event_state"]
    # Pages of prognoses with a cursor, newest first.
    first = api.get(f"{D}/rul?limit=1").json()
    assert first["items"][0]["t_s"] == items[-1]["t_s"] and first["truncated"]
    second = api.get(f"{D}/rul?limit=1&cursor={first['next_cursor']}").json()
    assert second["items"][0]["t_s"] == items[0]["t_s"] and second["next_cursor"] is None


def test_rul_on_a_stream_clock_has_no_absolute_time(api: Api) -> None:
    from estimators.simulators.friction_drive import simulate_friction_drive

    api.post("/v1/aircraft", json={"tail": "FD"})
    cfg = {"deterioration_ekf": {"rul_every_s": 5.0, "health_window_samples": 5000, "rul_trajectories": 100}}
    api.post("/v1/aircraft/FD/actuators", json={"actuator_id": "d", "kind": "friction_drive", "estimators": cfg})
    t, chans, _ = simulate_friction_drive(10.0, 1000.0, m=0.05, seed=2)
    for k in range(2):
        sl = slice(k * 5000, (k + 1) * 5000)
        body = {"batch_id": f"b{k}", "t": t[sl].tolist(), "channels": {c: v[sl].tolist() for c, v in chans.items()}}
        api.post("/v1/aircraft/FD/actuators/d/telemetry", content=orjson.dumps(body),
                 headers={"content-type": "application/json"})
    wait_applied(api, "/v1/aircraft/FD/actuators/d", 2)
    it = api.get("/v1/aircraft/FD/actuators/d/rul").json()["latest"]["deterioration_ekf"]
    assert it["time_basis"] == "stream" and it["time_of_event"] is None
    assert it["time_of_event_t_s"] == pytest.approx(it["t_s"] + it["q50_s"])
    assert it["rul_operating_hours"] is None and it["rul_cycles"] is None
