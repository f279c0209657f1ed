"""RUL prognosis: the closed-form segment solution, the propagation against the simulator's
ground truth, the Monte Carlo statistics and their calibration, load assumptions."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from estimators import rul
from estimators.base import ConfigError
from estimators.kernels import dekf_kernels as kern
from estimators.simulators.friction_drive import (
    FrictionDriveParams,
    SquareWave,
    first_crossing_time,
    simulate_friction_drive,
)

PARAMS = FrictionDriveParams()
PLANT = PARAMS.as_array()


def _memo(segments: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    return np.zeros((len(segments[0]), kern.MAX_SUB + 2))


# ----------------------------------------------------------------------------- segment solution


@pytest.mark.parametrize(
    ("alpha", "current", "w0", "tau"),
    [(10.0, 20.0, (3.0, 1.0), 0.7), (0.05, 20.0, (150.0, 2.0), 1.5), (40.0, -8.0, (0.0, 5.0), 2.0)],
)
def test_segment_matches_an_ode_solver(
    alpha: float, current: float, w0: tuple[float, float], tau: float
) -> None:
    """Frozen alpha: speeds and int dv^2 against DOP853 at rtol 1e-12 (the closed form is exact
    up to round-off, so 1e-9 relative is a loose bound)."""

    def rhs(_t: float, y: np.ndarray) -> list[float]:
        w1, w2, _ = y
        dv = PARAMS.r1_m * w1 - PARAMS.r2_m * w2
        return [
            (-alpha * PARAMS.r1_m * dv - PARAMS.b1_nm_s * w1 + PARAMS.km_nm_a * current)
            / PARAMS.j1_kg_m2,
            (alpha * PARAMS.r2_m * dv - PARAMS.b2_nm_s * w2) / PARAMS.j2_kg_m2,
            dv * dv,
        ]

    sol = solve_ivp(rhs, (0.0, tau), [*w0, 0.0], method="DOP853", rtol=1e-12, atol=1e-12)
    got = kern.segment(PLANT, w0[0], w0[1], alpha, current, tau)
    np.testing.assert_allclose(got, sol.y[:, -1], rtol=1e-9, atol=1e-9)


def test_periodic_steady_state_is_the_limit_of_the_periods() -> None:
    seg_d, seg_c = rul.load_segments(rul.SquareWaveLoad(), 0.3)
    w1, w2 = 0.0, 0.0
    for _ in range(200):  # 400 s, thousands of slowest time constants
        for d, c in zip(seg_d, seg_c, strict=True):
            w1, w2, _ = kern.segment(PLANT, w1, w2, 4.0, c, d)
    ss = kern.periodic_steady_state(PLANT, seg_d, seg_c, 4.0)
    np.testing.assert_allclose(ss[:2], (w1, w2), rtol=1e-10)


# ----------------------------------------------------------------------------- against the truth

# (load in the simulator, assumption, m, failure Dn, sample rate, duration): the fast regime of
# the seed (ln alpha changes by 1-15 % per period), a slow one where cycle jumps are used, an
# asymmetric pulse, a recorded profile and a constant current (started at its equilibrium, with
# a large m so that the steady sliding wears the contact within minutes)
CASES = [
    (SquareWave(), rul.SquareWaveLoad(), 0.01, 0.9, 1000.0, 300.0),
    (SquareWave(), rul.SquareWaveLoad(), 0.0005, 0.6, 250.0, 4000.0),
    (
        SquareWave(high_a=15.0, low_a=-5.0, period_s=3.0, duty=0.3, t0_s=0.4),
        rul.SquareWaveLoad(high_a=15.0, low_a=-5.0, period_s=3.0, duty=0.3, t0_s=0.4),
        0.02,
        0.8,
        1000.0,
        300.0,
    ),
    (
        None,
        rul.ProfileLoad(durations_s=(0.5, 0.25, 0.75), current_a=(10.0, 25.0, 0.0)),
        0.01,
        0.7,
        1000.0,
        300.0,
    ),
    (20.0, rul.ConstantLoad(current_a=20.0), 50.0, 0.8, 200.0, 2000.0),
]


def _profile_current(t: np.ndarray) -> np.ndarray:
    phase = np.mod(t, 1.5)
    return np.where(phase < 0.5 - 1e-9, 10.0, np.where(phase < 0.75 - 1e-9, 25.0, 0.0))


@pytest.mark.parametrize("case", range(len(CASES)))
def test_time_to_failure_matches_the_simulated_truth(case: int) -> None:
    """From the true state at several times, the propagated time to the threshold equals the
    simulated one within 2e-3 relative: the midpoint rule at rul_segment_tol = 0.01 has shown
    relative errors of 1e-4 to 7e-4 on these plants (bias toward early failure), and the cycle
    jumps below 1e-4."""
    sim_load, load, m, failure_dn, fs, duration = CASES[case]
    current = _profile_current(np.arange(int(duration * fs)) / fs) if sim_load is None else sim_load
    start = (0.0, 0.0)
    if isinstance(load, rul.ConstantLoad):
        seg = rul.load_segments(load, 0.0)
        start = kern.periodic_steady_state(PLANT, seg[0], seg[1], 10.0)[:2]
    t, _, tr = simulate_friction_drive(
        duration, fs, m=m, current=current, stop_dn=failure_dn + 0.01, initial_speeds=start
    )
    t_fail = first_crossing_time(t, tr["dn"], failure_dn)
    assert t_fail is not None
    for frac in (0.0, 0.35, 0.7, 0.95):
        k = int(frac * t_fail * fs) + 7
        segments = rul.load_segments(load, float(t[k]))
        got = kern.time_to_failure(
            PLANT,
            segments[0],
            segments[1],
            tr["w1"][k],
            tr["w2"][k],
            tr["alpha"][k],
            m,
            math.log(10.0 * (1.0 - failure_dn)),
            1e9,
            0.01,
            0.25,
            _memo(segments),
        )
        true = t_fail - t[k]
        assert got == pytest.approx(true, rel=2e-3, abs=2.0 / fs)


def test_never_and_already_failed() -> None:
    segments = rul.load_segments(rul.SquareWaveLoad(), 0.0)
    args = (math.log(1.0), 1e9, 0.01, 0.25, _memo(segments))
    assert math.isnan(kern.time_to_failure(PLANT, *segments, 0.0, 0.0, 5.0, -0.01, *args))
    assert math.isnan(kern.time_to_failure(PLANT, *segments, 0.0, 0.0, 5.0, 0.0, *args))
    assert kern.time_to_failure(PLANT, *segments, 0.0, 0.0, 0.9, 0.01, *args) == 0.0
    assert kern.time_to_failure(PLANT, *segments, 0.0, 0.0, -1.0, 0.01, *args) == 0.0
    # no current: no sliding, alpha never changes
    idle = (np.array([1.0]), np.array([0.0]))
    assert math.isnan(kern.time_to_failure(PLANT, *idle, 0.0, 0.0, 5.0, 0.01, *args))
    # beyond the horizon
    short = (math.log(1.0), 10.0, 0.01, 0.25, _memo(segments))
    assert math.isnan(kern.time_to_failure(PLANT, *segments, 0.0, 0.0, 9.0, 0.01, *short))


# ----------------------------------------------------------------------------- Monte Carlo


def _estimate() -> tuple[np.ndarray, np.ndarray]:
    seg_d, seg_c = rul.load_segments(rul.SquareWaveLoad(), 0.0)
    w1, w2 = kern.periodic_steady_state(PLANT, seg_d, seg_c, 8.0)[:2]
    x = np.array([w1, w2, 8.0, 0.01])
    sd = np.array([1e-4, 1e-5, 2e-3, 4e-4])
    corr = np.array(
        [[1.0, 0.3, 0.1, 0.0], [0.3, 1.0, 0.2, 0.1], [0.1, 0.2, 1.0, -0.5], [0.0, 0.1, -0.5, 1.0]]
    )
    return x, corr * np.outer(sd, sd)


def test_monte_carlo_is_calibrated_when_the_truth_is_drawn_from_the_estimate() -> None:
    """If the true state is a draw from N(x, P), the true RUL falls in the Monte Carlo [q05,
    q95] with probability 0.9: over 300 draws the hit rate is within 0.9 +- 3 binomial standard
    deviations (0.017)."""
    x, cov = _estimate()
    segments = rul.load_segments(rul.SquareWaveLoad(), 0.0)
    settings = rul.PrognosisSettings(failure_dn=0.8, n_trajectories=2000)
    res = rul.prognose(PLANT, 10.0, x, cov, 0.0, segments, settings)
    assert res.reached_fraction == 1.0
    truths = np.random.default_rng(5).multivariate_normal(x, cov, size=300)
    true_rul = kern.rul_times(PLANT, *segments, truths, math.log(2.0), 1e7, 0.01, 0.25)
    hits = np.mean((true_rul >= res.q05_s) & (true_rul <= res.q95_s))
    assert 0.9 - 3 * 0.017 <= hits <= 0.9 + 3 * 0.017
    assert res.pessimistic_s < res.q05_s < res.q50_s < res.q95_s < res.optimistic_s
    assert res.mean_s == pytest.approx(float(np.mean(res.times_s)))
    assert res.std_s == pytest.approx(float(np.std(res.times_s)))


def test_prognosis_is_deterministic_per_time_and_seed() -> None:
    x, cov = _estimate()
    segments = rul.load_segments(rul.SquareWaveLoad(), 3.0)
    settings = rul.PrognosisSettings(n_trajectories=50)
    a = rul.prognose(PLANT, 10.0, x, cov, 3.0, segments, settings)
    b = rul.prognose(PLANT, 10.0, x, cov, 3.0, segments, settings)
    c = rul.prognose(PLANT, 10.0, x, cov, 3.0 + 1e-9, segments, settings)
    np.testing.assert_array_equal(a.times_s, b.times_s)
    assert not np.array_equal(a.times_s, c.times_s)
    assert a.entropy[0] == 0 and a.entropy != c.entropy


def test_censored_statistics() -> None:
    """m straddling 0: trajectories with m <= 0 never fail; the mean is then undefined and the
    95 % quantile too when more than 5 % do not reach the threshold."""
    x, cov = _estimate()
    cov = cov.copy()
    cov[3, 3] = (0.01 / 1.2) ** 2  # P(m <= 0) = 0.2
    cov[3, :3] = cov[:3, 3] = 0.0
    segments = rul.load_segments(rul.SquareWaveLoad(), 0.0)
    res = rul.prognose(
        PLANT, 10.0, x, cov, 0.0, segments, rul.PrognosisSettings(n_trajectories=400)
    )
    assert 0.7 < res.reached_fraction < 0.9
    assert res.mean_s is None and res.std_s is None and res.q95_s is None
    assert res.q05_s is not None and res.q50_s is not None
    assert res.optimistic_s is None  # m - 3 s_m < 0
    sorted_times = np.sort(np.where(np.isfinite(res.times_s), res.times_s, np.inf))
    assert res.q50_s == pytest.approx(
        np.quantile(sorted_times[np.isfinite(sorted_times)], 0.5 / res.reached_fraction), rel=0.05
    )


def test_quantile_and_covariance_factor() -> None:
    s = np.array([1.0, 2.0, 3.0, np.inf])
    assert rul.quantile_or_none(s, 0.5) == pytest.approx(np.quantile([1.0, 2.0, 3.0, 4.0], 0.5))
    assert rul.quantile_or_none(s, 0.95) is None
    singular = np.diag([1.0, 0.0, 4.0, 0.0])
    singular[0, 2] = singular[2, 0] = 2.0  # rank 1 block
    fac = rul.covariance_factor(singular)
    np.testing.assert_allclose(fac @ fac.T, singular, atol=1e-12)


# ----------------------------------------------------------------------------- load laws


def test_load_segments_are_phased_by_stream_time() -> None:
    load = rul.SquareWaveLoad(high_a=20.0, low_a=0.0, period_s=2.0, duty=0.5, t0_s=0.5)
    d, c = rul.load_segments(load, 0.75)  # 0.25 s into the high half
    np.testing.assert_allclose(d, [0.75, 1.0, 0.25])
    np.testing.assert_allclose(c, [20.0, 0.0, 20.0])
    d, c = rul.load_segments(load, 2.5)  # exactly on a rising edge
    np.testing.assert_allclose(d, [1.0, 1.0])
    np.testing.assert_allclose(c, [20.0, 0.0])
    d, c = rul.load_segments(rul.ConstantLoad(current_a=5.0), 123.0)
    assert c.tolist() == [5.0] and d.tolist() == [rul.CONSTANT_SEGMENT_S]
    profile = rul.ProfileLoad(durations_s=(1.0, 2.0, 3.0), current_a=(1.0, 2.0, 3.0), t0_s=0.0)
    d, c = rul.load_segments(profile, 6.0 + 2.0)  # 1 s into the second segment
    np.testing.assert_allclose(d, [1.0, 3.0, 1.0, 1.0])
    np.testing.assert_allclose(c, [2.0, 3.0, 1.0, 2.0])
    observed = rul.ObservedLoad(bins=4, merge_tolerance_a=0.1)
    assert rul.load_segments(observed, 0.0, (np.ones(3), np.ones(3))) is None
    d, c = rul.load_segments(observed, 0.0, (np.ones(4), np.array([1.0, 1.05, 5.0, 5.0])))
    np.testing.assert_allclose(d, [2.0, 2.0])
    np.testing.assert_allclose(c, [1.025, 5.0])


@pytest.mark.parametrize(
    ("raw", "match"),
    [
        ({"kind": "sine"}, "kind"),
        ({"kind": "square_wave", "period_s": 0.0}, "period_s"),
        ({"kind": "square_wave", "duty": 1.0}, "duty"),
        ({"kind": "square_wave", "high": 1.0}, r"rul_load.high: Extra inputs"),
        ({"kind": "constant", "current_a": float("nan")}, "current_a"),
        ({"kind": "profile", "durations_s": [1.0], "current_a": [1.0, 2.0]}, "equal length"),
        ({"kind": "profile", "durations_s": [1.0, -1.0], "current_a": [1.0, 2.0]}, "durations_s"),
        ({"kind": "observed", "bins": 0}, "bins"),
        ({"kind": "observed", "merge_tolerance_a": -1.0}, "merge_tolerance_a"),
        ([1, 2], "object"),
    ],
)
def test_bad_load_assumptions(raw: object, match: str) -> None:
    with pytest.raises(ConfigError, match=match):
        rul.parse_load(raw)


def test_load_round_trip() -> None:
    for load in (
        rul.SquareWaveLoad(high_a=3.0),
        rul.ConstantLoad(current_a=7.0),
        rul.ProfileLoad(durations_s=(1.0, 2.0), current_a=(0.0, 4.0), t0_s=1.0),
        rul.ObservedLoad(bins=10),
    ):
        assert rul.parse_load(rul.load_to_dict(load)) == load


def _mission_samples(alpha: float, m: float, m_rel: float, n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.column_stack(
        [
            5.0 + 1e-3 * rng.standard_normal(n),
            0.45 + 1e-4 * rng.standard_normal(n),
            alpha * (1.0 + 0.02 * rng.standard_normal(n)),
            m * (1.0 + m_rel * rng.standard_normal(n)),
        ]
    )


@pytest.mark.parametrize(("alpha", "m", "m_rel"), [(9.5, 0.01, 0.05), (5.0, 0.003, 0.1)])
def test_tabulated_times_match_the_period_by_period_propagation(
    alpha: float, m: float, m_rel: float
) -> None:
    """The shared per-period wear table gives the times of the period-by-period propagation on
    the drive generator's mission profile (130 segments per 14 s after merging at 0.5 A): the
    quantiles within 0.5 %, each trajectory within 2 %, the median error below 1e-3."""
    from estimators.simulators.friction_drive_scenarios import mission_profile

    durations, currents = mission_profile(1.0)
    load = rul.ProfileLoad(durations_s=durations, current_a=currents, merge_tolerance_a=0.5)
    segments = rul.load_segments(load, 15.0)
    assert segments is not None
    seg_d = np.ascontiguousarray(segments[0])
    seg_c = np.ascontiguousarray(segments[1])
    assert seg_d.shape[0] >= rul.PrognosisSettings().table_min_segments
    samples = _mission_samples(alpha, m, m_rel, 120, seed=11)
    args = (math.log(1.0), 1e7, 0.01, 0.25)
    exact = kern.rul_times(PLANT, seg_d, seg_c, samples, *args)
    table = kern.rul_times_tabulated(PLANT, seg_d, seg_c, samples, *args)
    assert np.all(np.isfinite(exact)) and np.all(np.isfinite(table))
    assert float(np.median(exact)) > 8 * 14.0  # the table's regime: many periods to go
    rel = table / exact - 1.0
    assert float(np.max(np.abs(rel))) < 0.02
    assert abs(float(np.median(rel))) < 1e-3
    for q in (0.05, 0.5, 0.95):
        assert float(np.quantile(table, q)) == pytest.approx(float(np.quantile(exact, q)), rel=5e-3)


def test_tabulated_times_fall_back_for_short_lives_and_special_samples() -> None:
    """A life of a few periods, a non-positive m, a failed or non-finite sample: the same times
    as the period-by-period propagation."""
    from estimators.simulators.friction_drive_scenarios import mission_profile

    durations, currents = mission_profile(1.0)
    load = rul.ProfileLoad(durations_s=durations, current_a=currents, merge_tolerance_a=0.5)
    segments = rul.load_segments(load, 15.0)
    assert segments is not None
    seg_d = np.ascontiguousarray(segments[0])
    seg_c = np.ascontiguousarray(segments[1])
    samples = _mission_samples(2.0, 0.02, 0.2, 20, seed=3)
    samples[0, 3] = -0.001
    samples[1, 2] = 0.5  # below alpha_f = 1
    samples[2, 0] = np.nan
    args = (math.log(1.0), 1e7, 0.01, 0.25)
    exact = kern.rul_times(PLANT, seg_d, seg_c, samples, *args)
    table = kern.rul_times_tabulated(PLANT, seg_d, seg_c, samples, *args)
    np.testing.assert_array_equal(np.isnan(table), np.isnan(exact))
    np.testing.assert_allclose(table, exact, rtol=1e-12, equal_nan=True)
    assert table[1] == 0.0 and np.isnan(table[0]) and np.isnan(table[2])


def _cloud_estimate(alpha: float, m: float, rel_alpha: float, rel_m: float) -> tuple[np.ndarray, np.ndarray]:
    """An estimate and a covariance like the filter's (speeds near their steady state, alpha
    and m negatively correlated)."""
    x = np.array([139.7, 12.0, alpha, m])
    sd = np.array([3e-5, 1e-6, rel_alpha * alpha, rel_m * m])
    corr = np.eye(4)
    corr[0, 1] = corr[1, 0] = 0.6
    corr[2, 3] = corr[3, 2] = -0.5
    corr[0, 2] = corr[2, 0] = 0.2
    return x, corr * np.outer(sd, sd)


def _telegraph_dwells(seed: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    level = np.cumsum(rng.random(1500) < 0.04) % 2
    dl = rul.dwell_load(np.full(1500, 0.02), np.where(level == 1, 20.0, 0.0), 16, 0.05)
    assert dl is not None
    return dl.durations_s, dl.currents_a


def _fit_cases() -> list[tuple[str, tuple[np.ndarray, np.ndarray], float, float]]:
    square = rul.load_segments(rul.SquareWaveLoad(), 3.3)
    constant = rul.load_segments(rul.ConstantLoad(current_a=20.0), 0.0)
    assert square is not None and constant is not None
    return [
        ("square wave, fast wear", square, 9.2, 0.013),
        ("square wave, slow wear (cycle jumps)", square, 9.0, 0.001),
        ("constant 20 A", constant, 9.5, 0.01),
        ("telegraph read as dwells", _telegraph_dwells(17), 9.0, 0.01),
        ("telegraph read as dwells, slow wear", _telegraph_dwells(23), 9.0, 0.002),
    ]


@pytest.mark.parametrize("case", range(5))
def test_fitted_times_match_the_period_by_period_propagation(case: int) -> None:
    """Loads of fewer segments than the table's: the Monte Carlo times come from the response
    surface (and say so), each within FIT_TOL of the period-by-period propagation of the same
    samples, the quantiles within 2e-4."""
    _, segments, alpha, m = _fit_cases()[case]
    x, cov = _cloud_estimate(alpha, m, 2e-3, 0.02)
    settings = rul.PrognosisSettings(n_trajectories=400, failure_dn=0.9)
    t_s = 41.0 + case
    res = rul.prognose(PLANT, 10.0, x, cov, t_s, segments, settings)
    assert res.propagation == "fitted"
    rng, _ = rul.prognosis_rng(settings.seed, t_s)
    z = rng.standard_normal((settings.n_trajectories, 4))
    samples = np.ascontiguousarray(x[None, :] + z @ rul.covariance_factor(cov).T)
    exact = kern.rul_times(
        PLANT, np.ascontiguousarray(segments[0]), np.ascontiguousarray(segments[1]), samples,
        math.log(10.0 * (1.0 - settings.failure_dn)), settings.horizon_s, settings.eps_seg,
        settings.eps_jump,
    )  # fmt: skip
    assert np.all(np.isfinite(exact))
    rel = res.times_s / exact - 1.0
    assert float(np.max(np.abs(rel))) <= rul.FIT_TOL
    for q in (0.05, 0.5, 0.95):
        assert float(np.quantile(res.times_s, q)) == pytest.approx(
            float(np.quantile(exact, q)), rel=2e-4
        )
    # a surface that ignored the samples' spread would not pass: the times do spread
    assert float(np.std(np.log(exact))) > 10.0 * rul.FIT_TOL


def test_fitted_times_fall_back_where_the_surface_does_not_hold() -> None:
    """A cloud with samples that never wear (m spread wider than m), too few trajectories, or
    lives beyond the horizon: every sample is propagated, with the propagation's times."""
    square = rul.load_segments(rul.SquareWaveLoad(), 3.3)
    assert square is not None
    seg_d = np.ascontiguousarray(square[0])
    seg_c = np.ascontiguousarray(square[1])
    x, cov = _cloud_estimate(9.2, 0.013, 2e-3, 0.02)
    fitted = rul.prognose(PLANT, 10.0, x, cov, 5.0, square, rul.PrognosisSettings(n_trajectories=400))
    assert fitted.propagation == "fitted"
    in_cloud = float(np.median(fitted.times_s))  # a horizon inside the cloud of times
    for rel_m, n, horizon in ((2.0, 400, 1e7), (0.02, 150, 1e7), (0.02, 400, in_cloud)):
        x, cov = _cloud_estimate(9.2, 0.013, 2e-3, rel_m)
        settings = rul.PrognosisSettings(n_trajectories=n, horizon_s=horizon)
        res = rul.prognose(PLANT, 10.0, x, cov, 5.0, square, settings)
        assert res.propagation == "exact"
        rng, _ = rul.prognosis_rng(settings.seed, 5.0)
        z = rng.standard_normal((n, 4))
        samples = np.ascontiguousarray(x[None, :] + z @ rul.covariance_factor(cov).T)
        ell_fail = math.log(10.0 * (1.0 - settings.failure_dn))
        exact = kern.rul_times(PLANT, seg_d, seg_c, samples, ell_fail, horizon, 0.01, 0.25)
        np.testing.assert_array_equal(res.times_s, exact)


def test_composite_design_is_rotatable_and_fits_a_quadratic_exactly() -> None:
    """The 25 design points in 4 dimensions lie on three spheres (centre, radius r), and a
    quadratic is recovered from them to rounding."""
    dz = rul.composite_design(4, 3.0)
    assert dz.shape == (25, 4)
    radii = np.sqrt((dz * dz).sum(axis=1))
    np.testing.assert_allclose(np.sort(radii)[1:], 3.0, rtol=1e-12)
    coef = np.arange(1.0, 16.0) / 7.0
    fit = np.linalg.lstsq(rul.quadratic_features(dz), rul.quadratic_features(dz) @ coef, rcond=None)
    np.testing.assert_allclose(fit[0], coef, rtol=1e-10)


def test_wear_clock_and_its_inverse() -> None:
    """The steady-state wear clock grows by the period's wear each period and its inverse
    gives back the times, inside and across segments."""
    segments = _telegraph_dwells(29)
    seg_d = np.ascontiguousarray(segments[0])
    seg_c = np.ascontiguousarray(segments[1])
    period = float(seg_d.sum())
    t = np.array([0.0, 0.013, 0.4 * period, period, 3.7 * period + 0.01, 41.0 * period])
    clock = kern.wear_clock(PLANT, seg_d, seg_c, 1.0, t)
    assert clock[0] == 0.0 and np.all(np.diff(clock) > 0.0)
    per = kern.wear_clock(PLANT, seg_d, seg_c, 1.0, np.array([period, 2.0 * period]))
    assert per[1] == pytest.approx(2.0 * per[0], rel=1e-12)
    np.testing.assert_allclose(kern.wear_clock_times(PLANT, seg_d, seg_c, 1.0, clock), t, rtol=1e-10, atol=1e-12)
