"""Deterioration EKF speed: ns per sample against filterpy's ExtendedKalmanFilter on the same
model, and the time of a 1,000-trajectory RUL prognosis under several regimes.

Prints figures measured side by side in one run; asserts nothing.
Run: ``.venv/bin/python bench/bench_deterioration_ekf.py``. ``--parts CHUNK`` times the kernel
with each adaptive part of the defaults off in turn. ``--baseline DIR`` instead times the
RUL cases and the default EKF of this tree and of another source tree (e.g. an extract of
``main``) in alternating child processes, and prints both side by side with their ratio.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from filterpy.kalman import ExtendedKalmanFilter
from scipy.linalg import expm

from estimators import deterioration_ekf as de
from estimators import rul
from estimators.base import Batch
from estimators.kernels import dekf_kernels as kern
from estimators.simulators.friction_drive import FrictionDriveParams, simulate_friction_drive

PROGNOSIS_Q = [0.0, 0.0, 0.0, 1e-13]


#: The seed's filter (sections 4.2, 5.2): known alpha0, held input, fixed R and Q, no gating.
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


def best_of(fn: Callable[[], Any], repeats: int) -> float:
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def filterpy_seconds_per_sample(
    t: np.ndarray, ch: dict[str, np.ndarray], n: int, *, exact: bool
) -> float:
    """filterpy's EKF on the same model and Jacobian (seed eq. 19). ``exact``: ``Phi = expm(F
    dt)`` and the local-linearization state step from scipy's expm of the augmented matrix (the
    estimator's discretization); otherwise Euler, ``Phi = I + F dt``, ``x + f(x) dt`` (filterpy's
    cheapest use, not the same discretization)."""
    p = FrictionDriveParams()
    config = de.parse_config(SEED)
    h = np.eye(4)[:2]
    aug = np.zeros((8, 8))
    aug[:4, 4:] = np.eye(4)

    def hx(x: np.ndarray) -> np.ndarray:
        return h @ x

    def run() -> None:
        ekf = ExtendedKalmanFilter(dim_x=4, dim_z=2)
        ekf.x = np.array([[ch["motor_speed"][0]], [ch["wheel_speed"][0]], [10.0], [0.01]])
        ekf.P = np.diag(config.p0_diag)
        ekf.Q = np.diag(config.q_diag)
        ekf.R = np.diag(config.r_diag)
        for k in range(1, n):
            w1, w2, al, m = ekf.x[:, 0]
            dv = p.r1_m * w1 - p.r2_m * w2
            u = ch["current"][k - 1]
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
                    [-2 * al * m * p.r1_m * dv, 2 * al * m * p.r2_m * dv, -m * dv * dv,
                     -al * dv * dv],
                    [0.0, 0.0, 0.0, 0.0],
                ]
            )  # fmt: skip
            dt = t[k] - t[k - 1]
            if exact:
                aug[:4, :4] = jac
                gamma = expm(aug * dt)[:4, 4:]
                ekf.F = expm(jac * dt)
                ekf.x = ekf.x + (gamma @ f)[:, None]
            else:
                ekf.F = np.eye(4) + jac * dt
                ekf.x = ekf.x + (f * dt)[:, None]
            ekf.P = ekf.F @ ekf.P @ ekf.F.T + ekf.Q
            ekf.update(np.array([[ch["motor_speed"][k]], [ch["wheel_speed"][k]]]), lambda _x: h, hx)

    return best_of(run, 5) / (n - 1)


def rul_cases() -> list[tuple[str, np.ndarray, np.ndarray, tuple[np.ndarray, np.ndarray], float]]:
    """(label, x, P, load segments, alpha0) taken from filter runs on the simulator."""
    cases = []
    for label, m, extra, load in (
        ("seed scenario at t = 15 s (fast wear, ~75 periods)", 0.01, {}, rul.SquareWaveLoad()),
        ("m = 0.001 (slow wear, cycle jumps)", 0.001, {}, rul.SquareWaveLoad()),
        ("constant 20 A (the seed's assumption)", 0.01, {}, rul.ConstantLoad(current_a=20.0)),
        (
            "seed Q: wide spread of m",
            0.01,
            {"q_diag": list(de.parse_config(SEED).q_diag)},
            rul.SquareWaveLoad(),
        ),
    ):
        t, ch, _ = simulate_friction_drive(15.0, 1000.0, m=m, seed=3)
        config = de.parse_config({**SEED, "q_diag": PROGNOSIS_Q, "rul_every_s": None, **extra})
        state, _ = de.step(config, de.initial_state(config), Batch(t, ch))
        segments = rul.load_segments(load, float(t[-1]))
        assert segments is not None
        cases.append((label, state.x, state.P, segments, 10.0))
    # observed load: 8 s of 40 ms bins of a measured current (noise 0.05 A), merged at 0.5 A
    t, ch, _ = simulate_friction_drive(15.0, 1000.0, seed=3, current_noise_a=0.05)
    load_raw = {"kind": "observed", "bin_samples": 40, "bins": 200, "merge_tolerance_a": 0.5}
    config = de.parse_config(
        {"q_diag": PROGNOSIS_Q, "rul_every_s": "every_batch", "rul_load": load_raw,
         "current_var": 0.05**2}
    )  # fmt: skip
    state, _ = de.step(config, de.initial_state(config), Batch(t, ch))
    row = de._end_snapshot(state.vector, float(t[-1]), config.observed_bins)
    observed = de._observed_profile(row, config.observed_bins)
    segments = rul.load_segments(config.rul_load, float(t[-1]), observed)
    assert segments is not None
    cases.append(
        (f"observed load ({len(segments[0])} segments per 8 s)", state.x, state.P, segments, 10.0)
    )
    # the recorded mission profile of the drive generator (700 segments of 20 ms per 14 s)
    from estimators.simulators.friction_drive_scenarios import mission_profile

    durations, currents = mission_profile(1.0)
    t, ch, _ = simulate_friction_drive(15.0, 1000.0, seed=3)
    config = de.parse_config({**SEED, "q_diag": PROGNOSIS_Q, "rul_every_s": None})
    state, _ = de.step(config, de.initial_state(config), Batch(t, ch))
    profile = rul.ProfileLoad(durations_s=durations, current_a=currents)
    segments = rul.load_segments(profile, float(t[-1]))
    assert segments is not None
    cases.append(
        (f"mission profile ({len(segments[0])} segments per 14 s)", state.x, state.P, segments, 10.0)
    )
    # a random telegraph read as two levels and its dwells (32 segments per period)
    rng = np.random.default_rng(5)
    n_bins = 1500
    level = np.cumsum(rng.random(n_bins) < 0.02 * 2) % 2
    dwells = rul.dwell_load(np.full(n_bins, 0.02), np.where(level == 1, 20.0, 0.0), 16, 0.05)
    assert dwells is not None
    cases.append(
        (
            f"observed load read as dwells ({dwells.durations_s.shape[0]} segments per period)",
            state.x, state.P, (dwells.durations_s, dwells.currents_a), 10.0,
        )
    )  # fmt: skip
    merged = rul.ProfileLoad(durations_s=durations, current_a=currents, merge_tolerance_a=0.5)
    segments = rul.load_segments(merged, float(t[-1]))
    assert segments is not None
    cases.append(
        (
            f"mission profile merged at 0.5 A ({len(segments[0])} segments per 14 s)",
            state.x, state.P, segments, 10.0,
        )
    )  # fmt: skip
    return cases


def cpu_best_of(fn: Callable[[], Any], repeats: int) -> float:
    """Smallest CPU time of the calling thread over ``repeats`` calls (leaves out the time the
    thread waits for a core on a shared machine)."""
    best = float("inf")
    for _ in range(repeats):
        t0 = time.thread_time()
        fn()
        best = min(best, time.thread_time() - t0)
    return best


def rul_timings(repeats: int = 5) -> dict[str, tuple[float, float | None]]:
    """CPU seconds (best of ``repeats``) and q50 of each RUL case, widening of the defaults on."""
    plant = FrictionDriveParams().as_array()
    settings = rul.PrognosisSettings(n_trajectories=1000)
    out: dict[str, tuple[float, float | None]] = {}
    for label, x, cov, segments, alpha0 in rul_cases():

        def run(
            x: np.ndarray = x,
            cov: np.ndarray = cov,
            segments: tuple[np.ndarray, np.ndarray] = segments,
            alpha0: float = alpha0,
        ) -> Any:
            return rul.prognose(
                plant, alpha0, x, cov, 15.0, segments, settings, log_time_var=0.01,
                walk_rel_var_per_s=1e-6, time_scale=1.02,
            )  # fmt: skip

        q50 = run().q50_s
        out[f"RUL: {label}"] = (cpu_best_of(run, repeats), q50)
    return out


def ekf_default_timings(n: int = 300_000) -> dict[str, tuple[float, float | None]]:
    """CPU seconds per sample of the defaults' kernel, of ``step`` on one batch of ``n`` samples
    and on 10,000-sample batches (best of 5)."""
    t, ch, _ = simulate_friction_drive(n / 1000.0, 1000.0, m=0.0005, seed=1)
    config = de.parse_config({"alpha0": 10.0, "rul_every_s": None})
    state0 = de.initial_state(config)
    batch = Batch(t, ch)
    chunks = [
        Batch(t[i : i + 10_000], {k: v[i : i + 10_000] for k, v in ch.items()})
        for i in range(0, n, 10_000)
    ]

    def kernel_only() -> None:
        kern.ekf_batch(
            config.kernel_vector, state0.vector.copy(), t, ch["current"], ch["motor_speed"],
            ch["wheel_speed"],
        )  # fmt: skip

    def stream() -> None:
        state = state0
        for chunk in chunks:
            state, _ = de.step(config, state, chunk)

    return {
        f"EKF defaults, kernel alone, {n}-sample batch (per sample)": (
            cpu_best_of(kernel_only, 5) / n, None,
        ),
        f"EKF defaults, step(), {n}-sample batch (per sample)": (
            cpu_best_of(lambda: de.step(config, state0, batch), 5) / n, None,
        ),
        "EKF defaults, step(), 10,000-sample batches (per sample)": (
            cpu_best_of(stream, 5) / n, None,
        ),
    }  # fmt: skip


#: One adaptive part of the defaults off at a time (the seed's filter: all of them off).
PARTS: dict[str, dict[str, Any]] = {
    "defaults": {},
    "interval input (no edge model)": {"input_model": "interval"},
    "held input": {"input_model": "hold"},
    "no noise estimation": {"noise_adaptation": False},
    "no gating": {"gate_sigma": None},
    "no projection": {"nonnegative": False},
    "no band scaling": {"covariance_scaling": False},
    "no plant calibration": {"plant_calibration": False},
    "no random walk of m": {"m_walk_rel": 0.0},
    "seed's filter": SEED,
}


def ekf_part_timings(n: int = 300_000, chunk: int = 300_000, rounds: int = 5) -> None:
    """Kernel CPU time per sample with each adaptive part of the defaults off, on ``n`` samples
    in batches of ``chunk``; the configurations alternate, best of ``2 rounds`` calls each."""
    t, ch, _ = simulate_friction_drive(n / 1000.0, 1000.0, m=0.0005, seed=1)
    runs: dict[str, Callable[[], None]] = {}
    for label, extra in PARTS.items():
        config = de.parse_config({"alpha0": 10.0, "rul_every_s": None, **extra})
        vec0 = de.initial_state(config).vector

        def run(kv: np.ndarray = config.kernel_vector, vec0: np.ndarray = vec0) -> None:
            st = vec0.copy()
            for i in range(0, n, chunk):
                s = slice(i, i + chunk)
                kern.ekf_batch(
                    kv, st, t[s], ch["current"][s], ch["motor_speed"][s], ch["wheel_speed"][s]
                )

        runs[label] = run
    best = dict.fromkeys(runs, float("inf"))
    for _ in range(rounds):
        for label, fn in runs.items():
            best[label] = min(best[label], cpu_best_of(fn, 2))
    print(f"kernel, {n} samples in batches of {chunk}, thread CPU, best of {2 * rounds}")
    for label, secs in best.items():
        saved = (best["defaults"] - secs) / n * 1e9
        print(f"{label:<32} {secs / n * 1e9:7.1f} ns/sample  (defaults minus this {saved:6.1f})")


_TREE_TIMING = """
import importlib.util, json, sys
spec = importlib.util.spec_from_file_location("bench_dekf", sys.argv[1])
mod = importlib.util.module_from_spec(spec)
spec.loader.exec_module(mod)
mod.de.warm_up()
print(json.dumps({**mod.ekf_default_timings(), **mod.rul_timings()}))
"""


def tree_timings(tree: Path) -> dict[str, tuple[float, float | None]]:
    """:func:`ekf_default_timings` and :func:`rul_timings` with ``tree``'s ``estimators`` (this
    file's cases and timing, run in a child process)."""
    env = {**os.environ, "PYTHONPATH": str(tree)}
    res = subprocess.run(
        [sys.executable, "-c", _TREE_TIMING, str(Path(__file__).resolve())],
        cwd=tree, env=env, check=True, capture_output=True, text=True,
    )  # fmt: skip
    raw = json.loads(res.stdout.strip().splitlines()[-1])
    return {k: (float(v[0]), v[1]) for k, v in raw.items()}


def side_by_side(baseline: Path, rounds: int) -> None:
    """This tree against ``baseline``, alternating, best of ``rounds`` child processes each."""
    here = Path(__file__).resolve().parent.parent
    best: dict[str, dict[str, tuple[float, float | None]]] = {"new": {}, "base": {}}
    for _ in range(rounds):
        for label, tree in (("base", baseline), ("new", here)):
            for name, (secs, q50) in tree_timings(tree).items():
                if secs < best[label].get(name, (float("inf"), None))[0]:
                    best[label][name] = (secs, q50)
    print(f"side by side with {baseline}, thread CPU time, best of {rounds} alternating runs")
    width = max(len(k) for k in best["new"])
    print(f"{'measure':<{width}}  {'base':>10}  {'new':>10}  ratio  q50 base -> new")
    for name, (new, q_new) in best["new"].items():
        old, q_old = best["base"].get(name, (float("nan"), None))
        unit, scale = ("ns", 1e9) if name.startswith("EKF") else ("ms", 1e3)
        q = "" if q_new is None and q_old is None else f"  {q_old} -> {q_new}"
        print(
            f"{name:<{width}}  {old * scale:7.1f} {unit}  {new * scale:7.1f} {unit}  "
            f"{new / old:5.2f}{q}"
        )


def main() -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n")[0])
    ap.add_argument(
        "--baseline", type=Path, default=None,
        help="another source tree: time the RUL cases and the default EKF of both, side by side",
    )  # fmt: skip
    ap.add_argument("--rounds", type=int, default=3, help="alternating runs per tree (--baseline)")
    ap.add_argument(
        "--parts", type=int, default=None, metavar="CHUNK",
        help="kernel time with each adaptive part off, batches of CHUNK samples",
    )  # fmt: skip
    args = ap.parse_args()
    if args.parts is not None:
        de.warm_up()
        ekf_part_timings(chunk=args.parts)
        return
    if args.baseline is not None:
        side_by_side(args.baseline.resolve(), args.rounds)
        return
    de.warm_up()
    n_long = 1_000_000
    t, ch, _ = simulate_friction_drive(n_long / 1000.0, 1000.0, m=0.0005, seed=1)
    rows: list[tuple[str, str]] = []
    for label, extra in (
        ("defaults (edge input, noise estimation, gating, projection)", {"alpha0": 10.0}),
        ("defaults, interval input", {"alpha0": 10.0, "input_model": "interval"}),
        ("defaults, alpha0 estimated", {"alpha0": None}),
        ("seed Q, F44 = 0", {}),
        ("prognosis tuning", {"q_diag": PROGNOSIS_Q}),
        ("seed Q, F44 = -100", {"f44": -100.0}),
        ("seed Q, expm_tol = 1e-12", {"expm_tol": 1e-12}),
    ):
        base = {} if label.startswith("defaults") else SEED
        config = de.parse_config({**base, "rul_every_s": None, **extra})
        state0 = de.initial_state(config)
        batch = Batch(t, ch)
        s_step = best_of(
            lambda config=config, state0=state0, batch=batch: de.step(config, state0, batch), 5
        )

        def kernel_only(config: de.DekfConfig = config, state0: de.DekfState = state0) -> None:
            kern.ekf_batch(
                config.kernel_vector, state0.vector.copy(), t, ch["current"],
                ch["motor_speed"], ch["wheel_speed"],
            )  # fmt: skip

        s_kernel = best_of(kernel_only, 5)
        rows.append(
            (f"EKF step(), {label}, 1e6-sample batch", f"{s_step / n_long * 1e9:8.1f} ns/sample")
        )
        rows.append(("  compiled kernel alone", f"{s_kernel / n_long * 1e9:8.1f} ns/sample"))
        if label == "seed Q, F44 = 0":
            per_sample = s_step / n_long
        if label.startswith("defaults (edge"):
            # the same samples as a stream of 10,000-sample batches (the outputs of a batch
            # then stay in cache; a 1e6 batch writes 19 x 8 MB of outputs to memory)
            chunks = [
                Batch(t[i : i + 10_000], {k: v[i : i + 10_000] for k, v in ch.items()})
                for i in range(0, n_long, 10_000)
            ]

            def stream(
                config: de.DekfConfig = config,
                state0: de.DekfState = state0,
                chunks: list[Batch] = chunks,
            ) -> None:
                state = state0
                for chunk in chunks:
                    state, _ = de.step(config, state, chunk)

            rows.append(
                (
                    "  the same 1e6 samples in 10,000-sample batches",
                    f"{best_of(stream, 3) / n_long * 1e9:8.1f} ns/sample",
                )
            )

            def outputs_only() -> None:
                out = np.empty((kern.OUT_LEN, n_long))
                out[:] = 1.0

            rows.append(
                (
                    "  writing 19 output rows of a 1e6 batch alone (np.empty, fill)",
                    f"{best_of(outputs_only, 5) / n_long * 1e9:8.1f} ns/sample",
                )
            )
    n_fp = 1000
    for exact, label in ((True, "scipy expm (same discretization)"), (False, "Euler")):
        s_fp = filterpy_seconds_per_sample(t, ch, n_fp, exact=exact)
        rows.append(
            (
                f"filterpy ExtendedKalmanFilter, {label}, {n_fp} samples",
                f"{s_fp * 1e9:8.0f} ns/sample",
            )
        )
        rows.append(("  ratio to step() (seed Q, F44 = 0)", f"{s_fp / per_sample:8.0f} x"))

    config = de.parse_config({**SEED, "rul_every_s": None})
    state0 = de.initial_state(config)
    b10k = Batch(t[:10_000], {k: v[:10_000] for k, v in ch.items()})
    b1 = Batch(t[:1], {k: v[:1] for k, v in ch.items()})
    rows.append(
        (
            "step() on a 10,000-sample batch",
            f"{best_of(lambda: de.step(config, state0, b10k), 100) * 1e6:8.1f} us",
        )
    )
    rows.append(
        (
            "step() on a 1-sample batch",
            f"{best_of(lambda: de.step(config, state0, b1), 1000) * 1e6:8.1f} us",
        )
    )

    plant = FrictionDriveParams().as_array()
    settings = rul.PrognosisSettings(n_trajectories=1000)
    for label, x, cov, segments, alpha0 in rul_cases():
        res = rul.prognose(plant, alpha0, x, cov, 15.0, segments, settings)
        # with the widening of the defaults on (model-error record, random walk of m)
        s_rul = best_of(
            lambda x=x, cov=cov, segments=segments, alpha0=alpha0: rul.prognose(
                plant, alpha0, x, cov, 15.0, segments, settings, log_time_var=0.01,
                walk_rel_var_per_s=1e-6, time_scale=1.02,
            ),
            5,
        )
        q50 = "-" if res.q50_s is None else f"{res.q50_s:.4g} s"
        rows.append(
            (
                f"RUL, 1,000 trajectories: {label}",
                f"{s_rul * 1e3:8.1f} ms  (q50 {q50}, {res.propagation})",
            )
        )
    width = max(len(r[0]) for r in rows)
    print(f"{'measure':<{width}}  value")
    print("-" * (width + 30))
    for name, value in rows:
        print(f"{name:<{width}}  {value}")


if __name__ == "__main__":
    main()
