"""The durable event log and alarms over the API, on SQLite and PostgreSQL: events logged in
the apply's transaction with ids per operator, read back after a cursor; alarms raised from
them, de-duplicated, acknowledged and cleared, counted on the list and the fleet board."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from app.auth.service import create_key
from tests.app.conftest import Api
from tests.conftest import make_series


def _flat(n: int = 800, t0: float = 0.0) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Constant current: the model cannot be identified, the status turns unknown."""
    return t0 + np.arange(n) * 0.001, {"current": np.ones(n), "voltage": np.ones(n)}


def _events(api: Api, after: int = 0, **params: Any) -> dict[str, Any]:
    r = api.get("/v1/events", params={"after": after, **params})
    assert r.status_code == 200, r.text
    return r.json()  # type: ignore[no-any-return]


def test_status_change_is_logged_and_raises_one_alarm_with_a_lifecycle(api: Api) -> None:
    api.setup_actuator("N1", "ema1")
    t, ch = _flat()
    assert api.send_json("N1", "ema1", "b1", t, ch).status_code in (200, 202)
    page = _events(api)
    types = [(e["id"], e["type"]) for e in page["items"]]
    assert types == [(1, "status_changed"), (2, "alarm_raised")]
    change, raised = page["items"]
    assert (change["tail"], change["actuator_id"], change["from"], change["to"]) == ("N1", "ema1", "learning", "unknown")
    assert change["seq"] == 1 and change["reasons"]
    assert raised["cause_event_id"] == 1 and raised["alarm"]["status"] == "active"
    assert page["next_after"] == 2 and page["last_event_id"] == 2 and not page["has_more"]

    alarms = api.get("/v1/alarms").json()
    assert len(alarms["items"]) == 1
    alarm = alarms["items"][0]
    assert (alarm["cause"], alarm["severity"], alarm["status"], alarm["raised_event_id"]) == ("status", "minor", "active", 1)
    assert alarms["counts"]["open"] == 1 and alarms["counts"]["open_by_severity"]["minor"] == 1
    board = api.get("/v1/fleet/health").json()["aircraft"][0]
    assert board["open_alarms"] == 1 and board["actuators"][0]["open_alarms"] == 1

    # Still unknown: the same cause does not raise a second alarm.
    t2, ch2 = _flat(t0=1.0)
    assert api.send_json("N1", "ema1", "b2", t2, ch2).status_code in (200, 202)
    assert len(api.get("/v1/alarms?status=open").json()["items"]) == 1

    aid = alarm["id"]
    r = api.post(f"/v1/alarms/{aid}/acknowledge", json={"comment": "looking at it", "by": "J. Doe"})
    assert r.status_code == 200, r.text
    acked = r.json()
    assert acked["status"] == "acknowledged" and acked["acknowledge_comment"] == "looking at it"
    assert acked["acknowledged_by"].startswith("J. Doe") and acked["acknowledged_at"] is not None
    assert api.post(f"/v1/alarms/{aid}/acknowledge").status_code == 409  # only an active one
    assert api.get("/v1/alarms?status=active").json()["items"] == []

    r = api.post(f"/v1/alarms/{aid}/clear", json={"comment": "sensor replaced"})
    assert r.status_code == 200, r.text
    cleared = r.json()
    assert cleared["status"] == "cleared" and cleared["clear_comment"] == "sensor replaced"
    assert api.post(f"/v1/alarms/{aid}/clear").status_code == 409
    assert api.get("/v1/fleet/health").json()["aircraft"][0]["open_alarms"] == 0

    tail = _events(api, after=2)["items"]
    assert [e["type"] for e in tail] == ["alarm_acknowledged", "alarm_cleared"]
    assert [e["id"] for e in tail] == [3, 4] and tail[1]["alarm"]["cleared_event_id"] == 4
    counts = api.get("/v1/alarms").json()["counts"]
    assert counts["status"] == {"active": 0, "acknowledged": 0, "cleared": 1} and counts["open"] == 0


def test_events_page_with_a_cursor_and_filters(api: Api) -> None:
    for tail in ("A1", "A2", "A3"):
        api.setup_actuator(tail, "ema1")
        t, ch = _flat()
        assert api.send_json(tail, "ema1", "b1", t, ch).status_code in (200, 202)
    seen: list[int] = []
    after = 0
    for _ in range(10):  # bounded
        page = _events(api, after=after, limit=2)
        seen += [e["id"] for e in page["items"]]
        after = page["next_after"]
        if not page["has_more"]:
            break
    assert seen == list(range(1, 7))
    only = _events(api, type="status_changed", tail="A2,A3")["items"]
    assert [(e["type"], e["tail"]) for e in only] == [("status_changed", "A2"), ("status_changed", "A3")]
    assert api.get("/v1/events?type=gossip").status_code == 422
    # Alarm filters.
    assert {a["tail"] for a in api.get("/v1/alarms?tail=A1").json()["items"]} == {"A1"}
    assert api.get("/v1/alarms?severity=critical").json()["items"] == []
    first = api.get("/v1/alarms?limit=2").json()
    rest = api.get(f"/v1/alarms?limit=2&before={first['next_before']}").json()
    assert [a["id"] for a in first["items"] + rest["items"]] == [3, 2, 1] and rest["next_before"] is None


def test_another_operator_sees_none_of_it(api: Api) -> None:
    api.setup_actuator("N1", "ema1")
    t, ch = _flat()
    assert api.send_json("N1", "ema1", "b1", t, ch).status_code in (200, 202)
    with api.app.state.db.write() as s:  # type: ignore[attr-defined]
        _, other = create_key(s, "other", ["read"])
    stranger = Api(api.c, other)
    assert stranger.get("/v1/events").json()["items"] == []
    assert stranger.get("/v1/alarms").json()["items"] == []
    aid = api.get("/v1/alarms").json()["items"][0]["id"]
    assert stranger.get(f"/v1/alarms/{aid}").status_code == 404
    assert stranger.post(f"/v1/alarms/{aid}/acknowledge").status_code == 404


def test_an_alarm_clears_itself_when_its_cause_ends(api: Api) -> None:
    api.setup_actuator("N1", "ema1")
    good = make_series(3000, seed=1)
    chans = {"current": good.current, "voltage": good.voltage}
    assert api.send_json("N1", "ema1", "good", good.t_s, chans).status_code in (200, 202)
    t, ch = _flat(t0=float(good.t_s[-1]) + 0.001)
    assert api.send_json("N1", "ema1", "flat", t, ch).status_code in (200, 202)
    assert api.health()["status"] == "alert"
    again = make_series(3000, seed=2, t0=float(t[-1]) + 0.001)
    chans = {"current": again.current, "voltage": again.voltage}
    assert api.send_json("N1", "ema1", "again", again.t_s, chans).status_code in (200, 202)
    assert api.health()["status"] == "ok"
    log = _events(api)["items"]
    assert [(e["type"], e.get("to")) for e in log] == [
        ("status_changed", "ok"),
        ("status_changed", "alert"),
        ("alarm_raised", None),
        ("status_changed", "ok"),
        ("alarm_cleared", None),
    ]
    assert log[4]["cause_event_id"] == log[3]["id"]
    (alarm,) = api.get("/v1/alarms").json()["items"]
    assert (alarm["status"], alarm["severity"], alarm["cleared_by"]) == ("cleared", "major", "rule")
    assert alarm["raised_event_id"] == log[1]["id"] and alarm["cleared_event_id"] == log[4]["id"]
    assert alarm["clear_comment"] == "status back to ok"


def test_events_commit_with_the_apply_or_not_at_all(api_noproc: Api, monkeypatch: Any) -> None:
    from app.alarms import service as alarms_service
    from app.fleet import service as fleet
    from app.processing import service as processing

    api = api_noproc
    api.setup_actuator("N1", "ema1")
    t, ch = _flat()
    assert api.send_json("N1", "ema1", "b1", t, ch, wait=0).status_code == 202
    db = api.app.state.db  # type: ignore[attr-defined]

    def apply() -> Any:
        with db.write() as s:
            pk = fleet.get_actuator(s, 1, "N1", "ema1").id
            return processing.apply_pending(s, pk, max_samples=10**6, store_outputs=True, is_sqlite=db.is_sqlite)

    def broken(*args: Any, **kwargs: Any) -> Any:
        raise RuntimeError("the alarm step failed")

    with monkeypatch.context() as m:
        m.setattr(alarms_service, "log_with_alarms", broken)
        with pytest.raises(RuntimeError, match="alarm step"):
            apply()
    assert api.health()["last_applied_seq"] == 0  # the apply rolled back with its events
    assert _events(api)["items"] == []
    assert apply() is not None
    assert api.health()["last_applied_seq"] == 1
    assert [e["type"] for e in _events(api)["items"]] == ["status_changed", "alarm_raised"]


def test_a_surface_fault_raises_an_alarm_that_clears_with_the_fault(api: Api) -> None:
    import orjson

    from estimators.simulators.uav_closed_loop import SurfaceFault, simulate_flight

    api.post("/v1/aircraft", json={"tail": "UAV1"})
    r = api.post("/v1/aircraft/UAV1/actuators", json={"actuator_id": "fcu", "kind": "flight_controls"})
    assert r.status_code == 201, r.text
    fault = SurfaceFault("elevator_left", 20.0, 35.0, "stuck", position_deg=6.0)
    t, chans, _ = simulate_flight(60.0, faults=(fault,), seed=11)

    def send(lo: float, hi: float) -> None:
        for k, start in enumerate(np.arange(lo, hi, 5.0)):
            part = (t >= start) & (t < start + 5.0)
            body = {"batch_id": f"b{lo:.0f}-{k}", "t": t[part].tolist(),
                    "channels": {c: v[part].tolist() for c, v in chans.items()}}
            r = api.post("/v1/aircraft/UAV1/actuators/fcu/telemetry?wait=60", content=orjson.dumps(body),
                         headers={"content-type": "application/json"})
            assert r.status_code == 202, r.text

    send(0.0, 30.0)  # into the fault
    open_ = api.get("/v1/alarms?status=open&cause=fault").json()
    (alarm,) = open_["items"]
    assert (alarm["subject"], alarm["severity"], alarm["estimator"]) == ("elevator_left", "major", "stmmae")
    raised = next(e for e in _events(api, limit=1000)["items"] if e["id"] == alarm["raised_event_id"])
    assert raised["type"] == "fault_detected" and raised["detail"]["component"] == "elevator_left"
    board = next(a for a in api.get("/v1/fleet/health").json()["aircraft"] if a["tail"] == "UAV1")
    assert board["open_alarms"] == api.get("/v1/alarms?status=open&tail=UAV1").json()["counts"]["open"] >= 1

    send(30.0, 60.0)  # the surface works again from 35 s
    after = api.get(f"/v1/alarms/{alarm['id']}").json()
    assert (after["status"], after["cleared_by"]) == ("cleared", "rule")
    cleared = next(e for e in _events(api, limit=1000)["items"] if e["id"] == after["cleared_event_id"])
    assert cleared["type"] == "alarm_cleared" and cleared["alarm"]["subject"] == "elevator_left"
    assert api.get("/v1/alarms?status=open&cause=fault").json()["items"] == []


def test_a_split_surface_group_alarm_is_handed_to_the_half(api: Api) -> None:
    """The right aileron stuck at +12 deg: the bank first detects "one of the two ailerons";
    through the service the group opens a fault and a major alarm, and when the right half is
    isolated the group's fault and alarm close ("isolated as aileron_right") while the half's
    stay open."""
    import orjson

    from estimators.simulators.uav_closed_loop import SurfaceFault, simulate_flight

    api.post("/v1/aircraft", json={"tail": "UAV2"})
    r = api.post("/v1/aircraft/UAV2/actuators", json={"actuator_id": "fcu", "kind": "flight_controls"})
    assert r.status_code == 201, r.text
    fault = SurfaceFault("aileron_right", 8.0, 20.0, "stuck", position_deg=12.0)
    t, chans, _ = simulate_flight(15.0, faults=(fault,), seed=11)
    body = {"batch_id": "all", "t": t.tolist(), "channels": {c: v.tolist() for c, v in chans.items()}}
    r = api.post("/v1/aircraft/UAV2/actuators/fcu/telemetry?wait=60", content=orjson.dumps(body),
                 headers={"content-type": "application/json"})
    assert r.status_code == 202, r.text
    faults = api.get("/v1/aircraft/UAV2/actuators/fcu/faults").json()
    kinds = [(e["kind"], e["detail"]["component"]) for e in faults["events"]]
    assert kinds[:3] == [
        ("fault_detected", "aileron"),
        ("fault_detected", "aileron_right"),
        ("fault_cleared", "aileron"),
    ]
    assert faults["events"][0]["detail"]["candidates"] == ["aileron_left", "aileron_right"]
    assert faults["events"][2]["detail"]["isolated_as"] == "aileron_right"
    assert [f["detail"]["component"] for f in faults["active_faults"]] == ["aileron_right"]
    alarms = api.get("/v1/alarms?cause=fault&tail=UAV2").json()["items"]
    by_subject = {a["subject"]: a for a in alarms}
    assert set(by_subject) == {"aileron", "aileron_right"}
    assert by_subject["aileron_right"]["status"] == "active"  # open, not acknowledged
    group = api.get(f"/v1/alarms/{by_subject['aileron']['id']}").json()
    assert (group["status"], group["cleared_by"]) == ("cleared", "rule")
    cleared = next(e for e in _events(api, limit=1000)["items"] if e["id"] == group["cleared_event_id"])
    assert cleared["type"] == "alarm_cleared" and "isolated as aileron_right" in str(cleared)


def test_fleet_subscribers_hear_of_an_acknowledgement_at_once(db_url: str) -> None:
    from fastapi.testclient import TestClient

    from app.main import create_app
    from tests.app.conftest import ADMIN_KEY, make_settings

    # A poll far beyond the test's time: only the wake-up after the commit can bring the event.
    with TestClient(create_app(make_settings(db_url, events_poll_s=600.0))) as client:
        api = Api(client)
        api.setup_actuator("N1", "ema1")
        t, ch = _flat()
        assert api.send_json("N1", "ema1", "b1", t, ch).status_code == 202
        aid = api.get("/v1/alarms").json()["items"][0]["id"]
        headers = {"Authorization": f"Bearer {ADMIN_KEY}"}
        with client.websocket_connect("/v1/fleet/events?types=alarm_acknowledged", headers=headers) as ws:
            assert ws.receive_json()["type"] == "ready"
            assert api.post(f"/v1/alarms/{aid}/acknowledge", json={"comment": "seen"}).status_code == 200
            ev = ws.receive_json()
        assert (ev["type"], ev["alarm"]["id"], ev["alarm"]["acknowledge_comment"]) == ("alarm_acknowledged", aid, "seen")
