"""Compiled per-sample loop of the ``darr_fekf`` estimator: smoothing differentiator, the seven
distributed analytical redundancy relations (DARR), threshold calibration, detection with
latching and clearance, and the EKF / fuzzy adaptive EKF (FEKF) of the implicated subsystems.

``estimators.darr_fekf`` builds the flat configuration arrays once per configuration, holds the
state arrays, calls :func:`darr_batch` once per batch and turns the few event and health-window
rows it returns into Python objects. Everything that runs once per sample lives here.

Arrays (index constants below):

* ``cfg`` (``CFG_*``): scalars of the configuration;
* ``w0`` (W,): the smoother's equivalent FIR weights (their sum of squares scales the noise
  of smoothed signals);
* ``chan_order`` (C,): highest derivative order read of each channel;
* DARR terms ``term_res``/``term_chan``/``term_order``/``term_coef``: residual l = sum of
  ``term_coef`` times the smoothed ``term_order``-th derivative of channel ``term_chan`` over
  its terms (channel -1: the constant 1);
* ``res_chan`` (7, C): 1 where residual l reads channel c (for the missing-sample rule);
* subsystem arrays (``SC_*`` configuration row, ``sub_*`` term tables) and state rows
  (``SS_*``);
* state ``st`` (``ST_*`` scalars), ``hist`` (C, M, H) ring buffers of the inputs of the M
  box stages of the smoothing differentiator (stage 0 holds the raw values), ``sums`` (C, M)
  the stages' running sums, ``miss`` (C, W) missing flags over the smoother's support,
  ``sub_st`` (subsystems, ``SS_LEN``), ``cal_buf`` (capacity, 7) absolute residuals kept for
  a quantile calibration.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

N_RES = 7
N_CHAN = 9
MAX_ORDER = 3  # highest derivative order the relations read
BITS = np.array([float(2**i) for i in range(N_RES)])  # bit l of a coherence mask: residual l+1
MAX_PARAMS = 8
MAX_DIM = MAX_PARAMS + 1

# ----------------------------------------------------------------------------- configuration
CFG_DT = 0
CFG_N_WIN = 1
CFG_MAX_MISSING = 2  # largest number of filled (missing) samples allowed in a window
CFG_CAL_S = 3  # calibration window (s of stream time); <= 0: none
CFG_RULE = 4  # RULE_*
CFG_MARGIN = 5
CFG_Q = 6
CFG_MIN_DUR = 7  # samples above threshold before a residual counts as exceeded
CFG_CLEAR = 8  # samples with every residual below threshold before a fault is cleared
CFG_HEALTH_N = 9
CFG_N_SUB = 10
CFG_BOX = 11  # samples L of one box stage
CFG_N_SEG = 12  # segments of the calibration window (robust statistics)
CFG_SEG_OUTLIER = 13  # a segment with rms above this times the median segment rms is excluded
CFG_PEAK_RATIO = 14  # a segment with a peak above this times the median segment rms is excluded
CFG_SUSPICIOUS = 15  # robust rms / expected rms above this: calibration suspicious
CFG_REFUSE = 16  # robust rms / expected rms above this: calibration refused
CFG_FALLBACK_SIGMAS = 17  # thresholds after a refusal without reference: this times expected sd
CFG_HAS_REF = 18  # 1.0: a fault-free reference (thresholds, residual rms) is configured
CFG_SENSOR_LAMBDA = 19  # forgetting factor of the sensors' running noise variance
CFG_STUCK_N = 20  # unchanged raw samples before a sensor counts as stuck
CFG_NOISE_RATIO = 21  # running / calibrated noise variance above this: noisy sensor
CFG_FIT_DEC = 22  # isolation fit: one sample in this many
CFG_SENSOR_MIN_N = 23  # samples after calibration before the noise check runs
CFG_REF_THR = 24  # 7 reference thresholds
CFG_REF_RMS = CFG_REF_THR + 7  # 7 reference residual rms
CFG_REF_NOISE = CFG_REF_RMS + 7  # 9 reference noise variances (NaN: none)
CFG_NOISE_PERSIST = CFG_REF_NOISE + 9  # samples the running noise stays over the level: noisy
CFG_FIT_LAMBDA = CFG_NOISE_PERSIST + 1  # forgetting factor of the isolation fit per fit sample
CFG_WHITE_RATIO = CFG_FIT_LAMBDA + 1  # lower noise level that applies when the extra noise is white
CFG_WHITE_LEVEL = CFG_WHITE_RATIO + 1  # lag-1 autocorrelation of third differences: white below
CFG_LEN = CFG_WHITE_LEVEL + 1

N_STAGES = MAX_ORDER + 2  # box stages: the smoother is a B-spline of degree N_STAGES - 1

RULE_FIXED = 0.0
RULE_MAX = 1.0
RULE_MAX_MARGIN = 2.0
RULE_QUANTILE = 3.0

# subsystem configuration row
SC_RES = 0  # residual index (0-based)
SC_STATE_CHAN = 1
SC_N_PARAMS = 2
SC_FEKF = 3  # 1.0: fuzzy adaptive EKF, 0.0: EKF
SC_N_TERMS = 4  # terms of the relation
SC_R = 5  # measurement noise variance of the state channel; NaN: calibrated
SC_Q_STATE = 6  # process noise variance of the state per sample; NaN: from the inputs' noise
SC_P0_STATE = 7  # initial variance of the state; NaN: R
SC_C = 8  # robust constant c of eq. 41
SC_LAMBDA = 9  # forgetting factor of the innovation variance (eq. 38 over a window)
SC_LEVEL_IN = 10  # 3 input levels of the fuzzy sets ZO, PS, PB
SC_LEVEL_OUT = 13  # 3 output levels (alpha of ZO, PS, PB)
SC_RHO_MIN = 16
SC_RHO_MAX = 17
SC_RELATION = 18  # 1.0: the relation is the measurement (parameters only); 0.0: the state
SC_NEEDS_CAL = 19  # 1.0: the filter needs calibrated noise before it can start
SC_ALPHA_MIN = 20  # floor of the fuzzy factor
SC_WINDOW = 21  # T_w: time constant of the innovation statistics (s)
SC_Q_PARAM = 22  # MAX_PARAMS relative variances per second
SC_P0_PARAM = SC_Q_PARAM + MAX_PARAMS  # MAX_PARAMS relative variances
SC_NOMINAL = SC_P0_PARAM + MAX_PARAMS  # MAX_PARAMS nominal values
SC_LEN = SC_NOMINAL + MAX_PARAMS

# subsystem term kinds
TK_CONST = 0
TK_STATE = 1
TK_STATE_DOT = 2
TK_INPUT = 3

# subsystem state row
SS_RUNNING = 0
SS_T_START = 1
SS_D = 2  # windowed mean of the squared (scaled) innovation
SS_ALPHA = 3
SS_SCALE = 4  # s_y: state scale (sqrt of R)
SS_R = 5  # R in use (channel units squared)
SS_N_UPDATES = 6
SS_R_SAMPLE = 7  # variance of one sample's measurement noise (FEKF statistics)
SS_Z = 8  # MAX_DIM scaled state [y / s_y, rho_1 .. rho_p]
SS_P = SS_Z + MAX_DIM  # MAX_DIM^2 covariance of the scaled state, row-major
SS_LEN = SS_P + MAX_DIM * MAX_DIM

# state scalars
ST_N_SEEN = 0
ST_T_FIRST = 1
ST_T_LAST = 2
ST_POS = 3  # position of the newest sample in the stage ring buffers
ST_CALIBRATED = 4
ST_CAL_BUF_N = 5
ST_FAULT = 6
ST_FIRST_T = 7  # time the active fault was first detected
ST_BELOW = 8
ST_IRREGULAR = 9
ST_WIN_COUNT = 10
ST_WIN_T0 = 11
ST_WIN_FAULT = 12
ST_WIN_MASK = 13
ST_THR_READY = 14
ST_LATCH = 15  # 7 flags: the coherence vector
ST_ABOVE = ST_LATCH + N_RES  # 7 run lengths above threshold
ST_THR = ST_ABOVE + N_RES  # 7 thresholds in use
ST_CAL_MAX = ST_THR + N_RES  # 7 max |r| during calibration
ST_LAST_R = ST_CAL_MAX + N_RES  # 7 last finite residual values
ST_WIN_SUM2 = ST_LAST_R + N_RES
ST_WIN_N = ST_WIN_SUM2 + N_RES
ST_WIN_MAX = ST_WIN_N + N_RES
ST_LAST_VALID = ST_WIN_MAX + N_RES  # C last finite raw values
ST_MISS_COUNT = ST_LAST_VALID + N_CHAN  # C missing samples in the window
ST_NOISE_SUM2 = ST_MISS_COUNT + N_CHAN  # C sums of squared third differences (calibration)
ST_NOISE_N = ST_NOISE_SUM2 + N_CHAN
ST_NOISE_VAR = ST_NOISE_N + N_CHAN  # C calibrated noise variances (NaN before)
ST_MEAN_SQ = ST_NOISE_VAR + N_CHAN  # C sum of squared raw values in calibration
ST_PREV_SMOOTH = ST_MEAN_SQ + N_CHAN  # C smoothed channel values at the previous sample
ST_CAL_SUM2 = ST_PREV_SMOOTH + N_CHAN  # 7 sums of r^2 during calibration
ST_CAL_N = ST_CAL_SUM2 + N_RES  # 7 counts
ST_RES_VAR = ST_CAL_N + N_RES  # 7 calibrated mean squares of the residuals (NaN before)
ST_LEN_V1 = ST_RES_VAR + N_RES  # end of the version-1 layout; version 2 appends:
ST_CAL_STATE = ST_LEN_V1  # CAL_* below
ST_CAL_FLAGS = ST_CAL_STATE + 1  # bit mask of CALF_* reasons
ST_FIT_N = ST_CAL_FLAGS + 1  # effective samples in the isolation fit (with forgetting)
ST_SENS_MASK = ST_FIT_N + 1  # latched sensor flags as a bit mask (SENSOR_BITS)
ST_SENS_N = ST_SENS_MASK + 1  # samples the sensor noise check has seen since calibration
ST_EXP_SD = ST_SENS_N + 1  # 7 residual sd expected from the channels' noise (the model)
ST_CAL_ROBUST = ST_EXP_SD + N_RES  # 7 median segment rms of the calibration window
ST_CAL_EXCLUDED = ST_CAL_ROBUST + N_RES  # 7 segments excluded from the threshold statistic
ST_CAL_RATIO = ST_CAL_EXCLUDED + N_RES  # 7 robust rms / expected (or reference) rms
ST_CAL_ZERO = ST_CAL_RATIO + N_RES  # C unchanged consecutive raw samples in calibration
ST_CAL_RAW_N = ST_CAL_ZERO + N_CHAN  # C raw samples compared in calibration
ST_SENS_VAR = ST_CAL_RAW_N + N_CHAN  # C running noise variance (third differences)
ST_SENS_RUN = ST_SENS_VAR + N_CHAN  # C current run of unchanged raw samples
ST_SUB_WITHHELD = ST_SENS_RUN + N_CHAN  # 7 per subsystem: 1.0 while a flagged sensor stops it
ST_SENS_ABOVE = ST_SUB_WITHHELD + 7  # C samples in a row with the running noise over the level
ST_LEN_V2 = ST_SENS_ABOVE + N_CHAN  # end of the version-2 layout; version 3 appends:
ST_SENS_COV1 = ST_LEN_V2  # C running lag-1 product of the third differences (/20)
ST_SENS_E_PREV = ST_SENS_COV1 + N_CHAN  # C previous third difference (NaN: none)
ST_LEN = ST_SENS_E_PREV + N_CHAN
# lag-1 autocorrelation of the third differences of white noise: -15 / 20
WHITE_LAG1 = -0.75

# calibration states (ST_CAL_STATE)
CAL_CALIBRATING = 0.0
CAL_CALIBRATED = 1.0
CAL_SUSPICIOUS = 2.0
CAL_REFUSED = 3.0
# calibration reasons (bits of ST_CAL_FLAGS)
CALF_SEGMENT = 1  # a segment of the window is out of line with the others (onset inside)
CALF_LEVEL = 2  # residual level above the expected (or reference) level: suspicious
CALF_LEVEL_REFUSED = 4  # residual level far above the expected (or reference) level
CALF_STUCK = 8  # a sensor did not change during the window
CALF_NOISE = 16  # a channel's noise above the reference noise
# sensor flags: bit c stuck, bit N_CHAN + c noisy
SENSOR_BITS = np.array([float(2**i) for i in range(2 * N_CHAN)])
SENSOR_CHANNELS = 7  # the seven sensors (the inputs x_v, U_a are commands, never flagged)

# isolation fit columns: relative parameter changes, their ramps in time, then sensor bias
# by channel, sensor ramp by channel, and the residual
N_PARAMS_MODEL = 22
FIT_PRAMP = N_PARAMS_MODEL
FIT_BIAS = FIT_PRAMP + N_PARAMS_MODEL
FIT_RAMP = FIT_BIAS + N_CHAN
FIT_R = FIT_RAMP + N_CHAN
FIT_DIM = FIT_R + 1
FIT_FORGET_EVERY = 16  # fit samples between applications of the forgetting factor

# calibration segment statistics (rows of cal_seg[ri, k])
SEG_SUM2 = 0
SEG_N = 1
SEG_MAX = 2
SEG_LEN = 3
MAX_SEGMENTS = 32

# event rows
EV_T = 0
EV_KIND = 1
EV_MASK = 2  # coherence vector as a bit mask (bit l = residual l + 1)
EV_PREV_MASK = 3
EV_FIRST_T = 4
EV_SUB = 5  # subsystem index (estimation started)
EV_THR = 6  # 7 thresholds (calibration)
EV_NOISE = EV_THR + N_RES  # C noise standard deviations (calibration)
EV_CAL_STATE = EV_NOISE + N_CHAN  # calibration state (calibration)
EV_CAL_FLAGS = EV_CAL_STATE + 1
EV_SENS_MASK = EV_CAL_FLAGS + 1  # sensor flags (detection, clearance)
EV_PREV_SENS = EV_SENS_MASK + 1
EV_LEN = EV_PREV_SENS + 1
EV_CALIBRATED = 1.0
EV_DETECTED = 2.0
EV_CLEARED = 3.0
EV_EST_STARTED = 4.0

# health-window rows
WIN_T0 = 0
WIN_T1 = 1
WIN_N = 2
WIN_FAULT = 3
WIN_MASK = 4
WIN_RMS = 5  # 7
WIN_PEAK = WIN_RMS + N_RES  # 7 max |r| / threshold
WIN_LEN = WIN_PEAK + N_RES


# ----------------------------------------------------------------------------- differentiator
def box_length(window_s: float, dt: float) -> int:
    """Odd box length L whose N_STAGES-fold cascade spans about ``window_s``."""
    target = window_s / dt / N_STAGES + 1.0
    n = max(3, int(round(target)))
    return n if n % 2 == 1 else n + 1


def smoother_weights(box: int, dt: float, max_order: int) -> FloatArray:
    """Equivalent FIR weights of the smoothing differentiator, newest sample first.

    The smoother is the N_STAGES-fold cascade of a moving average of ``box`` samples (a
    discrete B-spline kernel of degree N_STAGES - 1 spanning ``W = N_STAGES (box - 1) + 1``
    samples, centred ``(W - 1) / 2`` samples back); the o-th derivative is the o-th backward
    difference of the smoothed signal over dt^o, computed as the o-th lag-``box`` difference of
    the cascade of N_STAGES - o stages over (box dt)^o (the same numbers, with far less
    rounding). Row o has ``W + o`` weights (zero-padded to ``W + max_order``).
    """
    stage = np.full(box, 1.0 / box)
    kernel = np.array([1.0])
    for _ in range(N_STAGES):
        kernel = np.convolve(kernel, stage)
    width = kernel.shape[0] + max_order
    out = np.zeros((max_order + 1, width))
    for o in range(max_order + 1):
        k = kernel
        for _ in range(o):
            k = np.convolve(k, np.array([1.0, -1.0]))
        out[o, : k.shape[0]] = k / dt**o
    return out


# ----------------------------------------------------------------------------- fuzzy factor
@njit(cache=True, nogil=True, error_model="numpy")
def fuzzy_alpha(x: float, lv: FloatArray, out: FloatArray) -> float:
    """Adaptive factor of the fuzzy system (seed eqs. 43-44, Table 2).

    Input sets ZO, PS, PB are triangular on the levels ``lv = (l1, l2, l3)`` (ZO is 1 up to
    l1, PB is 1 from l3); the output sets ZO, PS, PB are the discrete levels
    ``out = (y_ZO, y_PS, y_PB)``, each with membership 1 at its own level and 0 at the other
    two. Rules ZO -> PB, PS -> PS, PB -> ZO; max-min inference, centroid over the three output
    levels.
    """
    l1 = lv[0]
    l2 = lv[1]
    l3 = lv[2]
    if x <= l1:
        mu_zo, mu_ps, mu_pb = 1.0, 0.0, 0.0
    elif x < l2:
        mu_zo = (l2 - x) / (l2 - l1)
        mu_ps = (x - l1) / (l2 - l1)
        mu_pb = 0.0
    elif x < l3:
        mu_zo = 0.0
        mu_ps = (l3 - x) / (l3 - l2)
        mu_pb = (x - l2) / (l3 - l2)
    else:
        mu_zo, mu_ps, mu_pb = 0.0, 0.0, 1.0
    # max-min: output level y_j gets the firing strength of the rule concluding on its set
    mu_out_zo = mu_pb  # rule PB -> ZO
    mu_out_ps = mu_ps  # rule PS -> PS
    mu_out_pb = mu_zo  # rule ZO -> PB
    total = mu_out_zo + mu_out_ps + mu_out_pb
    return float((mu_out_zo * out[0] + mu_out_ps * out[1] + mu_out_pb * out[2]) / total)


# ----------------------------------------------------------------------------- subsystem filter
@njit(cache=True, nogil=True, error_model="numpy")
def _phi1(x: float) -> tuple[float, float]:
    """``phi1(x) = (e^x - 1) / x`` and its derivative, with series near 0."""
    if abs(x) < 1.0e-3:
        return (
            1.0 + x / 2.0 + x * x / 6.0 + x * x * x / 24.0,
            0.5 + x / 3.0 + x * x / 8.0 + x * x * x / 30.0,
        )
    em1 = math.expm1(x)
    return em1 / x, (x * (em1 + 1.0) - em1) / (x * x)


# work vectors of the subsystem filter (rows of ``vec``)
WV_Z = 0
WV_F = 1  # first row of the Jacobian
WV_GAIN = 2  # Kalman gain
WV_A_R = 3  # d a / d rho
WV_AY_R = 4  # d a_y / d rho
WV_B_R = 5  # d b_sum / d rho
WV_U = 6  # d y+ / d u_c by channel
WV_H = 7  # measurement row H
WV_PH = 8  # P- H^T
WV_ROWS = 9
WV_LEN = max(MAX_DIM, N_CHAN)


@njit(cache=True, nogil=True, error_model="numpy")
def _monomial(coef: float, exps: FloatArray, z: FloatArray, n_par: int) -> float:
    """``coef * prod_p z[p] ** exps[p]`` (integer exponents +-1 without a power); callers pass a
    view that starts at the first parameter, so one compiled version serves every offset."""
    m = coef
    for p in range(n_par):
        e = exps[p]
        if e == 1.0:
            m *= z[p]
        elif e == -1.0:
            m /= z[p]
        elif e != 0.0:
            m *= z[p] ** e
    return m


@njit(cache=True, nogil=True, error_model="numpy")
def subsystem_model(
    n_par: int,
    kinds: IntArray,
    chans: IntArray,
    coefs: FloatArray,
    exps: FloatArray,
    n_terms: int,
    u_mid: FloatArray,
    dt: float,
    scale: float,
    vec: FloatArray,
) -> float:
    """One step of a subsystem's model; returns the predicted scaled state ``y+ / s_y``.

    The subsystem's DARR, ``0 = a(rho) y' + a_y(rho) y + sum_j b_j(rho) u_j``, gives
    ``y' = A y + B`` with ``A = -a_y / a``, ``B = -sum_j b_j u_j / a``; each coefficient is a
    monomial ``c prod_p rho_p^e_p`` of the relative parameters ``rho_p = theta_p / theta_nom``.
    With the inputs held at ``u_mid`` over the step (exponential Euler, exact for that hold):

        y+ = e^(A dt) y + dt phi1(A dt) B,      phi1(x) = (e^x - 1) / x

    Reads the scaled state ``z = vec[WV_Z]``; writes the Jacobian row
    ``d(y+ / s_y) / d[z_0, rho]`` into ``vec[WV_F]`` and ``d(y+) / du_c`` into ``vec[WV_U]``.
    """
    z = vec[WV_Z]
    z_par = z[1:]
    a_r = vec[WV_A_R]
    ay_r = vec[WV_AY_R]
    b_r = vec[WV_B_R]
    gain_u = vec[WV_U]
    a = 0.0
    a_y = 0.0
    b_sum = 0.0
    for p in range(n_par):
        a_r[p] = 0.0
        ay_r[p] = 0.0
        b_r[p] = 0.0
    for c in range(N_CHAN):
        gain_u[c] = 0.0
    for j in range(n_terms):
        m = _monomial(coefs[j], exps[j], z_par, n_par)
        kind = kinds[j]
        if kind == TK_STATE_DOT:
            a += m
            for p in range(n_par):
                a_r[p] += exps[j, p] * m / z[1 + p]
        elif kind == TK_STATE:
            a_y += m
            for p in range(n_par):
                ay_r[p] += exps[j, p] * m / z[1 + p]
        else:
            u = 1.0
            if kind == TK_INPUT:
                u = u_mid[chans[j]]
                gain_u[chans[j]] += m
            b_sum += m * u
            for p in range(n_par):
                b_r[p] += exps[j, p] * m * u / z[1 + p]
    big_a = -a_y / a
    big_b = -b_sum / a
    x = big_a * dt
    e_x = math.exp(x)
    phi, dphi = _phi1(x)
    y = z[0] * scale
    f_row = vec[WV_F]
    f_row[0] = e_x
    for p in range(n_par):
        da = -(ay_r[p] * a - a_y * a_r[p]) / (a * a)
        db = -(b_r[p] * a - b_sum * a_r[p]) / (a * a)
        f_row[1 + p] = (dt * da * (e_x * y + dt * dphi * big_b) + dt * phi * db) / scale
    for c in range(N_CHAN):
        gain_u[c] = -dt * phi * gain_u[c] / a
    return float((e_x * y + dt * phi * big_b) / scale)


@njit(cache=True, nogil=True, error_model="numpy")
def _symmetrize(m: FloatArray, d: int) -> None:
    for i in range(d):
        for j in range(i + 1, d):
            s = 0.5 * (m[i, j] + m[j, i])
            m[i, j] = s
            m[j, i] = s


@njit(cache=True, nogil=True, error_model="numpy")
def _update(
    sc: FloatArray,
    ss: FloatArray,
    z: FloatArray,
    pp: FloatArray,
    d: int,
    eps: float,
    r_var: float,
    r_sample: float,
    dt: float,
    vec: FloatArray,
) -> None:
    """Scalar measurement update of ``z`` and ``pp`` (the prior covariance, overwritten by
    the posterior) with innovation ``eps``, measurement row ``vec[WV_H]``: EKF (seed eqs.
    29-32, Joseph form) or, when configured, FEKF (seed eqs. 33-45).

    ``r_var`` is the measurement variance the gain uses; ``r_sample`` is the variance of one
    sample's noise, smaller when consecutive samples' noise is correlated (``r_var`` is then
    inflated so that one sample carries the information of one independent sample). The FEKF
    statistics compare the innovation with ``r_sample``:

    * ``D``: forgetting-factor mean of eps^2 over the window (eq. 38), ``h = H P- H^T``,
      ``sigma^2 = max(D - h, r_sample)``;
    * robust factor ``gamma = min(1, c / |eps / sigma|)`` (eq. 41): the equivalent observation
      variance is ``r_var / gamma`` (eqs. 39-40);
    * the ratio of the predicted-state to the observation variance factor (eqs. 33-37, 42),
      ``(sigma^2 / (h + r_sample))^2``, gives alpha through the fuzzy system (eqs. 43-44),
      floored at ``alpha_min``;
    * alpha is the prior's weight over one window ``T_w``: per sample the prior covariance is
      divided by ``alpha^(dt / T_w)``, and the gain is eq. 45,
      ``K = P- H^T / (h + alpha_k r_var / gamma)``, ``alpha_k = alpha^(dt / T_w)``.

    The covariance follows from the (inflated) prior and the gain (Joseph form), symmetrized.
    """
    hrow = vec[WV_H]
    ph = vec[WV_PH]
    r_eq = r_var
    if sc[SC_FEKF] == 1.0:
        h0 = 0.0
        for i in range(d):
            for j in range(d):
                h0 += hrow[i] * pp[i, j] * hrow[j]
        lam = sc[SC_LAMBDA]
        ss[SS_D] = lam * ss[SS_D] + (1.0 - lam) * eps * eps
        sig2 = max(ss[SS_D] - h0, r_sample)
        v_std = abs(eps) / math.sqrt(sig2)
        gamma = 1.0 if v_std <= sc[SC_C] else sc[SC_C] / v_std
        ratio = sig2 / (h0 + r_sample)
        alpha = fuzzy_alpha(
            ratio * ratio,
            sc[SC_LEVEL_IN : SC_LEVEL_IN + 3],
            sc[SC_LEVEL_OUT : SC_LEVEL_OUT + 3],
        )
        alpha = max(alpha, sc[SC_ALPHA_MIN])
        ss[SS_ALPHA] = alpha
        r_eq = r_var / gamma
        if alpha < 1.0:
            inflate = alpha ** (-dt / sc[SC_WINDOW])
            for i in range(d):
                for j in range(d):
                    pp[i, j] *= inflate
    h = 0.0
    for i in range(d):
        acc = 0.0
        for j in range(d):
            acc += pp[i, j] * hrow[j]
        ph[i] = acc
        h += hrow[i] * acc
    denom = h + r_eq
    gain = vec[WV_GAIN]
    for i in range(d):
        gain[i] = ph[i] / denom
        z[i] += gain[i] * eps
    # Joseph form: (I - K H) P (I - K H)^T + r K K^T, with P H^T = ph
    for i in range(d):
        for j in range(i, d):
            v = (
                pp[i, j]
                - gain[i] * ph[j]
                - (ph[i] - gain[i] * h) * gain[j]
                + r_eq * gain[i] * gain[j]
            )
            pp[i, j] = v
            pp[j, i] = v
    ss[SS_N_UPDATES] += 1.0


@njit(cache=True, nogil=True, error_model="numpy")
def relation_step(
    sc: FloatArray,
    kinds: IntArray,
    chans: IntArray,
    orders: IntArray,
    coefs: FloatArray,
    exps: FloatArray,
    ss: FloatArray,
    sig: FloatArray,
    usable: bool,
    dt: float,
    vec: FloatArray,
    mats: FloatArray,
) -> None:
    """Parameter filter on the subsystem's relation used as a pseudo-measurement (equation
    error): state ``rho`` (random walk), measurement ``0 = r(rho, s)`` with the smoothed
    signals and derivatives ``sig``, innovation ``-r(rho-)``, row ``H = dr / drho``."""
    n_par = int(sc[SC_N_PARAMS])
    z = vec[WV_Z]
    pp = mats[2]
    for i in range(n_par):
        z[i] = ss[SS_Z + i]
        for j in range(n_par):
            pp[i, j] = ss[SS_P + i * MAX_DIM + j]
    for p in range(n_par):
        pp[p, p] += sc[SC_Q_PARAM + p] * dt
    if usable:
        hrow = vec[WV_H]
        for p in range(n_par):
            hrow[p] = 0.0
        r = 0.0
        for j in range(int(sc[SC_N_TERMS])):
            m = _monomial(coefs[j], exps[j], z, n_par)
            value = 1.0 if kinds[j] == TK_CONST else sig[chans[j], orders[j]]
            r += m * value
            for p in range(n_par):
                if exps[j, p] != 0.0:
                    hrow[p] += exps[j, p] * m * value / z[p]
        _update(sc, ss, z, pp, n_par, -r, ss[SS_R], ss[SS_R_SAMPLE], dt, vec)
    for p in range(n_par):
        z[p] = min(max(z[p], sc[SC_RHO_MIN]), sc[SC_RHO_MAX])
    for i in range(n_par):
        ss[SS_Z + i] = z[i]
        for j in range(n_par):
            ss[SS_P + i * MAX_DIM + j] = pp[i, j]


@njit(cache=True, nogil=True, error_model="numpy")
def subsystem_step(
    sc: FloatArray,
    kinds: IntArray,
    chans: IntArray,
    coefs: FloatArray,
    exps: FloatArray,
    ss: FloatArray,
    u_mid: FloatArray,
    y_meas: float,
    dt: float,
    noise_var: FloatArray,
    vec: FloatArray,
    mats: FloatArray,
) -> None:
    """Predict and update the state-measured filter of one subsystem in place (``ss`` is its
    state row; ``vec`` (WV_ROWS, WV_LEN) and ``mats`` (3, MAX_DIM, MAX_DIM) are scratch).

    EKF (seed eqs. 27-32) on the scaled state ``z = [y / s_y, rho_1 .. rho_p]`` with random-walk
    parameters: prediction by :func:`subsystem_model`, ``P- = F P F^T + Q``, then the scalar
    update of :func:`_update` with the smoothed state ``y_meas`` (NaN: predict only).
    """
    n_par = int(sc[SC_N_PARAMS])
    d = n_par + 1
    scale = ss[SS_SCALE]
    z = vec[WV_Z]
    p_mat = mats[0]
    fp = mats[1]
    pp = mats[2]
    for i in range(d):
        z[i] = ss[SS_Z + i]
        for j in range(d):
            p_mat[i, j] = ss[SS_P + i * MAX_DIM + j]
    z0_next = subsystem_model(
        n_par, kinds, chans, coefs, exps, int(sc[SC_N_TERMS]), u_mid, dt, scale, vec
    )
    f_row = vec[WV_F]
    gain_u = vec[WV_U]
    # process noise of the state: the inputs' noise through the model (the mean of two
    # samples), unless given
    q_state = sc[SC_Q_STATE]
    if not math.isfinite(q_state):
        q_state = 0.0
        for c in range(N_CHAN):
            if gain_u[c] != 0.0:
                q_state += gain_u[c] * gain_u[c] * 0.5 * noise_var[c]
    # predict, F = I except its first row: P- = F P F^T + Q
    for i in range(d):
        for j in range(d):
            fp[i, j] = p_mat[i, j]
    for j in range(d):
        acc = 0.0
        for m in range(d):
            acc += f_row[m] * p_mat[m, j]
        fp[0, j] = acc
    for i in range(d):
        for j in range(d):
            pp[i, j] = fp[i, j]
        acc = 0.0
        for m in range(d):
            acc += fp[i, m] * f_row[m]
        pp[i, 0] = acc
    pp[0, 0] += q_state / (scale * scale)
    for p in range(n_par):
        pp[1 + p, 1 + p] += sc[SC_Q_PARAM + p] * dt
    _symmetrize(pp, d)
    z[0] = z0_next
    if math.isfinite(y_meas):
        hrow = vec[WV_H]
        for i in range(d):
            hrow[i] = 0.0
        hrow[0] = 1.0
        s2 = scale * scale
        _update(
            sc, ss, z, pp, d, y_meas / scale - z[0], ss[SS_R] / s2, ss[SS_R_SAMPLE] / s2, dt, vec
        )
    for p in range(n_par):
        z[1 + p] = min(max(z[1 + p], sc[SC_RHO_MIN]), sc[SC_RHO_MAX])
    for i in range(d):
        ss[SS_Z + i] = z[i]
        for j in range(d):
            ss[SS_P + i * MAX_DIM + j] = pp[i, j]


@njit(cache=True, nogil=True, error_model="numpy")
def subsystem_start(
    sc: FloatArray, ss: FloatArray, y0: float, t: float, r_var: float, r_sample: float
) -> None:
    """Start a subsystem filter at the nominal parameters.

    State measurement: the state starts at the smoothed ``y0`` with variance ``p0_state`` (or
    ``r_var``), scaled by ``s_y = sqrt(r_var)``. Relation measurement: the state is the
    relative parameters only. ``r_var`` is the measurement variance the gain uses and
    ``r_sample`` the variance of one sample's noise (see :func:`_update`).
    """
    n_par = int(sc[SC_N_PARAMS])
    for i in range(SS_Z, SS_LEN):
        ss[i] = 0.0
    ss[SS_RUNNING] = 1.0
    ss[SS_T_START] = t
    ss[SS_ALPHA] = 1.0
    ss[SS_N_UPDATES] = 0.0
    ss[SS_R_SAMPLE] = r_sample
    first = 0
    if sc[SC_RELATION] == 1.0:
        ss[SS_R] = r_var
        ss[SS_SCALE] = 1.0
        ss[SS_D] = r_sample  # the innovation variance expected at the start
    else:
        scale = math.sqrt(r_var)
        p0 = sc[SC_P0_STATE] if math.isfinite(sc[SC_P0_STATE]) else r_var
        ss[SS_R] = r_var
        ss[SS_SCALE] = scale
        ss[SS_Z] = y0 / scale
        ss[SS_P] = p0 / r_var
        ss[SS_D] = (p0 + r_sample) / r_var
        first = 1
    for p in range(n_par):
        ss[SS_Z + first + p] = 1.0
        ss[SS_P + (first + p) * MAX_DIM + (first + p)] = sc[SC_P0_PARAM + p]


# ----------------------------------------------------------------------------- batch loop
@njit(cache=True, nogil=True, error_model="numpy")
def _push(rows: FloatArray, n_rows: int) -> FloatArray:
    """``rows`` with room for one more row (doubling the capacity when full)."""
    if n_rows < rows.shape[0]:
        return rows
    bigger = np.empty((2 * rows.shape[0] + 4, rows.shape[1]))
    bigger[:n_rows] = rows[:n_rows]
    return bigger


@njit(cache=True, nogil=True, error_model="numpy")
def _quantile(values: FloatArray, q: float) -> float:
    """Linear-interpolation quantile (numpy's default) of a non-empty array."""
    s = np.sort(values)
    pos = q * (s.shape[0] - 1)
    lo = int(math.floor(pos))
    hi = min(lo + 1, s.shape[0] - 1)
    return float(s[lo] + (s[hi] - s[lo]) * (pos - lo))


@njit(cache=True, nogil=True, error_model="numpy")
def _median(values: FloatArray) -> float:
    """Median of a non-empty array (mean of the two middle values for an even count)."""
    s = np.sort(values)
    n = s.shape[0]
    if n % 2 == 1:
        return float(s[n // 2])
    return float(0.5 * (s[n // 2 - 1] + s[n // 2]))


@njit(cache=True, nogil=True, error_model="numpy")
def _finish_calibration(
    cfg: FloatArray,
    st: FloatArray,
    cal_buf: FloatArray,
    cal_seg: FloatArray,
    res_gain2: FloatArray,
    row: FloatArray,
) -> None:
    """Noise variances, the checks of the calibration window, thresholds; fills the event row.

    1. Noise variance of each channel from the third differences of its raw samples
       (``var(x_k - 3 x_(k-1) + 3 x_(k-2) - x_(k-3)) / 20``); a parameter fault or a sensor
       bias or drift does not change it.
    2. Expected residual sd from the model: each residual is a linear FIR of the channels,
       ``sd_l^2 = sum_c G2[l, c] sigma_c^2`` with ``G2[l, c]`` the squared norm of the FIR
       weights residual l puts on channel c (``res_gain2``).
    3. Robust level: the window is split into segments; the median segment rms is the robust
       level; a segment whose rms exceeds ``CFG_SEG_OUTLIER`` times it, or whose peak exceeds
       ``CFG_PEAK_RATIO`` times it, is excluded from the threshold statistic (a fault that
       starts inside the window) and makes the calibration suspicious.
    4. Robust level over the expected (or reference) level: above ``CFG_SUSPICIOUS``
       suspicious, above ``CFG_REFUSE`` refused (a fault present over the whole window); a
       sensor that never changed during the window, or a channel noisier than its reference,
       refuses it too.
    5. Thresholds: by the configured rule over the kept segments; when refused, the
       reference thresholds if configured, otherwise ``CFG_FALLBACK_SIGMAS`` times the
       expected sd.
    """
    rule = cfg[CFG_RULE]
    n_seg = int(cfg[CFG_N_SEG])
    # 1. noise: third differences of white noise of variance s2 have variance 20 s2
    factor = 20.0
    for c in range(N_CHAN):
        if math.isfinite(st[ST_NOISE_VAR + c]):
            continue  # given in the configuration
        n_c = st[ST_NOISE_N + c]
        if n_c > 0.0:
            var = st[ST_NOISE_SUM2 + c] / n_c / factor
            # floor: a noise-free channel still needs a positive variance in a filter
            floor = 1.0e-12 * st[ST_MEAN_SQ + c] / n_c
            st[ST_NOISE_VAR + c] = max(var, floor, 1.0e-300)
    flags = 0
    for c in range(N_CHAN):
        ref = cfg[CFG_REF_NOISE + c]
        if math.isfinite(ref) and ref > 0.0 and st[ST_NOISE_VAR + c] > cfg[CFG_NOISE_RATIO] * ref:
            flags |= CALF_NOISE
        if (
            c < SENSOR_CHANNELS
            and st[ST_CAL_RAW_N + c] > 0.0
            and st[ST_CAL_ZERO + c] >= 0.99 * st[ST_CAL_RAW_N + c]
        ):
            flags |= CALF_STUCK
    # 2.-4. levels and segments
    n_buf = int(st[ST_CAL_BUF_N])
    seg_rms = np.empty(n_seg)
    keep = np.zeros(n_seg)
    for ri in range(N_RES):
        var_e = 0.0
        for c in range(N_CHAN):
            var_e += res_gain2[ri, c] * st[ST_NOISE_VAR + c]
        st[ST_EXP_SD + ri] = math.sqrt(var_e) if var_e > 0.0 else np.nan
        n_ok = 0
        for k in range(n_seg):
            if cal_seg[ri, k, SEG_N] > 0.0:
                seg_rms[n_ok] = math.sqrt(cal_seg[ri, k, SEG_SUM2] / cal_seg[ri, k, SEG_N])
                n_ok += 1
        med = _median(seg_rms[:n_ok]) if n_ok > 0 else np.nan
        st[ST_CAL_ROBUST + ri] = med
        excluded = 0
        peak = 0.0
        for k in range(n_seg):
            keep[k] = 0.0
            if cal_seg[ri, k, SEG_N] <= 0.0:
                continue
            rms_k = math.sqrt(cal_seg[ri, k, SEG_SUM2] / cal_seg[ri, k, SEG_N])
            if (
                med > 0.0
                and rms_k <= cfg[CFG_SEG_OUTLIER] * med
                and cal_seg[ri, k, SEG_MAX] <= cfg[CFG_PEAK_RATIO] * med
            ):
                keep[k] = 1.0
                peak = max(peak, cal_seg[ri, k, SEG_MAX])
            else:
                excluded += 1
        st[ST_CAL_EXCLUDED + ri] = excluded
        if excluded > 0:
            flags |= CALF_SEGMENT
        level = cfg[CFG_REF_RMS + ri] if cfg[CFG_HAS_REF] == 1.0 else st[ST_EXP_SD + ri]
        ratio = med / level if level > 0.0 else np.nan
        st[ST_CAL_RATIO + ri] = ratio
        if ratio > cfg[CFG_REFUSE]:
            flags |= CALF_LEVEL_REFUSED
        elif ratio > cfg[CFG_SUSPICIOUS]:
            flags |= CALF_LEVEL
        if rule == RULE_FIXED:
            continue
        if rule == RULE_QUANTILE:
            col = np.empty(n_buf)
            n_q = 0
            for i in range(n_buf):
                v = cal_buf[i, ri]
                if math.isfinite(v) and keep[int(cal_buf[i, N_RES])] == 1.0:
                    col[n_q] = v
                    n_q += 1
            thr = cfg[CFG_MARGIN] * _quantile(col[:n_q], cfg[CFG_Q]) if n_q > 0 else np.nan
        elif rule == RULE_MAX_MARGIN:
            thr = cfg[CFG_MARGIN] * peak if peak > 0.0 else np.nan
        else:
            thr = peak if peak > 0.0 else np.nan
        st[ST_THR + ri] = thr
    refused = (flags & (CALF_LEVEL_REFUSED | CALF_STUCK | CALF_NOISE)) != 0
    for ri in range(N_RES):
        if refused:
            # explicit (fixed) thresholds stay; calibrated ones fall back
            if cfg[CFG_HAS_REF] == 1.0:
                if rule != RULE_FIXED:
                    st[ST_THR + ri] = cfg[CFG_REF_THR + ri]
                st[ST_RES_VAR + ri] = cfg[CFG_REF_RMS + ri] ** 2
            else:
                if rule != RULE_FIXED:
                    st[ST_THR + ri] = cfg[CFG_FALLBACK_SIGMAS] * st[ST_EXP_SD + ri]
                st[ST_RES_VAR + ri] = st[ST_EXP_SD + ri] ** 2
        elif st[ST_CAL_N + ri] > 0.0:
            # the filters' noise: the robust level, so that a faulty segment does not inflate it
            st[ST_RES_VAR + ri] = st[ST_CAL_ROBUST + ri] ** 2
    if refused:
        st[ST_CAL_STATE] = CAL_REFUSED
    elif flags != 0:
        st[ST_CAL_STATE] = CAL_SUSPICIOUS
    else:
        st[ST_CAL_STATE] = CAL_CALIBRATED
    st[ST_CAL_FLAGS] = flags
    st[ST_CALIBRATED] = 1.0
    if rule != RULE_FIXED:
        st[ST_THR_READY] = 1.0
    for ri in range(N_RES):
        row[EV_THR + ri] = st[ST_THR + ri]
    for c in range(N_CHAN):
        row[EV_NOISE + c] = math.sqrt(st[ST_NOISE_VAR + c])
    row[EV_CAL_STATE] = st[ST_CAL_STATE]
    row[EV_CAL_FLAGS] = flags


@njit(cache=True, nogil=True, error_model="numpy")
def _window_sum(ring: FloatArray, newest: int, count: int, n: int) -> float:
    """Sum of the ``count`` newest values of a ring buffer of length ``n``."""
    first = newest - count + 1
    acc = 0.0
    if first >= 0:
        for i in range(first, newest + 1):
            acc += ring[i]
        return acc
    for i in range(first + n, n):
        acc += ring[i]
    for i in range(0, newest + 1):
        acc += ring[i]
    return acc


@njit(cache=True, nogil=True, error_model="numpy")
def _push_samples(
    hist: FloatArray,
    sums: FloatArray,
    y: FloatArray,
    hpos: int,
    old_pos: int,
    box: int,
    inv_box: float,
    anchor: bool,
) -> None:
    """Feed one sample of every channel (``y``, replaced by the smoothed values) through the
    box stages.

    Stage j averages the last ``box`` values of its input ``hist[c, j]`` (stage 0's input is
    the raw channel); ``old_pos`` is the ring position ``box`` samples back. The running sums
    are recomputed from the ring buffers when ``anchor`` is set (every ``box`` samples), so
    rounding errors never accumulate. Channels are the inner loop: they are independent.
    """
    n_hist = hist.shape[2]
    for j in range(N_STAGES):
        for c in range(N_CHAN):
            hist[c, j, hpos] = y[c]
            if anchor:
                sums[c, j] = _window_sum(hist[c, j], hpos, box, n_hist)
            else:
                sums[c, j] += y[c] - hist[c, j, old_pos]
            y[c] = sums[c, j] * inv_box


@njit(cache=True, nogil=True, error_model="numpy")
def _derivatives(
    hist: FloatArray,
    c: int,
    lag_pos: IntArray,
    inv_h: FloatArray,
    max_order: int,
    out: FloatArray,
) -> None:
    """Orders 1..max_order of channel ``c``: the o-th lag-``box`` difference of the output of
    stage N_STAGES - o - 1 (``hist[c, N_STAGES - o]``) over (box dt)^o; ``lag_pos[i]`` is the
    ring position i boxes back and ``inv_h[o]`` is (box dt)^-o."""
    for o in range(1, max_order + 1):
        row = N_STAGES - o
        acc = 0.0
        binom = 1.0
        for i in range(o + 1):
            acc += binom * hist[c, row, lag_pos[i]]
            binom *= -(o - i) / (i + 1.0)
        out[o] = acc * inv_h[o]


@njit(cache=True, nogil=True, error_model="numpy")
def darr_batch(
    cfg: FloatArray,
    w0: FloatArray,
    chan_order: IntArray,
    term_res: IntArray,
    term_chan: IntArray,
    term_order: IntArray,
    term_coef: FloatArray,
    res_chan: IntArray,
    sub_cfg: FloatArray,
    sub_kind: IntArray,
    sub_chan: IntArray,
    sub_order: IntArray,
    sub_coef: FloatArray,
    sub_exp: FloatArray,
    sub_fuse: IntArray,
    n_fused: int,
    res_gain2: FloatArray,
    term_fit: FloatArray,
    sub_reads: FloatArray,
    st: FloatArray,
    hist: FloatArray,
    sums: FloatArray,
    miss: FloatArray,
    sub_st: FloatArray,
    cal_buf: FloatArray,
    cal_seg: FloatArray,
    gram: FloatArray,
    t: FloatArray,
    data: FloatArray,
    out: FloatArray,
) -> tuple[FloatArray, FloatArray, int]:
    """Run the estimator over one batch, updating the state arrays in place.

    ``data`` is (N_CHAN, n) in the model's channel order; ``out`` (rows, n) receives the seven
    residuals, each subsystem's parameter estimates (in subsystem order), the fused estimates
    (``sub_fuse[i, p]``: the fused row of subsystem i's parameter p) and each subsystem's
    adaptive factor (see ``estimators.darr_fekf.sample_output_names``).

    Returns:
        (events, windows, status): event rows (``EV_*``), completed health-window rows
        (``WIN_*``), and 0, or -1 when the batch's times are not strictly increasing (nothing
        is then changed).
    """
    n = t.shape[0]
    for k in range(1, n):
        if not t[k] > t[k - 1]:
            return np.empty((0, EV_LEN)), np.empty((0, WIN_LEN)), -1
    n_win = int(cfg[CFG_N_WIN])
    box = int(cfg[CFG_BOX])
    inv_box = 1.0 / box
    n_hist = hist.shape[2]
    lag_pos = np.zeros(MAX_ORDER + 1, dtype=np.int64)
    y_in = np.empty(N_CHAN)
    inv_h = np.empty(MAX_ORDER + 1)
    dt_nom = cfg[CFG_DT]
    for o in range(MAX_ORDER + 1):
        inv_h[o] = (box * dt_nom) ** -o
    max_missing = cfg[CFG_MAX_MISSING]
    cal_s = cfg[CFG_CAL_S]
    rule = cfg[CFG_RULE]
    min_dur = cfg[CFG_MIN_DUR]
    clear_n = cfg[CFG_CLEAR]
    health_n = cfg[CFG_HEALTH_N]
    n_sub = int(cfg[CFG_N_SUB])
    n_terms = term_res.shape[0]
    sub_rows = 0
    for i in range(n_sub):
        sub_rows += int(sub_cfg[i, SC_N_PARAMS])
    fused_row0 = N_RES + sub_rows
    alpha_row0 = fused_row0 + n_fused

    events = np.empty((4, EV_LEN))
    n_ev: int = np.int64(0)  # type: ignore[assignment]  # typed, not the literal 0: _push compiles once
    windows = np.empty((int(n // health_n) + 1, WIN_LEN))
    n_wo = 0
    sig = np.empty((N_CHAN, MAX_ORDER + 1))
    r = np.empty(N_RES)
    u_mid = np.empty(N_CHAN)
    smooth = np.empty(N_CHAN)
    noise_var = st[ST_NOISE_VAR : ST_NOISE_VAR + N_CHAN]
    # the filters read smoothed signals, whose white-noise variance is sigma^2 sum(w0^2)
    smooth_gain = np.sum(w0 * w0)
    noise_var_s = np.empty(N_CHAN)
    vec = np.zeros((WV_ROWS, WV_LEN))
    mats = np.zeros((3, MAX_DIM, MAX_DIM))
    phi = np.zeros((FIT_DIM, N_RES))
    nz = np.zeros(FIT_DIM, dtype=np.int64)
    fit_w = np.empty(N_RES)
    n_seg = int(cfg[CFG_N_SEG])
    sens_lambda = cfg[CFG_SENSOR_LAMBDA]
    stuck_n = cfg[CFG_STUCK_N]
    noise_ratio = cfg[CFG_NOISE_RATIO]
    fit_dec = int(cfg[CFG_FIT_DEC])
    pos = int(st[ST_POS])
    for k in range(n):
        tk = t[k]
        first = st[ST_N_SEEN] == 0.0
        if first:
            st[ST_T_FIRST] = tk
        elif abs((tk - st[ST_T_LAST]) - dt_nom) > 0.01 * dt_nom:
            st[ST_IRREGULAR] += 1.0
        dt_k = dt_nom if first else tk - st[ST_T_LAST]
        # --- smoothing differentiator (missing samples hold the last valid value, 0 before any)
        pos = pos + 1 if pos + 1 < n_hist else 0
        for i in range(MAX_ORDER + 1):
            lag = pos - i * box
            lag_pos[i] = lag if lag >= 0 else lag + n_hist
        mpos = int(st[ST_N_SEEN]) % n_win
        anchor = int(st[ST_N_SEEN]) % box == 0
        for c in range(N_CHAN):
            x = data[c, k]
            flag = 0.0
            if math.isfinite(x):
                st[ST_LAST_VALID + c] = x
            else:
                x = st[ST_LAST_VALID + c]
                flag = 1.0
                if not math.isfinite(x):
                    x = 0.0
            st[ST_MISS_COUNT + c] += flag - miss[c, mpos]
            miss[c, mpos] = flag
            y_in[c] = x
        _push_samples(hist, sums, y_in, pos, lag_pos[1], box, inv_box, anchor)
        for c in range(N_CHAN):
            sig[c, 0] = y_in[c]
            _derivatives(hist, c, lag_pos, inv_h, chan_order[c], sig[c])
        st[ST_N_SEEN] += 1.0
        ready = st[ST_N_SEEN] >= n_win + MAX_ORDER
        # --- residuals
        if ready:
            for ri in range(N_RES):
                r[ri] = 0.0
            for j in range(n_terms):
                c = term_chan[j]
                value = 1.0 if c < 0 else sig[c, term_order[j]]
                r[term_res[j]] += term_coef[j] * value
            for ri in range(N_RES):
                for c in range(N_CHAN):
                    if res_chan[ri, c] == 1 and st[ST_MISS_COUNT + c] > max_missing:
                        r[ri] = np.nan
        else:
            for ri in range(N_RES):
                r[ri] = np.nan
        for ri in range(N_RES):
            out[ri, k] = r[ri]
            if math.isfinite(r[ri]):
                st[ST_LAST_R + ri] = r[ri]
        # --- calibration window
        if st[ST_CALIBRATED] == 0.0 and cal_s > 0.0:
            if tk - st[ST_T_FIRST] < cal_s:
                seg = min(int((tk - st[ST_T_FIRST]) / cal_s * n_seg), n_seg - 1)
                for ri in range(N_RES):
                    if math.isfinite(r[ri]):
                        st[ST_CAL_MAX + ri] = max(st[ST_CAL_MAX + ri], abs(r[ri]))
                        st[ST_CAL_SUM2 + ri] += r[ri] * r[ri]
                        st[ST_CAL_N + ri] += 1.0
                        cal_seg[ri, seg, SEG_SUM2] += r[ri] * r[ri]
                        cal_seg[ri, seg, SEG_N] += 1.0
                        cal_seg[ri, seg, SEG_MAX] = max(cal_seg[ri, seg, SEG_MAX], abs(r[ri]))
                if rule == RULE_QUANTILE and ready:
                    nb = int(st[ST_CAL_BUF_N])
                    if nb < cal_buf.shape[0]:
                        for ri in range(N_RES):
                            cal_buf[nb, ri] = abs(r[ri])
                        cal_buf[nb, N_RES] = seg
                        st[ST_CAL_BUF_N] = nb + 1
                if st[ST_N_SEEN] >= 2.0:
                    p1 = pos - 1 if pos >= 1 else pos - 1 + n_hist
                    for c in range(N_CHAN):
                        if math.isfinite(data[c, k]) and miss[c, (mpos - 1) % n_win] == 0.0:
                            st[ST_CAL_RAW_N + c] += 1.0
                            if hist[c, 0, pos] == hist[c, 0, p1]:
                                st[ST_CAL_ZERO + c] += 1.0
                if ready:
                    # third difference of the raw samples: the signal's share is (w dt)^3,
                    # white noise of variance s2 gives 20 s2
                    p1 = pos - 1 if pos >= 1 else pos - 1 + n_hist
                    p2 = pos - 2 if pos >= 2 else pos - 2 + n_hist
                    p3 = pos - 3 if pos >= 3 else pos - 3 + n_hist
                    for c in range(N_CHAN):
                        if st[ST_MISS_COUNT + c] == 0.0:
                            raw_c = hist[c, 0, pos]
                            e = raw_c - 3.0 * hist[c, 0, p1] + 3.0 * hist[c, 0, p2] - hist[c, 0, p3]
                            st[ST_NOISE_SUM2 + c] += e * e
                            st[ST_NOISE_N + c] += 1.0
                            st[ST_MEAN_SQ + c] += raw_c * raw_c
            else:
                events = _push(events, n_ev)
                row = events[n_ev]
                row[:] = np.nan
                row[EV_T] = tk
                row[EV_KIND] = EV_CALIBRATED
                _finish_calibration(cfg, st, cal_buf, cal_seg, res_gain2, row)
                for c in range(N_CHAN):
                    st[ST_SENS_VAR + c] = st[ST_NOISE_VAR + c]
                    st[ST_SENS_COV1 + c] = WHITE_LAG1 * st[ST_NOISE_VAR + c]
                    st[ST_SENS_E_PREV + c] = np.nan
                n_ev += 1
        # --- sensor self-checks after calibration: stuck (raw value unchanged for stuck_n
        # samples) and noisy (running noise variance over noise_ratio times the calibrated one)
        sens_now = 0
        if st[ST_CALIBRATED] == 1.0 and st[ST_N_SEEN] >= 4.0:
            p1 = pos - 1 if pos >= 1 else pos - 1 + n_hist
            p2 = pos - 2 if pos >= 2 else pos - 2 + n_hist
            p3 = pos - 3 if pos >= 3 else pos - 3 + n_hist
            st[ST_SENS_N] += 1.0
            for c in range(SENSOR_CHANNELS):
                if math.isfinite(data[c, k]):
                    if hist[c, 0, pos] == hist[c, 0, p1]:
                        st[ST_SENS_RUN + c] += 1.0
                    else:
                        st[ST_SENS_RUN + c] = 0.0
                if st[ST_MISS_COUNT + c] == 0.0:
                    e = (
                        hist[c, 0, pos]
                        - 3.0 * hist[c, 0, p1]
                        + 3.0 * hist[c, 0, p2]
                        - hist[c, 0, p3]
                    )
                    st[ST_SENS_VAR + c] = (
                        sens_lambda * st[ST_SENS_VAR + c] + (1.0 - sens_lambda) * e * e / 20.0
                    )
                    e_prev = st[ST_SENS_E_PREV + c]
                    if math.isfinite(e_prev):
                        st[ST_SENS_COV1 + c] = (
                            sens_lambda * st[ST_SENS_COV1 + c]
                            + (1.0 - sens_lambda) * e * e_prev / 20.0
                        )
                    st[ST_SENS_E_PREV + c] = e
                else:
                    st[ST_SENS_E_PREV + c] = np.nan
                if st[ST_SENS_RUN + c] >= stuck_n:
                    sens_now |= 1 << c
                var_c = st[ST_SENS_VAR + c]
                # white extra noise keeps the third differences' lag-1 autocorrelation at
                # -0.75; a plant transient (a resonance excited by a fault) moves it towards
                # cos(w dt), so a lower level applies to white increases only
                white = st[ST_SENS_COV1 + c] < cfg[CFG_WHITE_LEVEL] * var_c
                if st[ST_SENS_N] >= cfg[CFG_SENSOR_MIN_N] and (
                    var_c > noise_ratio * noise_var[c]
                    or (white and var_c > cfg[CFG_WHITE_RATIO] * noise_var[c])
                ):
                    st[ST_SENS_ABOVE + c] += 1.0
                else:
                    st[ST_SENS_ABOVE + c] = 0.0
                # a plant transient (a fault exciting a stiff mode) raises the third
                # differences for a while; increased sensor noise stays
                if st[ST_SENS_ABOVE + c] >= cfg[CFG_NOISE_PERSIST]:
                    sens_now |= 1 << (N_CHAN + c)
        # --- detection, latching, clearance
        if st[ST_THR_READY] == 1.0:
            any_above = sens_now != 0
            prev_mask = 0.0
            prev_sens = int(st[ST_SENS_MASK])
            changed = (prev_sens | sens_now) != prev_sens
            st[ST_SENS_MASK] = float(prev_sens | sens_now)
            for ri in range(N_RES):
                if st[ST_LATCH + ri] == 1.0:
                    prev_mask += BITS[ri]
                if math.isfinite(r[ri]):
                    if abs(r[ri]) > st[ST_THR + ri]:
                        st[ST_ABOVE + ri] += 1.0
                        any_above = True
                    else:
                        st[ST_ABOVE + ri] = 0.0
                if st[ST_ABOVE + ri] >= min_dur and st[ST_LATCH + ri] == 0.0:
                    st[ST_LATCH + ri] = 1.0
                    changed = True
            if changed:
                if st[ST_FAULT] == 0.0:
                    st[ST_FAULT] = 1.0
                    st[ST_FIRST_T] = tk
                    st[ST_FIT_N] = 0.0
                    gram[:, :] = 0.0
                st[ST_BELOW] = 0.0
                events = _push(events, n_ev)
                row = events[n_ev]
                row[:] = np.nan
                row[EV_T] = tk
                row[EV_KIND] = EV_DETECTED
                row[EV_MASK] = _mask(st)
                row[EV_PREV_MASK] = prev_mask
                row[EV_FIRST_T] = st[ST_FIRST_T]
                row[EV_SENS_MASK] = st[ST_SENS_MASK]
                row[EV_PREV_SENS] = prev_sens
                n_ev += 1
            elif st[ST_FAULT] == 1.0:
                st[ST_BELOW] = 0.0 if any_above else st[ST_BELOW] + 1.0
                if st[ST_BELOW] >= clear_n:
                    events = _push(events, n_ev)
                    row = events[n_ev]
                    row[:] = np.nan
                    row[EV_T] = tk
                    row[EV_KIND] = EV_CLEARED
                    row[EV_MASK] = _mask(st)
                    row[EV_FIRST_T] = st[ST_FIRST_T]
                    row[EV_SENS_MASK] = st[ST_SENS_MASK]
                    n_ev += 1
                    st[ST_FAULT] = 0.0
                    st[ST_BELOW] = 0.0
                    st[ST_SENS_MASK] = 0.0
                    for i in range(n_sub):
                        st[ST_SUB_WITHHELD + i] = 0.0
                    for ri in range(N_RES):
                        st[ST_LATCH + ri] = 0.0
                        st[ST_ABOVE + ri] = 0.0
                    for i in range(n_sub):
                        sub_st[i, SS_RUNNING] = 0.0
        # --- isolation fit of the active fault: weighted normal equations of the residuals
        # on the fault directions (relative parameter changes, sensor bias and ramp by channel)
        # (from one smoother window after detection: the smoothed step of a sudden fault is
        # a transient that neither a bias nor a parameter change describes)
        if (
            st[ST_FAULT] == 1.0
            and ready
            and int(st[ST_N_SEEN]) % fit_dec == 0
            and tk - st[ST_FIRST_T] >= n_win * dt_nom
        ):
            all_finite = True
            for ri in range(N_RES):
                if not math.isfinite(r[ri]):
                    all_finite = False
            if all_finite:
                phi[:, :] = 0.0
                t_rel = tk - st[ST_FIRST_T]
                for j in range(n_terms):
                    c = term_chan[j]
                    value = 1.0 if c < 0 else sig[c, term_order[j]]
                    l_j = term_res[j]
                    for p in range(N_PARAMS_MODEL):
                        f = term_fit[j, p]
                        if f != 0.0:
                            phi[p, l_j] += f * value
                    if c >= 0:
                        if term_order[j] == 0:
                            phi[FIT_BIAS + c, l_j] += term_coef[j]
                            phi[FIT_RAMP + c, l_j] += term_coef[j] * t_rel
                        elif term_order[j] == 1:
                            phi[FIT_RAMP + c, l_j] += term_coef[j]
                for p in range(N_PARAMS_MODEL):
                    for ri in range(N_RES):
                        phi[FIT_PRAMP + p, ri] = phi[p, ri] * t_rel
                for ri in range(N_RES):
                    phi[FIT_R, ri] = r[ri]
                    sd = st[ST_EXP_SD + ri]
                    if not (sd > 0.0):
                        sd = math.sqrt(st[ST_RES_VAR + ri])
                    fit_w[ri] = 1.0 / (sd * sd) if sd > 0.0 else 0.0
                # exponential forgetting: the fit follows a fault whose course changes (a ramp
                # that stops) with constant and ramp columns over about the last window;
                # applied every FIT_FORGET_EVERY fit samples (lambda^FIT_FORGET_EVERY) to save
                # the full pass over the matrix
                fit_count = int(st[ST_N_SEEN]) // fit_dec
                fit_lambda = cfg[CFG_FIT_LAMBDA]
                if fit_lambda < 1.0 and fit_count % FIT_FORGET_EVERY == 0:
                    chunk = fit_lambda**FIT_FORGET_EVERY
                    for a in range(FIT_DIM):
                        for b in range(a, FIT_DIM):
                            gram[a, b] *= chunk
                    st[ST_FIT_N] *= chunk
                # only the nonzero entries of each residual's row of phi (about a third)
                for ri in range(N_RES):
                    w_l = fit_w[ri]
                    n_nz = 0
                    for a in range(FIT_DIM):
                        if phi[a, ri] != 0.0:
                            nz[n_nz] = a
                            n_nz += 1
                    for i_a in range(n_nz):
                        a = nz[i_a]
                        pa = phi[a, ri] * w_l
                        for i_b in range(i_a, n_nz):
                            b = nz[i_b]
                            gram[a, b] += pa * phi[b, ri]
                st[ST_FIT_N] += 1.0
        # --- estimators of the implicated subsystems, at the smoothed signals' time (lag)
        for c in range(N_CHAN):
            smooth[c] = sig[c, 0] if ready else np.nan
            u_mid[c] = 0.5 * (st[ST_PREV_SMOOTH + c] + smooth[c])
            noise_var_s[c] = noise_var[c] * smooth_gain
        row_par = N_RES
        for i in range(n_sub):
            sc = sub_cfg[i]
            n_par = int(sc[SC_N_PARAMS])
            ss = sub_st[i]
            chan = int(sc[SC_STATE_CHAN])
            res = int(sc[SC_RES])
            relation = sc[SC_RELATION] == 1.0
            # a sensor flagged stuck or noisy corrupts the relations that read it: no estimate
            sens_mask = int(st[ST_SENS_MASK])
            for c in range(N_CHAN):
                if sub_reads[i, c] == 1.0 and (
                    ((sens_mask >> c) & 1) == 1 or ((sens_mask >> (N_CHAN + c)) & 1) == 1
                ):
                    st[ST_SUB_WITHHELD + i] = 1.0
            if st[ST_SUB_WITHHELD + i] == 1.0:
                ss[SS_RUNNING] = 0.0
            elif ss[SS_RUNNING] == 1.0:
                if relation:
                    usable = math.isfinite(r[res])
                    relation_step(
                        sc,
                        sub_kind[i],
                        sub_chan[i],
                        sub_order[i],
                        sub_coef[i],
                        sub_exp[i],
                        ss,
                        sig,
                        usable,
                        dt_k,
                        vec,
                        mats,
                    )
                else:
                    y_meas = smooth[chan] if st[ST_MISS_COUNT + chan] <= max_missing else np.nan
                    subsystem_step(
                        sc,
                        sub_kind[i],
                        sub_chan[i],
                        sub_coef[i],
                        sub_exp[i],
                        ss,
                        u_mid,
                        y_meas,
                        dt_k,
                        noise_var_s,
                        vec,
                        mats,
                    )
            elif (
                st[ST_FAULT] == 1.0
                and st[ST_LATCH + res] == 1.0
                and math.isfinite(r[res])
                and (sc[SC_NEEDS_CAL] == 0.0 or st[ST_CALIBRATED] == 1.0)
            ):
                # one sample of a smoothed signal carries the information of one raw sample:
                # the gain uses the smoothed quantity's variance times the smoother's equivalent
                # number of averaged samples, 1 / sum(w0^2)
                if relation:
                    r_sample = sc[SC_R] if math.isfinite(sc[SC_R]) else st[ST_RES_VAR + res]
                else:
                    r_raw = sc[SC_R] if math.isfinite(sc[SC_R]) else noise_var[chan]
                    r_sample = r_raw * smooth_gain
                r_var = r_sample / smooth_gain
                if math.isfinite(r_var) and r_var > 0.0:
                    subsystem_start(sc, ss, smooth[chan], tk, r_var, r_sample)
                    events = _push(events, n_ev)
                    row = events[n_ev]
                    row[:] = np.nan
                    row[EV_T] = tk
                    row[EV_KIND] = EV_EST_STARTED
                    row[EV_SUB] = i
                    row[EV_MASK] = _mask(st)
                    row[EV_FIRST_T] = st[ST_FIRST_T]
                    n_ev += 1
            running = ss[SS_RUNNING] == 1.0
            for p in range(n_par):
                z_p = ss[SS_Z + _first_param(sc) + p]
                out[row_par + p, k] = z_p * sc[SC_NOMINAL + p] if running else np.nan
            out[alpha_row0 + i, k] = ss[SS_ALPHA] if running else np.nan
            row_par += n_par
        for f in range(n_fused):
            num = 0.0
            den = 0.0
            for i in range(n_sub):
                if sub_st[i, SS_RUNNING] != 1.0:
                    continue
                for p in range(int(sub_cfg[i, SC_N_PARAMS])):
                    if sub_fuse[i, p] == f:
                        nom = sub_cfg[i, SC_NOMINAL + p]
                        q = _first_param(sub_cfg[i]) + p
                        var = sub_st[i, SS_P + q * MAX_DIM + q] * nom * nom
                        est = sub_st[i, SS_Z + q] * nom
                        num += est / var
                        den += 1.0 / var
            out[fused_row0 + f, k] = num / den if den > 0.0 else np.nan
        # --- health window
        if st[ST_WIN_COUNT] == 0.0:
            st[ST_WIN_T0] = tk
            st[ST_WIN_FAULT] = 0.0
            st[ST_WIN_MASK] = 0.0
            for ri in range(N_RES):
                st[ST_WIN_SUM2 + ri] = 0.0
                st[ST_WIN_N + ri] = 0.0
                st[ST_WIN_MAX + ri] = np.nan
        st[ST_WIN_COUNT] += 1.0
        if st[ST_FAULT] == 1.0:
            st[ST_WIN_FAULT] = 1.0
            st[ST_WIN_MASK] = _or_mask(st[ST_WIN_MASK], _mask(st))
        for ri in range(N_RES):
            if math.isfinite(r[ri]):
                st[ST_WIN_SUM2 + ri] += r[ri] * r[ri]
                st[ST_WIN_N + ri] += 1.0
                if st[ST_THR_READY] == 1.0:
                    ratio = abs(r[ri]) / st[ST_THR + ri]
                    if not ratio <= st[ST_WIN_MAX + ri]:
                        st[ST_WIN_MAX + ri] = ratio
        if st[ST_WIN_COUNT] >= health_n:
            close_health_window(st, tk, windows[n_wo])
            n_wo += 1
        for c in range(N_CHAN):
            st[ST_PREV_SMOOTH + c] = smooth[c]
        st[ST_T_LAST] = tk
    st[ST_POS] = pos
    return events[:n_ev].copy(), windows[:n_wo].copy(), 0


@njit(cache=True, nogil=True, error_model="numpy")
def close_health_window(st: FloatArray, t_end: float, row: FloatArray) -> None:
    """Write the open health window's row (``WIN_*``) ending at ``t_end`` and start a new one
    (the per-sample loop when a window is full; ``darr_fekf.step`` for the partial window of a
    run closed by ``end_of_run``)."""
    row[WIN_T0] = st[ST_WIN_T0]
    row[WIN_T1] = t_end
    row[WIN_N] = st[ST_WIN_COUNT]
    row[WIN_FAULT] = st[ST_WIN_FAULT]
    row[WIN_MASK] = st[ST_WIN_MASK]
    for ri in range(N_RES):
        n_l = st[ST_WIN_N + ri]
        row[WIN_RMS + ri] = math.sqrt(st[ST_WIN_SUM2 + ri] / n_l) if n_l > 0.0 else np.nan
        row[WIN_PEAK + ri] = st[ST_WIN_MAX + ri]
    st[ST_WIN_COUNT] = 0.0


@njit(cache=True, nogil=True, error_model="numpy")
def _first_param(sc: FloatArray) -> int:
    """Index of the first parameter in a subsystem's state vector (after the state, if any)."""
    return 0 if sc[SC_RELATION] == 1.0 else 1


@njit(cache=True, nogil=True, error_model="numpy")
def _mask(st: FloatArray) -> float:
    """The latched coherence vector as a bit mask (bit l: residual l + 1)."""
    m = 0.0
    for ri in range(N_RES):
        if st[ST_LATCH + ri] == 1.0:
            m += BITS[ri]
    return m


@njit(cache=True, nogil=True, error_model="numpy")
def _or_mask(a: float, b: float) -> float:
    return float(int(a) | int(b))
