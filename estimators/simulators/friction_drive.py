"""Roller-on-tire friction drive with contact deterioration: a reference plant with known truth
for the deterioration EKF.

Plant (seed eqs. 1-4 and 7): a DC motor (radius r1) drives a wheel (radius r2) through a
friction contact whose force is ``Fc = alpha (r1 w1 - r2 w2)``; the contact quality ``alpha``
wears with the dissipated power::

    J1 dw1/dt = -alpha r1 dv - B1 w1 + Km I,      dv = r1 w1 - r2 w2
    J2 dw2/dt =  alpha r2 dv - B2 w2
    dalpha/dt = -m dv^2 alpha

The motor current I is applied as a zero-order hold between samples (the value at sample k
holds over ``[t_k, t_{k+1})``, which is also what the filter assumes); the ODE is integrated
with classical Runge-Kutta at ``substeps`` steps per sample (by default enough for
``h |lambda| <= 0.05`` on the fastest mode at ``alpha0``). The wear rate ``m`` may jump at given
times (seed assumption ii) or drift linearly (assumption iii). Both speeds are measured with
white Gaussian noise (default: the seed's R, section 5.2); the current is measured with optional
white noise.

Default parameters are the seed's Table 1 and its section 5.1 scenario: a square-wave current
of 20 A, period 2 s, 50 % duty, ``alpha(0) = 10``, ``m = 0.01``. The seed does not state whether
its square wave is 0/20 A or -20/20 A; a pulse between 0 and 20 A is used here (its "duty cycle"
wording is that of a pulse generator).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numba import njit
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.float64]

#: Standard deviations of the seed's measurement noise (sigma1^2 = 1.0063e-8,
#: sigma2^2 = 1.0083e-10, section 5.2), rad/s.
PAPER_NOISE_STD = (math.sqrt(1.0063e-8), math.sqrt(1.0083e-10))
CHANNELS = ("current", "motor_speed", "wheel_speed")


@dataclass(frozen=True)
class FrictionDriveParams:
    """Physical parameters (seed Table 1).

    Attributes:
        r1_m: external radius of the motor roller.
        r2_m: external radius of the driven wheel.
        b1_nm_s: viscous damping of the motor (N m s/rad).
        b2_nm_s: viscous damping of the wheel (N m s/rad).
        j1_kg_m2: motor inertia.
        j2_kg_m2: wheel inertia.
        km_nm_a: motor constant (torque per ampere).
    """

    r1_m: float = 0.0315
    r2_m: float = 0.35
    b1_nm_s: float = 6.36e-3
    b2_nm_s: float = 1.76e-3
    j1_kg_m2: float = 3.47e-4
    j2_kg_m2: float = 0.2
    km_nm_a: float = 0.0477465

    def as_array(self) -> FloatArray:
        """``[r1, r2, B1, B2, J1, J2, Km]``, the layout of the compiled kernels."""
        return np.array(
            [
                self.r1_m,
                self.r2_m,
                self.b1_nm_s,
                self.b2_nm_s,
                self.j1_kg_m2,
                self.j2_kg_m2,
                self.km_nm_a,
            ],
            dtype=np.float64,
        )


@dataclass(frozen=True)
class SquareWave:
    """A periodic pulse current: ``high_a`` for ``duty * period_s`` from each rising edge at
    ``t0_s + k period_s``, ``low_a`` for the rest of the period."""

    high_a: float = 20.0
    low_a: float = 0.0
    period_s: float = 2.0
    duty: float = 0.5
    t0_s: float = 0.0

    def at(self, t_s: ArrayLike) -> FloatArray:
        """The current at times ``t_s``."""
        t = np.asarray(t_s, dtype=np.float64)
        phase = np.mod(t - self.t0_s, self.period_s)
        # a relative tolerance keeps edges that fall on sample times on the same side
        # whatever the rounding of t - t0
        edge = self.duty * self.period_s * (1.0 - 1e-12)
        return np.where(phase < edge, self.high_a, self.low_a)


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
def _integrate(
    p: FloatArray,
    dt: float,
    substeps: int,
    current: FloatArray,
    m_of_k: FloatArray,
    w1: float,
    w2: float,
    al: float,
    stop_alpha: float,
) -> tuple[FloatArray, int]:
    """RK4 over the samples; row k of the result is the state at sample k. Stops after the first
    sample with ``alpha <= stop_alpha`` (returns the number of samples filled)."""
    n = current.shape[0]
    x = np.empty((n, 3))
    h = dt / substeps
    for k in range(n):
        x[k, 0] = w1
        x[k, 1] = w2
        x[k, 2] = al
        if al <= stop_alpha:
            return x, k + 1
        u = current[k]
        m = m_of_k[k]
        for _ in range(substeps):
            a1, b1, c1 = _rhs(p, w1, w2, al, m, u)
            a2, b2, c2 = _rhs(p, w1 + 0.5 * h * a1, w2 + 0.5 * h * b1, al + 0.5 * h * c1, m, u)
            a3, b3, c3 = _rhs(p, w1 + 0.5 * h * a2, w2 + 0.5 * h * b2, al + 0.5 * h * c2, m, u)
            a4, b4, c4 = _rhs(p, w1 + h * a3, w2 + h * b3, al + h * c3, m, u)
            w1 += h * (a1 + 2.0 * a2 + 2.0 * a3 + a4) / 6.0
            w2 += h * (b1 + 2.0 * b2 + 2.0 * b3 + b4) / 6.0
            al += h * (c1 + 2.0 * c2 + 2.0 * c3 + c4) / 6.0
    return x, n


def default_substeps(params: FrictionDriveParams, alpha0: float, sample_rate_hz: float) -> int:
    """RK4 steps per sample so that ``h |lambda| <= 0.05`` on the fastest mode at ``alpha0``
    (Gershgorin bound of ``A(alpha0)``; the modes slow down as alpha wears)."""
    p = params
    a = (alpha0 * p.r1_m**2 + p.b1_nm_s) / p.j1_kg_m2
    b = alpha0 * p.r1_m * p.r2_m / p.j1_kg_m2
    c = alpha0 * p.r1_m * p.r2_m / p.j2_kg_m2
    d = (alpha0 * p.r2_m**2 + p.b2_nm_s) / p.j2_kg_m2
    bound = max(a + b, c + d)
    return max(1, math.ceil(bound / sample_rate_hz / 0.05))


def _wear_rate(
    t: FloatArray, m: float, m_changes: Sequence[tuple[float, float]], m_drift_per_s: float
) -> FloatArray:
    """``m`` at each sample: the last value set at or before t, plus the linear drift."""
    m_of_t = np.full(t.shape, float(m))
    for t_change, m_new in sorted(m_changes):
        m_of_t[t >= t_change] = float(m_new)
    return np.asarray(np.maximum(m_of_t + m_drift_per_s * (t - t[0]), 0.0), dtype=np.float64)


def simulate_friction_drive(
    duration_s: float,
    sample_rate_hz: float = 1000.0,
    *,
    alpha0: float = 10.0,
    m: float = 0.01,
    seed: int = 0,
    current: float | SquareWave | ArrayLike | None = None,
    m_changes: Sequence[tuple[float, float]] = (),
    m_drift_per_s: float = 0.0,
    noise: tuple[float, float] = PAPER_NOISE_STD,
    current_noise_a: float = 0.0,
    params: FrictionDriveParams | None = None,
    initial_speeds: tuple[float, float] = (0.0, 0.0),
    t0_s: float = 0.0,
    substeps: int | None = None,
    stop_dn: float | None = None,
) -> tuple[FloatArray, dict[str, FloatArray], dict[str, FloatArray]]:
    """Simulate the friction drive and its measured telemetry.

    Args:
        duration_s: length of the run; samples at ``t0_s + k / sample_rate_hz``, k = 0..n-1.
        sample_rate_hz: sampling rate of the telemetry (and of the zero-order-hold input).
        alpha0: contact quality at the start, alpha(0).
        m: wear rate at the start.
        seed: seed of the measurement noise.
        current: applied current: a number (constant), a :class:`SquareWave`, or an array of
            one value per sample. Default: ``SquareWave()`` (20 A, 2 s, 50 %), phase ``t0_s``.
        m_changes: ``(t_s, m_new)`` pairs: m jumps to ``m_new`` at the first sample at or after
            ``t_s`` (seed assumption ii).
        m_drift_per_s: linear drift of m per second of the run (assumption iii).
        noise: standard deviations of the motor and wheel speed noise (rad/s).
        current_noise_a: standard deviation of the current measurement noise (A).
        params: plant parameters (default: seed Table 1).
        initial_speeds: ``(w1, w2)`` at the first sample.
        t0_s: time of the first sample.
        substeps: RK4 steps per sample (default :func:`default_substeps`).
        stop_dn: if given, the run ends at the first sample whose true Dn reaches this value.

    Returns:
        ``(t_s, channels, truth)``: sample times; measured channels ``current`` (A),
        ``motor_speed`` (w1, rad/s) and ``wheel_speed`` (w2, rad/s) as named by the
        ``friction_drive`` actuator kind; true ``w1``, ``w2``, ``alpha``, ``m``, ``dn`` (``1 -
        alpha / alpha0``) and ``current`` (applied, A). All arrays have shape (n,).
    """
    p = params or FrictionDriveParams()
    n = int(round(duration_s * sample_rate_hz))
    t = t0_s + np.arange(n, dtype=np.float64) / sample_rate_hz
    if current is None:
        current = SquareWave(t0_s=t0_s)
    if isinstance(current, SquareWave):
        applied = current.at(t)
    elif np.ndim(current) == 0:
        applied = np.full(n, float(current))  # type: ignore[arg-type]
    else:
        applied = np.asarray(current, dtype=np.float64)
        if applied.shape != (n,):
            raise ValueError(f"current: expected {n} values, got shape {applied.shape}")
    m_of_t = _wear_rate(t, m, m_changes, m_drift_per_s)
    steps = substeps or default_substeps(p, alpha0, sample_rate_hz)
    stop_alpha = -math.inf if stop_dn is None else alpha0 * (1.0 - stop_dn)
    x, filled = _integrate(
        p.as_array(),
        1.0 / sample_rate_hz,
        steps,
        np.ascontiguousarray(applied),
        m_of_t,
        float(initial_speeds[0]),
        float(initial_speeds[1]),
        float(alpha0),
        stop_alpha,
    )
    t = t[:filled]
    applied = applied[:filled]
    rng = np.random.default_rng(seed)
    channels = {
        "current": applied + current_noise_a * rng.standard_normal(filled),
        "motor_speed": x[:filled, 0] + noise[0] * rng.standard_normal(filled),
        "wheel_speed": x[:filled, 1] + noise[1] * rng.standard_normal(filled),
    }
    truth = {
        "w1": x[:filled, 0].copy(),
        "w2": x[:filled, 1].copy(),
        "alpha": x[:filled, 2].copy(),
        "m": m_of_t[:filled],
        "dn": 1.0 - x[:filled, 2] / alpha0,
        "current": applied,
    }
    return t, channels, truth


def first_crossing_time(t_s: FloatArray, values: FloatArray, level: float) -> float | None:
    """Time at which ``values`` first reaches ``level``, linearly interpolated between samples
    (None if it never does)."""
    above = np.flatnonzero(values >= level)
    if above.size == 0:
        return None
    k = int(above[0])
    if k == 0:
        return float(t_s[0])
    v0, v1 = float(values[k - 1]), float(values[k])
    return float(t_s[k - 1] + (level - v0) / (v1 - v0) * (t_s[k] - t_s[k - 1]))
