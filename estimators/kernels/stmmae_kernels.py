"""Compiled per-sample loop of the strong-tracking multiple-model filter bank (``stmmae``).

``estimators.stmmae`` builds the bank's matrices once per configuration (:class:`BankArrays`),
packs the state into one flat float64 vector and calls :func:`bank_batch` once per batch; the
loop over samples and filters runs here, compiled by numba.

Bank layout: hypothesis 0 is the no-fault filter, then one hypothesis per monitored surface and
(optionally) one per pair of surfaces. Every filter has ``na = n + slots`` states (the model's
``n`` plus one deflection slot per surface it declares faulty; ``BankArrays.slot_surface`` maps
slots to surfaces; unused slots stay identically zero). Decisions are taken per surface on its
marginal fault probability (the sum over the hypotheses that hold it).

State vector (indices from :func:`state_layout`): a header (samples seen, covariance failures,
time of the previous sample), per filter ``x`` (na), ``P`` (na x na, row-major, full: the
one-sided strong-tracking form makes it non-symmetric), ``V`` (p x p innovation covariance
estimate) and its "started" flag; the hypothesis probabilities; the last valid inputs; per
surface the decision fields (``D_*``) and the 0.05 s block history of its deflection estimate
for the fault-kind test; the health-window accumulators (``W_*``); the inputs applied over the
step into the next sample (the servo model's output, :func:`_bank_kernel`); per surface the group
decision fields (``G_*``, used for the first half of each pair of twin halves).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numba import njit
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

VARIANT_IMPROVED = 0
VARIANT_STRONG_TRACKING = 1
VARIANT_EMMAE = 2
LIKELIHOOD_EUCLIDEAN = 0
LIKELIHOOD_GAUSSIAN = 1
LOG_2PI = math.log(2.0 * math.pi)
# floating-point contraction (fused multiply-add) and reciprocals (no assumption about NaN or
# infinity, which the code tests for). Not reassociation: with it, the kernel compiled in a
# process and the same kernel loaded from numba's cache differed in the last bits (so two
# processes could decide a marginal detection differently on the same data;
# tests/estimators/test_stmmae.py::test_a_kernel_loaded_from_numbas_cache_gives_the_bits_of_a_fresh_compile)
FAST = {"contract", "arcp"}

# scalar configuration vector
CFG_VARIANT = 0
CFG_LIKELIHOOD = 1
CFG_RHO = 2  # forgetting factor of the innovation covariance estimate
CFG_BETA = 3  # weakening factor
CFG_FLOOR = 4  # probability floor
CFG_DETECT_P = 5
CFG_CLEAR_P = 6
CFG_HOLD_S = 7
CFG_CLEAR_HOLD_S = 8
CFG_ONSET_P = 9
CFG_WINDOW = 10  # health window length, samples
CFG_SMOOTH_S = 11  # time constant of the smoothed deflection estimate
CFG_MIN_ERR = 12  # smallest |deflection estimate - command| (rad) for a detection
CFG_LIMIT = 13  # deflection estimates are clipped to +-CFG_LIMIT (rad) before smoothing
CFG_KIND_WINDOW_S = 14  # span from the start of the detection hold over which the kind is judged
CFG_REBASE = 15  # 1: on detection the other filters take the faulty surface's estimate as input
CFG_CLEAR_DEFL = 16  # clearance band of |smoothed (deflection estimate - command)| (rad)
CFG_CLEAR_SMOOTH_S = 17  # time constant of that smoothing
CFG_MIN_LLR = 18  # smallest log-likelihood ratio (fault vs no-fault) summed over the hold
CFG_OSC_CORR = 19  # autocorrelation level below which a deflection history is oscillating
CFG_OSC_SWING = 20  # swing (rad) an oscillating fault must also exceed
CFG_HOLD_ACTIVE_S = 21  # detection hold time while another surface is in fault
CFG_MIN_ERR_STD = 22  # smallest |deflection estimate - command| in posterior std of the estimate
CFG_KIND_CUT = 24  # 1: a detection cuts the open kind spans of the faults active before it
CFG_SERVO_A = 23  # servo model: a surface's applied deflection moves by this share of the gap
# to its command per model step (1 - exp(-dt / tau); 1: no lag)
CFG_KIND_TWIN = 25  # 1: a fault's kind history is conditioned on the active stuck faults' positions
CFG_GROUP = 26  # 1: twin halves are detected together ("one of the two") before one is isolated
CFG_GROUP_ISO = 27  # isolation odds a half needs while its group is detected, no other fault active
CFG_GROUP_HOLD_S = 28  # detection hold time of a group
CFG_GROUP_WINDOW_S = 29  # a group is detected only this long after its onset
CFG_RANGE_SMOOTH_S = 30  # time constant of the measurements smoothed for the operating range
CFG_OSC_SMALL_SWING = 31  # swing (rad) below which an oscillation needs the deeper lobe
CFG_OSC_SMALL_CORR = 32  # autocorrelation level of that deeper lobe
CFG_GROUP_HOLD_ACTIVE_S = 33  # detection hold time of a group while a surface is in fault
CFG_HOLD_ENDING = 34  # 1: no new detection while a detected fault is ending (fault_ending)
CFG_HOLD_TWIN_S = 35  # detection hold time of a surface while its twin is in fault
CFG_GROUP_HALF_EVIDENCE = 36  # 1: a half of a detected group is also named on the summed
# log-likelihood of its single-fault filter against its twin's (G_HALF_LLR)
CFG_KIND_WAIT_S = 37  # longest wait of a kind span's end for a fault whose onset lies inside it
CFG_DEFL_VAR_CAP = 38  # largest posterior variance of a deflection a filter contributes (rad^2)
CFG_RANGE_SETTLE_S = 39  # no new detection for this long after a sample outside the range
CFG_HALF_GROUP_ODDS = 40  # 1: a half against its twin needs CFG_GROUP_ISO before its group too
CFG_LEN = 41
COLLINEAR_STEPS = 20  # model steps over which a deflection's effect on the measurements is taken

KIND_BLOCK_S = 0.05  # the kind test reads the deflection estimate as means over 0.05 s blocks
KIND_BLOCKS = 200  # capacity of the block history: fault_kind_window_s <= 10 s
KIND_MIN_LAG_S = 0.2  # shortest lag of the autocorrelation test (half period of 2.5 Hz)
KIND_MIN_BLOCKS = 20  # a history shorter than 1 s leaves the kind undetermined
# when another surface is detected during a fault's kind span, the span is cut this long before
# that surface's onset (its probability passes the onset level some tenths of a second after
# its fault begins, and from then on its effect leaks into this fault's estimate)
KIND_CUT_MARGIN_S = 0.5
# a condition "held for T s" is met when the time since its run started reaches T less this
# tolerance: sample times are floats (k * 0.01 s: 20.06 - 20.01 is 0.04999999999999716), and
# without it a 0.05 s hold at 100 Hz took 5 or 6 samples, by the rounding of the absolute times
HOLD_TOL_S = 1e-9
KIND_PENDING = 0.0
KIND_STUCK = 1.0
KIND_OSCILLATING = 2.0

# header of the state vector
ST_N_SEEN = 0
ST_COV_FAIL = 1
ST_T_PREV = 2
ST_HEADER = 3

# decision fields of one fault hypothesis
D_ACTIVE = 0
D_ABOVE_T = 1  # start of the current run above the detection probability (NaN: none)
D_ONSET_T = 2  # start of the current run above the onset probability (NaN: none)
D_BELOW_T = 3  # start of the current run below the clearance probability while active
D_DETECTED_T = 4
D_SMOOTH = 5  # smoothed deflection estimate (rad)
D_SMOOTH_SET = 6
# precision-weighted sums of the (clipped) deflection estimate over the episode's samples above
# CFG_DETECT_P, from the start of the run that led to the detection until CFG_KIND_WINDOW_S after
# the detection (then frozen: the fault kind is judged on that span); weight 1 / P_dd
D_EP_SUM = 7  # sum of w d
D_EP_SUMSQ = 8  # sum of w d^2
D_EP_N = 9  # sum of w
D_CSMOOTH = 10  # smoothed (deflection estimate - command), rad, for the clearance test
D_LLR = 11  # log-likelihood ratio fault vs no-fault summed over the current detection run
D_KIND = 12  # KIND_PENDING, KIND_STUCK or KIND_OSCILLATING
D_KIND_T0 = 13  # start of the kind span (start of the run that led to the detection)
D_BLK_IDX = 14  # index of the block being filled (-1: none yet)
D_BLK_SUM = 15  # sum of the estimates in that block
D_BLK_N = 16  # their count
D_KIND_CORR = 17  # the autocorrelation statistic the kind was judged on
D_DEFL = 18  # latest deflection estimate (probability-weighted over the surface's filters), rad
D_PROB = 19  # latest marginal fault probability of the surface
D_LEN = 20
D_TIMES = (D_ABOVE_T, D_ONSET_T, D_BELOW_T, D_DETECTED_T, D_KIND_T0)  # NaN when unset

# group decision fields, per surface (used on the row of the first half of a twin pair)
G_ACTIVE = 0  # 1: the group is detected and neither half isolated yet
G_ABOVE_T = 1  # start of the current run of the group's detection conditions (NaN: none)
G_ONSET_T = 2  # start of the current run of the group's probability above the onset level
G_DETECTED_T = 3
G_BELOW_T = 4  # start of the current run of the group's clearance conditions
G_LLR = 5  # evidence summed over the current detection run (nats)
G_HALF_LLR = 6  # while the group is detected and no other surface in fault: log-likelihood of
# the first half's single-fault filter minus the second's, summed since the detection (nats)
G_LEN = 7
G_TIMES = (G_ABOVE_T, G_ONSET_T, G_DETECTED_T, G_BELOW_T)  # NaN when unset

# health-window accumulators
W_COUNT = 0
W_T0 = 1
W_SUM_NOMINAL = 2
W_MAX_FAULT = 3
W_MAX_FAULT_HYP = 4
W_SUM_NIS = 5
W_N_NIS = 6
W_N_ACTIVE = 7
W_COV_FAIL = 8
W_LEN = 9

# health-window rows
WIN_T0 = 0
WIN_T1 = 1
WIN_N = 2
WIN_NOMINAL_MEAN = 3
WIN_MAX_FAULT = 4
WIN_MAX_FAULT_HYP = 5
WIN_NIS_MEAN = 6  # mean of NIS / (number of measurements used), no-fault filter
WIN_ACTIVE_FRACTION = 7
WIN_COV_FAIL = 8
WIN_OUTSIDE_FRACTION = 9  # share of the samples with the smoothed measurements outside the range
WIN_NOISE_RATIO = 10  # mean of the no-fault filter's innovation energy in units of the model's R
WIN_LEN = 11

# status checks, after the (p,) smoothed measurements of the operating range
CK_OUTSIDE = 0  # samples outside the operating range in the open health window
CK_NOISE_SUM = 1  # sum of the no-fault filter's innovation energy (units of R) in that window
CK_NOISE_N = 2  # its count
CK_NOISE_SMOOTH = 3  # the innovation energy smoothed over CFG_RANGE_SMOOTH_S (NaN: none yet)
CK_LAST_OUTSIDE_T = 4  # time of the last sample outside the operating range (NaN: none yet)
CK_LEN = 5

# event rows
EV_T = 0
EV_KIND = 1  # EV_DETECTED or EV_CLEARED
EV_HYP = 2
EV_ONSET_T = 3
EV_DETECTED_T = 4
EV_CLEARED_T = 5
EV_SWING = 6  # twice the standard deviation of the smoothed deflection over the episode (rad)
EV_MEAN = 7  # mean of the smoothed deflection over the episode (rad)
EV_FAULT_KIND = 8  # KIND_* at the time of the event
EV_CORR = 9  # the kind test's autocorrelation statistic (NaN while pending)
EV_LLR = 10  # log-likelihood ratio summed over the detection run
EV_TWIN = 11  # group event: index + 1 of the group's other half (EV_HYP the first); 0 otherwise
EV_ISOLATED_AS = 12  # group clearance on isolation: index + 1 of the half detected; 0 otherwise
EV_LEN = 13
EV_DETECTED = 1
EV_CLEARED = 2
EV_CLASSIFIED = 3
EV_GROUP_ISOLATED = 4  # _decide_group's code when a half of the detected group is detected


class BankArrays(NamedTuple):
    """Matrices of the bank, built once per configuration (all float64, C-contiguous).

    Attributes:
        phi: (nh, na, na) transition matrices.
        gin: (nh, na, m) input matrices (the filter's own surface column zeroed).
        offset: (nh, na) constant term ``-G_i u*_i`` of the fault filters.
        q: (nh, na, na) process noise covariances.
        h: (p, na) measurement matrix.
        r: (p, p) measurement noise covariance.
        hth_cols, hth_vals, hth_nnz: the non-zero entries of each row of ``H^T W H``,
            ``W = diag(1 / R_jj)`` (traces in sensor-noise units).
        hqh_diag: (nh, p) diagonal of ``H Q H^T``.
        h_cols, h_vals, h_nnz: the non-zero entries of each row of ``h`` (column indices
            (p, k) int64, values (p, k), counts (p,) int64), so that products with H cost
            what its non-zeros cost (one per row for a selection matrix).
        phi_cols, phi_vals, phi_nnz: the same for the rows of each ``phi`` ((nh, na, k),
            (nh, na, k), (nh, na)): the longitudinal and lateral blocks of a model linearized
            at level flight do not couple.
        phi_t: (nh, na, na) the transposed transition matrices.
        fading_weights: (nh, na) prior-knowledge weights ``a_j`` of the fading factors.
        euclid_weights: (p,) ``1 / R_jj``, the units of the Euclidean-norm likelihood.
        x_trim: (n,) trim state; u_trim: (m,) trim inputs; y_trim: (p,) ``H x*``.
        x0: (nh, na) initial states; p0: (nh, na, na) initial covariances.
        slot_surface: (nh, na - n) int64: the surface (index among the monitored surfaces)
            whose deflection each augmented state slot of a filter holds, -1 for none (the
            no-fault filter has none, a single-fault filter one, a pair filter two).
        floors: (nh,) probability floor of each hypothesis.
        collinear: (s, s) cosine between two surfaces' whitened effects on the measurements
            over the ``COLLINEAR_STEPS`` steps after a deflection (1 on the diagonal).
        range_lo, range_hi: (p,) the model's operating range: bounds of each measurement
            smoothed over ``CFG_RANGE_SMOOTH_S`` (-inf / +inf: not bounded).
    """

    phi: FloatArray
    gin: FloatArray
    offset: FloatArray
    q: FloatArray
    h: FloatArray
    r: FloatArray
    hth_cols: IntArray
    hth_vals: FloatArray
    hth_nnz: IntArray
    hqh_diag: FloatArray
    h_cols: IntArray
    h_vals: FloatArray
    h_nnz: IntArray
    phi_cols: IntArray
    phi_vals: FloatArray
    phi_nnz: IntArray
    phi_t: FloatArray
    fading_weights: FloatArray
    euclid_weights: FloatArray
    x_trim: FloatArray
    u_trim: FloatArray
    y_trim: FloatArray
    x0: FloatArray
    p0: FloatArray
    slot_surface: IntArray
    floors: FloatArray
    collinear: FloatArray
    range_lo: FloatArray
    range_hi: FloatArray


class Layout(NamedTuple):
    """Offsets of the state vector for a bank of ``nh`` filters of ``na`` states."""

    nh: int
    na: int
    p: int
    m: int
    s: int  # monitored surfaces
    filt: int  # start of the first filter block
    filt_len: int  # length of one filter block: na + na*na + p*p + 1
    probs: int
    u_last: int
    decisions: int
    kind_blocks: int  # (s, KIND_BLOCKS) block means of the deflection estimate (rad)
    window: int
    applied: int  # (m,) the inputs applied over the step into the next sample (servo model)
    groups: int  # (s, G_LEN) group decision fields (twin halves detected together)
    operating: int  # (p,) smoothed measurements of the operating range
    checks: int  # (CK_LEN,) status checks (``CK_*``)
    group_kinds: int  # (s, D_LEN) kind spans of the groups, one row per half (``D_*`` kind fields)
    group_kind_blocks: int  # (s, KIND_BLOCKS) their block histories (rad)
    length: int


def state_layout(nh: int, na: int, p: int, m: int, s: int) -> Layout:
    """The state-vector layout of a bank of ``nh`` filters over ``s`` surfaces."""
    filt_len = na + na * na + p * p + 1
    filt = ST_HEADER
    probs = filt + nh * filt_len
    u_last = probs + nh
    decisions = u_last + m
    kind_blocks = decisions + s * D_LEN
    window = kind_blocks + s * KIND_BLOCKS
    applied = window + W_LEN
    return Layout(
        nh,
        na,
        p,
        m,
        s,
        filt,
        filt_len,
        probs,
        u_last,
        decisions,
        kind_blocks,
        window,
        applied,
        applied + m,
        applied + m + s * G_LEN,
        applied + m + s * G_LEN + p,
        applied + m + s * G_LEN + p + CK_LEN,
        applied + m + s * G_LEN + p + CK_LEN + s * D_LEN,
        applied + m + s * G_LEN + p + CK_LEN + s * (D_LEN + KIND_BLOCKS),
    )


# ----------------------------------------------------------------------------- linear algebra
@njit(cache=True, nogil=True, error_model="numpy")
def lu_nopivot(a: FloatArray, k: int) -> bool:
    """In-place Doolittle LU of the leading ``k x k`` block (unit lower L below the diagonal,
    U on and above). Returns False when a pivot is not positive: for a symmetric matrix this is
    exactly "not positive definite"."""
    for j in range(k):
        for i in range(j + 1):
            s = a[i, j]
            for t in range(i):
                s -= a[i, t] * a[t, j]
            a[i, j] = s
        piv = a[j, j]
        if not piv > 0.0:
            return False
        for i in range(j + 1, k):
            s = a[i, j]
            for t in range(j):
                s -= a[i, t] * a[t, j]
            a[i, j] = s / piv
    return True


@njit(cache=True, nogil=True, error_model="numpy")
def lu_solve(lu: FloatArray, k: int, b: FloatArray, out: FloatArray) -> None:
    """Solve ``S z = b`` from :func:`lu_nopivot` factors (first ``k`` entries)."""
    for i in range(k):
        s = b[i]
        for t in range(i):
            s -= lu[i, t] * out[t]
        out[i] = s
    for i in range(k - 1, -1, -1):
        s = out[i]
        for t in range(i + 1, k):
            s -= lu[i, t] * out[t]
        out[i] = s / lu[i, i]


@njit(cache=True, nogil=True, error_model="numpy")
def gaussian_loglik(gam: FloatArray, s: FloatArray, k: int, work: FloatArray) -> float:
    """Log of the multivariate Gaussian density of innovation ``gam`` with covariance ``s``
    (leading ``k`` entries; ``s`` is overwritten by its LU factors); -inf when ``s`` is not
    positive definite."""
    if not lu_nopivot(s, k):
        return -np.inf
    lu_solve(s, k, gam, work)
    quad = 0.0
    logdet = 0.0
    for i in range(k):
        quad += gam[i] * work[i]
        logdet += math.log(s[i, i])
    return -0.5 * (quad + logdet + k * LOG_2PI)


@njit(cache=True, nogil=True, error_model="numpy")
def euclidean_loglik(gam: FloatArray, s_diag: FloatArray, w: FloatArray, k: int) -> float:
    """Log-likelihood from the Euclidean norm of the innovation in units of the sensor noise:
    ``e^2 = sum_j w_j gam_j^2``, ``sigma^2 = sum_j w_j S_jj`` (its expectation), and the 1-D
    Gaussian density ``N(e; 0, sigma^2)``."""
    e2 = 0.0
    s2 = 0.0
    for i in range(k):
        e2 += w[i] * gam[i] * gam[i]
        s2 += w[i] * s_diag[i]
    if not s2 > 0.0:
        return -np.inf
    return -0.5 * (e2 / s2 + math.log(s2) + LOG_2PI)


# ----------------------------------------------------------------------------- one filter
@njit(cache=True, nogil=True, error_model="numpy", fastmath=FAST)
def filter_step(
    f: int,
    bank: BankArrays,
    xs: FloatArray,
    ps: FloatArray,
    vs: FloatArray,
    vflags: FloatArray,
    du: FloatArray,
    ytil: FloatArray,
    valid: IntArray,
    nv: int,
    variant: int,
    likelihood: int,
    rho: float,
    beta: float,
    work: FloatArray,
    mats: FloatArray,
    out2: FloatArray,
    qx: FloatArray,
    n_qx: int,
) -> int:
    """Advance filter ``f`` (its rows of ``xs`` (nh, na), ``ps`` (nh, na, na), ``vs``
    (nh, p, p), ``vflags`` (nh,)) by one sample; returns 0, or 1 when S was not positive
    definite (the update is then skipped). ``out2[0]`` receives the log-likelihood, ``out2[1]``
    the NIS. ``work`` (6, max(na, p)) and ``mats`` (7, w, w), w = max(na, p), are scratch.

    Equations (docs/methods-stmmae.md), with gamma the innovation on the valid rows:

        x-   = Phi x + G u + c,   gamma = y - H x-,   A = Phi P Phi^T
        V    = gamma gamma^T (first) | (rho V + gamma gamma^T) / (1 + rho)
        N    = V - beta R - H Q H^T,   M_jj = (A H^T W H)_jj,   W = diag(1 / R_jj)
        c_k  = tr(W N) / sum_j a_j M_jj,  lambda_j = max(1, a_j c_k)
        P-   = L A L + Q (improved) | L A + Q (strong_tracking) | A + Q (emmae), L = diag(lambda)
        S    = H P- H^T + R,  K = P- H^T S^-1,  x = x- + K gamma,  P = P- - K H P-

    The fading factors are computed only when every measurement is present. Arrays are
    indexed in place (no views are made per sample: each view costs reference counting).
    """
    na = xs.shape[1]
    p_all = bank.r.shape[0]
    m = du.shape[0]
    xp = work[0]
    gam = work[1]
    lam = work[2]
    s_diag = work[3]
    ewv = work[4]
    sol = work[5]
    tmp = mats[0]
    amat = mats[1]
    pp = mats[2]
    pht = mats[3]  # (P- H^T)^T, rows: valid measurements
    kt = mats[4]  # K^T
    smat = mats[5]
    hp = mats[6]  # H P-
    for i in range(na):
        s = bank.offset[f, i]
        for e in range(bank.phi_nnz[f, i]):
            s += bank.phi_vals[f, i, e] * xs[f, bank.phi_cols[f, i, e]]
        for j in range(m):
            s += bank.gin[f, i, j] * du[j]
        xp[i] = s
    for a in range(nv):
        r = valid[a]
        s = ytil[r]
        for e in range(bank.h_nnz[r]):
            s -= bank.h_vals[r, e] * xp[bank.h_cols[r, e]]
        gam[a] = s
    # A = Phi P Phi^T in row-times-matrix (axpy) order: contiguous inner loops
    for i in range(na):
        for j in range(na):
            tmp[i, j] = 0.0
        for e in range(bank.phi_nnz[f, i]):
            c = bank.phi_cols[f, i, e]
            v = bank.phi_vals[f, i, e]
            for j in range(na):
                tmp[i, j] += v * ps[f, c, j]
    symmetric = variant != VARIANT_STRONG_TRACKING
    for i in range(na):
        for j in range(na):
            amat[i, j] = 0.0
        for t in range(na):
            v = tmp[i, t]
            for j in range(na):
                amat[i, j] += v * bank.phi_t[f, t, j]
    for j in range(na):
        lam[j] = 1.0
    if variant != VARIANT_EMMAE and nv == p_all:
        if vflags[f] == 0.0:
            for a in range(p_all):
                for b in range(p_all):
                    vs[f, a, b] = gam[a] * gam[b]
            vflags[f] = 1.0
        else:
            for a in range(p_all):
                for b in range(p_all):
                    vs[f, a, b] = (rho * vs[f, a, b] + gam[a] * gam[b]) / (1.0 + rho)
        tr_n = 0.0
        for a in range(p_all):
            tr_n += bank.euclid_weights[a] * (
                vs[f, a, a] - beta * bank.r[a, a] - bank.hqh_diag[f, a]
            )
        msum = 0.0
        for j in range(na):
            mjj = 0.0
            for e in range(bank.hth_nnz[j]):
                mjj += amat[j, bank.hth_cols[j, e]] * bank.hth_vals[j, e]
            msum += bank.fading_weights[f, j] * mjj
        if msum > 0.0 and tr_n > 0.0:
            ck = tr_n / msum
            for j in range(na):
                v = bank.fading_weights[f, j] * ck
                if v > 1.0:
                    lam[j] = v
    if variant == VARIANT_IMPROVED:
        for i in range(na):
            for j in range(na):
                pp[i, j] = lam[i] * amat[i, j] * lam[j] + bank.q[f, i, j]
    elif variant == VARIANT_STRONG_TRACKING:
        for i in range(na):
            for j in range(na):
                pp[i, j] = lam[i] * amat[i, j] + bank.q[f, i, j]
    else:
        for i in range(na):
            for j in range(na):
                pp[i, j] = amat[i, j] + bank.q[f, i, j]
    # rebased inputs: each input taken at an estimate adds g g^T var to the prior covariance
    # (``qx`` rows hold g sqrt(var) of the first ``n_qx`` such inputs)
    for e in range(n_qx):
        for i in range(na):
            v = qx[e, i]
            if v != 0.0:
                for j in range(na):
                    pp[i, j] += v * qx[e, j]
    if nv == 0:
        _accept_prior(f, xs, ps, xp, pp)
        out2[0] = 0.0
        out2[1] = np.nan
        return 0
    for a in range(nv):
        r = valid[a]
        for i in range(na):
            s = 0.0
            for e in range(bank.h_nnz[r]):
                s += pp[i, bank.h_cols[r, e]] * bank.h_vals[r, e]
            pht[a, i] = s
    for a in range(nv):
        ra = valid[a]
        for b in range(nv):
            s = bank.r[ra, valid[b]]
            for e in range(bank.h_nnz[ra]):
                s += bank.h_vals[ra, e] * pht[b, bank.h_cols[ra, e]]
            smat[a, b] = s
        s_diag[a] = smat[a, a]
        ewv[a] = bank.euclid_weights[ra]
    if not lu_nopivot(smat, nv):
        _accept_prior(f, xs, ps, xp, pp)
        out2[0] = -np.inf
        out2[1] = np.nan
        return 1
    lu_solve(smat, nv, gam, sol)
    nis = 0.0
    logdet = 0.0
    for a in range(nv):
        nis += gam[a] * sol[a]
        logdet += math.log(smat[a, a])
    out2[1] = nis
    if likelihood == LIKELIHOOD_GAUSSIAN:
        out2[0] = -0.5 * (nis + logdet + nv * LOG_2PI)
    else:
        out2[0] = euclidean_loglik(gam, s_diag, ewv, nv)
    # K^T from S^T K^T = H P-^T = U^T L^T K^T, all columns at once (contiguous rows)
    for a in range(nv):
        for i in range(na):
            kt[a, i] = pht[a, i]
        for t in range(a):
            v = smat[t, a]
            for i in range(na):
                kt[a, i] -= v * kt[t, i]
        v = 1.0 / smat[a, a]
        for i in range(na):
            kt[a, i] *= v
    for a in range(nv - 1, -1, -1):
        for t in range(a + 1, nv):
            v = smat[t, a]
            for i in range(na):
                kt[a, i] -= v * kt[t, i]
    for i in range(na):
        s = xp[i]
        for a in range(nv):
            s += kt[a, i] * gam[a]
        xs[f, i] = s
    # P = P- - K (H P-); H P- = (P- H^T)^T when P- is symmetric
    if symmetric:
        for a in range(nv):
            for j in range(na):
                hp[a, j] = pht[a, j]
    else:
        for a in range(nv):
            r = valid[a]
            for j in range(na):
                s = 0.0
                for e in range(bank.h_nnz[r]):
                    s += bank.h_vals[r, e] * pp[bank.h_cols[r, e], j]
                hp[a, j] = s
    for i in range(na):
        for j in range(na):
            ps[f, i, j] = pp[i, j]
        for a in range(nv):
            v = kt[a, i]
            for j in range(na):
                ps[f, i, j] -= v * hp[a, j]
    if symmetric:
        for i in range(na):
            for j in range(i + 1, na):
                v = 0.5 * (ps[f, i, j] + ps[f, j, i])
                ps[f, i, j] = v
                ps[f, j, i] = v
    return 0


@njit(cache=True, nogil=True, error_model="numpy")
def _accept_prior(f: int, xs: FloatArray, ps: FloatArray, xp: FloatArray, pp: FloatArray) -> None:
    """No update: the posterior is the prior."""
    na = xs.shape[1]
    for i in range(na):
        xs[f, i] = xp[i]
        for j in range(na):
            ps[f, i, j] = pp[i, j]


# ----------------------------------------------------------------------------- bank
@njit(cache=True, nogil=True, error_model="numpy")
def _bayes(probs: FloatArray, ll: FloatArray, floors: FloatArray) -> None:
    """``p_i <- p_i f_i / sum_j p_j f_j`` in the log domain, then the floor and renormalization.
    Hypotheses whose likelihood is not finite get zero weight (then the floor); if none is
    finite the probabilities are left unchanged."""
    nh = probs.shape[0]
    best = -np.inf
    for i in range(nh):
        if math.isfinite(ll[i]) and probs[i] > 0.0:
            v = math.log(probs[i]) + ll[i]
            if v > best:
                best = v
    if best == -np.inf:
        return
    total = 0.0
    for i in range(nh):
        if math.isfinite(ll[i]) and probs[i] > 0.0:
            w = math.exp(math.log(probs[i]) + ll[i] - best)
        else:
            w = 0.0
        probs[i] = w
        total += w
    total2 = 0.0
    for i in range(nh):
        v = probs[i] / total
        if v < floors[i]:
            v = floors[i]
        probs[i] = v
        total2 += v
    for i in range(nh):
        probs[i] /= total2


@njit(cache=True, nogil=True, error_model="numpy")
def _episode_add(dec: FloatArray, h: int, value: float, var: float) -> None:
    """Add one deflection estimate ``value`` of posterior variance ``var`` with weight
    ``1 / var`` (samples where the fading factor has just inflated the deflection's covariance,
    and the estimate jumps, count little)."""
    if not var > 0.0 or not math.isfinite(var):
        return
    w = 1.0 / var
    dec[h, D_EP_SUM] += w * value
    dec[h, D_EP_SUMSQ] += w * value * value
    dec[h, D_EP_N] += w


@njit(cache=True, nogil=True, error_model="numpy")
def episode_mean(dec: FloatArray, h: int) -> float:
    """Precision-weighted mean deflection estimate over the episode's span (NaN if empty)."""
    n = dec[h, D_EP_N]
    return dec[h, D_EP_SUM] / n if n > 0.0 else np.nan


@njit(cache=True, nogil=True, error_model="numpy")
def episode_swing(dec: FloatArray, h: int) -> float:
    """Twice the precision-weighted standard deviation of the deflection estimate over the
    episode's span (0 if empty): the peak-to-peak swing of a square wave, 0.71 times that of a
    sine."""
    n = dec[h, D_EP_N]
    if n <= 0.0:
        return 0.0
    mean = dec[h, D_EP_SUM] / n
    return 2.0 * math.sqrt(max(dec[h, D_EP_SUMSQ] / n - mean * mean, 0.0))


@njit(cache=True, nogil=True, error_model="numpy")
def _append_event(
    events: FloatArray,
    n_ev: int,
    t: float,
    kind: float,
    h: int,
    onset_t: float,
    detected_t: float,
) -> FloatArray:
    """Append one event row (doubling the array when full) with the fields every event has;
    returns the array (the row is ``events[n_ev]``)."""
    if n_ev >= events.shape[0]:
        bigger = np.empty((2 * events.shape[0], EV_LEN))
        bigger[:n_ev] = events[:n_ev]
        events = bigger
    row = events[n_ev]
    row[EV_T] = t
    row[EV_KIND] = kind
    row[EV_HYP] = h + 1
    row[EV_ONSET_T] = onset_t
    row[EV_DETECTED_T] = detected_t
    row[EV_CLEARED_T] = t if kind == EV_CLEARED else np.nan
    return events


@njit(cache=True, nogil=True, error_model="numpy")
def _write_event(
    events: FloatArray, n_ev: int, t: float, kind: float, dec: FloatArray, h: int
) -> FloatArray:
    """Append the event row of surface ``h``; returns the array."""
    events = _append_event(events, n_ev, t, kind, h, dec[h, D_ONSET_T], dec[h, D_DETECTED_T])
    row = events[n_ev]
    row[EV_SWING] = episode_swing(dec, h)
    row[EV_MEAN] = episode_mean(dec, h)
    row[EV_FAULT_KIND] = dec[h, D_KIND]
    row[EV_CORR] = dec[h, D_KIND_CORR]
    row[EV_LLR] = dec[h, D_LLR]
    row[EV_TWIN] = 0.0
    row[EV_ISOLATED_AS] = 0.0
    return events


@njit(cache=True, nogil=True, error_model="numpy")
def _kind_add(
    dec: FloatArray, kbuf: FloatArray, h: int, t: float, value: float, var: float
) -> None:
    """Add one deflection estimate to the kind span: the precision-weighted episode sums and the
    history of 0.05 s block means (a data gap repeats the last block's mean)."""
    _episode_add(dec, h, value, var)
    idx = int(math.floor((t - dec[h, D_KIND_T0]) / KIND_BLOCK_S))
    if idx >= KIND_BLOCKS:
        return
    cur = int(dec[h, D_BLK_IDX])
    if idx != cur:
        if cur >= 0 and dec[h, D_BLK_N] > 0.0:
            mean = dec[h, D_BLK_SUM] / dec[h, D_BLK_N]
            for b in range(cur, min(idx, KIND_BLOCKS)):
                kbuf[h, b] = mean
        dec[h, D_BLK_IDX] = idx
        dec[h, D_BLK_SUM] = 0.0
        dec[h, D_BLK_N] = 0.0
    dec[h, D_BLK_SUM] += value
    dec[h, D_BLK_N] += 1.0


@njit(cache=True, nogil=True, error_model="numpy")
def _kind_pad(cfg: FloatArray, dec: FloatArray, kbuf: FloatArray, h: int, t: float) -> None:
    """Before the kind is judged at ``t``: a history left shorter than ``KIND_MIN_BLOCKS`` by
    a gap at the end of the span (samples skipped, see :func:`_decide`) repeats the last
    block's mean up to ``t`` (at most the span's end), as a gap inside the span does, so that
    a kind is judged; a history long enough is judged as it is (a flat tail would dilute an
    oscillation's negative lobe)."""
    t_end = min(t, dec[h, D_KIND_T0] + cfg[CFG_KIND_WINDOW_S])
    idx = min(int(math.floor((t_end - dec[h, D_KIND_T0]) / KIND_BLOCK_S)), KIND_BLOCKS)
    cur = int(dec[h, D_BLK_IDX])
    if cur < 0 or cur + 1 >= KIND_MIN_BLOCKS or not dec[h, D_BLK_N] > 0.0 or idx <= cur + 1:
        return
    mean = dec[h, D_BLK_SUM] / dec[h, D_BLK_N]
    for b in range(cur, idx):
        kbuf[h, b] = mean
    dec[h, D_BLK_IDX] = idx - 1
    dec[h, D_BLK_SUM] = mean
    dec[h, D_BLK_N] = 1.0


@njit(cache=True, nogil=True, error_model="numpy")
def kind_correlation(x: FloatArray, nb: int) -> float:
    """Smallest normalized autocorrelation of the first ``nb`` block means ``x`` over lags from
    ``KIND_MIN_LAG_S`` to half the history:

        r(L) = [sum_{i < nb - L} e_i e_{i+L} / (nb - L)] / [sum_i e_i^2 / nb],  e = x - mean(x)

    A periodic deflection has r = -1 at half its period (sine or square wave); a constant one
    seen through estimation noise and slow model-error drift has no such negative lobe (r stays
    near 0 or positive, up to about -0.3 from the finite history). NaN when ``nb`` is too short
    or the history has no variance."""
    lo = int(math.ceil(KIND_MIN_LAG_S / KIND_BLOCK_S - 1e-9))
    hi = nb // 2
    if nb < KIND_MIN_BLOCKS or hi < lo:
        return np.nan
    mean = 0.0
    for i in range(nb):
        mean += x[i]
    mean /= nb
    var = 0.0
    for i in range(nb):
        var += (x[i] - mean) ** 2
    var /= nb
    if not var > 0.0:
        return np.nan
    best = np.inf
    for lag in range(lo, hi + 1):
        s = 0.0
        for i in range(nb - lag):
            s += (x[i] - mean) * (x[i + lag] - mean)
        r = s / (nb - lag) / var
        if r < best:
            best = r
    return best


@njit(cache=True, nogil=True, error_model="numpy")
def is_oscillating(cfg: FloatArray, corr: float, swing: float) -> bool:
    """The kind test on a closed span: a negative lobe of the block history's autocorrelation
    ``corr`` (:func:`kind_correlation`) below ``CFG_OSC_CORR`` and a swing (2 std, rad) above
    ``CFG_OSC_SWING``; a swing below ``CFG_OSC_SMALL_SWING``, as small as a stuck surface's
    estimation noise makes, needs the deeper lobe ``CFG_OSC_SMALL_CORR``."""
    if math.isnan(corr) or not swing > cfg[CFG_OSC_SWING]:
        return False
    level = cfg[CFG_OSC_CORR] if swing >= cfg[CFG_OSC_SMALL_SWING] else cfg[CFG_OSC_SMALL_CORR]
    return bool(corr < level)


@njit(cache=True, nogil=True, error_model="numpy")
def _judge_kind(cfg: FloatArray, dec: FloatArray, kbuf: FloatArray, h: int) -> None:
    """Close the kind span: oscillating when :func:`is_oscillating`; stuck otherwise; left
    pending (undetermined) when the history is shorter than ``KIND_MIN_BLOCKS``."""
    cur = int(dec[h, D_BLK_IDX])
    nb = cur
    if 0 <= cur < KIND_BLOCKS and dec[h, D_BLK_N] > 0.0:
        kbuf[h, cur] = dec[h, D_BLK_SUM] / dec[h, D_BLK_N]
        nb = cur + 1
    nb = min(nb, KIND_BLOCKS)
    corr = kind_correlation(kbuf[h], nb) if nb > 0 else np.nan
    dec[h, D_KIND_CORR] = corr
    if math.isnan(corr):
        if nb >= KIND_MIN_BLOCKS:  # a flat history: constant deflection
            dec[h, D_KIND] = KIND_STUCK
        return
    osc = is_oscillating(cfg, corr, episode_swing(dec, h))
    dec[h, D_KIND] = KIND_OSCILLATING if osc else KIND_STUCK


@njit(cache=True, nogil=True, error_model="numpy")
def cut_kind_span(cfg: FloatArray, dec: FloatArray, kbuf: FloatArray, h: int, t_cut: float) -> bool:
    """Another surface was detected while the kind span of ``h`` is open: judge the kind on the
    block history before ``t_cut`` (the other surface's onset less ``KIND_CUT_MARGIN_S``) and
    close the span, if that history has at least ``KIND_MIN_BLOCKS`` blocks and either shows an
    oscillation or covers at least half of ``fault_kind_window_s`` (a shorter history cannot
    show the negative lobe of a slow oscillation, so "stuck" is not concluded from it: the span
    then runs on as before). The span's mean and swing are then those of the blocks kept (the
    episode sums are replaced by them, equal weights). Returns True when the span was closed
    (the caller writes ``fault_classified``).

    Why: from the other fault's start its effect enters this surface's estimate (the filters
    that free this surface explain part of it, and the estimate switches filters when the
    active set changes), so an oscillation of the other surface made a stuck one look
    oscillating, and a stuck other half damped an oscillation (docs/methods-stmmae.md)."""
    if dec[h, D_KIND] != KIND_PENDING or not dec[h, D_BLK_IDX] < KIND_BLOCKS:
        return False
    nb = int(math.floor((t_cut - dec[h, D_KIND_T0]) / KIND_BLOCK_S))
    if nb < KIND_MIN_BLOCKS:
        return False
    cur = int(dec[h, D_BLK_IDX])
    if 0 <= cur < KIND_BLOCKS and dec[h, D_BLK_N] > 0.0:
        kbuf[h, cur] = dec[h, D_BLK_SUM] / dec[h, D_BLK_N]
    nb = min(nb, cur + 1, KIND_BLOCKS)
    if nb < KIND_MIN_BLOCKS:
        return False
    s1 = 0.0
    s2 = 0.0
    for i in range(nb):
        s1 += kbuf[h, i]
        s2 += kbuf[h, i] * kbuf[h, i]
    mean = s1 / nb
    swing = 2.0 * math.sqrt(max(s2 / nb - mean * mean, 0.0))
    corr = kind_correlation(kbuf[h], nb)
    osc = is_oscillating(cfg, corr, swing)
    if not osc and nb * KIND_BLOCK_S < 0.5 * cfg[CFG_KIND_WINDOW_S]:
        return False
    dec[h, D_EP_N] = float(nb)
    dec[h, D_EP_SUM] = s1
    dec[h, D_EP_SUMSQ] = s2
    dec[h, D_KIND_CORR] = corr
    dec[h, D_KIND] = KIND_OSCILLATING if osc else KIND_STUCK
    dec[h, D_BLK_IDX] = KIND_BLOCKS  # span closed
    return True


@njit(cache=True, nogil=True, error_model="numpy")
def deflection_gate(cfg: FloatArray, defl_var: float) -> float:
    """Smallest |smoothed deflection estimate - command| (rad) for a detection: at least
    ``CFG_MIN_ERR`` and at least ``CFG_MIN_ERR_STD`` posterior standard deviations of the
    estimate (an estimate closer to the command than its own uncertainty does not show that
    the surface left its command)."""
    gate = float(cfg[CFG_MIN_ERR])
    if cfg[CFG_MIN_ERR_STD] > 0.0 and defl_var > 0.0 and math.isfinite(defl_var):
        gate = max(gate, cfg[CFG_MIN_ERR_STD] * math.sqrt(defl_var))
    return gate


@njit(cache=True, nogil=True, error_model="numpy")
def _start_run(dec: FloatArray, h: int, t: float) -> None:
    """A new run of the detection conditions starts at ``t``: reset its evidence and kind span."""
    dec[h, D_ABOVE_T] = t
    dec[h, D_LLR] = 0.0
    dec[h, D_EP_N] = 0.0
    dec[h, D_EP_SUM] = 0.0
    dec[h, D_EP_SUMSQ] = 0.0
    dec[h, D_KIND] = KIND_PENDING
    dec[h, D_KIND_T0] = t
    dec[h, D_BLK_IDX] = -1.0
    dec[h, D_BLK_SUM] = 0.0
    dec[h, D_BLK_N] = 0.0
    dec[h, D_KIND_CORR] = np.nan


@njit(cache=True, nogil=True, error_model="numpy")
def _decide(
    cfg: FloatArray,
    dec: FloatArray,
    kbuf: FloatArray,
    h: int,
    t: float,
    dt: float,
    prob: float,
    iso: float,
    iso_level: float,
    defl: float,
    defl_var: float,
    cmd: float,
    a_smooth: float,
    a_clear: float,
    llr: float,
    hold: float,
    kval: float,
    other_onset: float,
    outside: bool,
) -> int:
    """Detection, classification and clearance of one surface at one sample; returns 0 or
    ``EV_DETECTED``/``EV_CLASSIFIED``/``EV_CLEARED`` (the caller writes the event from
    ``dec[h]``; after a clearance it calls :func:`reset_after_clearance`).

    Detection needs, held together for ``hold`` (:func:`detection_hold`): the marginal
    probability ``prob`` above ``CFG_DETECT_P`` and the isolation odds ``iso`` (the surface's
    probability of being the only new fault against its strongest competitor's) above
    ``iso_level`` (``CFG_DETECT_P``; ``CFG_GROUP_ISO`` while no other surface is in fault and
    the surface's group is detected, or with ``CFG_HALF_GROUP_ODDS`` before it is, while its
    strongest competitor is its twin; infinite while outside the operating range, less than
    ``CFG_RANGE_SETTLE_S`` back inside it, or while a fault ends), the smoothed deflection
    estimate more than ``CFG_MIN_ERR`` from the command, and at the end the log-likelihood
    ratio between the nested families (:func:`_relevant_loglik`) summed over the run at least
    ``CFG_MIN_LLR``.
    ``kval`` is the value the kind history records (``defl``, or the estimate conditioned on
    its twin's known position, :func:`kind_value`); ``other_onset`` the latest open onset of a
    surface or group not in fault (-inf: none), for which the end of the kind span waits when
    it lies inside the span (``CFG_KIND_WAIT_S``); ``outside``: the sample is outside the
    operating range (not added to the kind history).
    Clearance (hysteresis): the smoothed difference between deflection estimate
    and command inside ``CFG_CLEAR_DEFL`` (the surface follows its command again) and, unless
    the bank is rebased (the probability then no longer compares with the command), the
    probability below ``CFG_CLEAR_P``, together for ``CFG_CLEAR_HOLD_S``."""
    lim = cfg[CFG_LIMIT]
    defl = min(max(defl, -lim), lim)
    kval = min(max(kval, -lim), lim)
    if dec[h, D_SMOOTH_SET] == 0.0 or not dt > 0.0:
        dec[h, D_SMOOTH] = defl
        dec[h, D_CSMOOTH] = defl - cmd
        dec[h, D_SMOOTH_SET] = 1.0
    else:
        dec[h, D_SMOOTH] += a_smooth * (defl - dec[h, D_SMOOTH])
        dec[h, D_CSMOOTH] += a_clear * (defl - cmd - dec[h, D_CSMOOTH])
    active = dec[h, D_ACTIVE] == 1.0
    if prob > cfg[CFG_ONSET_P]:
        if math.isnan(dec[h, D_ONSET_T]):
            dec[h, D_ONSET_T] = t
    elif not active:
        dec[h, D_ONSET_T] = np.nan
    if not active:
        holds = (
            prob > cfg[CFG_DETECT_P]
            and iso > iso_level
            and abs(dec[h, D_SMOOTH] - cmd) > deflection_gate(cfg, defl_var)
        )
        if holds:
            if math.isnan(dec[h, D_ABOVE_T]):
                _start_run(dec, h, t)
            if math.isfinite(llr):
                dec[h, D_LLR] += llr
            _kind_add(dec, kbuf, h, t, kval, defl_var)
            if t - dec[h, D_ABOVE_T] >= hold - HOLD_TOL_S and dec[h, D_LLR] >= cfg[CFG_MIN_LLR]:
                dec[h, D_ACTIVE] = 1.0
                dec[h, D_DETECTED_T] = t
                dec[h, D_BELOW_T] = np.nan
                return EV_DETECTED
        else:
            dec[h, D_ABOVE_T] = np.nan
        return 0
    code = 0
    if dec[h, D_KIND] == KIND_PENDING and dec[h, D_BLK_IDX] < KIND_BLOCKS:
        span = t - dec[h, D_KIND_T0]
        if span < cfg[CFG_KIND_WINDOW_S]:
            # the estimate is the probability-weighted mean of the filters that free the
            # surface: while they hold less than the onset level of the probability, the data
            # reject them and their estimate says nothing of the surface (a gap: the block
            # history repeats the last block's mean)
            if prob > cfg[CFG_ONSET_P] and not outside:
                _kind_add(dec, kbuf, h, t, kval, defl_var)
        elif not (
            cfg[CFG_KIND_CUT] != 0.0
            and dec[h, D_KIND_T0] < other_onset
            and other_onset - KIND_CUT_MARGIN_S < dec[h, D_KIND_T0] + cfg[CFG_KIND_WINDOW_S]
            and span < cfg[CFG_KIND_WINDOW_S] + cfg[CFG_KIND_WAIT_S]
            and span < KIND_BLOCKS * KIND_BLOCK_S
        ):
            _kind_pad(cfg, dec, kbuf, h, t)
            _judge_kind(cfg, dec, kbuf, h)
            dec[h, D_BLK_IDX] = KIND_BLOCKS  # span closed
            code = EV_CLASSIFIED
        # else: another surface's (or group's) onset lies inside the span and it is not
        # detected yet: the judgment waits, the history as it stood at the span's end, up to
        # CFG_KIND_WAIT_S (and the history's capacity), for that detection to cut the span
        # before its onset (:func:`cut_kind_span`); without it the kind is judged as it would
        # have been
    back = abs(dec[h, D_CSMOOTH]) < cfg[CFG_CLEAR_DEFL]
    if cfg[CFG_REBASE] == 0.0:
        back = back and prob < cfg[CFG_CLEAR_P]
    if back:
        if math.isnan(dec[h, D_BELOW_T]):
            dec[h, D_BELOW_T] = t
        if t - dec[h, D_BELOW_T] >= cfg[CFG_CLEAR_HOLD_S] - HOLD_TOL_S:
            if dec[h, D_BLK_IDX] < KIND_BLOCKS:
                _kind_pad(cfg, dec, kbuf, h, t)
                _judge_kind(cfg, dec, kbuf, h)
                dec[h, D_BLK_IDX] = KIND_BLOCKS
            return EV_CLEARED
    else:
        dec[h, D_BELOW_T] = np.nan
    return code


@njit(cache=True, nogil=True, error_model="numpy")
def detection_hold(cfg: FloatArray, dec: FloatArray, h: int, twin: int, n_active: int) -> float:
    """Hold time of a detection of surface ``h`` (its twin ``twin``, -1 for none) with
    ``n_active`` surfaces in fault: ``CFG_HOLD_S`` while none is, ``CFG_HOLD_TWIN_S`` while its
    twin is, ``CFG_HOLD_ACTIVE_S`` while another surface is."""
    if n_active == 0:
        return float(cfg[CFG_HOLD_S])
    if twin >= 0 and dec[twin, D_ACTIVE] == 1.0:
        return float(cfg[CFG_HOLD_TWIN_S])
    return float(cfg[CFG_HOLD_ACTIVE_S])


@njit(cache=True, nogil=True, error_model="numpy")
def twins(collinear: FloatArray, h: int, a: int) -> bool:
    """``h`` and ``a`` are each other's most collinear surface (the cosine of their whitened
    effects on the measurements, ``BankArrays.collinear``, the largest in absolute value in
    both rows): the halves of a split surface, whose data determine mainly the sum of the two
    deflections."""
    c = abs(collinear[h, a])
    for o in range(collinear.shape[0]):
        if o != h and o != a and (abs(collinear[h, o]) >= c or abs(collinear[a, o]) >= c):
            return False
    return True


@njit(cache=True, nogil=True, error_model="numpy")
def twin_index(collinear: FloatArray, h: int) -> int:
    """The twin of surface ``h`` (:func:`twins`), -1 for none."""
    for a in range(collinear.shape[0]):
        if a != h and twins(collinear, h, a):
            return a
    return -1


@njit(cache=True, nogil=True, error_model="numpy")
def twin_pair_mass(bank: BankArrays, dec: FloatArray, probs: FloatArray, h: int, a: int) -> float:
    """Probability of the hypotheses whose new faults (surfaces not in fault) are exactly ``h``
    and ``a``."""
    total = 0.0
    for f in range(probs.shape[0]):
        has_h = False
        has_a = False
        other_new = False
        for e in range(bank.slot_surface.shape[1]):
            g = bank.slot_surface[f, e]
            if g == h:
                has_h = True
            elif g == a:
                has_a = True
            elif g >= 0 and dec[g, D_ACTIVE] != 1.0:
                other_new = True
        if has_h and has_a and not other_new:
            total += probs[f]
    return total


@njit(cache=True, nogil=True, error_model="numpy")
def _decide_group(
    cfg: FloatArray,
    gdec: FloatArray,
    dec: FloatArray,
    h: int,
    a: int,
    t: float,
    q: float,
    iso: float,
    llr: float,
    deflected: bool,
    back: bool,
    outside: bool,
    others_active: bool,
) -> int:
    """Detection and clearance of the group of twin halves ``h`` and ``a`` (fields on
    ``gdec[h]``) at one sample; returns 0, ``EV_DETECTED``, ``EV_CLEARED`` or
    ``EV_GROUP_ISOLATED``.

    The group is detected, inside the operating range (``outside`` false) and while neither
    half is in fault, when for ``CFG_GROUP_HOLD_S`` (``CFG_GROUP_HOLD_ACTIVE_S`` while another
    surface is in fault: ``others_active``) together: ``q``, the probability that the new fault
    is in the group (either half or both), and ``iso``, its odds against the strongest other
    surface or group, are
    above ``CFG_DETECT_P``; one half's smoothed deflection estimate passes its deflection gate
    (``deflected``); and at the end the evidence ``llr`` (the better half's filter against the
    base family, per sample) summed over the run is at least ``CFG_MIN_LLR``: the conditions of
    a surface's detection with the group in place of the surface; and the detection comes no
    later than ``CFG_GROUP_WINDOW_S`` after the group's onset (the first sample of ``q`` above
    ``CFG_ONSET_P`` since ``q`` was last below ``CFG_CLEAR_P``). It ends when either half is
    detected (``EV_GROUP_ISOLATED``), or is cleared when ``q`` is below ``CFG_CLEAR_P`` and both
    halves follow their commands (``back``) for ``CFG_CLEAR_HOLD_S``."""
    if gdec[h, G_ACTIVE] == 1.0:
        if dec[h, D_ACTIVE] == 1.0 or dec[a, D_ACTIVE] == 1.0:
            return EV_GROUP_ISOLATED
        if back and q < cfg[CFG_CLEAR_P]:
            if math.isnan(gdec[h, G_BELOW_T]):
                gdec[h, G_BELOW_T] = t
            if t - gdec[h, G_BELOW_T] >= cfg[CFG_CLEAR_HOLD_S] - HOLD_TOL_S:
                return EV_CLEARED
        else:
            gdec[h, G_BELOW_T] = np.nan
        return 0
    # the onset: the first sample above the onset level since the probability was last below the
    # clearance level (a dip between the two levels does not restart it)
    if q > cfg[CFG_ONSET_P]:
        if math.isnan(gdec[h, G_ONSET_T]):
            gdec[h, G_ONSET_T] = t
    elif q < cfg[CFG_CLEAR_P]:
        gdec[h, G_ONSET_T] = np.nan
    late = t - gdec[h, G_ONSET_T] > cfg[CFG_GROUP_WINDOW_S] + HOLD_TOL_S
    half_active = dec[h, D_ACTIVE] == 1.0 or dec[a, D_ACTIVE] == 1.0
    if (
        outside
        or half_active
        or late
        or not (q > cfg[CFG_DETECT_P] and iso > cfg[CFG_DETECT_P] and deflected)
    ):
        gdec[h, G_ABOVE_T] = np.nan
        return 0
    if math.isnan(gdec[h, G_ABOVE_T]):
        gdec[h, G_ABOVE_T] = t
        gdec[h, G_LLR] = 0.0
    if math.isfinite(llr):
        gdec[h, G_LLR] += llr
    hold = cfg[CFG_GROUP_HOLD_ACTIVE_S] if others_active else cfg[CFG_GROUP_HOLD_S]
    if t - gdec[h, G_ABOVE_T] >= hold - HOLD_TOL_S and gdec[h, G_LLR] >= cfg[CFG_MIN_LLR]:
        gdec[h, G_ACTIVE] = 1.0
        gdec[h, G_DETECTED_T] = t
        gdec[h, G_BELOW_T] = np.nan
        return EV_DETECTED
    return 0


@njit(cache=True, nogil=True, error_model="numpy")
def _write_group_event(
    events: FloatArray,
    n_ev: int,
    t: float,
    kind: float,
    gdec: FloatArray,
    h: int,
    a: int,
    isolated_as: int,
    gkd: FloatArray,
) -> FloatArray:
    """Append the event row of the group of ``h`` and ``a`` (``isolated_as``: the half
    detected, -1 for none), with the kind of its span (:func:`_group_kind`) once judged;
    returns the array."""
    events = _append_event(events, n_ev, t, kind, h, gdec[h, G_ONSET_T], gdec[h, G_DETECTED_T])
    row = events[n_ev]
    r = group_kind_row(gkd, h, a)
    row[EV_SWING] = episode_swing(gkd, r) if r >= 0 else np.nan
    row[EV_MEAN] = episode_mean(gkd, r) if r >= 0 else np.nan
    row[EV_FAULT_KIND] = gkd[r, D_KIND] if r >= 0 else KIND_PENDING
    row[EV_CORR] = gkd[r, D_KIND_CORR] if r >= 0 else np.nan
    row[EV_LLR] = gdec[h, G_LLR]
    row[EV_TWIN] = a + 1
    row[EV_ISOLATED_AS] = isolated_as + 1
    return events


@njit(cache=True, nogil=True, error_model="numpy")
def fault_ending(
    cfg: FloatArray,
    dec: FloatArray,
    pm: FloatArray,
    dmean: FloatArray,
    applied: FloatArray,
    surface_inputs: IntArray,
) -> bool:
    """Whether a detected fault is ending: a surface in fault whose marginal probability ``pm``
    is below ``CFG_CLEAR_P`` and whose deflection estimate ``dmean`` is back within
    ``CFG_CLEAR_DEFL`` of its command (``applied``, through ``surface_inputs``): the clearance
    conditions on the estimate itself rather than on its smoothed value, which lags the
    surface's return by a second or two. Its clearance is then pending, and meanwhile the
    filters re-converge after the surface's return: those freeing another surface fit that
    transient better than the no-fault filter and than the ending fault's own, which detected
    that surface wrongly 0.3-2 s after the end of a fault; no new detection is made while one
    is ending."""
    for h in range(dec.shape[0]):
        if (
            dec[h, D_ACTIVE] == 1.0
            and pm[h] < cfg[CFG_CLEAR_P]
            and abs(dmean[h] - applied[surface_inputs[h]]) < cfg[CFG_CLEAR_DEFL]
        ):
            return True
    return False


@njit(cache=True, nogil=True, error_model="numpy")
def _outside_range(bank: BankArrays, ysm: FloatArray, y_k: FloatArray, a_range: float) -> bool:
    """Smooth each bounded measurement (first-order, share ``a_range`` of the gap per sample;
    the first valid value starts it; a missing value holds it) and return whether any smoothed
    value is outside ``[range_lo, range_hi]``."""
    outside = False
    for a in range(ysm.shape[0]):
        if not (bank.range_lo[a] > -np.inf or bank.range_hi[a] < np.inf):
            continue
        v = y_k[a]
        if math.isfinite(v):
            if math.isnan(ysm[a]):
                ysm[a] = v
            else:
                ysm[a] += a_range * (v - ysm[a])
        if ysm[a] < bank.range_lo[a] or ysm[a] > bank.range_hi[a]:
            outside = True
    return outside


@njit(cache=True, nogil=True, error_model="numpy")
def _innovation_energy(gam: FloatArray, valid: IntArray, nv: int, weights: FloatArray) -> float:
    """``sum_a gamma_a^2 / R_aa / nv`` over the ``nv`` valid measurements (``weights``: 1 / R_aa):
    about 1 when R is the sensors' noise; NaN without a measurement."""
    if nv == 0:
        return np.nan
    e2 = 0.0
    for a in range(nv):
        e2 += gam[a] * gam[a] * weights[valid[a]]
    return e2 / nv


@njit(cache=True, nogil=True, error_model="numpy")
def _add_noise(checks: FloatArray, energy: float, a_range: float) -> None:
    """Add one sample's innovation energy to the window sums and the smoothed value (the first
    value starts it; share ``a_range`` of the gap per sample after that)."""
    if not math.isfinite(energy):
        return
    checks[CK_NOISE_SUM] += energy
    checks[CK_NOISE_N] += 1.0
    if math.isnan(checks[CK_NOISE_SMOOTH]):
        checks[CK_NOISE_SMOOTH] = energy
    else:
        checks[CK_NOISE_SMOOTH] += a_range * (energy - checks[CK_NOISE_SMOOTH])


@njit(cache=True, nogil=True, error_model="numpy")
def add_half_evidence(gdec: FloatArray, ll: FloatArray, h: int, a: int, on: bool) -> None:
    """Sum into ``gdec[h, G_HALF_LLR]`` the log-likelihood of half ``h``'s single-fault filter
    less its twin ``a``'s at this sample (filter ``g + 1`` holds surface ``g`` alone,
    ``hypothesis_members``), while ``on`` (the group is detected and no other surface is in
    fault); otherwise the sum restarts at 0. A sample on which either filter's update failed
    (a log-likelihood not finite) adds nothing."""
    if not on:
        gdec[h, G_HALF_LLR] = 0.0
        return
    lh = ll[h + 1]
    la = ll[a + 1]
    if math.isfinite(lh) and math.isfinite(la):
        gdec[h, G_HALF_LLR] += lh - la


@njit(cache=True, nogil=True, error_model="numpy")
def half_odds(gdec: FloatArray, lead: int, h: int) -> float:
    """Odds of half ``h`` against its twin, ``1 / (1 + exp(-L))``, from the summed
    log-likelihood ``L`` of the group whose fields are on row ``lead`` (its sign turned for the
    second half)."""
    e = gdec[lead, G_HALF_LLR] if h == lead else -gdec[lead, G_HALF_LLR]
    e = min(max(e, -700.0), 700.0)
    return 1.0 / (1.0 + math.exp(-e))


@njit(cache=True, nogil=True, error_model="numpy")
def reset_group(gdec: FloatArray, h: int) -> None:
    """The group of ``h`` back to "not detected" after its clearance (or isolation) event."""
    gdec[h, G_ACTIVE] = 0.0
    gdec[h, G_ABOVE_T] = np.nan
    gdec[h, G_ONSET_T] = np.nan
    gdec[h, G_DETECTED_T] = np.nan
    gdec[h, G_BELOW_T] = np.nan
    gdec[h, G_LLR] = 0.0
    gdec[h, G_HALF_LLR] = 0.0


@njit(cache=True, nogil=True, error_model="numpy")
def group_kind_lead(gkd: FloatArray, h: int, a: int) -> int:
    """The half of the group of ``h`` and ``a`` whose history gives the group's kind: the one
    whose filters held more probability over the span (summed in the ``D_LLR`` field of the
    group's kind rows)."""
    return a if gkd[a, D_LLR] > gkd[h, D_LLR] else h


@njit(cache=True, nogil=True, error_model="numpy")
def group_kind_row(gkd: FloatArray, h: int, a: int) -> int:
    """The row of ``gkd`` holding the judged kind of the group of ``h`` and ``a`` (its lead
    half's, :func:`group_kind_lead`), or -1 while its span is open or left it pending."""
    lead = group_kind_lead(gkd, h, a)
    if gkd[lead, D_BLK_IDX] >= KIND_BLOCKS and gkd[lead, D_KIND] != KIND_PENDING:
        return lead
    return -1


@njit(cache=True, nogil=True, error_model="numpy")
def _group_kind(
    cfg: FloatArray,
    gdec: FloatArray,
    gkd: FloatArray,
    gkb: FloatArray,
    h: int,
    a: int,
    t: float,
    kval: FloatArray,
    dvar: FloatArray,
    pm: FloatArray,
    q: float,
    outside: bool,
    code: int,
) -> bool:
    """The kind span of the group of twin halves ``h`` and ``a`` at one sample, after
    :func:`_decide_group` returned ``code``; returns True when the kind was judged at this
    sample with the group still detected (the caller writes ``fault_classified``).

    A group is raised when the new fault is in one of two halves whose effects the
    measurements barely tell apart; which half is open, but whether it is stuck or oscillating
    is not. Each half's kind value (:func:`kind_value`, the half's estimate with its twin at its
    command) is recorded on its row of ``gkd``/``gkb`` (fields and blocks as a surface's kind
    span) over the same span as a surface's: from the start of the group's detection run
    (only its samples before the detection), then while the group's probability ``q`` is above
    the onset level inside the operating range, up to ``fault_kind_window_s``. The span is
    judged at its end, or at the group's clearance, on each row (:func:`_judge_kind`); the
    group's kind is that of the half whose filters held more probability over the span
    (:func:`group_kind_lead`). When a half is isolated, its own span gives the kind and the
    group's is dropped."""
    if code == EV_GROUP_ISOLATED:
        return False
    add = False
    judge = False
    if gdec[h, G_ACTIVE] != 1.0 and code != EV_CLEARED:
        if gdec[h, G_ABOVE_T] == t:
            _start_run(gkd, h, t)
            _start_run(gkd, a, t)
        add = math.isfinite(gdec[h, G_ABOVE_T])  # the run's samples before the detection
    elif not math.isfinite(gkd[h, D_KIND_T0]) or not gkd[h, D_BLK_IDX] < KIND_BLOCKS:
        return False  # no span open (closed, or a group detected before the span was kept)
    elif code == EV_DETECTED:
        add = True
    elif code != EV_CLEARED and t - gkd[h, D_KIND_T0] < cfg[CFG_KIND_WINDOW_S]:
        add = q > cfg[CFG_ONSET_P] and not outside
    else:
        judge = True
    for x in (h, a):
        if add:
            _kind_add(gkd, gkb, x, t, kval[x], dvar[x])
            gkd[x, D_LLR] += pm[x]
        elif judge:
            _kind_pad(cfg, gkd, gkb, x, t)
            _judge_kind(cfg, gkd, gkb, x)
            gkd[x, D_BLK_IDX] = KIND_BLOCKS  # span closed
    return judge and code != EV_CLEARED


@njit(cache=True, nogil=True, error_model="numpy")
def kind_value(
    cfg: FloatArray,
    dec: FloatArray,
    slot_surface: IntArray,
    xs: FloatArray,
    ps: FloatArray,
    probs: FloatArray,
    n: int,
    h: int,
    defl: FloatArray,
    twin: int,
    twin_cmd: float,
) -> float:
    """The value the kind history of ``h`` records: its deflection estimate conditioned on the
    known position ``pos`` of its twin ``twin`` (:func:`twins`; -1 for none), the
    probability-weighted mean over the filters freeing ``h`` of

        x_f,h + P_f,ha / P_f,aa (pos - x_f,a)     (a filter freeing the twin too)
        x_f,h                                     (one that holds the twin at its command)

    with ``pos`` the twin's stuck position while it is in fault and judged stuck, its command
    ``twin_cmd`` while it is not in fault. Only the sum of two halves' deflections is well
    determined, so the excursions of a filter's twin estimate are in good part ``h``'s
    deflection misattributed to the twin. Without a known position (the twin oscillating or
    not judged yet), or with the option off: the plain estimate ``defl[h]``."""
    val = float(defl[h])
    if cfg[CFG_KIND_TWIN] == 0.0 or twin < 0:
        return val
    if dec[twin, D_ACTIVE] == 1.0:
        if dec[twin, D_KIND] != KIND_STUCK:
            return val
        pos = episode_mean(dec, twin)
    else:
        pos = twin_cmd
    if not math.isfinite(pos):
        return val
    num = 0.0
    den = 0.0
    for f in range(slot_surface.shape[0]):
        sh = -1
        sa = -1
        for e in range(slot_surface.shape[1]):
            if slot_surface[f, e] == h:
                sh = n + e
            elif slot_surface[f, e] == twin:
                sa = n + e
        if sh < 0:
            continue
        v = xs[f, sh]
        if sa >= 0 and ps[f, sa, sa] > 0.0:
            v += ps[f, sh, sa] / ps[f, sa, sa] * (pos - xs[f, sa])
        num += probs[f] * v
        den += probs[f]
    return num / den if den > 0.0 else val


@njit(cache=True, nogil=True, error_model="numpy")
def _relevant_loglik(
    bank: BankArrays,
    dec: FloatArray,
    ll: FloatArray,
    probs: FloatArray,
    rel_in: FloatArray,
    base: FloatArray,
    p_new: FloatArray,
) -> None:
    """Log-likelihoods of the detection evidence of each surface ``g`` not in fault, a
    generalized likelihood ratio between two nested families of hypotheses (``A`` the active
    faults):

        rel_in[g] = max_{h : g in S_h, S_h - {g} subset of A} log f_h
        base[g]   = max_{h : S_h subset of A} log f_h

    ``rel_in``: "g has failed (and some of the active faults hold)", ``base``: "no fault beyond
    the active ones" (with none active: the filters of ``g`` against the no-fault filter). The
    base family holds the subsets of ``A`` so that a fault that has just ended (its filter
    re-converging, the no-fault filter already right) does not lend evidence to another
    surface, and with two active faults a third is measured against their pair's filter.
    ``p_new[g]``: the probability of the first family (``g`` the only new fault), for the
    isolation condition."""
    nh = ll.shape[0]
    ns = rel_in.shape[0]
    n_slots = bank.slot_surface.shape[1]
    for g in range(ns):
        rel_in[g] = -np.inf
        base[g] = -np.inf
        p_new[g] = 0.0
    for f in range(nh):
        n_new = 0
        new_g = -1
        for e in range(n_slots):
            g = bank.slot_surface[f, e]
            if g >= 0 and dec[g, D_ACTIVE] != 1.0:
                n_new += 1
                new_g = g
        if n_new == 0:
            for g in range(ns):
                if ll[f] > base[g]:
                    base[g] = ll[f]
        elif n_new == 1:
            p_new[new_g] += probs[f]
            if ll[f] > rel_in[new_g]:
                rel_in[new_g] = ll[f]


@njit(cache=True, nogil=True, error_model="numpy")
def reset_after_clearance(dec: FloatArray, h: int) -> None:
    """Back to "no fault" after a clearance event was written."""
    dec[h, D_ACTIVE] = 0.0
    dec[h, D_ABOVE_T] = np.nan
    dec[h, D_ONSET_T] = np.nan
    dec[h, D_BELOW_T] = np.nan
    dec[h, D_DETECTED_T] = np.nan
    dec[h, D_EP_N] = 0.0
    dec[h, D_EP_SUM] = 0.0
    dec[h, D_EP_SUMSQ] = 0.0
    dec[h, D_KIND] = KIND_PENDING
    dec[h, D_KIND_T0] = np.nan
    dec[h, D_BLK_IDX] = -1.0
    dec[h, D_KIND_CORR] = np.nan


@njit(cache=True, nogil=True, error_model="numpy")
def _close_window(wacc: FloatArray, checks: FloatArray, t_end: float, row: FloatArray) -> None:
    """Write the health window's row from its accumulators ``wacc`` and the window fields of
    ``checks`` (``CK_*``), then reset them."""
    row[:] = np.nan
    n = wacc[W_COUNT]
    row[WIN_T0] = wacc[W_T0]
    row[WIN_T1] = t_end
    row[WIN_N] = n
    row[WIN_NOMINAL_MEAN] = wacc[W_SUM_NOMINAL] / n
    row[WIN_MAX_FAULT] = wacc[W_MAX_FAULT]
    row[WIN_MAX_FAULT_HYP] = wacc[W_MAX_FAULT_HYP]
    if wacc[W_N_NIS] > 0.0:
        row[WIN_NIS_MEAN] = wacc[W_SUM_NIS] / wacc[W_N_NIS]
    row[WIN_ACTIVE_FRACTION] = wacc[W_N_ACTIVE] / n
    row[WIN_COV_FAIL] = wacc[W_COV_FAIL]
    row[WIN_OUTSIDE_FRACTION] = checks[CK_OUTSIDE] / n
    if checks[CK_NOISE_N] > 0.0:
        row[WIN_NOISE_RATIO] = checks[CK_NOISE_SUM] / checks[CK_NOISE_N]
    wacc[:] = 0.0
    checks[CK_OUTSIDE] = 0.0
    checks[CK_NOISE_SUM] = 0.0
    checks[CK_NOISE_N] = 0.0


def bank_batch(
    cfg: FloatArray,
    arrays: BankArrays,
    st: FloatArray,
    t: FloatArray,
    y: FloatArray,
    u: FloatArray,
    surface_inputs: IntArray,
) -> tuple[FloatArray, FloatArray, FloatArray, int]:
    """Run the bank over one batch, updating ``st`` in place.

    Args:
        cfg: scalar configuration (``CFG_*``).
        arrays: the bank's matrices.
        st: state vector (:func:`state_layout`).
        t: sample times, shape (k,).
        y: measurements, shape (p, k); NaN = missing.
        u: inputs (commands), shape (m, k); NaN = hold the last valid value.
        surface_inputs: input index of each monitored surface, shape (s,).

    Returns:
        ``(samples, windows, events, status)``: ``samples`` is (nh + n + 2 s + 1, k):
        hypothesis probabilities, blended states, deflection estimates, marginal fault
        probabilities of the surfaces, NIS of the no-fault filter;
        ``windows``/``events`` are row arrays (``WIN_LEN``/``EV_LEN`` columns); ``status`` is 0,
        or -1 when the times are not strictly increasing (``st`` is then left untouched).
    """
    nh, na = arrays.x0.shape
    n = na - arrays.slot_surface.shape[1]
    ns = surface_inputs.shape[0]
    samples = np.empty((nh + n + 2 * ns + 1, t.shape[0]))
    windows, events, status = _bank_kernel(cfg, arrays, st, t, y, u, surface_inputs, samples)
    return samples, windows, events, status


@njit(cache=True, nogil=True, error_model="numpy")
def _unpack(
    st: FloatArray, nh: int, na: int, p: int
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """Filter blocks of the state vector as arrays ``(xs, ps, vs, vflags)``."""
    flen = na + na * na + p * p + 1
    xs = np.empty((nh, na))
    ps = np.empty((nh, na, na))
    vs = np.empty((nh, p, p))
    vflags = np.empty(nh)
    for f in range(nh):
        off = ST_HEADER + f * flen
        for i in range(na):
            xs[f, i] = st[off + i]
            for j in range(na):
                ps[f, i, j] = st[off + na + i * na + j]
        voff = off + na + na * na
        for a in range(p):
            for b in range(p):
                vs[f, a, b] = st[voff + a * p + b]
        vflags[f] = st[voff + p * p]
    return xs, ps, vs, vflags


@njit(cache=True, nogil=True, error_model="numpy")
def _pack(
    st: FloatArray, xs: FloatArray, ps: FloatArray, vs: FloatArray, vflags: FloatArray
) -> None:
    """Inverse of :func:`_unpack`."""
    nh, na = xs.shape
    p = vs.shape[1]
    flen = na + na * na + p * p + 1
    for f in range(nh):
        off = ST_HEADER + f * flen
        for i in range(na):
            st[off + i] = xs[f, i]
            for j in range(na):
                st[off + na + i * na + j] = ps[f, i, j]
        voff = off + na + na * na
        for a in range(p):
            for b in range(p):
                st[voff + a * p + b] = vs[f, a, b]
        st[voff + p * p] = vflags[f]


@njit(cache=True, nogil=True, error_model="numpy")
def _bank_kernel(
    cfg: FloatArray,
    bank: BankArrays,
    st: FloatArray,
    t: FloatArray,
    y: FloatArray,
    u: FloatArray,
    surface_inputs: IntArray,
    samples: FloatArray,
) -> tuple[FloatArray, FloatArray, int]:
    """The compiled loop of :func:`bank_batch`."""
    k_len = t.shape[0]
    nh, na = bank.offset.shape
    n = na - bank.slot_surface.shape[1]
    p = bank.r.shape[0]
    m = u.shape[0]
    for k in range(1, k_len):
        if not t[k] > t[k - 1]:
            return np.empty((0, WIN_LEN)), np.empty((0, EV_LEN)), -1
    flen = na + na * na + p * p + 1
    lay_probs = ST_HEADER + nh * flen
    lay_u = lay_probs + nh
    lay_dec = lay_u + m
    ns = surface_inputs.shape[0]
    n_slots = bank.slot_surface.shape[1]
    lay_kind = lay_dec + ns * D_LEN
    lay_win = lay_kind + ns * KIND_BLOCKS
    lay_groups = lay_win + W_LEN + m
    hw = cfg[CFG_WINDOW]
    windows = np.empty((int(k_len // hw) + 1, WIN_LEN))
    events = np.empty((8, EV_LEN))
    # counters start as int(np.int64(0)), not a literal 0: numba would otherwise compile the callees
    # twice, once for the literal type of the first iteration and once for int64
    n_win = 0
    n_ev = int(np.int64(0))
    variant = int(cfg[CFG_VARIANT])
    likelihood = int(cfg[CFG_LIKELIHOOD])
    rho = cfg[CFG_RHO]
    beta = cfg[CFG_BETA]
    xs, ps, vs, vflags = _unpack(st, nh, na, p)
    dec = st[lay_dec : lay_dec + ns * D_LEN].copy().reshape((ns, D_LEN))
    kbuf = st[lay_kind:lay_win].copy().reshape((ns, KIND_BLOCKS))
    gdec = st[lay_groups : lay_groups + ns * G_LEN].copy().reshape((ns, G_LEN))
    lay_op = lay_groups + ns * G_LEN
    ysm = st[lay_op : lay_op + p]  # smoothed measurements of the operating range (views)
    checks = st[lay_op + p : lay_op + p + CK_LEN]  # status checks (``CK_*``)
    lay_gk = lay_op + p + CK_LEN
    lay_gkb = lay_gk + ns * D_LEN
    gkd = st[lay_gk:lay_gkb].copy().reshape((ns, D_LEN))
    gkb = st[lay_gkb : lay_gkb + ns * KIND_BLOCKS].copy().reshape((ns, KIND_BLOCKS))
    kv = np.empty(ns)  # kind value of each surface at this sample (kind_value)
    dvar = np.empty(ns)  # posterior variance of its deflection estimate
    noise0 = np.nan
    groups_on = cfg[CFG_GROUP] != 0.0
    twin_of = np.full(ns, -1, dtype=np.int64)
    unit_q = np.empty(ns)
    for g in range(ns):
        twin_of[g] = twin_index(bank.collinear, g)
    rebase = cfg[CFG_REBASE] != 0.0
    du_f = np.empty(m)
    qx = np.zeros((max(ns, 1), na))
    # per surface: marginal probability, weighted deflection and variance, best log-likelihood
    # of the filters holding it and of those not holding it
    pm = np.empty(ns)
    dsum = np.empty(ns)
    dmean = np.empty(ns)
    vsum = np.empty(ns)
    ll_in = np.empty(ns)
    ll_out = np.empty(ns)
    rel_in = np.empty(ns)
    rel_base = np.empty(ns)
    p_new = np.empty(ns)
    iso = np.empty(ns)
    rival = np.empty(ns, dtype=np.int64)  # the strongest competitor of each surface's odds
    best_in = np.full(ns, -1, dtype=np.int64)
    probs = st[lay_probs : lay_probs + nh]
    u_last = st[lay_u : lay_u + m]
    wacc = st[lay_win : lay_win + W_LEN]
    applied = st[lay_win + W_LEN : lay_win + W_LEN + m]
    servo_a = cfg[CFG_SERVO_A]
    var_cap = cfg[CFG_DEFL_VAR_CAP]
    is_surface = np.zeros(m, dtype=np.bool_)
    for g in range(ns):
        is_surface[surface_inputs[g]] = True
    du = np.empty(m)
    ytil = np.empty(p)
    valid = np.empty(p, dtype=np.int64)
    ll = np.empty(nh)
    wide = max(na, p)
    work = np.empty((6, wide))
    mats = np.empty((7, wide, wide))
    out2 = np.empty(2)
    nis0 = np.nan
    for k in range(k_len):
        tk = t[k]
        first = st[ST_N_SEEN] == 0.0
        for j in range(m):
            v = u[j, k]
            if math.isfinite(v):
                u_last[j] = v
            if first:
                applied[j] = u_last[j]
            # the step into this sample is driven by the inputs applied after the previous
            # sample (x_k = F x_{k-1} + G u_{k-1}): the previous command through the servo model
            du[j] = applied[j] - bank.u_trim[j]
        nv = int(np.int64(0))
        for a in range(p):
            v = y[a, k]
            if math.isfinite(v):
                ytil[a] = v - bank.y_trim[a]
                valid[nv] = a
                nv += 1
        fails = 0
        for f in range(nh):
            # rebased bank: every other filter takes an active fault's surface at its own
            # filter's estimate (previous posterior), not at its command
            for j in range(m):
                du_f[j] = du[j]
            n_qx = int(np.int64(0))
            if rebase:
                for g in range(ns):
                    if dec[g, D_ACTIVE] != 1.0:
                        continue
                    own = False
                    for e in range(n_slots):
                        if bank.slot_surface[f, e] == g:
                            own = True
                    if own:
                        continue
                    col = surface_inputs[g]
                    du_f[col] = dec[g, D_SMOOTH] - bank.u_trim[col]
                    sd = math.sqrt(max(ps[best_in[g], n, n], 0.0)) if best_in[g] >= 0 else 0.0
                    for i in range(n):
                        qx[n_qx, i] = bank.gin[0, i, col] * sd
                    n_qx += 1
            fails += filter_step(
                f,
                bank,
                xs,
                ps,
                vs,
                vflags,
                du_f,
                ytil,
                valid,
                nv,
                variant,
                likelihood,
                rho,
                beta,
                work,
                mats,
                out2,
                qx,
                n_qx,
            )
            ll[f] = out2[0] if not math.isnan(out2[0]) else -np.inf
            if f == 0:
                nis0 = out2[1] / nv if nv > 0 else np.nan
                noise0 = _innovation_energy(work[1], valid, nv, bank.euclid_weights)
        st[ST_COV_FAIL] += fails
        if nv > 0:
            _bayes(probs, ll, bank.floors)
        # per-sample outputs
        row = 0
        for f in range(nh):
            samples[row, k] = probs[f]
            row += 1
        for i in range(n):
            s = 0.0
            for f in range(nh):
                s += probs[f] * xs[f, i]
            samples[row, k] = bank.x_trim[i] + s
            row += 1
        dt = tk - st[ST_T_PREV] if st[ST_N_SEEN] > 0.0 else 0.0
        a_smooth = 1.0 - math.exp(-dt / cfg[CFG_SMOOTH_S])
        # operating range: outside while a bounded measurement, smoothed, is beyond its bounds;
        # no new detection is made there (the model does not hold)
        a_range = 1.0 - math.exp(-dt / cfg[CFG_RANGE_SMOOTH_S])
        outside = _outside_range(bank, ysm, y[:, k], a_range)
        if outside:
            checks[CK_LAST_OUTSIDE_T] = tk
        # back inside the range, the aircraft is often still near its edge and the filters
        # re-converge from what they tracked outside: no new detection until it has stayed
        # inside for CFG_RANGE_SETTLE_S
        settling = tk - checks[CK_LAST_OUTSIDE_T] < cfg[CFG_RANGE_SETTLE_S]
        _add_noise(checks, noise0, a_range)
        a_clear = 1.0 - math.exp(-dt / cfg[CFG_CLEAR_SMOOTH_S])
        any_active = False
        max_fault = -1.0
        max_hyp = 0
        for g in range(ns):
            pm[g] = 0.0
            dsum[g] = 0.0
            vsum[g] = 0.0
            ll_in[g] = -np.inf
            ll_out[g] = -np.inf
            best_in[g] = -1
        for f in range(nh):
            for g in range(ns):
                slot = -1
                for e in range(n_slots):
                    if bank.slot_surface[f, e] == g:
                        slot = n + e
                if slot >= 0:
                    pm[g] += probs[f]
                    dsum[g] += probs[f] * xs[f, slot]
                    # a filter the data reject (at its probability floor) can have a deflection
                    # variance far beyond its prior, which would swamp the variance of those
                    # that hold the mass: it adds at most the prior's
                    vsum[g] += probs[f] * min(ps[f, slot, slot], var_cap)
                    if ll[f] > ll_in[g] or best_in[g] < 0:
                        ll_in[g] = ll[f]
                        best_in[g] = f
                elif ll[f] > ll_out[g]:
                    ll_out[g] = ll[f]
        _relevant_loglik(bank, dec, ll, probs, rel_in, rel_base, p_new)
        # isolation odds of each surface not in fault against its strongest competitor among
        # the other surfaces not in fault, on the probabilities of "it is the only new fault"
        for g in range(ns):
            comp = 0.0
            rival[g] = -1
            for o in range(ns):
                if o != g and dec[o, D_ACTIVE] != 1.0 and p_new[o] > comp:
                    comp = p_new[o]
                    rival[g] = o
            tot = p_new[g] + comp
            iso[g] = p_new[g] / tot if tot > 0.0 else 0.0
        n_active_before = 0
        for h in range(ns):
            if dec[h, D_ACTIVE] == 1.0:
                n_active_before += 1
        for h in range(ns):
            dmean[h] = dsum[h] / pm[h]
        if groups_on and cfg[CFG_GROUP_HALF_EVIDENCE] != 0.0 and nv > 0:
            for h in range(ns):
                if twin_of[h] > h:
                    on = gdec[h, G_ACTIVE] == 1.0 and n_active_before == 0
                    add_half_evidence(gdec, ll, h, twin_of[h], on)
        ending = cfg[CFG_HOLD_ENDING] != 0.0 and fault_ending(
            cfg, dec, pm, dmean, applied, surface_inputs
        )
        # the latest open onset of a surface or a group not in fault (-inf: none)
        other_onset = -np.inf
        for g in range(ns):
            if dec[g, D_ACTIVE] == 1.0:
                continue
            if math.isfinite(dec[g, D_ONSET_T]):
                other_onset = max(other_onset, dec[g, D_ONSET_T])
            b = twin_of[g]
            if (
                groups_on
                and b > g
                and dec[b, D_ACTIVE] != 1.0
                and gdec[g, G_ACTIVE] != 1.0
                and math.isfinite(gdec[g, G_ONSET_T])
            ):
                other_onset = max(other_onset, gdec[g, G_ONSET_T])
        for h in range(ns):
            defl = dmean[h]
            samples[row, k] = defl
            samples[row + ns, k] = pm[h]
            row += 1
            dec[h, D_DEFL] = defl
            dec[h, D_PROB] = pm[h]
            cmd = applied[surface_inputs[h]]  # the command as the surface follows it
            llr = rel_in[h] - rel_base[h] if nv > 0 and dec[h, D_ACTIVE] != 1.0 else 0.0
            # while its group is detected and no other surface is in fault, a half is named on
            # the stronger odds CFG_GROUP_ISO (beside another fault, on the detection odds, as
            # without the group: the group stage then changes no surface's detection); its odds
            # are then also those of its single-fault filter against its twin's, summed since
            # the group's detection: while the filter freeing both halves holds the mass, both
            # single filters sit at their probability floor, which erases the evidence between
            # them (a fast oscillation of one half, which its own filter follows worse)
            # (with CFG_HALF_GROUP_ODDS the stronger odds hold before the group's detection too,
            # while the half's strongest competitor is its twin: its odds against the twin rest
            # on the small term that separates them, and the first tenths of a second of a
            # fault can favour the wrong half; the group raises the alert meanwhile)
            iso_level = cfg[CFG_DETECT_P]
            iso_h = iso[h]
            lead = min(h, twin_of[h])
            if groups_on and lead >= 0 and n_active_before == 0:
                group_on = gdec[lead, G_ACTIVE] == 1.0
                if group_on or (cfg[CFG_HALF_GROUP_ODDS] != 0.0 and rival[h] == twin_of[h]):
                    iso_level = max(iso_level, cfg[CFG_GROUP_ISO])
                if group_on and cfg[CFG_GROUP_HALF_EVIDENCE] != 0.0:
                    iso_h = max(iso_h, half_odds(gdec, lead, h))
            if outside or settling or ending:
                iso_level = np.inf  # no odds pass: detection withheld (fault_ending)
            dvar[h] = vsum[h] / pm[h]
            kv[h] = kind_value(
                cfg,
                dec,
                bank.slot_surface,
                xs,
                ps,
                probs,
                n,
                h,
                dmean,
                twin_of[h],
                applied[surface_inputs[twin_of[h]]] if twin_of[h] >= 0 else np.nan,
            )
            code = _decide(
                cfg,
                dec,
                kbuf,
                h,
                tk,
                dt,
                pm[h],
                iso_h,
                iso_level,
                defl,
                dvar[h],
                cmd,
                a_smooth,
                a_clear,
                llr,
                detection_hold(cfg, dec, h, twin_of[h], n_active_before),
                kv[h],
                other_onset,
                outside,
            )
            if code != 0:
                events = _write_event(events, n_ev, tk, float(code), dec, h)
                n_ev += 1
                if code == EV_CLEARED:
                    reset_after_clearance(dec, h)
            if dec[h, D_ACTIVE] == 1.0:
                any_active = True
            if pm[h] > max_fault:
                max_fault = pm[h]
                max_hyp = h + 1
        n_active_after = 0
        for h in range(ns):
            if dec[h, D_ACTIVE] == 1.0:
                n_active_after += 1
        if n_active_after != n_active_before:
            # the active set changed: the other surfaces' detection runs restart, their
            # evidence is now measured against the new base hypothesis
            for h in range(ns):
                if dec[h, D_ACTIVE] != 1.0:
                    dec[h, D_ABOVE_T] = np.nan
            # a new detection cuts the open kind spans of the faults active before it
            if n_active_after > n_active_before and cfg[CFG_KIND_CUT] != 0.0:
                for g in range(ns):
                    if dec[g, D_ACTIVE] != 1.0 or dec[g, D_DETECTED_T] != tk:
                        continue
                    for h in range(ns):
                        # a span kept open past its end (CFG_KIND_WAIT_S) is cut at that end at
                        # the latest: the wait only shortens a history
                        t_cut = min(
                            dec[g, D_ONSET_T] - KIND_CUT_MARGIN_S,
                            dec[h, D_KIND_T0] + cfg[CFG_KIND_WINDOW_S],
                        )
                        if (
                            h != g
                            and dec[h, D_ACTIVE] == 1.0
                            and dec[h, D_DETECTED_T] != tk
                            and cut_kind_span(cfg, dec, kbuf, h, t_cut)
                        ):
                            events = _write_event(events, n_ev, tk, EV_CLASSIFIED, dec, h)
                            n_ev += 1
        if groups_on:
            # probability that the new fault is in each unit not in fault: a surface, or a group
            # of twins not in fault (either half or both, on its first half's row; -1 elsewhere)
            for g in range(ns):
                b = twin_of[g]
                unit_q[g] = -1.0
                if dec[g, D_ACTIVE] == 1.0:
                    continue
                if b < 0 or dec[b, D_ACTIVE] == 1.0:
                    unit_q[g] = p_new[g]
                elif b > g:
                    unit_q[g] = p_new[g] + p_new[b] + twin_pair_mass(bank, dec, probs, g, b)
            for h in range(ns):
                a = twin_of[h]
                if a <= h:
                    continue
                q = max(unit_q[h], 0.0)
                comp = 0.0
                for o in range(ns):
                    if o != h and o != a and unit_q[o] > comp:
                        comp = unit_q[o]
                iso_g = q / (q + comp) if q + comp > 0.0 else 0.0
                deflected = False
                for x in (h, a):
                    gate = deflection_gate(cfg, vsum[x] / pm[x])
                    if abs(dec[x, D_SMOOTH] - applied[surface_inputs[x]]) > gate:
                        deflected = True
                back = (
                    abs(dec[h, D_CSMOOTH]) < cfg[CFG_CLEAR_DEFL]
                    and abs(dec[a, D_CSMOOTH]) < cfg[CFG_CLEAR_DEFL]
                )
                llr_g = max(rel_in[h], rel_in[a]) - rel_base[h] if nv > 0 else 0.0
                code = _decide_group(
                    cfg,
                    gdec,
                    dec,
                    h,
                    a,
                    tk,
                    q,
                    iso_g,
                    llr_g,
                    deflected,
                    back,
                    # while as many surfaces are in fault as a hypothesis frees, each filter
                    # freeing a half holds a surface in fault at its command: the group's
                    # evidence is then evidence against a detected fault, not for a new one
                    outside or settling or ending or n_active_after >= n_slots,
                    n_active_after > 0,
                )
                classified = _group_kind(
                    cfg, gdec, gkd, gkb, h, a, tk, kv, dvar, pm, q, outside, code
                )
                if code == EV_GROUP_ISOLATED:
                    half = h if dec[h, D_ACTIVE] == 1.0 else a
                    events = _write_group_event(events, n_ev, tk, EV_CLEARED, gdec, h, a, half, gkd)
                    n_ev += 1
                    reset_group(gdec, h)
                elif code != 0:
                    events = _write_group_event(events, n_ev, tk, float(code), gdec, h, a, -1, gkd)
                    n_ev += 1
                    if code == EV_CLEARED:
                        reset_group(gdec, h)
                if classified:
                    events = _write_group_event(
                        events, n_ev, tk, EV_CLASSIFIED, gdec, h, a, -1, gkd
                    )
                    n_ev += 1
                if gdec[h, G_ACTIVE] == 1.0:
                    any_active = True
        row += ns
        samples[row, k] = nis0
        # health window
        if wacc[W_COUNT] == 0.0:
            wacc[W_T0] = tk
            wacc[W_MAX_FAULT] = -1.0
        wacc[W_COUNT] += 1.0
        wacc[W_SUM_NOMINAL] += probs[0]
        if max_fault > wacc[W_MAX_FAULT]:
            wacc[W_MAX_FAULT] = max_fault
            wacc[W_MAX_FAULT_HYP] = max_hyp
        if math.isfinite(nis0):
            wacc[W_SUM_NIS] += nis0
            wacc[W_N_NIS] += 1.0
        if any_active:
            wacc[W_N_ACTIVE] += 1.0
        if outside:
            checks[CK_OUTSIDE] += 1.0
        wacc[W_COV_FAIL] += fails
        if wacc[W_COUNT] >= hw:
            _close_window(wacc, checks, tk, windows[n_win])
            n_win += 1
        # servo model: a healthy surface follows its command through a first-order lag; the
        # other inputs (throttle) act as commanded, one step later
        for j in range(m):
            if is_surface[j]:
                applied[j] += servo_a * (u_last[j] - applied[j])
            else:
                applied[j] = u_last[j]
        st[ST_T_PREV] = tk
        st[ST_N_SEEN] += 1.0
    _pack(st, xs, ps, vs, vflags)
    st[lay_dec : lay_dec + ns * D_LEN] = dec.ravel()
    st[lay_kind:lay_win] = kbuf.ravel()
    st[lay_groups : lay_groups + ns * G_LEN] = gdec.ravel()
    st[lay_gk:lay_gkb] = gkd.ravel()
    st[lay_gkb : lay_gkb + ns * KIND_BLOCKS] = gkb.ravel()
    return windows[:n_win].copy(), events[:n_ev].copy(), 0
