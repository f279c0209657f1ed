"""A stream blocked by a bad batch (logged before the input bounds existed) is recovered by a
recorded rewind: the bad batch is discarded, the estimators restart when they had applied it,
and the outputs are then those of a stream that never saw it."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient

from app.main import create_app
from tests.app.conftest import Api, make_settings
from tests.conftest import make_series

FLEETHEALTH = str(Path(sys.executable).parent / "fleethealth")
N = 400


@pytest.fixture
def loose_api(db_url: str) -> Iterator[Api]:
    """The service with bounds as loose as before they existed (far-future times accepted)."""
    settings = make_settings(db_url, max_time_s=1e308, max_future_s=1e308)
    with TestClient(create_app(settings)) as client:
        yield Api(client)


def _send(api: Api, act: str, batch_id: str, part: int) -> Any:
    s = make_series(3 * N, seed=5)
    sl = slice(part * N, (part + 1) * N)
    return api.send_json("N1", act, batch_id, s.t_s[sl], {"current": s.current[sl], "voltage": s.voltage[sl]})


def _applied(api: Api, act: str) -> int:
    return int(api.health("N1", act)["last_applied_seq"])


def _wait_applied(api: Api, act: str, seq: int, timeout_s: float = 60.0) -> None:
    deadline = time.monotonic() + timeout_s
    while _applied(api, act) != seq:
        assert time.monotonic() < deadline, f"{act} not applied up to {seq}"
        time.sleep(0.1)


def _same_outputs(api: Api, a: str, b: str) -> None:
    ha, hb = api.history("N1", a), api.history("N1", b)
    assert len(ha) == len(hb) > 0
    for wa, wb in zip(ha, hb, strict=True):
        assert {k: v for k, v in wa.items() if k != "seq"} == {k: v for k, v in wb.items() if k != "seq"}
    oa, ob = api.outputs("N1", a), api.outputs("N1", b)
    assert oa.keys() == ob.keys()
    for key in oa:
        if isinstance(oa[key], dict):
            for name in oa[key]:
                np.testing.assert_array_equal(np.asarray(oa[key][name], dtype=float),
                                              np.asarray(ob[key][name], dtype=float))


def test_rewind_discards_a_poison_batch_and_is_recorded(loose_api: Api, db_url: str) -> None:
    api = loose_api
    api.setup_actuator(act="ema1")
    api.setup_actuator(act="ref")
    for act in ("ema1", "ref"):
        assert _send(api, act, "b1", 0).status_code == 202
        assert _send(api, act, "b2", 1).status_code == 202
    # Times in the wrong unit, accepted before the bounds existed, and applied.
    r = api.post("/v1/aircraft/N1/actuators/ema1/telemetry?wait=30",
                 json={"batch_id": "poison", "t": [1e300, 2e300], "channels": {"current": [0.1, 0.2], "voltage": [1.0, 1.1]}})
    assert r.status_code in (202, 409), r.text  # 409: applying it failed the stream
    assert _send(api, "ema1", "b3", 2).status_code == 409  # StaleBatch for good

    # A reason is required, and to_seq must leave something to discard.
    assert api.post("/v1/aircraft/N1/actuators/ema1/rewind", json={"to_seq": 3, "reason": "x"}).status_code == 422
    assert api.post("/v1/aircraft/N1/actuators/ema1/rewind", json={"to_seq": 2}).status_code == 422
    r = api.post("/v1/aircraft/N1/actuators/ema1/rewind", json={"to_seq": 2, "reason": "times in ms by mistake"})
    assert r.status_code == 200, r.text
    rec = r.json()
    assert rec["to_seq"] == 2 and rec["from_logged_seq"] == 3 and rec["reason"] == "times in ms by mistake"
    assert [d["batch_id"] for d in rec["discarded"]] == ["poison"] and rec["actor"].startswith("api key ")
    assert rec["estimators_reset"] == (rec["from_applied_seq"] == 3)

    # The stream takes the next batch again, and ends up as if the poison was never sent.
    r = _send(api, "ema1", "b3", 2)
    assert r.status_code == 202 and r.json()["seq"] == 3, r.text
    assert _send(api, "ref", "b3", 2).status_code == 202
    _wait_applied(api, "ema1", 3)
    _wait_applied(api, "ref", 3)
    assert api.health("N1", "ema1")["status"] == api.health("N1", "ref")["status"]
    _same_outputs(api, "ema1", "ref")

    # The same from the command line (another process), and the record of both.
    env = {**os.environ, "FLEETHEALTH_DATABASE_URL": db_url}
    done = subprocess.run(
        [FLEETHEALTH, "streams", "rewind", "--operator", "default", "--to-seq", "1", "--reason", "re-run b2 and b3",
         "N1", "ema1"], env=env, capture_output=True, text=True, timeout=120, check=False)
    assert done.returncode == 0, done.stderr
    assert "discarded 2 batches" in done.stdout and "estimators restarted" in done.stdout
    assert _send(api, "ema1", "b2", 1).status_code == 202
    assert _send(api, "ema1", "b3", 2).status_code == 202
    _wait_applied(api, "ema1", 3)
    _same_outputs(api, "ema1", "ref")
    items = api.get("/v1/aircraft/N1/actuators/ema1/rewinds").json()["items"]
    assert [(i["to_seq"], [d["batch_id"] for d in i["discarded"]]) for i in items] == [
        (2, ["poison"]), (1, ["b2", "b3"])]
    assert items[1]["actor"].startswith("cli ")
    listed = subprocess.run([FLEETHEALTH, "streams", "rewinds", "--operator", "default", "N1", "ema1"],
                            env=env, capture_output=True, text=True, timeout=120, check=False)
    assert listed.returncode == 0 and len(listed.stdout.strip().splitlines()) == 2, listed.stderr
