"""Reference small-UAV model: the Aerosonde airframe with five independent control surfaces.

Source of the airframe data: R. W. Beard and T. W. McLain, *Small Unmanned Aircraft: Theory and
Practice*, Princeton University Press, 2012, Appendix E (Aerosonde UAV: mass, inertia, geometry,
aerodynamic and propulsion coefficients), with the equations of motion of its chapters 3-4
(rigid body, forces and moments in the stability/body frames, propeller thrust
``0.5 rho S_prop C_prop ((k_motor delta_t)^2 - Va^2)``; propeller torque omitted as k_Tp = 0).

Changes made here (see ``docs/methods-stmmae.md``):

* linear lift ``C_L = C_L0 + C_La alpha`` (no stall blending: the model is used near trim) and
  the quadratic drag polar ``C_D = C_Dp + C_L^2 / (pi e AR)``;
* the aileron and the elevator are each split into independent left and right halves carrying
  half of the published control derivative each. Left/right halves would then be
  indistinguishable, so each half also gets the effects its offset from the plane of symmetry
  implies: an aileron half changes the wing lift (``C_L = C_l_half / eta_a``, the roll moment
  divided by its span arm fraction ``eta_a``) and, that lift acting ``x_a`` aft of the centre of
  gravity, the pitching moment; an elevator half's tail lift (from ``C_m_de / 2`` and the tail
  arm) acting ``eta_e b`` off the plane of symmetry gives a roll moment. The three geometric
  fractions are assumptions, not published Aerosonde data.

Sign conventions: an aileron half is positive in the sense of a positive roll moment (left half
trailing edge down, right half trailing edge up), an elevator half as the published elevator,
the rudder as published. Angles in rad, rates in rad/s, airspeed in m/s.

The estimator's model is the linearization of these equations at a straight and level trim,
reduced to the eight states that close on themselves (position and heading do not enter the
dynamics at constant air density), discretized exactly (zero-order hold).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.linalg import expm

FloatArray = NDArray[np.float64]
GRAVITY_M_S2 = 9.81

SURFACES = ("aileron_left", "aileron_right", "elevator_left", "elevator_right", "rudder")
INPUTS = (*SURFACES, "throttle")
STATES = ("airspeed", "alpha", "beta", "p", "q", "r", "phi", "theta")
MEASUREMENTS = ("p", "q", "r", "alpha", "beta", "airspeed")
# full rigid-body state order of :func:`derivatives`
FULL_STATES = ("pn", "pe", "pd", "u", "v", "w", "phi", "theta", "psi", "p", "q", "r")


@dataclass(frozen=True)
class AerosondeParams:
    """Aerosonde airframe (Beard & McLain 2012, Appendix E) plus the split-surface geometry.

    The last three attributes are the assumed geometry of the split surfaces (fractions, not
    published data): ``aileron_span_arm`` is the aileron lift centroid's distance from the plane
    of symmetry over the span, ``aileron_chord_arm`` its distance aft of the centre of gravity
    over the mean chord, ``elevator_span_arm`` an elevator half's lift centroid's distance from
    the plane of symmetry over the span; ``tail_arm_m`` is the tail lift's distance aft of the
    centre of gravity.
    """

    mass_kg: float = 13.5
    jx: float = 0.8244
    jy: float = 1.135
    jz: float = 1.759
    jxz: float = 0.1204
    s_wing: float = 0.55
    b: float = 2.8956
    c: float = 0.18994
    s_prop: float = 0.2027
    rho: float = 1.2682
    k_motor: float = 80.0
    e_oswald: float = 0.9
    c_prop: float = 1.0
    c_l0: float = 0.28
    c_l_alpha: float = 3.45
    c_l_q: float = 0.0
    c_l_de: float = -0.36
    c_d_p: float = 0.0437
    c_d_q: float = 0.0
    c_d_de: float = 0.0
    c_m0: float = -0.02338
    c_m_alpha: float = -0.38
    c_m_q: float = -3.6
    c_m_de: float = -0.5
    c_y0: float = 0.0
    c_y_beta: float = -0.98
    c_y_p: float = 0.0
    c_y_r: float = 0.0
    c_y_da: float = 0.0
    c_y_dr: float = -0.17
    c_ell0: float = 0.0
    c_ell_beta: float = -0.12
    c_ell_p: float = -0.26
    c_ell_r: float = 0.14
    c_ell_da: float = 0.08
    c_ell_dr: float = 0.105
    c_n0: float = 0.0
    c_n_beta: float = 0.25
    c_n_p: float = 0.022
    c_n_r: float = -0.35
    c_n_da: float = 0.06
    c_n_dr: float = -0.032
    aileron_span_arm: float = 0.4
    aileron_chord_arm: float = 0.25
    elevator_span_arm: float = 0.06
    tail_arm_m: float = 0.9


@dataclass(frozen=True)
class Trim:
    """Straight and level trim.

    Attributes:
        airspeed_m_s: trim airspeed.
        alpha_rad: angle of attack (= pitch angle, level flight).
        elevator_rad: deflection of both elevator halves.
        throttle: throttle setting (0..1).
    """

    airspeed_m_s: float
    alpha_rad: float
    elevator_rad: float
    throttle: float

    @property
    def inputs(self) -> FloatArray:
        """Trim inputs in :data:`INPUTS` order, shape (6,)."""
        e = self.elevator_rad
        return np.array([0.0, 0.0, e, e, 0.0, self.throttle])

    @property
    def reduced_state(self) -> FloatArray:
        """Trim in :data:`STATES` order, shape (8,)."""
        a = self.alpha_rad
        return np.array([self.airspeed_m_s, a, 0.0, 0.0, 0.0, 0.0, 0.0, a])


def _coefficients(
    prm: AerosondeParams, alpha: float, delta: FloatArray
) -> tuple[float, float, float, float]:
    """Lift and drag coefficients (without rate terms) and the split-surface roll and pitch
    increments ``(c_lift, c_drag, d_c_ell, d_c_m)`` for deflections ``delta`` (INPUTS order)."""
    a_l, a_r, e_l, e_r = delta[0], delta[1], delta[2], delta[3]
    ar = prm.b * prm.b / prm.s_wing
    c_lift_alpha = prm.c_l0 + prm.c_l_alpha * alpha
    c_drag = prm.c_d_p + c_lift_alpha * c_lift_alpha / (math.pi * prm.e_oswald * ar)
    # aileron halves: wing lift of opposite signs, acting aft of the centre of gravity
    k_lift_a = 0.5 * prm.c_ell_da / prm.aileron_span_arm
    d_lift_a = k_lift_a * (a_l - a_r)
    # elevator halves: tail lift from the pitching moment and the tail arm, off the symmetry plane
    tail_lift_per_rad = -0.5 * prm.c_m_de * prm.c / prm.tail_arm_m
    d_ell_e = tail_lift_per_rad * prm.elevator_span_arm * (e_l - e_r)
    d_m_a = -d_lift_a * prm.aileron_chord_arm
    c_lift = c_lift_alpha + d_lift_a + 0.5 * prm.c_l_de * (e_l + e_r)
    return c_lift, c_drag, d_ell_e, d_m_a


def forces_moments(prm: AerosondeParams, x: FloatArray, delta: FloatArray) -> FloatArray:
    """Body-frame forces (N) and moments (N m) ``[fx, fy, fz, l, m, n]``.

    Args:
        prm: airframe.
        x: full state in :data:`FULL_STATES` order, shape (12,).
        delta: inputs in :data:`INPUTS` order (rad, throttle 0..1), shape (6,).
    """
    u, v, w = x[3], x[4], x[5]
    phi, theta = x[6], x[7]
    p, q, r = x[9], x[10], x[11]
    va = math.sqrt(u * u + v * v + w * w)
    alpha = math.atan2(w, u)
    beta = math.asin(v / va)
    c_lift, c_drag, d_ell_e, d_m_a = _coefficients(prm, alpha, delta)
    d_a = 0.5 * (delta[0] + delta[1])
    d_e = 0.5 * (delta[2] + delta[3])
    d_r = delta[4]
    qbar_s = 0.5 * prm.rho * va * va * prm.s_wing
    ca, sa = math.cos(alpha), math.sin(alpha)
    cq = prm.c * q / (2.0 * va)
    bp = prm.b * p / (2.0 * va)
    br = prm.b * r / (2.0 * va)
    c_x = -c_drag * ca + c_lift * sa + (-prm.c_d_q * ca + prm.c_l_q * sa) * cq
    c_x += -prm.c_d_de * ca * d_e
    c_z = -c_drag * sa - c_lift * ca + (-prm.c_d_q * sa - prm.c_l_q * ca) * cq
    c_z += -prm.c_d_de * sa * d_e
    mg = prm.mass_kg * GRAVITY_M_S2
    thrust = 0.5 * prm.rho * prm.s_prop * prm.c_prop * ((prm.k_motor * delta[5]) ** 2 - va * va)
    fx = -mg * math.sin(theta) + qbar_s * c_x + thrust
    c_y = prm.c_y0 + prm.c_y_beta * beta + prm.c_y_p * bp + prm.c_y_r * br
    c_y += prm.c_y_da * d_a + prm.c_y_dr * d_r
    fy = mg * math.cos(theta) * math.sin(phi) + qbar_s * c_y
    fz = mg * math.cos(theta) * math.cos(phi) + qbar_s * c_z
    c_ell = prm.c_ell0 + prm.c_ell_beta * beta + prm.c_ell_p * bp + prm.c_ell_r * br
    c_ell += prm.c_ell_da * d_a + prm.c_ell_dr * d_r + d_ell_e
    c_m = prm.c_m0 + prm.c_m_alpha * alpha + prm.c_m_q * cq + prm.c_m_de * d_e + d_m_a
    c_n = prm.c_n0 + prm.c_n_beta * beta + prm.c_n_p * bp + prm.c_n_r * br
    c_n += prm.c_n_da * d_a + prm.c_n_dr * d_r
    return np.array(
        [fx, fy, fz, qbar_s * prm.b * c_ell, qbar_s * prm.c * c_m, qbar_s * prm.b * c_n]
    )


def derivatives(prm: AerosondeParams, x: FloatArray, delta: FloatArray) -> FloatArray:
    """Time derivative of the full state (Beard & McLain eqs. 3.14-3.17), shape (12,).

    Position is north-east-down; ``psi`` enters only the position rates.
    """
    fm = forces_moments(prm, x, delta)
    u, v, w = x[3], x[4], x[5]
    phi, theta, psi = x[6], x[7], x[8]
    p, q, r = x[9], x[10], x[11]
    cph, sph = math.cos(phi), math.sin(phi)
    cth, sth, tth = math.cos(theta), math.sin(theta), math.tan(theta)
    cps, sps = math.cos(psi), math.sin(psi)
    m = prm.mass_kg
    pn_dot = cth * cps * u + (sph * sth * cps - cph * sps) * v + (cph * sth * cps + sph * sps) * w
    pe_dot = cth * sps * u + (sph * sth * sps + cph * cps) * v + (cph * sth * sps - sph * cps) * w
    pd_dot = -sth * u + sph * cth * v + cph * cth * w
    u_dot = r * v - q * w + fm[0] / m
    v_dot = p * w - r * u + fm[1] / m
    w_dot = q * u - p * v + fm[2] / m
    phi_dot = p + (q * sph + r * cph) * tth
    theta_dot = q * cph - r * sph
    psi_dot = (q * sph + r * cph) / cth
    jx, jy, jz, jxz = prm.jx, prm.jy, prm.jz, prm.jxz
    gam = jx * jz - jxz * jxz
    ell, mm, nn = fm[3], fm[4], fm[5]
    p_dot = (jxz * (jx - jy + jz) * p * q - (jz * (jz - jy) + jxz * jxz) * q * r) / gam
    p_dot += (jz * ell + jxz * nn) / gam
    q_dot = ((jz - jx) * p * r - jxz * (p * p - r * r) + mm) / jy
    r_dot = (((jx - jy) * jx + jxz * jxz) * p * q - jxz * (jx - jy + jz) * q * r) / gam
    r_dot += (jxz * ell + jx * nn) / gam
    return np.array(
        [pn_dot, pe_dot, pd_dot, u_dot, v_dot, w_dot, phi_dot, theta_dot, psi_dot]
        + [p_dot, q_dot, r_dot]
    )


def full_from_reduced(z: FloatArray) -> FloatArray:
    """Full state (position 0, heading 0) from a reduced state in :data:`STATES` order."""
    va, alpha, beta, p, q, r, phi, theta = z
    u = va * math.cos(alpha) * math.cos(beta)
    v = va * math.sin(beta)
    w = va * math.sin(alpha) * math.cos(beta)
    return np.array([0.0, 0.0, 0.0, u, v, w, phi, theta, 0.0, p, q, r])


def air_data(x: FloatArray) -> tuple[float, float, float]:
    """``(airspeed, alpha, beta)`` of a full state (no wind)."""
    u, v, w = x[3], x[4], x[5]
    va = math.sqrt(u * u + v * v + w * w)
    return va, math.atan2(w, u), math.asin(v / va)


def reduced_derivatives(prm: AerosondeParams, z: FloatArray, delta: FloatArray) -> FloatArray:
    """Time derivative of the reduced state :data:`STATES`, shape (8,)."""
    x = full_from_reduced(z)
    xd = derivatives(prm, x, delta)
    u, v, w = x[3], x[4], x[5]
    ud, vd, wd = xd[3], xd[4], xd[5]
    va = z[0]
    va_dot = (u * ud + v * vd + w * wd) / va
    alpha_dot = (u * wd - w * ud) / (u * u + w * w)
    beta_dot = (va * vd - v * va_dot) / (va * va * math.cos(z[2]))
    return np.array([va_dot, alpha_dot, beta_dot, xd[9], xd[10], xd[11], xd[6], xd[7]])


def trim_level(prm: AerosondeParams, airspeed_m_s: float = 25.0) -> Trim:
    """Straight and level trim by Newton iterations on ``u_dot = w_dot = q_dot = 0``."""
    unknowns = np.array([0.05, -0.05, 0.5])  # alpha, elevator, throttle

    def residual(s: FloatArray) -> FloatArray:
        alpha, elev, thr = s
        z = np.array([airspeed_m_s, alpha, 0.0, 0.0, 0.0, 0.0, 0.0, alpha])
        d = np.array([0.0, 0.0, elev, elev, 0.0, thr])
        zd = reduced_derivatives(prm, z, d)
        return np.array([zd[0], zd[1], zd[4]])

    for _ in range(50):
        f0 = residual(unknowns)
        jac = np.empty((3, 3))
        for j in range(3):
            h = 1e-7
            s = unknowns.copy()
            s[j] += h
            jac[:, j] = (residual(s) - f0) / h
        step = np.linalg.solve(jac, f0)
        unknowns = unknowns - step
        if float(np.max(np.abs(step))) < 1e-13:
            break
    alpha, elev, thr = (float(v) for v in unknowns)
    return Trim(airspeed_m_s=airspeed_m_s, alpha_rad=alpha, elevator_rad=elev, throttle=thr)


def linearize(prm: AerosondeParams, trim: Trim) -> tuple[FloatArray, FloatArray]:
    """Continuous-time Jacobians ``(A, B)`` of :func:`reduced_derivatives` at ``trim`` (central
    differences), shapes (8, 8) and (8, 6)."""
    z0 = trim.reduced_state
    d0 = trim.inputs
    a = np.empty((8, 8))
    b = np.empty((8, 6))
    for j in range(8):
        h = 1e-6 * max(1.0, abs(z0[j]))
        zp, zm = z0.copy(), z0.copy()
        zp[j] += h
        zm[j] -= h
        a[:, j] = (reduced_derivatives(prm, zp, d0) - reduced_derivatives(prm, zm, d0)) / (2 * h)
    for j in range(6):
        h = 1e-6
        dp, dm = d0.copy(), d0.copy()
        dp[j] += h
        dm[j] -= h
        b[:, j] = (reduced_derivatives(prm, z0, dp) - reduced_derivatives(prm, z0, dm)) / (2 * h)
    return a, b


def discretize(a: FloatArray, b: FloatArray, dt_s: float) -> tuple[FloatArray, FloatArray]:
    """Zero-order-hold discretization ``(F, G)`` by the matrix exponential of ``[[A, B], [0, 0]]``."""
    n, m = b.shape
    blk = np.zeros((n + m, n + m))
    blk[:n, :n] = a
    blk[:n, n:] = b
    e = expm(blk * dt_s)
    return e[:n, :n], e[:n, n:]


# per-step process noise of the filter model (standard deviations, STATES order): about three
# times the largest per-step RMS of this linear model's one-step error, driven by the commands
# through the 20 ms servo lag and one step later (as the estimator drives it), over four
# fault-free randomized flights of the closed-loop simulator (seeds 5001-5004; the airspeed
# 1.4 times: its large sensor noise covers a slow thrust bias); docs/methods-stmmae.md, "Noise"
PROCESS_STD = (0.005, 1.5e-4, 3e-5, 1e-4, 1e-4, 3e-5, 1e-4, 3e-4)
# sensor noise variances of the seed paper (p, q, r: rad^2/s^2; alpha, beta: rad^2; airspeed:
# m^2/s^2), MEASUREMENTS order
SENSOR_VAR = (0.0076, 0.0076, 0.0076, 0.0012, 0.0012, 1.0)
INITIAL_STD = (1.0, 0.05, 0.05, 0.2, 0.2, 0.2, 0.05, 0.05)


# half-width of the reference model's operating range in airspeed (m/s): fault-free flights
# cruising 5-7 m/s off the model's trim airspeed raised false alarms, 0-4.5 m/s off none
OPERATING_AIRSPEED_BAND_M_S = 4.0
# bound of the reference model's operating range in sideslip (deg, either side of the trim's 0):
# on fault-free development flights the share of samples with a surface's fault probability
# above 0.5 grew from under 1 % to 5-10 % with the 10 s smoothed sideslip beyond 4 deg and up
# to 41 % beyond 6 deg (docs/methods-stmmae.md, "Operating range")
OPERATING_SIDESLIP_DEG = 6.0
# bounds of the reference model's operating range in angle of attack (deg either side of the
# trim's) and in each angular rate p, q, r (deg/s either side of the trim's 0): in 10 fault-free
# flight hours the 10 s smoothed angle of attack stayed within 4.3 deg of trim and the smoothed
# rates within 13 deg/s; after some faults the simulated aircraft departs into loops (angle of
# attack 0.5 rad, pitch rate 1.5-4 rad/s) where the linear model says nothing
# (docs/methods-stmmae.md, "Operating range")
OPERATING_ALPHA_DEG = 7.0
OPERATING_RATE_DEG_S = 30.0


@lru_cache(maxsize=8)
def reference_model(dt_s: float = 0.01, airspeed_m_s: float = 25.0) -> dict[str, Any]:
    """The estimator model (JSON-ready): discrete deviation model at the level trim.

    ``x_{k+1} - x* = F (x_k - x*) + G (u_k - u*)``, ``y_k = H x_k``; ``x*``/``u*`` the trim.
    Inputs are the five surfaces (monitored) and the throttle (known input, not monitored).
    """
    prm = AerosondeParams()
    trim = trim_level(prm, airspeed_m_s)
    a, b = linearize(prm, trim)
    f, g = discretize(a, b, dt_s)
    h = np.zeros((len(MEASUREMENTS), len(STATES)))
    for i, name in enumerate(MEASUREMENTS):
        h[i, STATES.index(name)] = 1.0
    channels = {s: f"cmd_{s}" for s in INPUTS}
    return {
        "name": f"aerosonde_split_surfaces_{airspeed_m_s:g}m_s_{1.0 / dt_s:g}hz",
        "dt_s": dt_s,
        "states": list(STATES),
        "inputs": [{"name": s, "channel": channels[s], "surface": s in SURFACES} for s in INPUTS],
        "measurements": [{"name": m, "channel": m} for m in MEASUREMENTS],
        "F": f.tolist(),
        "G": g.tolist(),
        "H": h.tolist(),
        "Q": np.diag(np.square(PROCESS_STD)).tolist(),
        "R": np.diag(SENSOR_VAR).tolist(),
        "P0": np.diag(np.square(INITIAL_STD)).tolist(),
        "x_trim": trim.reduced_state.tolist(),
        "u_trim": trim.inputs.tolist(),
        # where the linearization holds, each measurement smoothed: the airspeed within
        # OPERATING_AIRSPEED_BAND_M_S of the trim airspeed, the sideslip within
        # OPERATING_SIDESLIP_DEG of the trim's zero, the angle of attack within OPERATING_ALPHA_DEG
        # of the trim's and the angular rates within OPERATING_RATE_DEG_S of zero
        # (docs/methods-stmmae.md, "Operating range")
        "operating_range": {
            "airspeed": [
                airspeed_m_s - OPERATING_AIRSPEED_BAND_M_S,
                airspeed_m_s + OPERATING_AIRSPEED_BAND_M_S,
            ],
            "beta": [-math.radians(OPERATING_SIDESLIP_DEG), math.radians(OPERATING_SIDESLIP_DEG)],
            "alpha": [
                trim.alpha_rad - math.radians(OPERATING_ALPHA_DEG),
                trim.alpha_rad + math.radians(OPERATING_ALPHA_DEG),
            ],
            **{
                rate: [-math.radians(OPERATING_RATE_DEG_S), math.radians(OPERATING_RATE_DEG_S)]
                for rate in ("p", "q", "r")
            },
        },
    }
