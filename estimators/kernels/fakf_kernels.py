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
CFG_LEN = 14

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
ST_LEN = ST_WG + ACC_LEN

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
WIN_LEN = 19

# event output rows
EV_T = 0
EV_KIND = 1  # 1 identified, 2 identification failed
EV_FIT = 2  # FIT_LEN values
EV_Q = EV_FIT + FIT_LEN
EV_R = EV_Q + 1
EV_LEN = EV_R + 1
EV_IDENTIFIED = 1.0
EV_FAILED = 2.0

# chi-square(1) central 95 % interval of the normalized innovation squared
NIS_LO = 0.0009820691171752583
NIS_HI = 5.023886187314888


# ----------------------------------------------------------------------------- least squares
@njit(cache=True, error_model="numpy")
def acc_add_row(
    acc: FloatArray,
    off: int,
    v1: float,
    v2: float,
    i0: float,
    i1: float,
    i2: float,
    y: float,
) -> None:
    """Add one regression row ``phi = [-v1, -v2, i0, i1, i2]``, target ``y`` (eq. 15)."""
    p0 = -v1
    p1 = -v2
    acc[off + 0] += p0 * p0
    acc[off + 1] += p0 * p1
    acc[off + 2] += p0 * i0
    acc[off + 3] += p0 * i1
    acc[off + 4] += p0 * i2
    acc[off + 5] += p1 * p1
    acc[off + 6] += p1 * i0
    acc[off + 7] += p1 * i1
    acc[off + 8] += p1 * i2
    acc[off + 9] += i0 * i0
    acc[off + 10] += i0 * i1
    acc[off + 11] += i0 * i2
    acc[off + 12] += i1 * i1
    acc[off + 13] += i1 * i2
    acc[off + 14] += i2 * i2
    acc[off + 15] += p0 * y
    acc[off + 16] += p1 * y
    acc[off + 17] += i0 * y
    acc[off + 18] += i1 * y
    acc[off + 19] += i2 * y
    acc[off + 20] += y * y
    acc[off + 21] += i0
    acc[off + 22] += 1.0


@njit(cache=True, error_model="numpy")
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
            acc_add_row(acc, 0, v1, v2, i0, i1, i2, y)


@njit(cache=True, error_model="numpy")
def max_pole_modulus(a0: float, a1: float) -> float:
    """Largest |z| with z^2 + a0 z + a1 = 0 (poles of 1 / (1 + a0 z^-1 + a1 z^-2))."""
    disc = a0 * a0 - 4.0 * a1
    if disc >= 0.0:
        s = math.sqrt(disc)
        return max(abs(-a0 + s), abs(-a0 - s)) * 0.5
    return math.sqrt(a1)  # complex pair: |z|^2 = a1


@njit(cache=True, error_model="numpy")
def acc_solve(
    acc: FloatArray, off: int, cond_limit: float, min_current_std: float, min_rows: float
) -> FloatArray:
    """Least-squares coefficients from an accumulator block, with the checks of the fit.

    Solves ``G theta = b`` for ``theta = [a0, a1, b0, b1, b2]`` after scaling ``G`` to unit
    diagonal (``C = D^-1 G D^-1``); the condition number reported and checked is that of ``C``,
    so it measures collinearity of the regressors, not their units.

    Returns:
        float64 vector of length ``FIT_LEN``; ``FIT_REASON`` is ``FIT_OK`` or the failure code.
    """
    out = np.full(FIT_LEN, np.nan)
    n = acc[off + ACC_N]
    out[FIT_ROWS] = n
    if n < min_rows:
        out[FIT_REASON] = FIT_TOO_FEW_ROWS
        return out
    mean_i = acc[off + ACC_SUM_I] / n
    var_i = acc[off + ACC_G + _TRI[2, 2]] / n - mean_i * mean_i
    i_std = math.sqrt(max(var_i, 0.0))
    out[FIT_I_STD] = i_std
    if i_std < min_current_std:
        out[FIT_REASON] = FIT_LOW_CURRENT_STD
        return out
    d = np.empty(N_COEF)
    for i in range(N_COEF):
        gii = acc[off + ACC_G + _TRI[i, i]]
        if not gii > 0.0:
            out[FIT_COND] = np.inf
            out[FIT_REASON] = FIT_ILL_CONDITIONED
            return out
        d[i] = math.sqrt(gii)
    c = np.empty((N_COEF, N_COEF))
    for i in range(N_COEF):
        for j in range(N_COEF):
            c[i, j] = acc[off + ACC_G + _TRI[i, j]] / (d[i] * d[j])
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
        t = acc[off + ACC_B + i] / d[i]
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
    # SSE = y'y - 2 theta'b + theta' G theta
    sse = acc[off + ACC_YY]
    for i in range(N_COEF):
        sse -= 2.0 * theta[i] * acc[off + ACC_B + i]
        for j in range(N_COEF):
            sse += theta[i] * acc[off + ACC_G + _TRI[i, j]] * theta[j]
    out[FIT_RESID_RMS] = math.sqrt(max(sse, 0.0) / n)
    pole = max_pole_modulus(theta[0], theta[1])
    out[FIT_POLE] = pole
    out[FIT_REASON] = FIT_UNSTABLE if not pole < 1.0 else FIT_OK
    return out


@njit(cache=True, error_model="numpy")
def prediction_drift(acc: FloatArray, off: int, theta_w: FloatArray, theta_b: FloatArray) -> float:
    """RMS difference of two models' one-step predictions over a window, relative to the RMS of
    the window's voltage: ``sqrt(d' G d / n) / sqrt(y'y / n)``, ``d = theta_w - theta_b``.

    Computed from the window's Gram matrix alone, so it needs no sample buffer.
    """
    n = acc[off + ACC_N]
    yy = acc[off + ACC_YY]
    if not (n > 0.0 and yy > 0.0):
        return np.nan
    quad = 0.0
    for i in range(N_COEF):
        di = theta_w[i] - theta_b[i]
        for j in range(N_COEF):
            quad += di * acc[off + ACC_G + _TRI[i, j]] * (theta_w[j] - theta_b[j])
    return math.sqrt(max(quad, 0.0) / yy)


# ----------------------------------------------------------------------------- filter
@njit(cache=True, error_model="numpy")
def _same(x: float, y: float) -> bool:
    """Bitwise equality of two floats that are not NaN (``==`` plus the sign of zero)."""
    return x == y and math.copysign(1.0, x) == math.copysign(1.0, y)


@njit(cache=True, error_model="numpy")
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


@njit(cache=True, error_model="numpy")
def _reset_window(st: FloatArray) -> None:
    for i in range(ST_W_COUNT, ST_W_N_MODEL + 1):
        st[i] = 0.0
    for i in range(ACC_LEN):
        st[ST_WG + i] = 0.0


@njit(cache=True, error_model="numpy")
def _close_window(
    st: FloatArray, wacc: FloatArray, cfg: FloatArray, t_end: float, row: FloatArray
) -> None:
    """Write the indicators of the completed window into ``row`` (NaN = undefined)."""
    row[:] = np.nan
    row[WIN_T0] = st[ST_W_T0]
    row[WIN_T1] = t_end
    row[WIN_N] = st[ST_W_COUNT]
    row[WIN_READY] = st[ST_READY]
    row[WIN_REF_RMS] = st[ST_REF_RMS]
    row[WIN_LAST_FAIL] = st[ST_LAST_FAIL]
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
    fit = acc_solve(wacc, 0, cfg[CFG_COND_LIMIT], cfg[CFG_MIN_CURRENT_STD], cfg[CFG_MIN_ROWS])
    # Window coefficients are reported when the window's data support a fit, even if its
    # poles are outside the unit circle: an unstable window model is itself a sign of change.
    if fit[FIT_REASON] == FIT_OK or fit[FIT_REASON] == FIT_UNSTABLE:
        for i in range(N_COEF):
            row[WIN_COEF + i] = fit[FIT_COEF + i]
        if st[ST_READY] == 1.0:
            row[WIN_DRIFT] = prediction_drift(
                wacc, 0, fit[FIT_COEF : FIT_COEF + N_COEF], st[ST_COEF : ST_COEF + N_COEF]
            )


def fakf_batch(
    cfg: FloatArray, st: FloatArray, t: FloatArray, current: FloatArray, voltage: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray, FloatArray, int]:
    """Run the FAKF over one batch, updating ``st`` in place.

    Per sample k, once a model is available (seed eqs. 7-11 with the eq. 15 model, eq. 16):

        u_k   = b0 I_k + b1 I_{k-1} + b2 I_{k-2}
        x-_k  = F x_{k-1} + [u_k, 0],  F = [[-a0, -a1], [1, 0]]
        P-_k  = F P_{k-1} F^T + diag(q, 0)
        S_k   = P-_k[0, 0] + r,  e_k = V_k - x-_k[0],  K_k = P-_k[:, 0] / S_k
        x_k   = x-_k + K_k e_k
        P_k   = (I - K H) P-_k (I - K H)^T + r K K^T      (Joseph form, as filterpy)

    A NaN voltage skips the update (x_k = x-_k, P_k = P-_k); a NaN current is replaced by the
    last valid current (0 before any). The model-only output is the same recursion without the
    update.

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
    windows, events, status = _fakf_kernel(cfg, st, t, current, voltage, out)
    return out[0], out[1], out[2], out[3], windows, events, status


@njit(cache=True, error_model="numpy")
def _fakf_kernel(
    cfg: FloatArray,
    st: FloatArray,
    t: FloatArray,
    current: FloatArray,
    voltage: FloatArray,
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
    windows = np.empty((int(n // hw) + 1, WIN_LEN))
    events = np.empty((int(n // n_ident) + 1 if cfg[CFG_FIXED] == 0.0 else 0, EV_LEN))
    for k in range(1, n):
        if not t[k] > t[k - 1]:
            out[:] = np.nan
            return windows[:0], events[:0], -1

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
    w_count = st[ST_W_COUNT]
    s_innov2 = st[ST_W_SUM_INNOV2]
    n_innov = st[ST_W_N_INNOV]
    s_nis = st[ST_W_SUM_NIS]
    n_nis_in = st[ST_W_N_NIS_IN]
    s_abs = st[ST_W_SUM_ABS_ERR]
    s_sq = st[ST_W_SUM_SQ_ERR]
    n_err = st[ST_W_N_ERR]
    s_abs_m = st[ST_W_SUM_ABS_MODEL]
    n_mod = st[ST_W_N_MODEL]
    id_count = st[ST_ID_COUNT]
    # private copies of the accumulators: no aliasing with the output arrays in the hot loop
    wacc = st[ST_WG : ST_WG + ACC_LEN].copy()
    iacc = st[ST_ID : ST_ID + ACC_LEN].copy()
    # the health-window accumulator block in scalars (layout of acc_add_row): g00..g14 Gram
    # upper triangle, g15..g19 sum phi y, g20 sum y^2, g21 sum I, g22 rows
    g00 = wacc[0]
    g01 = wacc[1]
    g02 = wacc[2]
    g03 = wacc[3]
    g04 = wacc[4]
    g05 = wacc[5]
    g06 = wacc[6]
    g07 = wacc[7]
    g08 = wacc[8]
    g09 = wacc[9]
    g10 = wacc[10]
    g11 = wacc[11]
    g12 = wacc[12]
    g13 = wacc[13]
    g14 = wacc[14]
    g15 = wacc[15]
    g16 = wacc[16]
    g17 = wacc[17]
    g18 = wacc[18]
    g19 = wacc[19]
    g20 = wacc[20]
    g21 = wacc[21]
    g22 = wacc[22]

    for k in range(n):
        ik = current[k]
        vk = voltage[k]
        if w_count == 0.0:
            st[ST_W_T0] = t[k]
        # --- least-squares rows (identification and health window), eq. 15
        if (
            math.isfinite(ik)
            and math.isfinite(vk)
            and math.isfinite(i1)
            and math.isfinite(i2)
            and math.isfinite(v1)
            and math.isfinite(v2)
        ):
            ph0 = -v1
            ph1 = -v2
            g00 += ph0 * ph0
            g01 += ph0 * ph1
            g02 += ph0 * ik
            g03 += ph0 * i1
            g04 += ph0 * i2
            g05 += ph1 * ph1
            g06 += ph1 * ik
            g07 += ph1 * i1
            g08 += ph1 * i2
            g09 += ik * ik
            g10 += ik * i1
            g11 += ik * i2
            g12 += i1 * i1
            g13 += i1 * i2
            g14 += i2 * i2
            g15 += ph0 * vk
            g16 += ph1 * vk
            g17 += ik * vk
            g18 += i1 * vk
            g19 += i2 * vk
            g20 += vk * vk
            g21 += ik
            g22 += 1.0
            if not ready:
                acc_add_row(iacc, 0, v1, v2, ik, i1, i2, vk)
        ih = ik if math.isfinite(ik) else ih1
        # --- filter, eqs. 7-11 and 16
        if ready:
            u = b0 * ih + b1 * ih1 + b2 * ih2
            xp0 = f0 * x0 + f1 * x1 + u
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
            mk = f0 * m0 + f1 * m1 + u
            m1 = m0
            m0 = mk
            mod[k] = mk
            if math.isfinite(vk):
                e = vk - xp0
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
                x0 = xp0 + k0 * e
                x1 = xp1 + k1 * e
                inn[k] = e
                est[k] = x0
                nis = e * e * inv_s
                s_innov2 += e * e
                s_nis += nis
                n_innov += 1.0
                if nis >= NIS_LO and nis <= NIS_HI:
                    n_nis_in += 1.0
                err = x0 - vk
                s_abs += abs(err)
                s_sq += err * err
                n_err += 1.0
                s_abs_m += abs(mk - vk)
                n_mod += 1.0
            else:
                x0 = xp0
                x1 = xp1
                p00 = pp00
                p01 = pp01
                p11 = pp11
                p_fixed = False
                inn[k] = np.nan
                est[k] = x0
        else:
            est[k] = np.nan
            mod[k] = np.nan
            inn[k] = np.nan
            svar[k] = np.nan
        # --- lags
        i2 = i1
        i1 = ik
        v2 = v1
        v1 = vk
        ih2 = ih1
        ih1 = ih
        # --- identification window complete?
        if not ready and not fixed:
            id_count += 1.0
            if id_count >= n_ident:
                fit = acc_solve(
                    iacc, 0, cfg[CFG_COND_LIMIT], cfg[CFG_MIN_CURRENT_STD], cfg[CFG_MIN_ROWS]
                )
                ev = events[n_ev]
                ev[:] = np.nan
                ev[EV_T] = t[k]
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
                    st[ST_REF_RMS] = fit[FIT_RESID_RMS]
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
                    x0 = st[ST_X]
                    x1 = st[ST_X + 1]
                    p00 = st[ST_P]
                    p01 = st[ST_P + 1]
                    p11 = st[ST_P + 2]
                    m0 = st[ST_M]
                    m1 = st[ST_M + 1]
                else:
                    ev[EV_KIND] = EV_FAILED
                    st[ST_LAST_FAIL] = fit[FIT_REASON]
                id_count = 0.0
                iacc[:] = 0.0
        # --- health window complete?
        w_count += 1.0
        if w_count >= hw:
            st[ST_W_COUNT] = w_count
            st[ST_W_SUM_INNOV2] = s_innov2
            st[ST_W_N_INNOV] = n_innov
            st[ST_W_SUM_NIS] = s_nis
            st[ST_W_N_NIS_IN] = n_nis_in
            st[ST_W_SUM_ABS_ERR] = s_abs
            st[ST_W_SUM_SQ_ERR] = s_sq
            st[ST_W_N_ERR] = n_err
            st[ST_W_SUM_ABS_MODEL] = s_abs_m
            st[ST_W_N_MODEL] = n_mod
            wacc[0] = g00
            wacc[1] = g01
            wacc[2] = g02
            wacc[3] = g03
            wacc[4] = g04
            wacc[5] = g05
            wacc[6] = g06
            wacc[7] = g07
            wacc[8] = g08
            wacc[9] = g09
            wacc[10] = g10
            wacc[11] = g11
            wacc[12] = g12
            wacc[13] = g13
            wacc[14] = g14
            wacc[15] = g15
            wacc[16] = g16
            wacc[17] = g17
            wacc[18] = g18
            wacc[19] = g19
            wacc[20] = g20
            wacc[21] = g21
            wacc[22] = g22
            _close_window(st, wacc, cfg, t[k], windows[n_win])
            n_win += 1
            _reset_window(st)
            g00 = 0.0
            g01 = 0.0
            g02 = 0.0
            g03 = 0.0
            g04 = 0.0
            g05 = 0.0
            g06 = 0.0
            g07 = 0.0
            g08 = 0.0
            g09 = 0.0
            g10 = 0.0
            g11 = 0.0
            g12 = 0.0
            g13 = 0.0
            g14 = 0.0
            g15 = 0.0
            g16 = 0.0
            g17 = 0.0
            g18 = 0.0
            g19 = 0.0
            g20 = 0.0
            g21 = 0.0
            g22 = 0.0
            w_count = 0.0
            s_innov2 = 0.0
            n_innov = 0.0
            s_nis = 0.0
            n_nis_in = 0.0
            s_abs = 0.0
            s_sq = 0.0
            n_err = 0.0
            s_abs_m = 0.0
            n_mod = 0.0

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
    st[ST_N_SEEN] += n
    st[ST_ID_COUNT] = id_count
    st[ST_W_COUNT] = w_count
    st[ST_W_SUM_INNOV2] = s_innov2
    st[ST_W_N_INNOV] = n_innov
    st[ST_W_SUM_NIS] = s_nis
    st[ST_W_N_NIS_IN] = n_nis_in
    st[ST_W_SUM_ABS_ERR] = s_abs
    st[ST_W_SUM_SQ_ERR] = s_sq
    st[ST_W_N_ERR] = n_err
    st[ST_W_SUM_ABS_MODEL] = s_abs_m
    st[ST_W_N_MODEL] = n_mod
    wacc[0] = g00
    wacc[1] = g01
    wacc[2] = g02
    wacc[3] = g03
    wacc[4] = g04
    wacc[5] = g05
    wacc[6] = g06
    wacc[7] = g07
    wacc[8] = g08
    wacc[9] = g09
    wacc[10] = g10
    wacc[11] = g11
    wacc[12] = g12
    wacc[13] = g13
    wacc[14] = g14
    wacc[15] = g15
    wacc[16] = g16
    wacc[17] = g17
    wacc[18] = g18
    wacc[19] = g19
    wacc[20] = g20
    wacc[21] = g21
    wacc[22] = g22
    st[ST_WG : ST_WG + ACC_LEN] = wacc
    st[ST_ID : ST_ID + ACC_LEN] = iacc
    return windows[:n_win], events[:n_ev], 0
