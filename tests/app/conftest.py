from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import numpy as np
import orjson
import pyarrow as pa
import pytest
from fastapi.testclient import TestClient
from sqlalchemy import select

from app.config import Settings
from app.db import Database
from app.main import create_app
from app.models import Actuator
from tests.conftest import make_series

ADMIN_KEY = "test-admin-key-abcdefghijklmnop"
FAKF_SMALL = {"identification_samples": 200, "health_window_samples": 250}


def make_settings(db_url: str, **kw: Any) -> Settings:
    """Settings of an in-process test app: the processor in a thread of the test's own process
    (its internals are looked at) unless ``apply_process="on"`` is asked for."""
    kw.setdefault("apply_process", "off")
    return Settings(
        database_url=db_url,
        bootstrap_admin_key=ADMIN_KEY,
        processor_scan_interval_s=0.2,
        **kw,
    )


class FakeClock:
    """A clock the test moves by hand (for the look-up caches' TTLs)."""

    def __init__(self) -> None:
        self.now = 1000.0

    def __call__(self) -> float:
        return self.now


class Api:
    """A TestClient with the admin key and helpers for the common calls."""

    def __init__(self, client: TestClient, key: str = ADMIN_KEY) -> None:
        self.c = client
        self.h = {"Authorization": f"Bearer {key}"}
        self.app = client.app

    def get(self, path: str, **kw: Any) -> Any:
        return self.c.get(path, headers={**self.h, **kw.pop("headers", {})}, **kw)

    def post(self, path: str, **kw: Any) -> Any:
        return self.c.post(path, headers={**self.h, **kw.pop("headers", {})}, **kw)

    def setup_actuator(self, tail: str = "N1", act: str = "ema1", estimators: Any = None) -> None:
        r = self.post("/v1/aircraft", json={"tail": tail})
        assert r.status_code in (201, 409), r.text
        r = self.post(
            f"/v1/aircraft/{tail}/actuators",
            json={"actuator_id": act, "kind": "ema_voltage", "estimators": estimators or {"fakf": FAKF_SMALL}},
        )
        assert r.status_code == 201, r.text

    def send_json(self, tail: str, act: str, batch_id: str, t: np.ndarray, chans: dict[str, np.ndarray],
                  wait: float = 30.0) -> Any:
        body = {
            "batch_id": batch_id,
            "t": t.tolist(),
            "channels": {k: [None if np.isnan(x) else float(x) for x in v] for k, v in chans.items()},
        }
        return self.post(
            f"/v1/aircraft/{tail}/actuators/{act}/telemetry?wait={wait}",
            content=orjson.dumps(body),
            headers={"content-type": "application/json"},
        )

    def send_arrow(self, tail: str, act: str, batch_id: str, t: np.ndarray, chans: dict[str, np.ndarray],
                   wait: float = 30.0) -> Any:
        return self.post(
            f"/v1/aircraft/{tail}/actuators/{act}/telemetry?batch_id={batch_id}&wait={wait}",
            content=arrow_bytes({"t": t, **chans}),
            headers={"content-type": "application/vnd.apache.arrow.stream"},
        )

    def log_series(self, tail: str, act: str, n_batches: int, batch: int, seed: int) -> None:
        """Register ``act`` and log ``n_batches`` Arrow batches of ``batch`` samples of one
        series, without waiting for their application."""
        self.setup_actuator(tail, act)
        s = make_series(n_batches * batch, seed=seed)
        for k in range(n_batches):
            sl = slice(k * batch, (k + 1) * batch)
            chans = {"current": s.current[sl], "voltage": s.voltage[sl]}
            r = self.send_arrow(tail, act, f"b{k}", s.t_s[sl], chans, wait=0)
            assert r.status_code == 202, r.text

    def history(self, tail: str = "N1", act: str = "ema1") -> list[dict[str, Any]]:
        r = self.get(f"/v1/aircraft/{tail}/actuators/{act}/health/history?order=asc")
        assert r.status_code == 200, r.text
        return r.json()["items"]  # type: ignore[no-any-return]

    def outputs(self, tail: str = "N1", act: str = "ema1") -> dict[str, Any]:
        r = self.get(f"/v1/aircraft/{tail}/actuators/{act}/outputs?estimator=fakf&max_samples=1000000&order=asc")
        assert r.status_code == 200, r.text
        return r.json()  # type: ignore[no-any-return]

    def health(self, tail: str = "N1", act: str = "ema1") -> dict[str, Any]:
        r = self.get(f"/v1/aircraft/{tail}/actuators/{act}/health")
        assert r.status_code == 200, r.text
        return r.json()  # type: ignore[no-any-return]


def actuator_pk(db: Database, act: str = "ema1") -> int:
    """The primary key of actuator ``act`` (the stream key of the log and the processor)."""
    with db.read() as s:
        return int(s.scalar(select(Actuator.id).where(Actuator.actuator_id == act)))  # type: ignore[arg-type]


def arrow_bytes(cols: dict[str, np.ndarray]) -> bytes:
    table = pa.table({k: pa.array(np.asarray(v, dtype=np.float64)) for k, v in cols.items()})
    sink = pa.BufferOutputStream()
    with pa.ipc.new_stream(sink, table.schema) as w:
        w.write_table(table)
    return sink.getvalue().to_pybytes()


@pytest.fixture
def api(db_url: str) -> Iterator[Api]:
    with TestClient(create_app(make_settings(db_url))) as client:
        yield Api(client)


@pytest.fixture
def api_noproc(db_url: str) -> Iterator[Api]:
    """The service with its processor switched off: batches are logged, never applied."""
    with TestClient(create_app(make_settings(db_url, processor_enabled=False))) as client:
        yield Api(client)
