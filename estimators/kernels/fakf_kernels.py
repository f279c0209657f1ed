"""Compiled per-sample loops of the feature-aided Kalman filter (FAKF).

Everything that runs once per sample lives here, compiled by numba; ``estimators.fakf`` only
packs the configuration and state into flat float64 vectors, calls :func:`fakf_batch` once per
batch and unpacks the few health windows and events it returns.

Flat layouts (indices are the module constants below):

* configuration vector ``cfg`` (``CFG_*``), built by ``estimators.fakf``;
* state vector ``st`` (``ST_*``) holding the filter, the model-only simulation, the lags, the
  identification accumulators (block at ``ST_ID``) and the health-window accumulators (Gram block
  at ``ST_WG`` plus ``ST_W_*`` sums). Counters are stored as floats (exact below 2**53).

A least-squares accumulator block (``ACC_LEN`` floats) holds the upper triangle of the 5x5 Gram
matrix ``sum phi phi^T`` (15), ``sum phi y`` (5), ``sum y^2``, ``sum I_k``, and the row count,
with ``phi_k = [-V_{k-1}, -V_{k-2}, I_k, I_{k-1}, I_{k-2}]`` and ``y_k = V_k`` (seed eq. 15).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]

# ----------------------------------------------------------------------------- layouts
N_COEF = 5
# upper-triangle index of (i, j), i <= j, row-major
_TRI = np.array(
    [
        [0, 1, 2, 3, 4],
        [1, 5, 6, 7, 8],
        [2, 6, 9, 10, 11],
        [3, 7, 10, 12, 13],
        [4, 8, 11, 13, 14],
    ],
    dtype=np.int64,
)
ACC_G = 0  # 15 upper-triangle entries
ACC_B = 15  # 5 entries of sum(phi * y)
ACC_YY = 20
ACC_SUM_I = 21
ACC_N = 22
ACC_LEN = 23

CFG_N_IDENT = 0
CFG_HEALTH_WINDOW = 1
CFG_Q = 2  # NaN: automatic
CFG_R = 3  # NaN: automatic
CFG_P0 = 4
CFG_COND_LIMIT = 5
CFG_MIN_CURRENT_STD = 6
CFG_FIXED = 7  # 1.0 when the coefficients are given
CFG_COEF = 8  # 5 fixed coefficients a0, a1, b0, b1, b2
CFG_MIN_ROWS = 13
CFG_RAIL_LO = 14  # lower voltage rail (V); NaN: none
CFG_RAIL_HI = 15  # upper voltage rail (V); NaN: none
CFG_IDLE_CLOSE = 16  # stream-time gap (s) that closes a segment; NaN: never
CFG_REIDENT = 17  # 1.0: re-identify when the prior loses to persistence
CFG_REIDENT_MARGIN = 18  # a window loses when prior RMS > (1 + margin) persistence RMS
CFG_REIDENT_WINDOWS = 19  # consecutive losing windows before re-identifying
CFG_MIN_SCORED = 20  # fewest paired samples for a persistence comparison
CFG_LEN = 21

ST_READY = 0  # 1.0 once a model is available
ST_COEF = 1  # 5 baseline coefficients
ST_Q = 6
ST_R = 7
ST_REF_RMS = 8  # reference scale of the innovations (identification residual RMS)
ST_X = 9  # 2: posterior state [V_k, V_{k-1}]
ST_P = 11  # 3: posterior covariance p00, p01, p11
ST_M = 14  # 2: model-only outputs m_{k}, m_{k-1}
ST_I_LAG = 16  # 2: raw currents I_{k-1}, I_{k-2} (may be NaN)
ST_V_LAG = 18  # 2: raw voltages V_{k-1}, V_{k-2} (may be NaN)
ST_IH_LAG = 20  # 2: held currents used as the filter input
ST_N_SEEN = 22
ST_ID_COUNT = 23  # samples seen in the current identification attempt
ST_LAST_FAIL = 24  # reason code of the last failed identification (0: none)
ST_W_COUNT = 25
ST_W_T0 = 26
ST_W_SUM_INNOV2 = 27
ST_W_N_INNOV = 28
ST_W_SUM_NIS = 29
ST_W_N_NIS_IN = 30
ST_W_SUM_ABS_ERR = 31
ST_W_SUM_SQ_ERR = 32
ST_W_N_ERR = 33
ST_W_SUM_ABS_MODEL = 34
ST_W_N_MODEL = 35
ST_ID = 36  # identification accumulator block
ST_WG = ST_ID + ACC_LEN  # health-window accumulator block
ST_LEN_V1 = ST_WG + ACC_LEN  # end of the version-1 layout; version 2 appends:
ST_BASE_COEF = ST_LEN_V1  # 5: reference model of coef_drift (the first identified)
ST_T_LAST = ST_BASE_COEF + 5  # time of the last sample (-inf before any)
ST_RESTART = ST_T_LAST + 1  # 1.0: the filter restarts on the next usable voltage
ST_V_PERSIST = ST_RESTART + 1  # last measured voltage of the segment (persistence prediction)
ST_W_SUM_PRIOR2_PAIRED = ST_V_PERSIST + 1  # window: sum of squared prior errors, paired
ST_W_SUM_PERSIST2 = ST_W_SUM_PRIOR2_PAIRED + 1  # window: sum of squared persistence errors
ST_W_N_PAIRED = ST_W_SUM_PERSIST2 + 1  # window: samples scored by both
ST_W_N_CENSORED = ST_W_N_PAIRED + 1  # window: samples at or beyond a rail
ST_LOSE_COUNT = ST_W_N_CENSORED + 1  # consecutive full windows the prior lost to persistence
ST_N_REIDENT = ST_LOSE_COUNT + 1  # re-identifications so far
ST_PREV_STATUS = ST_N_REIDENT + 1  # index in STATUSES of the last graded window (-1: none)
# The reference filter: the first identified model kept running after a re-identification
# (only then does it differ from the filter in use); the health consistency indicators come
# from it, so a new model cannot hide a change against the healthy start.
ST_XR = ST_PREV_STATUS + 1  # 2: reference filter posterior state
ST_PR = ST_XR + 2  # 3: reference filter covariance p00, p01, p11
ST_BASE_Q = ST_PR + 3  # q of the reference model
ST_BASE_R = ST_BASE_Q + 1  # r of the reference model
ST_LEN = ST_BASE_R + 1

# reasons an identification fails
FIT_OK = 0
FIT_TOO_FEW_ROWS = 1
FIT_LOW_CURRENT_STD = 2
FIT_ILL_CONDITIONED = 3
FIT_UNSTABLE = 4

# fit result vector: coefficients (5), residual RMS, condition number, max pole modulus,
# current std, rows, reason code
FIT_COEF = 0
FIT_RESID_RMS = 5
FIT_COND = 6
FIT_POLE = 7
FIT_I_STD = 8
FIT_ROWS = 9
FIT_REASON = 10
FIT_LEN = 11

# health-window output rows
WIN_T0 = 0
WIN_T1 = 1
WIN_N = 2
WIN_INNOV_RMS = 3
WIN_NIS_MEAN = 4
WIN_NIS_IN = 5
WIN_MAE = 6
WIN_RMSE = 7
WIN_MODEL_MAE = 8
WIN_DRIFT = 9
WIN_COEF = 10  # 5
WIN_READY = 15
WIN_REF_RMS = 16
WIN_N_INNOV = 17
WIN_LAST_FAIL = 18
WIN_PERSIST_RMS = 19  # persistence (repeat the last sample) RMS error, paired samples
WIN_PRIOR_RMS_PAIRED = 20  # prior RMS error on the same samples
WIN_N_PAIRED = 21
WIN_N_CENSORED = 22
WIN_GAIN = 23  # static gain of the window model (V/A)
WIN_POLE = 24  # dominant pole of the window model (signed if real, modulus if complex)
WIN_CLOSED_BY = 25  # CLOSE_* code
WIN_REIDENT = 26  # REID_* code
WIN_REIDENT_CODE = 27  # FIT_* reason of a refused re-identification
WIN_LOSE_COUNT = 28  # consecutive losing windows, this one included
WIN_REF_RESID_RMS = 29  # the reference model's one-step (equation-error) residual RMS
WIN_LEN = 30

# why a window was closed
CLOSE_FULL = 0.0
CLOSE_END_OF_RUN = 1.0
CLOSE_IDLE = 2.0
# what the persistence comparison did at a window's close
REID_NONE = 0.0
REID_DONE = 1.0
REID_REFUSED = 2.0
FIT_NOT_BETTER = 5  # refusal code: the window model does not beat persistence in-sample

# event output rows
EV_T = 0
EV_KIND = 1  # 1 identified, 2 identification failed
EV_FIT = 2  # FIT_LEN values
EV_Q = EV_FIT + FIT_LEN
EV_R = EV_Q + 1
EV_PRIOR_RMS = EV_R + 1  # re-identification events: the losing window's prior RMS
EV_PERSIST_RMS = EV_PRIOR_RMS + 1  # and its persistence RMS
EV_LEN = EV_PERSIST_RMS + 1
EV_IDENTIFIED = 1.0
EV_FAILED = 2.0
EV_REIDENTIFIED = 3.0
EV_REIDENT_FAILED = 4.0

# chi-square(1) central 95 % interval of the normalized innovation squared
NIS_LO = 0.0009820691171752583
NIS_HI = 5.023886187314888


# ----------------------------------------------------------------------------- least squares
@njit(cache=True, nogil=True, error_model="numpy")
def acc_add_row(
    acc: FloatArray,
    v1: float,
    v2: float,
    i0: float,
    i1: float,
    i2: float,
    y: float,
) -> None:
    """Add one regression row ``phi = [-v1, -v2, i0, i1, i2]``, target ``y`` (eq. 15), to the
    accumulator block ``acc`` (``ACC_LEN`` floats, e.g. a view of a state vector)."""
    p0 = -v1
    p1 = -v2
    acc[0] += p0 * p0
    acc[1] += p0 * p1
    acc[2] += p0 * i0
    acc[3] += p0 * i1
    acc[4] += p0 * i2
    acc[5] += p1 * p1
    acc[6] += p1 * i0
    acc[7] += p1 * i1
    acc[8] += p1 * i2
    acc[9] += i0 * i0
    acc[10] += i0 * i1
    acc[11] += i0 * i2
    acc[12] += i1 * i1
    acc[13] += i1 * i2
    acc[14] += i2 * i2
    acc[15] += p0 * y
    acc[16] += p1 * y
    acc[17] += i0 * y
    acc[18] += i1 * y
    acc[19] += i2 * y
    acc[20] += y * y
    acc[21] += i0
    acc[22] += 1.0


@njit(cache=True, nogil=True, error_model="numpy")
def acc_accumulate(acc: FloatArray, current: FloatArray, voltage: FloatArray) -> None:
    """Accumulate the rows k = 2..n-1 of two whole arrays into ``acc`` (rows with a NaN skipped)."""
    for k in range(2, current.shape[0]):
        v1 = voltage[k - 1]
        v2 = voltage[k - 2]
        i0 = current[k]
        i1 = current[k - 1]
        i2 = current[k - 2]
        y = voltage[k]
        if (
            math.isfinite(v1)
            and math.isfinite(v2)
            and math.isfinite(i0)
            and math.isfinite(i1)
            and math.isfinite(i2)
            and math.isfinite(y)
        ):
            acc_add_row(acc, v1, v2, i0, i1, i2, y)


@njit(cache=True, nogil=True, error_model="numpy")
def max_pole_modulus(a0: float, a1: float) -> float:
    """Largest |z| with z^2 + a0 z + a1 = 0 (poles of 1 / (1 + a0 z^-1 + a1 z^-2))."""
    disc = a0 * a0 - 4.0 * a1
    if disc >= 0.0:
        s = math.sqrt(disc)
        return max(abs(-a0 + s), abs(-a0 - s)) * 0.5
    return math.sqrt(a1)  # complex pair: |z|^2 = a1


@njit(cache=True, nogil=True, error_model="numpy")
def acc_solve(
    acc: FloatArray, cond_limit: float, min_current_std: float, min_rows: float
) -> FloatArray:
    """Least-squares coefficients from an accumulator block, with the checks of the fit.

    Solves ``G theta = b`` for ``theta = [a0, a1, b0, b1, b2]`` after scaling ``G`` to unit
    diagonal (``C = D^-1 G D^-1``); the condition number reported and checked is that of ``C``,
    so it measures collinearity of the regressors, not their units.

    Returns:
        float64 vector of length ``FIT_LEN``; ``FIT_REASON`` is ``FIT_OK`` or the failure code.
    """
    out = np.full(FIT_LEN, np.nan)
    n = acc[ACC_N]
    out[FIT_ROWS] = n
    if n < min_rows:
        out[FIT_REASON] = FIT_TOO_FEW_ROWS
        return out
    mean_i = acc[ACC_SUM_I] / n
    var_i = acc[ACC_G + _TRI[2, 2]] / n - mean_i * mean_i
    i_std = math.sqrt(max(var_i, 0.0))
    out[FIT_I_STD] = i_std
    if i_std < min_current_std:
        out[FIT_REASON] = FIT_LOW_CURRENT_STD
        return out
    d = np.empty(N_COEF)
    for i in range(N_COEF):
        gii = acc[ACC_G + _TRI[i, i]]
        if not gii > 0.0:
            out[FIT_COND] = np.inf
            out[FIT_REASON] = FIT_ILL_CONDITIONED
            return out
        d[i] = math.sqrt(gii)
    c = np.empty((N_COEF, N_COEF))
    for i in range(N_COEF):
        for j in range(N_COEF):
            c[i, j] = acc[ACC_G + _TRI[i, j]] / (d[i] * d[j])
    eig = np.linalg.eigvalsh(c)
    cond = np.inf if eig[0] <= 0.0 else eig[N_COEF - 1] / eig[0]
    out[FIT_COND] = cond
    if not cond <= cond_limit:
        out[FIT_REASON] = FIT_ILL_CONDITIONED
        return out
    # Cholesky solve of C z = D^-1 b (C is symmetric positive definite here), theta = D^-1 z
    low = np.zeros((N_COEF, N_COEF))
    for j in range(N_COEF):
        s = c[j, j]
        for m in range(j):
            s -= low[j, m] * low[j, m]
        ljj = math.sqrt(s)
        low[j, j] = ljj
        for i in range(j + 1, N_COEF):
            t = c[i, j]
            for m in range(j):
                t -= low[i, m] * low[j, m]
            low[i, j] = t / ljj
    w = np.empty(N_COEF)
    for i in range(N_COEF):
        t = acc[ACC_B + i] / d[i]
        for m in range(i):
            t -= low[i, m] * w[m]
        w[i] = t / low[i, i]
    z = np.empty(N_COEF)
    for i in range(N_COEF - 1, -1, -1):
        t = w[i]
        for m in range(i + 1, N_COEF):
            t -= low[m, i] * z[m]
        z[i] = t / low[i, i]
    theta = z / d
    for i in range(N_COEF):
        out[FIT_COEF + i] = theta[i]
    out[FIT_RESID_RMS] = residual_rms(acc, theta)
    pole = max_pole_modulus(theta[0], theta[1])
    out[FIT_POLE] = pole
    out[FIT_REASON] = FIT_UNSTABLE if not pole < 1.0 else FIT_OK
    return out


@njit(cache=True, nogil=True, error_model="numpy")
def residual_rms(acc: FloatArray, theta: FloatArray) -> float:
    """RMS of the one-step residual ``V_k - phi_k^T theta`` over the rows of an accumulator
    block, from its sums alone: ``SSE = y'y - 2 theta'b + theta' G theta`` (NaN without rows)."""
    n = acc[ACC_N]
    if not n > 0.0:
        return np.nan
    sse = acc[ACC_YY]
    for i in range(N_COEF):
        sse -= 2.0 * theta[i] * acc[ACC_B + i]
        for j in range(N_COEF):
            sse += theta[i] * acc[ACC_G + _TRI[i, j]] * theta[j]
    return math.sqrt(max(sse, 0.0) / n)


@njit(cache=True, nogil=True, error_model="numpy")
def prediction_drift(acc: FloatArray, theta_w: FloatArray, theta_b: FloatArray) -> float:
    """RMS difference of two models' one-step predictions over a window, relative to the RMS of
    the window's voltage: ``sqrt(d' G d / n) / sqrt(y'y / n)``, ``d = theta_w - theta_b``.

    Computed from the window's Gram matrix alone, so it needs no sample buffer.
    """
    n = acc[ACC_N]
    yy = acc[ACC_YY]
    if not (n > 0.0 and yy > 0.0):
        return np.nan
    quad = 0.0
    for i in range(N_COEF):
        di = theta_w[i] - theta_b[i]
        for j in range(N_COEF):
            quad += di * acc[ACC_G + _TRI[i, j]] * (theta_w[j] - theta_b[j])
    return math.sqrt(max(quad, 0.0) / yy)


# ----------------------------------------------------------------------------- filter
@njit(cache=True, nogil=True, error_model="numpy")
def _same(x: float, y: float) -> bool:
    """Bitwise equality of two floats that are not NaN (``==`` plus the sign of zero)."""
    return x == y and math.copysign(1.0, x) == math.copysign(1.0, y)


@njit(cache=True, nogil=True, error_model="numpy")
def _start_model(st: FloatArray, theta: FloatArray, q: float, r: float, p0: float) -> None:
    """Make a model available: coefficients, noise levels, x and model-only history from the
    last two measured voltages (0 where missing), P = p0 I."""
    for i in range(N_COEF):
        st[ST_COEF + i] = theta[i]
    st[ST_Q] = q
    st[ST_R] = r
    v1 = st[ST_V_LAG]
    v2 = st[ST_V_LAG + 1]
    v1 = v1 if math.isfinite(v1) else 0.0
    v2 = v2 if math.isfinite(v2) else 0.0
    st[ST_X] = v1
    st[ST_X + 1] = v2
    st[ST_M] = v1
    st[ST_M + 1] = v2
    st[ST_P] = p0
    st[ST_P + 1] = 0.0
    st[ST_P + 2] = p0
    st[ST_READY] = 1.0

    st[ST_RESTART] = 0.0 if math.isfinite(st[ST_V_LAG]) else 1.0


@njit(cache=True, nogil=True, error_model="numpy")
def _clamp(v: float, lo: float, hi: float) -> float:
    """``v`` limited to the rails ``[lo, hi]``; a NaN rail is no limit (comparisons with NaN are
    false), so without rails this returns ``v`` bit for bit."""
    if v < lo:
        return lo
    if v > hi:
        return hi
    return v


@njit(cache=True, nogil=True, error_model="numpy")
def static_gain(theta: FloatArray) -> float:
    """DC gain of eq. 15, ``(b0 + b1 + b2) / (1 + a0 + a1)`` (V/A): V(z)/I(z) at z = 1."""
    den = 1.0 + theta[0] + theta[1]
    if den == 0.0:
        return np.nan
    gain: float = (theta[2] + theta[3] + theta[4]) / den
    return gain


@njit(cache=True, nogil=True, error_model="numpy")
def dominant_pole(a0: float, a1: float) -> float:
    """The pole of ``1 + a0 z^-1 + a1 z^-2`` of largest modulus: its signed value when the poles
    are real, the common modulus ``sqrt(a1)`` when they are a complex pair."""
    disc = a0 * a0 - 4.0 * a1
    if disc >= 0.0:
        s = math.sqrt(disc)
        p1 = 0.5 * (-a0 + s)
        p2 = 0.5 * (-a0 - s)
        return p1 if abs(p1) >= abs(p2) else p2
    return math.sqrt(a1)


@njit(cache=True, nogil=True, error_model="numpy")
def _reset_window(st: FloatArray) -> None:
    for i in range(ST_W_COUNT, ST_W_N_MODEL + 1):
        st[i] = 0.0
    for i in range(ACC_LEN):
        st[ST_WG + i] = 0.0
    st[ST_W_SUM_PRIOR2_PAIRED] = 0.0
    st[ST_W_SUM_PERSIST2] = 0.0
    st[ST_W_N_PAIRED] = 0.0
    st[ST_W_N_CENSORED] = 0.0


@njit(cache=True, nogil=True, error_model="numpy")
def _close_window(
    st: FloatArray,
    cfg: FloatArray,
    t_end: float,
    closed_by: float,
    row: FloatArray,
    ev: FloatArray,
) -> bool:
    """Write the indicators of the window ending at ``t_end`` into ``row`` (NaN = undefined),
    compare the prior with persistence and re-identify when the rule says so, then reset the
    window accumulators.

    Re-identification rule (full windows only, identified models only): a window *loses* when
    its paired prior RMS exceeds ``(1 + margin)`` times the persistence RMS over at least
    ``CFG_MIN_SCORED`` paired samples; a window that does not lose resets the count. After
    ``CFG_REIDENT_WINDOWS`` consecutive losing windows the model identified on the window just
    closed (its Gram block, eq. 15 by least squares) replaces the model in use, if the fit is
    accepted and its in-sample one-step residual beats persistence; otherwise the refusal is
    reported and the next losing window tries again.

    Returns:
        True when ``ev`` holds an event (re-identified or refused).
    """
    row[:] = np.nan
    row[WIN_T0] = st[ST_W_T0]
    row[WIN_T1] = t_end
    row[WIN_N] = st[ST_W_COUNT]
    row[WIN_READY] = st[ST_READY]
    row[WIN_REF_RMS] = st[ST_REF_RMS]
    row[WIN_LAST_FAIL] = st[ST_LAST_FAIL]
    row[WIN_CLOSED_BY] = closed_by
    row[WIN_REIDENT] = REID_NONE
    row[WIN_N_CENSORED] = st[ST_W_N_CENSORED]
    n_innov = st[ST_W_N_INNOV]
    row[WIN_N_INNOV] = n_innov
    if n_innov > 0.0:
        row[WIN_INNOV_RMS] = math.sqrt(st[ST_W_SUM_INNOV2] / n_innov)
        row[WIN_NIS_MEAN] = st[ST_W_SUM_NIS] / n_innov
        row[WIN_NIS_IN] = st[ST_W_N_NIS_IN] / n_innov
    n_err = st[ST_W_N_ERR]
    if n_err > 0.0:
        row[WIN_MAE] = st[ST_W_SUM_ABS_ERR] / n_err
        row[WIN_RMSE] = math.sqrt(st[ST_W_SUM_SQ_ERR] / n_err)
    if st[ST_W_N_MODEL] > 0.0:
        row[WIN_MODEL_MAE] = st[ST_W_SUM_ABS_MODEL] / st[ST_W_N_MODEL]
    n_paired = st[ST_W_N_PAIRED]
    row[WIN_N_PAIRED] = n_paired
    persist_rms = np.nan
    prior_rms = np.nan
    if n_paired > 0.0:
        persist_rms = math.sqrt(st[ST_W_SUM_PERSIST2] / n_paired)
        prior_rms = math.sqrt(st[ST_W_SUM_PRIOR2_PAIRED] / n_paired)
        row[WIN_PERSIST_RMS] = persist_rms
        row[WIN_PRIOR_RMS_PAIRED] = prior_rms
    wacc = st[ST_WG : ST_WG + ACC_LEN]
    fit = acc_solve(wacc, cfg[CFG_COND_LIMIT], cfg[CFG_MIN_CURRENT_STD], cfg[CFG_MIN_ROWS])
    theta_w = fit[FIT_COEF : FIT_COEF + N_COEF]
    # Window coefficients are reported when the window's data support a fit, even if its
    # poles are outside the unit circle: an unstable window model is itself a sign of change.
    if fit[FIT_REASON] == FIT_OK or fit[FIT_REASON] == FIT_UNSTABLE:
        for i in range(N_COEF):
            row[WIN_COEF + i] = theta_w[i]
        row[WIN_GAIN] = static_gain(theta_w)
        row[WIN_POLE] = dominant_pole(theta_w[0], theta_w[1])
        if st[ST_READY] == 1.0:
            row[WIN_DRIFT] = prediction_drift(
                wacc, theta_w, st[ST_BASE_COEF : ST_BASE_COEF + N_COEF]
            )
    if st[ST_READY] == 1.0 and st[ST_WG + ACC_N] >= cfg[CFG_MIN_SCORED]:
        # how well the reference (first) model still predicts, whatever model is in use
        row[WIN_REF_RESID_RMS] = residual_rms(wacc, st[ST_BASE_COEF : ST_BASE_COEF + N_COEF])
    has_event = False
    judged = (
        st[ST_READY] == 1.0
        and closed_by == CLOSE_FULL
        and n_paired >= cfg[CFG_MIN_SCORED]
        and persist_rms > 0.0
    )
    if judged:
        if prior_rms > (1.0 + cfg[CFG_REIDENT_MARGIN]) * persist_rms:
            st[ST_LOSE_COUNT] += 1.0
        else:
            st[ST_LOSE_COUNT] = 0.0
        row[WIN_LOSE_COUNT] = st[ST_LOSE_COUNT]
        if (
            cfg[CFG_REIDENT] == 1.0
            and cfg[CFG_FIXED] == 0.0
            and st[ST_LOSE_COUNT] >= cfg[CFG_REIDENT_WINDOWS]
        ):
            has_event = True
            ev[:] = np.nan
            ev[EV_T] = t_end
            for j in range(FIT_LEN):
                ev[EV_FIT + j] = fit[j]
            ev[EV_PRIOR_RMS] = prior_rms
            ev[EV_PERSIST_RMS] = persist_rms
            code = fit[FIT_REASON]
            if code == FIT_OK and not fit[FIT_RESID_RMS] < persist_rms:
                code = FIT_NOT_BETTER
            if code == FIT_OK:
                var = fit[FIT_RESID_RMS] * fit[FIT_RESID_RMS]
                q_new = cfg[CFG_Q] if math.isfinite(cfg[CFG_Q]) else 0.5 * var
                r_new = cfg[CFG_R] if math.isfinite(cfg[CFG_R]) else 0.5 * var
                for i in range(N_COEF):
                    st[ST_COEF + i] = theta_w[i]
                st[ST_Q] = q_new
                st[ST_R] = r_new
                # ST_REF_RMS stays the reference model's residual (innovation_rms_ratio comes
                # from the reference filter); the new fit's residual is in the event
                st[ST_N_REIDENT] += 1.0
                st[ST_LOSE_COUNT] = 0.0
                ev[EV_KIND] = EV_REIDENTIFIED
                ev[EV_Q] = q_new
                ev[EV_R] = r_new
                row[WIN_REIDENT] = REID_DONE
            else:
                ev[EV_KIND] = EV_REIDENT_FAILED
                ev[EV_FIT + FIT_REASON] = code
                row[WIN_REIDENT] = REID_REFUSED
                row[WIN_REIDENT_CODE] = code
    _reset_window(st)
    return has_event


@njit(cache=True, nogil=True, error_model="numpy")
def _reference_step(
    st: FloatArray, ih: float, ih1: float, ih2: float, z: float, lo: float, hi: float
) -> tuple[float, float]:
    """One step of the reference filter (the first identified model, kept running after a
    re-identification): the recursion of :func:`fakf_batch` on ``st[ST_XR]``, ``st[ST_PR]`` with
    the reference coefficients and noise levels; ``z`` is the measured (or rail) voltage, NaN
    for predict-only. Returns (innovation or NaN, S)."""
    f0 = -st[ST_BASE_COEF]
    f1 = -st[ST_BASE_COEF + 1]
    u = st[ST_BASE_COEF + 2] * ih + st[ST_BASE_COEF + 3] * ih1 + st[ST_BASE_COEF + 4] * ih2
    q = st[ST_BASE_Q]
    r = st[ST_BASE_R]
    x0 = st[ST_XR]
    x1 = st[ST_XR + 1]
    p00 = st[ST_PR]
    p01 = st[ST_PR + 1]
    p11 = st[ST_PR + 2]
    xp0 = _clamp(f0 * x0 + f1 * x1 + u, lo, hi)
    xp1 = x0
    fp0 = f0 * p00 + f1 * p01
    fp1 = f0 * p01 + f1 * p11
    pp00 = fp0 * f0 + fp1 * f1 + q
    pp01 = fp0
    pp11 = p00
    s = pp00 + r
    if not math.isfinite(z):
        st[ST_XR] = xp0
        st[ST_XR + 1] = xp1
        st[ST_PR] = pp00
        st[ST_PR + 1] = pp01
        st[ST_PR + 2] = pp11
        return np.nan, s
    e = z - xp0
    k0 = pp00 / s
    k1 = pp01 / s
    c0 = 1.0 - k0
    st[ST_PR] = c0 * c0 * pp00 + r * k0 * k0
    st[ST_PR + 1] = c0 * (pp01 - k1 * pp00) + r * k0 * k1
    st[ST_PR + 2] = k1 * k1 * pp00 - 2.0 * k1 * pp01 + pp11 + r * k1 * k1
    st[ST_XR] = _clamp(xp0 + k0 * e, lo, hi)
    st[ST_XR + 1] = _clamp(xp1 + k1 * e, lo, hi)
    return e, s


def fakf_batch(
    cfg: FloatArray,
    st: FloatArray,
    t: FloatArray,
    current: FloatArray,
    voltage: FloatArray,
    end_of_run: bool = False,
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray, FloatArray, int]:
    """Run the FAKF over one batch, updating ``st`` in place.

    Per sample k, once a model is available (seed eqs. 7-11 with the eq. 15 model, eq. 16):

        u_k   = b0 I_k + b1 I_{k-1} + b2 I_{k-2}
        x-_k  = clamp(F x_{k-1} + [u_k, 0]),  F = [[-a0, -a1], [1, 0]]
        P-_k  = F P_{k-1} F^T + diag(q, 0)
        S_k   = P-_k[0, 0] + r,  e_k = V_k - x-_k[0],  K_k = P-_k[:, 0] / S_k
        x_k   = clamp(x-_k + K_k e_k)
        P_k   = (I - K H) P-_k (I - K H)^T + r K K^T      (Joseph form, as filterpy)

    ``clamp`` limits both state components to the configured rails (no-op without rails): the
    estimate is projected onto the physical range. A NaN voltage skips the update (x_k = x-_k,
    P_k = P-_k); a voltage at or beyond a rail is censored: it is not scored and enters the
    update as a pseudo-measurement at the rail value (the voltage is at least the rail, and the
    rail is the end of the physical range). A NaN current is replaced by the last valid current
    (0 before any). The model-only output is the same recursion without the update, clamped.

    A segment closes at the end of a batch marked ``end_of_run`` and before a sample that
    follows the previous one by more than the idle gap: the partial health window is closed,
    the lags are cleared (no regression row spans two segments) and the filter restarts from
    the first usable voltage of the next segment (x = [V, V], P = p0 I).

    Returns:
        (voltage_estimate, voltage_model, innovation, innovation_var, windows, events, status)
        where windows/events are row arrays (WIN_LEN / EV_LEN columns) and status is 0, or -1
        when the times inside the batch are not strictly increasing (the state is then left
        untouched; the caller checks the first time against the state's last one). The four
        per-sample outputs are rows of one (4, n) block allocated here by numpy, whose large
        allocations ask for transparent huge pages: far fewer page faults than four arrays
        allocated inside compiled code.
    """
    out = np.empty((4, t.shape[0]))
    windows, events, status = _fakf_kernel(cfg, st, t, current, voltage, end_of_run, out)
    return out[0], out[1], out[2], out[3], windows, events, status


@njit(cache=True, nogil=True, error_model="numpy")
def _fakf_kernel(
    cfg: FloatArray,
    st: FloatArray,
    t: FloatArray,
    current: FloatArray,
    voltage: FloatArray,
    end_of_run: bool,
    out: FloatArray,
) -> tuple[FloatArray, FloatArray, int]:
    """The compiled loop of :func:`fakf_batch`; fills ``out`` (every entry) and ``st``."""
    n = t.shape[0]
    # every entry of ``out`` is written exactly once below (NaN where undefined)
    est = out[0]
    mod = out[1]
    inn = out[2]
    svar = out[3]
    hw = cfg[CFG_HEALTH_WINDOW]
    n_ident = cfg[CFG_N_IDENT]
    idle = cfg[CFG_IDLE_CLOSE]
    lo = cfg[CFG_RAIL_LO]
    hi = cfg[CFG_RAIL_HI]
    for k in range(1, n):
        if not t[k] > t[k - 1]:
            out[:] = np.nan
            return np.empty((0, WIN_LEN)), np.empty((0, EV_LEN)), -1
    n_gaps = 0
    if math.isfinite(idle) and n > 0:
        if math.isfinite(st[ST_T_LAST]) and t[0] - st[ST_T_LAST] > idle:
            n_gaps += 1
        for k in range(1, n):
            if t[k] - t[k - 1] > idle:
                n_gaps += 1
    n_win_max = int(n // hw) + n_gaps + 2
    windows = np.empty((n_win_max, WIN_LEN))
    n_ev_max = (int(n // n_ident) + 1 if cfg[CFG_FIXED] == 0.0 else 0) + n_win_max
    events = np.empty((n_ev_max, EV_LEN))

    n_win = 0
    n_ev = 0
    fixed = cfg[CFG_FIXED] == 1.0
    p0 = cfg[CFG_P0]
    # Locals for the hot loop; written back at the end (and around rare events).
    ready = st[ST_READY] == 1.0
    a0 = st[ST_COEF]
    a1 = st[ST_COEF + 1]
    b0 = st[ST_COEF + 2]
    b1 = st[ST_COEF + 3]
    b2 = st[ST_COEF + 4]
    q = st[ST_Q]
    r = st[ST_R]
    x0 = st[ST_X]
    x1 = st[ST_X + 1]
    p00 = st[ST_P]
    p01 = st[ST_P + 1]
    p11 = st[ST_P + 2]
    f0 = -a0
    f1 = -a1
    # covariance-recursion values carried between samples (see the fixed point below)
    p_fixed = False
    pp00 = pp01 = pp11 = s = inv_s = k0 = k1 = 0.0
    m0 = st[ST_M]
    m1 = st[ST_M + 1]
    i1 = st[ST_I_LAG]
    i2 = st[ST_I_LAG + 1]
    v1 = st[ST_V_LAG]
    v2 = st[ST_V_LAG + 1]
    ih1 = st[ST_IH_LAG]
    ih2 = st[ST_IH_LAG + 1]
    restart = st[ST_RESTART] == 1.0
    shadow = st[ST_N_REIDENT] > 0.0  # the reference filter runs apart from the one in use
    v_persist = st[ST_V_PERSIST]
    t_last = st[ST_T_LAST]
    id_count = st[ST_ID_COUNT]
    iacc = st[ST_ID : ST_ID + ACC_LEN].copy()
    wacc = st[ST_WG : ST_WG + ACC_LEN]  # a view: rows go into the state itself

    for k in range(n):
        tk = t[k]
        # --- a gap longer than the idle time closes the segment before this sample
        if tk - t_last > idle and math.isfinite(t_last):
            if st[ST_W_COUNT] > 0.0:
                if _close_window(st, cfg, t_last, CLOSE_IDLE, windows[n_win], events[n_ev]):
                    n_ev += 1
                n_win += 1
            i1 = i2 = v1 = v2 = v_persist = np.nan
            restart = True
        t_last = tk
        ik = current[k]
        vk = voltage[k]
        censored = vk <= lo or vk >= hi
        usable = math.isfinite(vk) and not censored
        vreg = vk if usable else np.nan
        if st[ST_W_COUNT] == 0.0:
            st[ST_W_T0] = tk
        if censored:
            st[ST_W_N_CENSORED] += 1.0
        # --- least-squares rows (identification and health window), eq. 15; a censored
        # voltage leaves the rows that contain it out, as a missing one does
        if (
            math.isfinite(ik)
            and usable
            and math.isfinite(i1)
            and math.isfinite(i2)
            and math.isfinite(v1)
            and math.isfinite(v2)
        ):
            acc_add_row(wacc, v1, v2, ik, i1, i2, vk)
            if not ready:
                acc_add_row(iacc, v1, v2, ik, i1, i2, vk)
        ih = ik if math.isfinite(ik) else ih1
        # --- filter, eqs. 7-11 and 16
        if ready and restart:
            # first usable voltage of a segment: start the filter on it, score nothing
            if usable or censored:
                v0 = _clamp(vk, lo, hi)
                x0 = x1 = m0 = m1 = v0
                p00 = p11 = p0
                p01 = 0.0
                p_fixed = False
                restart = False
                ih1 = ih2 = ih
                est[k] = v0
                mod[k] = v0
                if shadow:
                    st[ST_XR] = st[ST_XR + 1] = v0
                    st[ST_PR] = st[ST_PR + 2] = p0
                    st[ST_PR + 1] = 0.0
            else:
                est[k] = np.nan
                mod[k] = np.nan
            inn[k] = np.nan
            svar[k] = np.nan
        elif ready:
            u = b0 * ih + b1 * ih1 + b2 * ih2
            xp0 = _clamp(f0 * x0 + f1 * x1 + u, lo, hi)
            xp1 = x0
            if not p_fixed:
                fp0 = f0 * p00 + f1 * p01
                fp1 = f0 * p01 + f1 * p11
                pp00 = fp0 * f0 + fp1 * f1 + q
                pp01 = fp0
                pp11 = p00
                s = pp00 + r
                inv_s = 1.0 / s  # as filterpy: K = P H' S^-1
            svar[k] = s
            mk = _clamp(f0 * m0 + f1 * m1 + u, lo, hi)
            m1 = m0
            m0 = mk
            mod[k] = mk
            if usable or censored:
                # a censored sample updates with the rail value (pseudo-measurement)
                z = vk if usable else _clamp(vk, lo, hi)
                e = z - xp0
                if not p_fixed:
                    k0 = pp00 * inv_s
                    k1 = pp01 * inv_s
                    c0 = 1.0 - k0
                    n00 = c0 * c0 * pp00 + r * k0 * k0
                    n01 = c0 * (pp01 - k1 * pp00) + r * k0 * k1
                    n11 = k1 * k1 * pp00 - 2.0 * k1 * pp01 + pp11 + r * k1 * k1
                    # A bitwise 1-step fixed point of the covariance recursion: every later
                    # update maps P to itself, so P-, S and K are reused until a skipped update.
                    p_fixed = _same(n00, p00) and _same(n01, p01) and _same(n11, p11)
                    p00 = n00
                    p01 = n01
                    p11 = n11
                x0 = _clamp(xp0 + k0 * e, lo, hi)
                x1 = _clamp(xp1 + k1 * e, lo, hi)
                est[k] = x0
                # consistency statistics: of the reference filter once it runs apart
                e_ref = e
                nis = e * e * inv_s
                if shadow:
                    e_ref, s_ref = _reference_step(st, ih, ih1, ih2, z, lo, hi)
                    nis = e_ref * e_ref / s_ref
                if usable:
                    inn[k] = e
                    st[ST_W_SUM_INNOV2] += e_ref * e_ref
                    st[ST_W_SUM_NIS] += nis
                    st[ST_W_N_INNOV] += 1.0
                    if nis >= NIS_LO and nis <= NIS_HI:
                        st[ST_W_N_NIS_IN] += 1.0
                    err = x0 - vk
                    st[ST_W_SUM_ABS_ERR] += abs(err)
                    st[ST_W_SUM_SQ_ERR] += err * err
                    st[ST_W_N_ERR] += 1.0
                    st[ST_W_SUM_ABS_MODEL] += abs(mk - vk)
                    st[ST_W_N_MODEL] += 1.0
                    if math.isfinite(v_persist):
                        # naive baseline: repeat the last measured sample
                        dp = vk - v_persist
                        st[ST_W_SUM_PRIOR2_PAIRED] += e * e
                        st[ST_W_SUM_PERSIST2] += dp * dp
                        st[ST_W_N_PAIRED] += 1.0
                else:
                    inn[k] = np.nan
            else:
                x0 = xp0
                x1 = xp1
                p00 = pp00
                p01 = pp01
                p11 = pp11
                p_fixed = False
                inn[k] = np.nan
                est[k] = x0
                if shadow:
                    _reference_step(st, ih, ih1, ih2, np.nan, lo, hi)
        else:
            est[k] = np.nan
            mod[k] = np.nan
            inn[k] = np.nan
            svar[k] = np.nan
        # --- lags
        i2 = i1
        i1 = ik
        v2 = v1
        v1 = vreg
        ih2 = ih1
        ih1 = ih
        if math.isfinite(vk):
            v_persist = vk
        # --- identification window complete?
        if not ready and not fixed:
            id_count += 1.0
            if id_count >= n_ident:
                fit = acc_solve(
                    iacc, cfg[CFG_COND_LIMIT], cfg[CFG_MIN_CURRENT_STD], cfg[CFG_MIN_ROWS]
                )
                ev = events[n_ev]
                ev[:] = np.nan
                ev[EV_T] = tk
                for j in range(FIT_LEN):
                    ev[EV_FIT + j] = fit[j]
                n_ev += 1
                if fit[FIT_REASON] == FIT_OK:
                    var = fit[FIT_RESID_RMS] * fit[FIT_RESID_RMS]
                    # automatic noise levels: half the one-step residual variance each
                    q_new = cfg[CFG_Q] if math.isfinite(cfg[CFG_Q]) else 0.5 * var
                    r_new = cfg[CFG_R] if math.isfinite(cfg[CFG_R]) else 0.5 * var
                    st[ST_V_LAG] = v1
                    st[ST_V_LAG + 1] = v2
                    _start_model(st, fit[FIT_COEF : FIT_COEF + N_COEF], q_new, r_new, p0)
                    for j in range(N_COEF):
                        st[ST_BASE_COEF + j] = fit[FIT_COEF + j]
                    st[ST_REF_RMS] = fit[FIT_RESID_RMS]
                    st[ST_BASE_Q] = q_new
                    st[ST_BASE_R] = r_new
                    st[ST_LAST_FAIL] = 0.0
                    ev[EV_KIND] = EV_IDENTIFIED
                    ev[EV_Q] = q_new
                    ev[EV_R] = r_new
                    ready = True
                    a0 = st[ST_COEF]
                    a1 = st[ST_COEF + 1]
                    f0 = -a0
                    f1 = -a1
                    p_fixed = False
                    b0 = st[ST_COEF + 2]
                    b1 = st[ST_COEF + 3]
                    b2 = st[ST_COEF + 4]
                    q = q_new
                    r = r_new
                    x0 = _clamp(st[ST_X], lo, hi)
                    x1 = _clamp(st[ST_X + 1], lo, hi)
                    p00 = st[ST_P]
                    p01 = st[ST_P + 1]
                    p11 = st[ST_P + 2]
                    m0 = x0
                    m1 = x1
                    restart = st[ST_RESTART] == 1.0
                else:
                    ev[EV_KIND] = EV_FAILED
                    st[ST_LAST_FAIL] = fit[FIT_REASON]
                id_count = 0.0
                iacc[:] = 0.0
        # --- health window complete?
        st[ST_W_COUNT] += 1.0
        if st[ST_W_COUNT] >= hw:
            if _close_window(st, cfg, tk, CLOSE_FULL, windows[n_win], events[n_ev]):
                n_ev += 1
                if events[n_ev - 1, EV_KIND] == EV_REIDENTIFIED:
                    if not shadow:
                        # the reference filter starts from the filter as it is now
                        st[ST_XR] = x0
                        st[ST_XR + 1] = x1
                        st[ST_PR] = p00
                        st[ST_PR + 1] = p01
                        st[ST_PR + 2] = p11
                        shadow = True
                    a0 = st[ST_COEF]
                    a1 = st[ST_COEF + 1]
                    f0 = -a0
                    f1 = -a1
                    b0 = st[ST_COEF + 2]
                    b1 = st[ST_COEF + 3]
                    b2 = st[ST_COEF + 4]
                    q = st[ST_Q]
                    r = st[ST_R]
                    p_fixed = False
            n_win += 1

    if end_of_run:
        if st[ST_W_COUNT] > 0.0:
            if _close_window(st, cfg, t_last, CLOSE_END_OF_RUN, windows[n_win], events[n_ev]):
                n_ev += 1
            n_win += 1
        i1 = i2 = v1 = v2 = v_persist = np.nan
        restart = True

    st[ST_READY] = 1.0 if ready else 0.0
    st[ST_X] = x0
    st[ST_X + 1] = x1
    st[ST_P] = p00
    st[ST_P + 1] = p01
    st[ST_P + 2] = p11
    st[ST_M] = m0
    st[ST_M + 1] = m1
    st[ST_I_LAG] = i1
    st[ST_I_LAG + 1] = i2
    st[ST_V_LAG] = v1
    st[ST_V_LAG + 1] = v2
    st[ST_IH_LAG] = ih1
    st[ST_IH_LAG + 1] = ih2
    st[ST_RESTART] = 1.0 if restart else 0.0
    st[ST_V_PERSIST] = v_persist
    st[ST_T_LAST] = t_last
    st[ST_N_SEEN] += n
    st[ST_ID_COUNT] = id_count
    st[ST_ID : ST_ID + ACC_LEN] = iacc
    return windows[:n_win], events[:n_ev], 0
