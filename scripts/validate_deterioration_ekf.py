"""Validate the deterioration EKF and its RUL prognosis on the friction-drive simulator; write the
``deterioration_ekf`` section of ``docs/validation.md`` (between ``<!-- deterioration_ekf:begin
-->`` and ``<!-- deterioration_ekf:end -->``; the rest of the file is kept).

Run: ``.venv/bin/python scripts/validate_deterioration_ekf.py [--runs 40] [--seed 0]``
(about 2-4 minutes for 40 runs on a shared 2-core machine).
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
from filterpy.kalman import ExtendedKalmanFilter
from scipy.linalg import expm

from estimators import deterioration_ekf as de
from estimators import rul as rulmod
from estimators.base import Batch, RulEstimate
from estimators.simulators.friction_drive import (
    PAPER_NOISE_STD,
    FrictionDriveParams,
    SquareWave,
    first_crossing_time,
    simulate_friction_drive,
)

ROOT = Path(__file__).resolve().parent.parent
DOC = ROOT / "docs" / "validation.md"
BEGIN, END = "<!-- deterioration_ekf:begin -->", "<!-- deterioration_ekf:end -->"
FS = 1000.0
PROGNOSIS_Q44 = 1e-13
SWEEP_Q44 = (1e-12, 1e-14)
DN_LEVELS = (0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8)
CURRENT_NOISE_A = 0.05
CAP_S = 2500.0  # longest simulated life; longer draws are redrawn (counted in the report)
#: The seed's filter (sections 4.2, 5.2) for the sections that reproduce it and for the
#: project-simulator runs below: known alpha0, held input, fixed R and Q, no gating.
SEED: dict[str, Any] = {
    "alpha0": 10.0,
    "input_model": "hold",
    "plant_calibration": False,
    "covariance_scaling": False,
    "noise_adaptation": False,
    "gate_sigma": None,
    "m_walk_rel": 0.0,
    "rul_model_error": False,
    "q_diag": [0.0, 0.0, 0.0, 0.02**2 / 12.0],
}


def seed_config(raw: dict[str, Any]) -> de.DekfConfig:
    """The seed's filter settings with ``raw`` on top."""
    return de.parse_config({**SEED, **raw})


# ----------------------------------------------------------------------------- seed scenario
def settle_time(t: np.ndarray, m_hat: np.ndarray, t_jump: float, m_new: float) -> float:
    """Time after the jump from which m-hat stays within 5 % of its new value (1 s means)."""
    sec = np.floor(t - t_jump)
    means = np.array([m_hat[sec == j].mean() for j in range(int(sec.max()) + 1)])
    outside = np.flatnonzero(np.abs(means - m_new) > 0.05 * m_new)
    return float(outside[-1] + 1) if outside.size else 0.0


def f44_on_the_state(seed: int) -> tuple[float, float]:
    """Mean m-hat over [5, 10) s and [15, 20) s of a filterpy EKF in which F44 = -100 acts on
    the state too (``dm/dt = -100 m`` in the prediction), the reading of section 5.2 that this
    estimator does not follow; local-linearization step by scipy's expm."""
    t, ch, _ = simulate_friction_drive(20.0, FS, m_changes=[(10.0, 0.02)], seed=100 + seed)
    p = FrictionDriveParams()
    config = seed_config({})
    ekf = ExtendedKalmanFilter(dim_x=4, dim_z=2)
    ekf.x = np.array([[ch["motor_speed"][0]], [ch["wheel_speed"][0]], [10.0], [0.01]])
    ekf.P = np.diag(config.p0_diag)
    ekf.Q = np.diag(config.q_diag)
    ekf.R = np.diag(config.r_diag)
    h = np.eye(4)[:2]
    aug = np.zeros((8, 8))
    aug[:4, 4:] = np.eye(4)
    m_hat = np.empty(len(t))
    for k in range(len(t)):
        if k > 0:
            w1, w2, al, m = ekf.x[:, 0]
            dv = p.r1_m * w1 - p.r2_m * w2
            f = np.array(
                [
                    (-al * p.r1_m * dv - p.b1_nm_s * w1 + p.km_nm_a * ch["current"][k - 1])
                    / p.j1_kg_m2,
                    (al * p.r2_m * dv - p.b2_nm_s * w2) / p.j2_kg_m2,
                    -m * dv * dv * al,
                    -100.0 * m,
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
                    [0.0, 0.0, 0.0, -100.0],
                ]
            )  # fmt: skip
            dt = t[k] - t[k - 1]
            aug[:4, :4] = jac
            ekf.F = expm(jac * dt)
            ekf.x = ekf.x + (expm(aug * dt)[:4, 4:] @ f)[:, None]
            ekf.P = ekf.F @ ekf.P @ ekf.F.T + ekf.Q
        z = np.array([[ch["motor_speed"][k]], [ch["wheel_speed"][k]]])
        ekf.update(z, lambda _x: h, lambda x: h @ x)
        m_hat[k] = ekf.x[3, 0]
    return float(m_hat[(t >= 5) & (t < 10)].mean()), float(m_hat[t >= 15].mean())


def seed_scenario_section(n_seeds: int) -> list[str]:
    rows = []
    tunings = {
        "seed Q (sigma_m^2 = 3.33e-5), F44 = 0": {},
        "seed Q, F44 = -100": {"f44": -100.0},
        f"prognosis tuning (q_m = {PROGNOSIS_Q44:g})": {"q_diag": [0.0, 0.0, 0.0, PROGNOSIS_Q44]},
    }
    keys = ("inside", "m_in", "dn_err", "m1", "m2", "m_sd", "settle", "nis", "cons")
    for label, extra in tunings.items():
        stats: dict[str, list[float]] = {k: [] for k in keys}
        for seed in range(n_seeds):
            t, ch, tr = simulate_friction_drive(20.0, FS, m_changes=[(10.0, 0.02)], seed=100 + seed)
            config = seed_config({"rul_every_s": None, "health_window_samples": 2000, **extra})
            _, out = de.step(config, de.initial_state(config), Batch(t, ch))
            s = out.samples
            after = t >= 1.0
            inside = np.abs(s["alpha"] - tr["alpha"]) <= s["alpha_3sigma"]
            stats["inside"].append(float(np.mean(inside[after])))
            stats["m_in"].append(float(np.mean((np.abs(s["m"] - tr["m"]) <= s["m_3sigma"])[after])))
            stats["dn_err"].append(float(np.max(np.abs(s["dn"] - tr["dn"])[after])))
            stats["m1"].append(float(s["m"][(t >= 5) & (t < 10)].mean()))
            stats["m2"].append(float(s["m"][t >= 15].mean()))
            stats["m_sd"].append(float(s["m"][(t >= 5) & (t < 10)].std()))
            late = t >= 10.0
            stats["settle"].append(settle_time(t[late], s["m"][late], 10.0, 0.02))
            stats["nis"].append(float(np.nanmean(s["nis"])))
            stats["cons"].append(
                float(np.mean([h.indicators["consistent"] == 1.0 for h in out.health]))
            )
        rows.append((label, {k: np.array(v) for k, v in stats.items()}))
    lines = [
        "### Seed scenario (section 5)",
        "",
        f"20 s at {FS:g} Hz, square wave 0/20 A of period 2 s, alpha0 = 10, m = 0.01 jumping to "
        f"0.02 at t = 10 s, the seed's R, P0 and Table 1, {n_seeds} noise seeds. Columns: share "
        "of samples after 1 s with alpha (and m) inside their 3-sigma bounds (min over seeds); "
        "largest |Dn error|; mean m-hat over [5, 10) s and [15, 20) s (mean over seeds); sample "
        "std of m-hat over [5, 10) s; seconds after the jump from which the 1 s means of m-hat "
        "stay within 5 % of 0.02 (max over seeds); mean NIS (expected 2); share of 2 s health "
        "windows passing all innovation tests.",
        "",
        "| tuning | alpha in 3 sigma | m in 3 sigma | max Dn error | m-hat 5-10 s | m-hat 15-20 s "
        "| std m-hat | settling s | NIS mean | consistent windows |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for label, st in rows:
        lines.append(
            f"| {label} | {st['inside'].min():.4f} | {st['m_in'].min():.4f} "
            f"| {st['dn_err'].max():.1e} | {st['m1'].mean():.5f} | {st['m2'].mean():.5f} "
            f"| {st['m_sd'].mean():.1e} | {st['settle'].max():.0f} | {st['nis'].mean():.3f} "
            f"| {st['cons'].mean():.2f} |"
        )
    m1, m2 = f44_on_the_state(0)
    lines.append(
        f"| seed Q, F44 = -100 on the state too (filterpy reference, noise seed 100) | - | - | - "
        f"| {m1:.5f} | {m2:.5f} | - | - | - | - |"
    )
    seed_q = rows[0][1]
    prog = rows[2][1]
    lines += [
        "",
        "The last row applies F44 = -100 to the state prediction as well (`dm/dt = -100 m`): "
        "m-hat is then pulled toward 0 between updates and biased low, which is why the "
        "estimator applies F44 to the covariance only.",
        "",
        "With the seed's Q, alpha stays inside its bounds and m-hat follows the jump on "
        f"average, but m-hat is noisy (std {seed_q['m_sd'].mean():.1e}, F44 = -100 narrows it) "
        "and its variance far exceeds its actual error; the motor-speed innovations are then "
        "negatively correlated and the NIS is below 2, so the consistency tests flag most "
        "windows, as the seed's section 4.4 says they should when Q does not match the data. "
        f"The prognosis tuning (random walk of {PROGNOSIS_Q44:g} per sample on m) gives an m-hat "
        f"std of {prog['m_sd'].mean():.1e} while m is constant, but it is slow to follow the "
        f"abrupt jump (settling {prog['settle'].max():.0f} s) and is inconsistent meanwhile "
        f"(alpha inside its bounds {100 * prog['inside'].min():.1f} % of the time at worst, mean "
        f"NIS {prog['nis'].mean():.1f}): the random walk on m trades the reaction to abrupt "
        "changes against the precision of a slowly varying m.",
        "",
    ]
    return lines


def seed_rul_example() -> list[str]:
    """The seed's own prognosis assumption: constant 20 A, from the end of the scenario."""
    t, ch, _ = simulate_friction_drive(20.0, FS, seed=100)
    lines = [
        "### The seed's RUL example (section 6)",
        "",
        "The seed reports RUL = 106.09 h, std 3.36 h (its Fig. 8) for a constant 20 A, with m "
        "constant, from an unstated prognosis time and a threshold of Dn = 1 (reached only "
        "asymptotically here). From the end of the 20 s scenario above (m = 0.01, prognosis "
        "tuning), under a constant 20 A:",
        "",
        "| failure Dn | q05 h | q50 h | q95 h | mean h | std h |",
        "|---:|---:|---:|---:|---:|---:|",
    ]
    for failure in (0.9, 0.99):
        config = seed_config(
            {
                "q_diag": [0.0, 0.0, 0.0, PROGNOSIS_Q44],
                "rul_every_s": "every_batch",
                "rul_load": {"kind": "constant", "current_a": 20.0},
                "rul_failure_dn": failure,
                "dn_alert": min(0.7, failure - 0.05),
            }
        )
        _, out = de.step(config, de.initial_state(config), Batch(t, ch))
        r = out.rul[0]
        h = 3600.0
        lines.append(
            f"| {failure:g} | {fmt(r.q05_s, h)} | {fmt(r.q50_s, h)} | {fmt(r.q95_s, h)} "
            f"| {fmt(r.mean_s, h)} | {fmt(r.std_s, h)} |"
        )
    lines += [
        "",
        "Same order of magnitude as the seed's 106 h; the seed's prognosis time, threshold and "
        "filter state are not given, so no closer comparison is possible. The spread here is "
        "far smaller than the seed's (3 %) because m is estimated to about 0.1 % with the "
        "seed's very precise speed sensors.",
        "",
    ]
    return lines


# ----------------------------------------------------------------------------- run to failure
@dataclass(frozen=True)
class Draw:
    """One simulated actuator run to failure."""

    alpha0: float
    m: float
    high_a: float
    low_a: float
    period_s: float
    duty: float
    failure_dn: float
    noise_scale: float
    param_factors: tuple[float, ...]
    seed: int


def make_draw(rng: np.random.Generator, seed: int) -> Draw:
    return Draw(
        alpha0=float(rng.uniform(5.0, 20.0)),
        m=float(math.exp(rng.uniform(math.log(0.004), math.log(0.03)))),
        high_a=float(rng.uniform(10.0, 30.0)),
        low_a=float(rng.choice([0.0, rng.uniform(-10.0, 5.0)])),
        period_s=float(rng.uniform(1.0, 4.0)),
        duty=float(rng.uniform(0.3, 0.7)),
        failure_dn=float(rng.choice([0.7, 0.8, 0.9])),
        noise_scale=float(10 ** rng.uniform(0.0, 1.0)),
        param_factors=tuple(float(v) for v in rng.uniform(0.8, 1.25, size=7)),
        seed=seed,
    )


def params_of(d: Draw) -> FrictionDriveParams:
    base = asdict(FrictionDriveParams())
    return FrictionDriveParams(
        **{k: v * f for (k, v), f in zip(base.items(), d.param_factors, strict=True)}
    )


def wave_of(d: Draw) -> SquareWave:
    return SquareWave(high_a=d.high_a, low_a=d.low_a, period_s=d.period_s, duty=d.duty)


@dataclass
class Outcome:
    """One prognosis against the truth."""

    draw: int
    level: float
    true_s: float
    est: RulEstimate


def run_config(
    d: Draw,
    t: np.ndarray,
    ch: dict[str, np.ndarray],
    ks: list[int],
    extra: dict[str, Any],
) -> list[RulEstimate]:
    """The estimator over the stream cut right after each prognosis sample ("every_batch")."""
    p = params_of(d)
    raw = {
        "plant": asdict(p),
        "r_diag": [
            (PAPER_NOISE_STD[0] * d.noise_scale) ** 2,
            (PAPER_NOISE_STD[1] * d.noise_scale) ** 2,
        ],
        "alpha0": d.alpha0,
        "current_var": CURRENT_NOISE_A**2,
        "rul_every_s": "every_batch",
        "rul_failure_dn": d.failure_dn,
        "dn_watch": 0.5 * d.failure_dn,
        "dn_alert": 0.6 * d.failure_dn,
        "health_window_samples": 50_000,
        "rul_load": rulmod.load_to_dict(
            rulmod.SquareWaveLoad(high_a=d.high_a, low_a=d.low_a, period_s=d.period_s, duty=d.duty)
        ),
        **extra,
    }
    config = seed_config(raw)
    state = de.initial_state(config)
    out: list[RulEstimate] = []
    lo = 0
    for k in ks:
        state, step_out = de.step(
            config, state, Batch(t[lo : k + 1], {n: v[lo : k + 1] for n, v in ch.items()})
        )
        out.extend(step_out.rul)
        lo = k + 1
    return out


PROGNOSIS = {"q_diag": [0.0, 0.0, 0.0, PROGNOSIS_Q44]}
CONFIGS: dict[str, dict[str, Any]] = {
    "A: prognosis tuning, same load law": PROGNOSIS,
    "B: seed Q, same load law": {},
    "C: prognosis tuning, load assumed = seed default (mismatched)": {
        **PROGNOSIS,
        "rul_load": {"kind": "square_wave"},
    },
    "D: prognosis tuning, observed load (truth's law not given)": {
        **PROGNOSIS,
        "rul_load": {"kind": "observed", "bin_samples": 40, "bins": 200, "merge_tolerance_a": 0.5},
    },
    **{f"A with q_m = {q:g}": {"q_diag": [0.0, 0.0, 0.0, q]} for q in SWEEP_Q44},
    **{
        f"{name[:1]} + the stream's record (rul_model_error)": {**extra, "rul_model_error": True}
        for name, extra in (
            ("A", PROGNOSIS),
            ("C", {**PROGNOSIS, "rul_load": {"kind": "square_wave"}}),
            (
                "D",
                {
                    **PROGNOSIS,
                    "rul_load": {
                        "kind": "observed",
                        "bin_samples": 40,
                        "bins": 200,
                        "merge_tolerance_a": 0.5,
                    },
                },
            ),
        )
    },
}
DRIFT_CONFIG = "E: prognosis tuning, truth's m drifting +50 % over its life"


def simulate(d: Draw, m_drift_per_s: float = 0.0) -> tuple[Any, Any, Any]:
    return simulate_friction_drive(
        CAP_S,
        FS,
        alpha0=d.alpha0,
        m=d.m,
        seed=d.seed,
        current=wave_of(d),
        noise=(PAPER_NOISE_STD[0] * d.noise_scale, PAPER_NOISE_STD[1] * d.noise_scale),
        current_noise_a=CURRENT_NOISE_A,
        params=params_of(d),
        stop_dn=d.failure_dn + 0.005,
        m_drift_per_s=m_drift_per_s,
    )


def score(
    d: Draw, t: np.ndarray, ch: dict[str, np.ndarray], dn: np.ndarray, extra: dict[str, Any], i: int
) -> list[Outcome]:
    """Prognoses at the first samples where the true Dn reaches each level, against the truth."""
    t_fail = first_crossing_time(t, dn, d.failure_dn)
    assert t_fail is not None
    levels = [lv for lv in DN_LEVELS if lv < d.failure_dn - 0.05]
    ks = [int(np.argmax(dn >= lv)) for lv in levels]
    by_t = {e.t_s: e for e in run_config(d, t, ch, ks, extra)}
    return [
        Outcome(i, lv, t_fail - t[k], by_t[t[k]])
        for lv, k in zip(levels, ks, strict=True)
        if t[k] in by_t
    ]


def run_to_failure(
    n_runs: int, seed: int
) -> tuple[dict[str, list[Outcome]], list[tuple[Draw, float]], int, float]:
    rng = np.random.default_rng(seed)
    results: dict[str, list[Outcome]] = {name: [] for name in [*CONFIGS, DRIFT_CONFIG]}
    draws: list[tuple[Draw, float]] = []
    redrawn = 0
    t0 = time.perf_counter()
    while len(draws) < n_runs:
        d = make_draw(rng, seed=1000 + len(draws) + redrawn)
        t, ch, tr = simulate(d)
        t_fail = first_crossing_time(t, tr["dn"], d.failure_dn)
        if t_fail is None:
            redrawn += 1
            continue
        i = len(draws)
        draws.append((d, t_fail))
        for name, extra in CONFIGS.items():
            results[name].extend(score(d, t, ch, tr["dn"], extra, i))
        # the same draw with m rising linearly by half its value over the constant-m life
        t2, ch2, tr2 = simulate(d, m_drift_per_s=0.5 * d.m / t_fail)
        if first_crossing_time(t2, tr2["dn"], d.failure_dn) is not None:
            results[DRIFT_CONFIG].extend(score(d, t2, ch2, tr2["dn"], PROGNOSIS, i))
        print(
            f"run {len(draws)}/{n_runs}: life {t_fail:7.1f} s, m {d.m:.4f}, alpha0 {d.alpha0:5.2f} "
            f"({time.perf_counter() - t0:5.0f} s)",
            flush=True,
        )
    return results, draws, redrawn, time.perf_counter() - t0


def fmt(v: float | None, scale: float = 1.0, spec: str = ".2f") -> str:
    return "-" if v is None else format(v / scale, spec)


def summarize(outcomes: list[Outcome], min_level: float) -> dict[str, float | int]:
    sel = [o for o in outcomes if o.level >= min_level]
    q50 = [o for o in sel if o.est.q50_s is not None]
    rel = np.array([(o.est.q50_s - o.true_s) / o.true_s for o in q50]) if q50 else np.array([])
    covered = [
        o.est.q05_s is not None
        and o.est.q05_s <= o.true_s
        and (o.est.q95_s is None or o.true_s <= o.est.q95_s)
        for o in sel
    ]
    bounds = [
        (o.est.pessimistic_s or 0.0) <= o.true_s <= (o.est.optimistic_s or math.inf) for o in sel
    ]
    width = [
        (o.est.q95_s - o.est.q05_s) / o.true_s
        for o in sel
        if o.est.q05_s is not None and o.est.q95_s is not None
    ]
    return {
        "n": len(sel),
        "n_q50": len(q50),
        "mae": float(np.mean(np.abs(rel))) if rel.size else math.nan,
        "bias": float(np.mean(rel)) if rel.size else math.nan,
        "p95": float(np.quantile(np.abs(rel), 0.95)) if rel.size else math.nan,
        "coverage": float(np.mean(covered)) if covered else math.nan,
        "bounds": float(np.mean(bounds)) if bounds else math.nan,
        "width": float(np.median(width)) if width else math.nan,
        "q95_none": sum(o.est.q95_s is None for o in sel),
    }


def rtf_section(n_runs: int, seed: int) -> list[str]:
    results, draws, redrawn, elapsed = run_to_failure(n_runs, seed)
    lives = np.array([life for _, life in draws])
    lines = [
        "### Run to failure: RUL against the simulated truth",
        "",
        f"{n_runs} simulated actuators (generator seed {seed}), each run at {FS:g} Hz until its "
        "true Dn reaches the failure threshold. Drawn per run: alpha0 ~ U(5, 20); m log-uniform "
        "in [0.004, 0.03], constant; a square-wave current, high ~ U(10, 30) A, low 0 A or ~ "
        "U(-10, 5) A, period ~ U(1, 4) s, duty ~ U(0.3, 0.7); each Table 1 parameter times "
        "U(0.8, 1.25) (the filter is given the drawn values); speed noise 1 to 10 times the "
        "seed's (R set to match), current noise 0.05 A; failure Dn in {0.7, 0.8, 0.9}. "
        f"{redrawn} draw(s) that would not fail within {CAP_S:g} s were redrawn. A prognosis "
        "(1,000 trajectories) is made when the true Dn first reaches 0.1, 0.2, ..., 0.8 (levels "
        "up to 0.05 below the threshold); the truth's RUL is the simulated time to the "
        f"threshold from there. Lives: median {np.median(lives):.0f} s, range "
        f"{lives.min():.0f}-{lives.max():.0f} s. Wall time {elapsed:.0f} s.",
        "",
        "Error = (q50 - true) / true. Coverage = share of prognoses with the truth in "
        "[q05, q95] (a q95 of None, i.e. more than 5 % of trajectories not failing within the "
        "horizon, counts as +inf). Bounds = share within [pessimistic, optimistic]. Width = "
        "median (q95 - q05) / true.",
        "",
        "| configuration | Dn levels | prognoses | mean abs error | mean error | 95 % abs error "
        "| coverage 5-95 % | within bounds | width | q95 None |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    summaries = {}
    for name, outs in results.items():
        for min_level, label in ((0.3, ">= 0.3"), (0.1, "all")):
            s = summarize(outs, min_level)
            summaries[(name, min_level)] = s
            lines.append(
                f"| {name} | {label} | {s['n']} | {100 * s['mae']:.2f} % | {100 * s['bias']:+.2f} % "
                f"| {100 * s['p95']:.2f} % | {100 * s['coverage']:.1f} % | {100 * s['bounds']:.1f} % "
                f"| {100 * s['width']:.2f} % | {s['q95_none']} |"
            )
    lines += [
        "",
        "By Dn level, configuration A:",
        "",
        "| Dn at prognosis | prognoses | mean abs error | coverage |",
        "|---:|---:|---:|---:|",
    ]
    a_name = next(iter(CONFIGS))
    for lv in DN_LEVELS:
        outs = [o for o in results[a_name] if o.level == lv]
        if not outs:
            continue
        s = summarize(outs, 0.0)
        lines.append(
            f"| {lv:.1f} | {s['n']} | {100 * s['mae']:.2f} % | {100 * s['coverage']:.1f} % |"
        )
    a = summaries[(a_name, 0.3)]
    goal_err = a["mae"] < 0.10
    goal_cov = 0.80 <= a["coverage"] <= 0.98
    lines += [
        "",
        "**Goals** (mean absolute RUL error under 10 % once Dn > 0.2; 5-95 % coverage between "
        f"80 and 98 %), configuration A: error {100 * a['mae']:.2f} % "
        f"({'met' if goal_err else 'NOT met'}), coverage {100 * a['coverage']:.1f} % "
        f"({'met' if goal_cov else 'NOT met'}).",
        "",
    ]
    names = list(CONFIGS)
    b = summaries[(names[1], 0.3)]
    c = summaries[(names[2], 0.3)]
    dd = summaries[(names[3], 0.3)]
    e = summaries[(DRIFT_CONFIG, 0.3)]
    sweep = ", ".join(
        f"{100 * summaries[(f'A with q_m = {q:g}', 0.3)]['coverage']:.0f} % (width "
        f"{100 * summaries[(f'A with q_m = {q:g}', 0.3)]['width']:.2f} %) for q_m = {q:g}"
        for q in SWEEP_Q44
    )
    lines += [
        f"**Random walk on m.** The coverage of A rests on the assumed random walk on m: {sweep}, "
        f"against {100 * a['coverage']:.0f} % for {PROGNOSIS_Q44:g}. The truth's m is constant, so "
        "the filter's m variance is set by this random walk, and at small values the interval "
        "becomes narrower than the propagation's own bias (the midpoint rule at "
        "`rul_segment_tol` = 0.01 predicts failure about 0.03 % early, see the methods). The "
        f"value {PROGNOSIS_Q44:g} was chosen on a separate calibration set (generator seed 7, "
        "10 runs).",
        "",
        f"**Seed Q (B).** Error {100 * b['mae']:.1f} %, coverage {100 * b['coverage']:.0f} %, q95 "
        f"None in {b['q95_none']} of {b['n']} prognoses: the random walk of 3.3e-5 per sample on "
        "m makes m-hat noisy and its variance huge, so many trajectories draw m <= 0 and never "
        "fail, and the median inherits the noise of m-hat at the prognosis instant. The seed's Q "
        "suits tracking abrupt changes of m, not prognosis.",
        "",
        "**Load assumption.** In A and B the prognosis assumes the truth's own load law (same "
        "square wave, same phase); the only errors are those of the estimate and of the "
        "propagation. C keeps the default assumption (the seed's 20 A, 2 s, 50 % wave) while "
        f"each truth runs its own wave: error {100 * c['mae']:.0f} %, coverage "
        f"{100 * c['coverage']:.0f} %. The wrong future load dominates and no covariance accounts "
        "for it (the stream's record below does). D assumes the recently observed load (8 s of current in 40 ms bins, repeated), "
        f"which needs no knowledge of the law: error {100 * dd['mae']:.1f} %, coverage "
        f"{100 * dd['coverage']:.0f} %; the bins smear the current edges and the 8 s window is "
        "not a whole number of the truth's periods, so the repeated profile is biased, and the "
        "interval does not include that bias.",
        "",
        "**The stream's record** (`rul_model_error`, on by default, off in the rows above to "
        "show the seed's prognosis): the intervals widened by the relative wear-rate errors the "
        "stream has seen between prognoses. "
        + "; ".join(
            f"{key[:1]}: error {100 * summaries[(key, 0.3)]['mae']:.1f} %, coverage "
            f"{100 * summaries[(key, 0.3)]['coverage']:.0f} %, width "
            f"{100 * summaries[(key, 0.3)]['width']:.1f} %"
            for key in CONFIGS
            if key.endswith("(rul_model_error)")
        )
        + ". Here a prognosis is made only at each Dn level (0.1, 0.2, ...), so the record "
        "holds few comparisons, each over a long span.",
        "",
        f"**Drifting m (E).** When the truth's m rises linearly by 50 % over the life, the "
        f"prognosis (which assumes m constant from now on) has error {100 * e['mae']:.1f} % "
        f"(mean {100 * e['bias']:+.1f} %), coverage {100 * e['coverage']:.0f} %.",
        "",
    ]
    return lines


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--runs", type=int, default=40)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--scenario-seeds", type=int, default=5)
    ap.add_argument("--drives", type=int, default=60)
    ap.add_argument(
        "--cache", type=Path, default=None, help="directory keeping the simulated drives"
    )
    args = ap.parse_args()
    de.warm_up()
    lines = [
        BEGIN,
        "## Deterioration EKF and RUL (friction drive)",
        "",
        "Generated by `scripts/validate_deterioration_ekf.py "
        f"--runs {args.runs} --seed {args.seed} --drives {args.drives}`; method in "
        "`docs/methods-deterioration-ekf.md`.",
        "",
        "The first section runs the kind's defaults on drives made by an independent generator "
        "(not the filter's discretization). The sections after it reproduce the seed and "
        "today's checks on the project's own simulator with the seed's filter settings "
        "(`input_model` hold, fixed R and Q, no gating, no random walk of m, no plant "
        "calibration, no band scaling, alpha0 given), "
        "which that simulator matches by construction (current held over each sample, "
        "channels sampled together).",
        "",
    ]
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from validate_dekf_drives import drives_section

    lines += drives_section(
        args.drives, log=lambda msg: print(msg, flush=True), cache=args.cache
    )
    lines += seed_scenario_section(args.scenario_seeds)
    lines += seed_rul_example()
    lines += rtf_section(args.runs, args.seed)
    lines.append(END)
    section = "\n".join(lines)
    text = DOC.read_text(encoding="utf-8") if DOC.exists() else "# Validation\n\n"
    if BEGIN in text and END in text:
        head, rest = text.split(BEGIN, 1)
        _, tail = rest.split(END, 1)
        text = head + section + tail
    else:
        text = text.rstrip("\n") + "\n\n" + section + "\n"
    DOC.parent.mkdir(parents=True, exist_ok=True)
    DOC.write_text(text, encoding="utf-8")
    print(f"wrote {DOC}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
