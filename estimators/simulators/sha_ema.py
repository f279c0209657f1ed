"""SHA/EMA dissimilar redundant actuation system: a servo-hydraulic actuator (SHA) and an
electro-mechanical actuator (EMA) driving one control surface by force summing. Reference plant
with ground truth for the ``darr_fekf`` estimator (seed paper 003, eqs. 1-13, Table 3).

Plant (seed eqs. 1-13), twelve states
``[x_v, dx_v/dt, P_L, v_p, F_H, i_m, w, F_c, v, F_E, v_1, x_1]``, inputs ``i_v`` (valve current)
and ``U_a`` (motor voltage):

    x_v'' = w_v^2 (K_v i_v - x_v) - 2 eps_v w_v x_v'                     (1) valve
    C_hj P_L' = K_q x_v - K_c P_L - A_h v_p - P_L / R_il                (2), (5) cylinder
    m_h v_p' = A_h P_L - B_h v_p - F_H + d_piston                        (6) piston
    F_H' = K_2 (v_p - v_1)                                               (12) piston rod
    L_w i_m' = U_a - R_w i_m - K_m w + d_volt                            (7) motor circuit
    J_m w' = K_m i_m - f_m w + S_e - T_m + d_torque,  T_m = (P / 2 pi) F_c   (8), (10)
    F_c' = K_s ((P / 2 pi) w - v)                                        (9) screw stiffness
    m v' = F_c - f_r v - F_E + d_screw                                   (11) screw mass
    F_E' = K_1 (v - v_1)                                                 (12) screw attachment
    m_r v_1' = F_E + F_H + F_1 - B_d v_1 - K_d x_1 + d_surface           (13) surface
    x_1' = v_1

The ``d_*`` terms are the process noise: zero-mean Gaussian disturbances of variance
``process_noise_var`` (seed: 5e-5) in V, N m and N, held over each sample. The seed gives no
valve dynamics: ``omega_v`` and ``eps_v`` are plausible values (100 Hz, 0.7).

Inputs (the seed does not give its profiles): an open-loop command with feedforward from the
nominal model, so that both actuators follow one position profile ``x_c(t) = sum a_i sin(2 pi
f_i t)`` and each also gets an independent excitation:

    i_v = A_h,nom x_c' / (K_q K_v) + i_e sin(2 pi f_i t) + i_d sin(2 pi f_d t)
    U_a = clip(K_m (2 pi / P) x_c' + U_0 + U_e sin(2 pi f_u t), -U, U)

Measured channels (units): ``w`` rad/s, ``f_c`` N, ``v`` m/s, ``f_e`` N, ``f_h`` N, ``v_p`` m/s,
``p_l`` Pa, and the two inputs ``x_v`` m and ``u_a`` V. The seed's measurement noise variance
(5e-2) is taken in each sensor's reading unit: rad/s, N, mm/s (velocities) and bar (pressure), so
the default noise standard deviations are sqrt(5e-2) rad/s, N, 1e-3 m/s and 1e5 Pa times that.
The inputs are known exactly by default (noise 0).

Integration: classical Runge-Kutta (order 4) with ``substeps`` steps per sample, parameters held
over each sample, inputs evaluated at each substep's midpoint, starting from rest ``settle_s``
before the first sample (the start transient is not returned).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, fields, replace
from typing import Literal

import numpy as np
from numba import njit
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]

CHANNELS: tuple[str, ...] = ("w", "f_c", "v", "f_e", "f_h", "v_p", "p_l", "x_v", "u_a")
CHANNEL_UNITS: dict[str, str] = {
    "w": "rad/s",
    "f_c": "N",
    "v": "m/s",
    "f_e": "N",
    "f_h": "N",
    "v_p": "m/s",
    "p_l": "Pa",
    "x_v": "m",
    "u_a": "V",
}
STATE_NAMES: tuple[str, ...] = (
    "x_v",
    "dx_v",
    "p_l",
    "v_p",
    "f_h",
    "i_m",
    "w",
    "f_c",
    "v",
    "f_e",
    "v_1",
    "x_1",
)
_NOISE_UNIT_STD = math.sqrt(5.0e-2)
DEFAULT_NOISE_STD: dict[str, float] = {
    "w": _NOISE_UNIT_STD,
    "f_c": _NOISE_UNIT_STD,
    "v": _NOISE_UNIT_STD * 1.0e-3,
    "f_e": _NOISE_UNIT_STD,
    "f_h": _NOISE_UNIT_STD,
    "v_p": _NOISE_UNIT_STD * 1.0e-3,
    "p_l": _NOISE_UNIT_STD * 1.0e5,
    "x_v": 0.0,
    "u_a": 0.0,
}


@dataclass(frozen=True)
class ShaEmaParams:
    """Plant parameters, SI units (seed Table 3 unless noted).

    Attributes:
        k_q: valve flow gain K_q (m^2/s).
        k_c: flow-pressure coefficient K_c (m^3/(s Pa)).
        k_v: valve current gain K_v (m/A).
        omega_v: valve natural frequency (rad/s; not in the seed).
        eps_v: valve damping ratio (not in the seed).
        c_hj: hydraulic capacitance of the cylinder C_hj (m^3/Pa).
        r_il: internal leakage resistance R_il (Pa s/m^3).
        a_h: piston effective area A_h (m^2).
        b_h: piston viscous damping B_h (N s/m).
        m_h: piston equivalent mass m_h (kg).
        k_2: surface-to-piston rod stiffness K_2 (N/m).
        m_r: surface equivalent mass m_r (kg).
        b_d: surface viscous damping B_d (N s/m).
        f_m: motor bearing friction f_m (N m s/rad).
        f_r: ball-screw viscous friction f_r (N s/m).
        r_w: motor resistance R_w (ohm).
        k_m: motor torque constant K_m (N m/A).
        j_m: motor and screw inertia J_m (kg m^2).
        s_e: motor starting friction torque S_e (N m).
        lead: ball-screw lead P (m).
        k_s: ball-screw stiffness K_s (N/m).
        k_1: surface-to-screw stiffness K_1 (N/m).
        m_screw: ball-screw mass m (kg).
        l_w: motor inductance L_w (H).
        f_1: surface load force F_1 (N).
        k_d: surface load stiffness K_d (N/m).
    """

    k_q: float = 2.7
    k_c: float = 1.75e-11
    k_v: float = 1.52e-4
    omega_v: float = 2.0 * math.pi * 100.0
    eps_v: float = 0.7
    c_hj: float = 4.59e-14
    r_il: float = 5.0e11
    a_h: float = 1.47e-3
    b_h: float = 1.0e4
    m_h: float = 55.0
    k_2: float = 1.0e8
    m_r: float = 600.0
    b_d: float = 2300.0
    f_m: float = -4.0e-4
    f_r: float = 1.0e4
    r_w: float = 1.5
    k_m: float = 0.2
    j_m: float = 0.0012
    s_e: float = -0.01
    lead: float = 0.00254
    k_s: float = 3.0e8
    k_1: float = 1.0e8
    m_screw: float = 1.0
    l_w: float = 0.0025
    f_1: float = -10000.0
    k_d: float = 4.57e5

    def as_array(self) -> FloatArray:
        """The parameters in field order, shape (len(PARAMETER_NAMES),)."""
        return np.array([getattr(self, name) for name in PARAMETER_NAMES], dtype=np.float64)


PARAMETER_NAMES: tuple[str, ...] = tuple(f.name for f in fields(ShaEmaParams))


@dataclass(frozen=True)
class Excitation:
    """Open-loop input profiles (the seed does not give its own).

    Attributes:
        position_amplitudes_m: amplitudes a_i of the common position profile.
        position_frequencies_hz: its frequencies f_i.
        valve_current_a: amplitude i_e of the independent valve-current sine (A).
        valve_frequency_hz: its frequency f_i.
        dither_current_a: amplitude i_d of the valve dither (A), a small fast sine that servo
            valves commonly carry against spool stiction.
        dither_frequency_hz: its frequency f_d.
        voltage_offset_v: constant motor voltage U_0 (V), sharing the constant load F_1.
        voltage_amplitude_v: amplitude U_e of the independent motor-voltage sine (V).
        voltage_frequency_hz: its frequency f_u.
        supply_v: motor voltage limit U (seed Table 3: 40 V).
    """

    position_amplitudes_m: tuple[float, ...] = (0.01, 0.0025)
    position_frequencies_hz: tuple[float, ...] = (0.4, 1.3)
    valve_current_a: float = 0.02
    valve_frequency_hz: float = 3.1
    dither_current_a: float = 0.02
    dither_frequency_hz: float = 17.0
    voltage_offset_v: float = 8.0
    voltage_amplitude_v: float = 5.0
    voltage_frequency_hz: float = 2.3
    supply_v: float = 40.0


@dataclass(frozen=True)
class FaultSchedule:
    """A change of one plant parameter over time.

    Profiles:
        ``"step"``: the parameter jumps to ``value`` at ``start_s``; with ``end_s`` it returns to
            its previous value at ``end_s`` (an intermittent fault), else it stays.
        ``"gradual"``: linear drift from its value at ``start_s`` to ``value`` at ``end_s``,
            held after.
        ``"values"``: piecewise constant: ``values`` holds ``(time_s, value)`` pairs with
            strictly increasing times, the first at ``start_s``; each value holds until the next
            time (the last until the end).

    Faults on one parameter apply in order of ``start_s``, each from the value left by the
    previous ones.

    Attributes:
        parameter: a field name of :class:`ShaEmaParams`, e.g. ``"a_h"``.
        start_s: stream time the fault starts.
        profile: ``"step"``, ``"gradual"`` or ``"values"``.
        value: final value (step and gradual).
        end_s: end of the ramp (gradual) or of the fault (step, optional).
        values: ``(time_s, value)`` pairs (values profile).
    """

    parameter: str
    start_s: float
    profile: Literal["step", "gradual", "values"]
    value: float | None = None
    end_s: float | None = None
    values: tuple[tuple[float, float], ...] = ()

    def __post_init__(self) -> None:
        _check_fault(self)


def _check_fault(fault: FaultSchedule) -> None:
    """Raise ValueError naming the problem with a fault schedule."""
    if fault.parameter not in PARAMETER_NAMES:
        raise ValueError(f"fault parameter {fault.parameter!r}: not a plant parameter")
    if not math.isfinite(fault.start_s):
        raise ValueError(f"fault on {fault.parameter}: start_s must be finite")
    if fault.profile in ("step", "gradual"):
        if fault.value is None or not math.isfinite(fault.value):
            raise ValueError(f"fault on {fault.parameter}: {fault.profile} needs a finite value")
        if fault.profile == "gradual" and (fault.end_s is None or not fault.end_s > fault.start_s):
            raise ValueError(f"fault on {fault.parameter}: gradual needs end_s > start_s")
        if fault.profile == "step" and fault.end_s is not None and not fault.end_s > fault.start_s:
            raise ValueError(f"fault on {fault.parameter}: step end_s must be after start_s")
    elif fault.profile == "values":
        times = [pair[0] for pair in fault.values]
        if (
            not times
            or times[0] != fault.start_s
            or any(b <= a for a, b in zip(times, times[1:], strict=False))
        ):
            raise ValueError(
                f"fault on {fault.parameter}: values need strictly increasing times, "
                "the first equal to start_s"
            )
        if not all(math.isfinite(v) for _, v in fault.values):
            raise ValueError(f"fault on {fault.parameter}: values must be finite")
    else:
        raise ValueError(f"fault on {fault.parameter}: unknown profile {fault.profile!r}")


# The seed's scenario: at 4 s a gradual drop of A_h and a stepwise drop of B_h (6000 N s/m from
# 4 to 6 s, 4000 N s/m from 6 s). The seed's Table 4 prints the final A_h as 0.0001275 m^2; read
# here as 0.001275 m^2 (a 13 % drop; a 91 % loss of area would stop the piston), reached at 7 s.
PAPER_SCENARIO: tuple[FaultSchedule, ...] = (
    FaultSchedule("a_h", 4.0, "gradual", value=1.275e-3, end_s=7.0),
    FaultSchedule("b_h", 4.0, "values", values=((4.0, 6000.0), (6.0, 4000.0))),
)


@dataclass(frozen=True)
class ShaEmaTruth:
    """Ground truth of a simulated run.

    Attributes:
        states: noise-free plant signals at the sample times, by :data:`STATE_NAMES` plus
            ``"i_v"`` (valve current) and ``"u_a"`` (applied motor voltage).
        parameters: true parameter value at each sample, for every parameter with a fault.
        nominal: the parameters without faults.
        faults: the fault schedules applied.
        excitation: the input profiles.
        noise_std: measurement noise standard deviation of each channel.
        process_noise_var: variance of the process disturbances.
    """

    states: dict[str, FloatArray]
    parameters: dict[str, FloatArray]
    nominal: ShaEmaParams
    faults: tuple[FaultSchedule, ...]
    excitation: Excitation
    noise_std: dict[str, float]
    process_noise_var: float

    def parameter(self, name: str, t_index: int | slice | NDArray[np.int64]) -> FloatArray:
        """True value of ``name`` at the given sample indices (nominal when not faulted)."""
        if name in self.parameters:
            return np.asarray(self.parameters[name][t_index], dtype=np.float64)
        n = next(iter(self.states.values())).shape[0]
        return np.full(n, getattr(self.nominal, name), dtype=np.float64)[t_index]


def parameter_trajectories(
    faults: Sequence[FaultSchedule], nominal: ShaEmaParams, t_s: FloatArray
) -> dict[str, FloatArray]:
    """Value of each faulted parameter at the times ``t_s``."""
    out: dict[str, FloatArray] = {}
    for fault in sorted(faults, key=lambda f: f.start_s):
        traj = out.get(fault.parameter)
        if traj is None:
            traj = np.full(t_s.shape, getattr(nominal, fault.parameter), dtype=np.float64)
        after = t_s >= fault.start_s
        if not np.any(after):
            out[fault.parameter] = traj
            continue
        before_value = float(traj[np.argmax(after)])
        new = traj.copy()
        if fault.profile == "step":
            assert fault.value is not None
            active = after if fault.end_s is None else after & (t_s < fault.end_s)
            new[active] = fault.value
        elif fault.profile == "gradual":
            assert fault.value is not None and fault.end_s is not None
            frac = np.clip((t_s - fault.start_s) / (fault.end_s - fault.start_s), 0.0, 1.0)
            new[after] = before_value + (fault.value - before_value) * frac[after]
        else:
            for time_s, value in fault.values:
                new[t_s >= time_s] = value
        out[fault.parameter] = new
    return out


# ----------------------------------------------------------------------------- compiled plant
@njit(cache=True, error_model="numpy")
def _derivatives(
    x: FloatArray, th: FloatArray, i_v: float, u_a: float, dist: FloatArray, out: FloatArray
) -> None:
    """Right-hand side of the twelve plant equations (parameters in PARAMETER_NAMES order)."""
    k_q, k_c, k_v, omega_v, eps_v, c_hj, r_il, a_h, b_h, m_h = th[0:10]
    k_2, m_r, b_d, f_m, f_r, r_w, k_m, j_m, s_e, lead = th[10:20]
    k_s, k_1, m_screw, l_w, f_1, k_d = th[20:26]
    x_v, dx_v, p_l, v_p, f_h, i_m, w, f_c, v, f_e, v_1, x_1 = x[0:12]
    tr = lead / (2.0 * math.pi)
    out[0] = dx_v
    out[1] = omega_v * omega_v * (k_v * i_v - x_v) - 2.0 * eps_v * omega_v * dx_v
    out[2] = (k_q * x_v - k_c * p_l - a_h * v_p - p_l / r_il) / c_hj
    out[3] = (a_h * p_l - b_h * v_p - f_h + dist[3]) / m_h
    out[4] = k_2 * (v_p - v_1)
    out[5] = (u_a - r_w * i_m - k_m * w + dist[0]) / l_w
    out[6] = (k_m * i_m - f_m * w + s_e - tr * f_c + dist[1]) / j_m
    out[7] = k_s * (tr * w - v)
    out[8] = (f_c - f_r * v - f_e + dist[2]) / m_screw
    out[9] = k_1 * (v - v_1)
    out[10] = (f_e + f_h + f_1 - b_d * v_1 - k_d * x_1 + dist[4]) / m_r
    out[11] = v_1


@njit(cache=True, error_model="numpy")
def _inputs(t: float, ex: FloatArray, n_sines: int, th_nom: FloatArray) -> tuple[float, float]:
    """Valve current and motor voltage at time ``t`` (see the module docstring).

    ``ex`` = [a_1..a_n, f_1..f_n, i_e, f_i, i_d, f_d, U_0, U_e, f_u, U].
    """
    vel = 0.0
    for i in range(n_sines):
        w = 2.0 * math.pi * ex[n_sines + i]
        vel += ex[i] * w * math.cos(w * t)
    base = 2 * n_sines
    k_q = th_nom[0]
    k_v = th_nom[2]
    a_h = th_nom[7]
    k_m = th_nom[16]
    lead = th_nom[19]
    i_v = a_h * vel / (k_q * k_v) + ex[base] * math.sin(2.0 * math.pi * ex[base + 1] * t)
    i_v += ex[base + 2] * math.sin(2.0 * math.pi * ex[base + 3] * t)
    u = k_m * (2.0 * math.pi / lead) * vel + ex[base + 4]
    u += ex[base + 5] * math.sin(2.0 * math.pi * ex[base + 6] * t)
    u_max = ex[base + 7]
    return i_v, min(max(u, -u_max), u_max)


@njit(cache=True, error_model="numpy")
def _simulate(
    th_nom: FloatArray,
    fault_index: NDArray[np.int64],
    fault_values: FloatArray,
    ex: FloatArray,
    n_sines: int,
    t_first: float,
    dt: float,
    n_settle: int,
    n: int,
    substeps: int,
    disturbances: FloatArray,
) -> FloatArray:
    """Integrate the plant; returns (n, 14): the twelve states, i_v and U_a at each sample.

    ``fault_values[j, k]`` is parameter ``fault_index[j]`` over sample k (held during
    the settle period at its value at sample 0); ``disturbances`` is (n_settle + n, 5).
    """
    out = np.empty((n, 14))
    x = np.zeros(12)
    th = th_nom.copy()
    k1 = np.empty(12)
    k2 = np.empty(12)
    k3 = np.empty(12)
    k4 = np.empty(12)
    tmp = np.empty(12)
    h = dt / substeps
    for step in range(n_settle + n):
        k = step - n_settle
        kk = max(k, 0)
        for j in range(fault_index.shape[0]):
            th[fault_index[j]] = fault_values[j, kk]
        dist = disturbances[step]
        t0 = t_first + (k - 1) * dt  # integrate from the previous sample time to this one
        i_v = 0.0
        u_a = 0.0
        for s in range(substeps):
            i_v, u_a = _inputs(t0 + (s + 0.5) * h, ex, n_sines, th_nom)
            _derivatives(x, th, i_v, u_a, dist, k1)
            for i in range(12):
                tmp[i] = x[i] + 0.5 * h * k1[i]
            _derivatives(tmp, th, i_v, u_a, dist, k2)
            for i in range(12):
                tmp[i] = x[i] + 0.5 * h * k2[i]
            _derivatives(tmp, th, i_v, u_a, dist, k3)
            for i in range(12):
                tmp[i] = x[i] + h * k3[i]
            _derivatives(tmp, th, i_v, u_a, dist, k4)
            for i in range(12):
                x[i] += h / 6.0 * (k1[i] + 2.0 * k2[i] + 2.0 * k3[i] + k4[i])
        if k >= 0:
            i_v, u_a = _inputs(t_first + k * dt, ex, n_sines, th_nom)
            for i in range(12):
                out[k, i] = x[i]
            out[k, 12] = i_v
            out[k, 13] = u_a
    return out


# ----------------------------------------------------------------------------- public API
def simulate_sha_ema(
    duration_s: float,
    *,
    faults: Sequence[FaultSchedule] = (),
    seed: int = 0,
    dt: float = 1.0e-4,
    params: ShaEmaParams | Mapping[str, float] | None = None,
    excitation: Excitation | None = None,
    noise_std: Mapping[str, float] | None = None,
    process_noise_var: float = 5.0e-5,
    substeps: int = 10,
    settle_s: float = 1.0,
    t0_s: float = 0.0,
) -> tuple[FloatArray, dict[str, FloatArray], ShaEmaTruth]:
    """Simulate the SHA/EMA system with parameter faults.

    Args:
        duration_s: length of the returned run (s).
        faults: parameter fault schedules (times are stream times, as ``t_s``).
        seed: seed of ``numpy.random.default_rng`` for process and measurement noise.
        dt: sample period (s); the seed uses 1e-4 s.
        params: nominal parameters (a :class:`ShaEmaParams` or overrides of its fields).
        excitation: input profiles (default :class:`Excitation`).
        noise_std: overrides of :data:`DEFAULT_NOISE_STD` by channel (same units as the channel).
        process_noise_var: variance of the five process disturbances (seed: 5e-5).
        substeps: Runge-Kutta steps per sample.
        settle_s: simulated time before the first sample, not returned.
        t0_s: time of the first sample.

    Returns:
        ``(t_s, channels, truth)``: sample times (n,), measured channels by :data:`CHANNELS`
        (each (n,), float64) and the :class:`ShaEmaTruth`.

    Raises:
        ValueError: a bad duration, step, parameter name, noise channel or fault schedule.
    """
    if not (duration_s > 0.0 and dt > 0.0 and substeps >= 1 and settle_s >= 0.0):
        raise ValueError("duration_s, dt and substeps must be positive, settle_s non-negative")
    if isinstance(params, ShaEmaParams):
        nominal = params
    else:
        overrides = dict(params or {})
        unknown = sorted(set(overrides) - set(PARAMETER_NAMES))
        if unknown:
            raise ValueError(f"{unknown[0]}: unknown SHA/EMA parameter")
        nominal = replace(ShaEmaParams(), **overrides)
    ex = excitation or Excitation()
    if len(ex.position_amplitudes_m) != len(ex.position_frequencies_hz):
        raise ValueError("excitation: as many position amplitudes as frequencies are needed")
    std = dict(DEFAULT_NOISE_STD)
    for name, value in (noise_std or {}).items():
        if name not in std:
            raise ValueError(f"noise_std: unknown channel {name!r}")
        std[name] = float(value)
    for fault in faults:
        _check_fault(fault)

    n = int(round(duration_s / dt))
    n_settle = int(round(settle_s / dt))
    t_s = t0_s + np.arange(n, dtype=np.float64) * dt
    trajectories = parameter_trajectories(faults, nominal, t_s)
    names = sorted(trajectories)
    fault_index = np.array([PARAMETER_NAMES.index(p) for p in names], dtype=np.int64)
    fault_values = (
        np.vstack([trajectories[p] for p in names]) if names else np.zeros((0, n), np.float64)
    )
    ex_vec = np.array(
        [
            *ex.position_amplitudes_m,
            *ex.position_frequencies_hz,
            ex.valve_current_a,
            ex.valve_frequency_hz,
            ex.dither_current_a,
            ex.dither_frequency_hz,
            ex.voltage_offset_v,
            ex.voltage_amplitude_v,
            ex.voltage_frequency_hz,
            ex.supply_v,
        ],
        dtype=np.float64,
    )
    rng = np.random.default_rng(seed)
    disturbances = rng.normal(0.0, math.sqrt(process_noise_var), size=(n_settle + n, 5))
    raw = _simulate(
        nominal.as_array(),
        fault_index,
        np.ascontiguousarray(fault_values),
        ex_vec,
        len(ex.position_amplitudes_m),
        t0_s,
        dt,
        n_settle,
        n,
        substeps,
        disturbances,
    )
    states = {name: np.ascontiguousarray(raw[:, i]) for i, name in enumerate(STATE_NAMES)}
    states["i_v"] = np.ascontiguousarray(raw[:, 12])
    states["u_a"] = np.ascontiguousarray(raw[:, 13])
    channels: dict[str, FloatArray] = {}
    for name in CHANNELS:
        clean = states[name]
        noise = rng.standard_normal(n) * std[name] if std[name] > 0.0 else 0.0
        channels[name] = np.ascontiguousarray(clean + noise, dtype=np.float64)
    truth = ShaEmaTruth(
        states=states,
        parameters=trajectories,
        nominal=nominal,
        faults=tuple(faults),
        excitation=ex,
        noise_std=std,
        process_noise_var=float(process_noise_var),
    )
    return t_s, channels, truth
