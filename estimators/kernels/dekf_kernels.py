"""Compiled loops of the deterioration EKF and of its remaining-useful-life propagation.

``estimators.deterioration_ekf`` packs the configuration and the state into flat float64 vectors
and calls :func:`ekf_batch` once per batch; ``estimators.rul`` calls :func:`rul_times` once per
prognosis. Everything that runs per sample or per trajectory lives here, compiled by numba.

Model (seed eqs. 1-11), state ``x = [w1, w2, alpha, m]``, input ``u = I``::

    dv      = r1 w1 - r2 w2                         (relative tangential speed)
    dw1/dt  = (-alpha r1 dv - B1 w1 + Km u) / J1
    dw2/dt  = ( alpha r2 dv - B2 w2) / J2
    dalpha/dt = -m dv^2 alpha                        (eq. 7, sliding factor p = dv^2)
    dm/dt   = 0                                      (eq. 11)

Flat layouts (indices are the module constants below):

* configuration vector ``cfg`` (``CFG_*``), built by ``estimators.deterioration_ekf``;
* state vector ``st`` (``ST_*``): filter state and covariance (upper triangle), the held current,
  the health-window accumulators, the Dn level, the next prognosis time and the ring of binned
  applied current used by the "observed" load assumption (``2 * bins`` values at ``ST_RING``).
  Counters are stored as floats (exact below 2**53).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
from numba import njit
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]

# ----------------------------------------------------------------------------- layouts
CFG_R1 = 0
CFG_R2 = 1
CFG_B1 = 2
CFG_B2 = 3
CFG_J1 = 4
CFG_J2 = 5
CFG_KM = 6
CFG_RV = 7  # 2: measurement noise variances of w1, w2
CFG_Q = 9  # 4: per-sample process noise variances (diagonal)
CFG_P0 = 13  # 4: initial variances (diagonal)
CFG_W0 = 17  # 2: initial speeds (NaN: the first measurement)
CFG_ALPHA0 = 19
CFG_M0 = 20
CFG_F44 = 21
CFG_BOUND_C = 22
CFG_HEALTH_WINDOW = 23
CFG_EXPM_TOL = 24
CFG_DN_WATCH = 25
CFG_DN_ALERT = 26
CFG_DN_HYST = 27
CFG_RUL_EVERY = 28  # NaN: no scheduled prognosis
CFG_OBS_BIN_SAMPLES = 29  # 0: no observed-load ring
CFG_OBS_BINS = 30
CFG_NIS_BOUNDS = 31  # 4: per-sample central 95 % chi-square bounds, 1 dof (lo, hi), 2 dof (lo, hi)
CFG_PROJECT = 35  # 1.0: alpha-hat clipped at 0, wear rate max(m-hat, 0) in the prediction
CFG_CURRENT_VAR = 36  # variance of the measured current (A^2), propagated as process noise
CFG_INV_J1 = 37  # 1 / J1
CFG_INV_J2 = 38  # 1 / J2
CFG_DT_NOMINAL = 39  # nominal sample period (0: use the actual spacing)
CFG_INPUT_INTERVAL = 40  # 2.0: edge response moments; 1.0: interval-mean input; 0.0: held input
CFG_INPUT_TIMING = 41  # channel skew/jitter allowance (s)
CFG_ADAPT_MEMORY = 42  # memory of the noise estimates (s); 0: R and Q fixed
CFG_GATE = 43  # 2: NIS gates for 1 and 2 measured channels (inf: no gating)
CFG_ALPHA_MAX = 45  # alpha-hat <= alpha0 * this (projection)
CFG_M_WALK = 46  # relative random walk of m per sqrt(s)
CFG_CALIB_S = 47  # alpha0 calibration length (s), when alpha0 is NaN
CFG_ALPHA_PRIOR = 48  # initial alpha while calibrating
CFG_ALPHA_PRIOR_VAR = 49  # its variance
CFG_SKEW = 50  # time offset of the w1 samples after the w2 samples (s), from the calibration
CFG_PCAL = 51  # 1.0: accumulate the plant-calibration sums over the healthy start
CFG_PCAL_TOL = 52  # current change tolerated in a calibration interval, relative to max |I|
CFG_COV_SCALE = 53  # 1.0: report bands scaled by the running NIS / dof (when above 1)
CFG_ALPHA_FLOOR = 54  # relative std of alpha the data cannot reduce (the plant calibration's)
CFG_LEN = 55
#: std of a normal over the median of its absolute value
MEDIAN_TO_SIGMA = 1.0 / 0.6744897501960817
#: the same for a third difference of white noise (variance 20 r)
D3_TO_SIGMA = MEDIAN_TO_SIGMA / math.sqrt(20.0)
NOISE_FLOOR = 1e-3  # smallest share of a residual's variance left to its own sensor
#: one-step residuals needed (per speed) before the noise estimate replaces the configured R
MIN_DIFFS = 8
#: largest ln-factor of the back-extrapolation of alpha0 over the calibration segment
CALIB_MAX_LOG = 0.5
#: A spacing within this fraction of the nominal period is taken as the nominal period.
DT_SNAP_TOL = 1e-3

ST_INIT = 0
ST_T_LAST = 1
ST_U_HELD = 2
ST_N_SEEN = 3
ST_X = 4  # 4
ST_P = 8  # 10: p00 p01 p02 p03 p11 p12 p13 p22 p23 p33
ST_DN_LEVEL = 18
ST_T_NEXT_RUL = 19
ST_W_COUNT = 20
ST_W_T0 = 21
ST_W_DN0 = 22
ST_W_N_UPD = 23
ST_W_SUM_NIS = 24
ST_W_SUM_DOF = 25
ST_W_N_NIS_OUT = 26
ST_W_N_E_OUT = 27
ST_W_N_E = 28
ST_W_CH = 29  # 2 x 5: n, sum nu, sum nu^2, sum nu_k nu_{k-1}, lag pairs
CH_N = 0
CH_SUM = 1
CH_SUM2 = 2
CH_LAG = 3
CH_N_LAG = 4
CH_LEN = 5
ST_NU_PREV = 39  # 2: last normalized innovations (NaN when missing)
ST_LAST_CONSISTENT = 41  # NaN before the first window
ST_RUL_LEVEL = 42
ST_RUL_Q05 = 43
ST_OB_SUM_UDT = 44
ST_OB_SUM_DT = 45
ST_OB_COUNT = 46
ST_OB_HEAD = 47
ST_OB_FILLED = 48
# version 2
ST_R_HAT = 49  # 2: estimated measurement noise variances (NaN: the configured ones)
ST_N_ADAPT = 51  # noise-estimate updates so far
ST_DU_PREV = 52  # current change over the previous interval (A)
ST_ALPHA0 = 53  # alpha0 in use (NaN while it is being estimated)
ST_CALIB_T_END = 54  # end of the alpha0 calibration segment (s)
ST_CALIB_INT = 55  # integral of dv^2 dt over the calibration segment so far
ST_W_N_GATED = 56  # window accumulator: down-weighted updates
ST_N_GATED = 57  # down-weighted updates since the stream start
ST_BAD_STREAK = 58  # consecutive inconsistent health windows
ST_GOOD_STREAK = 59  # consecutive consistent health windows
ST_VERDICT = 60  # consistency verdict after hysteresis (NaN: none yet, 1 consistent, 0 not)
ST_FAILED = 61  # 1.0 once Dn-hat has reached the failure threshold (latched)
ST_HIST_T = 62  # last prognosis: time (NaN: none)
ST_HIST_ELL = 63  # its ln(alpha-hat)
ST_HIST_RATE = 64  # its predicted rate of -ln(alpha) (1/s)
ST_HIST_VAR = 65  # its variance of ln(alpha-hat)
ST_ERR_N = 66  # log-rate error record: count
ST_ERR_SUM2 = 67  # sum of squared log-rate errors
ST_ERR_SUMV = 68  # sum of the squared errors the covariance explains
ST_RUL_STATUS = 69  # index in STATUSES of the last prognosis status (NaN: none)
ST_QW = 70  # 2: estimated process noise of w1, w2 per step (covariance matching)
ST_Y_HIST = 72  # 6: last three valid measurements of w1, then of w2 (NaN: fewer)
ST_QTL = 78  # 2: running median of |third difference| of w1, w2
ST_N_QTL = 80  # 2: its sample counts
ST_A0_BEST = 82  # alpha0 candidate of least variance during the calibration (NaN: none)
ST_A0_VAR = 83  # variance of ln(alpha0-hat) (0 when alpha0 is configured)
ST_ERR_SUM = 84  # log-rate error record: sum of the relative errors
ST_ERR_REAL = 85  # sum of the realized changes of -ln(alpha) between prognoses
ST_ERR_PRED = 86  # sum of the predicted changes
# version 3: plant calibration (instrumental-variable sums over the healthy start)
ST_PCAL_END = 87  # end time of the plant calibration segment (NaN: none pending)
ST_PCAL_T = 88  # time the calibration was applied (NaN: not applied)
ST_PCAL_N = 89  # rows in the sums
ST_PCAL_DT = 90  # sum of the rows' sample spacings
ST_PCAL_HIST = 91  # 11: y1 at k-1..k-3, y2 at k-1..k-3, I at k-1..k-3, t at k-1, k-2
ST_PCAL_ALPHA_MID = 102  # alpha-hat at the segment centre (NaN before)
ST_PCAL_INT_MID = 103  # int dv^2 dt from the stream start to the centre
ST_PCAL_INT = 104  # int dv^2 dt over the segment so far
ST_PCAL_UMAX = 105  # largest |I| seen in the segment
ST_PLANT = 106  # 5: B1, B2, J1, J2, skew in use after calibration (NaN: configured; skew 0)
ST_PCAL_WZ = 111  # 36: sum w z^T (6 x 6, row-major), w the instruments, z the regressors
ST_PCAL_WY = 147  # 12: sum w y^T (6 x 2)
ST_PCAL_ZZ = 159  # 36: sum z z^T
ST_PCAL_ZY = 195  # 12: sum z y^T
ST_PCAL_YY = 207  # 4: sum y y^T
ST_PCAL_WW = 211  # 36: sum w w^T (the instrumental-variable covariance)
ST_PCAL_OK = 247  # 1.0 applied, 0.0 rejected, NaN not done
ST_NIS_RATIO = 248  # NIS / dof of the last health window (the covariance scale of the bands)
ST_NIS_N = 249  # windows that set it
ST_PCAL_ALPHA_REL = 250  # relative std of the calibrated alpha: a floor of the alpha band
ST_Y_RES = 251  # 2: posterior residuals y - x of w1, w2 at the last sample (NaN: missing)
ST_QTL_RES = 253  # 2: running median of |one-step residual| of w1, w2
ST_N_QTL_RES = 255  # 2: its sample counts
ST_DW_T = 257  # dwell record of an observed load: end of the newest bin counted (NaN: none)
ST_DW_LEVEL = 258  # level in force there (0 low, 1 high; NaN: none)
ST_DW_RUN = 259  # time at that level since its last switch (NaN: the run began unseen)
ST_DW_EXPO = 260  # 2: time at the low, the high level (forgetting-weighted)
ST_DW_SWITCH = 262  # 2: switches out of the low, the high level
ST_DW_N = 264  # 2: completed dwells seen whole at the low, the high level
ST_DW_SUM = 266  # 2: their summed lengths
ST_DW_SUM2 = 268  # 2: their summed squared lengths
ST_DW_RESTARTS = 270  # restarts of the record by the stationarity check
ST_DW_HIST = 271  # 2 x DW_HIST_BINS: histogram of the whole dwells' lengths, low then high
DW_HIST_BINS = 40
# version 6: the last prognosis' state, from which the prognosis record predicts the next span
ST_HIST_W = 351  # 2: its w1-hat, w2-hat (NaN: none)
ST_HIST_M = 353  # its m-hat
ST_RING = 354  # bins currents, then bins durations
ST_BASE_LEN = 354
ST_BASE_LEN_V5 = 351
ST_BASE_LEN_V4 = 257
ST_BASE_LEN_V3 = 251
ST_BASE_LEN_V1 = 49
ST_BASE_LEN_V2 = 87
PCAL_HIST_LEN = 11
PCAL_REG = 6  # regressors: w1, w2, I and the same times (t - t_centre)

# health-window rows
WIN_T0 = 0
WIN_T1 = 1
WIN_N = 2
WIN_N_UPD = 3
WIN_SUM_NIS = 4
WIN_SUM_DOF = 5
WIN_N_NIS_OUT = 6
WIN_N_E_OUT = 7
WIN_N_E = 8
WIN_CH = 9  # 2 x CH_LEN
WIN_DN0 = 19
WIN_X = 20  # 4
WIN_SIGMA = 24  # 4
WIN_N_GATED = 28
WIN_R = 29  # 2: noise variances in use at the window end
WIN_ALPHA0 = 31
WIN_COV_SCALE = 32  # covariance scale at the window end
WIN_LEN = 33

# Dn level change rows
EV_T = 0
EV_FROM = 1
EV_TO = 2
EV_DN = 3
EV_DN_LO = 4
EV_DN_HI = 5
EV_LEN = 6

# prognosis snapshot rows: time, x (4), P upper triangle (10), filled bins, alpha0, ring (2 x bins)
RS_T = 0
RS_X = 1
RS_P = 5
RS_FILLED = 15
RS_ALPHA0 = 16
RS_A0_VAR = 17
RS_COV_SCALE = 18  # covariance scale max(1, running NIS / dof) at the snapshot
RS_OB_PARTIAL = 19  # duration of the observed-load bin under way (the newest full bin ends t - this)
RS_RING = 20
RS_BASE_LEN = 20

# per-sample output rows
OUT_W1 = 0
OUT_W2 = 1
OUT_ALPHA = 2
OUT_M = 3
OUT_SIG = 4  # 4: c sqrt(P_ii)
OUT_DN = 8
OUT_DN_LO = 9
OUT_DN_HI = 10
OUT_E = 11  # 2 innovations
OUT_E_BOUND = 13  # 2: c sqrt(S_jj)
OUT_NIS = 15
OUT_R = 16  # 2: measurement noise variances in use
OUT_GATED = 18  # 1.0 where the update was down-weighted by the gate
OUT_LEN = 19

# fused multiply-add contraction only (no reassociation, no assumptions on NaN or infinity):
# the hot loops are chains of products and sums
FMA = {"contract"}
THETA_MAX = 0.5  # largest balanced ||G dt||_1 before scaling and squaring
MAX_ORDER = 24
# 1 / j for j = 0 .. MAX_ORDER + 2 (index 0 unused): the Horner steps multiply instead of divide
RECIP = np.array([0.0] + [1.0 / j for j in range(1, MAX_ORDER + 4)])
#: 1 / (j + 1)! for j = 0 .. MAX_ORDER: the coefficients of phi1
INV_FACT1 = np.array([1.0 / math.factorial(j + 1) for j in range(MAX_ORDER + 1)])
# cycle jumps of the prognosis: only where ln(alpha) changes by at most this per period (the
# modified equation is then accurate to O(delta^2) relative), over at least this many periods,
# and stopping this many periods before the threshold
JUMP_MAX_DELTA = 0.01
JUMP_MIN_PERIODS = 16.0
JUMP_MARGIN_PERIODS = 8.0
MAX_SUB = 256  # sub-segments per load segment in the prognosis


# ----------------------------------------------------------------------------- model
@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def taylor_order(theta: float, tol: float) -> int:
    """Smallest N >= 2 whose remainder bound of phi1 to order N is at most ``tol``.

    For ``||X|| <= theta`` the remainder ``sum_(j>N) X^j / (j+1)!`` is bounded by the tail
    ``sum_(j>N) theta^j / (j+1)! <= theta^(N+1) / (N+2)! / (1 - theta / (N+3))`` (each term at
    most theta / (N+3) times the one before), for theta < N + 3. Inlined into the filter's loop
    (a call there makes the compiler store every live value around it)."""
    term = theta * theta * theta * RECIP[24]  # N = 2: theta^3 / 4!
    order = 2
    while order < MAX_ORDER and term > tol * (1.0 - theta * RECIP[order + 3]):
        order += 1
        term *= theta * RECIP[order + 2]
    return order


@njit(cache=True, nogil=True, error_model="numpy", fastmath=FMA)
def discretize(
    cfg: FloatArray, w1: float, w2: float, al: float, m: float, u: float, dt: float
) -> tuple[
    float, float, float, float, float, float, float, float, float,
    float, float, float, float, float, float, float, float, float, float, float, float,
]:  # fmt: skip
    """:func:`discretize_plant` with the plant and the series settings of ``cfg``."""
    bal1 = math.sqrt(cfg[CFG_INV_J2] / cfg[CFG_INV_J1])
    return discretize_plant(
        cfg[CFG_R1], cfg[CFG_R2], cfg[CFG_B1], cfg[CFG_B2], cfg[CFG_INV_J1], cfg[CFG_INV_J2],
        cfg[CFG_KM], cfg[CFG_F44], cfg[CFG_EXPM_TOL], bal1, 1.0 / bal1, w1, w2, al, m, u, dt,
    )  # fmt: skip


@njit(cache=True, nogil=True, error_model="numpy", fastmath=FMA, inline="always")
def discretize_plant(
    r1: float, r2: float, b1: float, b2: float, ij1: float, ij2: float, km: float, f44: float,
    tol: float, bal1: float, ibal1: float, w1: float, w2: float, al: float, m: float, u: float,
    dt: float,
) -> tuple[
    float, float, float, float, float, float, float, float, float,
    float, float, float, float, float, float, float, float, float, float, float, float,
]:  # fmt: skip
    """Local-linearization step of the model from the posterior ``[w1, w2, al, m]``.

    With ``F`` the Jacobian (seed eq. 19) at the posterior, ``G`` its upper-left 3x3 block,
    ``g = [0, 0, F34]`` and ``F44`` the configured value:

        Phi   = expm(F dt) = [[E, c4], [0, exp(F44 dt)]],  E = expm(G dt)
        Gamma = int_0^dt expm(G s) ds = dt phi1(G dt)
        dx    = Gamma (f(x) + B u)              (state prediction of w1, w2, alpha; m is held)
        c4    = int_0^dt expm(G (dt - s)) g exp(F44 s) ds
        gb    = Gamma B                         (how a current error over the step moves x)

    ``phi1(X) = sum_j X^j / (j+1)!`` is evaluated to the smallest order N whose remainder
    bound (``taylor_order``, on the 1-norm of the balanced ``D^-1 X D`` below) is at most ``tol
    min(d1, 1 / d1)``, so that each entry of the speed block of phi1 is within ``tol``, after
    halving ``dt`` s times if that norm exceeds ``THETA_MAX``; ``E`` and ``Gamma`` are then
    doubled back (``Gamma(2h) = (I + E(h)) Gamma(h)``, ``E(2h) = E(h)^2``). The polynomial is
    evaluated by the Paterson-Stockmeyer scheme in ``X^2`` (about N / 2 3x3 products, against
    N - 1 for Horner's rule in X).

    The plant is ``r1, r2, B1, B2, 1 / J1, 1 / J2, Km``; passed as numbers (not the
    configuration vector) so that the filter's loop, into which this is inlined, keeps them in
    registers and passes no array. ``bal1 = sqrt(J1 / J2)`` (``d1``) and ``ibal1 = 1 / bal1``
    are the caller's, computed once per batch.

    Returns:
        (E00, E01, E02, E10, E11, E12, E20, E21, E22, c40, c41, c42, e44, dx0, dx1, dx2, gb0,
        gb1, gb2, N, s): N the series order, s the halvings of dt (the filter ignores both).
    """
    dv = r1 * w1 - r2 * w2
    # Jacobian, seed eq. 19
    g00 = -(al * r1 * r1 + b1) * ij1
    g01 = al * r1 * r2 * ij1
    g02 = -r1 * dv * ij1
    g10 = al * r1 * r2 * ij2
    g11 = -(al * r2 * r2 + b2) * ij2
    g12 = r2 * dv * ij2
    g20 = -2.0 * al * m * r1 * dv
    g21 = 2.0 * al * m * r2 * dv
    g22 = -m * dv * dv
    f34 = -al * dv * dv
    # drift f(x) + B u (m has none)
    v0 = (-al * r1 * dv - b1 * w1 + km * u) * ij1
    v1 = (al * r2 * dv - b2 * w2) * ij2
    v2 = g22 * al
    # The order is chosen from the 1-norm of the balanced matrix D^-1 G D, D = diag(1, d1, b):
    # d1 = sqrt(J1 / J2) (``bal1``, the kinetic-energy scaling sqrt(J) w, in which the speed
    # coupling alpha r1 r2 / sqrt(J1 J2) is symmetric) and b^2 = (|g20| + d1 |g21|) / (|g02| +
    # |g12| / d1). The truncated series commutes with the similarity: R(X) = D R(D^-1 X D) D^-1
    # for its remainder R, so an entry of the speed block is off by at most max(d1, 1 / d1)
    # times the balanced bound, which is therefore held below tol min(d1, 1 / d1); neither the
    # light motor's large coupling column nor the alpha column (units of speed per unit alpha)
    # inflates the order.
    col_a = abs(g02) + abs(g12) * ibal1
    row_a = abs(g20) + abs(g21) * bal1
    bal = math.sqrt(row_a * col_a)
    norm = max(abs(g00) + abs(g10) * ibal1, abs(g01) * bal1 + abs(g11), abs(g22)) + bal
    theta = norm * dt
    s = 0
    h = dt
    if theta > THETA_MAX:
        s = int(math.ceil(math.log2(theta / THETA_MAX)))
        h = dt / 2.0**s
        theta = norm * h
    tol_bal = tol * min(bal1, ibal1)
    order = taylor_order(theta, tol_bal)
    x00 = g00 * h
    x01 = g01 * h
    x02 = g02 * h
    x10 = g10 * h
    x11 = g11 * h
    x12 = g12 * h
    x20 = g20 * h
    x21 = g21 * h
    x22 = g22 * h
    # phi1(X) = sum_j c_j X^j, c_j = 1 / (j+1)!, by Paterson-Stockmeyer in X2 = X^2: groups
    # (c_i I + c_(i+1) X) by Horner in X2, one 3x3 product per two orders (Horner in X: one
    # per order)
    xx00 = x00 * x00 + x01 * x10 + x02 * x20
    xx01 = x00 * x01 + x01 * x11 + x02 * x21
    xx02 = x00 * x02 + x01 * x12 + x02 * x22
    xx10 = x10 * x00 + x11 * x10 + x12 * x20
    xx11 = x10 * x01 + x11 * x11 + x12 * x21
    xx12 = x10 * x02 + x11 * x12 + x12 * x22
    xx20 = x20 * x00 + x21 * x10 + x22 * x20
    xx21 = x20 * x01 + x21 * x11 + x22 * x21
    xx22 = x20 * x02 + x21 * x12 + x22 * x22
    if order % 2 == 0:
        # top group c_(N-2) I + c_(N-1) X + c_N X2 (no product)
        i = order - 4
        ca = INV_FACT1[order - 2]
        cb = INV_FACT1[order - 1]
        cz = INV_FACT1[order]
        y00 = ca + cb * x00 + cz * xx00
        y01 = cb * x01 + cz * xx01
        y02 = cb * x02 + cz * xx02
        y10 = cb * x10 + cz * xx10
        y11 = ca + cb * x11 + cz * xx11
        y12 = cb * x12 + cz * xx12
        y20 = cb * x20 + cz * xx20
        y21 = cb * x21 + cz * xx21
        y22 = ca + cb * x22 + cz * xx22
    else:
        i = order - 3
        ca = INV_FACT1[order - 1]
        cb = INV_FACT1[order]
        y00 = ca + cb * x00
        y01 = cb * x01
        y02 = cb * x02
        y10 = cb * x10
        y11 = ca + cb * x11
        y12 = cb * x12
        y20 = cb * x20
        y21 = cb * x21
        y22 = ca + cb * x22
    while i >= 0:
        ca = INV_FACT1[i]
        cb = INV_FACT1[i + 1]
        n00 = ca + cb * x00 + (xx00 * y00 + xx01 * y10 + xx02 * y20)
        n01 = cb * x01 + (xx00 * y01 + xx01 * y11 + xx02 * y21)
        n02 = cb * x02 + (xx00 * y02 + xx01 * y12 + xx02 * y22)
        n10 = cb * x10 + (xx10 * y00 + xx11 * y10 + xx12 * y20)
        n11 = ca + cb * x11 + (xx10 * y01 + xx11 * y11 + xx12 * y21)
        n12 = cb * x12 + (xx10 * y02 + xx11 * y12 + xx12 * y22)
        n20 = cb * x20 + (xx20 * y00 + xx21 * y10 + xx22 * y20)
        n21 = cb * x21 + (xx20 * y01 + xx21 * y11 + xx22 * y21)
        n22 = ca + cb * x22 + (xx20 * y02 + xx21 * y12 + xx22 * y22)
        y00, y01, y02, y10, y11, y12, y20, y21, y22 = n00, n01, n02, n10, n11, n12, n20, n21, n22
        i -= 2
    # E = I + X Y, Gamma = h Y
    e00 = 1.0 + x00 * y00 + x01 * y10 + x02 * y20
    e01 = x00 * y01 + x01 * y11 + x02 * y21
    e02 = x00 * y02 + x01 * y12 + x02 * y22
    e10 = x10 * y00 + x11 * y10 + x12 * y20
    e11 = 1.0 + x10 * y01 + x11 * y11 + x12 * y21
    e12 = x10 * y02 + x11 * y12 + x12 * y22
    e20 = x20 * y00 + x21 * y10 + x22 * y20
    e21 = x20 * y01 + x21 * y11 + x22 * y21
    e22 = 1.0 + x20 * y02 + x21 * y12 + x22 * y22
    q00 = h * y00
    q01 = h * y01
    q02 = h * y02
    q10 = h * y10
    q11 = h * y11
    q12 = h * y12
    q20 = h * y20
    q21 = h * y21
    q22 = h * y22
    # column 4 of Phi (rows 0..2) for the small step h
    if f44 == 0.0:
        e44 = 1.0
        k0 = k1 = k2 = 0.0  # filled from Gamma after the doubling
    else:
        e44 = math.exp(f44 * h)
        # c4(h) = exp(F44 h) h phi1((G - F44 I) h) g, by Horner on the vector g = [0, 0, F34]
        z00 = x00 - f44 * h
        z11 = x11 - f44 * h
        z22 = x22 - f44 * h
        # ||D^-1 (G - F44 I) h D||_1 <= theta + |F44| h, in the same balanced scales
        order_z = taylor_order(theta + abs(f44) * h, tol_bal)
        c = RECIP[order_z + 1]
        k0 = x02 * f34 * c
        k1 = x12 * f34 * c
        k2 = f34 + z22 * f34 * c
        for j in range(order_z - 1, 0, -1):
            c = RECIP[j + 1]
            n0 = (z00 * k0 + x01 * k1 + x02 * k2) * c
            n1 = (x10 * k0 + z11 * k1 + x12 * k2) * c
            n2 = f34 + (x20 * k0 + x21 * k1 + z22 * k2) * c
            k0, k1, k2 = n0, n1, n2
        k0 *= e44 * h
        k1 *= e44 * h
        k2 *= e44 * h
    for _ in range(s):
        if f44 != 0.0:
            n0 = e00 * k0 + e01 * k1 + e02 * k2 + k0 * e44
            n1 = e10 * k0 + e11 * k1 + e12 * k2 + k1 * e44
            n2 = e20 * k0 + e21 * k1 + e22 * k2 + k2 * e44
            k0, k1, k2 = n0, n1, n2
            e44 = e44 * e44
        # Gamma <- Gamma + E Gamma
        n00 = q00 + e00 * q00 + e01 * q10 + e02 * q20
        n01 = q01 + e00 * q01 + e01 * q11 + e02 * q21
        n02 = q02 + e00 * q02 + e01 * q12 + e02 * q22
        n10 = q10 + e10 * q00 + e11 * q10 + e12 * q20
        n11 = q11 + e10 * q01 + e11 * q11 + e12 * q21
        n12 = q12 + e10 * q02 + e11 * q12 + e12 * q22
        n20 = q20 + e20 * q00 + e21 * q10 + e22 * q20
        n21 = q21 + e20 * q01 + e21 * q11 + e22 * q21
        n22 = q22 + e20 * q02 + e21 * q12 + e22 * q22
        q00, q01, q02, q10, q11, q12, q20, q21, q22 = n00, n01, n02, n10, n11, n12, n20, n21, n22
        # E <- E E
        n00 = e00 * e00 + e01 * e10 + e02 * e20
        n01 = e00 * e01 + e01 * e11 + e02 * e21
        n02 = e00 * e02 + e01 * e12 + e02 * e22
        n10 = e10 * e00 + e11 * e10 + e12 * e20
        n11 = e10 * e01 + e11 * e11 + e12 * e21
        n12 = e10 * e02 + e11 * e12 + e12 * e22
        n20 = e20 * e00 + e21 * e10 + e22 * e20
        n21 = e20 * e01 + e21 * e11 + e22 * e21
        n22 = e20 * e02 + e21 * e12 + e22 * e22
        e00, e01, e02, e10, e11, e12, e20, e21, e22 = n00, n01, n02, n10, n11, n12, n20, n21, n22
    if f44 == 0.0:
        k0 = q02 * f34
        k1 = q12 * f34
        k2 = q22 * f34
    dx0 = q00 * v0 + q01 * v1 + q02 * v2
    dx1 = q10 * v0 + q11 * v1 + q12 * v2
    dx2 = q20 * v0 + q21 * v1 + q22 * v2
    kb = km * ij1
    return (
        e00, e01, e02, e10, e11, e12, e20, e21, e22, k0, k1, k2, e44, dx0, dx1, dx2,
        q00 * kb, q10 * kb, q20 * kb, float(order), float(s),
    )  # fmt: skip


EDGE_MAX_TERMS = 48  # series terms of the edge-response moments (theta up to about 12)


@njit(cache=True, nogil=True, error_model="numpy", fastmath=FMA)
def edge_moments(
    cfg: FloatArray, w1: float, w2: float, al: float, m: float, dt: float
) -> tuple[float, float, float, float, float, float, float, float, float]:
    """Mean and covariance of the response at the end of an interval of length ``dt`` to a unit
    current step at an unknown instant, uniform over the interval.

    A step of the current at ``t_k - h`` moves ``[w1, w2, alpha]`` at ``t_k`` by
    ``g(h) = int_0^h expm(G s) ds b`` (``G`` the Jacobian block at the posterior, ``b = [Km /
    J1, 0, 0]``). With ``h ~ U(0, dt)`` and ``a_i = dt^(i+1) / (i+1)! G^i b``:

        E[g]      = sum_i a_i / (i + 2)
        E[g g^T]  = sum_ij a_i a_j^T / (i + j + 3)

    (``E[h^n] = dt^n / (n + 1)``). The response of a step late in the interval is not a
    multiple of an early one (the wheel lags the motor), so the uncertainty is not rank one.

    Returns:
        (mu0, mu1, mu2, c00, c01, c02, c11, c12, c22), the covariance ``E[g g^T] - mu mu^T``.
    """
    r1 = cfg[CFG_R1]
    r2 = cfg[CFG_R2]
    ij1 = cfg[CFG_INV_J1]
    ij2 = cfg[CFG_INV_J2]
    dv = r1 * w1 - r2 * w2
    g00 = -(al * r1 * r1 + cfg[CFG_B1]) * ij1 * dt
    g01 = al * r1 * r2 * ij1 * dt
    g02 = -r1 * dv * ij1 * dt
    g10 = al * r1 * r2 * ij2 * dt
    g11 = -(al * r2 * r2 + cfg[CFG_B2]) * ij2 * dt
    g12 = r2 * dv * ij2 * dt
    g20 = -2.0 * al * m * r1 * dv * dt
    g21 = 2.0 * al * m * r2 * dv * dt
    g22 = -m * dv * dv * dt
    a = np.empty((EDGE_MAX_TERMS, 3))
    a[0, 0] = cfg[CFG_KM] * ij1 * dt
    a[0, 1] = 0.0
    a[0, 2] = 0.0
    scale = abs(a[0, 0])
    n = 1
    while n < EDGE_MAX_TERMS:
        c = 1.0 / (n + 1.0)
        p0 = a[n - 1, 0]
        p1 = a[n - 1, 1]
        p2 = a[n - 1, 2]
        a[n, 0] = (g00 * p0 + g01 * p1 + g02 * p2) * c
        a[n, 1] = (g10 * p0 + g11 * p1 + g12 * p2) * c
        a[n, 2] = (g20 * p0 + g21 * p1 + g22 * p2) * c
        n += 1
        if abs(a[n - 1, 0]) + abs(a[n - 1, 1]) <= 1e-13 * scale and n > 3:
            break
    mu0 = mu1 = mu2 = 0.0
    s00 = s01 = s02 = s11 = s12 = s22 = 0.0
    for i in range(n):
        ci = 1.0 / (i + 2.0)
        mu0 += a[i, 0] * ci
        mu1 += a[i, 1] * ci
        mu2 += a[i, 2] * ci
        for j in range(n):
            c = 1.0 / (i + j + 3.0)
            s00 += a[i, 0] * a[j, 0] * c
            s01 += a[i, 0] * a[j, 1] * c
            s02 += a[i, 0] * a[j, 2] * c
            s11 += a[i, 1] * a[j, 1] * c
            s12 += a[i, 1] * a[j, 2] * c
            s22 += a[i, 2] * a[j, 2] * c
    return (
        mu0, mu1, mu2, s00 - mu0 * mu0, s01 - mu0 * mu1, s02 - mu0 * mu2, s11 - mu1 * mu1,
        s12 - mu1 * mu2, s22 - mu2 * mu2,
    )  # fmt: skip


# ----------------------------------------------------------------------------- filter
@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _median_step(q: float, a: float, n: float, g_min: float, up_min: float, down_min: float) -> float:
    """One step of a running median of ``|a|`` (a stochastic-approximation quantile): ``q``
    times ``g`` if ``a > q``, else divided by it, ``g = 1 + max(1 / (n + 1), g_min)``.
    ``up_min = 1 + g_min`` and ``down_min = 1 / up_min`` are the caller's, shared by all medians
    once ``n + 1 >= 1 / g_min``, so that the step then costs no division (the early return
    keeps the compiler from computing the early steps' gain on every call)."""
    if n == 0.0:
        return max(a, 1e-300)
    if (n + 1.0) * g_min >= 1.0:
        return q * (up_min if a > q else down_min)
    up = 1.0 + 1.0 / (n + 1.0)
    return q * (up if a > q else 1.0 / up)


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _matching_step(n: float, d_min: float) -> float:
    """Step of the covariance matching after ``n`` updates: ``1 / (n + 2)`` while that is above
    ``d_min``, then ``d_min`` (returned early, so that the division is not done then)."""
    if not (n + 2.0) * d_min < 1.0:
        return d_min
    return 1.0 / (n + 2.0)


@njit(cache=True, nogil=True, error_model="numpy")
def _dn_target(dn: float, watch: float, alert: float) -> int:
    if dn >= alert:
        return 2
    if dn >= watch:
        return 1
    return 0

@njit(cache=True, nogil=True, error_model="numpy")
def _pcal_accumulate(
    cfg: FloatArray, st: FloatArray, tk: float, y1: float, y2: float, ik: float, t_centre: float
) -> None:
    """Add the calibration row of the interval ``[t_{k-2}, t_{k-1}]`` and push sample k.

    A row is kept when the current is the same (within ``CFG_PCAL_TOL`` of the largest |I|
    so far) at samples k-3 .. k: the interval and its neighbours hold no edge, so over it
    ``y_{k-1} = Ad y_{k-2} + Bd I`` exactly for the sampled LTI plant (alpha frozen). The
    regressors ``z = [w1_{k-2}, w2_{k-2}, I, tau w1_{k-2}, tau w2_{k-2}, tau I]`` (``tau`` the
    time from the segment centre: a first-order drift of the map as alpha wears) and the
    instruments ``w`` (the same with the samples at k-3, whose noise is independent of the
    row's) give the sums ``w z^T``, ``w y^T`` and, for the residual variances, ``z z^T``,
    ``z y^T``, ``y y^T``.
    """
    h = ST_PCAL_HIST
    a1 = st[h]
    a2 = st[h + 1]
    a3 = st[h + 2]
    b1 = st[h + 3]
    b2 = st[h + 4]
    b3 = st[h + 5]
    u1 = st[h + 6]
    u2 = st[h + 7]
    u3 = st[h + 8]
    t1 = st[h + 9]
    t2 = st[h + 10]
    if math.isfinite(ik):
        st[ST_PCAL_UMAX] = max(st[ST_PCAL_UMAX], abs(ik))
    tol = cfg[CFG_PCAL_TOL] * st[ST_PCAL_UMAX]
    if (
        math.isfinite(a1 + a2 + a3 + b1 + b2 + b3 + u1 + u2 + u3 + ik + t1 + t2)
        and abs(ik - u1) <= tol
        and abs(u1 - u2) <= tol
        and abs(u2 - u3) <= tol
    ):
        tau = t1 - t_centre
        um = 0.5 * (u1 + u2)
        z = (a2, b2, um, tau * a2, tau * b2, tau * um)
        w = (a3, b3, um, tau * a3, tau * b3, tau * um)
        y = (a1, b1)
        for i in range(PCAL_REG):
            for j in range(PCAL_REG):
                st[ST_PCAL_WZ + PCAL_REG * i + j] += w[i] * z[j]
                st[ST_PCAL_ZZ + PCAL_REG * i + j] += z[i] * z[j]
                st[ST_PCAL_WW + PCAL_REG * i + j] += w[i] * w[j]
            for j in range(2):
                st[ST_PCAL_WY + 2 * i + j] += w[i] * y[j]
                st[ST_PCAL_ZY + 2 * i + j] += z[i] * y[j]
        st[ST_PCAL_YY] += a1 * a1
        st[ST_PCAL_YY + 1] += a1 * b1
        st[ST_PCAL_YY + 2] += b1 * a1
        st[ST_PCAL_YY + 3] += b1 * b1
        st[ST_PCAL_N] += 1.0
        st[ST_PCAL_DT] += t1 - t2
    st[h + 2] = a2
    st[h + 1] = a1
    st[h] = y1
    st[h + 5] = b2
    st[h + 4] = b1
    st[h + 3] = y2
    st[h + 8] = u2
    st[h + 7] = u1
    st[h + 6] = ik
    st[h + 10] = t1
    st[h + 9] = tk


def ekf_batch(
    cfg: FloatArray,
    st: FloatArray,
    t: FloatArray,
    current: FloatArray,
    w1_meas: FloatArray,
    w2_meas: FloatArray,
    calibrate: Callable[[FloatArray, FloatArray, float], FloatArray] | None = None,
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, int]:
    """Run the EKF over one batch, updating ``st`` in place.

    When the plant-calibration segment ends inside the batch the compiled loop stops after
    that sample; ``calibrate(st, cfg, t_end)`` then fits the plant from the sums in ``st``
    (updating ``st``) and returns the configuration vector to continue with (the calibrated
    plant and skew in place of the configured ones). The stop depends on sample times only,
    so the outputs do not depend on how the stream is split into batches.

    Returns:
        (out, windows, events, snapshots, status): ``out`` has ``OUT_LEN`` rows of per-sample
        outputs; ``windows`` / ``events`` / ``snapshots`` are row arrays (``WIN_LEN`` /
        ``EV_LEN`` / ``RS_BASE_LEN + 2 bins`` columns) of completed health windows, Dn level
        changes and prognosis snapshots; ``status`` is 0, or -1 when the times inside the
        batch are not strictly increasing (the state is then left untouched).
    """
    n = t.shape[0]
    out = np.empty((OUT_LEN, n))
    wins: list[FloatArray] = []
    evs: list[FloatArray] = []
    snaps: list[FloatArray] = []
    start = 0
    while True:
        windows, events, snap, stop = _ekf_kernel(
            cfg, st, t, current, w1_meas, w2_meas, out, start
        )
        if stop < 0:
            return np.full((OUT_LEN, n), np.nan), windows, events, snap, -1
        wins.append(windows)
        evs.append(events)
        snaps.append(snap)
        if stop == 0:
            break
        start = stop
        if calibrate is not None:
            cfg = calibrate(st, cfg, float(t[start - 1]))
        if start >= n:
            break
    if len(wins) == 1:
        return out, wins[0], evs[0], snaps[0], 0
    return out, np.vstack(wins), np.vstack(evs), np.vstack(snaps), 0


@njit(cache=True, nogil=True, error_model="numpy", fastmath=FMA)
def _ekf_kernel(
    cfg: FloatArray,
    st: FloatArray,
    t: FloatArray,
    current: FloatArray,
    w1_meas: FloatArray,
    w2_meas: FloatArray,
    out: FloatArray,
    start: int,
) -> tuple[FloatArray, FloatArray, FloatArray, int]:
    """The compiled loop of :func:`ekf_batch` over samples ``start ..`` of the batch, writing
    their columns of ``out``; returns the index after the sample it stopped at (the end of the
    plant-calibration segment), 0 when it ran to the end, -1 on times out of order."""
    n = t.shape[0]
    bins = int(cfg[CFG_OBS_BINS])
    t_prev = t[start] if n > start else 0.0
    for k in range(start + 1, n):
        t_k = t[k]
        if not t_k > t_prev:
            out[:] = np.nan
            return np.empty((0, WIN_LEN)), np.empty((0, EV_LEN)), np.empty((0, 1)), -1
        t_prev = t_k
    stop = 0
    hw = cfg[CFG_HEALTH_WINDOW]
    windows = np.empty((int((n - start) // hw) + 1, WIN_LEN))
    # at most one level change per sample (reserved, not touched: the rows written are few)
    events = np.empty((n - start, EV_LEN))
    every = cfg[CFG_RUL_EVERY]
    dt_nominal = cfg[CFG_DT_NOMINAL]
    n_snap_max = 0
    if math.isfinite(every) and n > start:
        t_next0 = st[ST_T_NEXT_RUL]
        if not math.isfinite(t_next0):
            t_next0 = t[start] + every
        n_snap_max = int(max(0.0, (t[n - 1] - t_next0) / every)) + 2
    snaps = np.empty((n_snap_max, RS_BASE_LEN + 2 * bins))
    n_win = 0
    n_ev = 0
    n_snap = 0

    rv0 = cfg[CFG_RV]
    rv1 = cfg[CFG_RV + 1]
    qd0 = cfg[CFG_Q]
    qd1 = cfg[CFG_Q + 1]
    qd2 = cfg[CFG_Q + 2]
    qd3 = cfg[CFG_Q + 3]
    bc = cfg[CFG_BOUND_C]
    dn_watch = cfg[CFG_DN_WATCH]
    dn_alert = cfg[CFG_DN_ALERT]
    dn_hyst = cfg[CFG_DN_HYST]
    nis1_lo = cfg[CFG_NIS_BOUNDS]
    nis1_hi = cfg[CFG_NIS_BOUNDS + 1]
    nis2_lo = cfg[CFG_NIS_BOUNDS + 2]
    nis2_hi = cfg[CFG_NIS_BOUNDS + 3]
    bin_samples = cfg[CFG_OBS_BIN_SAMPLES]
    project = cfg[CFG_PROJECT] == 1.0
    var_i = cfg[CFG_CURRENT_VAR]
    interval = cfg[CFG_INPUT_INTERVAL] >= 1.0
    edge_model = cfg[CFG_INPUT_INTERVAL] == 2.0
    timing = cfg[CFG_INPUT_TIMING]
    memory = cfg[CFG_ADAPT_MEMORY]
    inv_memory = 1.0 / memory if memory > 0.0 else 0.0
    dt_timing = np.nan  # the spacing (timing / dt)^2 was last computed for
    g_min_of = np.nan  # the median gain up_min and down_min were last computed for
    up_min = down_min = 1.0
    timing2 = 0.0
    gate1 = cfg[CFG_GATE]
    gate2 = cfg[CFG_GATE + 1]
    alpha_max = cfg[CFG_ALPHA_MAX]
    m_walk2 = cfg[CFG_M_WALK] * cfg[CFG_M_WALK]
    m_ref = 0.1 * abs(cfg[CFG_M0])
    r1 = cfg[CFG_R1]
    r2 = cfg[CFG_R2]
    fric1 = cfg[CFG_B1]
    fric2 = cfg[CFG_B2]
    ij1 = cfg[CFG_INV_J1]
    ij2 = cfg[CFG_INV_J2]
    bal1 = math.sqrt(ij2 / ij1)  # speed scaling of the series order's norm (discretize_plant)
    ibal1 = 1.0 / bal1
    km = cfg[CFG_KM]
    f44 = cfg[CFG_F44]
    expm_tol = cfg[CFG_EXPM_TOL]
    skew = cfg[CFG_SKEW]
    pcal_on = cfg[CFG_PCAL] == 1.0
    # a calibration under way stops if the configuration no longer asks for it
    pcal_end = st[ST_PCAL_END] if pcal_on else np.nan
    pcal_int = st[ST_PCAL_INT]
    half_calib = 0.5 * cfg[CFG_CALIB_S]
    scale_on = cfg[CFG_COV_SCALE] == 1.0
    alpha_floor = cfg[CFG_ALPHA_FLOOR]
    nis_ratio = st[ST_NIS_RATIO]
    nis_n = st[ST_NIS_N]
    cs = math.sqrt(nis_ratio) if scale_on and nis_ratio > 1.0 else 1.0

    init = st[ST_INIT] == 1.0
    a0_inv_of = np.nan  # the alpha0 inv_a0 was last computed for
    inv_a0 = np.nan
    qw0 = st[ST_QW]
    qw1 = st[ST_QW + 1]
    pr0 = st[ST_Y_RES]
    pr1 = st[ST_Y_RES + 1]
    h00 = st[ST_Y_HIST]
    h01 = st[ST_Y_HIST + 1]
    h02 = st[ST_Y_HIST + 2]
    h10 = st[ST_Y_HIST + 3]
    h11 = st[ST_Y_HIST + 4]
    h12 = st[ST_Y_HIST + 5]
    qr0 = st[ST_QTL_RES]
    qr1 = st[ST_QTL_RES + 1]
    nr0 = st[ST_N_QTL_RES]
    nr1 = st[ST_N_QTL_RES + 1]
    ph00 = 1.0
    ph01 = 0.0
    ph10 = 0.0
    ph11 = 1.0
    qt0 = st[ST_QTL]
    qt1 = st[ST_QTL + 1]
    nq0 = st[ST_N_QTL]
    nq1 = st[ST_N_QTL + 1]
    rh0 = st[ST_R_HAT]
    rh1 = st[ST_R_HAT + 1]
    if not math.isfinite(rh0):
        rh0 = rv0
    if not math.isfinite(rh1):
        rh1 = rv1
    n_adapt = st[ST_N_ADAPT]
    du_prev = st[ST_DU_PREV]
    alpha0 = st[ST_ALPHA0]
    calib_end = st[ST_CALIB_T_END]
    calib_int = st[ST_CALIB_INT]
    w_n_gated = st[ST_W_N_GATED]
    n_gated = st[ST_N_GATED]
    a0_best = st[ST_A0_BEST]
    a0_var = st[ST_A0_VAR]
    t_last = st[ST_T_LAST]
    u_held = st[ST_U_HELD]
    x0 = st[ST_X]
    x1 = st[ST_X + 1]
    x2 = st[ST_X + 2]
    x3 = st[ST_X + 3]
    if init and not math.isfinite(alpha0) and not math.isfinite(calib_end):
        # a state upgraded from version 1 (always run with a configured alpha0)
        alpha0 = cfg[CFG_ALPHA0] if math.isfinite(cfg[CFG_ALPHA0]) else st[ST_X + 2]
    p00 = st[ST_P]
    p01 = st[ST_P + 1]
    p02 = st[ST_P + 2]
    p03 = st[ST_P + 3]
    p11 = st[ST_P + 4]
    p12 = st[ST_P + 5]
    p13 = st[ST_P + 6]
    p22 = st[ST_P + 7]
    p23 = st[ST_P + 8]
    p33 = st[ST_P + 9]
    level = int(st[ST_DN_LEVEL])
    t_next = st[ST_T_NEXT_RUL]
    w_count = st[ST_W_COUNT]
    nu_prev0 = st[ST_NU_PREV]
    nu_prev1 = st[ST_NU_PREV + 1]
    ob_udt = st[ST_OB_SUM_UDT]
    ob_dt = st[ST_OB_SUM_DT]
    ob_count = st[ST_OB_COUNT]
    ob_head = int(st[ST_OB_HEAD])
    ob_filled = st[ST_OB_FILLED]
    # health-window sums in locals (written back at window ends and at the end of the batch)
    w_t0 = st[ST_W_T0]
    w_dn0 = st[ST_W_DN0]
    w_n_upd = st[ST_W_N_UPD]
    w_sum_nis = st[ST_W_SUM_NIS]
    w_sum_dof = st[ST_W_SUM_DOF]
    w_n_nis_out = st[ST_W_N_NIS_OUT]
    w_n_e_out = st[ST_W_N_E_OUT]
    w_n_e = st[ST_W_N_E]
    c0_n = st[ST_W_CH + CH_N]
    c0_sum = st[ST_W_CH + CH_SUM]
    c0_sum2 = st[ST_W_CH + CH_SUM2]
    c0_lag = st[ST_W_CH + CH_LAG]
    c0_nlag = st[ST_W_CH + CH_N_LAG]
    c1_n = st[ST_W_CH + CH_LEN + CH_N]
    c1_sum = st[ST_W_CH + CH_LEN + CH_SUM]
    c1_sum2 = st[ST_W_CH + CH_LEN + CH_SUM2]
    c1_lag = st[ST_W_CH + CH_LEN + CH_LAG]
    c1_nlag = st[ST_W_CH + CH_LEN + CH_N_LAG]

    for k in range(start, n):
        tk = t[k]
        y0 = w1_meas[k]
        y1 = w2_meas[k]
        have0 = math.isfinite(y0)
        have1 = math.isfinite(y1)
        predicted = init
        if not init:
            # prior at the first sample: configured speeds, else the first measurement (else 0)
            w0c = cfg[CFG_W0]
            w1c = cfg[CFG_W0 + 1]
            x0 = w0c if math.isfinite(w0c) else (y0 if have0 else 0.0)
            x1 = w1c if math.isfinite(w1c) else (y1 if have1 else 0.0)
            alpha0 = cfg[CFG_ALPHA0]
            x3 = cfg[CFG_M0]
            p00 = cfg[CFG_P0]
            p11 = cfg[CFG_P0 + 1]
            p33 = cfg[CFG_P0 + 3]
            if math.isfinite(alpha0):
                x2 = alpha0
                p22 = cfg[CFG_P0 + 2]
                a0_var = 0.0
            else:
                # alpha0 unknown: a wide prior, estimated over the calibration segment
                x2 = cfg[CFG_ALPHA_PRIOR]
                p22 = cfg[CFG_ALPHA_PRIOR_VAR]
                calib_end = tk + cfg[CFG_CALIB_S]
                calib_int = 0.0
            p01 = p02 = p03 = p12 = p13 = p23 = 0.0
            u_held = 0.0
            du_prev = 0.0
            init = True
            if pcal_on:
                pcal_end = tk + cfg[CFG_CALIB_S]
                pcal_int = 0.0
            if math.isfinite(every) and not math.isfinite(t_next):
                t_next = tk + every
        else:
            dt = tk - t_last
            if dt_nominal > 0.0 and abs(dt - dt_nominal) <= DT_SNAP_TOL * dt_nominal:
                dt = dt_nominal
            # Wear does not heal (m >= 0, seed section 3.2): a negative m-hat, a statistical
            # excursion, does not make alpha grow in the prediction. Without this the filter
            # diverges once alpha nears 0 and m becomes unobservable.
            m_wear = max(x3, 0.0) if project else x3
            # Input over [t_{k-1}, t_k]. "interval": the mean of the bounding samples, and the
            # variance of an edge at an unknown instant of the interval (uniform: dI^2 / 12)
            # plus a timing allowance (skew / jitter between channels) on this interval and the
            # previous one; "hold": the earlier sample (seed eq. 16).
            # "edge": a change large enough to matter (its rank-one variance above a tenth of
            # the w1 noise) is a step at an unknown instant of the interval, moving the state by
            # du g(h) with the mean and covariance of edge_moments (the held current before it).
            u_step = u_held
            var_u = var_i
            edge = False
            if interval:
                ik = current[k]
                du = ik - u_held if math.isfinite(ik) else 0.0
                big = max(du * du, du_prev * du_prev)
                if big > 0.0:
                    if dt != dt_timing:
                        timing2 = (timing / dt) ** 2
                        dt_timing = dt
                    var_u += big * timing2
                kbdt = km * ij1 * dt
                edge = edge_model and du * du * kbdt * kbdt > 1.2 * rh0
                if not edge:
                    u_step = u_held + 0.5 * du
                    var_u += du * du * (1.0 / 12.0)
                du_prev = du
            if edge:
                (
                    em0, em1, em2, ec00, ec01, ec02, ec11, ec12, ec22,
                ) = edge_moments(cfg, x0, x1, x2, m_wear, dt)  # fmt: skip
            (
                e00, e01, e02, e10, e11, e12, e20, e21, e22, c0, c1, c2, e44, dx0, dx1, dx2,
                gb0, gb1, gb2, _, _,
            ) = discretize_plant(
                r1, r2, fric1, fric2, ij1, ij2, km, f44, expm_tol, bal1, ibal1, x0, x1, x2, m_wear,
                u_step, dt,
            )  # fmt: skip
            ph00 = e00
            ph01 = e01
            ph10 = e10
            ph11 = e11
            if edge:
                dx0 += du * em0
                dx1 += du * em1
                dx2 += du * em2
            if not math.isfinite(alpha0) or math.isfinite(pcal_end):
                dvc = r1 * x0 - r2 * x1
                if not math.isfinite(alpha0):
                    calib_int += dvc * dvc * dt
                if math.isfinite(pcal_end):
                    pcal_int += dvc * dvc * dt
            # random walk of m relative to its estimate (seed assumption iii)
            mref = max(x3, m_ref)
            qm = qd3 + m_walk2 * mref * mref * dt
            x0 += dx0
            x1 += dx1
            x2 += dx2
            # P- = Phi P Phi^T + Q, Phi = [[E, c], [0, e44]]
            m00 = e00 * p00 + e01 * p01 + e02 * p02 + c0 * p03
            m01 = e00 * p01 + e01 * p11 + e02 * p12 + c0 * p13
            m02 = e00 * p02 + e01 * p12 + e02 * p22 + c0 * p23
            m10 = e10 * p00 + e11 * p01 + e12 * p02 + c1 * p03
            m11 = e10 * p01 + e11 * p11 + e12 * p12 + c1 * p13
            m12 = e10 * p02 + e11 * p12 + e12 * p22 + c1 * p23
            m20 = e20 * p00 + e21 * p01 + e22 * p02 + c2 * p03
            m21 = e20 * p01 + e21 * p11 + e22 * p12 + c2 * p13
            m22 = e20 * p02 + e21 * p12 + e22 * p22 + c2 * p23
            w0 = e00 * p03 + e01 * p13 + e02 * p23 + c0 * p33
            w1 = e10 * p03 + e11 * p13 + e12 * p23 + c1 * p33
            w2 = e20 * p03 + e21 * p13 + e22 * p23 + c2 * p33
            # + Q + var(I) gb gb^T: the held current's error over the step
            n00 = m00 * e00 + m01 * e01 + m02 * e02 + w0 * c0 + qd0 + qw0 + var_u * gb0 * gb0
            n01 = m00 * e10 + m01 * e11 + m02 * e12 + w0 * c1 + var_u * gb0 * gb1
            n02 = m00 * e20 + m01 * e21 + m02 * e22 + w0 * c2 + var_u * gb0 * gb2
            n11 = m10 * e10 + m11 * e11 + m12 * e12 + w1 * c1 + qd1 + qw1 + var_u * gb1 * gb1
            n12 = m10 * e20 + m11 * e21 + m12 * e22 + w1 * c2 + var_u * gb1 * gb2
            n22 = m20 * e20 + m21 * e21 + m22 * e22 + w2 * c2 + qd2 + var_u * gb2 * gb2
            if edge:
                d2 = du * du
                n00 += d2 * ec00
                n01 += d2 * ec01
                n02 += d2 * ec02
                n11 += d2 * ec11
                n12 += d2 * ec12
                n22 += d2 * ec22
            p03 = w0 * e44
            p13 = w1 * e44
            p23 = w2 * e44
            p33 = p33 * e44 * e44 + qm
            p00, p01, p02, p11, p12, p22 = n00, n01, n02, n11, n12, n22
            # observed-load ring: the current held over this step, binned by steps
            if bins > 0:
                ob_udt += u_held * dt
                ob_dt += dt
                ob_count += 1.0
                if ob_count >= bin_samples:
                    st[ST_RING + ob_head] = ob_udt / ob_dt
                    st[ST_RING + bins + ob_head] = ob_dt
                    ob_head = (ob_head + 1) % bins
                    ob_filled = min(ob_filled + 1.0, float(bins))
                    ob_udt = 0.0
                    ob_dt = 0.0
                    ob_count = 0.0
        y0_raw = y0
        if skew != 0.0 and have0 and predicted:
            # the w1 sample is taken skew seconds after the w2 sample (the filter's time): it
            # is compared with w1 + skew dw1/dt, the slope from the model at the prior
            ik = current[k]
            u_now = ik if math.isfinite(ik) else u_held
            dvp = r1 * x0 - r2 * x1
            y0 = y0 - skew * (-x2 * r1 * dvp - fric1 * x0 + km * u_now) * ij1
        # --- noise estimation (when adaptive).
        # Sensor noise R: two running medians per speed, each of a statistic that is the noise
        # plus a non-negative contamination, so the smaller estimate is kept:
        # * the third difference y_k - 3 y_k-1 + 3 y_k-2 - y_k-3 (white noise: N(0, 20 r));
        #   contaminated by the signal, which it does not remove at low sample rates;
        # * the one-step residual rho_k = (y_k - x_{k|k-1}) - Ew pr, pr the previous posterior
        #   residual y_{k-1} - x_{k-1|k-1}, Ew the speed block of Phi: rho_k = v_k - Ew v_{k-1}
        #   + state error, so Var(rho_j) = r_j + sum_i Ew_ji^2 r_i (a 2x2 system for r); the
        #   model's step removes the signal, but an estimate still converging contaminates it.
        # The medians (robust to the transients of unmodelled inputs) move by multiplicative
        # steps of 1 / (n + 1), then at least 2 dt / memory.
        # Process noise of the speeds (model, input-timing and discretization error) by
        # covariance matching of the innovations against their predicted variance:
        # q_j <- max(0, q_j + d (min(e_j^2, gate S_jj) - S_jj)), d = max(1 / (n + 2), dt / memory).
        if memory > 0.0:
            g_min = 2.0 * (tk - t_last) * inv_memory if predicted else 1.0
            if g_min != g_min_of:
                # the factors depend on the spacing only: recomputed when it changes
                up_min = 1.0 + g_min
                down_min = 1.0 / up_min
                g_min_of = g_min
            if have0:
                if math.isfinite(h02):
                    a3 = abs(y0_raw - 3.0 * h00 + 3.0 * h01 - h02)
                    qt0 = _median_step(qt0, a3, nq0, g_min, up_min, down_min)
                    nq0 += 1.0
                h02 = h01
                h01 = h00
                h00 = y0_raw
            else:
                h00 = h01 = h02 = np.nan
            if have1:
                if math.isfinite(h12):
                    a3 = abs(y1 - 3.0 * h10 + 3.0 * h11 - h12)
                    qt1 = _median_step(qt1, a3, nq1, g_min, up_min, down_min)
                    nq1 += 1.0
                h12 = h11
                h11 = h10
                h10 = y1
            else:
                h10 = h11 = h12 = np.nan
            if predicted and math.isfinite(pr0) and math.isfinite(pr1):
                if have0:
                    a3 = abs(y0 - x0 - ph00 * pr0 - ph01 * pr1)
                    qr0 = _median_step(qr0, a3, nr0, g_min, up_min, down_min)
                    nr0 += 1.0
                if have1:
                    a3 = abs(y1 - x1 - ph10 * pr0 - ph11 * pr1)
                    qr1 = _median_step(qr1, a3, nr1, g_min, up_min, down_min)
                    nr1 += 1.0
            if nq0 >= MIN_DIFFS:
                rh0 = (qt0 * D3_TO_SIGMA) ** 2
            if nq1 >= MIN_DIFFS:
                rh1 = (qt1 * D3_TO_SIGMA) ** 2
            if nr0 >= MIN_DIFFS and nr1 >= MIN_DIFFS:
                v0 = (qr0 * MEDIAN_TO_SIGMA) ** 2
                v1 = (qr1 * MEDIAN_TO_SIGMA) ** 2
                ca = 1.0 + ph00 * ph00
                cb = ph01 * ph01
                cc = ph10 * ph10
                cd = 1.0 + ph11 * ph11
                rdet = 1.0 / (ca * cd - cb * cc)
                rh0 = min(rh0, max((v0 * cd - cb * v1) * rdet, NOISE_FLOOR * v0 / ca))
                rh1 = min(rh1, max((ca * v1 - cc * v0) * rdet, NOISE_FLOOR * v1 / cd))
            if predicted and nq0 >= MIN_DIFFS and nq1 >= MIN_DIFFS:
                d = _matching_step(n_adapt, 0.5 * g_min)
                if have0:
                    ea = y0 - x0
                    sa = p00 + rh0
                    qw0 = max(qw0 + d * (min(ea * ea, gate1 * sa) - sa), 0.0)
                if have1:
                    ea = y1 - x1
                    sa = p11 + rh1
                    qw1 = max(qw1 + d * (min(ea * ea, gate1 * sa) - sa), 0.0)
                n_adapt += 1.0
        rv0 = rh0
        rv1 = rh1
        # --- update (Joseph form), with the measured channels only; an update whose NIS
        # exceeds the gate is down-weighted: S scaled by lam = NIS / gate (K / lam, and the
        # Joseph form with the matching R_eff = lam S - H P H^T)
        e0 = np.nan
        e1 = np.nan
        s00 = p00 + rv0
        s11 = p11 + rv1
        nis = np.nan
        dof = 0.0
        gated = 0.0
        if have0 and have1:
            e0 = y0 - x0
            e1 = y1 - x1
            s01 = p01
            rdet = 1.0 / (s00 * s11 - s01 * s01)
            i00 = s11 * rdet
            i01 = -s01 * rdet
            i11 = s00 * rdet
            nis = e0 * (i00 * e0 + i01 * e1) + e1 * (i01 * e0 + i11 * e1)
            dof = 2.0
            r01 = 0.0
            if nis > gate2:
                lam = nis / gate2
                gated = 1.0
                w_n_gated += 1.0
                n_gated += 1.0
                rv0 = lam * rv0 + (lam - 1.0) * p00
                rv1 = lam * rv1 + (lam - 1.0) * p11
                r01 = (lam - 1.0) * p01
                il = 1.0 / lam
                i00 *= il
                i01 *= il
                i11 *= il
            # K = P H^T S^-1, rows 0..3
            k00 = p00 * i00 + p01 * i01
            k01 = p00 * i01 + p01 * i11
            k10 = p01 * i00 + p11 * i01
            k11 = p01 * i01 + p11 * i11
            k20 = p02 * i00 + p12 * i01
            k21 = p02 * i01 + p12 * i11
            k30 = p03 * i00 + p13 * i01
            k31 = p03 * i01 + p13 * i11
            x0 += k00 * e0 + k01 * e1
            x1 += k10 * e0 + k11 * e1
            x2 += k20 * e0 + k21 * e1
            x3 += k30 * e0 + k31 * e1
            # A = (I - K H) P (full rows), then P = A - A[:, :2] K^T + K R K^T
            a00 = p00 - k00 * p00 - k01 * p01
            a01 = p01 - k00 * p01 - k01 * p11
            a02 = p02 - k00 * p02 - k01 * p12
            a03 = p03 - k00 * p03 - k01 * p13
            a10 = p01 - k10 * p00 - k11 * p01
            a11 = p11 - k10 * p01 - k11 * p11
            a12 = p12 - k10 * p02 - k11 * p12
            a13 = p13 - k10 * p03 - k11 * p13
            a20 = p02 - k20 * p00 - k21 * p01
            a21 = p12 - k20 * p01 - k21 * p11
            a22 = p22 - k20 * p02 - k21 * p12
            a23 = p23 - k20 * p03 - k21 * p13
            a30 = p03 - k30 * p00 - k31 * p01
            a31 = p13 - k30 * p01 - k31 * p11
            a33 = p33 - k30 * p03 - k31 * p13
            p00 = a00 - a00 * k00 - a01 * k01 + rv0 * k00 * k00 + rv1 * k01 * k01
            p01 = a01 - a00 * k10 - a01 * k11 + rv0 * k00 * k10 + rv1 * k01 * k11
            p02 = a02 - a00 * k20 - a01 * k21 + rv0 * k00 * k20 + rv1 * k01 * k21
            p03 = a03 - a00 * k30 - a01 * k31 + rv0 * k00 * k30 + rv1 * k01 * k31
            p11 = a11 - a10 * k10 - a11 * k11 + rv0 * k10 * k10 + rv1 * k11 * k11
            p12 = a12 - a10 * k20 - a11 * k21 + rv0 * k10 * k20 + rv1 * k11 * k21
            p13 = a13 - a10 * k30 - a11 * k31 + rv0 * k10 * k30 + rv1 * k11 * k31
            p22 = a22 - a20 * k20 - a21 * k21 + rv0 * k20 * k20 + rv1 * k21 * k21
            p23 = a23 - a20 * k30 - a21 * k31 + rv0 * k20 * k30 + rv1 * k21 * k31
            p33 = a33 - a30 * k30 - a31 * k31 + rv0 * k30 * k30 + rv1 * k31 * k31
            if r01 != 0.0:
                # the cross term of the gated R_eff, added last (it is zero otherwise)
                p00 += r01 * (k00 * k01 + k01 * k00)
                p01 += r01 * (k00 * k11 + k01 * k10)
                p02 += r01 * (k00 * k21 + k01 * k20)
                p03 += r01 * (k00 * k31 + k01 * k30)
                p11 += r01 * (k10 * k11 + k11 * k10)
                p12 += r01 * (k10 * k21 + k11 * k20)
                p13 += r01 * (k10 * k31 + k11 * k30)
                p22 += r01 * (k20 * k21 + k21 * k20)
                p23 += r01 * (k20 * k31 + k21 * k30)
                p33 += r01 * (k30 * k31 + k31 * k30)
        elif have0 or have1:
            # scalar update with channel j: K = P[:, j] / S, P = A - A[:, j] K^T + r K K^T
            if have0:
                e = y0 - x0
                e0 = e
                sj = s00
                rj = rv0
                h0 = p00
                h1 = p01
                h2 = p02
                h3 = p03
            else:
                e = y1 - x1
                e1 = e
                sj = s11
                rj = rv1
                h0 = p01
                h1 = p11
                h2 = p12
                h3 = p13
            nis = e * e / sj
            dof = 1.0
            hj = h0 if have0 else h1
            if nis > gate1:
                lam = nis / gate1
                gated = 1.0
                w_n_gated += 1.0
                n_gated += 1.0
                rj = lam * rj + (lam - 1.0) * hj
                sj = lam * sj
            kk0 = h0 / sj
            kk1 = h1 / sj
            kk2 = h2 / sj
            kk3 = h3 / sj
            x0 += kk0 * e
            x1 += kk1 * e
            x2 += kk2 * e
            x3 += kk3 * e
            # A = P - K h^T (h = P[:, j]); A[:, j] = h - K S... computed directly
            a00 = p00 - kk0 * h0
            a01 = p01 - kk0 * h1
            a02 = p02 - kk0 * h2
            a03 = p03 - kk0 * h3
            a11 = p11 - kk1 * h1
            a12 = p12 - kk1 * h2
            a13 = p13 - kk1 * h3
            a22 = p22 - kk2 * h2
            a23 = p23 - kk2 * h3
            a33 = p33 - kk3 * h3
            # A[:, j] = h - K h_j
            b0 = h0 - kk0 * hj
            b1 = h1 - kk1 * hj
            b2 = h2 - kk2 * hj
            b3 = h3 - kk3 * hj
            p00 = a00 - b0 * kk0 + rj * kk0 * kk0
            p01 = a01 - b0 * kk1 + rj * kk0 * kk1
            p02 = a02 - b0 * kk2 + rj * kk0 * kk2
            p03 = a03 - b0 * kk3 + rj * kk0 * kk3
            p11 = a11 - b1 * kk1 + rj * kk1 * kk1
            p12 = a12 - b1 * kk2 + rj * kk1 * kk2
            p13 = a13 - b1 * kk3 + rj * kk1 * kk3
            p22 = a22 - b2 * kk2 + rj * kk2 * kk2
            p23 = a23 - b2 * kk3 + rj * kk2 * kk3
            p33 = a33 - b3 * kk3 + rj * kk3 * kk3
        # physical projection of the estimate (seed section 3.2: alpha >= 0, m >= 0, and alpha
        # only wears from alpha0): the mean is moved onto the bounds, P is kept
        if project:
            x3 = max(x3, 0.0)
            if math.isfinite(alpha0):
                x2 = min(x2, alpha0 * alpha_max)
            x2 = max(x2, 0.0)
        # posterior residuals for the next step's noise estimate
        pr0 = y0 - x0 if have0 else np.nan
        pr1 = y1 - x1 if have1 else np.nan
        # alpha0 calibration: each sample gives a candidate alpha-hat carried back over the
        # wear so far, ln alpha0 = ln alpha(t) + m int_0^t dv^2 dt (eq. 7), of variance
        # P_aa / alpha^2 + I^2 P_mm + 2 I P_am / alpha; the candidate of least variance is
        # kept and fixed at the end of the segment (the log factor capped at CALIB_MAX_LOG)
        if not math.isfinite(alpha0) and x2 > 0.0:
            lf = min(max(x3, 0.0) * calib_int, CALIB_MAX_LOG)
            v_a0 = p22 / (x2 * x2) + calib_int * calib_int * p33 + 2.0 * calib_int * p23 / x2
            if not math.isfinite(a0_var) or v_a0 < a0_var:
                a0_var = v_a0
                a0_best = x2 * math.exp(lf)
            if tk >= calib_end:
                alpha0 = a0_best
        # plant calibration: the sums of the instrumental-variable regression (healthy start)
        if math.isfinite(pcal_end):
            if tk >= pcal_end - half_calib and not math.isfinite(st[ST_PCAL_ALPHA_MID]):
                st[ST_PCAL_ALPHA_MID] = x2
                st[ST_PCAL_INT_MID] = pcal_int
            _pcal_accumulate(cfg, st, tk, y0_raw, y1, current[k], pcal_end - half_calib)
        # --- per-sample outputs
        # covariance scale of the reported bands: NIS / dof of the last completed health window
        # (set at the window's end below), when above 1. If the innovations exceed their
        # predicted covariance by lam on average, the unmodelled error acting like noise, Q and
        # R are too small by lam; scaling both leaves the gain unchanged and scales P by lam.
        sg0 = math.sqrt(max(p00, 0.0)) * cs
        sg1 = math.sqrt(max(p11, 0.0)) * cs
        sg2 = math.sqrt(max(p22, 0.0) * cs * cs + (alpha_floor * x2) ** 2)
        sg3 = math.sqrt(max(p33, 0.0)) * cs
        if alpha0 != a0_inv_of:
            inv_a0 = 1.0 / alpha0
            a0_inv_of = alpha0
        dn = 1.0 - x2 * inv_a0
        out[OUT_W1, k] = x0
        out[OUT_W2, k] = x1
        out[OUT_ALPHA, k] = x2
        out[OUT_M, k] = x3
        out[OUT_SIG, k] = bc * sg0
        out[OUT_SIG + 1, k] = bc * sg1
        out[OUT_SIG + 2, k] = bc * sg2
        out[OUT_SIG + 3, k] = bc * sg3
        out[OUT_DN, k] = dn
        out[OUT_DN_LO, k] = 1.0 - (x2 + bc * sg2) * inv_a0
        out[OUT_DN_HI, k] = 1.0 - (x2 - bc * sg2) * inv_a0
        out[OUT_E, k] = e0
        out[OUT_E + 1, k] = e1
        sd0 = math.sqrt(s00)
        sd1 = math.sqrt(s11)
        inv_sd01 = 1.0 / (sd0 * sd1)
        inv_sd0 = sd1 * inv_sd01
        inv_sd1 = sd0 * inv_sd01
        out[OUT_E_BOUND, k] = bc * sd0
        out[OUT_E_BOUND + 1, k] = bc * sd1
        out[OUT_R, k] = rh0
        out[OUT_R + 1, k] = rh1
        out[OUT_GATED, k] = gated
        out[OUT_NIS, k] = nis
        # --- health-window accumulators
        if w_count == 0.0:
            w_t0 = tk
            w_dn0 = dn
        if dof > 0.0:
            w_n_upd += 1.0
            w_sum_nis += nis
            w_sum_dof += dof
            lo = nis1_lo if dof == 1.0 else nis2_lo
            hi = nis1_hi if dof == 1.0 else nis2_hi
            if nis < lo or nis > hi:
                w_n_nis_out += 1.0
        nu0 = np.nan
        nu1 = np.nan
        if have0:
            nu0 = e0 * inv_sd0
            w_n_e += 1.0
            if abs(nu0) > bc:
                w_n_e_out += 1.0
            c0_n += 1.0
            c0_sum += nu0
            c0_sum2 += nu0 * nu0
            if math.isfinite(nu_prev0):
                c0_lag += nu0 * nu_prev0
                c0_nlag += 1.0
        if have1:
            nu1 = e1 * inv_sd1
            w_n_e += 1.0
            if abs(nu1) > bc:
                w_n_e_out += 1.0
            c1_n += 1.0
            c1_sum += nu1
            c1_sum2 += nu1 * nu1
            if math.isfinite(nu_prev1):
                c1_lag += nu1 * nu_prev1
                c1_nlag += 1.0
        nu_prev0 = nu0
        nu_prev1 = nu1
        # --- Dn level, with hysteresis on the way down
        target = _dn_target(dn, dn_watch, dn_alert)
        if target < level:
            target = max(target, _dn_target(dn + dn_hyst, dn_watch, dn_alert))
        if target != level and math.isfinite(dn):
            events[n_ev, EV_T] = tk
            events[n_ev, EV_FROM] = level
            events[n_ev, EV_TO] = target
            events[n_ev, EV_DN] = dn
            events[n_ev, EV_DN_LO] = out[OUT_DN_LO, k]
            events[n_ev, EV_DN_HI] = out[OUT_DN_HI, k]
            n_ev += 1
            level = target
        # --- held current for the next step (zero-order hold of the last valid current)
        ik = current[k]
        if math.isfinite(ik):
            u_held = ik
        t_last = tk
        # --- prognosis snapshot (a sample-time crossing: independent of batch splits)
        if math.isfinite(every) and tk >= t_next:
            snaps[n_snap, RS_T] = tk
            snaps[n_snap, RS_X] = x0
            snaps[n_snap, RS_X + 1] = x1
            snaps[n_snap, RS_X + 2] = x2
            snaps[n_snap, RS_X + 3] = x3
            snaps[n_snap, RS_P] = p00
            snaps[n_snap, RS_P + 1] = p01
            snaps[n_snap, RS_P + 2] = p02
            snaps[n_snap, RS_P + 3] = p03
            snaps[n_snap, RS_P + 4] = p11
            snaps[n_snap, RS_P + 5] = p12
            snaps[n_snap, RS_P + 6] = p13
            snaps[n_snap, RS_P + 7] = p22
            snaps[n_snap, RS_P + 8] = p23
            snaps[n_snap, RS_P + 9] = p33
            snaps[n_snap, RS_FILLED] = ob_filled
            snaps[n_snap, RS_ALPHA0] = alpha0
            snaps[n_snap, RS_A0_VAR] = a0_var
            snaps[n_snap, RS_COV_SCALE] = cs * cs
            snaps[n_snap, RS_OB_PARTIAL] = ob_dt
            for b in range(bins):
                # oldest bin first
                src = (ob_head + b) % bins
                snaps[n_snap, RS_RING + b] = st[ST_RING + src]
                snaps[n_snap, RS_RING + bins + b] = st[ST_RING + bins + src]
            n_snap += 1
            t_next += every * (math.floor((tk - t_next) / every) + 1.0)
        # --- health window complete?
        w_count += 1.0
        if w_count >= hw:
            windows[n_win, WIN_T0] = w_t0
            windows[n_win, WIN_T1] = tk
            windows[n_win, WIN_N] = w_count
            windows[n_win, WIN_N_UPD] = w_n_upd
            windows[n_win, WIN_SUM_NIS] = w_sum_nis
            windows[n_win, WIN_SUM_DOF] = w_sum_dof
            windows[n_win, WIN_N_NIS_OUT] = w_n_nis_out
            windows[n_win, WIN_N_E_OUT] = w_n_e_out
            windows[n_win, WIN_N_E] = w_n_e
            windows[n_win, WIN_CH + CH_N] = c0_n
            windows[n_win, WIN_CH + CH_SUM] = c0_sum
            windows[n_win, WIN_CH + CH_SUM2] = c0_sum2
            windows[n_win, WIN_CH + CH_LAG] = c0_lag
            windows[n_win, WIN_CH + CH_N_LAG] = c0_nlag
            windows[n_win, WIN_CH + CH_LEN + CH_N] = c1_n
            windows[n_win, WIN_CH + CH_LEN + CH_SUM] = c1_sum
            windows[n_win, WIN_CH + CH_LEN + CH_SUM2] = c1_sum2
            windows[n_win, WIN_CH + CH_LEN + CH_LAG] = c1_lag
            windows[n_win, WIN_CH + CH_LEN + CH_N_LAG] = c1_nlag
            windows[n_win, WIN_DN0] = w_dn0
            windows[n_win, WIN_X] = x0
            windows[n_win, WIN_X + 1] = x1
            windows[n_win, WIN_X + 2] = x2
            windows[n_win, WIN_X + 3] = x3
            windows[n_win, WIN_SIGMA] = sg0
            windows[n_win, WIN_SIGMA + 1] = sg1
            windows[n_win, WIN_SIGMA + 2] = sg2
            windows[n_win, WIN_SIGMA + 3] = sg3
            windows[n_win, WIN_N_GATED] = w_n_gated
            windows[n_win, WIN_R] = rh0
            windows[n_win, WIN_R + 1] = rh1
            windows[n_win, WIN_ALPHA0] = alpha0
            if w_sum_dof > 0.0:
                nis_ratio = w_sum_nis / w_sum_dof
                nis_n += 1.0
                cs = math.sqrt(nis_ratio) if scale_on and nis_ratio > 1.0 else 1.0
            windows[n_win, WIN_COV_SCALE] = nis_ratio if scale_on and nis_ratio > 1.0 else 1.0
            n_win += 1
            w_count = 0.0
            w_n_upd = w_sum_nis = w_sum_dof = w_n_nis_out = w_n_e_out = w_n_e = 0.0
            w_n_gated = 0.0
            c0_n = c0_sum = c0_sum2 = c0_lag = c0_nlag = 0.0
            c1_n = c1_sum = c1_sum2 = c1_lag = c1_nlag = 0.0
        # --- end of the plant-calibration segment: stop, the caller fits and continues
        if math.isfinite(pcal_end) and tk >= pcal_end:
            pcal_end = np.nan
            stop = k + 1
            break

    st[ST_PCAL_END] = pcal_end
    st[ST_NIS_RATIO] = nis_ratio
    st[ST_NIS_N] = nis_n
    st[ST_PCAL_INT] = pcal_int
    st[ST_INIT] = 1.0 if init else 0.0
    st[ST_T_LAST] = t_last
    st[ST_U_HELD] = u_held
    st[ST_N_SEEN] += (stop if stop > 0 else n) - start
    st[ST_X] = x0
    st[ST_X + 1] = x1
    st[ST_X + 2] = x2
    st[ST_X + 3] = x3
    st[ST_P] = p00
    st[ST_P + 1] = p01
    st[ST_P + 2] = p02
    st[ST_P + 3] = p03
    st[ST_P + 4] = p11
    st[ST_P + 5] = p12
    st[ST_P + 6] = p13
    st[ST_P + 7] = p22
    st[ST_P + 8] = p23
    st[ST_P + 9] = p33
    st[ST_DN_LEVEL] = level
    st[ST_T_NEXT_RUL] = t_next
    st[ST_W_COUNT] = w_count
    st[ST_W_T0] = w_t0
    st[ST_W_DN0] = w_dn0
    st[ST_W_N_UPD] = w_n_upd
    st[ST_W_SUM_NIS] = w_sum_nis
    st[ST_W_SUM_DOF] = w_sum_dof
    st[ST_W_N_NIS_OUT] = w_n_nis_out
    st[ST_W_N_E_OUT] = w_n_e_out
    st[ST_W_N_E] = w_n_e
    st[ST_W_CH + CH_N] = c0_n
    st[ST_W_CH + CH_SUM] = c0_sum
    st[ST_W_CH + CH_SUM2] = c0_sum2
    st[ST_W_CH + CH_LAG] = c0_lag
    st[ST_W_CH + CH_N_LAG] = c0_nlag
    st[ST_W_CH + CH_LEN + CH_N] = c1_n
    st[ST_W_CH + CH_LEN + CH_SUM] = c1_sum
    st[ST_W_CH + CH_LEN + CH_SUM2] = c1_sum2
    st[ST_W_CH + CH_LEN + CH_LAG] = c1_lag
    st[ST_W_CH + CH_LEN + CH_N_LAG] = c1_nlag
    st[ST_NU_PREV] = nu_prev0
    st[ST_NU_PREV + 1] = nu_prev1
    st[ST_OB_SUM_UDT] = ob_udt
    st[ST_OB_SUM_DT] = ob_dt
    st[ST_OB_COUNT] = ob_count
    st[ST_OB_HEAD] = ob_head
    st[ST_OB_FILLED] = ob_filled
    st[ST_R_HAT] = rh0
    st[ST_R_HAT + 1] = rh1
    st[ST_N_ADAPT] = n_adapt
    st[ST_DU_PREV] = du_prev
    st[ST_ALPHA0] = alpha0
    st[ST_CALIB_T_END] = calib_end
    st[ST_CALIB_INT] = calib_int
    st[ST_W_N_GATED] = w_n_gated
    st[ST_N_GATED] = n_gated
    st[ST_QW] = qw0
    st[ST_QW + 1] = qw1
    st[ST_A0_BEST] = a0_best
    st[ST_A0_VAR] = a0_var
    st[ST_Y_RES] = pr0
    st[ST_Y_RES + 1] = pr1
    st[ST_Y_HIST] = h00
    st[ST_Y_HIST + 1] = h01
    st[ST_Y_HIST + 2] = h02
    st[ST_Y_HIST + 3] = h10
    st[ST_Y_HIST + 4] = h11
    st[ST_Y_HIST + 5] = h12
    st[ST_QTL_RES] = qr0
    st[ST_QTL_RES + 1] = qr1
    st[ST_N_QTL_RES] = nr0
    st[ST_N_QTL_RES + 1] = nr1
    st[ST_QTL] = qt0
    st[ST_QTL + 1] = qt1
    st[ST_N_QTL] = nq0
    st[ST_N_QTL + 1] = nq1
    return windows[:n_win], events[:n_ev], snaps[:n_snap], stop


# ----------------------------------------------------------------------------- prognosis
@njit(cache=True, nogil=True, error_model="numpy", fastmath=FMA)
def segment(
    plant: FloatArray, w1: float, w2: float, al: float, u: float, tau: float
) -> tuple[float, float, float]:
    """Exact solution over ``tau`` seconds of constant current ``u`` with ``alpha`` frozen.

    With ``A(alpha)`` of seed eq. 3 (real eigenvalues ``l1 > l2``, both negative: its
    off-diagonal terms have the same sign, its trace is negative and its determinant
    ``(alpha r1^2 B2 + alpha r2^2 B1 + B1 B2) / (J1 J2)`` positive), ``x_eq = -A^-1 B u`` and the
    spectral projectors ``P1 = (A - l2 I) / (l1 - l2)``, ``P2 = I - P1``:

        x(t)  = x_eq + exp(l1 t) P1 d0 + exp(l2 t) P2 d0,       d0 = x(0) - x_eq
        dv(t) = s_eq + b1 exp(l1 t) + b2 exp(l2 t)               (c = [r1, -r2])
        int_0^tau dv^2 dt  in closed form (sums of (exp(l tau) - 1) / l terms).

    ``plant`` is ``[r1, r2, B1, B2, J1, J2, Km]``.

    Returns:
        (w1(tau), w2(tau), integral of the sliding factor dv^2 over [0, tau]).
    """
    r1 = plant[0]
    r2 = plant[1]
    j1 = plant[4]
    j2 = plant[5]
    a = -(al * r1 * r1 + plant[2]) / j1
    b = al * r1 * r2 / j1
    c = al * r1 * r2 / j2
    d = -(al * r2 * r2 + plant[3]) / j2
    bu = plant[6] * u / j1
    det = a * d - b * c
    xe1 = -d * bu / det
    xe2 = c * bu / det
    half = 0.5 * (a - d)
    bc = b * c
    sq = math.sqrt(half * half + bc)
    l2 = 0.5 * (a + d) - sq  # the larger magnitude, computed without cancellation
    l1 = det / l2
    # a - l2 = half + sq and d - l2 = sq - half; their product is bc: take the stable one
    if half >= 0.0:
        ap = half + sq
        dp = bc / ap
    else:
        dp = sq - half
        ap = bc / dp
    d1 = w1 - xe1
    d2 = w2 - xe2
    inv = 0.5 / sq
    q1 = (ap * d1 + b * d2) * inv
    q2 = (c * d1 + dp * d2) * inv
    em1 = math.expm1(l1 * tau)
    em2 = math.expm1(l2 * tau)
    ex1 = 1.0 + em1
    ex2 = 1.0 + em2
    w1e = xe1 + ex1 * q1 + ex2 * (d1 - q1)
    w2e = xe2 + ex1 * q2 + ex2 * (d2 - q2)
    seq = r1 * xe1 - r2 * xe2
    be1 = r1 * q1 - r2 * q2
    be2 = (r1 * d1 - r2 * d2) - be1
    i1 = em1 / l1
    i2 = em2 / l2
    i11 = i1 * (ex1 + 1.0) * 0.5
    i22 = i2 * (ex2 + 1.0) * 0.5
    i12 = (em1 * ex2 + em2) / (l1 + l2)
    integral = (
        seq * seq * tau
        + 2.0 * seq * (be1 * i1 + be2 * i2)
        + be1 * be1 * i11
        + 2.0 * be1 * be2 * i12
        + be2 * be2 * i22
    )
    return w1e, w2e, max(integral, 0.0)


@njit(cache=True, nogil=True, error_model="numpy")
def periodic_steady_state(
    plant: FloatArray, seg_dur: FloatArray, seg_cur: FloatArray, al: float
) -> tuple[float, float, float, float, float, float]:
    """Speeds at the start of the load period in its periodic steady state, ``alpha`` frozen.

    The one-period map is affine, ``x -> M x + g`` with ``M = expm(A T)``; its fixed point is
    ``(I - M)^-1 g``.

    Returns:
        (w1, w2, M00, M01, M10, M11).
    """
    g1 = 0.0
    g2 = 0.0
    period = 0.0
    for j in range(seg_dur.shape[0]):
        g1, g2, _ = segment(plant, g1, g2, al, seg_cur[j], seg_dur[j])
        period += seg_dur[j]
    m00, m10, _ = segment(plant, 1.0, 0.0, al, 0.0, period)
    m01, m11, _ = segment(plant, 0.0, 1.0, al, 0.0, period)
    w1, w2 = _solve_i_minus(m00, m01, m10, m11, g1, g2)
    return w1, w2, m00, m01, m10, m11


@njit(cache=True, nogil=True, error_model="numpy")
def _solve_i_minus(
    m00: float, m01: float, m10: float, m11: float, b1: float, b2: float
) -> tuple[float, float]:
    """``(I - M)^-1 b`` for a 2x2 M."""
    a00 = 1.0 - m00
    a11 = 1.0 - m11
    det = a00 * a11 - m01 * m10
    return (a11 * b1 + m01 * b2) / det, (a00 * b2 + m10 * b1) / det


@njit(cache=True, nogil=True, error_model="numpy")
def _crossing_time(
    plant: FloatArray, w1: float, w2: float, al: float, u: float, tau: float, target: float
) -> float:
    """Smallest t in [0, tau] with int_0^t dv^2 = target.

    Newton's method on the closed-form integral (its derivative is ``dv(t)^2``, from the
    speeds at t), started at the linear interpolation of the segment's integral and kept in a
    bracket that each evaluation narrows; a step that leaves the bracket or a zero slope
    bisects it instead. Stops at a step below ``1e-13 tau``, or with the bracket after 64
    evaluations (the bisection's resolution)."""
    lo = 0.0
    hi = tau
    _, _, total = segment(plant, w1, w2, al, u, tau)
    if not target < total:
        return tau
    t = tau * target / total if total > 0.0 else 0.5 * tau
    for _ in range(64):
        a1, a2, integral = segment(plant, w1, w2, al, u, t)
        f = integral - target
        if f >= 0.0:
            hi = t
        else:
            lo = t
        dv = plant[0] * a1 - plant[1] * a2
        slope = dv * dv
        t_new = t - f / slope if slope > 0.0 else 0.5 * (lo + hi)
        if not (lo < t_new < hi):
            t_new = 0.5 * (lo + hi)
        if abs(t_new - t) <= 1e-13 * tau or hi - lo <= 1e-13 * tau:
            return t_new
        t = t_new
    return hi


@njit(cache=True, nogil=True, error_model="numpy", fastmath=FMA)
def one_period(
    plant: FloatArray,
    seg_dur: FloatArray,
    seg_cur: FloatArray,
    w1: float,
    w2: float,
    ell: float,
    m: float,
    ell_fail: float,
    eps_seg: float,
    memo: FloatArray,
) -> tuple[float, float, float, float]:
    """Propagate one load period from ``(w1, w2, ell = ln alpha)`` with deterioration rate ``m``.

    Each constant-current segment is solved exactly with ``alpha`` frozen at its midpoint value
    (explicit midpoint rule on ``d ln(alpha)/dt = -m dv^2``): the second pass at
    ``exp(ell - delta_pred / 2)`` gives the speeds and ``ell_end = ell - m I``. A segment whose
    ``ln alpha`` would change by more than ``eps_seg`` is cut into equal sub-segments (exact,
    since the current is constant). The predictor ``delta_pred`` is the change over the same
    sub-segment one period earlier times the growth of the segment's change between the two
    previous periods, kept in ``memo`` (row j: sub-segment count, growth, then the changes;
    count 0: none); without it, a first pass at the start value gives ``delta_pred = m I``.

    Returns:
        (w1, w2, ell, t_cross): ``t_cross`` is the time into the period at which ``ell`` reaches
        ``ell_fail`` (NaN when it does not; the other values are then those at the end).
    """
    t = 0.0
    for j in range(seg_dur.shape[0]):
        tau = seg_dur[j]
        u = seg_cur[j]
        n_prev = int(memo[j, 0])
        growth = memo[j, 1]
        total_prev = 0.0
        if n_prev > 0:
            for sub in range(n_prev):
                total_prev += memo[j, 2 + sub]
            # the expected change, with a 20 % margin, sets the sub-segment count
            n_sub = min(max(int(math.ceil(1.2 * growth * total_prev / eps_seg)), 1), MAX_SUB)
            if n_sub != n_prev:
                n_prev = 0
        if n_prev == 0:
            _, _, i_first = segment(plant, w1, w2, math.exp(ell), u, tau)
            n_sub = min(max(int(math.ceil(m * i_first / eps_seg)), 1), MAX_SUB)
        ts = tau / n_sub
        total = 0.0
        for sub in range(n_sub):
            if n_prev > 0:
                pred = memo[j, 2 + sub] * growth
            elif n_sub == 1:
                pred = m * i_first
            else:
                _, _, i_a = segment(plant, w1, w2, math.exp(ell), u, ts)
                pred = m * i_a
            al_mid = math.exp(ell - 0.5 * pred)
            w1n, w2n, i_b = segment(plant, w1, w2, al_mid, u, ts)
            ell_new = ell - m * i_b
            if ell_new <= ell_fail:
                tc = _crossing_time(plant, w1, w2, al_mid, u, ts, (ell - ell_fail) / m)
                return w1, w2, ell_fail, t + sub * ts + tc
            memo[j, 2 + sub] = ell - ell_new
            total += ell - ell_new
            w1 = w1n
            w2 = w2n
            ell = ell_new
        memo[j, 1] = total / total_prev if n_prev > 0 and total_prev > 0.0 else 1.0
        memo[j, 0] = n_sub
        t += tau
    return w1, w2, ell, np.nan


@njit(cache=True, nogil=True, error_model="numpy")
def drifting_probe(
    plant: FloatArray,
    seg_dur: FloatArray,
    seg_cur: FloatArray,
    ell: float,
    m: float,
    eps_seg: float,
    memo: FloatArray,
) -> tuple[float, float, float, float]:
    """Per-period change of ``ln alpha`` on the slowly drifting periodic trajectory near ``ell``.

    While alpha wears, the speeds at the period start lag the frozen-alpha steady state by an
    offset that the period map contracts by ``M = expm(A T)`` and the drift renews each period:
    ``lag = (I - M)^-1 d``, ``d`` = end of one period started in the steady state at ``ell``
    minus the steady state at its end. One more period from ``steady state + lag`` gives the
    change. ``memo`` is scratch for :func:`one_period`. Returns (ell at that period's start, change over it, lag of w1, lag of w2).
    """
    memo[:, 0] = 0.0
    s1, s2, _, _, _, _ = periodic_steady_state(plant, seg_dur, seg_cur, math.exp(ell))
    w1, w2, ell_a, _ = one_period(plant, seg_dur, seg_cur, s1, s2, ell, m, -math.inf, eps_seg, memo)
    s1, s2, m00, m01, m10, m11 = periodic_steady_state(plant, seg_dur, seg_cur, math.exp(ell_a))
    lag1, lag2 = _solve_i_minus(m00, m01, m10, m11, w1 - s1, w2 - s2)
    _, _, ell_b, _ = one_period(
        plant, seg_dur, seg_cur, s1 + lag1, s2 + lag2, ell_a, m, -math.inf, eps_seg, memo
    )
    return ell_a, ell_b - ell_a, lag1, lag2


@njit(cache=True, nogil=True, error_model="numpy")
def _quadratic(
    x0: float, y0: float, x1: float, y1: float, x2: float, y2: float, x: float
) -> tuple[float, float]:
    """Value and derivative at x of the parabola through three points (Lagrange form)."""
    d0 = (x0 - x1) * (x0 - x2)
    d1 = (x1 - x0) * (x1 - x2)
    d2 = (x2 - x0) * (x2 - x1)
    value = (
        y0 * (x - x1) * (x - x2) / d0
        + y1 * (x - x0) * (x - x2) / d1
        + y2 * (x - x0) * (x - x1) / d2
    )
    slope = (
        y0 * (2.0 * x - x1 - x2) / d0
        + y1 * (2.0 * x - x0 - x2) / d1
        + y2 * (2.0 * x - x0 - x1) / d2
    )
    return value, slope


@njit(cache=True, nogil=True, error_model="numpy")
def _periods_per_ell(
    xp: float, dp: float, xm: float, dm: float, xe: float, de: float, x: float
) -> float:
    """``1 / |g(x)|``: periods per unit of ln(alpha) of the flow whose time-1 map is the
    per-period change ``delta`` (modified equation ``g = delta (1 - delta' / 2)``), with delta
    interpolated through the three probes."""
    delta, slope = _quadratic(xp, dp, xm, dm, xe, de, x)
    return 1.0 / abs(delta * (1.0 - 0.5 * slope))


@njit(cache=True, nogil=True, error_model="numpy")
def time_to_failure(
    plant: FloatArray,
    seg_dur: FloatArray,
    seg_cur: FloatArray,
    w1: float,
    w2: float,
    al: float,
    m: float,
    ell_fail: float,
    horizon: float,
    eps_seg: float,
    eps_jump: float,
    memo: FloatArray,
) -> float:
    """Time until ``ln alpha`` reaches ``ell_fail`` under the periodic load, or NaN if not
    within ``horizon`` (or never: ``m <= 0`` or no sliding).

    Periods are simulated one by one (:func:`one_period`). Where ``ln alpha`` changes by at
    most ``JUMP_MAX_DELTA`` per period, a span of up to ``eps_jump`` in ``ln alpha`` is crossed
    at once ("cycle jump"): the per-period change is probed at the middle and the end of the
    span (:func:`drifting_probe`), interpolated by a parabola with the last simulated period,
    and the number of periods is Simpson's rule on ``d n / d ell = 1 / g(ell)``; the jump takes
    the whole number of periods, so the load phase is kept. Jumps stop a few periods before
    the threshold, which is always located by simulated periods. ``memo`` is scratch of shape
    ``(segments, MAX_SUB + 2)``.
    """
    if not (math.isfinite(w1) and math.isfinite(w2) and math.isfinite(al) and math.isfinite(m)):
        return np.nan
    if al <= 0.0 or math.log(al) <= ell_fail:
        return 0.0
    if m <= 0.0:
        return np.nan
    period = 0.0
    for j in range(seg_dur.shape[0]):
        period += seg_dur[j]
    ell = math.log(al)
    t = 0.0
    settled = 0
    memo[:, 0] = 0.0
    while t <= horizon:
        ell0 = ell
        w1, w2, ell, tc = one_period(
            plant, seg_dur, seg_cur, w1, w2, ell, m, ell_fail, eps_seg, memo
        )
        if math.isfinite(tc):
            t += tc
            return t if t <= horizon else np.nan
        t += period
        delta = ell - ell0
        if not delta < 0.0:
            return np.nan  # no sliding over a whole period: alpha stays constant
        settled += 1
        if settled < 2 or -delta > JUMP_MAX_DELTA:
            continue
        span = min(eps_jump, ell - ell_fail + JUMP_MARGIN_PERIODS * delta)
        if span < JUMP_MIN_PERIODS * -delta:
            continue
        xm, dm, _, _ = drifting_probe(plant, seg_dur, seg_cur, ell - 0.5 * span, m, eps_seg, memo)
        xe, de, lag1, lag2 = drifting_probe(plant, seg_dur, seg_cur, ell - span, m, eps_seg, memo)
        target = ell - span
        n = (span / 6.0) * (
            _periods_per_ell(ell0, delta, xm, dm, xe, de, ell)
            + 4.0 * _periods_per_ell(ell0, delta, xm, dm, xe, de, ell - 0.5 * span)
            + _periods_per_ell(ell0, delta, xm, dm, xe, de, target)
        )
        k = math.floor(n)
        if k < 2.0:
            continue
        if t + k * period > horizon:
            return np.nan  # alpha stays above the threshold beyond the horizon
        # back from the target by the fractional part of a period
        ell = target + (n - k) / _periods_per_ell(ell0, delta, xm, dm, xe, de, target)
        s1, s2, _, _, _, _ = periodic_steady_state(plant, seg_dur, seg_cur, math.exp(ell))
        w1 = s1 + lag1
        w2 = s2 + lag2
        t += k * period
        settled = 1
        memo[:, 0] = 0.0
    return np.nan


@njit(cache=True, nogil=True, error_model="numpy")
def rul_times(
    plant: FloatArray,
    seg_dur: FloatArray,
    seg_cur: FloatArray,
    samples: FloatArray,
    ell_fail: float,
    horizon: float,
    eps_seg: float,
    eps_jump: float,
) -> FloatArray:
    """:func:`time_to_failure` for each row ``[w1, w2, alpha, m]`` of ``samples``."""
    n = samples.shape[0]
    times = np.empty(n)
    memo = np.zeros((seg_dur.shape[0], MAX_SUB + 2))
    for i in range(n):
        times[i] = time_to_failure(
            plant,
            seg_dur,
            seg_cur,
            samples[i, 0],
            samples[i, 1],
            samples[i, 2],
            samples[i, 3],
            ell_fail,
            horizon,
            eps_seg,
            eps_jump,
            memo,
        )
    return times


TABLE_NODES = 33  # probes of the per-period change over [ln alpha_f, ln alpha_top]
TABLE_PAD = 0.2  # the top probe starts this far above the largest ln alpha of the samples
TABLE_MIN_PERIODS = 8.0  # shorter lives are propagated period by period (time_to_failure)


@njit(cache=True, nogil=True, error_model="numpy")
def _interval_of(xs: FloatArray, x: float) -> int:
    """Index k with xs[k] <= x < xs[k + 1] (clamped to the ends) for increasing ``xs``."""
    lo = 0
    hi = xs.shape[0] - 1
    while hi - lo > 1:
        mid = (lo + hi) // 2
        if xs[mid] <= x:
            lo = mid
        else:
            hi = mid
    return lo


@njit(cache=True, nogil=True, error_model="numpy")
def _table_at(xs: FloatArray, ls: FloatArray, cum: FloatArray, x: float) -> tuple[float, float]:
    """``(A(x), L(x))``: ``L`` the piecewise-linear interpolation of ``ln |delta|`` through the
    nodes, ``A(x) = int_{xs[0]}^x exp(-L(s)) ds`` (exact for the piecewise-linear L; ``cum``
    holds A at the nodes)."""
    k = _interval_of(xs, x)
    h = x - xs[k]
    b = (ls[k + 1] - ls[k]) / (xs[k + 1] - xs[k])
    ea = math.exp(-ls[k])
    part = ea * h * (1.0 - 0.5 * b * h) if abs(b * h) < 1e-8 else -ea * math.expm1(-b * h) / b
    return cum[k] + part, ls[k] + b * h


@njit(cache=True, nogil=True, error_model="numpy")
def rul_times_tabulated(
    plant: FloatArray,
    seg_dur: FloatArray,
    seg_cur: FloatArray,
    samples: FloatArray,
    ell_fail: float,
    horizon: float,
    eps_seg: float,
    eps_jump: float,
) -> FloatArray:
    """:func:`rul_times` for a load of many segments per period, from a table of the
    per-period change shared by all samples.

    The samples differ in ``(alpha, m)`` (their speeds only in the first period's transient).
    On the slowly drifting periodic trajectory the change of ``ln alpha`` per period is
    ``delta(ell)``, and for a rate ``m`` it is ``(m / m_ref) delta(ell)`` to first order (the
    sliding factor does not depend on m; the speeds' lag behind the steady state, which does,
    is a small part). So ``delta`` is probed once, at ``m_ref`` the samples' median m, on
    ``TABLE_NODES`` points over ``[ell_fail, max ell + TABLE_PAD]`` (:func:`drifting_probe`),
    ``ln |delta|`` interpolated linearly between them. The number of periods from ``ell0`` to
    ``ell_fail`` is the integral of the modified equation's ``dn / d ell = 1 / (delta (1 -
    delta' / 2))``, to first order in delta':

        N = A(ell0) m_ref / m - (L(ell0) - L(ell_fail)) / 2 + c,
        A(x) = int_{ell_fail}^x ds / |delta(s)|,  L = ln |delta|,

    with ``c`` the periods the first period gains or loses against the drifting trajectory
    (its transient from the estimated speeds: one period simulated from the samples' mean).
    The time is ``floor(N)`` periods plus the time into the last period at which the wear
    reaches the fraction ``N - floor(N)`` of that period's, in the periodic steady state at
    ``alpha_f``. Samples with fewer than ``TABLE_MIN_PERIODS`` periods to go, above the table
    or of a non-positive m, and all samples when the probes find no sliding, are propagated by
    :func:`time_to_failure`.
    """
    n = samples.shape[0]
    n_seg = seg_dur.shape[0]
    times = np.full(n, np.nan)
    exact = np.zeros(n, dtype=np.bool_)
    memo = np.zeros((n_seg, MAX_SUB + 2))
    period = 0.0
    for j in range(n_seg):
        period += seg_dur[j]
    m_pos = np.empty(n)
    n_pos = 0
    ell_top = ell_fail
    w1_sum = 0.0
    w2_sum = 0.0
    ell_sum = 0.0
    for i in range(n):
        w1 = samples[i, 0]
        w2 = samples[i, 1]
        al = samples[i, 2]
        m = samples[i, 3]
        if not (
            math.isfinite(w1) and math.isfinite(w2) and math.isfinite(al) and math.isfinite(m)
        ):
            continue  # NaN, as time_to_failure
        if al <= 0.0 or math.log(al) <= ell_fail:
            times[i] = 0.0
            continue
        if m <= 0.0:
            continue  # never wears
        ell0 = math.log(al)
        m_pos[n_pos] = m
        n_pos += 1
        ell_top = max(ell_top, ell0)
        w1_sum += w1
        w2_sum += w2
        ell_sum += ell0
        exact[i] = True  # provisional: the table decides below
    if n_pos == 0:
        return times
    m_ref = np.median(m_pos[:n_pos])
    # the first period from the samples' mean; a life of few periods skips the table
    ell_ref = ell_sum / n_pos
    memo[:, 0] = 0.0
    _, _, ell_1, _ = one_period(
        plant, seg_dur, seg_cur, w1_sum / n_pos, w2_sum / n_pos, ell_ref, m_ref, -math.inf,
        eps_seg, memo,
    )  # fmt: skip
    ok = (ell_ref - ell_1) * 2.0 * TABLE_MIN_PERIODS < ell_ref - ell_fail
    xs = np.empty(TABLE_NODES)
    ls = np.empty(TABLE_NODES)
    span = ell_top + TABLE_PAD - ell_fail
    for k in range(TABLE_NODES if ok else 0):
        start = ell_fail + span * k / (TABLE_NODES - 1.0)
        ell_a, delta, _, _ = drifting_probe(plant, seg_dur, seg_cur, start, m_ref, eps_seg, memo)
        if not (delta < 0.0) or (k > 0 and not ell_a > xs[k - 1]):
            ok = False
            break
        xs[k] = ell_a
        ls[k] = math.log(-delta)
    # the periodic steady state at alpha_f: cumulative wear at the segment ends
    cum_w = np.empty(n_seg + 1)
    seg_t0 = np.empty(n_seg)  # start of each segment in the period
    acc = 0.0
    for j in range(n_seg):
        seg_t0[j] = acc
        acc += seg_dur[j]
    seg_w1 = np.empty(n_seg)
    seg_w2 = np.empty(n_seg)
    al_f = math.exp(ell_fail)
    if ok:
        s1, s2, _, _, _, _ = periodic_steady_state(plant, seg_dur, seg_cur, al_f)
        cum_w[0] = 0.0
        for j in range(n_seg):
            seg_w1[j] = s1
            seg_w2[j] = s2
            s1, s2, integral = segment(plant, s1, s2, al_f, seg_cur[j], seg_dur[j])
            cum_w[j + 1] = cum_w[j] + integral
        ok = bool(cum_w[n_seg] > 0.0)
    if ok:
        cum = np.empty(TABLE_NODES)
        cum[0] = 0.0
        for k in range(TABLE_NODES - 1):
            h = xs[k + 1] - xs[k]
            b = (ls[k + 1] - ls[k]) / h
            ea = math.exp(-ls[k])
            cum[k + 1] = cum[k] + (ea * h if abs(b * h) < 1e-8 else -ea * math.expm1(-b * h) / b)
        a_fail, l_fail = _table_at(xs, ls, cum, ell_fail)
        # the first period from the samples' mean against the drifting trajectory
        a_ref, l_ref = _table_at(xs, ls, cum, ell_ref)
        a_1, l_1 = _table_at(xs, ls, cum, ell_1)
        c_first = 1.0 - ((a_ref - a_1) - 0.5 * (l_ref - l_1))
        for i in range(n):
            if not exact[i]:
                continue
            ell0 = math.log(samples[i, 2])
            if ell0 > xs[TABLE_NODES - 1]:
                continue
            a0, l0 = _table_at(xs, ls, cum, ell0)
            periods = (a0 - a_fail) * m_ref / samples[i, 3] - 0.5 * (l0 - l_fail) + c_first
            if periods < TABLE_MIN_PERIODS:
                continue
            whole = math.floor(periods)
            target = (periods - whole) * cum_w[n_seg]
            j = min(_interval_of(cum_w, target), n_seg - 1)
            tc = _crossing_time(
                plant, seg_w1[j], seg_w2[j], al_f, seg_cur[j], seg_dur[j], target - cum_w[j]
            )
            t = whole * period + seg_t0[j] + tc
            times[i] = t if t <= horizon else np.nan
            exact[i] = False
    for i in range(n):
        if exact[i]:
            times[i] = time_to_failure(
                plant, seg_dur, seg_cur, samples[i, 0], samples[i, 1], samples[i, 2],
                samples[i, 3], ell_fail, horizon, eps_seg, eps_jump, memo,
            )  # fmt: skip
    return times


@njit(cache=True, nogil=True, error_model="numpy")
def _steady_clock(
    plant: FloatArray, seg_dur: FloatArray, seg_cur: FloatArray, al: float
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """The periodic steady state at ``al``: speeds at the segment starts, the segment start
    times and the cumulative ``int dv^2`` at the segment ends (first entry 0)."""
    n_seg = seg_dur.shape[0]
    seg_w1 = np.empty(n_seg)
    seg_w2 = np.empty(n_seg)
    seg_t0 = np.empty(n_seg + 1)
    cum_w = np.empty(n_seg + 1)
    s1, s2, _, _, _, _ = periodic_steady_state(plant, seg_dur, seg_cur, al)
    seg_t0[0] = 0.0
    cum_w[0] = 0.0
    for j in range(n_seg):
        seg_w1[j] = s1
        seg_w2[j] = s2
        s1, s2, integral = segment(plant, s1, s2, al, seg_cur[j], seg_dur[j])
        seg_t0[j + 1] = seg_t0[j] + seg_dur[j]
        cum_w[j + 1] = cum_w[j] + integral
    return seg_w1, seg_w2, seg_t0, cum_w


@njit(cache=True, nogil=True, error_model="numpy")
def wear_clock(
    plant: FloatArray, seg_dur: FloatArray, seg_cur: FloatArray, al: float, times: FloatArray
) -> FloatArray:
    """``C(t) = int_0^t dv^2`` in the periodic steady state at ``al`` of the load repeated from
    0, at each of ``times`` (>= 0): the wear the load's phase makes in t, at that alpha."""
    seg_w1, seg_w2, seg_t0, cum_w = _steady_clock(plant, seg_dur, seg_cur, al)
    n_seg = seg_dur.shape[0]
    period = seg_t0[n_seg]
    out = np.empty(times.shape[0])
    for i in range(times.shape[0]):
        k = math.floor(times[i] / period)
        r = times[i] - k * period
        j = min(_interval_of(seg_t0, r), n_seg - 1)
        _, _, part = segment(plant, seg_w1[j], seg_w2[j], al, seg_cur[j], r - seg_t0[j])
        out[i] = k * cum_w[n_seg] + cum_w[j] + part
    return out


@njit(cache=True, nogil=True, error_model="numpy")
def wear_clock_times(
    plant: FloatArray, seg_dur: FloatArray, seg_cur: FloatArray, al: float, wear: FloatArray
) -> FloatArray:
    """The inverse of :func:`wear_clock`: the smallest t with ``C(t)`` equal to each of
    ``wear`` (>= 0; the period's wear must be positive)."""
    seg_w1, seg_w2, seg_t0, cum_w = _steady_clock(plant, seg_dur, seg_cur, al)
    n_seg = seg_dur.shape[0]
    period = seg_t0[n_seg]
    out = np.empty(wear.shape[0])
    for i in range(wear.shape[0]):
        k = math.floor(wear[i] / cum_w[n_seg])
        r = wear[i] - k * cum_w[n_seg]
        j = min(_interval_of(cum_w, r), n_seg - 1)
        tc = _crossing_time(
            plant, seg_w1[j], seg_w2[j], al, seg_cur[j], seg_dur[j], r - cum_w[j]
        )
        out[i] = k * period + seg_t0[j] + tc
    return out
