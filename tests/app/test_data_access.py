"""Reading data back: raw telemetry by time range, streamed exports (Arrow IPC, CSV, Parquet)
that round-trip what was ingested, and cursor pagination of every list, on SQLite and
PostgreSQL."""

from __future__ import annotations

import io
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.csv as pacsv
import pyarrow.parquet as pq
from sqlalchemy import update

from app.db import Database
from app.models import TelemetryBatch
from tests.app.conftest import Api, arrow_bytes
from tests.app.test_lifecycle import wait_applied
from tests.conftest import make_series

A = "/v1/aircraft/N1/actuators/ema1"


def _ingest(api: Api, n_batches: int = 4, n: int = 1200) -> dict[str, np.ndarray]:
    """Arrow uploads with missing samples (nulls and NaN); the columns as sent, joined."""
    api.setup_actuator()
    s = make_series(n, seed=7)
    cur, volt = s.current.copy(), s.voltage.copy()
    cur[[5, 600]] = np.nan
    volt[[7, 8, 1100]] = np.nan
    edges = np.linspace(0, n, n_batches + 1).astype(int)
    for k in range(n_batches):
        sl = slice(edges[k], edges[k + 1])
        r = api.post(
            f"{A}/telemetry?batch_id=b{k}",
            content=arrow_bytes({"t": s.t_s[sl], "current": cur[sl], "voltage": volt[sl]}),
            headers={"content-type": "application/vnd.apache.arrow.stream"},
        )
        assert r.status_code == 202, r.text
    wait_applied(api, A, n_batches)
    return {"t": s.t_s, "current": cur, "voltage": volt}


def _expected(cols: dict[str, np.ndarray], keep: np.ndarray | None = None) -> pa.Table:
    keep = np.ones(len(cols["t"]), dtype=bool) if keep is None else keep
    return pa.table({k: pa.array(v[keep], type=pa.float64(), from_pandas=True) for k, v in cols.items()})


def _read(body: bytes, fmt: str) -> pa.Table:
    if fmt == "arrow":
        return pa.ipc.open_stream(body).read_all()
    if fmt == "parquet":
        return pq.read_table(io.BytesIO(body))
    types = {"t": pa.float64(), "current": pa.float64(), "voltage": pa.float64()}
    return pacsv.read_csv(io.BytesIO(body), convert_options=pacsv.ConvertOptions(column_types=types))


def test_exported_telemetry_equals_what_was_ingested(api: Api) -> None:
    sent = _ingest(api)
    for fmt, media in [("arrow", "application/vnd.apache.arrow.stream"), ("parquet", "application/vnd.apache.parquet"),
                       ("csv", "text/csv")]:
        r = api.get(f"{A}/telemetry/export?format={fmt}")
        assert r.status_code == 200, r.text
        assert r.headers["content-type"].startswith(media)
        assert "attachment" in r.headers["content-disposition"]
        got = _read(r.content, fmt)
        assert got.equals(_expected(sent)), fmt
    # Written block by block: one record batch per logged batch, not one whole-series table.
    reader = pa.ipc.open_stream(api.get(f"{A}/telemetry/export").content)
    assert [len(b) for b in reader] == [300, 300, 300, 300]
    # A time range cuts inside batches.
    r = api.get(f"{A}/telemetry/export?from_s=0.25&to_s=0.7001")
    t = sent["t"]
    assert pa.ipc.open_stream(r.content).read_all().equals(_expected(sent, (t >= 0.25) & (t <= 0.7001)))
    # An empty range is a valid, empty file.
    empty = pa.ipc.open_stream(api.get(f"{A}/telemetry/export?from_s=99").content).read_all()
    assert empty.num_rows == 0 and empty.column_names == ["t", "current", "voltage"]
    assert api.get(f"{A}/telemetry/export?format=xlsx").status_code == 422
    assert api.get("/v1/aircraft/N1/actuators/nope/telemetry/export").status_code == 404


def test_telemetry_read_back_by_time_range_in_pages(api: Api, db_url: str) -> None:
    sent = _ingest(api)
    t = sent["t"]
    lo, hi = 0.1, 0.95
    want = (t >= lo) & (t <= hi)
    for order in ("asc", "desc"):
        got_t: list[float] = []
        got_v: list[float | None] = []
        cursor = None
        pages = 0
        while True:
            q = f"{A}/telemetry?from_s={lo}&to_s={hi}&max_samples=200&order={order}"
            r = api.get(q + (f"&cursor={cursor}" if cursor else ""))
            assert r.status_code == 200, r.text
            body = r.json()
            assert len(body["t_s"]) <= 200
            got_t += body["t_s"]
            got_v += body["channels"]["voltage"]
            pages += 1
            cursor = body["next_cursor"]
            if cursor is None:
                break
        exp_t, exp_v = t[want], sent["voltage"][want]
        if order == "desc":
            exp_t, exp_v = exp_t[::-1], exp_v[::-1]
        assert got_t == exp_t.tolist()
        assert got_v == [None if np.isnan(x) else x for x in exp_v.tolist()]
        assert pages == -(-int(want.sum()) // 200)
    # Newest first by default.
    assert api.get(f"{A}/telemetry?max_samples=1").json()["t_s"] == [t[-1]]
    # Batches whose samples retention dropped are named, not silently skipped.
    db = Database(db_url)
    try:
        with db.write() as s:
            s.execute(update(TelemetryBatch).where(TelemetryBatch.seq == 2).values(payload=None))
    finally:
        db.dispose()
    body = api.get(f"{A}/telemetry?order=asc").json()
    assert [d["seq"] for d in body["dropped"]] == [2]
    assert len(body["t_s"]) == 900


def test_outputs_page_newest_first_with_a_cursor(api: Api) -> None:
    _ingest(api)
    full = api.outputs()  # order=asc, every sample
    n = len(full["t_s"])
    # The README's example: the five newest samples (identified, so not the learning NaNs).
    r = api.get(f"{A}/outputs?estimator=fakf&max_samples=5")
    first = r.json()
    assert first["t_s"] == full["t_s"][::-1][:5]
    assert all(v is not None for v in first["series"]["voltage_estimate"])
    assert first["truncated"] is True and first["next_cursor"]
    walked: list[float] = []
    cursor: str | None = None
    for _ in range(n):
        r = api.get(f"{A}/outputs?estimator=fakf&max_samples=97" + (f"&cursor={cursor}" if cursor else ""))
        walked += r.json()["t_s"]
        cursor = r.json()["next_cursor"]
        if cursor is None:
            break
    assert walked == full["t_s"][::-1]
    # A cursor is bound to its list and order.
    assert api.get(f"{A}/outputs?estimator=fakf&order=asc&cursor={first['next_cursor']}").status_code == 400
    assert api.get(f"{A}/events?cursor={first['next_cursor']}").json()["error"] == "InvalidCursor"
    assert api.get(f"{A}/outputs?estimator=fakf&cursor=garbage!").status_code == 400


def test_exported_outputs_carry_their_labels(api: Api) -> None:
    _ingest(api)
    full = api.outputs()
    r = api.get(f"{A}/outputs/export?estimator=fakf&format=parquet")
    assert r.status_code == 200, r.text
    table = pq.read_table(io.BytesIO(r.content))
    assert table.column("t").to_pylist() == full["t_s"]
    for name, values in full["series"].items():
        assert table.column(name).to_pylist() == values, name
    assert set(table.column("seq").to_pylist()) == {1, 2, 3, 4}
    assert set(table.column("config_version").to_pylist()) == {1}
    assert set(table.column("baseline").to_pylist()) == {1}
    assert api.get(f"{A}/outputs/export?estimator=nope").status_code == 404


def _walk(api: Api, path: str, key: str = "items", **params: Any) -> tuple[list[Any], int]:
    items: list[Any] = []
    cursor = None
    for pages in range(1, 1000):
        q = "&".join(f"{k}={v}" for k, v in params.items())
        r = api.get(f"{path}?{q}" + (f"&cursor={cursor}" if cursor else ""))
        assert r.status_code == 200, r.text
        items += r.json()[key]
        cursor = r.json()["next_cursor"]
        if cursor is None:
            return items, pages
    raise AssertionError("pagination did not end")


def test_every_list_pages_with_a_cursor(api: Api) -> None:
    for k in range(5):
        assert api.post("/v1/aircraft", json={"tail": f"T{k}"}).status_code == 201
    items, pages = _walk(api, "/v1/aircraft", limit=2)
    assert [a["tail"] for a in items] == ["T4", "T3", "T2", "T1", "T0"] and pages == 3
    items, _ = _walk(api, "/v1/aircraft", limit=2, order="asc")
    assert [a["tail"] for a in items] == ["T0", "T1", "T2", "T3", "T4"]
    for k in range(3):
        api.post("/v1/aircraft/T0/actuators", json={"actuator_id": f"a{k}", "kind": "ema_voltage"})
    items, pages = _walk(api, "/v1/aircraft/T0/actuators", limit=2)
    assert [a["actuator_id"] for a in items] == ["a2", "a1", "a0"] and pages == 2
    board, pages = _walk(api, "/v1/fleet/health", key="aircraft", limit=2, sort="tail")
    assert [a["tail"] for a in board] == ["T0", "T1", "T2", "T3", "T4"] and pages == 3
    board, _ = _walk(api, "/v1/fleet/health", key="aircraft", limit=2)
    assert [a["tail"] for a in board] == [a["tail"] for a in api.get("/v1/fleet/health").json()["aircraft"]]

    _ingest(api)
    hist_all = api.get(f"{A}/health/history").json()["items"]
    assert [w["t_end_s"] for w in hist_all] == sorted((w["t_end_s"] for w in hist_all), reverse=True)
    hist, pages = _walk(api, f"{A}/health/history", limit=1)
    assert hist == hist_all and pages == len(hist_all)
    events, _ = _walk(api, f"{A}/events", limit=1, order="asc")
    assert events == api.get(f"{A}/events?order=asc").json()["items"]
    for m in range(3):
        api.post(f"{A}/maintenance", json={"action": "inspection", "performed_by": f"p{m}"})
    acts, pages = _walk(api, f"{A}/maintenance", limit=2)
    assert [a["performed_by"] for a in acts] == ["p2", "p1", "p0"] and pages == 2
    api.c.patch(A, headers=api.h, json={"estimators": {"fakf": {"thresholds": {"nis_mean_watch": 2.5}}}})
    versions, _ = _walk(api, f"{A}/configs", limit=1)
    assert [v["version"] for v in versions] == [2, 1]
