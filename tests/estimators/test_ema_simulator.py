"""EMA simulator: determinism, physics (eqs. 13-14), interference."""

from __future__ import annotations

import math

import numpy as np
import pytest

from estimators.simulators.ema_motor import NEWTON_PER_LBF, simulate_ema


def test_seeded_and_deterministic() -> None:
    a = simulate_ema(duration_s=2.0, seed=3)
    b = simulate_ema(duration_s=2.0, seed=3)
    c = simulate_ema(duration_s=2.0, seed=4)
    np.testing.assert_array_equal(a.voltage_measured_v, b.voltage_measured_v)
    np.testing.assert_array_equal(a.current_a, b.current_a)
    assert not np.array_equal(a.voltage_measured_v, c.voltage_measured_v)
    # the plant does not depend on the seed, only the sensors do
    np.testing.assert_array_equal(a.voltage_true_v, c.voltage_true_v)
    assert a.t_s.shape == (2000,)
    assert a.t_s[1] - a.t_s[0] == pytest.approx(1e-3)


def test_sample_rate_is_configurable() -> None:
    run = simulate_ema(duration_s=3.0, sample_rate_hz=100.0)
    assert run.t_s.shape == (300,)
    assert np.allclose(np.diff(run.t_s), 0.01)


@pytest.mark.parametrize("load_lbs", [-40.0, 40.0])
def test_true_signals_satisfy_the_motor_equations(load_lbs: float) -> None:
    # sample at the control rate so finite differences resolve the electrical time constant
    run = simulate_ema(
        duration_s=1.0, sample_rate_hz=20_000.0, control_rate_hz=20_000.0, load_lbs=load_lbs
    )
    p = run.params
    dt = run.t_s[1] - run.t_s[0]
    i, w, v = run.current_true_a, run.speed_rad_s, run.voltage_true_v
    # eq. 13 over one step (trapezoidal average; v is held over the step)
    i_mid, w_mid = 0.5 * (i[1:] + i[:-1]), 0.5 * (w[1:] + w[:-1])
    lhs13 = v[:-1]
    rhs13 = p.ke_v_s_rad * w_mid + p.resistance_ohm * i_mid + p.inductance_h * np.diff(i) / dt
    assert np.sqrt(np.mean((lhs13 - rhs13) ** 2)) < 0.01 * np.std(v)
    # eq. 14 with the ball-screw load torque
    t_ex = load_lbs * NEWTON_PER_LBF * p.lead_m / (2 * math.pi * p.screw_efficiency)
    lhs14 = p.kt_nm_a * i_mid - t_ex
    rhs14 = p.damping_nm_s_rad * w_mid + p.inertia_kg_m2 * np.diff(w) / dt
    assert np.sqrt(np.mean((lhs14 - rhs14) ** 2)) < 0.01 * np.std(lhs14)


def test_controller_tracks_the_profile_and_load_shifts_current() -> None:
    neg = simulate_ema(duration_s=4.0, load_lbs=-40.0)
    pos = simulate_ema(duration_s=4.0, load_lbs=40.0)
    for run in (neg, pos):
        assert np.max(np.abs(run.position_m - run.position_ref_m)) < 0.1 * run.params.amplitude_m
        assert np.max(np.abs(run.voltage_true_v)) <= run.params.supply_v
    # the load torque needs a mean current of +-T_ex / Kt
    p = pos.params
    i_load = 40.0 * NEWTON_PER_LBF * p.lead_m / (2 * math.pi * p.screw_efficiency) / p.kt_nm_a
    assert np.mean(pos.current_true_a) == pytest.approx(i_load, rel=0.05)
    assert np.mean(neg.current_true_a) == pytest.approx(-i_load, rel=0.05)


def test_interference_has_the_configured_parts() -> None:
    spiky = simulate_ema(
        duration_s=20.0, seed=1, voltage_noise_v=0.0, spike_rate_hz=5.0, periodic_amplitude_v=0.0
    )
    spikes = spiky.voltage_measured_v - spiky.voltage_true_v
    hits = spikes != 0.0
    assert 70 < hits.sum() < 130  # Poisson, mean 5/s x 20 s = 100, std 10
    assert np.all((np.abs(spikes[hits]) >= 4.0) & (np.abs(spikes[hits]) <= 12.0))
    gauss = simulate_ema(duration_s=20.0, seed=1, spike_rate_hz=0.0, periodic_amplitude_v=0.0)
    noise = gauss.voltage_measured_v - gauss.voltage_true_v
    assert np.std(noise) == pytest.approx(1.0, rel=0.03)
    assert abs(np.mean(noise)) < 0.03
    quiet = simulate_ema(
        duration_s=2.0, voltage_noise_v=0.0, spike_rate_hz=0.0, periodic_amplitude_v=1.5
    )
    tone = quiet.voltage_measured_v - quiet.voltage_true_v
    assert np.max(np.abs(tone)) == pytest.approx(1.5, rel=0.01)
    assert np.sqrt(np.mean(tone**2)) == pytest.approx(1.5 / math.sqrt(2), rel=0.02)


def test_trapezoid_profile_has_dwells() -> None:
    run = simulate_ema(duration_s=2.0, profile="trapezoid")
    ref = run.position_ref_m
    flat = np.isclose(np.abs(ref), run.params.amplitude_m)
    assert 0.2 < flat.mean() < 0.6


def test_unknown_parameter_is_refused() -> None:
    with pytest.raises(ValueError, match="bogus"):
        simulate_ema(duration_s=1.0, bogus=1.0)
    with pytest.raises(ValueError, match="profile"):
        simulate_ema(duration_s=1.0, profile="square")


def test_sweep_profile_rises_in_frequency() -> None:
    run = simulate_ema(
        duration_s=20.0,
        sample_rate_hz=1000.0,
        profile="sweep",
        frequency_hz=0.5,
        sweep_end_frequency_hz=3.0,
        amplitude_m=0.005,
    )
    ref = run.position_ref_m
    crossings = np.flatnonzero(np.diff(np.sign(ref)) != 0)
    # zero crossings of a linear chirp: 2 (f0 t + (f1 - f0) t^2 / 2T) in [0, t]
    first, last = run.t_s < 5.0, run.t_s >= 15.0
    n_first = np.sum(first[crossings])
    n_last = np.sum(last[crossings])
    assert n_first == pytest.approx(2 * (0.5 * 5 + 2.5 * 25 / 40), abs=1)
    assert n_last == pytest.approx(2 * (0.5 * 5 + 2.5 * (400 - 225) / 40), abs=1)
    # the position loop follows, lagging more as the frequency rises
    err = np.abs(run.position_m - ref)
    assert np.max(err[first]) < 0.1 * run.params.amplitude_m
    assert np.max(err) < 0.3 * run.params.amplitude_m


def test_voltage_sensor_clips_at_its_limits() -> None:
    run = simulate_ema(
        duration_s=6.0,
        sample_rate_hz=100.0,
        profile="sweep",
        frequency_hz=0.3,
        sweep_end_frequency_hz=3.0,
        voltage_clip_low_v=-25.3,
        voltage_clip_high_v=23.9,
    )
    v = run.voltage_measured_v
    assert v.min() == -25.3 and v.max() == 23.9
    assert np.max(np.abs(run.voltage_true_v)) > 25.3  # the true voltage goes past the clip
    free = (v > -25.3) & (v < 23.9)
    unclipped = simulate_ema(
        duration_s=6.0,
        sample_rate_hz=100.0,
        profile="sweep",
        frequency_hz=0.3,
        sweep_end_frequency_hz=3.0,
    )
    np.testing.assert_array_equal(v[free], unclipped.voltage_measured_v[free])
