"""An open WebSocket is closed (1008) once its key is revoked or loses the scope it needs, by
whichever process changed the key (here the ``fleethealth keys`` command, a separate process)."""

from __future__ import annotations

import os
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient
from starlette.websockets import WebSocketDisconnect

from app.auth.service import create_key
from app.db import Database
from app.main import create_app
from tests.app.conftest import Api, make_settings

FLEETHEALTH = str(Path(sys.executable).parent / "fleethealth")


@pytest.fixture
def api_recheck(db_url: str) -> Iterator[Api]:
    with TestClient(create_app(make_settings(db_url, ws_auth_recheck_s=0.2))) as client:
        yield Api(client)


def _keys_command(db_url: str, *args: str) -> None:
    env = {**os.environ, "FLEETHEALTH_DATABASE_URL": db_url}
    out = subprocess.run([FLEETHEALTH, "keys", *args], env=env, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr


def _closed_with(ws: object, code: int) -> dict[str, object]:
    """The error message sent before the close, and check the close code."""
    msg = ws.receive_json()  # type: ignore[attr-defined]
    with pytest.raises(WebSocketDisconnect) as closed:
        ws.receive_json()  # type: ignore[attr-defined]
    assert closed.value.code == code
    return msg  # type: ignore[no-any-return]


def test_revoked_ingest_key_and_lost_read_scope_close_open_sockets(api_recheck: Api, db_url: str) -> None:
    api = api_recheck
    api.setup_actuator()
    db = Database(db_url)
    with db.write() as s:
        ingest_row, ingest_key = create_key(s, "default", ["ingest"], name="stand")
        read_row, read_key = create_key(s, "default", ["read"], name="board")
        other_row, other_key = create_key(s, "default", ["read"], name="kept")
    db.dispose()
    frame = {"type": "samples", "client_seq": 1, "t": [0.0, 0.001], "channels": {"current": [0.1, 0.2], "voltage": [1.0, 1.1]}}
    with (
        api.c.websocket_connect("/v1/aircraft/N1/actuators/ema1/stream",
                                headers={"Authorization": f"Bearer {ingest_key}"}) as stream,
        api.c.websocket_connect("/v1/fleet/events", headers={"Authorization": f"Bearer {read_key}"}) as events,
        api.c.websocket_connect("/v1/fleet/events?types=applied",
                                headers={"Authorization": f"Bearer {other_key}"}) as kept,
    ):
        assert stream.receive_json()["type"] == "ready"
        assert events.receive_json()["type"] == "ready"
        assert kept.receive_json()["type"] == "ready"
        stream.send_json(frame)
        assert stream.receive_json()["type"] == "logged"
        _keys_command(db_url, "revoke", str(ingest_row.id))
        _keys_command(db_url, "scopes", str(read_row.id), "ingest")
        # The stream may still deliver the frame's result before the close.
        msg = stream.receive_json()
        if msg["type"] == "result":
            msg = stream.receive_json()
        assert msg == {"type": "error", "error": "Unauthorized", "detail": "the API key was revoked"}
        with pytest.raises(WebSocketDisconnect) as closed:
            stream.receive_json()
        assert closed.value.code == 1008
        msg = _closed_with(events, 1008)
        assert msg["error"] == "Forbidden" and "read" in str(msg["detail"])
        # A key left alone keeps its subscription: a batch applied after the closes reaches it.
        r = api.send_json("N1", "ema1", "after", np.array([1.0, 1.001]), {"current": np.array([0.1, 0.2]),
                                                                          "voltage": np.array([1.0, 1.1])})
        assert r.status_code == 202, r.text
        seqs = []
        while 2 not in seqs:
            ev = kept.receive_json()
            assert ev["type"] == "applied"
            seqs.append(ev["seq"])
    # The revoked key is refused for new connections too.
    with api.c.websocket_connect("/v1/fleet/events", headers={"Authorization": f"Bearer {ingest_key}"}) as ws:
        msg = _closed_with(ws, 1008)
        assert msg["error"] == "Unauthorized"
