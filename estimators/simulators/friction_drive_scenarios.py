"""Run-to-failure friction-drive telemetry made independently of the filter's discretization.

The deterioration EKF predicts over each sample interval with a held (or interval-mean) current
and samples every channel at the same instant. Real telemetry does neither, so this generator:

* integrates the plant (seed eqs. 1-4 and 7) with classical Runge-Kutta at a fine step
  (``fine_step_s``, 0.1 ms by default, at least 10x the fastest sample rate), cutting the step
  exactly at every current switch, which happens at arbitrary instants (load laws below);
* samples each channel at its own instants: nominal times ``t_k = k / rate`` plus a per-channel
  constant skew and a per-sample jitter; the telemetry carries the nominal ``t_k`` only;
* adds white Gaussian noise of 1x to 1000x the seed's standard deviation (section 5.2);
* draws per drive: alpha0 (nominal 10, +-30 %), the wear rate m, the failure threshold Dn
  (0.3-0.9), the load law (square wave of random period, duty, levels and phase; a random
  telegraph between two levels; a recorded mission profile with ramps) and, optionally, a plant
  whose friction and inertia differ from the nominal (Table 1) ones by up to +-20 %.

The filter under test is given the nominal plant; the truth's plant may differ.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numba import njit
from numpy.typing import NDArray

from estimators.simulators.friction_drive import PAPER_NOISE_STD, FrictionDriveParams

FloatArray = NDArray[np.float64]

#: A "recorded" mission profile (current in A, seconds): taxi, run-up, cruise with corrections,
#: descent; the ramps are recorded at 50 Hz (steps of 20 ms).
MISSION_KNOTS_S = (0.0, 2.0, 2.6, 6.0, 6.5, 9.0, 9.4, 11.0, 13.0, 14.0)
MISSION_KNOTS_A = (4.0, 4.0, 24.0, 18.0, 26.0, 12.0, 12.0, 20.0, 2.0, 4.0)
MISSION_STEP_S = 0.02


@dataclass(frozen=True)
class Drive:
    """One randomized run-to-failure drive.

    Attributes:
        seed: the seed it was drawn from.
        rate_hz: telemetry sample rate.
        alpha0: true contact quality at the start.
        m: true wear rate (constant).
        failure_dn: the failure threshold on Dn.
        noise_factor: sensor noise std as a multiple of the seed's.
        skew_s: (current, w1, w2) constant time offsets of the channels, s.
        jitter_s: std of the per-sample timing jitter of every channel, s.
        load: "square", "telegraph" or "mission".
        load_params: the law's parameters (levels, period, duty, phase, dwell, scale).
        plant: the truth's plant (nominal, or friction/inertia off by up to +-20 %).
        mismatch: whether the plant differs from the nominal one.
    """

    seed: int
    rate_hz: float
    alpha0: float
    m: float
    failure_dn: float
    noise_factor: float
    skew_s: tuple[float, float, float]
    jitter_s: float
    load: str
    load_params: dict[str, float] = field(default_factory=dict)
    plant: FrictionDriveParams = field(default_factory=FrictionDriveParams)
    mismatch: bool = False


def switches(drive: Drive, duration_s: float) -> tuple[FloatArray, FloatArray]:
    """(switch times, current from each switch on) of the drive's load over ``duration_s``;
    the first switch is at 0."""
    p = drive.load_params
    rng = np.random.default_rng([drive.seed, 7])
    if drive.load == "square":
        period, duty, phase = p["period_s"], p["duty"], p["phase_s"]
        k = math.floor(-phase / period) - 1
        events: list[tuple[float, float]] = []
        while phase + k * period <= duration_s:
            rise = phase + k * period
            events.extend(((rise, p["high_a"]), (rise + duty * period, p["low_a"])))
            k += 1
        first = [v for t, v in events if t <= 0.0][-1]
        later = [(t, v) for t, v in events if 0.0 < t <= duration_s]
        return (
            np.array([0.0] + [t for t, _ in later]),
            np.array([first] + [v for _, v in later]),
        )
    if drive.load == "telegraph":
        t = 0.0
        level = bool(rng.integers(2))
        tt, vv = [], []
        while t <= duration_s:
            tt.append(t)
            vv.append(p["high_a"] if level else p["low_a"])
            t += rng.exponential(p["dwell_s"])
            level = not level
        return np.array(tt), np.array(vv)
    # mission: the profile at 50 Hz steps, scaled, repeated, phase-shifted
    knots_t = np.array(MISSION_KNOTS_S)
    knots_a = np.array(MISSION_KNOTS_A) * p["scale"]
    period = float(knots_t[-1])
    grid = np.arange(0.0, period, MISSION_STEP_S)
    profile = np.interp(grid, knots_t, knots_a)
    n_rep = int(math.ceil((duration_s + period) / period)) + 1
    starts = (np.arange(n_rep)[:, None] * period + grid[None, :]).ravel() - p["phase_s"]
    values = np.tile(profile, n_rep)
    keep = starts > 0.0
    first = values[~keep][-1] if (~keep).any() else values[0]
    return np.concatenate([[0.0], starts[keep]]), np.concatenate([[first], values[keep]])


def square_wave_law(drive: Drive, high_scale: float = 1.0) -> dict[str, float | str]:
    """A square-wave drive's own load law as the "square_wave" load assumption a user would
    configure (``high_scale`` scales the high level, to assume a wrong law)."""
    p = drive.load_params
    return {
        "kind": "square_wave",
        "high_a": high_scale * p["high_a"],
        "low_a": p["low_a"],
        "period_s": p["period_s"],
        "duty": p["duty"],
        "t0_s": p["phase_s"],
    }


def mission_profile(scale: float) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """The mission profile as (durations, currents) segments (what a user would configure as
    the "profile" load assumption from the recording)."""
    knots_t = np.array(MISSION_KNOTS_S)
    grid = np.arange(0.0, knots_t[-1], MISSION_STEP_S)
    profile = np.interp(grid, knots_t, np.array(MISSION_KNOTS_A) * scale)
    durations = np.diff(np.append(grid, knots_t[-1]))
    return tuple(float(v) for v in durations), tuple(float(v) for v in profile)


@njit(cache=True, error_model="numpy")
def _rhs(
    p: FloatArray, w1: float, w2: float, al: float, m: float, u: float
) -> tuple[float, float, float]:
    dv = p[0] * w1 - p[1] * w2
    return (
        (-al * p[0] * dv - p[2] * w1 + p[6] * u) / p[4],
        (al * p[1] * dv - p[3] * w2) / p[5],
        -m * dv * dv * al,
    )


@njit(cache=True, error_model="numpy")
def integrate_at(
    p: FloatArray,
    m: float,
    alpha0: float,
    sw_t: FloatArray,
    sw_u: FloatArray,
    targets: FloatArray,
    h_max: float,
) -> FloatArray:
    """RK4 from rest at t = 0 with steps of at most ``h_max``, cut at every switch and every
    target time (``targets`` sorted); rows ``[w1, w2, alpha, current]`` at the targets."""
    n = targets.shape[0]
    out = np.empty((n, 4))
    w1 = 0.0
    w2 = 0.0
    al = alpha0
    t = 0.0
    j = 0
    n_sw = sw_t.shape[0]
    u = sw_u[0]
    while j + 1 < n_sw and sw_t[j + 1] <= t:
        j += 1
        u = sw_u[j]
    for i in range(n):
        target = targets[i]
        while t < target:
            nxt = sw_t[j + 1] if j + 1 < n_sw else math.inf
            h = min(h_max, target - t, nxt - t)
            a1, b1, c1 = _rhs(p, w1, w2, al, m, u)
            a2, b2, c2 = _rhs(p, w1 + 0.5 * h * a1, w2 + 0.5 * h * b1, al + 0.5 * h * c1, m, u)
            a3, b3, c3 = _rhs(p, w1 + 0.5 * h * a2, w2 + 0.5 * h * b2, al + 0.5 * h * c2, m, u)
            a4, b4, c4 = _rhs(p, w1 + h * a3, w2 + h * b3, al + h * c3, m, u)
            w1 += h * (a1 + 2.0 * a2 + 2.0 * a3 + a4) / 6.0
            w2 += h * (b1 + 2.0 * b2 + 2.0 * b3 + b4) / 6.0
            al += h * (c1 + 2.0 * c2 + 2.0 * c3 + c4) / 6.0
            t += h
            if t >= nxt:
                t = nxt
                j += 1
                u = sw_u[j]
        out[i, 0] = w1
        out[i, 1] = w2
        out[i, 2] = al
        out[i, 3] = u
    return out


def draw_drive(
    seed: int,
    *,
    rate_hz: float | None = None,
    noise_factor: float | None = None,
    load: str | None = None,
    mismatch: bool | None = None,
    skew: bool | None = None,
) -> Drive:
    """A random drive; any of the named conditions may be fixed instead of drawn."""
    rng = np.random.default_rng([seed, 1])
    rate = rate_hz if rate_hz is not None else float(rng.choice([50.0, 100.0, 200.0, 500.0, 1000.0]))
    noise = noise_factor if noise_factor is not None else float(10.0 ** rng.uniform(0.0, 3.0))
    law = load if load is not None else str(rng.choice(["square", "telegraph", "mission"]))
    mis = bool(rng.integers(2)) if mismatch is None else mismatch
    skew = bool(rng.integers(2)) if skew is None else skew
    if law == "square":
        high = rng.uniform(10.0, 30.0)
        params = {
            "high_a": high,
            "low_a": float(rng.choice([0.0, rng.uniform(-10.0, 5.0)])),
            "period_s": rng.uniform(1.0, 4.0),
            "duty": rng.uniform(0.3, 0.7),
            "phase_s": rng.uniform(0.0, 4.0),
        }
    elif law == "telegraph":
        params = {
            "high_a": rng.uniform(10.0, 30.0),
            "low_a": rng.uniform(-5.0, 5.0),
            "dwell_s": rng.uniform(0.3, 2.0),
        }
    else:
        params = {"scale": rng.uniform(0.6, 1.4), "phase_s": rng.uniform(0.0, 14.0)}
    nominal = FrictionDriveParams()
    plant = nominal
    if mis:
        f = rng.uniform(0.8, 1.2, 4)
        plant = FrictionDriveParams(
            b1_nm_s=nominal.b1_nm_s * f[0],
            b2_nm_s=nominal.b2_nm_s * f[1],
            j1_kg_m2=nominal.j1_kg_m2 * f[2],
            j2_kg_m2=nominal.j2_kg_m2 * f[3],
        )
    skews = (
        tuple(float(v) for v in rng.uniform(-1.5e-3, 1.5e-3, 3)) if skew else (0.0, 0.0, 0.0)
    )
    return Drive(
        seed=seed,
        rate_hz=rate,
        alpha0=10.0 * rng.uniform(0.7, 1.3),
        m=float(10.0 ** rng.uniform(math.log10(0.003), math.log10(0.03))),
        failure_dn=float(rng.uniform(0.3, 0.9)),
        noise_factor=noise,
        skew_s=skews,  # type: ignore[arg-type]
        jitter_s=float(rng.uniform(0.0, 2e-4)) if skew else 0.0,
        load=law,
        load_params={k: float(v) for k, v in params.items()},
        plant=plant,
        mismatch=mis,
    )


@dataclass(frozen=True)
class DriveData:
    """Telemetry of a drive and its truth.

    Attributes:
        t_s: nominal sample times (what the telemetry carries), shape (n,).
        channels: ``current`` (A), ``motor_speed``, ``wheel_speed`` (rad/s) as measured.
        alpha: true alpha at the speed sample instants.
        dn: true Dn at the speed sample instants.
        t_fail_s: first time the true Dn reaches the failure threshold (fine grid).
    """

    t_s: FloatArray
    channels: dict[str, FloatArray]
    alpha: FloatArray
    dn: FloatArray
    t_fail_s: float


def simulate_drive(
    drive: Drive, max_s: float = 1500.0, fine_step_s: float = 1e-4, margin_s: float = 5.0
) -> DriveData | None:
    """Simulate the drive to ``margin_s`` past its failure; None if it does not fail within
    ``max_s`` (the caller redraws)."""
    p = drive.plant.as_array()
    # failure time on a coarse pass of the fine integration (targets every 0.1 s)
    probe_t = np.arange(0.1, max_s, 0.1)
    sw_t, sw_u = switches(drive, max_s + margin_s + 1.0)
    probe = integrate_at(p, drive.m, drive.alpha0, sw_t, sw_u, probe_t, fine_step_s)
    alpha_fail = drive.alpha0 * (1.0 - drive.failure_dn)
    below = np.flatnonzero(probe[:, 2] <= alpha_fail)
    if below.size == 0:
        return None
    k = int(below[0])
    lo = probe_t[k - 1] if k > 0 else 0.0
    fine_t = np.linspace(lo, probe_t[k], 1001)[1:]
    fine = integrate_at(p, drive.m, drive.alpha0, sw_t, sw_u, fine_t, fine_step_s)
    t_fail = float(fine_t[int(np.flatnonzero(fine[:, 2] <= alpha_fail)[0])])
    t_s, channels, alpha = telemetry(drive, t_fail + margin_s, sw_t, sw_u, fine_step_s)
    return DriveData(
        t_s=t_s, channels=channels, alpha=alpha, dn=1.0 - alpha / drive.alpha0, t_fail_s=t_fail
    )


def telemetry(
    drive: Drive,
    duration_s: float,
    sw_t: FloatArray | None = None,
    sw_u: FloatArray | None = None,
    fine_step_s: float = 1e-4,
) -> tuple[FloatArray, dict[str, FloatArray], FloatArray]:
    """(nominal times, measured channels, true alpha at the w1 instants) over ``duration_s``."""
    p = drive.plant.as_array()
    if sw_t is None or sw_u is None:
        sw_t, sw_u = switches(drive, duration_s + 1.0)
    rng = np.random.default_rng([drive.seed, 2])
    n = int(duration_s * drive.rate_hz)
    t_nom = 0.5 / drive.rate_hz + np.arange(n) / drive.rate_hz
    rows = []
    for skew in drive.skew_s:
        inst = t_nom + skew + drive.jitter_s * rng.standard_normal(n)
        inst = np.maximum(inst, 1e-6)
        order = np.argsort(inst)
        vals = np.empty((n, 4))
        vals[order] = integrate_at(
            p, drive.m, drive.alpha0, sw_t, sw_u, np.ascontiguousarray(inst[order]), fine_step_s
        )
        rows.append(vals)
    std1, std2 = (drive.noise_factor * s for s in PAPER_NOISE_STD)
    channels = {
        "current": rows[0][:, 3].copy(),
        "motor_speed": rows[1][:, 0] + std1 * rng.standard_normal(n),
        "wheel_speed": rows[2][:, 1] + std2 * rng.standard_normal(n),
    }
    return t_nom, channels, rows[1][:, 2].copy()


def draw_failing_drive(
    seed: int, max_s: float = 1500.0, min_life_s: float = 40.0, **conditions: object
) -> tuple[Drive, DriveData]:
    """Draw drives from ``seed`` (then derived seeds) until one fails within
    [``min_life_s``, ``max_s``]."""
    for attempt in range(50):
        drive = draw_drive(seed * 1000 + attempt, **conditions)  # type: ignore[arg-type]
        data = simulate_drive(drive, max_s=max_s)
        if data is not None and data.t_fail_s >= min_life_s:
            return drive, data
    raise RuntimeError(f"no failing drive drawn from seed {seed}")
