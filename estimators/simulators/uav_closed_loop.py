"""Closed-loop small-UAV flight with control-surface faults: the reference plant of ``stmmae``.

The nonlinear Aerosonde equations of ``estimators.models.small_uav`` (five independent surfaces
plus throttle) are integrated with fourth-order Runge-Kutta at the sample rate. An autopilot
holds airspeed, altitude, wings level and heading: a linear-quadratic regulator designed on the
linearization at trim, with integral action on the airspeed, altitude, bank and heading errors,
commanding one aileron, one elevator, one rudder and one throttle signal; both aileron halves
receive the aileron command and both elevator halves the elevator command. The autopilot reads
the true state (a well-filtered navigation solution); commands are limited to
``+-surface_limit_deg`` and each surface follows its command through a first-order servo lag.

A fault replaces a surface's actual deflection by the fault signal during ``[start_s, end_s)``:
``stuck`` holds ``position_deg``; ``square`` alternates between ``center_deg + amplitude_deg``
and ``center_deg - amplitude_deg`` every half ``period_s`` (starting high); ``sine`` is
``center_deg + amplitude_deg sin(2 pi (t - start_s) / period_s)``. The servo lag restarts from
the fault value when the fault ends.

Measured channels carry white Gaussian noise with the seed paper's variances (p, q, r:
0.0076 rad^2/s^2; alpha, beta: 0.0012 rad^2; airspeed: 1 m^2/s^2); command channels are exact.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from functools import lru_cache
from typing import Literal

import numpy as np
from numpy.typing import NDArray
from scipy.linalg import solve_continuous_are

from estimators.models import small_uav as uav

FloatArray = NDArray[np.float64]
FaultKind = Literal["stuck", "square", "sine"]

MEASURED_CHANNELS = ("p", "q", "r", "alpha", "beta", "airspeed")
COMMAND_CHANNELS = tuple(f"cmd_{name}" for name in uav.INPUTS)
CHANNELS = MEASURED_CHANNELS + COMMAND_CHANNELS
SENSOR_VAR = dict(zip(MEASURED_CHANNELS, uav.SENSOR_VAR, strict=True))


@dataclass(frozen=True)
class SurfaceFault:
    """One fault of one surface.

    Attributes:
        surface: one of ``small_uav.SURFACES``.
        start_s: fault onset (stream time, s).
        end_s: fault end (the surface works again from then on).
        kind: ``"stuck"``, ``"square"`` or ``"sine"``.
        position_deg: stuck position (``stuck``).
        center_deg: mean deflection (``square``, ``sine``).
        amplitude_deg: half the peak-to-peak swing (``square``, ``sine``).
        period_s: period of the oscillation (``square``, ``sine``).
    """

    surface: str
    start_s: float
    end_s: float
    kind: FaultKind = "stuck"
    position_deg: float = 0.0
    center_deg: float = 0.0
    amplitude_deg: float = 0.0
    period_s: float = 2.0

    def __post_init__(self) -> None:
        if self.surface not in uav.SURFACES:
            raise ValueError(f"surface: expected one of {uav.SURFACES}, got {self.surface!r}")
        if self.kind not in ("stuck", "square", "sine"):
            raise ValueError(f"kind: expected stuck, square or sine, got {self.kind!r}")
        if not self.end_s > self.start_s:
            raise ValueError("end_s must be after start_s")
        if self.kind != "stuck" and not self.period_s > 0.0:
            raise ValueError("period_s must be positive")

    def deflection_rad(self, t_s: float) -> float:
        """The surface's deflection at ``t_s`` (inside the fault interval)."""
        if self.kind == "stuck":
            return math.radians(self.position_deg)
        phase = (t_s - self.start_s) / self.period_s
        if self.kind == "square":
            high = (phase - math.floor(phase)) < 0.5
            return math.radians(
                self.center_deg + (self.amplitude_deg if high else -self.amplitude_deg)
            )
        return math.radians(self.center_deg + self.amplitude_deg * math.sin(2.0 * math.pi * phase))

    @property
    def oscillating(self) -> bool:
        """True for the oscillating kinds."""
        return self.kind != "stuck"


@dataclass(frozen=True)
class Manoeuvre:
    """A change of the autopilot's heading and altitude references, ramped linearly over
    ``[start_s, start_s + duration_s]`` (a coordinated turn and/or a climb or descent); the
    references then hold their new values.

    Attributes:
        start_s: start of the ramp (stream time, s).
        duration_s: ramp length (s).
        heading_change_deg: heading change (positive: turn right).
        altitude_change_m: altitude change (positive: climb).
    """

    start_s: float
    duration_s: float
    heading_change_deg: float = 0.0
    altitude_change_m: float = 0.0

    def __post_init__(self) -> None:
        if not self.duration_s > 0.0:
            raise ValueError("duration_s must be positive")

    def offsets(self, t_s: float) -> tuple[float, float]:
        """``(heading change rad, altitude change m)`` reached at ``t_s``."""
        frac = min(max((t_s - self.start_s) / self.duration_s, 0.0), 1.0)
        return math.radians(self.heading_change_deg) * frac, self.altitude_change_m * frac


PAPER_FAULT_SCHEDULE: tuple[SurfaceFault, ...] = (
    SurfaceFault("aileron_left", 10.0, 40.0, "stuck", position_deg=-15.0),
    SurfaceFault("aileron_right", 70.0, 100.0, "square", center_deg=0.0, amplitude_deg=15.0),
    SurfaceFault("rudder", 130.0, 160.0, "stuck", position_deg=-1.0),
    SurfaceFault("elevator_left", 190.0, 220.0, "stuck", position_deg=10.0),
    SurfaceFault("elevator_right", 250.0, 280.0, "square", center_deg=4.0, amplitude_deg=2.0),
)
"""The seed paper's fault sequence (section 3.2); square-wave period 2 s (the paper gives none)."""


@dataclass(frozen=True)
class FlightTruth:
    """What the simulator knows and the estimator must infer.

    Attributes:
        states: reduced state name (``small_uav.STATES``) -> true values, each shape (n,).
        deflections_rad: surface -> actual deflection, shape (n,).
        faulty_surface: index into ``small_uav.SURFACES`` of the surface in fault at each
            sample, -1 when none, shape (n,).
        faults: the schedule simulated.
        trim: the trim the flight starts from and the autopilot holds.
    """

    states: dict[str, FloatArray]
    deflections_rad: dict[str, FloatArray]
    faulty_surface: NDArray[np.int64]
    faults: tuple[SurfaceFault, ...]
    trim: uav.Trim = field(repr=False)


@dataclass(frozen=True)
class _Autopilot:
    gain: FloatArray  # (4, 14)
    trim: uav.Trim
    limit_rad: float


def _ap_state(x: FloatArray) -> FloatArray:
    """Autopilot state ``[Va, alpha, beta, p, q, r, phi, theta, psi, h]`` of a full state."""
    va, alpha, beta = uav.air_data(x)
    return np.array([va, alpha, beta, x[9], x[10], x[11], x[6], x[7], x[8], -x[2]])


def _ap_derivatives(prm: uav.AerosondeParams, z: FloatArray, d: FloatArray) -> FloatArray:
    x = uav.full_from_reduced(z[:8])
    x[8] = z[8]
    x[2] = -z[9]
    xd = uav.derivatives(prm, x, d)
    red = uav.reduced_derivatives(prm, z[:8], d)
    return np.concatenate([red, [xd[8], -xd[2]]])


# input mixing: [aileron, elevator, rudder, throttle] -> small_uav.INPUTS
_MIX = np.array(
    [
        [1.0, 0.0, 0.0, 0.0],
        [1.0, 0.0, 0.0, 0.0],
        [0.0, 1.0, 0.0, 0.0],
        [0.0, 1.0, 0.0, 0.0],
        [0.0, 0.0, 1.0, 0.0],
        [0.0, 0.0, 0.0, 1.0],
    ]
)


@lru_cache(maxsize=4)
def _autopilot(airspeed_m_s: float, limit_deg: float) -> _Autopilot:
    """LQR with integral action on airspeed, altitude, bank and heading errors."""
    prm = uav.AerosondeParams()
    trim = uav.trim_level(prm, airspeed_m_s)
    z0 = np.concatenate([trim.reduced_state, [0.0, 0.0]])
    d0 = trim.inputs
    n = 10
    a = np.empty((n, n))
    b = np.empty((n, 6))
    for j in range(n):
        h = 1e-6 * max(1.0, abs(z0[j]))
        zp, zm = z0.copy(), z0.copy()
        zp[j] += h
        zm[j] -= h
        a[:, j] = (_ap_derivatives(prm, zp, d0) - _ap_derivatives(prm, zm, d0)) / (2 * h)
    for j in range(6):
        dp, dm = d0.copy(), d0.copy()
        dp[j] += 1e-6
        dm[j] -= 1e-6
        b[:, j] = (_ap_derivatives(prm, z0, dp) - _ap_derivatives(prm, z0, dm)) / 2e-6
    b4 = b @ _MIX
    # integrators of airspeed (0), bank (6), heading (8), altitude (9) errors
    sel = (0, 6, 8, 9)
    na = n + len(sel)
    aa = np.zeros((na, na))
    aa[:n, :n] = a
    for i, s in enumerate(sel):
        aa[n + i, s] = 1.0
    ba = np.zeros((na, 4))
    ba[:n] = b4
    # Bryson-style weights: acceptable excursions of each state, integrator and input
    state_scale = np.array([1.0, 0.05, 0.05, 0.5, 0.5, 0.5, 0.1, 0.1, 0.1, 2.0])
    integ_scale = np.array([2.0, 0.2, 0.2, 4.0])
    input_scale = np.array([0.2, 0.2, 0.2, 0.2])
    qw = np.diag(1.0 / np.square(np.concatenate([state_scale, integ_scale])))
    rw = np.diag(1.0 / np.square(input_scale))
    p = solve_continuous_are(aa, ba, qw, rw)
    gain = np.linalg.solve(rw, ba.T @ p)
    return _Autopilot(gain=gain, trim=trim, limit_rad=math.radians(limit_deg))


def _rk4(prm: uav.AerosondeParams, x: FloatArray, d: FloatArray, dt: float) -> FloatArray:
    k1 = uav.derivatives(prm, x, d)
    k2 = uav.derivatives(prm, x + 0.5 * dt * k1, d)
    k3 = uav.derivatives(prm, x + 0.5 * dt * k2, d)
    k4 = uav.derivatives(prm, x + dt * k3, d)
    return x + (dt / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)


def _fault_values(faults: Sequence[SurfaceFault], t: float) -> tuple[list[float | None], int]:
    """Per-surface fault deflection (None: healthy) and the index of a faulty surface (-1)."""
    values: list[float | None] = [None] * len(uav.SURFACES)
    faulty = -1
    for f in faults:
        if f.start_s <= t < f.end_s:
            i = uav.SURFACES.index(f.surface)
            values[i] = f.deflection_rad(t)
            faulty = i
    return values, faulty


def simulate_flight(
    duration_s: float,
    *,
    sample_rate_hz: float = 100.0,
    faults: Sequence[SurfaceFault] = PAPER_FAULT_SCHEDULE,
    seed: int = 0,
    airspeed_m_s: float = 25.0,
    servo_time_constant_s: float = 0.02,
    surface_limit_deg: float = 30.0,
    noise_scale: float = 1.0,
    manoeuvres: Sequence[Manoeuvre] = (),
) -> tuple[FloatArray, dict[str, FloatArray], FlightTruth]:
    """Fly the closed loop from trim and return ``(t_s, channels, truth)``.

    Args:
        duration_s: flight length (s); samples at ``k / sample_rate_hz``, k = 0..n-1.
        sample_rate_hz: sensor, autopilot and integration rate.
        faults: fault schedule (:class:`SurfaceFault`; :data:`PAPER_FAULT_SCHEDULE` by default).
        seed: seed of the sensor noise (``numpy.random.default_rng``).
        airspeed_m_s: trim and held airspeed.
        servo_time_constant_s: first-order lag of each surface (0: none).
        surface_limit_deg: command and deflection limit.
        noise_scale: multiplies the sensor noise standard deviations (0: noise-free).
        manoeuvres: heading and altitude reference changes (:class:`Manoeuvre`; none: the
            autopilot holds the initial heading and altitude).

    Returns:
        ``t_s`` (n,); ``channels``: :data:`CHANNELS` -> (n,) float64 (measured channels in rad,
        rad/s, m/s; commands in rad, throttle 0..1); ``truth``: :class:`FlightTruth`.
    """
    faults = tuple(faults)
    n = int(round(duration_s * sample_rate_hz))
    dt = 1.0 / sample_rate_hz
    prm = uav.AerosondeParams()
    ap = _autopilot(float(airspeed_m_s), float(surface_limit_deg))
    trim = ap.trim
    x = uav.full_from_reduced(trim.reduced_state)
    x[2] = 0.0
    actual = trim.inputs.copy()
    integ = np.zeros(4)
    lag = 1.0 - math.exp(-dt / servo_time_constant_s) if servo_time_constant_s > 0 else 1.0
    t = np.arange(n, dtype=np.float64) * dt
    meas = np.empty((n, 6))
    cmds = np.empty((n, 6))
    actual_log = np.empty((n, 5))
    states = np.empty((n, 8))
    faulty = np.empty(n, dtype=np.int64)
    z_ref = np.concatenate([trim.reduced_state, [0.0, 0.0]])
    u_trim4 = np.array([0.0, trim.elevator_rad, 0.0, trim.throttle])
    lim = ap.limit_rad
    for k in range(n):
        z = _ap_state(x)
        err = z - z_ref
        for man in manoeuvres:
            d_psi, d_h = man.offsets(t[k])
            err[8] -= d_psi
            err[9] -= d_h
        cmd4 = u_trim4 - ap.gain @ np.concatenate([err, integ])
        cmd4[:3] = np.clip(cmd4[:3], -lim, lim)
        cmd4[3] = min(max(cmd4[3], 0.0), 1.0)
        cmd = _MIX @ cmd4
        fvals, faulty[k] = _fault_values(faults, t[k])
        for i in range(5):
            fv = fvals[i]
            actual[i] = fv if fv is not None else actual[i] + lag * (cmd[i] - actual[i])
        actual[5] = cmd[5]
        va, alpha, beta = uav.air_data(x)
        meas[k] = (x[9], x[10], x[11], alpha, beta, va)
        cmds[k] = cmd
        actual_log[k] = actual[:5]
        states[k] = (va, alpha, beta, x[9], x[10], x[11], x[6], x[7])
        integ += dt * err[[0, 6, 8, 9]]
        x = _rk4(prm, x, actual, dt)
    rng = np.random.default_rng(seed)
    std = noise_scale * np.sqrt(np.array(uav.SENSOR_VAR))
    meas = meas + rng.standard_normal((n, 6)) * std
    channels = {name: np.ascontiguousarray(meas[:, i]) for i, name in enumerate(MEASURED_CHANNELS)}
    for i, name in enumerate(COMMAND_CHANNELS):
        channels[name] = np.ascontiguousarray(cmds[:, i])
    truth = FlightTruth(
        states={name: np.ascontiguousarray(states[:, i]) for i, name in enumerate(uav.STATES)},
        deflections_rad={
            s: np.ascontiguousarray(actual_log[:, i]) for i, s in enumerate(uav.SURFACES)
        },
        faulty_surface=faulty,
        faults=faults,
        trim=trim,
    )
    return t, channels, truth
