"""People's changes to an actuator's life as fleet events, on SQLite and PostgreSQL: maintenance
actions and config versions are logged in the change's own transaction (with the status change
of a restart, which the alarm rules see), read back from ``GET /v1/events`` and pushed to fleet
subscribers at once."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient

from app.main import create_app
from tests.app.conftest import ADMIN_KEY, Api, make_settings

A = "/v1/aircraft/N1/actuators/ema1"


def _flat(n: int = 800, t0: float = 0.0) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Constant current: the model cannot be identified, the status turns unknown."""
    return t0 + np.arange(n) * 0.001, {"current": np.ones(n), "voltage": np.ones(n)}


def _events(api: Api, after: int = 0, **params: Any) -> list[dict[str, Any]]:
    r = api.get("/v1/events", params={"after": after, "limit": 1000, **params})
    assert r.status_code == 200, r.text
    return r.json()["items"]  # type: ignore[no-any-return]


def _kinds(events: list[dict[str, Any]]) -> list[tuple[int, str]]:
    return [(e["id"], e["type"]) for e in events]


def test_maintenance_and_config_versions_are_logged_with_the_status_they_change(api: Api) -> None:
    api.setup_actuator()
    t, ch = _flat()
    assert api.send_json("N1", "ema1", "b1", t, ch).status_code == 202
    assert _kinds(_events(api)) == [(1, "status_changed"), (2, "alarm_raised")]

    r = api.c.patch(A, headers=api.h, json={"estimators": {"fakf": {"p0": 2.0}}, "comment": "wider p0"})
    assert r.status_code == 200, r.text
    (changed,) = _events(api, after=2)
    assert (changed["id"], changed["type"], changed["tail"], changed["actuator_id"]) == (3, "config_changed", "N1", "ema1")
    assert (changed["estimator"], changed["version"], changed["from_seq"], changed["state"], changed["comment"]) == (
        "fakf", 2, 2, "kept", "wider p0")
    assert changed["seq"] is None  # a person's action, not a batch

    r = api.post(f"{A}/maintenance", json={"action": "inspection", "performed_by": "J. Doe", "comment": "looks fine"})
    assert r.status_code == 201, r.text
    (inspection,) = _events(api, after=3)  # the status is untouched: nothing else is logged
    assert inspection["type"] == "maintenance_recorded" and inspection["maintenance_id"] == r.json()["id"]
    assert (inspection["action"], inspection["baseline"], inspection["from_seq"], inspection["status_before"]) == (
        "inspection", 1, None, "unknown")

    r = api.post(f"{A}/maintenance", json={"action": "replacement", "performed_by": "MRO",
                                           "performed_at": "2026-12-02T08:00:00Z"})
    assert r.status_code == 201, r.text
    replaced, status, cleared = _events(api, after=4)
    assert (replaced["id"], replaced["type"], replaced["action"], replaced["baseline"], replaced["from_seq"]) == (
        5, "maintenance_recorded", "replacement", 2, 2)
    assert replaced["performed_at"] == "2026-12-02T08:00:00Z" and replaced["performed_by"] == "MRO"
    # Nothing was pending: the estimators restarted at once, the status with them.
    assert (status["type"], status["from"], status["to"]) == ("status_changed", "unknown", "learning")
    assert any("new baseline 2" in reason for reason in status["reasons"])
    assert (cleared["type"], cleared["cause_event_id"], cleared["alarm"]["status"]) == ("alarm_cleared", 6, "cleared")
    assert api.get("/v1/alarms?status=open").json()["items"] == []

    t2, ch2 = _flat(t0=1.0)
    assert api.send_json("N1", "ema1", "b2", t2, ch2).status_code == 202
    assert _kinds(_events(api, after=7)) == [(8, "status_changed"), (9, "alarm_raised")]
    r = api.c.patch(A, headers=api.h, json={"estimators": {"fakf": {"p0": 3.0}}, "reset_state": True})
    assert r.status_code == 200, r.text
    reset, status, cleared = _events(api, after=9)
    assert (reset["type"], reset["version"], reset["state"], reset["from_seq"]) == ("config_changed", 3, "reset", 3)
    assert (status["type"], status["from"], status["to"]) == ("status_changed", "unknown", "learning")
    assert cleared["type"] == "alarm_cleared"
    # The types filter the log like any other.
    mine = _events(api, type="maintenance_recorded,config_changed")
    assert [e["id"] for e in mine] == [3, 4, 5, 10]


def test_a_refused_change_logs_nothing_and_a_failed_log_records_nothing(
    api_noproc: Api, monkeypatch: pytest.MonkeyPatch
) -> None:
    from app.alarms import service as alarms_service

    api = api_noproc
    api.setup_actuator()
    t, ch = _flat()
    assert api.send_json("N1", "ema1", "b1", t, ch, wait=0).status_code == 202
    r = api.post(f"{A}/maintenance", json={"action": "repair", "performed_by": "MRO"})
    assert r.status_code == 201, r.text
    # The restart waits for the pending batch: the status is not changed yet, nor logged.
    assert _kinds(_events(api)) == [(1, "maintenance_recorded")]
    assert _events(api)[0]["from_seq"] == 2
    r = api.post(f"{A}/maintenance", json={"action": "replacement", "performed_by": "MRO"})
    assert r.status_code == 409, r.text
    assert api.c.patch(A, headers=api.h, json={"estimators": {"fakf": {"p0": -1.0}}}).status_code == 422
    assert _kinds(_events(api)) == [(1, "maintenance_recorded")]

    def broken(*args: Any, **kwargs: Any) -> Any:
        raise RuntimeError("the event log failed")

    with monkeypatch.context() as m:
        m.setattr(alarms_service, "log_with_alarms", broken)
        with pytest.raises(RuntimeError, match="event log"):
            api.post(f"{A}/maintenance", json={"action": "inspection", "performed_by": "x"})
        with pytest.raises(RuntimeError, match="event log"):
            api.c.patch(A, headers=api.h, json={"estimators": {"fakf": {"p0": 2.0}}})
    # Both changes rolled back with their events.
    assert [m["action"] for m in api.get(f"{A}/maintenance").json()["items"]] == ["repair"]
    assert api.get(A).json()["config_versions"] == {"fakf": 1}
    assert _kinds(_events(api)) == [(1, "maintenance_recorded")]


def test_fleet_subscribers_hear_of_maintenance_and_config_changes_at_once(db_url: str) -> None:
    # A poll far beyond the test's time: only the wake-up after the commit can bring the events.
    with TestClient(create_app(make_settings(db_url, events_poll_s=600.0))) as client:
        api = Api(client)
        api.setup_actuator()
        headers = {"Authorization": f"Bearer {ADMIN_KEY}"}
        url = "/v1/fleet/events?types=maintenance_recorded,config_changed"
        with client.websocket_connect(url, headers=headers) as ws:
            assert ws.receive_json()["type"] == "ready"
            r = api.post(f"{A}/maintenance", json={"action": "inspection", "performed_by": "J. Doe"})
            assert r.status_code == 201, r.text
            first = ws.receive_json()
            assert api.c.patch(A, headers=api.h, json={"estimators": {"fakf": {"p0": 2.0}}}).status_code == 200
            second = ws.receive_json()
    assert (first["type"], first["action"], first["tail"], first["actuator_id"]) == (
        "maintenance_recorded", "inspection", "N1", "ema1")
    assert (second["type"], second["estimator"], second["version"]) == ("config_changed", "fakf", 2)
    assert second["id"] == first["id"] + 1
