"""Compiled control loop of the EMA simulator (``estimators.simulators.ema_motor``)."""

from __future__ import annotations

import numpy as np
from numba import njit
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]


@njit(cache=True, nogil=True, error_model="numpy")
def ema_closed_loop(
    ad: FloatArray,
    bd: FloatArray,
    pos_ref_m: FloatArray,
    vel_ref_m_s: FloatArray,
    load_torque_nm: FloatArray,
    meters_per_rad: float,
    kp_pos: float,
    kp_vel: float,
    ki_vel: float,
    v_supply: float,
    dt_ctrl: float,
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """Cascaded position / speed control of a DC motor driving a ball screw.

    Per control step j (zero-order hold of the armature voltage and the load torque over the
    step; ``ad``/``bd`` are the exact discretization of eqs. 13-14 with state
    ``[i, w, theta]`` and input ``[v, T_ex]``):

        w_ref = v_ref / meters_per_rad + kp_pos (x_ref - x) / meters_per_rad
        v     = sat(kp_vel (w_ref - w) + ki_vel int(w_ref - w), +-v_supply)   (anti-windup)

    Returns:
        (voltage_v, current_a, speed_rad_s, position_m), each shape (n_steps,), values at the
        start of each control step (voltage: the one applied during the step).
    """
    n = pos_ref_m.shape[0]
    volt = np.empty(n)
    cur = np.empty(n)
    speed = np.empty(n)
    pos = np.empty(n)
    i = 0.0
    # start on the profile, moving at its speed, so no start-up transient enters the data
    w = vel_ref_m_s[0] / meters_per_rad
    th = pos_ref_m[0] / meters_per_rad
    integ = 0.0
    for j in range(n):
        x = th * meters_per_rad
        w_ref = (vel_ref_m_s[j] + kp_pos * (pos_ref_m[j] - x)) / meters_per_rad
        err = w_ref - w
        v_unsat = kp_vel * err + ki_vel * (integ + err * dt_ctrl)
        if v_unsat > v_supply:
            v = v_supply
        elif v_unsat < -v_supply:
            v = -v_supply
        else:
            v = v_unsat
            integ += err * dt_ctrl  # integrate only when not saturated
        volt[j] = v
        cur[j] = i
        speed[j] = w
        pos[j] = x
        tl = load_torque_nm[j]
        i_n = ad[0, 0] * i + ad[0, 1] * w + ad[0, 2] * th + bd[0, 0] * v + bd[0, 1] * tl
        w_n = ad[1, 0] * i + ad[1, 1] * w + ad[1, 2] * th + bd[1, 0] * v + bd[1, 1] * tl
        th_n = ad[2, 0] * i + ad[2, 1] * w + ad[2, 2] * th + bd[2, 0] * v + bd[2, 1] * tl
        i = i_n
        w = w_n
        th = th_n
    return volt, cur, speed, pos
