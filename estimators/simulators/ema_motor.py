"""DC-motor electro-mechanical actuator (EMA) with a ball screw, a position controller and EMI on
the measured motor voltage: a reference plant with known true voltage for the FAKF.

Plant (seed eqs. 13-14), state ``[i, w, theta]``, input ``[v, T_ex]``:

    v = Ke w + R i + L di/dt                                                          (13)
    Kt i - T_ex = B w + J dw/dt                                                       (14)
    x = (lead / 2 pi) theta,   T_ex = F_load lead / (2 pi eta)

discretized exactly (zero-order hold) at the control rate; a cascaded position (P) / speed (PI)
controller with voltage saturation follows a sine or trapezoid position profile. The measured
voltage is the true armature voltage plus electromagnetic interference: Gaussian noise, random
impulsive spikes (Poisson arrivals, random sign and size) and a periodic interference tone.

Default parameters are plausible for the small ball-screw actuators of NASA's FLEA stand (a
brushed DC motor of a few tens of mN m/A on a 28 V bus, 2 mm lead screw, +-40 lbs load):
they give currents of about 2 A std (peaks near 10 A) and voltages of about +-20 V, the same order as the FLEA
low-rate runs (currents of 1-3 A std, voltages saturating near +-25 V). They are not identified
from FLEA data.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray
from scipy.linalg import expm

from estimators.kernels.ema_kernels import ema_closed_loop

FloatArray = NDArray[np.float64]
NEWTON_PER_LBF = 4.4482216152605


@dataclass(frozen=True)
class EmaParams:
    """Plant, controller, profile and interference parameters.

    Attributes:
        resistance_ohm: armature resistance R.
        inductance_h: armature inductance L.
        ke_v_s_rad: back-emf constant Ke.
        kt_nm_a: torque constant Kt.
        inertia_kg_m2: net inertia J (motor, screw and reflected load).
        damping_nm_s_rad: net viscous friction B.
        lead_m: ball-screw lead (travel per motor revolution).
        screw_efficiency: ball-screw efficiency eta.
        supply_v: bus voltage (controller saturation).
        profile: "sine", "trapezoid" or "sweep" (a sine whose frequency rises linearly from
            ``frequency_hz`` at the start to ``sweep_end_frequency_hz`` at the end of the run)
            position profile.
        amplitude_m: profile amplitude.
        frequency_hz: profile frequency (start frequency of a sweep).
        sweep_end_frequency_hz: end frequency of a sweep.
        kp_pos_1_s: position loop gain (1/s).
        kp_vel_v_s_rad: speed loop proportional gain.
        ki_vel_v_rad: speed loop integral gain.
        control_rate_hz: controller and plant discretization rate (rounded to a multiple of
            the sample rate).
        current_noise_a: std of the current sensor noise.
        voltage_noise_v: std of the Gaussian part of the voltage interference.
        spike_rate_hz: mean rate of impulsive spikes on the voltage.
        spike_amplitude_v: spikes are uniform in [0.5, 1.5] x this, random sign.
        periodic_amplitude_v: amplitude of the periodic interference.
        periodic_frequency_hz: its frequency.
        voltage_clip_low_v: the voltage sensor's lower limit: measured values below it read as
            it (None: no limit). The FLEA voltage channel clips near -25.3 V.
        voltage_clip_high_v: the upper limit (None: none); FLEA: near +23.9 V.
    """

    resistance_ohm: float = 2.0
    inductance_h: float = 1.0e-3
    ke_v_s_rad: float = 0.03
    kt_nm_a: float = 0.03
    inertia_kg_m2: float = 3.0e-5
    damping_nm_s_rad: float = 2.0e-5
    lead_m: float = 0.002
    screw_efficiency: float = 0.9
    supply_v: float = 28.0
    profile: Literal["sine", "trapezoid", "sweep"] = "sine"
    amplitude_m: float = 0.025
    frequency_hz: float = 1.0
    sweep_end_frequency_hz: float = 4.0
    kp_pos_1_s: float = 40.0
    kp_vel_v_s_rad: float = 0.05
    ki_vel_v_rad: float = 2.0
    control_rate_hz: float = 10_000.0
    current_noise_a: float = 0.02
    voltage_noise_v: float = 1.0
    spike_rate_hz: float = 5.0
    spike_amplitude_v: float = 8.0
    periodic_amplitude_v: float = 2.0
    periodic_frequency_hz: float = 60.0
    voltage_clip_low_v: float | None = None
    voltage_clip_high_v: float | None = None


@dataclass(frozen=True)
class EmaRun:
    """A simulated run, sampled at ``sample_rate_hz``.

    Attributes:
        t_s: sample times, shape (n,).
        current_a: measured current (true current plus sensor noise), shape (n,).
        current_true_a: true armature current, shape (n,).
        voltage_true_v: true armature voltage, shape (n,).
        voltage_measured_v: measured voltage (true plus interference), shape (n,).
        speed_rad_s: motor speed, shape (n,).
        position_m: actuator position, shape (n,).
        position_ref_m: commanded position, shape (n,).
        load_lbs: external load force, shape (n,).
        sample_rate_hz: sampling rate.
        params: parameters used.
        seed: random seed used.
    """

    t_s: FloatArray
    current_a: FloatArray
    current_true_a: FloatArray
    voltage_true_v: FloatArray
    voltage_measured_v: FloatArray
    speed_rad_s: FloatArray
    position_m: FloatArray
    position_ref_m: FloatArray
    load_lbs: FloatArray
    sample_rate_hz: float
    params: EmaParams
    seed: int


def _profile(t: FloatArray, p: EmaParams, duration_s: float) -> tuple[FloatArray, FloatArray]:
    """Position and velocity references at times ``t``."""
    w = 2.0 * math.pi * p.frequency_hz
    if p.profile == "sine":
        return p.amplitude_m * np.sin(w * t), p.amplitude_m * w * np.cos(w * t)
    if p.profile == "sweep":
        # linear chirp: instantaneous frequency f0 + (f1 - f0) t / T
        rate = (p.sweep_end_frequency_hz - p.frequency_hz) / duration_s
        phase = 2.0 * math.pi * (p.frequency_hz * t + 0.5 * rate * t * t)
        w_inst = 2.0 * math.pi * (p.frequency_hz + rate * t)
        return p.amplitude_m * np.sin(phase), p.amplitude_m * w_inst * np.cos(phase)
    if p.profile == "trapezoid":
        # Triangle wave clipped at 60 % of its peak: ramps with flat dwells.
        phase = (t * p.frequency_hz) % 1.0
        tri = np.where(phase < 0.5, 4.0 * phase - 1.0, 3.0 - 4.0 * phase)
        dtri = np.where(phase < 0.5, 4.0, -4.0) * p.frequency_hz
        clip = 0.6
        pos = p.amplitude_m * np.clip(tri, -clip, clip) / clip
        vel = np.where(np.abs(tri) < clip, p.amplitude_m * dtri / clip, 0.0)
        return pos, vel
    raise ValueError(f"profile: expected 'sine', 'trapezoid' or 'sweep', got {p.profile!r}")


def _discretize(p: EmaParams, dt: float) -> tuple[FloatArray, FloatArray]:
    """Exact ZOH discretization of eqs. 13-14 with state [i, w, theta], input [v, T_ex]."""
    a = np.array(
        [
            [-p.resistance_ohm / p.inductance_h, -p.ke_v_s_rad / p.inductance_h, 0.0],
            [p.kt_nm_a / p.inertia_kg_m2, -p.damping_nm_s_rad / p.inertia_kg_m2, 0.0],
            [0.0, 1.0, 0.0],
        ]
    )
    b = np.array([[1.0 / p.inductance_h, 0.0], [0.0, -1.0 / p.inertia_kg_m2], [0.0, 0.0]])
    m = np.zeros((5, 5))
    m[:3, :3] = a * dt
    m[:3, 3:] = b * dt
    e = expm(m)
    return np.ascontiguousarray(e[:3, :3]), np.ascontiguousarray(e[:3, 3:])


def simulate_ema(
    duration_s: float = 30.0,
    sample_rate_hz: float = 1000.0,
    load_lbs: float = 40.0,
    seed: int = 0,
    **params: Any,
) -> EmaRun:
    """Simulate a run of the actuator under a constant external load.

    Args:
        duration_s: run length.
        sample_rate_hz: sampling rate of the returned signals (the FLEA low-rate channel of the
            seed paper is 1 kHz; the FLEA files kept here are 100 Hz).
        load_lbs: external axial load (lbs, sign kept: the torque it gives opposes positive
            motor torque when positive).
        seed: seed of ``numpy.random.default_rng`` for sensor noise and interference.
        **params: any field of :class:`EmaParams`.

    Raises:
        ValueError: an unknown parameter or a non-positive duration / rate.
    """
    known = {f.name for f in fields(EmaParams)}
    unknown = sorted(set(params) - known)
    if unknown:
        raise ValueError(f"{unknown[0]}: unknown EMA parameter")
    if not (duration_s > 0.0 and sample_rate_hz > 0.0):
        raise ValueError("duration_s and sample_rate_hz must be positive")
    p = replace(EmaParams(), **params)
    steps_per_sample = max(1, round(p.control_rate_hz / sample_rate_hz))
    dt_ctrl = 1.0 / (sample_rate_hz * steps_per_sample)
    n = int(round(duration_s * sample_rate_hz))
    n_ctrl = n * steps_per_sample
    t_ctrl = np.arange(n_ctrl, dtype=np.float64) * dt_ctrl
    pos_ref, vel_ref = _profile(t_ctrl, p, n / sample_rate_hz)
    force_n = load_lbs * NEWTON_PER_LBF
    load_torque = np.full(
        n_ctrl, force_n * p.lead_m / (2.0 * math.pi * p.screw_efficiency), dtype=np.float64
    )
    ad, bd = _discretize(p, dt_ctrl)
    meters_per_rad = p.lead_m / (2.0 * math.pi)
    volt, cur, speed, pos = ema_closed_loop(
        ad,
        bd,
        pos_ref,
        vel_ref,
        load_torque,
        meters_per_rad,
        p.kp_pos_1_s,
        p.kp_vel_v_s_rad,
        p.ki_vel_v_rad,
        p.supply_v,
        dt_ctrl,
    )
    idx = np.arange(n) * steps_per_sample
    t = t_ctrl[idx]
    v_true = volt[idx]
    i_true = cur[idx]

    rng = np.random.default_rng(seed)
    i_meas = i_true + p.current_noise_a * rng.standard_normal(n)
    gaussian = p.voltage_noise_v * rng.standard_normal(n)
    spike_prob = min(1.0, p.spike_rate_hz / sample_rate_hz)
    spikes = (rng.random(n) < spike_prob) * (
        rng.choice(np.array([-1.0, 1.0]), size=n)
        * p.spike_amplitude_v
        * rng.uniform(0.5, 1.5, size=n)
    )
    phase = rng.uniform(0.0, 2.0 * math.pi)
    periodic = p.periodic_amplitude_v * np.sin(2.0 * math.pi * p.periodic_frequency_hz * t + phase)
    v_meas = v_true + gaussian + spikes + periodic
    if p.voltage_clip_low_v is not None:
        v_meas = np.maximum(v_meas, p.voltage_clip_low_v)
    if p.voltage_clip_high_v is not None:
        v_meas = np.minimum(v_meas, p.voltage_clip_high_v)
    return EmaRun(
        t_s=t,
        current_a=i_meas,
        current_true_a=np.ascontiguousarray(i_true),
        voltage_true_v=np.ascontiguousarray(v_true),
        voltage_measured_v=v_meas,
        speed_rad_s=np.ascontiguousarray(speed[idx]),
        position_m=np.ascontiguousarray(pos[idx]),
        position_ref_m=np.ascontiguousarray(pos_ref[idx]),
        load_lbs=np.full(n, float(load_lbs)),
        sample_rate_hz=float(sample_rate_hz),
        params=p,
        seed=seed,
    )
