"""darr_fekf speed: residual evaluation and subsystem filters in ns per sample, against
filterpy and against one global EKF over all states and parameters (the cost the seed's
distributed form avoids).

Prints figures and ratios measured side by side in one run; asserts nothing.
Run: ``.venv/bin/python bench/bench_darr_fekf.py``.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable

import numpy as np
from filterpy.kalman import ExtendedKalmanFilter
from numba import njit

from estimators import darr_fekf as m
from estimators.base import Batch
from estimators.kernels import darr_kernels as kern
from estimators.simulators.sha_ema import CHANNELS, PAPER_SCENARIO, ShaEmaParams, simulate_sha_ema

NS = 1e9


def best_of(fn: Callable[[], object], repeats: int) -> float:
    best = math.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


# ----------------------------------------------------------------------------- subsystem filters
@njit(cache=True)
def _relation_loop(sc, kinds, chans, orders, coefs, exps, ss, sigs, dt, vec, mats) -> float:
    for k in range(sigs.shape[0]):
        kern.relation_step(sc, kinds, chans, orders, coefs, exps, ss, sigs[k], True, dt, vec, mats)
    return ss[kern.SS_Z]


def relation_filter_ns(config: m.DarrFekfConfig, key: str, sigs: np.ndarray) -> float:
    comp = config.compiled
    i = list(config.subsystems).index(key)
    ss = np.zeros(kern.SS_LEN)
    kern.subsystem_start(comp.sub_cfg[i], ss, 0.0, 0.0, 1e-12, 1e-12)
    vec = np.zeros((kern.WV_ROWS, kern.WV_LEN))
    mats = np.zeros((3, kern.MAX_DIM, kern.MAX_DIM))
    args = (
        comp.sub_cfg[i],
        comp.sub_kind[i],
        comp.sub_chan[i],
        comp.sub_order[i],
        comp.sub_coef[i],
        comp.sub_exp[i],
    )

    def call() -> None:
        ss2 = ss.copy()
        _relation_loop(*args, ss2, sigs, 1e-4, vec, mats)

    call()
    return best_of(call, 5) / sigs.shape[0] * NS


def filterpy_relation_ns(config: m.DarrFekfConfig, sigs: np.ndarray) -> float:
    """filterpy's ExtendedKalmanFilter on subsystem 7's relation (A_h, R_il, C_hj)."""
    p = config.parameters
    v_p, p_l, x_v = CHANNELS.index("v_p"), CHANNELS.index("p_l"), CHANNELS.index("x_v")

    def h_jac(x: np.ndarray, s: np.ndarray) -> np.ndarray:
        return np.array(
            [
                [
                    -p["a_h"] * s[v_p, 0],
                    p["r_il"] ** -1 * x[1, 0] ** -2 * s[p_l, 0],
                    -p["c_hj"] * s[p_l, 1],
                ]
            ]
        )

    def hx(x: np.ndarray, s: np.ndarray) -> np.ndarray:
        r = (
            p["k_q"] * s[x_v, 0]
            - p["k_c"] * s[p_l, 0]
            - p["a_h"] * x[0, 0] * s[v_p, 0]
            - s[p_l, 0] / (p["r_il"] * x[1, 0])
            - p["c_hj"] * x[2, 0] * s[p_l, 1]
        )
        return np.array([[r]])

    n = 3000

    def call() -> None:
        ekf = ExtendedKalmanFilter(dim_x=3, dim_z=1)
        ekf.x = np.ones((3, 1))
        ekf.P = np.eye(3) * 1e-2
        ekf.Q = np.eye(3) * 1e-8
        ekf.R = np.array([[1e-14]])
        zero = np.zeros((1, 1))
        for k in range(n):
            ekf.predict()
            ekf.update(zero, h_jac, hx, args=(sigs[k],), hx_args=(sigs[k],))

    return best_of(call, 2) / n * NS


# ----------------------------------------------------------------------------- global EKF
N_X = 10  # P_L, v_p, F_H, i_m, w, F_c, v, F_E, v_1, x_1 (x_v and U_a are measured inputs)
GLOBAL_PARAMS = tuple(m.PARAMETER_NAMES)
N_G = N_X + len(GLOBAL_PARAMS)
SENSORS = (4, 5, 6, 7, 2, 1, 0)  # w, F_c, v, F_E, F_H, v_p, P_L as state indices
PI = {name: i for i, name in enumerate(GLOBAL_PARAMS)}


@njit(cache=True)
def _global_rhs(x, th, x_v, u_a, f_1, out, jac) -> None:
    """The plant (seed eqs. 2-13) with all 22 parameters as states, and its Jacobian."""
    k_q, k_c, c_hj, r_il, a_h, b_h, m_h, k_2, m_r, b_d, f_m = th[0:11]
    f_r, r_w, k_m, j_m, s_e, lead, k_s, k_1, m_s, l_w, k_d = th[11:22]
    p_l, v_p, f_h, i_m, w, f_c, v, f_e, v_1, x_1 = x[0:10]
    tr = lead / (2.0 * math.pi)
    q = k_q * x_v - k_c * p_l - a_h * v_p - p_l / r_il
    out[0] = q / c_hj
    fp = a_h * p_l - b_h * v_p - f_h
    out[1] = fp / m_h
    out[2] = k_2 * (v_p - v_1)
    ue = u_a - r_w * i_m - k_m * w
    out[3] = ue / l_w
    tq = k_m * i_m - f_m * w + s_e - tr * f_c
    out[4] = tq / j_m
    out[5] = k_s * (tr * w - v)
    fs = f_c - f_r * v - f_e
    out[6] = fs / m_s
    out[7] = k_1 * (v - v_1)
    fsurf = f_e + f_h + f_1 - b_d * v_1 - k_d * x_1
    out[8] = fsurf / m_r
    out[9] = v_1
    jac[:, :] = 0.0
    o = N_X
    jac[0, 0] = (-k_c - 1.0 / r_il) / c_hj
    jac[0, 1] = -a_h / c_hj
    jac[0, o + 0] = x_v / c_hj
    jac[0, o + 1] = -p_l / c_hj
    jac[0, o + 2] = -q / (c_hj * c_hj)
    jac[0, o + 3] = p_l / (r_il * r_il * c_hj)
    jac[0, o + 4] = -v_p / c_hj
    jac[1, 0] = a_h / m_h
    jac[1, 1] = -b_h / m_h
    jac[1, 2] = -1.0 / m_h
    jac[1, o + 4] = p_l / m_h
    jac[1, o + 5] = -v_p / m_h
    jac[1, o + 6] = -fp / (m_h * m_h)
    jac[2, 1] = k_2
    jac[2, 8] = -k_2
    jac[2, o + 7] = v_p - v_1
    jac[3, 3] = -r_w / l_w
    jac[3, 4] = -k_m / l_w
    jac[3, o + 12] = -i_m / l_w
    jac[3, o + 13] = -w / l_w
    jac[3, o + 20] = -ue / (l_w * l_w)
    jac[4, 3] = k_m / j_m
    jac[4, 4] = -f_m / j_m
    jac[4, 5] = -tr / j_m
    jac[4, o + 10] = -w / j_m
    jac[4, o + 13] = i_m / j_m
    jac[4, o + 14] = -tq / (j_m * j_m)
    jac[4, o + 15] = 1.0 / j_m
    jac[4, o + 16] = -f_c / (2.0 * math.pi) / j_m
    jac[5, 4] = k_s * tr
    jac[5, 6] = -k_s
    jac[5, o + 16] = k_s * w / (2.0 * math.pi)
    jac[5, o + 17] = tr * w - v
    jac[6, 5] = 1.0 / m_s
    jac[6, 6] = -f_r / m_s
    jac[6, 7] = -1.0 / m_s
    jac[6, o + 11] = -v / m_s
    jac[6, o + 19] = -fs / (m_s * m_s)
    jac[7, 6] = k_1
    jac[7, 8] = -k_1
    jac[7, o + 18] = v - v_1
    jac[8, 2] = 1.0 / m_r
    jac[8, 7] = 1.0 / m_r
    jac[8, 8] = -b_d / m_r
    jac[8, 9] = -k_d / m_r
    jac[8, o + 8] = -fsurf / (m_r * m_r)
    jac[8, o + 9] = -v_1 / m_r
    jac[8, o + 21] = -x_1 / m_r
    jac[9, 8] = 1.0


@njit(cache=True)
def _global_ekf(z0, p0, q_diag, r_diag, meas, x_v, u_a, f_1, dt, substeps):
    """One EKF over the 10 plant states and the 22 parameters, 7 sensors; prediction by RK4
    (``substeps`` per sample, as the simulator), covariance through the RK4 transition of the
    linearized model, ``(I + Jh + (Jh)^2/2 + (Jh)^3/6 + (Jh)^4/24)^substeps``; sequential
    scalar updates in Joseph form. Returns the state estimates (n, 32)."""
    n = meas.shape[0]
    z = z0.copy()
    p = p0.copy()
    out = np.empty((n, N_G))
    h = dt / substeps
    f = np.empty(N_X)
    jac = np.zeros((N_X, N_G))
    kk = np.zeros((4, N_X))
    tmp = np.empty(N_G)
    eye = np.eye(N_G)
    for k in range(n):
        th = z[N_X:]
        x = z[:N_X].copy()
        for _ in range(substeps):
            for s in range(4):
                for i in range(N_X):
                    tmp[i] = x[i] + (0.0 if s == 0 else (0.5 * h if s < 3 else h)) * kk[s - 1, i]
                _global_rhs(tmp, th, x_v[k], u_a[k], f_1, f, jac)
                kk[s] = f
            for i in range(N_X):
                x[i] += h / 6.0 * (kk[0, i] + 2.0 * kk[1, i] + 2.0 * kk[2, i] + kk[3, i])
        _global_rhs(z[:N_X], th, x_v[k], u_a[k], f_1, f, jac)
        a = np.zeros((N_G, N_G))
        a[:N_X, :] = jac * h
        a2 = a @ a
        step = eye + a + a2 / 2.0 + (a2 @ a) / 6.0 + (a2 @ a2) / 24.0
        fm = eye.copy()
        for _ in range(substeps):
            fm = step @ fm
        z[:N_X] = x
        p = fm @ p @ fm.T
        for i in range(N_G):
            p[i, i] += q_diag[i]
        for j in range(7):
            s_idx = SENSORS[j]
            y = meas[k, j]
            if not math.isfinite(y):
                continue
            ph = p[:, s_idx].copy()
            denom = ph[s_idx] + r_diag[j]
            gain = ph / denom
            z += gain * (y - z[s_idx])
            ikh = eye.copy()
            ikh[:, s_idx] -= gain
            p = ikh @ p @ ikh.T + r_diag[j] * np.outer(gain, gain)
        out[k] = z
    return out


def global_ekf_ns(n: int) -> tuple[float, float, float]:
    """Cost per sample of the global EKF, and its v_p error against the raw sensor's."""
    params = ShaEmaParams()
    t, ch, truth = simulate_sha_ema(n * 1e-4 + 0.01, seed=0)
    theta = np.array([getattr(params, p) for p in GLOBAL_PARAMS])
    st = truth.states
    x0 = np.array(
        [st[s][0] for s in ("p_l", "v_p", "f_h", "i_m", "w", "f_c", "v", "f_e", "v_1", "x_1")]
    )
    z0 = np.concatenate([x0, theta])
    sensors = ("w", "f_c", "v", "f_e", "f_h", "v_p", "p_l")
    noise = np.array([truth.noise_std[c] for c in sensors]) ** 2
    # state scales from the run itself: initial spread 1 %, process noise 0.1 % of them per
    # sample; parameters: initial spread 0.1 %, a slow random walk
    names = ("p_l", "v_p", "f_h", "i_m", "w", "f_c", "v", "f_e", "v_1", "x_1")
    typical = np.array([np.std(st[s]) for s in names])
    p0 = np.diag(np.concatenate([(0.01 * typical) ** 2, (1e-3 * theta) ** 2]))
    q_diag = np.concatenate([(1e-3 * typical) ** 2, (1e-6 * theta) ** 2])
    meas = np.column_stack([ch[c] for c in sensors])
    args = (z0, p0, q_diag, noise, meas[:n], ch["x_v"][:n], ch["u_a"][:n], params.f_1, 1e-4, 10)
    _global_ekf(
        z0, p0, q_diag, noise, meas[:20], ch["x_v"][:20], ch["u_a"][:20], params.f_1, 1e-4, 10
    )
    est = None

    def call() -> None:
        nonlocal est
        est = _global_ekf(*args)

    sec = best_of(call, 2)
    assert est is not None
    err = float(np.sqrt(np.mean((est[:, 1] - st["v_p"][:n]) ** 2)))
    raw = float(np.sqrt(np.mean((ch["v_p"][:n] - st["v_p"][:n]) ** 2)))
    return sec / n * NS, err, raw


# ----------------------------------------------------------------------------- main
def main() -> None:
    m.warm_up()
    t, ch, _ = simulate_sha_ema(20.0, faults=PAPER_SCENARIO, seed=0)
    n = len(t)
    batch = Batch(t_s=t, channels=ch)
    fixed = {"thresholds": {"rule": "fixed", "values": [1e30] * 7, "window_s": 0.0}}
    residual_only = m.parse_config({**fixed, "subsystems": {}})
    default = m.parse_config({})
    # thresholds far below the residuals: both filters start at the first residual
    always = m.parse_config({"thresholds": {"rule": "fixed", "values": [1e-30] * 7}})
    # the same without the isolation fit (one fit sample in 10,000) and without sensor checks
    always_nofit = m.parse_config(
        {
            "thresholds": {"rule": "fixed", "values": [1e-30] * 7},
            "isolation": {"fit_decimation": 10_000},
            "sensors": {"enabled": False},
        }
    )
    runs = {}
    for name, config in (
        ("residuals", residual_only),
        ("default", default),
        ("filters", always),
        ("nofit", always_nofit),
    ):
        state = m.initial_state(config)
        m.step(config, state, Batch(t_s=t[:10], channels={k: v[:10] for k, v in ch.items()}))
        runs[name] = best_of(lambda c=config, s=state: m.step(c, s, batch), 3) / n * NS

    rng = np.random.default_rng(0)
    sigs = rng.normal(1.0, 0.1, (200_000, kern.N_CHAN, kern.MAX_ORDER + 1))
    ekf_cfg = m.parse_config(
        {"subsystems": {k: {**v, "estimator": "ekf"} for k, v in m.DEFAULT_SUBSYSTEMS.items()}}
    )
    rel_fekf = relation_filter_ns(default, "s7", sigs)
    rel_ekf = relation_filter_ns(ekf_cfg, "s7", sigs)
    fp_ns = filterpy_relation_ns(default, sigs)
    n_global = 2000
    global_ns, global_err, raw_err = global_ekf_ns(n_global)
    distributed = runs["filters"]

    rows = [
        (
            f"residuals r1..r7 + detection + health, {n:,}-sample batch",
            f"{runs['residuals']:9.0f} ns/sample",
        ),
        (
            "default configuration, seed scenario (filters from ~4.1 s)",
            f"{runs['default']:9.0f} ns/sample",
        ),
        (
            "residuals + both subsystem FEKFs running all the time",
            f"{runs['filters']:9.0f} ns/sample",
        ),
        (
            "  so two FEKFs (s6, s7) and the isolation fit add",
            f"{runs['filters'] - runs['residuals']:9.0f} ns/sample",
        ),
        (
            "  of which the isolation fit (1 in 10 samples) and sensor checks",
            f"{runs['filters'] - runs['nofit']:9.0f} ns/sample",
        ),
        ("FEKF on subsystem 7's relation, kernel alone", f"{rel_fekf:9.0f} ns/sample"),
        ("EKF on subsystem 7's relation, kernel alone", f"{rel_ekf:9.0f} ns/sample"),
        ("filterpy ExtendedKalmanFilter, same relation", f"{fp_ns:9.0f} ns/sample"),
        ("ratio filterpy / kernel EKF", f"{fp_ns / rel_ekf:9.0f} x"),
        (
            f"global EKF, 10 states + 22 parameters, 7 sensors ({n_global} samples)",
            f"{global_ns:9.0f} ns/sample",
        ),
        ("  its v_p RMS error / raw sensor's (sanity: it filters)", f"{global_err / raw_err:9.2f}"),
        (
            "ratio global EKF / distributed (residuals + two FEKFs)",
            f"{global_ns / distributed:9.0f} x",
        ),
    ]
    width = max(len(r[0]) for r in rows)
    print(f"{'measure':<{width}}  value")
    print("-" * (width + 20))
    for name, value in rows:
        print(f"{name:<{width}}  {value}")


if __name__ == "__main__":
    main()
