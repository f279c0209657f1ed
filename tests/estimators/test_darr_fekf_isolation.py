"""darr_fekf beyond the seed's schedule: checked calibration, sensor faults in the signature
matrix, the sensor-or-parameter fit, the public config model and the state upgrade."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from estimators import darr_fekf as m
from estimators.base import Batch, StateVersionError
from estimators.kernels import darr_kernels as kern
from estimators.simulators.sha_ema import FaultSchedule, simulate_sha_ema
from estimators.simulators.sha_ema_scenarios import SensorFault, apply_sensor_faults

DATA = Path(__file__).parent / "data"
# short calibration window to keep the runs small; the checks are the same at 3 s
FAST = {"thresholds": {"window_s": 1.2}}


def run(raw_config, t, ch, splits=()):
    config = m.parse_config(raw_config)
    state = m.initial_state(config)
    bounds = [0, *splits, len(t)]
    samples: dict[str, list[np.ndarray]] = {}
    events, statuses = [], []
    out = None
    for lo, hi in zip(bounds[:-1], bounds[1:], strict=True):
        state, out = m.step(config, state, Batch(t[lo:hi], {k: v[lo:hi] for k, v in ch.items()}))
        for k, v in out.samples.items():
            samples.setdefault(k, []).append(v)
        events += out.events
        statuses.append(out.status)
    assert out is not None and out.diagnosis is not None
    joined = {k: np.concatenate(v) for k, v in samples.items()}
    return state, joined, events, statuses, out.diagnosis.detail


def kinds(events):
    return [e.kind for e in events]


# ----------------------------------------------------------------------------- calibration


def test_status_is_learning_while_calibrating() -> None:
    t, ch, _ = simulate_sha_ema(1.6, seed=11)
    _, _, events, statuses, detail = run(FAST, t, ch, splits=[5_000])
    assert statuses[0].status == "learning"
    assert "calibrating" in statuses[0].reasons[0]
    assert statuses[-1].status == "ok"
    assert detail["calibration"]["state"] == "calibrated"
    assert kinds(events) == ["thresholds_calibrated"]
    ratios = [v["level_ratio"] for v in detail["calibration"]["residuals"].values()]
    assert all(0.5 < r < 1.5 for r in ratios), ratios  # the model's expected level holds


def test_fault_inside_the_calibration_window_is_flagged_and_then_detected() -> None:
    # the case that went unnoticed: R_il x0.3 inside the window inflated r7's threshold
    t, ch, _ = simulate_sha_ema(2.4, faults=[FaultSchedule("r_il", 0.8, "step", 1.5e11)], seed=4)
    _, _, events, statuses, detail = run(FAST, t, ch)
    cal = detail["calibration"]
    assert cal["state"] in ("suspicious", "refused")
    assert any(k in ("calibration_suspicious", "calibration_refused") for k in kinds(events))
    assert (
        cal["residuals"]["r7"]["excluded_segments"] > 0 or cal["residuals"]["r7"]["level_ratio"] > 3
    )
    detected = [e for e in events if e.kind == "fault_detected"]
    assert detected and detected[0].t_s < 1.25 and "r7" in detected[0].detail["residuals"]
    assert statuses[-1].status == "alert"
    assert any("calibration" in r for r in statuses[-1].reasons)
    # without the checks (ratios out of reach) the same stream is never detected
    blind = {
        "thresholds": {
            "window_s": 1.2,
            "segment_outlier_ratio": 1e9,
            "segment_peak_ratio": 1e9,
            "suspicious_ratio": 1e9,
            "refuse_ratio": 1e9,
        }
    }
    _, _, blind_events, _, blind_detail = run(blind, t, ch)
    assert blind_detail["calibration"]["state"] == "calibrated"
    assert "fault_detected" not in kinds(blind_events)


def test_fault_over_the_whole_window_is_refused_and_status_unknown() -> None:
    # present from the first sample and gone before the window ends: nothing to detect after,
    # but thresholds from this window cannot be trusted
    faults = [FaultSchedule("r_il", -1.0, "step", 1.0e11, end_s=1.1)]
    t, ch, _ = simulate_sha_ema(2.2, faults=faults, seed=5)
    _, _, events, statuses, detail = run(FAST, t, ch)
    cal = detail["calibration"]
    assert cal["state"] == "refused", cal
    assert "calibration_refused" in kinds(events)
    calibrated = next(e for e in events if e.kind == "thresholds_calibrated")
    assert calibrated.detail["source"] == "expected_level"
    assert statuses[-1].status == "unknown"
    assert "calibration refused" in statuses[-1].reasons[0]
    # the fallback thresholds are the expected level's, not the inflated window's
    r7 = detail["residuals"]["r7"]["threshold"]
    assert r7 == pytest.approx(7.0 * cal["residuals"]["r7"]["expected_rms"])


def test_reference_run_gives_thresholds_when_calibration_is_refused() -> None:
    t, ch, _ = simulate_sha_ema(1.4, seed=21)
    _, _, _, _, ref_detail = run(FAST, t, ch)
    reference = ref_detail["calibration"]["reference"]
    config = {"thresholds": {"window_s": 1.2, "reference": reference}}
    json.dumps(config)
    m.parse_config(config)
    faults = [FaultSchedule("r_il", -1.0, "step", 1.5e11)]
    t2, ch2, _ = simulate_sha_ema(1.6, faults=faults, seed=22)
    _, _, events, statuses, detail = run(config, t2, ch2)
    assert detail["calibration"]["state"] == "refused"
    assert detail["calibration"]["reference_used"]
    calibrated = next(e for e in events if e.kind == "thresholds_calibrated")
    assert calibrated.detail["source"] == "reference"
    assert calibrated.detail["thresholds"]["r7"] == pytest.approx(reference["thresholds"]["r7"])
    assert "fault_detected" in kinds(events) and statuses[-1].status == "alert"


# ----------------------------------------------------------------------------- sensor faults


def test_sensor_signature_columns_follow_the_derivative_orders() -> None:
    sig = m.SENSOR_SIGNATURES
    assert sig["sensor:f_h:bias"] == (0, 0, 0, 0, 0, 1, 0)  # F_H enters r4, r5 derived only
    assert sig["sensor:f_h:stuck"] == (0, 0, 0, 1, 1, 1, 0)
    assert sig["sensor:v_p:bias"] == (0, 0, 0, 0, 1, 1, 1)
    assert sig["sensor:p_l:bias"] == m.SIGNATURES["a_h"]  # the binary matrix cannot tell them
    sets = m.candidate_sets(
        [0, 0, 0, 0, 0, 1, 1], ["k_q", "k_c"], 1, sensor_faults=["sensor:p_l:bias"]
    )
    assert ["a_h"] in sets and ["sensor:p_l:bias"] in sets


def _sensor_run(fault: SensorFault, raw=None, seed=31, duration=2.4, splits=()):
    t, ch, _ = simulate_sha_ema(duration, seed=seed)
    ch = apply_sensor_faults(t, ch, [fault], seed=seed)
    return run(raw or FAST, t, ch, splits)


def test_pressure_bias_is_a_sensor_fault_and_parameters_are_withheld() -> None:
    # +1 bar on P_L: the seed's matrix explains it as an A_h fault
    state, samples, events, statuses, detail = _sensor_run(SensorFault("p_l", "bias", 1.4, 1e5))
    assert detail["fault_active"] and detail["coherence_vector"][5:] == [1, 1]
    assert ["sensor:p_l:bias"] in detail["candidates"] and ["a_h"] in detail["candidates"]
    iso = detail["isolation"]
    assert iso["explanation"] == "sensor", iso["hypotheses"][:3]
    assert not any(
        h["consistent"] for h in iso["hypotheses"] if not any("sensor:" in x for x in h["set"])
    )
    assert detail["parameters"] == {} and "sensor" in detail["parameters_withheld"]
    best = iso["hypotheses"][0]
    if best["set"] == ["sensor:p_l:bias"]:
        assert best["estimates"]["sensor:p_l:bias"]["bias"] == pytest.approx(1e5, rel=0.1)
    assert any("withheld" in r for r in statuses[-1].reasons)


def test_parameter_fault_keeps_its_estimates() -> None:
    t, ch, _ = simulate_sha_ema(2.4, faults=[FaultSchedule("a_h", 1.4, "step", 1.25e-3)], seed=32)
    _, _, _, _, detail = run(FAST, t, ch)
    iso = detail["isolation"]
    assert iso["explanation"] == "parameter", iso["hypotheses"][:3]
    assert iso["hypotheses"][0]["set"] == ["a_h"]
    change = iso["hypotheses"][0]["estimates"]["a_h"]["relative_change"]
    assert change == pytest.approx(1.25e-3 / 1.47e-3 - 1.0, abs=0.02)
    assert detail["parameters_withheld"] is None
    assert detail["parameters"]["a_h"]["estimate"] == pytest.approx(1.25e-3, rel=0.05)


def test_drift_is_estimated_as_a_drift() -> None:
    # a slow drift needs fault time: 0.35 s after its detection b_h is still consistent too
    # (the explanation is then "ambiguous"); 1.3 s after it only sensor faults are
    _, _, _, _, detail = _sensor_run(SensorFault("f_h", "drift", 1.3, -15.0), duration=3.4)
    iso = detail["isolation"]
    assert iso["explanation"] == "sensor"
    best = iso["hypotheses"][0]
    assert best["set"] == ["sensor:f_h:drift"]
    assert best["estimates"]["sensor:f_h:drift"]["drift_per_s"] == pytest.approx(-15.0, rel=0.15)


def test_stuck_sensor_is_flagged_and_stops_the_filters() -> None:
    fault = SensorFault("p_l", "stuck", 1.4)
    state, samples, events, _, detail = _sensor_run(fault, duration=2.0)
    assert detail["sensor_flags"] == {"p_l": "stuck"}
    assert detail["isolation"]["explanation"] == "sensor"
    assert detail["candidates"][0] == ["sensor:p_l:stuck"]
    assert any(e.detail.get("new_sensor_flags") == {"p_l": "stuck"} for e in events)
    assert all(v.get("withheld") for v in detail["subsystems"].values())
    assert np.isnan(samples["s7_r_il"][-100:]).all()
    # without the sensor checks nothing says the sensor is stuck
    off = {**FAST, "sensors": {"enabled": False}}
    _, _, _, _, detail_off = _sensor_run(fault, raw=off, duration=2.0)
    assert detail_off["sensor_flags"] == {}


def test_noisy_sensor_is_flagged() -> None:
    _, _, _, _, detail = _sensor_run(SensorFault("v_p", "noise", 1.4, 4.0), duration=3.2)
    assert detail["sensor_flags"] == {"v_p": "noisy"}
    assert detail["isolation"]["explanation"] == "sensor"


def test_fault_free_run_has_no_sensor_flag_or_detection() -> None:
    t, ch, _ = simulate_sha_ema(3.0, seed=33)
    _, _, events, statuses, detail = run(FAST, t, ch)
    assert kinds(events) == ["thresholds_calibrated"]
    assert detail["sensor_flags"] == {} and detail["isolation"] is None
    assert statuses[-1].status == "ok"


def test_split_invariance_with_sensor_checks_and_fit() -> None:
    t, ch, _ = simulate_sha_ema(2.2, faults=[FaultSchedule("b_h", 1.3, "step", 5e3)], seed=34)
    ch = apply_sensor_faults(t, ch, [SensorFault("v", "stuck", 1.6)], seed=34)
    ref_state, ref, ref_events, _, ref_detail = run(FAST, t, ch)
    splits = sorted({1, 7, 1_000, 11_999, 12_000, 12_001, 13_005, 16_000, 16_003, 19_000})
    state, got, events, _, detail = run(FAST, t, ch, splits)
    for name in ref:
        np.testing.assert_array_equal(got[name], ref[name], err_msg=name)
    assert events == ref_events and detail == ref_detail
    for name in m._ARRAYS:
        np.testing.assert_array_equal(getattr(state, name), getattr(ref_state, name))


# ----------------------------------------------------------------------------- contract


def test_config_model_schema_and_round_trip() -> None:
    schema = m.CONFIG_MODEL.model_json_schema()
    json.dumps(schema)
    assert "thresholds" in schema["properties"] and "sensors" in schema["properties"]
    config = m.parse_config({"thresholds": {"values": {r: 1.0 for r in m.RESIDUALS}}})
    assert config.thresholds.rule == "fixed"
    d = m.config_to_dict(config)
    assert m.parse_config(json.loads(json.dumps(d))) == config
    assert d["sensors"]["stuck_s"] == 0.1 and d["sensors"]["noise_persist_s"] == 1.0
    assert d["isolation"]["min_fit_s"] == 0.3


def test_version_1_state_loads_and_steps() -> None:
    # dumped by the version-1 code: differentiator 0.01 s, 0.5 s window, R_il x0.3 from 0.7 s
    config = m.parse_config({"differentiator_window_s": 0.01, "thresholds": {"window_s": 0.5}})
    blob = (DATA / "darr_fekf_state_v1.bin").read_bytes()
    assert json.loads(blob)["version"] == 1
    state = m.load_state(blob)
    assert state.version == m.STATE_VERSION and state.fault_active
    assert state.value("calibration_state") == 1.0  # calibrated (unchecked)
    np.testing.assert_array_equal(m.load_state(m.dump_state(state)).scalars, state.scalars)
    t, ch, _ = simulate_sha_ema(
        0.2, faults=[FaultSchedule("r_il", 0.0, "step", 1.5e11)], seed=3, t0_s=1.0
    )
    state2, out = m.step(config, state, Batch(t, ch))
    assert state2.t_last_s == pytest.approx(t[-1])
    assert np.isfinite(out.samples["r7"]).all() and state2.fault_active
    assert (
        out.diagnosis is not None and out.diagnosis.detail["calibration"]["state"] == "calibrated"
    )
    bad = blob.replace(b'"version":1', b'"version":0')
    with pytest.raises(StateVersionError):
        m.load_state(bad)
    assert state2.value("fit_samples") > 0  # the fit runs on the upgraded state


def test_plant_transient_is_not_taken_for_sensor_noise() -> None:
    # an f_r step excites the screw's stiff mode: F_C's third differences rise to 20x the
    # noise for about 0.4 s; the noise check's persistence (1 s) keeps that from flagging the
    # sensor, a 0.3 s persistence does not
    t, ch, _ = simulate_sha_ema(4.2, faults=[FaultSchedule("f_r", 2.2, "step", 1.5e4)], seed=36)
    _, _, _, _, detail = run(FAST, t, ch)
    assert detail["sensor_flags"] == {}
    assert detail["isolation"]["explanation"] == "parameter"
    assert detail["isolation"]["hypotheses"][0]["set"] == ["f_r"]
    hasty = {**FAST, "sensors": {"noise_persist_s": 0.3}}
    _, _, _, _, hasty_detail = run(hasty, t, ch)
    assert hasty_detail["sensor_flags"] == {"f_c": "noisy"}
    assert hasty_detail["isolation"]["explanation"] == "sensor"


@pytest.mark.parametrize("channel", ["f_h", "p_l"])
def test_white_noise_increase_below_the_general_level_is_flagged(channel) -> None:
    # extra white noise of 1.0 sd doubles the noise variance, below the general level 2.5: the
    # lower level for white increases flags it, the general level alone does not; the f_r
    # transient above (not white) stays unflagged under the lower level
    fault = SensorFault(channel, "noise", 1.4, 1.0)
    _, _, _, _, detail = _sensor_run(fault, seed=41, duration=3.4)
    assert detail["sensor_flags"] == {channel: "noisy"}
    general_only = {**FAST, "sensors": {"white_noise_ratio": 2.5}}
    _, _, _, _, detail_off = _sensor_run(fault, raw=general_only, seed=41, duration=3.4)
    assert detail_off["sensor_flags"] == {}


def test_third_difference_lag1_correlation_of_white_noise() -> None:
    # the statistic the white-noise test reads: -0.75 for white noise, near cos(w dt) for a
    # sinusoid, whatever the amplitude
    rng = np.random.default_rng(5)
    x = rng.standard_normal(200_000)
    e = x[3:] - 3 * x[2:-1] + 3 * x[1:-2] - x[:-3]
    assert np.mean(e[1:] * e[:-1]) / np.mean(e * e) == pytest.approx(kern.WHITE_LAG1, abs=0.01)
    s = 1e3 * np.sin(2.0 * np.arange(20_000))
    e = s[3:] - 3 * s[2:-1] + 3 * s[1:-2] - s[:-3]
    assert np.mean(e[1:] * e[:-1]) / np.mean(e * e) == pytest.approx(math.cos(2.0), abs=0.01)


def test_version_2_state_loads_and_steps() -> None:
    # dumped by the version-2 code: differentiator 0.01 s, 0.5 s window, R_il x0.3 from 0.7 s
    config = m.parse_config({"differentiator_window_s": 0.01, "thresholds": {"window_s": 0.5}})
    blob = (DATA / "darr_fekf_state_v2.bin").read_bytes()
    assert json.loads(blob)["version"] == 2
    state = m.load_state(blob)
    assert state.version == m.STATE_VERSION and state.fault_active
    var = state.part("sensor_noise_var")
    np.testing.assert_array_equal(state.part("sensor_noise_lag1"), kern.WHITE_LAG1 * var)
    t, ch, _ = simulate_sha_ema(
        0.2, faults=[FaultSchedule("r_il", 0.0, "step", 1.5e11)], seed=3, t0_s=1.0
    )
    state2, out = m.step(config, state, Batch(t, ch))
    assert state2.fault_active and np.isfinite(out.samples["r7"]).all()
    assert np.all(np.isfinite(state2.part("sensor_last_third_difference")[:7]))
