"""``GET .../series``: plot-ready, downsampled outputs and health indicators."""

from __future__ import annotations

import time

import numpy as np

from tests.app.conftest import Api
from tests.app.test_api import make_series

SERIES = "/v1/aircraft/N1/actuators/ema1/series"


def _feed(api: Api, n_batches: int = 4, n: int = 1000) -> None:
    api.setup_actuator()
    s = make_series(n_batches * n, seed=5)
    for b in range(n_batches):
        part = slice(b * n, (b + 1) * n)
        r = api.send_arrow("N1", "ema1", f"b{b}", s.t_s[part],
                           {"current": s.current[part], "voltage": s.voltage[part]})
        assert r.status_code == 202, r.text
    deadline = time.monotonic() + 300.0  # a cold kernel cache compiles first
    while api.health()["last_applied_seq"] < n_batches:
        assert time.monotonic() < deadline, "batches not applied in time"
        time.sleep(0.2)


def test_series_downsample_the_outputs_and_keep_their_extremes(api: Api) -> None:
    _feed(api)
    full = api.outputs()
    t_full = np.array(full["t_s"])
    v_full = np.array([np.nan if x is None else x for x in full["series"]["voltage_estimate"]])
    r = api.get(SERIES, params={"estimator": "fakf", "names": "voltage_estimate,innovation", "points": 200})
    assert r.status_code == 200, r.text
    got = r.json()
    assert got["reduced"] and got["n_samples"] == 4000 == len(t_full)
    assert sorted(got["series"]) == ["innovation", "voltage_estimate"]
    assert 100 < len(got["t_s"]) <= 200
    v = np.array([np.nan if x is None else x for x in got["series"]["voltage_estimate"]])
    assert np.nanmax(v) == np.nanmax(v_full) and np.nanmin(v) == np.nanmin(v_full)
    assert got["from_s"] == t_full[0] and got["to_s"] == t_full[-1]

    # Zooming in: a short span has fewer samples than points and comes back sample by sample.
    lo, hi = float(t_full[1500]), float(t_full[1599])
    r = api.get(SERIES, params={"estimator": "fakf", "names": "voltage_estimate", "from_s": lo, "to_s": hi,
                                "points": 200})
    zoom = r.json()
    assert not zoom["reduced"] and zoom["n_samples"] == 100
    assert zoom["t_s"] == t_full[1500:1600].tolist()
    assert zoom["series"]["voltage_estimate"] == full["series"]["voltage_estimate"][1500:1600]


def test_series_of_health_indicators_at_window_ends(api: Api) -> None:
    _feed(api)
    windows = api.history()
    r = api.get(SERIES, params={"estimator": "fakf", "source": "health"})
    assert r.status_code == 200, r.text
    got = r.json()
    assert got["n_samples"] == len(windows) > 0 and not got["reduced"]
    assert got["t_s"] == [w["t_end_s"] for w in windows]
    name = next(iter(windows[-1]["indicators"]))
    assert got["series"][name] == [w["indicators"].get(name) for w in windows]


def test_series_refuse_unknown_names_and_estimators(api: Api) -> None:
    _feed(api, n_batches=1)
    r = api.get(SERIES, params={"estimator": "fakf", "names": "no_such_output"})
    assert r.status_code == 404 and "no_such_output" in r.json()["detail"]
    r = api.get(SERIES, params={"estimator": "stmmae"})
    assert r.status_code == 404
    r = api.get(SERIES, params={"estimator": "fakf", "points": 1})
    assert r.status_code == 422
    r = api.get(SERIES, params={"estimator": "fakf", "from_s": 1e9, "to_s": 2e9})
    assert r.status_code == 200 and r.json()["n_samples"] == 0 and r.json()["t_s"] == []


def test_series_of_the_logged_telemetry_share_the_outputs_time_stamps(api: Api) -> None:
    _feed(api, n_batches=2)
    out = api.get(SERIES, params={"estimator": "fakf", "names": "voltage_estimate", "points": 300}).json()
    tel = api.get(SERIES, params={"source": "telemetry", "names": "voltage", "points": 300}).json()
    assert tel["n_samples"] == out["n_samples"] == 2000 and tel["estimator"] is None
    assert tel["t_s"] == out["t_s"]  # the same samples give the same buckets: one plot, one x axis
    s = make_series(2000, seed=5)
    got = np.array([np.nan if x is None else x for x in tel["series"]["voltage"]])
    assert np.nanmax(got) == np.nanmax(s.voltage) and np.nanmin(got) == np.nanmin(s.voltage)
    r = api.get(SERIES, params={"source": "outputs"})
    assert r.status_code == 400 and r.json()["error"] == "InvalidQuery"


def test_decoding_some_columns_of_a_block_gives_the_same_values() -> None:
    from app.codec import column_names, decode_columns, encode_columns

    rng = np.random.default_rng(3)
    cols = {"t": np.arange(50.0), **{f"c{i}": rng.normal(size=50) for i in range(6)}}
    data = encode_columns(cols)
    some = decode_columns(data, {"t", "c4", "absent"})
    assert sorted(some) == ["c4", "t"]
    np.testing.assert_array_equal(some["c4"], cols["c4"])
    assert some["c4"].flags.writeable
    assert sorted(decode_columns(data)) == sorted(cols) and column_names(data) == list(cols)
