"""Deterioration EKF: filterpy equivalence, the seed's scenario, covariance health over 10^6
steps, health windows, events, RUL contract, batch-split invariance, state, configuration."""

from __future__ import annotations

import json
import math
from typing import Any

import numpy as np
import pytest
from filterpy.kalman import ExtendedKalmanFilter
from scipy.linalg import expm

from estimators import deterioration_ekf as de
from estimators.base import (
    Batch,
    ConfigError,
    EstimatorError,
    OutOfOrderError,
    RulEstimate,
    StateVersionError,
)
from estimators.kernels import dekf_kernels as kern
from estimators.simulators.friction_drive import FrictionDriveParams, simulate_friction_drive

PARAMS = FrictionDriveParams()
#: a tuning with a small random walk on m, suited to a constant wear rate (see the docs)
PROGNOSIS_Q = [0.0, 0.0, 0.0, 1e-12]
#: the seed's filter (section 4.2, 5.2): known alpha0, held input, fixed R and Q, no gating
SEED: dict[str, Any] = {
    "alpha0": 10.0,
    "input_model": "hold",
    "plant_calibration": False,
    "covariance_scaling": False,
    "noise_adaptation": False,
    "gate_sigma": None,
    "m_walk_rel": 0.0,
    "q_diag": [0.0, 0.0, 0.0, 0.02**2 / 12.0],
}


def seed_config(raw: dict[str, Any]) -> de.DekfConfig:
    """The seed's filter with ``raw`` on top."""
    return de.parse_config({**SEED, **raw})


def batch_of(t: np.ndarray, ch: dict[str, np.ndarray], lo: int = 0, hi: int | None = None) -> Batch:
    return Batch(t_s=t[lo:hi], channels={k: v[lo:hi] for k, v in ch.items()})


def run(
    config: de.DekfConfig, t: np.ndarray, ch: dict[str, np.ndarray], splits: list[int] | None = None
) -> tuple[de.DekfState, dict[str, np.ndarray], list[Any], list[Any], list[RulEstimate]]:
    """The estimator over the data in one batch or cut at the given split points."""
    state = de.initial_state(config)
    bounds = [0, *(splits or []), len(t)]
    samples: dict[str, list[np.ndarray]] = {name: [] for name in de.SAMPLE_OUTPUTS}
    health, events, ruls = [], [], []
    for lo, hi in zip(bounds[:-1], bounds[1:], strict=True):
        state, out = de.step(config, state, batch_of(t, ch, lo, hi))
        for name in de.SAMPLE_OUTPUTS:
            samples[name].append(out.samples[name])
        health.extend(out.health)
        events.extend(out.events)
        ruls.extend(out.rul)
    return state, {k: np.concatenate(v) for k, v in samples.items()}, health, events, ruls


# ----------------------------------------------------------------------------- filterpy


def _model(x: np.ndarray, u: float, f44: float) -> tuple[np.ndarray, np.ndarray]:
    """Drift f(x) + B u and the Jacobian of seed eq. 19 (with F44)."""
    p = PARAMS
    w1, w2, al, m = x
    dv = p.r1_m * w1 - p.r2_m * w2
    f = np.array(
        [
            (-al * p.r1_m * dv - p.b1_nm_s * w1 + p.km_nm_a * u) / p.j1_kg_m2,
            (al * p.r2_m * dv - p.b2_nm_s * w2) / p.j2_kg_m2,
            -m * dv * dv * al,
            0.0,
        ]
    )
    jac = np.array(
        [
            [-(al * p.r1_m**2 + p.b1_nm_s) / p.j1_kg_m2, al * p.r1_m * p.r2_m / p.j1_kg_m2,
             -p.r1_m * dv / p.j1_kg_m2, 0.0],
            [al * p.r1_m * p.r2_m / p.j2_kg_m2, -(al * p.r2_m**2 + p.b2_nm_s) / p.j2_kg_m2,
             p.r2_m * dv / p.j2_kg_m2, 0.0],
            [-2 * al * m * p.r1_m * dv, 2 * al * m * p.r2_m * dv, -m * dv * dv, -al * dv * dv],
            [0.0, 0.0, 0.0, f44],
        ]
    )  # fmt: skip
    return f, jac


class ReferenceEKF(ExtendedKalmanFilter):  # type: ignore[misc]
    """filterpy's EKF with the discretization of the estimator done by scipy's expm:
    ``Phi = expm(F dt)`` for the covariance and ``x + Gamma f(x)``, ``Gamma = int expm(F s) ds``
    (from the augmented matrix [[F, I], [0, 0]], F44 = 0) for the state."""

    def set_step(self, u: float, dt: float, f44: float) -> None:
        x = self.x[:, 0]
        f, jac = _model(x, u, f44)
        jac_state = jac.copy()
        jac_state[3, 3] = 0.0
        aug = np.zeros((8, 8))
        aug[:4, :4] = jac_state
        aug[:4, 4:] = np.eye(4)
        gamma = expm(aug * dt)[:4, 4:]
        self.F = expm(jac * dt)
        self._x_next = (x + gamma @ f)[:, None]

    def predict_x(self, u: Any = 0) -> None:
        self.x = self._x_next


def filterpy_reference(
    config: de.DekfConfig, t: np.ndarray, ch: dict[str, np.ndarray]
) -> dict[str, np.ndarray]:
    ekf = ReferenceEKF(dim_x=4, dim_z=2)
    ekf.x = np.array([[config.w1_0], [config.w2_0], [config.alpha0], [config.m0]])
    ekf.P = np.diag(config.p0_diag)
    ekf.Q = np.diag(config.q_diag)
    r = np.diag(config.r_diag)
    n = len(t)
    out = {k: np.full(n, np.nan) for k in ("w1", "alpha", "m", "e1", "e2", "nis", "p22", "p33")}
    u_held = 0.0
    for k in range(n):
        if k > 0:
            ekf.set_step(u_held, t[k] - t[k - 1], config.f44)
            ekf.predict()
        z = np.array([ch["motor_speed"][k], ch["wheel_speed"][k]])
        have = np.isfinite(z)
        if have.any():
            h = np.eye(4)[:2][have]
            ekf.update(
                z[have][:, None], lambda _x, h=h: h, lambda x, h=h: h @ x, R=r[np.ix_(have, have)]
            )
            e = ekf.y[:, 0]
            # NIS from the innovation and its covariance (not filterpy's likelihood helpers)
            out["nis"][k] = float(e @ np.linalg.solve(ekf.S, e))
            full = np.full(2, np.nan)
            full[have] = e
            out["e1"][k], out["e2"][k] = full
        out["w1"][k] = ekf.x[0, 0]
        out["alpha"][k] = ekf.x[2, 0]
        out["m"][k] = ekf.x[3, 0]
        out["p22"][k] = ekf.P[2, 2]
        out["p33"][k] = ekf.P[3, 3]
        if np.isfinite(ch["current"][k]):
            u_held = ch["current"][k]
    out["P"] = ekf.P
    return out


@pytest.mark.parametrize(
    ("seed", "extra", "irregular"),
    [
        (0, {}, False),
        (1, {"f44": -100.0}, False),
        (2, {"q_diag": [1e-6, 1e-8, 1e-9, 1e-12], "p0_diag": [1e-2, 1e-3, 1e-2, 1e-5]}, True),
    ],
)
def test_matches_filterpy_sample_by_sample(
    seed: int, extra: dict[str, Any], irregular: bool
) -> None:
    """Against filterpy's ExtendedKalmanFilter (Joseph update) driven by scipy's expm, with
    missing speeds (each alone and both) and currents, and uneven sample spacing.

    Tolerances: the Taylor series of the discretization stops at a remainder bound of 1e-9
    (the default ``expm_tol``, per entry of the speed block, relative to balanced scales
    elsewhere) and both sides round differently. Measured over 2500 steps: speeds within 1.7e-12
    relative, alpha and m within 1.1e-6 of their own standard deviation, innovations within 6e-7
    of sqrt(S) (an innovation is a difference of two ~100 rad/s numbers, so its relative error
    is large where it is near 0), NIS within 5e-6 relative, covariances within 9e-11 relative.
    The bounds leave a factor >= 10."""
    t, ch, _ = simulate_friction_drive(2.5, 1000.0, seed=seed, m_changes=[(1.5, 0.02)])
    rng = np.random.default_rng(seed)
    if irregular:
        t = t + rng.uniform(-3e-4, 3e-4, len(t))
        t[0] = 0.0
    for name, frac in (("motor_speed", 0.03), ("wheel_speed", 0.03), ("current", 0.01)):
        ch[name][rng.random(len(t)) < frac] = np.nan
    config = seed_config(
        {"w1_0": 0.0, "w2_0": 0.0, "rul_every_s": None, "nonnegative": False, **extra}
    )
    state, s, _, _, _ = run(config, t, ch)
    ref = filterpy_reference(config, t, ch)
    np.testing.assert_allclose(s["w1"], ref["w1"], rtol=2e-11)
    sig_alpha = np.sqrt(ref["p22"])
    sig_m = np.sqrt(ref["p33"])
    assert np.max(np.abs(s["alpha"] - ref["alpha"]) / sig_alpha) < 1e-5
    assert np.max(np.abs(s["m"] - ref["m"]) / sig_m) < 1e-5
    for name, key in (("innovation_w1", "e1"), ("innovation_w2", "e2")):
        np.testing.assert_array_equal(np.isnan(s[name]), np.isnan(ref[key]))
        sd = s[f"{name}_3sigma"] / 3.0
        assert np.nanmax(np.abs(s[name] - ref[key]) / sd) < 1e-5
    np.testing.assert_allclose(s["nis"], ref["nis"], rtol=5e-5, atol=1e-8)
    np.testing.assert_allclose((s["alpha_3sigma"] / 3) ** 2, ref["p22"], rtol=1e-9)
    np.testing.assert_allclose((s["m_3sigma"] / 3) ** 2, ref["p33"], rtol=1e-9)
    scale = np.sqrt(np.outer(np.diag(ref["P"]), np.diag(ref["P"])))
    np.testing.assert_allclose(state.P / scale, ref["P"] / scale, atol=1e-9)
    # both NaN: predict only, so no innovation
    both = np.isnan(ch["motor_speed"]) & np.isnan(ch["wheel_speed"])
    assert np.all(np.isnan(s["nis"][both]))


@pytest.mark.parametrize("tol", [1e-12, 1e-9])
def test_taylor_discretization_matches_expm(tol: float) -> None:
    """The compiled discretization against scipy's expm on states up to 150 rad/s and steps up
    to 0.5 s (scaling and squaring engaged), with and without F44. The remainder bound ``tol``
    holds in balanced scales; 1000 tol relative per entry leaves room for the rescaling."""
    rng = np.random.default_rng(3)
    rtol = 1e3 * tol
    for _ in range(40):
        x = np.array([rng.uniform(0, 150), rng.uniform(0, 13), rng.uniform(0.5, 20), 0.01])
        u, dt = rng.uniform(-20, 20), 10 ** rng.uniform(-4, -0.3)
        for f44 in (0.0, -100.0):
            cfg = seed_config({"f44": f44, "expm_tol": tol}).kernel_vector
            got = kern.discretize(cfg, *x, u, dt)
            f, jac = _model(x, u, f44)
            phi = expm(jac * dt)
            scale = np.abs(phi[:3, :3]).max()
            np.testing.assert_allclose(
                np.reshape(got[:9], (3, 3)), phi[:3, :3], rtol=rtol, atol=rtol * scale
            )
            np.testing.assert_allclose(
                got[9:12], phi[:3, 3], rtol=rtol, atol=rtol * np.abs(phi[:3, 3]).max()
            )
            assert got[12] == pytest.approx(phi[3, 3], rel=1e-12)
            jac[3, 3] = 0.0
            aug = np.zeros((8, 8))
            aug[:4, :4] = jac
            aug[:4, 4:] = np.eye(4)
            gamma = expm(aug * dt)[:4, 4:]
            dx = gamma @ f
            np.testing.assert_allclose(got[13:16], dx[:3], rtol=rtol, atol=rtol * np.abs(dx).max())
            gb = gamma[:3, 0] * PARAMS.km_nm_a / PARAMS.j1_kg_m2
            np.testing.assert_allclose(got[16:19], gb, rtol=rtol, atol=rtol * np.abs(gb).max())


def _tail_bound(theta: float, order: int) -> float:
    """Remainder bound of phi1 truncated at ``order`` for ||X|| <= theta (taylor_order's)."""
    return theta ** (order + 1) / math.factorial(order + 2) / (1.0 - theta / (order + 3))


@pytest.mark.parametrize("tol", [1e-5, 1e-7, 1e-9])
def test_series_order_meets_its_balanced_bound(tol: float) -> None:
    """The series order against a high-order reference (scipy's expm) at steps that need no
    halving: with D = diag(1, sqrt(J1 / J2), b) and theta the 1-norm of D^-1 G dt D, the order
    N meets theta^(N+1) / (N+2)! / (1 - theta / (N+3)) <= tol min(d1, 1 / d1); E is within
    theta times that bound in the balanced scales and each speed entry of Gamma / dt (its first
    column, the current's) within tol. At the bench's operating points (1 kHz, alpha near 10)
    the order is below the one the plain 1-norm would need at tol."""
    rng = np.random.default_rng(11)
    cfg = seed_config({"expm_tol": tol}).kernel_vector
    d1 = math.sqrt(cfg[kern.CFG_INV_J2] / cfg[kern.CFG_INV_J1])
    tol_bal = tol * min(d1, 1.0 / d1)
    kb = PARAMS.km_nm_a / PARAMS.j1_kg_m2
    states = [
        (np.array([30.0, 2.7, 9.9, 5e-4]), 0.0, 1e-3),
        (np.array([90.0, 8.0, 10.0, 0.01]), 20.0, 1e-3),
    ]
    for _ in range(40):
        x = np.array([rng.uniform(0, 150), rng.uniform(0, 13), rng.uniform(0.5, 20), 0.01])
        states.append((x, rng.uniform(-20, 20), 10 ** rng.uniform(-4, -2.5)))
    for i, (x, u, dt) in enumerate(states):
        got = kern.discretize(cfg, *x, u, dt)
        order, halvings = int(got[19]), int(got[20])
        if halvings:
            continue
        _, jac = _model(x, u, 0.0)
        g = jac[:3, :3]
        b = math.sqrt(
            (abs(g[2, 0]) + d1 * abs(g[2, 1])) / (abs(g[0, 2]) + abs(g[1, 2]) / d1)
        )
        d = np.diag([1.0, d1, b])
        di = np.linalg.inv(d)
        theta = np.abs(di @ g @ d * dt).sum(axis=0).max()
        assert _tail_bound(theta, order) <= tol_bal
        e_ref = expm(g * dt)
        aug = np.zeros((6, 6))
        aug[:3, :3] = g * dt
        aug[:3, 3:] = np.eye(3) * dt
        gamma = expm(aug)[:3, 3:]
        err_e = np.abs(di @ (np.reshape(got[:9], (3, 3)) - e_ref) @ d).sum(axis=0).max()
        assert err_e <= theta * tol_bal + 1e-14
        err_g = np.abs(np.asarray(got[16:18]) / kb - gamma[:2, 0]) / dt
        assert np.all(err_g <= tol + 1e-14)
        if i < 2:
            assert order < kern.taylor_order(np.abs(g * dt).sum(axis=0).max(), tol)


# ----------------------------------------------------------------------------- seed scenario


def test_paper_scenario_alpha_bounds_and_m_tracking() -> None:
    """Seed section 5: alpha0 = 10, m = 0.01, m jumps to 0.02 at 10 s, 20 A square wave of 2 s,
    the seed's Q, R, P0. alpha stays within its 3-sigma bounds (eq. 25) >= 99 % of the time after
    a 1 s convergence; m-hat follows the jump, and the slope of alpha-hat changes."""
    t, ch, tr = simulate_friction_drive(20.0, 1000.0, m_changes=[(10.0, 0.02)], seed=11)
    for f44 in (0.0, -100.0):
        config = seed_config(
            {
                "f44": f44,
                "rul_every_s": None,
                "nonnegative": False,
                "health_window_samples": 10_000,
            }
        )
        _, s, health, _, _ = run(config, t, ch)
        after = t >= 1.0
        inside = np.abs(s["alpha"] - tr["alpha"]) <= s["alpha_3sigma"]
        assert inside[after].mean() >= 0.99
        assert np.all(np.abs(s["dn"] - tr["dn"])[after] <= 1e-3)
        # m-hat is noisy under the seed's Q: compare 4 s means (thousands of samples)
        before = s["m"][(t >= 5.0) & (t < 10.0)].mean()
        late = s["m"][t >= 15.0].mean()
        assert before == pytest.approx(0.01, abs=2e-3)
        assert late == pytest.approx(0.02, abs=2e-3)
        slope_before = np.polyfit(t[(t > 2) & (t < 10)], s["alpha"][(t > 2) & (t < 10)], 1)[0]
        slope_after = np.polyfit(t[t > 12], s["alpha"][t > 12], 1)[0]
        assert slope_after / slope_before > 1.7
        assert len(health) == 2


def test_prognosis_tuning_tracks_m_and_is_consistent() -> None:
    """With a small random walk on m, m-hat settles within 1 % of the truth, alpha and m stay in
    their bounds, and the innovations pass the consistency tests in most windows."""
    t, ch, tr = simulate_friction_drive(60.0, 1000.0, seed=12)
    config = seed_config({"q_diag": PROGNOSIS_Q, "rul_every_s": None})
    _, s, health, events, _ = run(config, t, ch)
    after = t >= 5.0
    assert np.mean(np.abs(s["m"][after] - 0.01) <= s["m_3sigma"][after]) >= 0.99
    assert np.mean(np.abs(s["alpha"] - tr["alpha"])[after] <= s["alpha_3sigma"][after]) >= 0.99
    assert abs(s["m"][-1] - 0.01) < 1e-4
    assert sum(h.indicators["consistent"] == 1.0 for h in health) >= len(health) - 1
    assert all(h.indicators["nis_mean"] == pytest.approx(2.0, abs=0.15) for h in health)


def test_nominal_sample_period_makes_absolute_time_stamps_harmless() -> None:
    """POSIX-second time stamps at 1 kHz are rounded to about 2e-7 s; taken as the spacing, that
    rounding jitters the discretization and the innovations fail the consistency tests. With the
    nominal period stated, the outputs equal those on time stamps starting at 0 (to rounding)."""
    t, ch, _ = simulate_friction_drive(60.0, 1000.0, m=0.002, seed=3)
    offset = 1_795_312_500.123
    raw = {"q_diag": PROGNOSIS_Q, "rul_every_s": None}
    _, ref, ref_health, _, _ = run(seed_config({**raw, "sample_period_s": 0.001}), t, ch)
    _, snapped, snapped_health, _, _ = run(
        seed_config({**raw, "sample_period_s": 0.001}), t + offset, ch
    )
    _, jittered, jittered_health, _, _ = run(seed_config(raw), t + offset, ch)
    for name in ("alpha", "m", "nis"):
        np.testing.assert_allclose(snapped[name], ref[name], rtol=1e-9, atol=1e-12)
    assert [h.status for h in snapped_health] == [h.status for h in ref_health]
    # Without it the rounding is visible: the NIS drifts away from the reference run.
    assert np.max(np.abs(jittered["nis"] - ref["nis"])) > 1e-3


# ----------------------------------------------------------------------------- covariance


def test_covariance_stays_symmetric_psd_over_a_million_steps() -> None:
    """10^6 steps of a random telegraph current (0 to 30 A), 5 % missing speeds, 1 % missing
    currents, alpha wearing from 10 to well past failure, under both the seed's and the
    prognosis tuning; P is checked after each of 1000 batches: symmetric and with eigenvalues
    >= -1e-12 of its largest. The same stream without the non-negativity guard diverges."""
    n, per = 1_000_000, 1000
    rng = np.random.default_rng(7)
    levels = np.repeat(rng.choice([0.0, 10.0, 30.0], size=n // 500), 500)
    t, ch, tr = simulate_friction_drive(n / 1000.0, 1000.0, current=levels, m=0.004, seed=7)
    for name, frac in (("motor_speed", 0.05), ("wheel_speed", 0.05), ("current", 0.01)):
        ch[name][rng.random(n) < frac] = np.nan
    assert tr["dn"][-1] > 0.9
    for q in (list(de.DekfConfig().q_diag), PROGNOSIS_Q):
        config = seed_config(
            {"q_diag": q, "rul_every_s": None, "health_window_samples": 50_000}
        )
        state = de.initial_state(config)
        worst = 0.0
        for lo in range(0, n, per):
            state, out = de.step(config, state, batch_of(t, ch, lo, lo + per))
            cov = state.P
            assert np.array_equal(cov, cov.T)
            eig = np.linalg.eigvalsh(cov)
            worst = min(worst, eig[0] / eig[-1])
            assert np.all(np.isfinite(out.samples["alpha"]))
        assert worst >= -1e-12
        assert state.n_samples == n
    # without the non-negativity guard the seed's tuning diverges once alpha nears 0
    unguarded = seed_config({"rul_every_s": None, "nonnegative": False})
    _, out = de.step(unguarded, de.initial_state(unguarded), batch_of(t, ch))
    assert not np.all(np.isfinite(out.samples["alpha"]))


# ----------------------------------------------------------------------------- health, events


def test_health_indicators_match_the_per_sample_outputs() -> None:
    t, ch, _ = simulate_friction_drive(6.0, 1000.0, seed=3)
    ch["motor_speed"][100:160] = np.nan
    ch["wheel_speed"][150:170] = np.nan
    hw = 1000
    config = seed_config({"health_window_samples": hw, "rul_every_s": None})
    _, s, health, _, _ = run(config, t, ch)
    assert len(health) == 6
    for w, h in enumerate(health):
        sl = slice(w * hw, (w + 1) * hw)
        assert (h.t_start_s, h.t_end_s, h.n_samples) == (t[sl][0], t[sl][-1], hw)
        nis = s["nis"][sl]
        valid = np.isfinite(nis)
        dof = np.isfinite(s["innovation_w1"][sl]).astype(float) + np.isfinite(
            s["innovation_w2"][sl]
        )
        assert h.indicators["nis_mean"] == pytest.approx(nis[valid].mean(), rel=1e-12)
        assert h.indicators["valid_fraction"] == pytest.approx(valid.mean())
        lo = np.where(dof == 1, de.NIS_BOUNDS_95[0], de.NIS_BOUNDS_95[2])
        hi = np.where(dof == 1, de.NIS_BOUNDS_95[1], de.NIS_BOUNDS_95[3])
        out = ((nis < lo) | (nis > hi))[valid].mean()
        assert h.indicators["nis_out_fraction"] == pytest.approx(out, abs=1e-12)
        for name, sig in (("w1", "innovation_w1"), ("w2", "innovation_w2")):
            # normalized innovations nu = e / sqrt(S_jj), S_jj from the 3-sigma bound
            nu = s[sig][sl] / (s[f"{sig}_3sigma"][sl] / 3.0)
            if w > 0:
                prev = s[sig][w * hw - 1] / (s[f"{sig}_3sigma"][w * hw - 1] / 3.0)
                nu_prev = np.concatenate([[prev], nu[:-1]])
            else:
                nu_prev = np.concatenate([[np.nan], nu[:-1]])
            ok = np.isfinite(nu)
            pair = ok & np.isfinite(nu_prev)
            rho = np.sum(nu[pair] * nu_prev[pair]) / np.sum(nu[ok] ** 2)
            assert h.indicators[f"whiteness_{name}"] == pytest.approx(rho, rel=1e-9, abs=1e-12)
            z_bias = np.sum(nu[ok]) / np.sqrt(ok.sum())
            assert h.indicators[f"bias_z_{name}"] == pytest.approx(z_bias, rel=1e-9, abs=1e-12)
        assert h.indicators["alpha"] == s["alpha"][sl][-1]
        assert h.indicators["dn"] == pytest.approx(s["dn"][sl][-1], rel=1e-12)
        rate = (s["dn"][sl][-1] - s["dn"][sl][0]) / (t[sl][-1] - t[sl][0])
        assert h.indicators["dn_rate_per_s"] == pytest.approx(rate, rel=1e-9)


def test_mistuned_noise_is_flagged_inconsistent() -> None:
    """R 100 times below the true sensor noise: NIS far above its chi-square bounds, flagged in
    every window, with the status "unknown" (never ok while inconsistent) and an event."""
    t, ch, _ = simulate_friction_drive(5.0, 1000.0, seed=4)
    config = seed_config(
        {"r_diag": [1.0063e-10, 1.0083e-12], "health_window_samples": 1000, "rul_every_s": None}
    )
    state, _, health, events, _ = run(config, t, ch)
    assert all(h.indicators["consistent"] == 0.0 for h in health)
    assert all(h.indicators["nis_mean"] > h.indicators["nis_mean_upper"] for h in health)
    assert all(h.status == "unknown" and "NIS mean" in h.reasons[0] for h in health)
    assert [e.kind for e in events] == ["innovations_inconsistent"]
    state, out = de.step(config, de.initial_state(config), batch_of(t, ch, 0, 4000))
    _, out = de.step(config, state, batch_of(t, ch, 4000))
    assert out.status is not None and out.status.status == "unknown"
    assert "inconsistent" in out.status.reasons[0]


def test_dn_threshold_events_with_hysteresis() -> None:
    t, ch, _ = simulate_friction_drive(20.0, 1000.0, seed=5)
    config = seed_config(
        {"dn_watch": 0.05, "dn_alert": 0.1, "dn_hysteresis": 0.01, "rul_every_s": None}
    )
    _, s, health, events, _ = run(config, t, ch)
    crossed = [e for e in events if e.kind == "dn_threshold_crossed"]
    assert [(e.detail["from"], e.detail["to"]) for e in crossed] == [
        ("ok", "watch"),
        ("watch", "alert"),
    ]
    for e, level in zip(crossed, (0.05, 0.1), strict=True):
        k = int(np.searchsorted(t, e.t_s))
        assert s["dn"][k] >= level > s["dn"][k - 1]
        assert e.detail["level"] == level
    assert health[-1].status == "alert"
    # alpha re-estimated upward (e.g. after a repair): down-crossing only below level - 0.01
    state = de.initial_state(config)
    state, _ = de.step(config, state, batch_of(t, ch, 0, 20_000))
    vec = state.vector.copy()
    vec[kern.ST_X + 2] = 10.0 * (1 - 0.095)  # Dn 0.095: inside the hysteresis band
    vec.setflags(write=False)
    held = de.DekfState(state.version, state.t_last_s, vec)
    t2, ch2, _ = simulate_friction_drive(0.01, 1000.0, t0_s=30.0, m=0.0, current=0.0)
    _, out = de.step(config, held, Batch(t2, ch2))
    assert not [e for e in out.events if e.kind == "dn_threshold_crossed"]
    vec = vec.copy()
    vec[kern.ST_X + 2] = 10.0 * (1 - 0.08)
    vec.setflags(write=False)
    _, out = de.step(config, de.DekfState(state.version, state.t_last_s, vec), Batch(t2, ch2))
    down = [e for e in out.events if e.kind == "dn_threshold_crossed"]
    assert [(e.detail["from"], e.detail["to"], e.detail["direction"]) for e in down] == [
        ("alert", "watch", "down")
    ]


# ----------------------------------------------------------------------------- RUL contract


def _json_safe(obj: Any) -> str:
    return json.dumps(obj, allow_nan=False)


def test_rul_estimates_follow_the_contract() -> None:
    t, ch, tr = simulate_friction_drive(40.0, 1000.0, seed=6)
    config = seed_config(
        {
            "q_diag": PROGNOSIS_Q,
            "rul_every_s": 15.0,
            "rul_trajectories": 200,
            "rul_watch_s": 150.0,
            "rul_alert_s": 135.0,
        }
    )
    state, s, _, events, ruls = run(config, t, ch)
    assert [r.t_s for r in ruls] == [t[15_000], t[30_000]]
    first = ruls[0]
    assert first.threshold == 0.9
    assert set(first.health) == {"dn", "dn_lower", "dn_upper", "alpha", "m"}
    assert first.health["alpha"] == s["alpha"][15_000]
    assert first.q05_s < first.q50_s < first.q95_s
    assert first.pessimistic_s <= first.q05_s and first.q95_s <= first.optimistic_s
    a = first.assumption
    assert a["load"]["kind"] == "square_wave" and a["n_trajectories"] == 200
    assert a["horizon_s"] == 1e7 and a["seed"] == 0 and a["reached_fraction"] == 1.0
    # the seed scenario fails at Dn 0.9 after ~160 s: RUL ~145 s at 15 s (watch), ~130 s at 30 s
    assert first.status == "watch" and "RUL 5 % quantile" in first.reasons[0]
    assert ruls[1].status == "alert"
    kinds = [(e.kind, e.detail.get("to")) for e in events if e.kind == "rul_threshold_crossed"]
    assert kinds == [("rul_threshold_crossed", "watch"), ("rul_threshold_crossed", "alert")]
    for r in ruls:
        _json_safe(r.assumption)
        _json_safe(r.health)
    for e in events:
        _json_safe(e.detail)
    state, _ = de.step(config, de.initial_state(config), batch_of(t, ch, 0, 39_000))
    _, out = de.step(config, state, batch_of(t, ch, 39_000))
    _json_safe(out.diagnosis.detail)
    assert out.status.status == "alert"
    assert out.diagnosis.detail["rul_level"] == "alert"


def test_rul_every_batch_and_disabled() -> None:
    t, ch, _ = simulate_friction_drive(3.0, 1000.0, seed=6)
    config = seed_config({"rul_every_s": "every_batch", "rul_trajectories": 20})
    _, _, _, _, ruls = run(config, t, ch, splits=[1000, 2500])
    assert [r.t_s for r in ruls] == [t[999], t[2499], t[-1]]
    config = seed_config({"rul_every_s": None})
    _, _, _, _, ruls = run(config, t, ch, splits=[1000])
    assert ruls == []


def test_observed_load_bins_the_held_current() -> None:
    t, ch, _ = simulate_friction_drive(6.0, 1000.0, seed=8)
    ch["current"][[10, 11, 2500]] = np.nan
    load = {"kind": "observed", "bin_samples": 50, "bins": 80, "merge_tolerance_a": 0.0}
    config = seed_config({"rul_load": load, "rul_every_s": 5.0, "rul_trajectories": 20})
    state, _, _, _, ruls = run(config, t, ch)
    (est,) = ruls
    held = ch["current"].copy()
    for k in np.flatnonzero(np.isnan(held)):
        held[k] = held[k - 1]
    # prognosis at sample 5000: 4999 predict steps so far, 99 full bins; ring = the last 80
    # bins of 50 steps each, the step from k-1 to k applying the held current of k-1
    steps = held[:5000]
    means = steps.reshape(100, 50).mean(axis=1)[-80:]
    seg = est.assumption["load_segments"]
    merged = [means[0]]
    for v in means[1:]:
        if v != merged[-1]:
            merged.append(v)
    np.testing.assert_allclose(seg["current_a"], merged, rtol=1e-12)
    assert sum(seg["durations_s"]) == pytest.approx(80 * 50 * 1e-3, rel=1e-9)
    assert state.vector.shape[0] == kern.ST_BASE_LEN + 160


# ----------------------------------------------------------------------------- invariance, state


def _stream(seed: int, n: int) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    t, ch, _ = simulate_friction_drive(n / 1000.0, 1000.0, seed=seed, t0_s=100.0)
    rng = np.random.default_rng(seed)
    for name in ch:
        ch[name][rng.random(n) < 0.02] = np.nan
    return t, ch


@pytest.mark.parametrize("load", ["square_wave", "observed"])
def test_batch_split_invariance(load: str) -> None:
    n = 12_000
    t, ch = _stream(1, n)
    raw: dict[str, Any] = {
        "health_window_samples": 1500,
        "rul_every_s": 2.5,
        "rul_trajectories": 30,
        "dn_watch": 0.02,
        "dn_alert": 0.04,
        "q_diag": PROGNOSIS_Q,
    }
    if load == "observed":
        raw["rul_load"] = {"kind": "observed", "bin_samples": 25, "bins": 60}
    config = seed_config(raw)
    ref_state, ref, ref_health, ref_events, ref_rul = run(config, t, ch)
    rng = np.random.default_rng(2)
    splits = sorted(set(rng.integers(1, n, size=30).tolist()) | {1, 2, 1499, 1500, 1501, 2500})
    state, got, health, events, ruls = run(config, t, ch, splits)
    for name in de.SAMPLE_OUTPUTS:
        np.testing.assert_array_equal(got[name], ref[name])
    assert health == ref_health and len(health) == n // 1500
    assert events == ref_events and any(e.kind == "dn_threshold_crossed" for e in events)
    assert ruls == ref_rul and len(ruls) == 4
    np.testing.assert_array_equal(state.vector, ref_state.vector)


def test_state_round_trip_is_exact() -> None:
    t, ch = _stream(2, 6000)
    config = seed_config(
        {"rul_every_s": 2.0, "rul_trajectories": 20, "health_window_samples": 1000}
    )
    _, ref, ref_health, _, ref_rul = run(config, t, ch)
    state, out1 = de.step(config, de.initial_state(config), batch_of(t, ch, 0, 3333))
    blob = de.dump_state(state)
    loaded = de.load_state(blob)
    np.testing.assert_array_equal(loaded.vector, state.vector)
    assert loaded.t_last_s == state.t_last_s and de.dump_state(loaded) == blob
    _, out2 = de.step(config, loaded, batch_of(t, ch, 3333))
    np.testing.assert_array_equal(
        np.concatenate([out1.samples["alpha"], out2.samples["alpha"]]), ref["alpha"]
    )
    assert [*out1.health, *out2.health] == ref_health
    assert [*out1.rul, *out2.rul] == ref_rul


def test_state_errors() -> None:
    config = seed_config({})
    blob = de.dump_state(de.initial_state(config))
    with pytest.raises(StateVersionError, match="99"):
        de.load_state(blob.replace(f'"version":{de.STATE_VERSION}'.encode(), b'"version":99'))
    with pytest.raises(EstimatorError):
        de.load_state(b"not json")
    with pytest.raises(EstimatorError, match="kind"):
        de.load_state(blob.replace(b'"deterioration_ekf"', b'"fakf"'))
    observed = seed_config({"rul_load": {"kind": "observed"}})
    t, ch = _stream(3, 10)
    with pytest.raises(EstimatorError, match="observed"):
        de.step(observed, de.initial_state(config), batch_of(t, ch))


def test_out_of_order_and_missing_channel() -> None:
    t, ch = _stream(4, 20)
    config = seed_config({})
    state, _ = de.step(config, de.initial_state(config), batch_of(t, ch, 0, 10))
    with pytest.raises(OutOfOrderError):
        de.step(config, state, batch_of(t, ch, 9))
    bad_t = t[10:].copy()
    bad_t[5] = bad_t[4]
    with pytest.raises(OutOfOrderError):
        de.step(config, state, Batch(bad_t, {k: v[10:] for k, v in ch.items()}))
    state2, out = de.step(config, state, batch_of(t, ch, 10))
    assert state2.t_last_s == t[-1] and np.all(np.isfinite(out.samples["alpha"]))
    with pytest.raises(EstimatorError, match="wheel_speed"):
        de.step(
            config,
            state,
            Batch(t[10:], {"current": ch["current"][10:], "motor_speed": ch["motor_speed"][10:]}),
        )
    _, empty = de.step(config, state, Batch(np.empty(0), {}))
    assert set(empty.samples) == set(de.SAMPLE_OUTPUTS)


def test_nan_current_holds_the_last_valid_one() -> None:
    t, ch = _stream(5, 3000)
    ch["current"] = np.where(np.isnan(ch["current"]), 0.0, ch["current"])
    holed = dict(ch)
    holed["current"] = ch["current"].copy()
    holed["current"][[500, 501, 1700]] = np.nan
    held = dict(ch)
    held["current"] = ch["current"].copy()
    held["current"][[500, 501]] = ch["current"][499]
    held["current"][1700] = ch["current"][1699]
    config = seed_config({"rul_every_s": None})
    _, a, _, _, _ = run(config, t, holed)
    _, b, _, _, _ = run(config, t, held)
    for name in de.SAMPLE_OUTPUTS:
        np.testing.assert_array_equal(a[name], b[name])


# ----------------------------------------------------------------------------- configuration


def test_config_round_trip_and_defaults() -> None:
    config = de.parse_config({})
    d = de.config_to_dict(config)
    _json_safe(d)
    assert de.parse_config(d) == config
    assert de.parse_config(json.loads(json.dumps(d))) == config
    assert d["alpha0"] == 10.0 and d["input_model"] == "edge" and d["noise_adaptation"]
    assert de.parse_config({"alpha0": None}).alpha0 is None
    json.dumps(de.CONFIG_MODEL.model_json_schema())
    config = de.parse_config(SEED)
    d = de.config_to_dict(config)
    assert d["q_diag"] == [0.0, 0.0, 0.0, pytest.approx(3.3333e-5, rel=1e-4)]
    assert d["r_diag"] == [1.0063e-8, 1.0083e-10]
    assert d["rul_load"] == {
        "kind": "square_wave", "high_a": 20.0, "low_a": 0.0, "period_s": 2.0, "duty": 0.5, "t0_s": 0.0
    }  # fmt: skip
    assert de.required_channels(config) == ("current", "motor_speed", "wheel_speed")


@pytest.mark.parametrize(
    ("raw", "match"),
    [
        ({"bogus": 1}, "bogus: Extra inputs"),
        ({"plant": {"r1_m": 0.0}}, "plant.r1_m"),
        ({"plant": {"r3": 1.0}}, "plant.r3"),
        ({"r_diag": [1e-8]}, "r_diag"),
        ({"r_diag": [1e-8, 0.0]}, r"r_diag\.1"),
        ({"q_diag": [0, 0, 0, -1]}, r"q_diag\.3"),
        ({"p0_diag": [1, 1, 1, "x"]}, r"p0_diag\.3"),
        ({"alpha0": 0.0}, "alpha0"),
        ({"m0": float("inf")}, "m0"),
        ({"w1_0": "fast"}, "w1_0"),
        ({"f44": None}, "f44"),
        ({"bound_sigma": -3}, "bound_sigma"),
        ({"expm_tol": 1.0}, "expm_tol"),
        ({"health_window_samples": 10}, "health_window_samples"),
        ({"health_window_samples": 1000.0}, "health_window_samples"),
        ({"dn_watch": 0.8, "dn_alert": 0.6}, "dn_alert"),
        ({"dn_alert": 0.95}, "rul_failure_dn"),
        ({"rul_every_s": 0}, "rul_every_s"),
        ({"rul_every_s": "hourly"}, "rul_every_s"),
        ({"rul_failure_dn": 1.0}, "rul_failure_dn"),
        ({"rul_trajectories": 5}, "rul_trajectories"),
        ({"rul_watch_s": 10.0, "rul_alert_s": 20.0}, "rul_alert_s"),
        ({"rul_seed": -1}, "rul_seed"),
        ({"rul_load": {"kind": "square_wave", "duty": 2}}, "rul_load.square_wave.duty"),
        ({"rul_segment_tol": 0.0}, "rul_segment_tol"),
        ({"consistency_sigma": True}, "consistency_sigma"),
        ({"sample_period_s": 0.0}, "sample_period_s"),
    ],
)
def test_config_errors_name_the_field(raw: dict[str, Any], match: str) -> None:
    with pytest.raises(ConfigError, match=match):
        de.parse_config(raw)


def test_warm_up_runs() -> None:
    de.warm_up()
    assert math.isfinite(de.chi2_mean_bounds(200.0, 100.0, 3.0)[0])
