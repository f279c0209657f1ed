"""Deterioration EKF on telemetry its discretization did not make (the independent generator):
each robustness mechanism against a case that fails without it; served statuses; the state of
today's version and of version 1."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from estimators import deterioration_ekf as de
from estimators import rul as rulmod
from estimators.base import STATUSES, Batch, StateVersionError
from estimators.kernels import dekf_kernels as kern
from estimators.simulators import friction_drive_scenarios as fs
from tests.estimators.conftest import upgraded_dekf_state

DATA = Path(__file__).parent / "data"


def drive_of(seed: int, **changes: Any) -> fs.Drive:
    """A 100 Hz square-wave drive at 100x the seed's noise, exact plant, no skew (unless
    changed); seeds here are not those of the validation script."""
    base = fs.draw_drive(
        seed, rate_hz=100.0, load="square", mismatch=False, skew=False, noise_factor=100.0
    )
    return dataclasses.replace(base, **changes)


def run(raw: dict[str, Any], t: np.ndarray, ch: dict[str, np.ndarray]) -> tuple[Any, Any]:
    """The defaults with ``raw``; the plant calibration off unless asked for (each test here
    isolates one mechanism)."""
    config = de.parse_config({"rul_every_s": None, "plant_calibration": False, **raw})
    return de.step(config, de.initial_state(config), Batch(t_s=t, channels=ch))


@pytest.fixture(scope="module")
def square() -> tuple[fs.Drive, np.ndarray, dict[str, np.ndarray], np.ndarray]:
    drive = drive_of(501, m=0.01)
    t, ch, alpha = fs.telemetry(drive, 60.0)
    return drive, t, ch, alpha


def test_generator_switches_between_samples_and_integrates_finely(square: Any) -> None:
    drive, t, ch, alpha = square
    sw_t, _ = fs.switches(drive, 60.0)
    # edges at arbitrary instants: not on the 10 ms sample grid
    frac = np.mod(sw_t[1:] * drive.rate_hz, 1.0)
    assert np.all((frac > 1e-6) & (frac < 1 - 1e-6))
    # RK4 at 0.1 ms and at 0.05 ms agree (the truth does not depend on the fine step)
    p = drive.plant.as_array()
    targets = np.ascontiguousarray(t[:3000])
    a = fs.integrate_at(p, drive.m, drive.alpha0, *fs.switches(drive, 40.0), targets, 1e-4)
    b = fs.integrate_at(p, drive.m, drive.alpha0, *fs.switches(drive, 40.0), targets, 5e-5)
    np.testing.assert_allclose(a[:, :3], b[:, :3], rtol=1e-7, atol=1e-7)
    assert np.all(np.diff(alpha) <= 0.0) and alpha[0] < drive.alpha0


def test_interval_input_model_against_held_input(square: Any) -> None:
    """Edges between samples: the held input (seed eq. 16) biases alpha by more than an order
    of magnitude more than the interval mean with its edge variance."""
    drive, t, ch, alpha = square
    after = t > 20.0
    errs = {}
    for model in ("interval", "hold"):
        _, out = run({"alpha0": drive.alpha0, "input_model": model}, t, ch)
        errs[model] = np.median(np.abs(out.samples["alpha"] - alpha)[after]) / drive.alpha0
        errs[model + "_nis"] = float(np.nanmean(out.samples["nis"][after]))
    assert errs["interval"] < 2e-4
    assert errs["hold"] > 20 * errs["interval"] and errs["hold_nis"] > errs["interval_nis"]


def test_noise_is_estimated_without_a_datasheet(square: Any) -> None:
    """Configured R (the seed's) 10^4 times too small: the running-median estimate finds the
    true variances; without adaptation the innovations are inconsistent."""
    drive, t, ch, _ = square
    true_r = [(drive.noise_factor * s) ** 2 for s in fs.PAPER_NOISE_STD]
    state, out = run({"alpha0": drive.alpha0}, t, ch)
    np.testing.assert_allclose(state.noise_variances, true_r, rtol=1.0)
    assert np.all(state.noise_variances > 0.5 * np.array(true_r))
    assert out.samples["r_w1"][-1] == state.noise_variances[0]
    _, fixed = run({"alpha0": drive.alpha0, "noise_adaptation": False}, t, ch)
    assert np.nanmean(fixed.samples["nis"]) > 100.0 * np.nanmean(out.samples["nis"])


def test_gate_down_weights_outliers_and_counts_them(square: Any) -> None:
    drive, t, ch, alpha = square
    rng = np.random.default_rng(3)
    bad = {k: v.copy() for k, v in ch.items()}
    hits = rng.choice(np.arange(500, len(t)), 60, replace=False)
    bad["motor_speed"][hits] += rng.choice([-1.0, 1.0], 60) * 50.0
    bad["wheel_speed"][hits[:30]] += 5.0
    after = t > 20.0
    state, out = run({"alpha0": drive.alpha0}, t, bad)
    gated_err = np.max(np.abs(out.samples["alpha"] - alpha)[after]) / drive.alpha0
    assert state.gated_updates >= 60 and out.samples["gated"][hits].mean() > 0.9
    _, raw = run({"alpha0": drive.alpha0, "gate_sigma": None}, t, bad)
    raw_err = np.max(np.abs(raw.samples["alpha"] - alpha)[after]) / drive.alpha0
    assert gated_err < 0.01 < raw_err


def test_projection_keeps_the_physics() -> None:
    """alpha0 configured 25 % below the truth: alpha-hat stays <= alpha0 (1 + tol) and m-hat
    >= 0 with the projection, and leaves that box without it."""
    drive = drive_of(502, m=0.003)
    t, ch, _ = fs.telemetry(drive, 30.0)
    given = 0.75 * drive.alpha0
    _, out = run({"alpha0": given}, t, ch)
    assert np.all(out.samples["alpha"] <= given * 1.1 + 1e-12)
    assert np.all(out.samples["m"] >= 0.0)
    _, free = run({"alpha0": given, "nonnegative": False}, t, ch)
    assert np.max(free.samples["alpha"]) > given * 1.2 or np.min(free.samples["m"]) < 0.0


def test_alpha0_is_estimated_from_the_healthy_start() -> None:
    drive = drive_of(503, alpha0=12.7, m=0.01)
    t, ch, alpha = fs.telemetry(drive, 40.0)
    state, out = run(
        {"alpha0": None, "alpha0_calibration_s": 10.0, "health_window_samples": 500}, t, ch
    )
    assert abs(state.alpha0 / drive.alpha0 - 1.0) < 0.01
    calibrating = t < 9.9
    assert np.all(np.isnan(out.samples["dn"][calibrating]))
    assert all(w.status == "learning" for w in out.health if w.t_end_s < 9.9)
    late = t > 20.0
    dn_true = 1.0 - alpha / drive.alpha0
    assert np.max(np.abs(out.samples["dn"][late] - dn_true[late])) < 0.01
    # without the estimate the prior (10) is taken as alpha0 and Dn is off by ~20 %
    _, prior = run({"alpha0": 10.0, "alpha_max_rel": 1.0}, t, ch)
    assert np.max(np.abs(prior.samples["dn"][late] - dn_true[late])) > 0.1


def test_verdict_hysteresis_and_never_ok_while_inconsistent() -> None:
    vec = np.full(kern.ST_BASE_LEN, np.nan)
    vec[[kern.ST_GOOD_STREAK, kern.ST_BAD_STREAK]] = 0.0
    seen = []
    for verdict in (True, False, True, False, True, True, False):
        de._apply_verdict(vec, verdict, 2)
        seen.append(vec[kern.ST_VERDICT])
    # one rejection -> inconsistent at once; two passes in a row to recover
    assert seen == [1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0]
    config = de.parse_config({"alpha0": 10.0})
    vec[kern.ST_FAILED] = 0.0
    vec[kern.ST_RUL_STATUS] = np.nan
    assert de.serving_status(vec, config, 0.1, 1e9, 0.01, 1e-10)[0] == "unknown"
    vec[kern.ST_VERDICT] = 1.0
    assert de.serving_status(vec, config, 0.1, 1e9, 0.01, 1e-10)[0] == "ok"
    assert de.serving_status(vec, config, 0.1, 1e9, 0.01, 1e-4)[0] == "learning"
    assert de.serving_status(vec, config, None, 1e9, 0.01, 1e-10)[0] == "learning"
    # RUL level hysteresis: leaving watch needs q05 20 % above the level
    vec[kern.ST_RUL_STATUS] = STATUSES.index("watch")
    w = config.rul_watch_s
    assert de.serving_status(vec, config, 0.1, 1.1 * w, 0.01, 1e-10)[0] == "watch"
    assert de.serving_status(vec, config, 0.1, 1.3 * w, 0.01, 1e-10)[0] == "ok"
    vec[kern.ST_FAILED] = 1.0
    assert de.serving_status(vec, config, 0.1, 1e9, 0.01, 1e-10)[0] == "failed"


def test_failed_once_the_threshold_is_crossed_and_statuses_served() -> None:
    drive = drive_of(504, m=0.02, failure_dn=0.3)
    t, ch, alpha = fs.telemetry(drive, 120.0)
    raw = {
        "alpha0": drive.alpha0,
        "rul_failure_dn": 0.3,
        "dn_watch": 0.15,
        "dn_alert": 0.2,
        "rul_every_s": 5.0,
        "rul_trajectories": 50,
        "rul_load": fs.square_wave_law(drive),
    }
    config = de.parse_config(raw)
    state, out = de.step(config, de.initial_state(config), Batch(t_s=t, channels=ch))
    statuses = [r.status for r in out.rul]
    assert statuses[0] == "learning" and set(statuses) <= set(STATUSES)
    t_cross = t[np.argmax(1.0 - alpha / drive.alpha0 >= 0.3)]
    assert t_cross < t[-1] - 10.0
    after = [r.status for r in out.rul if r.t_s > t_cross + 5.0]
    assert after and all(s == "failed" for s in after)
    assert out.status is not None and out.status.status == "failed" and state.failed
    kinds = {e.kind for e in out.events}
    assert "rul_threshold_crossed" in kinds


def test_model_error_widens_intervals_from_the_streams_own_record() -> None:
    """The future load assumed 30 % too weak: the realized wear outruns the predictions; the
    record measures it and widens the intervals (rul_model_error on), which then cover the
    truth more often than without."""
    drive = drive_of(505, m=0.01, failure_dn=0.5)
    data = fs.simulate_drive(drive, max_s=600.0)
    assert data is not None
    raw = {
        "alpha0": drive.alpha0,
        "rul_failure_dn": 0.5,
        "dn_watch": 0.3,
        "dn_alert": 0.4,
        "rul_every_s": max(2.0, data.t_fail_s / 15.0),
        "rul_trajectories": 100,
        "rul_load": fs.square_wave_law(drive, high_scale=0.7),
    }
    cover = {}
    errs = {}
    for on in (True, False):
        _, out = run({**raw, "rul_model_error": on}, data.t_s, data.channels)
        late = [r for r in out.rul if r.t_s > 0.3 * data.t_fail_s and r.t_s < data.t_fail_s]
        assert late
        truth = [data.t_fail_s - r.t_s for r in late]
        cover[on] = np.mean(
            [
                (r.q05_s or 0.0) <= x <= (r.q95_s if r.q95_s is not None else math.inf)
                for r, x in zip(late, truth, strict=True)
            ]
        )
        errs[on] = float(
            np.median([abs((r.q50_s or 0.0) - x) / x for r, x in zip(late, truth, strict=True)])
        )
        if on:
            assert late[-1].assumption["wear_rate_ratio"] > 1.2
            assert late[-1].assumption["model_error_rel_std"] > 0.1
    assert cover[True] > cover[False] + 0.3


def test_prognose_widening_is_lognormal_and_leaves_the_state_draws() -> None:
    plant = de.parse_config({}).plant_vector
    x = np.array([100.0, 9.0, 8.0, 0.01])
    cov = np.diag([1e-4, 1e-6, 1e-6, 1e-12])
    seg = (np.array([1.0, 1.0]), np.array([20.0, 0.0]))
    settings = rulmod.PrognosisSettings(n_trajectories=400, failure_dn=0.5)
    base = rulmod.prognose(plant, 10.0, x, cov, 0.0, seg, settings)
    wide = rulmod.prognose(plant, 10.0, x, cov, 0.0, seg, settings, log_time_var=0.04)
    assert base.q50_s is not None and wide.q50_s is not None
    assert wide.q50_s == pytest.approx(base.q50_s, rel=0.05)
    spread = np.log(wide.times_s / base.times_s)
    assert np.std(spread) == pytest.approx(0.2, rel=0.15)


def test_split_invariance_with_the_adaptive_parts_on(square: Any) -> None:
    drive, t, ch, _ = square
    config = de.parse_config(
        {"rul_every_s": 7.0, "rul_trajectories": 20, "health_window_samples": 700}
    )
    ref_state, ref = de.step(config, de.initial_state(config), Batch(t_s=t, channels=ch))
    state = de.initial_state(config)
    outs = []
    for lo, hi in ((0, 333), (333, 1500), (1500, 4101), (4101, len(t))):
        state, out = de.step(
            config,
            de.load_state(de.dump_state(state)),
            Batch(t_s=t[lo:hi], channels={k: v[lo:hi] for k, v in ch.items()}),
        )
        outs.append(out)
    for name in de.SAMPLE_OUTPUTS:
        np.testing.assert_array_equal(
            np.concatenate([o.samples[name] for o in outs]), ref.samples[name]
        )
    assert [r for o in outs for r in o.rul] == list(ref.rul)
    assert [w for o in outs for w in o.health] == list(ref.health)
    # the plant calibration ends inside the batch (1500, 4101): the same fit, the same events
    assert any(e.kind.startswith("plant_calibrat") for e in ref.events)
    assert sorted((e.t_s, e.kind) for o in outs for e in o.events) == sorted(
        (e.t_s, e.kind) for e in ref.events
    )
    np.testing.assert_array_equal(state.vector, ref_state.vector)


def _mismatched(seed: int, **changes: Any) -> fs.Drive:
    nominal = fs.FrictionDriveParams()
    plant = dataclasses.replace(
        nominal,
        b1_nm_s=nominal.b1_nm_s * 0.85,
        j1_kg_m2=nominal.j1_kg_m2 * 1.18,
        j2_kg_m2=nominal.j2_kg_m2 * 0.88,
    )
    return drive_of(seed, m=0.01, plant=plant, mismatch=True, **changes)


def _calibration_event(out: Any) -> dict[str, Any]:
    events = [e for e in out.events if e.kind.startswith("plant_calibrat")]
    assert len(events) == 1
    return {"kind": events[0].kind, **events[0].detail}


def test_plant_calibration_removes_the_mismatch_bias() -> None:
    """Friction and inertia off by 12-18 %: without the calibration alpha-hat absorbs the
    mismatch (a bias of about 1 % or more, many of its sigmas); with it B1, J1 and J2 are found
    over the first 20 s and alpha-hat is unbiased afterwards."""
    drive = _mismatched(507)
    t, ch, alpha = fs.telemetry(drive, 60.0)
    after = t > 30.0
    _, off = run({"alpha0": drive.alpha0}, t, ch)
    _, on = run({"alpha0": drive.alpha0, "plant_calibration": True}, t, ch)
    err_off = np.median(np.abs(off.samples["alpha"] / alpha - 1.0)[after])
    err_on = np.median(np.abs(on.samples["alpha"] / alpha - 1.0)[after])
    assert err_off > 5e-3
    assert err_on < 1e-3
    fit = _calibration_event(on)
    assert fit["kind"] == "plant_calibrated" and fit["applied"]
    assert fit["b1_nm_s"] == pytest.approx(drive.plant.b1_nm_s, rel=0.01)
    assert fit["j1_kg_m2"] == pytest.approx(drive.plant.j1_kg_m2, rel=0.02)
    assert fit["j2_kg_m2"] == pytest.approx(drive.plant.j2_kg_m2, rel=0.02)
    assert on.diagnosis.detail["plant_calibration"]["applied"] is True


def test_plant_calibration_finds_and_corrects_the_channel_skew() -> None:
    """The motor speed sampled 1.5 ms after the wheel speed: the fit finds the offset and the
    skew-corrected update removes most of the alpha bias the skew makes."""
    drive = drive_of(509, m=0.01, skew_s=(0.0, 1.5e-3, 0.0))
    t, ch, alpha = fs.telemetry(drive, 60.0)
    after = t > 30.0
    _, off = run({"alpha0": drive.alpha0}, t, ch)
    _, on = run({"alpha0": drive.alpha0, "plant_calibration": True}, t, ch)
    fit = _calibration_event(on)
    assert fit["applied"] and fit["skew_s"] == pytest.approx(1.5e-3, abs=2e-4)
    err_off = np.median(np.abs(off.samples["alpha"] / alpha - 1.0)[after])
    err_on = np.median(np.abs(on.samples["alpha"] / alpha - 1.0)[after])
    assert err_on < 0.3 * err_off


def test_plant_calibration_is_refused_without_excitation() -> None:
    """A constant current gives no transient: the fit is refused with its reason and the
    configured plant stays in use (filter and prognosis)."""
    drive = drive_of(511, m=0.01)
    t, ch, _ = fs.telemetry(drive, 30.0)
    ch = {**ch, "current": np.full_like(ch["current"], 15.0)}
    config = de.parse_config({"alpha0": drive.alpha0, "rul_every_s": 25.0, "rul_trajectories": 20})
    state, out = de.step(config, de.initial_state(config), Batch(t_s=t, channels=ch))
    fit = _calibration_event(out)
    assert fit["kind"] == "plant_calibration_rejected" and not fit["applied"] and fit["reason"]
    assert de.calibrated_plant(config, state.vector) is None
    np.testing.assert_array_equal(de.plant_vector_of(config, state.vector), config.plant_vector)
    assert all(not r.assumption["plant"]["calibrated"] for r in out.rul)


def test_covariance_scaling_makes_the_bands_honest_when_the_noise_is_underestimated() -> None:
    """Sensor noise 30 times the configured variance (noise estimation off): the innovations
    exceed their covariance, the raw bands are too narrow, and the bands scaled by the last
    window's NIS / dof hold alpha; on a consistent stream the scale stays near 1."""
    drive = drive_of(513, m=0.01)
    t, ch, alpha = fs.telemetry(drive, 80.0)
    r_true = np.array(fs.PAPER_NOISE_STD) ** 2 * drive.noise_factor**2
    after = t > 25.0
    shares = {}
    for scaling in (False, True):
        _, out = run(
            {
                "alpha0": drive.alpha0,
                "noise_adaptation": False,
                "r_diag": list(r_true / 30.0),
                "covariance_scaling": scaling,
                "health_window_samples": 1000,
            },
            t,
            ch,
        )
        inside = np.abs(out.samples["alpha"] - alpha) <= out.samples["alpha_3sigma"]
        shares[scaling] = float(np.mean(inside[after]))
        if scaling:
            assert min(w.indicators["covariance_scale"] for w in out.health[1:]) > 5.0
    assert shares[False] < 0.8
    assert shares[True] > 0.97
    _, out = run({"alpha0": drive.alpha0, "noise_adaptation": False, "r_diag": list(r_true)}, t, ch)
    assert max(w.indicators["covariance_scale"] for w in out.health[1:]) < 2.5


def test_version_2_state_loads_and_steps() -> None:
    """Bytes dumped by the version-2 code (before the plant calibration) load, upgrade to the
    current version with no calibration pending (the configured plant stays) and step."""
    state = upgraded_dekf_state(2)
    assert state.initialized
    assert state.vector.shape[0] == kern.ST_BASE_LEN
    assert math.isnan(state.vector[kern.ST_PCAL_END])
    config = de.parse_config(
        {"alpha0": 10.0, "rul_every_s": 1.0, "rul_trajectories": 20, "sample_period_s": 0.001}
    )
    from estimators.simulators.friction_drive import simulate_friction_drive

    t, ch, truth = simulate_friction_drive(5.0, 1000.0, seed=3)
    keep = t > 3.0
    new_state, out = de.step(
        config, state, Batch(t_s=t[keep], channels={k: v[keep] for k, v in ch.items()})
    )
    assert not [e for e in out.events if e.kind.startswith("plant")]
    err = np.abs(out.samples["alpha"] - truth["alpha"][keep])
    assert np.max(err[-500:]) < 0.01


def test_version_1_state_loads_and_steps() -> None:
    """Bytes dumped by the version-1 code (before the adaptive parts) load, upgrade and step;
    an unknown version raises."""
    state = upgraded_dekf_state(1)
    assert state.initialized
    assert state.vector.shape[0] == kern.ST_BASE_LEN
    np.testing.assert_allclose(state.x[2], 9.838, rtol=1e-3)
    config = de.parse_config(
        {"alpha0": 10.0, "rul_every_s": 1.0, "rul_trajectories": 20, "sample_period_s": 0.001}
    )
    from estimators.simulators.friction_drive import simulate_friction_drive

    t, ch, truth = simulate_friction_drive(5.0, 1000.0, seed=3)
    keep = t > 3.0
    new_state, out = de.step(
        config, state, Batch(t_s=t[keep], channels={k: v[keep] for k, v in ch.items()})
    )
    assert math.isfinite(new_state.alpha0) and new_state.alpha0 == 10.0
    err = np.abs(out.samples["alpha"] - truth["alpha"][keep])
    assert np.max(err[-500:]) < 0.01
    with pytest.raises(StateVersionError, match="7"):
        de.load_state((DATA / "deterioration_ekf_state_v1.bin").read_bytes().replace(b'"version":1', b'"version":7'))


def test_profile_segments_merge_within_tolerance() -> None:
    """A recorded profile with 20 ms ramp steps: merged at 0.5 A it keeps its period and mean
    current with far fewer segments, and the prognosis moves by little; at 0 A nothing but
    equal currents merge (the exact profile)."""
    durations, currents = fs.mission_profile(1.0)
    exact = rulmod.load_segments(rulmod.ProfileLoad(durations_s=durations, current_a=currents), 3.0)
    merged = rulmod.load_segments(
        rulmod.ProfileLoad(durations_s=durations, current_a=currents, merge_tolerance_a=0.5), 3.0
    )
    assert exact is not None and merged is not None
    assert len(exact[0]) > 500 and len(merged[0]) < len(exact[0]) / 3
    assert merged[0].sum() == pytest.approx(exact[0].sum(), rel=1e-12)
    assert np.dot(*merged) == pytest.approx(np.dot(*exact), rel=1e-9)
    plant = fs.FrictionDriveParams().as_array()
    settings = rulmod.PrognosisSettings(n_trajectories=20, failure_dn=0.5)
    x = np.array([0.0, 0.0, 10.0, 0.01])
    cov = np.diag([1e-6, 1e-8, 1e-8, 1e-12])
    a = rulmod.prognose(plant, 10.0, x, cov, 3.0, exact, settings)
    b = rulmod.prognose(plant, 10.0, x, cov, 3.0, merged, settings)
    assert a.q50_s is not None and b.q50_s is not None
    assert b.q50_s == pytest.approx(a.q50_s, rel=0.05)


@pytest.mark.parametrize("seed", [511, 512, 513])
def test_record_explains_the_wear_of_an_exact_model(seed: int) -> None:
    """The model exact (plant, load law, constant m), prognoses every 1.37 periods: the
    record's predicted wear between two prognoses is the model's own propagation from the
    previous prognosis' state through the span's current (the load's phase over a span that
    is not a whole number of periods, the speeds' lag and the drift of the rate are in it), so
    the record's relative errors stay near the noise of ln(alpha-hat) and hardly widen the
    intervals. One period's drift-probe rate times the span read the phase as errors of 5-15 %
    rms (model_error_rel_std 0.06-0.14)."""
    drive = drive_of(seed, m=0.01, failure_dn=0.6)
    data = fs.simulate_drive(drive, max_s=600.0)
    assert data is not None
    p = drive.load_params
    raw = {
        "alpha0": drive.alpha0,
        "rul_failure_dn": 0.6,
        "dn_watch": 0.36,
        "dn_alert": 0.48,
        "rul_every_s": round(1.37 * p["period_s"], 3),
        "rul_trajectories": 50,
        "rul_load": fs.square_wave_law(drive),
    }
    state, out = run(raw, data.t_s, data.channels)
    vec = state.vector
    assert vec[kern.ST_ERR_N] >= de.MIN_RECORD
    assert math.sqrt(vec[kern.ST_ERR_SUM2] / vec[kern.ST_ERR_N]) < 0.02
    widen = [r.assumption["model_error_rel_std"] for r in out.rul if r.t_s < data.t_fail_s]
    assert float(np.median(widen)) < 0.03


def test_span_wear_is_the_propagation_through_the_spans_current() -> None:
    """``span_wear`` over 2.5 periods of a square wave equals the wear of the span's segments
    propagated in one piece (first pass of one_period over the span laid out), and differs
    from 2.5 periods' mean wear by where the span starts."""
    from estimators.simulators.friction_drive import FrictionDriveParams

    plant = FrictionDriveParams().as_array()
    seg_d = np.array([0.6, 0.9])
    seg_c = np.array([20.0, 0.0])
    al = 8.0
    s1, s2, *_ = kern.periodic_steady_state(plant, seg_d, seg_c, al)
    state = (s1, s2, math.log(al), 0.005)
    got = rulmod.span_wear(plant, (seg_d, seg_c), state, 2.5 * 1.5, 1e-4)
    laid_d = np.array([0.6, 0.9, 0.6, 0.9, 0.6, 0.15])
    laid_c = np.array([20.0, 0.0, 20.0, 0.0, 20.0, 0.0])
    memo = np.zeros((laid_d.shape[0], kern.MAX_SUB + 2))
    _, _, end, _ = kern.one_period(plant, laid_d, laid_c, s1, s2, math.log(al), 0.005, -math.inf, 1e-4, memo)
    assert got == pytest.approx(math.log(al) - end, rel=1e-6)
    memo = np.zeros((2, kern.MAX_SUB + 2))
    _, _, one, _ = kern.one_period(plant, seg_d, seg_c, s1, s2, math.log(al), 0.005, -math.inf, 1e-4, memo)
    assert got > 1.05 * 2.5 * (math.log(al) - one)  # the span ends after a high part


def test_version_5_state_loads_and_steps() -> None:
    """Bytes dumped by the version-5 code (a square-wave drive, 60 s, three comparisons in the
    prognosis record) load and upgrade to version 6 with the last prognosis' speeds and m-hat
    NaN (the rest unchanged); the first comparison after it is skipped (nothing to predict its
    span from) and the record goes on from the next."""
    state = upgraded_dekf_state(5)
    assert state.vector.shape[0] == kern.ST_BASE_LEN
    assert np.isnan(state.vector[kern.ST_HIST_W : kern.ST_HIST_M + 1]).all()
    n_before = float(state.vector[kern.ST_ERR_N])
    assert n_before > 0.0 and math.isfinite(state.vector[kern.ST_HIST_RATE])
    drive = fs.draw_drive(73_007, rate_hz=100.0, load="square", mismatch=False, skew=False)
    config = de.parse_config(
        {
            "alpha0": drive.alpha0,
            "rul_every_s": 5.0,
            "rul_trajectories": 50,
            "rul_load": fs.square_wave_law(drive),
        }
    )
    t, ch, _ = fs.telemetry(drive, 80.0)
    first = (t > state.t_last_s) & (t <= 62.0)
    mid, out = de.step(config, state, Batch(t_s=t[first], channels={k: v[first] for k, v in ch.items()}))
    assert len(out.rul) == 1
    assert mid.vector[kern.ST_ERR_N] == n_before
    assert np.isfinite(mid.vector[kern.ST_HIST_W : kern.ST_HIST_M + 1]).all()
    rest = t > 62.0
    end, out = de.step(config, mid, Batch(t_s=t[rest], channels={k: v[rest] for k, v in ch.items()}))
    assert len(out.rul) == 3
    assert end.vector[kern.ST_ERR_N] > n_before * de.RECORD_FORGETTING**3
