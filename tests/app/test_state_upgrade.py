"""A stream whose estimator state cannot be read: replayed from the log when it can be, else
failed with a reason that health, the fleet board, /metrics and ``?wait`` show; other apply
errors are retried a bounded number of times, then failed the same way."""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
import pytest
from fastapi.testclient import TestClient
from prometheus_client import REGISTRY
from sqlalchemy import select, update
from starlette.websockets import WebSocketDisconnect

from app import cli
from app.db import Database
from app.main import create_app
from app.models import Actuator, TelemetryBatch
from app.processing import repository
from estimators import fakf
from estimators.base import StateVersionError
from tests.app.conftest import Api, make_settings
from tests.conftest import make_series

N = 500  # samples per batch: two FAKF windows of 250


def _send(api: Api, act: str, k: int, s, wait: float = 30.0):  # type: ignore[no-untyped-def]
    sl = slice(N * k, N * (k + 1))
    return api.send_arrow("N1", act, f"b{k}", s.t_s[sl], {"current": s.current[sl], "voltage": s.voltage[sl]},
                          wait=wait)


def _bump_state_version(monkeypatch: pytest.MonkeyPatch) -> None:
    """As after an upgrade that changed FAKF's state layout: stored states are unreadable."""
    monkeypatch.setattr(fakf, "STATE_VERSION", fakf.STATE_VERSION + 1)


def _metric(name: str, **labels: str) -> float:
    return REGISTRY.get_sample_value(name, labels) or 0.0


def test_unreadable_state_is_replayed_from_the_log(api: Api, monkeypatch: pytest.MonkeyPatch) -> None:
    s = make_series(3 * N, seed=21)
    api.setup_actuator("N1", "upgraded")
    for k in range(2):
        assert _send(api, "upgraded", k, s).status_code == 202
    assert api.health("N1", "upgraded")["last_applied_seq"] == 2
    replays = _metric("fleethealth_state_replays_total")

    _bump_state_version(monkeypatch)
    r = _send(api, "upgraded", 2, s)
    assert r.status_code == 202, r.text
    h = api.health("N1", "upgraded")
    assert h["last_applied_seq"] == 3 and h["status"] != "failed" and h["failure"] is None
    assert _metric("fleethealth_state_replays_total") == replays + 1

    # The same samples through a stream that never had an old state: identical outputs, and
    # every window once (the replay replaced the old run's rows instead of adding to them).
    api.setup_actuator("N1", "fresh")
    for k in range(3):
        assert _send(api, "fresh", k, s).status_code == 202
    hu, hf = api.history("N1", "upgraded"), api.history("N1", "fresh")
    assert len(hu) == len(hf) == 6
    for a, b in zip(hu, hf, strict=True):
        assert (a["t_start_s"], a["t_end_s"], a["status"], a["seq"]) == (b["t_start_s"], b["t_end_s"], b["status"], b["seq"])
        assert a["indicators"] == pytest.approx(b["indicators"], rel=1e-12, abs=1e-12)
    ou, of = api.outputs("N1", "upgraded"), api.outputs("N1", "fresh")
    np.testing.assert_array_equal(ou["t_s"], s.t_s)
    for name, series in of["series"].items():
        np.testing.assert_array_equal(np.array(ou["series"][name], dtype=float), np.array(series, dtype=float))


def test_unreadable_state_without_the_log_fails_the_stream_visibly(
    api: Api, db_url: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    s = make_series(3 * N, seed=22)
    api.setup_actuator("N1", "ema1")
    api.setup_actuator("N1", "ok1")
    for k in range(2):
        assert _send(api, "ema1", k, s).status_code == 202
    assert _send(api, "ok1", 0, s).status_code == 202
    db = Database(db_url)
    with db.write() as session:  # retention dropped the first batch's samples
        ema1 = select(Actuator.id).where(Actuator.actuator_id == "ema1").scalar_subquery()
        session.execute(
            update(TelemetryBatch)
            .where(TelemetryBatch.actuator_pk == ema1, TelemetryBatch.seq == 1)
            .values(payload=None)
        )
    failures = _metric("fleethealth_stream_failures_total", cause="state_unreadable")

    _bump_state_version(monkeypatch)
    r = _send(api, "ema1", 2, s, wait=60.0)
    assert r.status_code == 409, r.text
    assert r.json()["error"] == "StreamFailed" and "seq 3" in r.json()["detail"]

    h = api.health("N1", "ema1")
    assert h["status"] == "failed" and h["last_applied_seq"] == 2
    assert "fakf" in h["failure"] and "no longer holds" in h["failure"]
    board = api.get("/v1/fleet/health").json()["aircraft"][0]
    assert board["status"] == "failed"
    first = board["actuators"][0]  # worst first
    assert (first["actuator_id"], first["status"], first["failure"]) == ("ema1", "failed", h["failure"])
    assert _metric("fleethealth_stream_failures_total", cause="state_unreadable") == failures + 1
    metrics = api.get("/metrics").text
    assert "fleethealth_streams_failed 1.0" in metrics

    # Not retried: the stream is out of the processor's scan, and another wait answers at once.
    with db.read() as session:
        pending = repository.pending_streams(session)
    assert pending == []
    r = _send(api, "ema1", 3, make_series(4 * N, seed=22), wait=60.0)
    assert r.status_code == 409 and r.json()["error"] == "StreamFailed"
    # The failed stream does not stop the others.
    assert _send(api, "ok1", 1, s).status_code == 202
    assert api.health("N1", "ok1")["last_applied_seq"] == 2
    db.dispose()

    # Once the cause is fixed (here: the stored version is readable again), an operator resets
    # the mark and the stream catches up on everything it logged meanwhile.
    monkeypatch.undo()
    monkeypatch.setenv("FLEETHEALTH_DATABASE_URL", db_url)
    assert cli.main(["streams", "reset", "--operator", "default", "N1", "ema1"]) == 0
    assert cli.main(["streams", "reset", "--operator", "default", "N1", "ema1"]) == 1  # not failed now
    assert _send(api, "ema1", 4, make_series(5 * N, seed=22)).status_code == 202
    h = api.health("N1", "ema1")
    assert h["status"] != "failed" and h["failure"] is None and h["last_applied_seq"] == 5


@pytest.fixture
def api_retrying(db_url: str) -> Iterator[Api]:
    settings = make_settings(db_url, processor_max_attempts=3, processor_retry_backoff_s=0.01)
    with TestClient(create_app(settings)) as client:
        yield Api(client)


def test_other_apply_errors_are_retried_then_fail_the_stream(
    api_retrying: Api, monkeypatch: pytest.MonkeyPatch
) -> None:
    api = api_retrying
    s = make_series(N, seed=23)
    api.setup_actuator()
    errors = _metric("fleethealth_apply_errors_total")
    calls = {"n": 0}

    def broken_step(cfg, state, batch):  # type: ignore[no-untyped-def]
        calls["n"] += 1
        raise RuntimeError("kernel exploded")

    # The start-up warm-up calls the module's step too: let it finish before the patch.
    assert api.app.state.kernels_warm.wait(300)
    monkeypatch.setattr(fakf, "step", broken_step)
    r = _send(api, "ema1", 0, s, wait=60.0)
    assert r.status_code == 409 and r.json()["error"] == "StreamFailed", r.text
    assert calls["n"] == 3  # bounded: one try per attempt, then no more
    assert _metric("fleethealth_apply_errors_total") == errors + 3
    h = api.health()
    assert h["status"] == "failed" and "3 times" in h["failure"] and "RuntimeError: kernel exploded" in h["failure"]
    assert h["last_applied_seq"] == 0


def test_a_stream_connection_to_a_failed_stream_is_told_why(api: Api, db_url: str) -> None:
    api.setup_actuator()
    db = Database(db_url)
    with db.write() as session:
        pk = session.scalar(select(Actuator.id).where(Actuator.actuator_id == "ema1"))
        assert pk is not None
        repository.mark_failed(session, pk, "test: cannot be applied")
    db.dispose()
    frame = {"type": "samples", "client_seq": 1, "t": [0.0, 0.001], "channels": {"current": [1.0, 2.0], "voltage": [0.5, None]}}
    with api.c.websocket_connect("/v1/aircraft/N1/actuators/ema1/stream", headers=api.h) as ws:
        ready = ws.receive_json()
        assert ready["type"] == "ready" and ready["failure"] == "test: cannot be applied"
        ws.send_json(frame)
        assert ws.receive_json()["type"] == "logged"  # durable all the same
        err = ws.receive_json()
        assert err["type"] == "error" and err["error"] == "StreamFailed" and "cannot be applied" in err["detail"]
        with pytest.raises(WebSocketDisconnect) as closed:
            ws.receive_json()
    assert closed.value.code == 1011
    assert api.health()["last_logged_seq"] == 1 and api.health()["last_applied_seq"] == 0


def test_a_state_that_cannot_be_read_back_after_a_replay_fails_the_stream(
    api_retrying: Api, monkeypatch: pytest.MonkeyPatch
) -> None:
    api = api_retrying
    s = make_series(2 * N, seed=24)
    api.setup_actuator()
    assert _send(api, "ema1", 0, s).status_code == 202

    def never_readable(data: bytes) -> object:
        raise StateVersionError("a FAKF state this build writes but cannot read (a bug)")

    monkeypatch.setattr(fakf, "load_state", never_readable)
    r = _send(api, "ema1", 1, s, wait=60.0)
    assert r.status_code == 409 and r.json()["error"] == "StreamFailed", r.text
    h = api.health()
    assert h["status"] == "failed" and "3 times" in h["failure"] and "StateUnreadable" in h["failure"]
    assert h["last_applied_seq"] == 1
