"""Plant calibration of the deterioration EKF over the healthy start of a stream.

The filter's plant (seed Table 1) is rarely the unit's: friction and inertia off by 10-20 % make
alpha-hat absorb the mismatch (a bias of up to the mismatch, thousands of its own sigma) and
make the prognosis propagate a wrong sliding factor. Over the calibration segment (the first
``alpha0_calibration_s`` seconds, the unit healthy, alpha nearly constant) the kernel
(``estimators.kernels.dekf_kernels._pcal_accumulate``) sums an instrumental-variable regression
of the sampled plant over the intervals that hold no current change::

    y_k = Ad y_{k-1} + Bd I          (exact for the LTI plant of seed eqs. 1-4, alpha frozen)

with a first-order drift of ``(Ad, Bd)`` in time (alpha wears a little over the segment) and
the samples at ``k-2`` as instruments (the noise of the regressor ``y_{k-1}`` would bias plain
least squares). :func:`fit_plant` then fits the physical parameters to the map at the segment
centre by Gauss-Newton (``scipy.optimize.least_squares``), weighted by the regression's
information::

    A(alpha, J1, B1, J2) = [[-(alpha r1^2 + B1)/J1, alpha r1 r2/J1],
                            [alpha r1 r2/J2, -(alpha r2^2 + B2)/J2]],   B = [Km/J1, 0]
    [[Ad, Bd], [0, 1]] = expm([[A, B], [0, 0]] dt)

and, for a w1 channel sampled ``skew`` seconds after the w2 channel, ``C = [e1^T expm(A skew),
e2^T]`` (with the matching input term): the observed map is ``C Ad C^-1`` (a pure common delay
of both channels leaves the map unchanged, so only the relative skew is identifiable).

Identifiability, with the torque constant ``Km`` and the radii known: the input gain gives J1,
the coupling terms alpha / J1 and alpha / J2, the steady states B1; alpha, J1, B1, J2 and the
relative skew follow. B2 only moves A22 by about 0.1 % (``B2 << alpha r2^2``) and is not
identifiable from such data: it keeps its configured value (it barely changes the wear, which
the transient slip dominates). A fit is applied only if it converged, every relative standard
deviation is below ``MAX_REL_STD`` and every factor is within ``MAX_FACTOR`` of the configured
value; otherwise the configured plant is kept and the rejection is reported.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.linalg import expm

from estimators.base import FloatArray
from estimators.kernels import dekf_kernels as kern

#: a parameter whose relative standard deviation exceeds this is not applied (nor the fit)
MAX_REL_STD = 0.05
#: a fitted factor beyond [1 / MAX_FACTOR, MAX_FACTOR] of the configured value is not believed
MAX_FACTOR = 1.6
#: the skew is applied only when it is this many of its standard deviations from 0 and at least
#: MIN_SKEW_S
SKEW_SIGNIFICANCE = 2.0
MIN_SKEW_S = 5e-5
#: rows needed before a fit is attempted
MIN_ROWS = 200
#: a fit is applied only if some parameter differs from its configured value by more than this
#: (relative) and by more than 3 of its standard deviations: the validation's fits were off by up
#: to 2-3 % of J1 (their standard deviations understate that), so a fit closer than this to the
#: configured plant confirms it rather than replacing it by a noisier one
MIN_CHANGE = 0.01


@dataclass(frozen=True)
class PlantFit:
    """Outcome of :func:`fit_plant`.

    Attributes:
        applied: the fit passed its checks and replaces the configured plant.
        reason: why it was rejected ("" when applied).
        rows: regression rows used.
        alpha: alpha at the segment centre, N s/m (NaN if no fit).
        alpha_rel_std: its relative standard deviation.
        b1, j1, j2: fitted B1 (N m s/rad), J1, J2 (kg m^2).
        rel_std: relative standard deviations of (B1, J1, J2).
        skew_s: time of the w1 samples after the w2 samples, s (0 if not significant).
        skew_std_s: its standard deviation, s.
    """

    applied: bool
    reason: str
    rows: int
    alpha: float = math.nan
    alpha_rel_std: float = math.nan
    b1: float = math.nan
    j1: float = math.nan
    j2: float = math.nan
    rel_std: tuple[float, float, float] = (math.nan, math.nan, math.nan)
    skew_s: float = 0.0
    skew_std_s: float = math.nan

    def as_dict(self) -> dict[str, object]:
        """JSON-serializable detail (NaN as None)."""

        def num(v: float) -> float | None:
            return float(v) if math.isfinite(v) else None

        return {
            "applied": self.applied,
            "reason": self.reason,
            "rows": self.rows,
            "alpha": num(self.alpha),
            "alpha_rel_std": num(self.alpha_rel_std),
            "b1_nm_s": num(self.b1),
            "j1_kg_m2": num(self.j1),
            "j2_kg_m2": num(self.j2),
            "b1_rel_std": num(self.rel_std[0]),
            "j1_rel_std": num(self.rel_std[1]),
            "j2_rel_std": num(self.rel_std[2]),
            "skew_s": num(self.skew_s),
            "skew_std_s": num(self.skew_std_s),
        }


def sampled_map(theta: FloatArray, plant: FloatArray, dt: float) -> FloatArray:
    """The observed one-step map ``[Ad^T; Bd^T]`` (3 x 2, the regression's layout) of the plant
    with ``theta = [ln alpha, ln J1, ln B1, ln J2, skew]``; ``plant`` = ``[r1, r2, B1, B2, J1,
    J2, Km]`` (r1, r2, B2, Km used)."""
    r1, r2, b2, km = plant[0], plant[1], plant[3], plant[6]
    al, j1, b1, j2 = np.exp(theta[:4])
    skew = float(theta[4])
    a = np.array(
        [[-(al * r1 * r1 + b1) / j1, al * r1 * r2 / j1], [al * r1 * r2 / j2, -(al * r2 * r2 + b2) / j2]]
    )
    b = np.array([km / j1, 0.0])
    aug = np.zeros((3, 3))
    aug[:2, :2] = a
    aug[:2, 2] = b
    e = expm(aug * dt)
    ad, bd = e[:2, :2], e[:2, 2]
    es = expm(aug * skew)
    c = np.array([es[0, :2], [0.0, 1.0]])
    cu = np.array([es[0, 2], 0.0])
    adp = c @ ad @ np.linalg.inv(c)
    bdp = c @ bd + cu - adp @ cu
    return np.vstack([adp.T, bdp[None, :]])


def _sums(
    st: FloatArray,
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray, FloatArray]:
    r = kern.PCAL_REG
    wz = st[kern.ST_PCAL_WZ : kern.ST_PCAL_WZ + r * r].reshape(r, r)
    wy = st[kern.ST_PCAL_WY : kern.ST_PCAL_WY + 2 * r].reshape(r, 2)
    zz = st[kern.ST_PCAL_ZZ : kern.ST_PCAL_ZZ + r * r].reshape(r, r)
    zy = st[kern.ST_PCAL_ZY : kern.ST_PCAL_ZY + 2 * r].reshape(r, 2)
    yy = st[kern.ST_PCAL_YY : kern.ST_PCAL_YY + 4].reshape(2, 2)
    ww = st[kern.ST_PCAL_WW : kern.ST_PCAL_WW + r * r].reshape(r, r)
    return wz, wy, zz, zy, yy, ww


def fit_plant(st: FloatArray, plant: FloatArray, alpha_guess: float) -> PlantFit:
    """Fit alpha, B1, J1, J2 and the w1 skew to the calibration sums held in ``st``.

    Args:
        st: the kernel state vector (``ST_PCAL_*`` sums).
        plant: the configured ``[r1, r2, B1, B2, J1, J2, Km]``.
        alpha_guess: start value of alpha (alpha-hat or alpha0).

    Returns:
        The fit; ``applied`` is False (with the reason) when it is not to be used.
    """
    rows = int(st[kern.ST_PCAL_N])
    if rows < MIN_ROWS:
        return PlantFit(False, f"{rows} intervals without a current change (need {MIN_ROWS})", rows)
    dt = float(st[kern.ST_PCAL_DT]) / rows
    wz, wy, zz, zy, yy, ww = _sums(st)
    try:
        theta_reg = np.linalg.solve(wz, wy)
        # covariance of the IV estimate per unit residual variance: (W'Z)^-1 W'W (Z'W)^-1;
        # the information on the map at the centre is the inverse of its first 3x3 block
        wz_inv = np.linalg.inv(wz)
        iv_cov = wz_inv @ ww @ wz_inv.T
        info = np.linalg.inv(0.5 * (iv_cov[:3, :3] + iv_cov[:3, :3].T))
        chol = np.linalg.cholesky(0.5 * (info + info.T))
    except np.linalg.LinAlgError:
        return PlantFit(False, "calibration regression singular (no excitation)", rows)
    resid = yy - theta_reg.T @ zy - zy.T @ theta_reg + theta_reg.T @ zz @ theta_reg
    sig2 = np.maximum(np.diag(resid) / max(rows - kern.PCAL_REG, 1), 1e-300)
    target = theta_reg[:3]

    def residual(theta: FloatArray) -> FloatArray:
        d = sampled_map(theta, plant, dt) - target
        return np.concatenate([(chol.T @ d[:, j]) / math.sqrt(sig2[j]) for j in range(2)])

    from scipy.optimize import least_squares  # here: a costly import, used at calibration only

    guess = alpha_guess if math.isfinite(alpha_guess) and alpha_guess > 0.0 else 10.0
    x0 = np.array([math.log(guess), math.log(plant[4]), math.log(plant[2]), math.log(plant[5]), 0.0])
    try:
        sol = least_squares(
            residual, x0, x_scale=np.array([0.1, 0.1, 0.1, 0.1, 1e-3]), method="lm", max_nfev=400
        )
        jac = sol.jac
        dof = max(sol.fun.shape[0] - x0.shape[0], 1)
        cov = np.linalg.pinv(jac.T @ jac) * max(1.0, 2.0 * sol.cost / dof)
    except (ValueError, np.linalg.LinAlgError) as exc:
        return PlantFit(False, f"calibration fit failed: {exc}", rows)
    sd = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    th = sol.x
    alpha, j1, b1, j2 = (float(v) for v in np.exp(th[:4]))
    skew, skew_sd = float(th[4]), float(sd[4])
    fit = PlantFit(
        applied=False,
        reason="",
        rows=rows,
        alpha=alpha,
        alpha_rel_std=float(sd[0]),
        b1=b1,
        j1=j1,
        j2=j2,
        rel_std=(float(sd[2]), float(sd[1]), float(sd[3])),
        skew_s=skew if abs(skew) > max(SKEW_SIGNIFICANCE * skew_sd, MIN_SKEW_S) else 0.0,
        skew_std_s=skew_sd,
    )
    if not sol.success or not np.all(np.isfinite(th)):
        return _rejected(fit, "calibration fit did not converge")
    for name, rel, value, ref in (
        ("alpha", float(sd[0]), alpha, guess),
        ("B1", float(sd[2]), b1, plant[2]),
        ("J1", float(sd[1]), j1, plant[4]),
        ("J2", float(sd[3]), j2, plant[5]),
    ):
        if not rel <= MAX_REL_STD:
            return _rejected(fit, f"{name} not identified (relative std {rel:.3g})")
        if name != "alpha" and not 1.0 / MAX_FACTOR <= value / ref <= MAX_FACTOR:
            return _rejected(fit, f"{name} {value:.4g} implausible (configured {ref:.4g})")
    changes = [
        (abs(value / ref - 1.0), rel)
        for value, ref, rel in ((b1, plant[2], sd[2]), (j1, plant[4], sd[1]), (j2, plant[5], sd[3]))
    ]
    if all(change <= max(MIN_CHANGE, 3.0 * float(rel)) for change, rel in changes):
        if fit.skew_s == 0.0:
            return _rejected(
                fit,
                f"the configured plant agrees with the fit (B1, J1, J2 within {MIN_CHANGE:g} "
                "relative): kept",
            )
        # only the skew is applied; the configured plant is confirmed
        return PlantFit(
            **{**fit.__dict__, "applied": True, "b1": plant[2], "j1": plant[4], "j2": plant[5]}
        )
    return PlantFit(**{**fit.__dict__, "applied": True})


def _rejected(fit: PlantFit, reason: str) -> PlantFit:
    return PlantFit(**{**fit.__dict__, "applied": False, "reason": reason})
