"""FAKF estimator: filterpy equivalence, identification, events, health windows, invariance."""

from __future__ import annotations

import math

import numpy as np
import pytest
from filterpy.kalman import KalmanFilter

from estimators import fakf
from estimators.base import (
    Batch,
    ConfigError,
    EstimatorError,
    OutOfOrderError,
    StateVersionError,
)
from estimators.simulators.ema_motor import simulate_ema

COEF = {"a0": -0.5, "a1": 0.06, "b0": 1.0, "b1": 2.0, "b2": -0.5}


def simulate_arx(
    coef: dict[str, float], n: int, seed: int, noise: float = 0.1
) -> tuple[np.ndarray, np.ndarray]:
    """Current (white + sine) and the eq. 15 ARX output with white equation noise."""
    rng = np.random.default_rng(seed)
    k = np.arange(n)
    current = rng.standard_normal(n) + 2.0 * np.sin(2 * np.pi * k / 200.0)
    v = np.zeros(n)
    e = noise * rng.standard_normal(n)
    for j in range(n):
        v1 = v[j - 1] if j >= 1 else 0.0
        v2 = v[j - 2] if j >= 2 else 0.0
        i1 = current[j - 1] if j >= 1 else 0.0
        i2 = current[j - 2] if j >= 2 else 0.0
        v[j] = (
            -coef["a0"] * v1
            - coef["a1"] * v2
            + coef["b0"] * current[j]
            + coef["b1"] * i1
            + coef["b2"] * i2
            + e[j]
        )
    return current, v


def batch_of(t: np.ndarray, current: np.ndarray, voltage: np.ndarray) -> Batch:
    return Batch(t_s=t, channels={"current": current, "voltage": voltage})


def run(config: fakf.FakfConfig, t, current, voltage, splits=None):
    """Run the estimator over the data in one batch or at the given split points."""
    state = fakf.initial_state(config)
    bounds = [0, *(splits or []), len(t)]
    samples: dict[str, list[np.ndarray]] = {name: [] for name in fakf.SAMPLE_OUTPUTS}
    health, events = [], []
    for lo, hi in zip(bounds[:-1], bounds[1:], strict=True):
        state, out = fakf.step(config, state, batch_of(t[lo:hi], current[lo:hi], voltage[lo:hi]))
        for name in fakf.SAMPLE_OUTPUTS:
            samples[name].append(out.samples[name])
        health.extend(out.health)
        events.extend(out.events)
    return state, {k: np.concatenate(v) for k, v in samples.items()}, health, events


def filterpy_reference(coef, q, r, p0, x0, current, voltage):
    """Sample-by-sample reference with filterpy's KalmanFilter (held current for NaN)."""
    kf = KalmanFilter(dim_x=2, dim_z=1)
    kf.F = np.array([[-coef["a0"], -coef["a1"]], [1.0, 0.0]])
    kf.B = np.array([[1.0], [0.0]])
    kf.H = np.array([[1.0, 0.0]])
    kf.Q = np.diag([q, 0.0])
    kf.R = np.array([[r]])
    kf.x = np.array([[x0[0]], [x0[1]]])
    kf.P = np.eye(2) * p0
    n = len(current)
    prior, post, s_var = np.empty(n), np.empty(n), np.empty(n)
    ih1 = ih2 = 0.0
    for k in range(n):
        ih = current[k] if np.isfinite(current[k]) else ih1
        u = coef["b0"] * ih + coef["b1"] * ih1 + coef["b2"] * ih2
        kf.predict(u=np.array([[u]]))
        prior[k] = kf.x[0, 0]
        s_var[k] = (kf.H @ kf.P @ kf.H.T + kf.R)[0, 0]
        kf.update(None if np.isnan(voltage[k]) else voltage[k])
        post[k] = kf.x[0, 0]
        ih2, ih1 = ih1, ih
    return prior, post, s_var, kf.P.copy()


# ----------------------------------------------------------------------------- filterpy


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_matches_filterpy_sample_by_sample(seed: int) -> None:
    n = 3000
    current, voltage = simulate_arx(COEF, n, seed, noise=0.5)
    voltage = voltage + np.random.default_rng(100 + seed).normal(0.0, 1.0, n)
    voltage[np.random.default_rng(seed).random(n) < 0.05] = np.nan  # predict-only samples
    q, r, p0 = 0.3, 1.7, 50.0
    config = fakf.parse_config({"coefficients": COEF, "q": q, "r": r, "p0": p0})
    t = np.arange(n) * 0.001
    state, s, _, _ = run(config, t, current, voltage)
    prior, post, s_var, p_final = filterpy_reference(COEF, q, r, p0, (0.0, 0.0), current, voltage)
    np.testing.assert_allclose(s["voltage_estimate"], post, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(s["innovation_var"], s_var, rtol=1e-9)
    valid = ~np.isnan(voltage)
    np.testing.assert_allclose(
        (voltage - s["innovation"])[valid], prior[valid], rtol=1e-9, atol=1e-9
    )
    assert np.all(np.isnan(s["innovation"][~valid]))
    np.testing.assert_allclose(state.P, p_final, rtol=1e-9)
    np.testing.assert_array_equal(state.P, state.P.T)
    assert np.all(np.linalg.eigvalsh(state.P) > 0.0)


def test_identified_model_then_filterpy() -> None:
    """After identification the filter equals filterpy started from the last two voltages."""
    n, n_id = 2500, 800
    current, voltage = simulate_arx(COEF, n, 7, noise=0.3)
    voltage = voltage + np.random.default_rng(8).normal(0.0, 0.5, n)
    config = fakf.parse_config({"identification_samples": n_id, "health_window_samples": 500})
    t = np.arange(n) * 0.01
    state, s, _, events = run(config, t, current, voltage)
    assert [e.kind for e in events] == ["identified"]
    det = events[0].detail
    assert events[0].t_s == t[n_id - 1]
    fit = fakf.identify_arx(current[:n_id], voltage[:n_id])
    assert det["coefficients"] == pytest.approx(fit.coefficients.__dict__, rel=1e-10)
    # auto noise levels: half the residual variance each
    assert det["q"] == pytest.approx(0.5 * fit.residual_rms**2, rel=1e-12)
    assert det["r"] == pytest.approx(0.5 * fit.residual_rms**2, rel=1e-12)
    assert np.all(np.isnan(s["voltage_estimate"][:n_id]))
    assert np.all(np.isnan(s["voltage_model"][:n_id]))
    kf_prior, kf_post, kf_s, _ = _filterpy_from(det, config.p0, current, voltage, n_id)
    np.testing.assert_allclose(s["voltage_estimate"][n_id:], kf_post, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(s["innovation_var"][n_id:], kf_s, rtol=1e-9)
    np.testing.assert_allclose(voltage[n_id:] - s["innovation"][n_id:], kf_prior, rtol=1e-9)


def _filterpy_from(det, p0, current, voltage, n_id):
    coef = det["coefficients"]
    kf = KalmanFilter(dim_x=2, dim_z=1)
    kf.F = np.array([[-coef["a0"], -coef["a1"]], [1.0, 0.0]])
    kf.B = np.array([[1.0], [0.0]])
    kf.H = np.array([[1.0, 0.0]])
    kf.Q = np.diag([det["q"], 0.0])
    kf.R = np.array([[det["r"]]])
    kf.x = np.array([[voltage[n_id - 1]], [voltage[n_id - 2]]])
    kf.P = np.eye(2) * p0
    prior, post, s_var = [], [], []
    for k in range(n_id, len(current)):
        u = coef["b0"] * current[k] + coef["b1"] * current[k - 1] + coef["b2"] * current[k - 2]
        kf.predict(u=np.array([[u]]))
        prior.append(kf.x[0, 0])
        s_var.append(kf.P[0, 0] + det["r"])
        kf.update(voltage[k])
        post.append(kf.x[0, 0])
    return np.array(prior), np.array(post), np.array(s_var), kf.P


# ----------------------------------------------------------------------------- identification


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_least_squares_recovers_known_coefficients(seed: int) -> None:
    current, voltage = simulate_arx(COEF, 6000, seed, noise=0.1)
    fit = fakf.identify_arx(current, voltage)
    assert fit.reason is None
    got = fit.coefficients.as_array()
    want = np.array([COEF[k] for k in fakf.COEFFICIENT_NAMES])
    # standard errors of LS with white equation error: sqrt(diag(sigma^2 (Phi'Phi)^-1))
    phi = np.column_stack([-voltage[1:-1], -voltage[:-2], current[2:], current[1:-1], current[:-2]])
    std_err = np.sqrt(np.diag(0.1**2 * np.linalg.inv(phi.T @ phi)))
    assert np.all(std_err < 0.03)
    assert np.all(np.abs(got - want) < 4.0 * std_err)
    assert fit.residual_rms == pytest.approx(0.1, rel=0.06)
    assert fit.rows == 5998
    gram = phi.T @ phi
    d = np.sqrt(np.diag(gram))
    assert fit.condition_number == pytest.approx(np.linalg.cond(gram / np.outer(d, d)), rel=1e-6)
    assert fit.max_pole_modulus < 1.0


def test_identification_skips_rows_with_nan() -> None:
    current, voltage = simulate_arx(COEF, 2000, 5, noise=0.1)
    current[100] = np.nan
    voltage[500] = np.nan
    fit = fakf.identify_arx(current, voltage)
    # a NaN at k removes the rows k, k+1, k+2 (it is a lag of the next two)
    assert fit.rows == 1998 - 6
    keep = np.ones(2000, dtype=bool)
    keep[[100, 101, 102, 500, 501, 502]] = False
    phi = np.column_stack(
        [-voltage[1:-1], -voltage[:-2], current[2:], current[1:-1], current[:-2]]
    )[keep[2:]]
    y = voltage[2:][keep[2:]]
    theta = np.linalg.lstsq(phi, y, rcond=None)[0]
    np.testing.assert_allclose(fit.coefficients.as_array(), theta, rtol=1e-9)


def test_unstable_fit_is_an_event_then_retried() -> None:
    n_id = 200
    unstable = {"a0": -2.1, "a1": 1.2, "b0": 1.0, "b1": 0.5, "b2": 0.2}  # |poles| = sqrt(1.2)
    c1, v1 = simulate_arx(unstable, n_id, 1, noise=0.01)
    c2, v2 = simulate_arx(COEF, 3 * n_id, 2, noise=0.1)
    current, voltage = np.concatenate([c1, c2]), np.concatenate([v1, v2])
    config = fakf.parse_config({"identification_samples": n_id, "health_window_samples": n_id})
    t = np.arange(len(current)) * 0.01
    _, s, health, events = run(config, t, current, voltage)
    assert [e.kind for e in events][:1] == ["identification_failed"]
    assert events[0].detail["reason_code"] == "unstable_model"
    assert events[0].detail["max_pole_modulus"] == pytest.approx(math.sqrt(1.2), rel=0.02)
    assert "unstable" in events[0].detail["reason"]
    assert health[0].status == "unknown"
    assert "identification failed" in health[0].reasons[0]
    assert np.all(np.isnan(s["voltage_estimate"][: 2 * n_id]))
    # the next window mixes the two models in its first rows but is stable: identified there
    assert events[1].kind == "identified"
    assert events[1].t_s == t[2 * n_id - 1]
    assert np.all(np.isfinite(s["voltage_estimate"][2 * n_id :]))
    assert health[2].status in ("ok", "watch")


def test_no_excitation_is_an_event() -> None:
    n = 300
    rng = np.random.default_rng(3)
    current = np.full(n, 1.5)
    voltage = 3.0 + 0.1 * rng.standard_normal(n)
    config = fakf.parse_config({"identification_samples": 100, "health_window_samples": 100})
    _, s, health, events = run(config, np.arange(n) * 0.01, current, voltage)
    assert [e.kind for e in events] == ["identification_failed"] * 3
    assert all(e.detail["reason_code"] == "low_current_excitation" for e in events)
    assert all(h.status == "unknown" for h in health)
    assert np.all(np.isnan(s["voltage_estimate"]))


def test_collinear_regressors_are_ill_conditioned() -> None:
    # a current of period 2 makes I_k and I_{k-2} identical columns
    n = 200
    current = np.where(np.arange(n) % 2 == 0, 1.0, -1.0)
    voltage = 2.0 * current + 0.1 * np.random.default_rng(4).standard_normal(n)
    fit = fakf.identify_arx(current, voltage)
    assert fit.reason == "ill_conditioned"
    assert fit.condition_number is None or fit.condition_number > 1e6
    config = fakf.parse_config({"identification_samples": 100, "health_window_samples": 100})
    _, _, _, events = run(config, np.arange(n) * 0.01, current, voltage)
    assert events[0].detail["reason_code"] == "ill_conditioned"


# ----------------------------------------------------------------------------- invariance, state


def _noisy_stream(n: int, seed: int):
    current, voltage = simulate_arx(COEF, n, seed, noise=0.3)
    rng = np.random.default_rng(seed + 50)
    voltage = voltage + rng.normal(0.0, 0.8, n)
    voltage[rng.random(n) < 0.02] = np.nan
    current[rng.random(n) < 0.01] = np.nan
    return np.arange(n) * 0.01 + 3.0, current, voltage


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_batch_split_invariance(seed: int) -> None:
    n = 2600
    t, current, voltage = _noisy_stream(n, seed)
    config = fakf.parse_config({"identification_samples": 700, "health_window_samples": 300})
    ref_state, ref, ref_health, ref_events = run(config, t, current, voltage)
    rng = np.random.default_rng(seed)
    splits = sorted(set(rng.integers(1, n, size=25).tolist()))
    # some 1-sample batches, including around the identification and window ends
    splits = sorted(set(splits) | {1, 2, 3, 699, 700, 701, 899, 900, 901})
    state, got, health, events = run(config, t, current, voltage, splits)
    for name in fakf.SAMPLE_OUTPUTS:
        np.testing.assert_array_equal(got[name], ref[name])
    assert health == ref_health
    assert events == ref_events
    assert len(ref_health) == n // 300
    np.testing.assert_array_equal(state.vector, ref_state.vector)


def test_state_round_trip_is_exact() -> None:
    n = 2000
    t, current, voltage = _noisy_stream(n, 9)
    config = fakf.parse_config({"identification_samples": 500, "health_window_samples": 400})
    _, ref, ref_health, _ = run(config, t, current, voltage)
    state = fakf.initial_state(config)
    state, out1 = fakf.step(config, state, batch_of(t[:1234], current[:1234], voltage[:1234]))
    blob = fakf.dump_state(state)
    loaded = fakf.load_state(blob)
    np.testing.assert_array_equal(loaded.vector, state.vector)
    assert loaded.t_last_s == state.t_last_s
    assert fakf.dump_state(loaded) == blob
    _, out2 = fakf.step(config, loaded, batch_of(t[1234:], current[1234:], voltage[1234:]))
    got = np.concatenate([out1.samples["voltage_estimate"], out2.samples["voltage_estimate"]])
    np.testing.assert_array_equal(got, ref["voltage_estimate"])
    assert [*out1.health, *out2.health] == ref_health


def test_state_version_is_checked() -> None:
    config = fakf.parse_config({})
    blob = fakf.dump_state(fakf.initial_state(config)).replace(b'"version":2', b'"version":99')
    with pytest.raises(StateVersionError, match="99"):
        fakf.load_state(blob)
    with pytest.raises(EstimatorError):
        fakf.load_state(b"not json")


def test_out_of_order_batch_is_refused() -> None:
    config = fakf.parse_config({"coefficients": COEF, "q": 1.0, "r": 1.0})
    current, voltage = simulate_arx(COEF, 20, 0)
    t = np.arange(20) * 0.01
    state, _ = fakf.step(
        config, fakf.initial_state(config), batch_of(t[:10], current[:10], voltage[:10])
    )
    with pytest.raises(OutOfOrderError):
        fakf.step(config, state, batch_of(t[9:], current[9:], voltage[9:]))
    bad_t = t[10:].copy()
    bad_t[5] = bad_t[4]
    with pytest.raises(OutOfOrderError):
        fakf.step(config, state, batch_of(bad_t, current[10:], voltage[10:]))
    # a refused batch leaves the state usable
    state2, out = fakf.step(config, state, batch_of(t[10:], current[10:], voltage[10:]))
    assert state2.t_last_s == t[-1]
    assert np.all(np.isfinite(out.samples["voltage_estimate"]))


def test_missing_channel_is_an_error() -> None:
    config = fakf.parse_config({"voltage_channel": "v_motor"})
    with pytest.raises(EstimatorError, match="v_motor"):
        fakf.step(
            config,
            fakf.initial_state(config),
            batch_of(np.arange(3.0), np.zeros(3), np.zeros(3)),
        )


# ----------------------------------------------------------------------------- NaN handling


def test_nan_voltage_predicts_only_and_p_grows() -> None:
    n = 400
    current, voltage = simulate_arx(COEF, n, 11, noise=0.2)
    voltage[200:203] = np.nan
    config = fakf.parse_config({"coefficients": COEF, "q": 0.2, "r": 0.5})
    state = fakf.initial_state(config)
    state, out_a = fakf.step(
        config, state, batch_of(np.arange(200.0), current[:200], voltage[:200])
    )
    p_before = state.P[0, 0]
    x_before = state.x
    state, out_b = fakf.step(
        config, state, batch_of(np.arange(200.0, 203.0), current[200:203], voltage[200:203])
    )
    assert np.all(np.isnan(out_b.samples["innovation"]))
    # estimate = prior = F x + u, exactly the model recursion from x_before
    u = COEF["b0"] * current[200] + COEF["b1"] * current[199] + COEF["b2"] * current[198]
    prior = -COEF["a0"] * x_before[0] - COEF["a1"] * x_before[1] + u
    assert out_b.samples["voltage_estimate"][0] == pytest.approx(prior, rel=1e-12)
    s = out_b.samples["innovation_var"]
    assert np.all(np.diff(s) > 0.0)
    assert state.P[0, 0] > p_before
    assert np.all(np.isfinite(out_a.samples["voltage_estimate"]))


def test_nan_current_holds_the_last_valid_current() -> None:
    n = 600
    current, voltage = simulate_arx(COEF, n, 12, noise=0.2)
    holed = current.copy()
    holed[[300, 301, 450]] = np.nan
    held = current.copy()
    held[[300, 301]] = current[299]
    held[450] = current[449]
    config = fakf.parse_config({"coefficients": COEF, "q": 0.2, "r": 0.5})
    t = np.arange(n) * 0.01
    _, s_holed, _, _ = run(config, t, holed, voltage)
    _, s_held, _, _ = run(config, t, held, voltage)
    for name in fakf.SAMPLE_OUTPUTS:
        np.testing.assert_array_equal(s_holed[name], s_held[name])


# ----------------------------------------------------------------------------- health windows


def test_health_indicators_match_the_per_sample_outputs() -> None:
    n, n_id, hw = 3000, 1000, 500
    current, voltage = simulate_arx(COEF, n, 21, noise=0.3)
    voltage = voltage + np.random.default_rng(22).normal(0.0, 0.5, n)
    config = fakf.parse_config({"identification_samples": n_id, "health_window_samples": hw})
    t = np.arange(n) * 0.01
    state, s, health, events = run(config, t, current, voltage)
    assert len(health) == n // hw
    base = events[0].detail["coefficients"]
    for w, h in enumerate(health):
        lo, hi = w * hw, (w + 1) * hw
        assert (h.t_start_s, h.t_end_s, h.n_samples) == (t[lo], t[hi - 1], hw)
        win_fit = fakf.identify_arx(current[max(lo - 2, 0) : hi], voltage[max(lo - 2, 0) : hi])
        np.testing.assert_allclose(
            [h.indicators[k] for k in fakf.COEFFICIENT_NAMES],
            win_fit.coefficients.as_array(),
            rtol=1e-9,
        )
        if hi <= n_id:
            assert h.indicators["nis_mean"] is None
            continue
        inn = s["innovation"][lo:hi]
        nis = inn**2 / s["innovation_var"][lo:hi]
        err = s["voltage_estimate"][lo:hi] - voltage[lo:hi]
        assert h.indicators["innovation_rms"] == pytest.approx(np.sqrt(np.mean(inn**2)), rel=1e-12)
        assert h.indicators["nis_mean"] == pytest.approx(nis.mean(), rel=1e-12)
        in_bounds = np.mean((nis >= 0.000982069117175) & (nis <= 5.02388618731489))
        assert h.indicators["nis_in_bounds"] == pytest.approx(in_bounds, abs=1e-12)
        assert h.indicators["mae"] == pytest.approx(np.abs(err).mean(), rel=1e-12)
        assert h.indicators["rmse"] == pytest.approx(np.sqrt(np.mean(err**2)), rel=1e-12)
        model_mae = np.abs(s["voltage_model"][lo:hi] - voltage[lo:hi]).mean()
        assert h.indicators["model_mae"] == pytest.approx(model_mae, rel=1e-12)
        # coef_drift: RMS difference of the two models' one-step predictions / RMS voltage
        k = np.arange(lo, hi)
        phi = np.column_stack(
            [-voltage[k - 1], -voltage[k - 2], current[k], current[k - 1], current[k - 2]]
        )
        base_arr = np.array([base[c] for c in fakf.COEFFICIENT_NAMES])
        diff = phi @ (win_fit.coefficients.as_array() - base_arr)
        drift = np.sqrt(np.mean(diff**2)) / np.sqrt(np.mean(voltage[lo:hi] ** 2))
        assert h.indicators["coef_drift"] == pytest.approx(drift, rel=1e-6)
        # healthy data like the identification window: NIS near 1, status ok
        assert 0.7 < h.indicators["nis_mean"] < 1.5
        assert h.status == "ok"
    assert state.n_samples == n


def test_changed_plant_raises_the_status() -> None:
    n, n_id, hw = 4000, 1000, 500
    current, voltage = simulate_arx(COEF, n, 31, noise=0.3)
    changed = {**COEF, "b1": 4.0}  # a plant change after t = 25 s
    _, v2 = simulate_arx(changed, n, 31, noise=0.3)
    voltage = np.concatenate([voltage[:2500], v2[2500:]])
    config = fakf.parse_config({"identification_samples": n_id, "health_window_samples": hw})
    _, _, health, _ = run(config, np.arange(n) * 0.01, current, voltage)
    before, after = health[2:5], health[5:]
    assert all(h.status == "ok" for h in before)
    assert all(h.status == "alert" for h in after)
    assert all(any(r.startswith("nis_mean") for r in h.reasons) for h in after)
    assert all(h.indicators["nis_mean"] > 50.0 for h in after)
    assert all(h.indicators["coef_drift"] < 0.02 for h in before)
    assert all(h.indicators["coef_drift"] > 0.2 for h in after)
    assert all(h.indicators["b1"] == pytest.approx(4.0, abs=0.1) for h in after[1:])


# ----------------------------------------------------------------------------- configuration


def test_config_defaults_round_trip() -> None:
    config = fakf.parse_config({})
    d = fakf.config_to_dict(config)
    assert d["q"] == "auto" and d["r"] == "auto"
    assert d["identification_samples"] == 1000 and d["health_window_samples"] == 1000
    assert d["coefficients"] is None
    assert fakf.parse_config(d) == config
    fixed = fakf.parse_config({"coefficients": COEF, "q": 1, "r": 2.5})
    assert fakf.parse_config(fakf.config_to_dict(fixed)) == fixed
    assert fakf.required_channels(config) == ("current", "voltage")


@pytest.mark.parametrize(
    ("raw", "field"),
    [
        ({"bogus": 1}, "bogus"),
        ({"q": 0}, "q"),
        ({"r": -1.0}, "r"),
        ({"r": "automatic"}, "r"),
        ({"q": True}, "q"),
        ({"p0": float("nan")}, "p0"),
        ({"identification_samples": 5}, "identification_samples"),
        ({"identification_samples": 100.0}, "identification_samples"),
        ({"health_window_samples": 0}, "health_window_samples"),
        ({"current_channel": ""}, "current_channel"),
        ({"coefficients": {"a0": 0.1, "a1": 0.0, "b0": 1.0, "b1": 1.0}}, "coefficients"),
        ({"coefficients": {**COEF, "b3": 1.0}, "q": 1, "r": 1}, "coefficients"),
        ({"coefficients": {**COEF, "a0": "x"}, "q": 1, "r": 1}, "coefficients.a0"),
        ({"coefficients": {**COEF, "a0": -2.5, "a1": 1.5}, "q": 1, "r": 1}, "coefficients"),
        ({"coefficients": COEF}, "q"),
        ({"thresholds": {"nis_mean_alert": 1.0}}, "thresholds.nis_mean_alert"),
        ({"thresholds": {"nope": 1.0}}, "thresholds.nope"),
        ({"condition_limit": -3}, "condition_limit"),
        ({"voltage_rail_low_v": 5.0, "voltage_rail_high_v": -5.0}, "voltage_rail_low_v"),
        ({"voltage_rail_high_v": float("inf")}, "voltage_rail_high_v"),
        ({"idle_close_s": 0.0}, "idle_close_s"),
        ({"reidentification": {"windows": 0}}, "reidentification.windows"),
        ({"reidentification": {"margin": -0.1}}, "reidentification.margin"),
        ({"min_graded_samples": 0}, "min_graded_samples"),
    ],
)
def test_config_errors_name_the_field(raw, field) -> None:
    with pytest.raises(ConfigError) as info:
        fakf.parse_config(raw)
    message = str(info.value)
    assert message.startswith("fakf: ")
    assert field in message


def test_registry_and_warm_up() -> None:
    from estimators.registry import get_estimator

    kind = get_estimator("fakf")
    assert kind is fakf and kind.STATE_VERSION == 2
    assert kind.CONFIG_MODEL is fakf.FakfConfig
    schema = fakf.CONFIG_MODEL.model_json_schema()
    assert "voltage_rail_low_v" in schema["properties"]
    assert "V" in schema["properties"]["voltage_rail_low_v"]["description"]
    fakf.warm_up()


# ----------------------------------------------------------------------------- simulator truth


@pytest.mark.parametrize("load_lbs", [-40.0, 40.0])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_fakf_beats_raw_and_model_against_true_voltage(load_lbs: float, seed: int) -> None:
    run_ = simulate_ema(duration_s=12.0, load_lbs=load_lbs, seed=seed)
    config = fakf.parse_config({"identification_samples": 2000, "health_window_samples": 2000})
    _, s, _, events = run(config, run_.t_s, run_.current_a, run_.voltage_measured_v)
    assert events[0].kind == "identified"
    valid = np.isfinite(s["voltage_estimate"])
    assert valid.sum() == len(run_.t_s) - 2000
    truth = run_.voltage_true_v[valid]

    def rmse(x: np.ndarray) -> float:
        return float(np.sqrt(np.mean((x[valid] - truth) ** 2)))

    fakf_err = rmse(s["voltage_estimate"])
    assert fakf_err < 0.9 * rmse(run_.voltage_measured_v)
    assert fakf_err < 0.5 * rmse(s["voltage_model"])


# ----------------------------------------------------------------------------- state versions


def _v1_fixture_stream() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The stream whose first 1700 samples produced ``data/fakf_state_v1.bin`` (saved with the
    version-1 code, config identification 500 / window 400), and 800 more samples of it."""
    rng = np.random.default_rng(5)
    n = 1700
    k = np.arange(n)
    cur = rng.standard_normal(n) + 2 * np.sin(2 * np.pi * k / 200)
    v = np.zeros(n)
    for j in range(2, n):
        v[j] = (
            0.5 * v[j - 1]
            - 0.06 * v[j - 2]
            + cur[j]
            + 2 * cur[j - 1]
            - 0.5 * cur[j - 2]
            + 0.3 * rng.standard_normal()
        )
    return k * 0.01, cur, v


def test_version_1_state_loads_upgraded_and_steps_like_a_fresh_run() -> None:
    from pathlib import Path

    blob = (Path(__file__).parent / "data" / "fakf_state_v1.bin").read_bytes()
    assert b'"version":1' in blob
    state = fakf.load_state(blob)
    assert state.version == fakf.STATE_VERSION == 2
    assert state.vector.shape == (fakf.kern.ST_LEN,)
    assert state.model_ready and state.reference_coefficients == state.coefficients
    config = fakf.parse_config({"identification_samples": 500, "health_window_samples": 400})
    t, cur, v = _v1_fixture_stream()
    # the same stream run from the start with today's code reaches the same filter state
    ref_state, _ = fakf.step(config, fakf.initial_state(config), batch_of(t, cur, v))
    for name in ("coefficients", "x", "covariance_upper", "voltage_lags", "window_gram"):
        np.testing.assert_array_equal(state.part(name), ref_state.part(name))
    # and the upgraded state steps on: continue with the stream's own model for 800 samples
    coef = state.coefficients
    assert coef is not None
    rng = np.random.default_rng(99)
    n2 = 800
    t2 = t[-1] + 0.01 * np.arange(1, n2 + 1)
    cur2 = rng.standard_normal(n2)
    v2 = np.empty(n2)
    vp, vpp, ip, ipp = v[-1], v[-2], cur[-1], cur[-2]
    for j in range(n2):
        v2[j] = -coef.a0 * vp - coef.a1 * vpp + coef.b0 * cur2[j] + coef.b1 * ip + coef.b2 * ipp
        v2[j] += 0.3 * rng.standard_normal()
        vpp, vp, ipp, ip = vp, v2[j], ip, cur2[j]
    s_up, out_up = fakf.step(config, state, batch_of(t2, cur2, v2))
    s_ref, out_ref = fakf.step(config, ref_state, batch_of(t2, cur2, v2))
    for name in fakf.SAMPLE_OUTPUTS:
        np.testing.assert_array_equal(out_up.samples[name], out_ref.samples[name])
    assert np.all(np.isfinite(out_up.samples["voltage_estimate"]))
    assert len(out_up.health) == len(out_ref.health) == 2
    assert out_up.health[0].status == "ok"
    assert fakf.load_state(fakf.dump_state(s_up)).version == 2


def test_unknown_state_versions_are_refused() -> None:
    blob = fakf.dump_state(fakf.initial_state(fakf.parse_config({})))
    for version in (b"0", b"3", b'"2"'):
        with pytest.raises(StateVersionError):
            fakf.load_state(blob.replace(b'"version":2', b'"version":' + version))
