"""Friction-drive simulator: against an independent ODE solver, the seed's deterioration law,
the analytic equilibrium, and its interface (channels, noise, wear-rate changes, early stop)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from estimators.registry import ACTUATOR_KINDS
from estimators.simulators.friction_drive import (
    PAPER_NOISE_STD,
    FrictionDriveParams,
    SquareWave,
    first_crossing_time,
    simulate_friction_drive,
)

P = FrictionDriveParams()


def _rhs(t: float, x: np.ndarray, current: float, m: float, p: FrictionDriveParams) -> list[float]:
    w1, w2, al = x
    dv = p.r1_m * w1 - p.r2_m * w2
    return [
        (-al * p.r1_m * dv - p.b1_nm_s * w1 + p.km_nm_a * current) / p.j1_kg_m2,
        (al * p.r2_m * dv - p.b2_nm_s * w2) / p.j2_kg_m2,
        -m * dv * dv * al,
    ]


@pytest.mark.parametrize(("alpha0", "m"), [(10.0, 0.01), (3.0, 0.05), (25.0, 0.002)])
def test_matches_an_adaptive_ode_solver(alpha0: float, m: float) -> None:
    """Sample by sample against scipy's DOP853 at rtol 1e-11 with the same zero-order-hold
    current; RK4 at h |lambda| <= 0.05 has a local error near 1e-9 of the state, so 1e-7
    relative on the speeds (which reach ~140 rad/s) and alpha is a safe bound."""
    fs = 1000.0
    t, _, truth = simulate_friction_drive(3.0, fs, alpha0=alpha0, m=m, noise=(0.0, 0.0))
    x = np.array([0.0, 0.0, alpha0])
    ref = np.empty((len(t), 3))
    for k in range(len(t)):
        ref[k] = x
        sol = solve_ivp(
            _rhs,
            (t[k], t[k] + 1.0 / fs),
            x,
            method="DOP853",
            rtol=1e-11,
            atol=1e-12,
            args=(truth["current"][k], m, P),
        )
        x = sol.y[:, -1]
    np.testing.assert_allclose(truth["w1"], ref[:, 0], rtol=1e-7, atol=1e-7)
    np.testing.assert_allclose(truth["w2"], ref[:, 1], rtol=1e-7, atol=1e-7)
    np.testing.assert_allclose(truth["alpha"], ref[:, 2], rtol=1e-9)


def test_alpha_follows_the_dissipated_energy_law() -> None:
    """Seed eqs. 5-6: alpha(t) = alpha(0) - m D(t), D = int alpha dv^2 dt (trapezoid on a 10 kHz
    grid: error O(h^2) on a smooth integrand, ~1e-6 relative here)."""
    t, _, tr = simulate_friction_drive(8.0, 10_000.0, m=0.01, noise=(0.0, 0.0))
    dv = P.r1_m * tr["w1"] - P.r2_m * tr["w2"]
    power = tr["alpha"] * dv**2
    energy = np.concatenate([[0.0], np.cumsum(0.5 * (power[1:] + power[:-1]) * np.diff(t))])
    np.testing.assert_allclose(tr["alpha"], 10.0 - 0.01 * energy, rtol=1e-6)
    np.testing.assert_allclose(tr["dn"], 1.0 - tr["alpha"] / 10.0, rtol=1e-12)
    assert np.all(np.diff(tr["alpha"]) <= 0.0)


def test_constant_current_reaches_the_analytic_equilibrium() -> None:
    """With m = 0, alpha stays constant and the speeds settle at -A(alpha)^-1 B I (seed eqs.
    3-4); the slowest mode is about 0.3 s, so 20 s leave e^-60 of the transient."""
    alpha, current = 7.0, 12.0
    _, _, tr = simulate_friction_drive(
        20.0, 500.0, alpha0=alpha, m=0.0, current=current, noise=(0.0, 0.0)
    )
    a = np.array(
        [
            [-(alpha * P.r1_m**2 + P.b1_nm_s) / P.j1_kg_m2, alpha * P.r1_m * P.r2_m / P.j1_kg_m2],
            [alpha * P.r1_m * P.r2_m / P.j2_kg_m2, -(alpha * P.r2_m**2 + P.b2_nm_s) / P.j2_kg_m2],
        ]
    )
    x_eq = -np.linalg.solve(a, [P.km_nm_a * current / P.j1_kg_m2, 0.0])
    np.testing.assert_allclose([tr["w1"][-1], tr["w2"][-1]], x_eq, rtol=1e-9)
    assert np.all(tr["alpha"] == alpha)


def test_channels_noise_and_reproducibility() -> None:
    t, ch, tr = simulate_friction_drive(10.0, 1000.0, seed=4, current_noise_a=0.1)
    assert tuple(ch) == ACTUATOR_KINDS["friction_drive"].channels
    assert len(t) == 10_000 and np.allclose(np.diff(t), 1e-3)
    # noise std within 3 standard errors of a 10,000-sample std estimate (~0.7 % each)
    for name, key, std in (
        ("motor_speed", "w1", PAPER_NOISE_STD[0]),
        ("wheel_speed", "w2", PAPER_NOISE_STD[1]),
        ("current", "current", 0.1),
    ):
        resid = ch[name] - tr[key]
        assert np.std(resid) == pytest.approx(std, rel=0.025)
        assert abs(np.mean(resid)) < 4.0 * std / np.sqrt(len(t))
    t2, ch2, _ = simulate_friction_drive(10.0, 1000.0, seed=4, current_noise_a=0.1)
    for name in ch:
        np.testing.assert_array_equal(ch[name], ch2[name])
    np.testing.assert_array_equal(t, t2)


def test_square_wave_and_current_forms() -> None:
    wave = SquareWave(high_a=15.0, low_a=-5.0, period_s=3.0, duty=0.3, t0_s=1.0)
    t = np.arange(0.0, 7.0, 0.5)
    # high on [1, 1.9) and [4, 4.9)
    expected = [-5, -5, 15, 15, -5, -5, -5, -5, 15, 15, -5, -5, -5, -5]
    np.testing.assert_array_equal(wave.at(t), expected)
    _, _, tr = simulate_friction_drive(1.0, 100.0, current=3.5)
    assert np.all(tr["current"] == 3.5)
    profile = np.linspace(0.0, 10.0, 100)
    _, _, tr = simulate_friction_drive(1.0, 100.0, current=profile)
    np.testing.assert_array_equal(tr["current"], profile)
    with pytest.raises(ValueError, match="100 values"):
        simulate_friction_drive(1.0, 100.0, current=np.zeros(5))


def test_wear_rate_changes_and_drift() -> None:
    t, _, tr = simulate_friction_drive(
        4.0, 100.0, m=0.01, m_changes=[(2.0, 0.03)], m_drift_per_s=0.001
    )
    np.testing.assert_allclose(tr["m"][t < 2.0], 0.01 + 0.001 * t[t < 2.0])
    np.testing.assert_allclose(tr["m"][t >= 2.0], 0.03 + 0.001 * t[t >= 2.0])


def test_stop_at_dn_and_crossing_time() -> None:
    t, ch, tr = simulate_friction_drive(1000.0, 1000.0, m=0.02, stop_dn=0.3)
    assert tr["dn"][-1] >= 0.3 > tr["dn"][-2]
    assert all(len(v) == len(t) for v in (*ch.values(), *tr.values()))
    tc = first_crossing_time(t, tr["dn"], 0.3)
    assert tc is not None and t[-2] <= tc <= t[-1]
    assert first_crossing_time(t, tr["dn"], 0.9) is None
    assert first_crossing_time(np.array([0.0, 1.0]), np.array([0.0, 2.0]), 0.5) == 0.25
