"""SHA/EMA simulator: determinism, plant equations (seed eqs. 1-13), fault schedules, noise."""

from __future__ import annotations

import math

import numpy as np
import pytest

from estimators.simulators.sha_ema import (
    CHANNELS,
    DEFAULT_NOISE_STD,
    PAPER_SCENARIO,
    FaultSchedule,
    ShaEmaParams,
    parameter_trajectories,
    simulate_sha_ema,
)

NO_NOISE = {c: 0.0 for c in CHANNELS}


def test_seeded_deterministic_and_shaped() -> None:
    t, a, truth_a = simulate_sha_ema(0.5, seed=3)
    _, b, _ = simulate_sha_ema(0.5, seed=3)
    _, c, truth_c = simulate_sha_ema(0.5, seed=4)
    assert t.shape == (5000,) and t[0] == 0.0
    assert np.allclose(np.diff(t), 1e-4)
    assert tuple(a) == CHANNELS
    for name in CHANNELS:
        assert a[name].dtype == np.float64 and a[name].shape == t.shape
        np.testing.assert_array_equal(a[name], b[name])
    assert not np.array_equal(a["v_p"], c["v_p"])
    # the inputs carry no noise by default, and the plant barely depends on the seed (only
    # through the tiny process disturbances)
    np.testing.assert_array_equal(a["u_a"], c["u_a"])
    scale = np.max(np.abs(truth_a.states["p_l"]))
    assert np.max(np.abs(truth_a.states["p_l"] - truth_c.states["p_l"])) < 1e-3 * scale


def _central(x: np.ndarray, dt: float) -> np.ndarray:
    return (x[2:] - x[:-2]) / (2.0 * dt)


def test_noise_free_truth_satisfies_the_plant_equations() -> None:
    """Seed eqs. 5-6, 7-8, 11 and 13 by central differences on the noise-free truth.

    Tolerance: 1e-3 of the largest term. Central differences at 10 kHz err by about
    (w dt)^2 / 6 on a component of angular frequency w; the fastest mode that matters here
    (piston on the rod stiffness, sqrt(K_2 / m_h) = 1.3e3 rad/s) gives 3e-3 of its own
    amplitude, which is a small part of each equation's terms.
    """
    dt = 1e-4
    _, _, truth = simulate_sha_ema(1.0, seed=0, noise_std=NO_NOISE, process_noise_var=0.0)
    p = truth.nominal
    s = {k: v[1:-1] for k, v in truth.states.items()}
    d = {k: _central(v, dt) for k, v in truth.states.items()}

    def check(terms: list[np.ndarray]) -> None:
        total = np.sum(terms, axis=0)
        scale = max(float(np.max(np.abs(x))) for x in terms)
        assert float(np.sqrt(np.mean(total**2))) < 1e-3 * scale

    # cylinder (2, 5): K_q x_v - K_c P_L = A_h v_p + C_hj P_L' + P_L / R_il
    check(
        [
            p.k_q * s["x_v"],
            -p.k_c * s["p_l"],
            -p.a_h * s["v_p"],
            -p.c_hj * d["p_l"],
            -s["p_l"] / p.r_il,
        ]
    )
    # piston (6): A_h P_L = m_h v_p' + B_h v_p + F_H
    check([p.a_h * s["p_l"], -p.m_h * d["v_p"], -p.b_h * s["v_p"], -s["f_h"]])
    # motor (7), (8) with T_m = (P / 2 pi) F_c
    check([s["u_a"], -p.l_w * d["i_m"], -p.r_w * s["i_m"], -p.k_m * s["w"]])
    tm = p.lead / (2 * math.pi) * s["f_c"]
    check([p.k_m * s["i_m"], -p.j_m * d["w"], -p.f_m * s["w"], p.s_e * np.ones_like(tm), -tm])
    # screw mass (11): F_c = f_r v + m v' + F_E
    check([s["f_c"], -p.f_r * s["v"], -p.m_screw * d["v"], -s["f_e"]])
    # surface (13): F_E + F_H + F_1 = m_r v_1' + B_d v_1 + K_d x_1
    check(
        [
            s["f_e"],
            s["f_h"],
            p.f_1 * np.ones_like(s["f_e"]),
            -p.m_r * d["v_1"],
            -p.b_d * s["v_1"],
            -p.k_d * s["x_1"],
        ]
    )


def test_measurement_noise_has_the_configured_level() -> None:
    _, ch, truth = simulate_sha_ema(1.0, seed=2)
    for name in ("w", "f_h", "v_p", "p_l"):
        err = ch[name] - truth.states[name]
        # 10^4 samples: the sample std is within 3 % of the true std at > 5 sigma
        assert np.std(err) == pytest.approx(DEFAULT_NOISE_STD[name], rel=0.03)
    np.testing.assert_array_equal(ch["x_v"], truth.states["x_v"])
    _, quiet, truth_q = simulate_sha_ema(0.2, seed=2, noise_std={"p_l": 0.0})
    np.testing.assert_array_equal(quiet["p_l"], truth_q.states["p_l"])


def test_fault_schedule_profiles() -> None:
    nominal = ShaEmaParams()
    t = np.arange(0.0, 10.0, 0.5)
    traj = parameter_trajectories(PAPER_SCENARIO, nominal, t)
    a_h, b_h = traj["a_h"], traj["b_h"]
    assert a_h[t < 4.0].tolist() == [nominal.a_h] * int(np.sum(t < 4.0))
    # linear from 1.47e-3 at 4 s to 1.275e-3 at 7 s, held after
    assert a_h[t == 5.5][0] == pytest.approx(1.47e-3 + 0.5 * (1.275e-3 - 1.47e-3))
    assert np.all(a_h[t >= 7.0] == 1.275e-3)
    assert np.all(b_h[(t >= 4.0) & (t < 6.0)] == 6000.0)
    assert np.all(b_h[t >= 6.0] == 4000.0)
    assert np.all(b_h[t < 4.0] == 1.0e4)
    step = parameter_trajectories(
        [FaultSchedule("k_s", 2.0, "step", value=1.0e8, end_s=3.0)], nominal, t
    )["k_s"]
    assert step[t == 2.5][0] == 1.0e8 and step[t == 3.0][0] == nominal.k_s
    # two faults on one parameter chain: the ramp starts from the step's value
    chained = parameter_trajectories(
        [
            FaultSchedule("r_il", 1.0, "step", value=4.0e11),
            FaultSchedule("r_il", 2.0, "gradual", value=2.0e11, end_s=4.0),
        ],
        nominal,
        t,
    )["r_il"]
    assert chained[t == 3.0][0] == pytest.approx(3.0e11)


def test_faults_change_the_plant_only_after_they_start() -> None:
    kw = {"noise_std": NO_NOISE, "process_noise_var": 0.0, "seed": 0}
    t, _, base = simulate_sha_ema(5.0, **kw)
    _, _, faulty = simulate_sha_ema(5.0, faults=PAPER_SCENARIO, **kw)
    before = t < 4.0
    np.testing.assert_array_equal(base.states["v_p"][before], faulty.states["v_p"][before])
    assert np.max(np.abs(base.states["v_p"][~before] - faulty.states["v_p"][~before])) > 1e-4
    assert faulty.parameter("b_h", 45_000) == 6000.0
    assert faulty.parameter("m_h", 45_000) == base.nominal.m_h


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"parameter": "nope", "start_s": 1.0, "profile": "step", "value": 1.0}, "nope"),
        ({"parameter": "a_h", "start_s": 1.0, "profile": "step"}, "value"),
        ({"parameter": "a_h", "start_s": 1.0, "profile": "gradual", "value": 1.0}, "end_s"),
        (
            {"parameter": "a_h", "start_s": 1.0, "profile": "values", "values": ((2.0, 1.0),)},
            "values",
        ),
        ({"parameter": "a_h", "start_s": 1.0, "profile": "ramp", "value": 1.0}, "profile"),
    ],
)
def test_bad_fault_schedules_are_refused(kwargs, match) -> None:
    with pytest.raises(ValueError, match=match):
        FaultSchedule(**kwargs)


def test_bad_arguments_are_refused() -> None:
    with pytest.raises(ValueError, match="unknown SHA/EMA parameter"):
        simulate_sha_ema(0.1, params={"bogus": 1.0})
    with pytest.raises(ValueError, match="noise_std"):
        simulate_sha_ema(0.1, noise_std={"bogus": 1.0})
    with pytest.raises(ValueError):
        simulate_sha_ema(-1.0)
