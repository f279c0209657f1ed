"""The architecture's invariants, each checked so that it fails when the code is wrong."""

from __future__ import annotations

import threading

import numpy as np
import pytest
from sqlalchemy import func, select

from app.codec import decode_columns
from app.db import Database
from app.models import Actuator, HealthWindowRow, Stream, TelemetryBatch
from app.processing import apply_pending
from estimators.registry import ESTIMATORS
from tests.app.conftest import Api
from tests.conftest import make_series


def _chans(s, sl=slice(None)):  # type: ignore[no-untyped-def]
    return {"current": s.current[sl], "voltage": s.voltage[sl]}


def test_ack_means_committed_in_log(api_noproc: Api, db_url: str) -> None:
    api = api_noproc
    api.setup_actuator()
    s = make_series(700, seed=1)
    r = api.send_arrow("N1", "ema1", "b1", s.t_s, _chans(s), wait=0)
    assert r.status_code == 202, r.text
    # Read through a separate engine: the batch is there, byte for byte, though nothing applied it.
    db = Database(db_url)
    with db.read() as session:
        row = session.scalar(select(TelemetryBatch))
        assert row is not None and row.seq == 1 and row.batch_id == "b1"
        cols = decode_columns(row.payload)
        np.testing.assert_array_equal(cols["t"], s.t_s)
        np.testing.assert_array_equal(cols["voltage"], s.voltage)
        assert session.scalar(select(Stream.last_applied_seq)) == 0
    db.dispose()


def test_exactly_once_in_order(api: Api, db_url: str) -> None:
    api.setup_actuator()
    s = make_series(3000, seed=2)
    for k in range(6):
        sl = slice(500 * k, 500 * (k + 1))
        assert api.send_arrow("N1", "ema1", f"b{k}", s.t_s[sl], _chans(s, sl)).status_code == 202
    h = api.health()
    assert h["last_applied_seq"] == h["last_logged_seq"] == 6
    hist = api.history()
    # 3000 samples, windows of 250: 12 windows, each once, contiguous and ordered in time.
    assert len(hist) == 12
    ends = [w["t_end_s"] for w in hist]
    assert ends == sorted(ends) and len(set(ends)) == 12
    starts = [w["t_start_s"] for w in hist]
    np.testing.assert_allclose(starts, s.t_s[::250])
    out = api.outputs()
    np.testing.assert_array_equal(out["t_s"], s.t_s)


def test_concurrent_workers_apply_each_batch_once(api_noproc: Api, db_url: str) -> None:
    api = api_noproc
    api.setup_actuator()
    s = make_series(2000, seed=3)
    for k in range(8):
        sl = slice(250 * k, 250 * (k + 1))
        assert api.send_arrow("N1", "ema1", f"b{k}", s.t_s[sl], _chans(s, sl), wait=0).status_code == 202
    db = Database(db_url)
    with db.read() as session:
        pk = session.scalar(select(Actuator.id))
    errors: list[BaseException] = []

    def worker() -> None:
        try:
            while True:
                with db.write() as session:
                    # Small transactions so that the two workers interleave.
                    res = apply_pending(session, pk, max_samples=250, store_outputs=True, is_sqlite=db.is_sqlite)
                if res is None:
                    with db.read() as session:
                        if session.scalar(select(Stream.last_applied_seq)) == 8:
                            return
        except BaseException as exc:  # surfaced below
            errors.append(exc)

    threads = [threading.Thread(target=worker) for _ in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(60)
    assert not errors, errors
    with db.read() as session:
        n = session.scalar(select(func.count()).select_from(HealthWindowRow))
        distinct = session.scalar(select(func.count(func.distinct(HealthWindowRow.t_end_s))))
    db.dispose()
    assert n == distinct == 8


def test_apply_is_atomic(api_noproc: Api, db_url: str, monkeypatch: pytest.MonkeyPatch) -> None:
    """A failure inside an apply transaction leaves no output, no state and no applied mark."""
    api = api_noproc
    api.setup_actuator()
    s = make_series(1000, seed=4)
    for k in range(4):
        sl = slice(250 * k, 250 * (k + 1))
        api.send_arrow("N1", "ema1", f"b{k}", s.t_s[sl], _chans(s, sl), wait=0)
    fakf = ESTIMATORS["fakf"]
    real_step = fakf.step
    calls = {"n": 0}

    def failing_step(cfg, state, batch):  # type: ignore[no-untyped-def]
        calls["n"] += 1
        if calls["n"] == 3:
            raise RuntimeError("simulated crash in the middle of a transaction")
        return real_step(cfg, state, batch)

    # The start-up warm-up calls the module's step too: let it finish before the patch.
    assert api.app.state.kernels_warm.wait(300)
    monkeypatch.setattr(fakf, "step", failing_step)
    db = Database(db_url)
    with db.read() as session:
        pk = session.scalar(select(Actuator.id))
    with pytest.raises(RuntimeError), db.write() as session:
        apply_pending(session, pk, max_samples=10_000, store_outputs=True, is_sqlite=db.is_sqlite)
    with db.read() as session:
        assert session.scalar(select(Stream.last_applied_seq)) == 0
        assert session.scalar(select(func.count()).select_from(HealthWindowRow)) == 0
    monkeypatch.setattr(fakf, "step", real_step)
    with db.write() as session:
        res = apply_pending(session, pk, max_samples=10_000, store_outputs=True, is_sqlite=db.is_sqlite)
    assert res is not None and res.last_applied_seq == 4
    db.dispose()
    assert len(api.history()) == 4


def test_idempotent_retry(api: Api) -> None:
    api.setup_actuator()
    s = make_series(600, seed=5)
    first = api.send_json("N1", "ema1", "same", s.t_s, _chans(s))
    assert first.status_code == 202 and "idempotent-replayed" not in first.headers
    again = api.send_arrow("N1", "ema1", "same", s.t_s, _chans(s))  # other format, same samples
    assert again.status_code == 202
    assert again.json() == first.json()
    assert again.headers["idempotent-replayed"] == "true"
    h = api.health()
    assert h["last_logged_seq"] == h["last_applied_seq"] == 1
    assert len(api.history()) == 2  # 600 samples -> two full windows of 250, applied once
    other = make_series(600, seed=6)
    r = api.send_json("N1", "ema1", "same", other.t_s, _chans(other))
    assert r.status_code == 409 and r.json()["error"] == "IdempotencyConflict"


def test_batch_split_invariance(api: Api) -> None:
    s = make_series(2600, seed=7)
    api.setup_actuator("N1", "whole")
    api.setup_actuator("N1", "split")
    assert api.send_arrow("N1", "whole", "all", s.t_s, _chans(s)).status_code == 202
    rng = np.random.default_rng(0)
    cuts = np.sort(rng.choice(np.arange(1, 2600), size=11, replace=False))
    edges = [0, 1, 2, *[int(c) for c in cuts if c > 2], 2600]
    for k, (a, b) in enumerate(zip(edges[:-1], edges[1:], strict=True)):
        r = api.send_json("N1", "split", f"p{k}", s.t_s[a:b], _chans(s, slice(a, b)))
        assert r.status_code == 202, r.text
    hw, hs = api.history("N1", "whole"), api.history("N1", "split")
    assert len(hw) == len(hs) == 10
    for a, b in zip(hw, hs, strict=True):
        assert (a["t_start_s"], a["t_end_s"], a["status"]) == (b["t_start_s"], b["t_end_s"], b["status"])
        for k, v in a["indicators"].items():
            assert b["indicators"][k] == pytest.approx(v, rel=1e-9, abs=1e-12), k
    ow, os_ = api.outputs("N1", "whole"), api.outputs("N1", "split")
    for name, series in ow["series"].items():
        np.testing.assert_allclose(
            np.array(os_["series"][name], dtype=float), np.array(series, dtype=float),
            rtol=1e-9, atol=1e-12, equal_nan=True,
        )


def test_missing_samples_are_predicted_through(api: Api) -> None:
    api.setup_actuator()
    s = make_series(800, seed=8)
    v = s.voltage.copy()
    holes = [300, 301, 302, 550]
    v[holes] = np.nan
    # JSON null for the first half, an empty CSV cell and Arrow NaN for the rest.
    r = api.send_json("N1", "ema1", "j", s.t_s[:400], {"current": s.current[:400], "voltage": v[:400]})
    assert r.status_code == 202, r.text
    rows = ["t,current,voltage"] + [
        f"{float(t)!r},{float(i)!r},{'' if np.isnan(x) else repr(float(x))}"
        for t, i, x in zip(s.t_s[400:600], s.current[400:600], v[400:600], strict=True)
    ]
    r = api.post(
        "/v1/aircraft/N1/actuators/ema1/telemetry?batch_id=c&wait=30",
        content="\n".join(rows).encode(),
        headers={"content-type": "text/csv"},
    )
    assert r.status_code == 202, r.text
    r = api.send_arrow("N1", "ema1", "a", s.t_s[600:], {"current": s.current[600:], "voltage": v[600:]})
    assert r.status_code == 202, r.text
    out = api.outputs()
    est = np.array(out["series"]["voltage_estimate"], dtype=float)
    innov = np.array(out["series"]["innovation"], dtype=float)
    assert len(est) == 800
    for k in holes:
        assert np.isnan(innov[k]) and np.isfinite(est[k])  # predicted, not updated
    assert np.isfinite(innov[250:300]).all()
