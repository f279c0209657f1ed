"""Deterioration EKF: the edge-response input model, the one-step-residual noise estimate, the
verdict restart at a plant calibration, the dwell load and the version-3 state upgrade. Drives come from the independent generator with seeds the validation
scripts do not use (the scripts use 20000+ and 0..)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
from scipy.linalg import expm

from estimators import deterioration_ekf as de
from estimators import rul
from estimators.base import Batch
from estimators.kernels import dekf_kernels as kern
from estimators.simulators import friction_drive_scenarios as fs
from estimators.simulators.friction_drive import PAPER_NOISE_STD, FrictionDriveParams
from tests.estimators.conftest import upgraded_dekf_state


def _drive(seed: int, **changes: object) -> fs.Drive:
    drive = fs.draw_drive(seed, rate_hz=50.0, load="square", mismatch=False, skew=False)
    return dataclasses.replace(drive, **changes)  # type: ignore[arg-type]


def _run(config: dict[str, object], t: np.ndarray, ch: dict[str, np.ndarray]) -> tuple[de.DekfState, object]:
    cfg = de.parse_config(config)
    return de.step(cfg, de.initial_state(cfg), Batch(t_s=t, channels=ch))


def test_edge_moments_against_quadrature() -> None:
    """Mean and covariance of the response to a step at a uniform instant of the interval
    equal a fine quadrature of ``int_0^h expm(G s) ds b`` computed with scipy's expm, at a
    step long against the motor's time constant (50 Hz) and a short one (1 kHz)."""
    config = de.parse_config({})
    cfg = de._kernel_config(config)
    p = config.plant_params
    w1, w2, al, m = 150.0, 13.0, 9.0, 0.01
    dv = p.r1_m * w1 - p.r2_m * w2
    g = np.array(
        [
            [-(al * p.r1_m**2 + p.b1_nm_s) / p.j1_kg_m2, al * p.r1_m * p.r2_m / p.j1_kg_m2, -p.r1_m * dv / p.j1_kg_m2],
            [al * p.r1_m * p.r2_m / p.j2_kg_m2, -(al * p.r2_m**2 + p.b2_nm_s) / p.j2_kg_m2, p.r2_m * dv / p.j2_kg_m2],
            [-2 * al * m * p.r1_m * dv, 2 * al * m * p.r2_m * dv, -m * dv * dv],
        ]
    )  # fmt: skip
    aug = np.zeros((4, 4))
    aug[:3, :3] = g
    aug[0, 3] = p.km_nm_a / p.j1_kg_m2
    for dt in (0.02, 0.001):
        mom = kern.edge_moments(cfg, w1, w2, al, m, dt)
        hs = (np.arange(4000) + 0.5) / 4000 * dt
        resp = np.array([expm(aug * h)[:3, 3] for h in hs])
        mu = resp.mean(axis=0)
        cov = np.cov(resp.T, bias=True)
        np.testing.assert_allclose(mom[:3], mu, rtol=1e-6, atol=1e-14)
        got = np.array([[mom[3], mom[4], mom[5]], [mom[4], mom[6], mom[7]], [mom[5], mom[7], mom[8]]])
        np.testing.assert_allclose(got, cov, rtol=1e-5, atol=1e-6 * abs(cov[0, 0]) * 1e-6)
        # not rank one: the wheel's response lags the motor's (the speeds' correlation < 1)
        corr = got[0, 1] / math.sqrt(got[0, 0] * got[1, 1])
        assert corr < (0.99 if dt == 0.02 else 0.9999)


def test_edge_input_model_consistent_at_edges_where_rank_one_is_not() -> None:
    """50 Hz square wave with its edges at arbitrary instants (exact plant, no skew, the true
    R): the edge model's NIS at the samples closing an edge interval is near its 2 degrees of
    freedom; the rank-one interval variance gives NIS far beyond (the step response late in an
    interval is not a multiple of an early one)."""
    drive = _drive(7_301)
    t, ch, _ = fs.telemetry(drive, 40.0)
    r_true = [(drive.noise_factor * s) ** 2 for s in PAPER_NOISE_STD]
    cur = ch["current"]
    edge = np.zeros(cur.shape[0], dtype=bool)
    edge[1:] = np.abs(np.diff(cur)) > 1e-9
    edge &= t > 2.0
    assert edge.sum() >= 20
    nis: dict[str, float] = {}
    for model in ("edge", "interval"):
        _, out = _run(
            {
                "alpha0": drive.alpha0, "input_model": model, "noise_adaptation": False,
                "r_diag": r_true, "plant_calibration": False, "rul_every_s": None,
                "input_timing_s": 0.0, "gate_sigma": None,
            },
            t, ch,
        )  # fmt: skip
        nis[model] = float(np.median(out.samples["nis"][edge]))  # type: ignore[attr-defined]
    assert nis["edge"] < 6.0
    assert nis["interval"] > 5.0 * nis["edge"]


def test_noise_estimate_from_one_step_residuals_at_a_low_rate() -> None:
    """At 50 Hz with low noise the smooth signal contaminates any difference of raw samples:
    the third-difference estimate alone (computed here from the data) is several times the
    truth. The one-step residual of the model removes the signal; the smaller of the two
    estimates at the end of a minute is within a factor 2.5 of the truth and well below the
    third-difference one."""
    drive = _drive(7_302, noise_factor=4.0)
    t, ch, _ = fs.telemetry(drive, 60.0)
    _, out = _run({"alpha0": drive.alpha0, "plant_calibration": False, "rul_every_s": None}, t, ch)
    r_true = [(drive.noise_factor * s) ** 2 for s in PAPER_NOISE_STD]
    for name, channel, truth in zip(
        ("r_w1", "r_w2"), ("motor_speed", "wheel_speed"), r_true, strict=True
    ):
        y = ch[channel]
        d3 = y[3:] - 3.0 * y[2:-1] + 3.0 * y[1:-2] - y[:-3]
        r_d3 = float((np.median(np.abs(d3)) * kern.D3_TO_SIGMA) ** 2)
        assert r_d3 > 2.5 * truth  # the contamination this estimate is for
        est = float(out.samples[name][-1])  # type: ignore[attr-defined]
        assert truth / 2.5 < est < 2.5 * truth, (name, est, truth)
        assert est < 0.7 * r_d3


def test_plant_calibration_restarts_the_verdict() -> None:
    """A plant whose J1 is 15 % off: the windows before the calibration reject, and the first
    window after an applied calibration starts at it; until that window completes the
    prognoses are served `learning` (no verdict of the replaced plant carries over)."""
    nominal = FrictionDriveParams()
    plant = dataclasses.replace(nominal, j1_kg_m2=nominal.j1_kg_m2 * 1.15)
    drive = fs.draw_drive(7_303, rate_hz=500.0, load="square", mismatch=False, skew=False)
    drive = dataclasses.replace(drive, plant=plant, mismatch=True, noise_factor=10.0)
    t, ch, _ = fs.telemetry(drive, 32.0)
    raw = {"alpha0": drive.alpha0, "rul_every_s": 1.0, "rul_trajectories": 20, "health_window_samples": 1500}
    state, out = _run(raw, t, ch)
    cal = [e for e in out.events if e.kind == "plant_calibrated"]  # type: ignore[attr-defined]
    assert cal, "the calibration must apply on this drive"
    # the calibrated kernel configuration and plant are read-only like the configured ones, so
    # each kernel is compiled for one signature (not a second one for writable vectors)
    config = de.parse_config(raw)
    calibrated_cfg = de._state_kernel_config(config, state.vector)
    assert calibrated_cfg is not config.kernel_vector and not calibrated_cfg.flags.writeable
    calibrated_plant = de.plant_vector_of(config, state.vector)
    assert calibrated_plant is not config.plant_vector and not calibrated_plant.flags.writeable
    t_cal = cal[0].t_s
    before = [w for w in out.health if w.t_end_s <= t_cal]  # type: ignore[attr-defined]
    after = [w for w in out.health if w.t_end_s > t_cal]  # type: ignore[attr-defined]
    assert any(w.indicators["consistent"] == 0.0 for w in before)
    assert after and after[0].t_start_s > t_cal
    first_end = after[0].t_end_s
    between = [e for e in out.rul if t_cal < e.t_s < first_end]  # type: ignore[attr-defined]
    assert between and all(e.status == "learning" for e in between)


def test_dwell_load_from_binned_telegraph() -> None:
    """A random telegraph between -2 A and 18 A (dwells exponential, means 0.5 s and 1.0 s)
    binned at 20 ms: levels recovered, mean dwells within their sampling error, the cycle's
    variance that of exponential dwells; a square wave has (almost) no cycle variance."""
    rng = np.random.default_rng(7_305)
    dt = 0.02
    edges = [0.0]
    level = [False]
    while edges[-1] < 600.0:
        edges.append(edges[-1] + rng.exponential(1.0 if level[-1] else 0.5))
        level.append(not level[-1])
    grid = np.arange(0.0, 600.0, dt)
    fine = np.arange(0.0, 600.0, dt / 50.0)
    idx = np.searchsorted(np.array(edges), fine, side="right") - 1
    cur_fine = np.where(np.array(level)[idx], 18.0, -2.0)
    currents = cur_fine.reshape(grid.shape[0], 50).mean(axis=1)
    durations = np.full(grid.shape[0], dt)
    dl = rul.dwell_load(durations, currents, 16, 0.05)
    assert dl is not None
    assert abs(dl.low_a + 2.0) < 0.01 and abs(dl.high_a - 18.0) < 0.01
    n_low, n_high = dl.dwells
    assert n_low > 300 and n_high > 300
    assert abs(dl.cycle_mean_s - 1.5) < 3.0 * math.sqrt(1.25 / min(n_low, n_high))
    assert 0.7 < dl.cycle_var_s2 / 1.25 < 1.3
    assert dl.durations_s.shape[0] == 32 and set(dl.currents_a) == {dl.low_a, dl.high_a}
    np.testing.assert_allclose(dl.renewal_var_s, dl.cycle_var_s2 / dl.cycle_mean_s)
    square = np.where(np.mod(grid, 2.0) < 0.8, 20.0, 0.0)
    sq = rul.dwell_load(durations, square, 8, 0.05)
    assert sq is not None and sq.cycle_var_s2 < 1e-3 and abs(sq.cycle_mean_s - 2.0) < 1e-9


def test_renewal_variance_widens_short_lives_more() -> None:
    """The future cycles' variance enters per trajectory as renewal_var_s / T: the interval of a
    prognosis widens, relatively more for a short remaining life; the median stays."""
    plant = FrictionDriveParams().as_array()
    settings = rul.PrognosisSettings(n_trajectories=400)
    seg = (np.array([1.0, 1.0]), np.array([20.0, 0.0]))
    cov = np.diag([1e-8, 1e-10, 1e-10, 1e-14])
    widths = {}
    for alpha in (1.2, 8.0):
        x = np.array([0.0, 0.0, alpha, 0.01])
        plain = rul.prognose(plant, 10.0, x, cov, 5.0, seg, settings)
        wide = rul.prognose(plant, 10.0, x, cov, 5.0, seg, settings, renewal_var_s=2.0)
        assert plain.q50_s and wide.q50_s and plain.q05_s and plain.q95_s and wide.q05_s and wide.q95_s
        assert abs(wide.q50_s / plain.q50_s - 1.0) < 0.1
        widths[alpha] = (wide.q95_s - wide.q05_s) / wide.q50_s
        assert widths[alpha] > 3.0 * (plain.q95_s - plain.q05_s) / plain.q50_s
    assert widths[1.2] > widths[8.0]


def test_dwells_model_in_a_prognosis() -> None:
    """The observed load with the dwell model: the prognosis reports the dwells it read and
    carries their sampling error in its model-error spread."""
    drive = fs.draw_drive(7_306, rate_hz=200.0, load="telegraph", mismatch=False, skew=False)
    t, ch, _ = fs.telemetry(drive, 45.0)
    load = {"kind": "observed", "bin_samples": 4, "bins": 1500, "model": "dwells"}
    _, out = _run(
        {"alpha0": drive.alpha0, "rul_every_s": 40.0, "rul_trajectories": 50, "rul_load": load},
        t, ch,
    )  # fmt: skip
    est = out.rul[-1]  # type: ignore[attr-defined]
    info = est.assumption["dwells"]
    assert isinstance(info, dict) and min(info["observed"].values()) >= rul.MIN_DWELLS
    assert abs(info["low_a"] - drive.load_params["low_a"]) < 0.05
    assert abs(info["high_a"] - drive.load_params["high_a"]) < 0.05
    assert est.assumption["model_error_rel_std"] >= info["estimate_rel_std"] - 1e-12


def test_version_3_state_loads_and_steps() -> None:
    """Bytes dumped by the version-3 code (third-difference noise estimate only) load, upgrade
    to version 4 with the one-step-residual entries fresh (the rest unchanged), and step on."""
    state = upgraded_dekf_state(3)
    assert state.vector.shape[0] == kern.ST_BASE_LEN
    assert np.isnan(state.vector[kern.ST_Y_RES : kern.ST_Y_RES + 2]).all()
    assert (state.vector[kern.ST_QTL_RES : kern.ST_N_QTL_RES + 2] == 0.0).all()
    assert state.vector[kern.ST_N_QTL] > 0.0  # the third-difference estimate carries on
    config = de.parse_config(
        {"alpha0": 10.0, "rul_every_s": 1.0, "rul_trajectories": 20, "sample_period_s": 0.001}
    )
    from estimators.simulators.friction_drive import simulate_friction_drive

    t, ch, truth = simulate_friction_drive(5.0, 1000.0, seed=3)
    keep = t > 3.0
    _, out = de.step(config, state, Batch(t_s=t[keep], channels={k: v[keep] for k, v in ch.items()}))
    err = np.abs(out.samples["alpha"] - truth["alpha"][keep])
    assert np.max(err[-500:]) < 0.01
