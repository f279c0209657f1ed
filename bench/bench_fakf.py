"""FAKF speed: ns per sample against filterpy, identification time, per-call overhead.

Prints figures; asserts nothing. Run: ``.venv/bin/python bench/bench_fakf.py``.
"""

from __future__ import annotations

import time

import numpy as np
from filterpy.kalman import KalmanFilter

from estimators import fakf
from estimators.base import Batch

SEED_S_PER_SAMPLE = 9.985 / 92_415  # seed paper: 9.985 s for 92,415 points
SEED_IDENT_S = 0.013  # seed paper: identification of 2,936 points
COEF = {"a0": -0.5, "a1": 0.06, "b0": 1.0, "b1": 2.0, "b2": -0.5}


def best_of(fn, repeats: int) -> float:
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def data(n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    current = rng.standard_normal(n) + 2.0 * np.sin(np.arange(n) * 2 * np.pi / 500.0)
    voltage = 3.0 * current + np.convolve(current, [0.0, 2.0, -0.5])[:n] + rng.normal(0, 1, n)
    return np.arange(n) * 1e-3, current, voltage


def arx(coef: dict[str, float], current: np.ndarray, noise: float, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    v = np.zeros(current.shape[0])
    for j in range(2, current.shape[0]):
        v[j] = (
            -coef["a0"] * v[j - 1]
            - coef["a1"] * v[j - 2]
            + coef["b0"] * current[j]
            + coef["b1"] * current[j - 1]
            + coef["b2"] * current[j - 2]
            + noise * rng.standard_normal()
        )
    return v


def reference_filter_cost() -> dict[str, float]:
    """ns/sample on a 20,000-sample continuation of a stream whose plant changed (a fast model,
    then a slow one on which the first loses to persistence), with re-identification on (the
    reference filter runs apart) and off."""
    slow = {"a0": -1.6, "a1": 0.64, "b0": 0.05, "b1": 0.0, "b2": 0.0}
    rng = np.random.default_rng(7)
    n1, n2, n3 = 1000, 2000, 20_000
    fast_i = rng.standard_normal(n1) + 2.0 * np.sin(np.arange(n1) * 2 * np.pi / 200.0)
    slow_i = np.cumsum(rng.standard_normal(n2 + n3)) * 0.5
    current = np.concatenate([fast_i, slow_i])
    voltage = np.concatenate([arx(COEF, fast_i, 0.3, 1), arx(slow, slow_i, 0.05, 2)])
    t = np.arange(current.shape[0]) * 0.01
    head = n1 + n2
    out = {}
    for name, extra in (("on", {}), ("off", {"reidentification": {"enabled": False}})):
        raw = {"identification_samples": n1, "health_window_samples": 500, **extra}
        cfg = fakf.parse_config(raw)
        state, _ = fakf.step(
            cfg,
            fakf.initial_state(cfg),
            Batch(t[:head], {"current": current[:head], "voltage": voltage[:head]}),
        )
        tail = Batch(t[head:], {"current": current[head:], "voltage": voltage[head:]})
        out[name] = (
            best_of(lambda cfg=cfg, state=state, tail=tail: fakf.step(cfg, state, tail), 200) / n3
        )
        out[f"{name}_reidentified"] = float(state.n_reidentifications)
    return out


def main() -> None:
    fakf.warm_up()
    n_long = 1_000_000
    t, current, voltage = data(n_long)
    fixed = fakf.parse_config({"coefficients": COEF, "q": 0.5, "r": 1.0})
    ident = fakf.parse_config({})
    state0_fixed = fakf.initial_state(fixed)
    state0_ident = fakf.initial_state(ident)
    batch_long = Batch(t_s=t, channels={"current": current, "voltage": voltage})

    s_fixed = best_of(lambda: fakf.step(fixed, state0_fixed, batch_long), 5)
    s_ident = best_of(lambda: fakf.step(ident, state0_ident, batch_long), 5)

    n_fp = 20_000
    kf_u = COEF["b0"] * current[2:n_fp] + COEF["b1"] * current[1 : n_fp - 1]
    kf_u = kf_u + COEF["b2"] * current[: n_fp - 2]

    def run_filterpy() -> None:
        kf = KalmanFilter(dim_x=2, dim_z=1)
        kf.F = np.array([[-COEF["a0"], -COEF["a1"]], [1.0, 0.0]])
        kf.B = np.array([[1.0], [0.0]])
        kf.H = np.array([[1.0, 0.0]])
        kf.Q = np.diag([0.5, 0.0])
        kf.R = np.array([[1.0]])
        for k in range(kf_u.shape[0]):
            kf.predict(u=kf_u[k])
            kf.update(voltage[k + 2])

    s_fp = best_of(run_filterpy, 3) / kf_u.shape[0]

    _, c3000, v3000 = data(3000, seed=1)
    s_id = best_of(lambda: fakf.identify_arx(c3000, v3000), 200)

    # per-call cost: a 10,000-sample batch (the service's size) and a 1-sample batch
    n_call = 10_000
    batch_10k = Batch(
        t_s=t[:n_call], channels={"current": current[:n_call], "voltage": voltage[:n_call]}
    )
    s_call = best_of(lambda: fakf.step(fixed, state0_fixed, batch_10k), 200)
    per_sample_fixed = s_fixed / n_long
    # in-cache batches (20,000 samples, inputs and outputs fit in L2): the kernel's own cost,
    # less sensitive to memory traffic from other processes on a shared machine
    n_small = 20_000
    batch_small = Batch(
        t_s=t[:n_small], channels={"current": current[:n_small], "voltage": voltage[:n_small]}
    )
    closed_small = Batch(t_s=batch_small.t_s, channels=batch_small.channels, end_of_run=True)
    railed = fakf.parse_config(
        {"voltage_rail_low_v": -12.0, "voltage_rail_high_v": 12.0, "idle_close_s": 1.0}
    )
    state0_railed = fakf.initial_state(railed)
    censored = float(np.mean(np.abs(voltage[:n_small]) >= 12.0))
    small = {
        "fixed": best_of(lambda: fakf.step(fixed, state0_fixed, batch_small), 300) / n_small,
        "ident": best_of(lambda: fakf.step(ident, state0_ident, batch_small), 300) / n_small,
        "railed": best_of(lambda: fakf.step(railed, state0_railed, closed_small), 300) / n_small,
    }
    shadow = reference_filter_cost()
    t_tiny = t[:1]
    batch_1 = Batch(t_s=t_tiny, channels={"current": current[:1], "voltage": voltage[:1]})
    s_one = best_of(lambda: fakf.step(fixed, state0_fixed, batch_1), 2000)

    ns = 1e9
    rows = [
        ("FAKF, fixed model, 1e6-sample batch", f"{per_sample_fixed * ns:8.1f} ns/sample"),
        (
            "FAKF, identification + health windows, 1e6 batch",
            f"{s_ident / n_long * ns:8.1f} ns/sample",
        ),
        (f"filterpy KalmanFilter, {kf_u.shape[0]} samples", f"{s_fp * ns:8.0f} ns/sample"),
        ("ratio filterpy / FAKF", f"{s_fp / per_sample_fixed:8.0f} x"),
        ("seed paper (9.985 s / 92,415 points)", f"{SEED_S_PER_SAMPLE * ns:8.0f} ns/sample"),
        ("ratio seed / FAKF", f"{SEED_S_PER_SAMPLE / per_sample_fixed:8.0f} x"),
        ("identification, 3000 samples", f"{s_id * 1e3:8.3f} ms  (seed: 13 ms for 2,936)"),
        ("step() on a 10,000-sample batch", f"{s_call * 1e6:8.1f} us"),
        ("  per sample", f"{s_call / n_call * ns:8.1f} ns/sample"),
        ("step() on a 1-sample batch (per-call overhead)", f"{s_one * 1e6:8.1f} us"),
        ("20,000-sample batch, fixed model", f"{small['fixed'] * ns:8.1f} ns/sample"),
        ("20,000-sample batch, identification + windows", f"{small['ident'] * ns:8.1f} ns/sample"),
        (
            f"20,000-sample batch, rails ({100 * censored:.0f} % censored), idle gap, end of run",
            f"{small['railed'] * ns:8.1f} ns/sample",
        ),
        (
            f"after a re-identification ({shadow['on_reidentified']:.0f}), reference filter on",
            f"{shadow['on'] * ns:8.1f} ns/sample",
        ),
        ("same stream, re-identification off", f"{shadow['off'] * ns:8.1f} ns/sample"),
    ]
    width = max(len(r[0]) for r in rows)
    print(f"{'measure':<{width}}  value")
    print("-" * (width + 24))
    for name, value in rows:
        print(f"{name:<{width}}  {value}")


if __name__ == "__main__":
    main()
