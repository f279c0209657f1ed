"""Deterioration EKF of a friction drive with remaining-useful-life prognosis.

Seed paper: Rodriguez Obando, Martinez Molina, Berenguer, "Deterioration estimation for remaining
useful lifetime prognosis in a friction drive system", IFAC World Congress 2017 (hal-01564499).

A roller-on-tire actuator: a DC motor drives a wheel through a friction contact of quality
``alpha``, which wears with the power dissipated at the contact (seed eqs. 1-8)::

    J1 dw1/dt = -alpha r1 dv - B1 w1 + Km I,   J2 dw2/dt = alpha r2 dv - B2 w2,
    dalpha/dt = -m dv^2 alpha,   dm/dt = 0,    dv = r1 w1 - r2 w2,
    Dn = 1 - alpha / alpha0                     (normalized deterioration, eq. 8)

An extended Kalman filter on ``x = [w1, w2, alpha, m]`` (eqs. 12-21) uses the measured motor
current as input and both measured speeds; ``estimators.kernels.dekf_kernels`` holds the
per-sample loop and ``estimators.rul`` the Monte Carlo prognosis (section 6).

Choices where the seed is silent (docs/methods-deterioration-ekf.md has the reasons):

* discretization: ``Phi = expm(F dt)`` by a Taylor series of bounded remainder with scaling and
  squaring; the state is predicted by local linearization ``x + int_0^dt expm(F s) ds f(x)``
  (the seed's eq. 16 writes the continuous model); the Jacobian is taken at the posterior;
  ``dt`` is the actual spacing of the sample times;
* the input over ``[t_{k-1}, t_k]`` (``input_model``): by default the mean of its two samples
  with the variance of an edge at an unknown instant, ``dI^2 / 12``, plus a channel-timing
  allowance, propagated through ``Gamma B``; ``"hold"`` is the seed's held ``u_{k-1}`` (eq. 16).
  A NaN current holds the last valid one (0 before any); a NaN speed drops that row of the
  update (both NaN: predict only);
* ``F44`` (the seed's optional ``-100``) enters the covariance propagation only; the state
  prediction keeps ``dm/dt = 0`` (applied to the state it biases ``m`` toward 0);
* the covariance update is in Joseph form (as filterpy's EKF) and stored as its upper triangle;
* noise (``noise_adaptation``): the sensor variances from the running median of the third
  differences of each speed, the speed process noise by covariance matching of the innovations;
  an update whose NIS exceeds the gate (``gate_sigma``) is down-weighted and counted;
* projection (``nonnegative``, seed section 3.2): ``m-hat >= 0``, ``0 <= alpha-hat <= alpha0
  (1 + alpha_max_rel)``; wear predicted at ``max(m, 0)``;
* ``alpha0 = None``: estimated over the first ``alpha0_calibration_s`` (least-variance
  candidate of alpha-hat carried back over the wear, eq. 7); Dn is NaN and the status
  ``learning`` meanwhile;
* plant calibration (``plant_calibration``, ``estimators.dekf_calibration``): over the same
  healthy segment an instrumental-variable regression of the sampled plant on the intervals
  without a current change, fitted for alpha, B1, J1, J2 and the motor-speed channel's time
  offset after the wheel-speed channel's (B2 is not identifiable and stays configured); a fit
  that passes its checks replaces the configured plant in the filter and the prognosis,
  alpha-hat restarts from it (the fit's alpha uncertainty stays as a floor of the band) and,
  with ``alpha0 = None``, gives alpha0; the motor speed is then compared with ``w1 + skew
  dw1/dt``;
* reported bands scaled by ``max(1, NIS / dof)`` of the last health window
  (``covariance_scaling``): innovations larger than their covariance mean P too small by that
  factor;
* served statuses (``serving_status``): ``failed`` latched past the threshold, ``learning``
  before convergence, ``unknown`` while the innovation tests reject (asymmetric hysteresis),
  else the Dn and RUL levels; prognoses are widened by the stream's record of predicted against
  realized wear;
* the first sample initializes the prior: speeds from the configuration or the first
  measurement, ``alpha0``, ``m0`` and ``P0``, and is then used as a measurement.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from functools import cached_property
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import AllowInfNan, Field, Strict, StrictInt, ValidationError, model_validator

from estimators import dekf_calibration as cal
from estimators import rul as rulmod
from estimators.base import (
    STATUSES,
    Batch,
    Diagnosis,
    EstimatorConfigModel,
    EstimatorError,
    EstimatorEvent,
    FloatArray,
    HealthWindow,
    OutOfOrderError,
    RulEstimate,
    Status,
    StatusReport,
    StepOutputs,
    config_error,
    dump_vector_state,
    load_vector_state,
    worst_status,
)
from estimators.kernels import dekf_kernels as kern
from estimators.simulators.friction_drive import FrictionDriveParams

NAME = "deterioration_ekf"
STATE_VERSION = 6
CHANNELS = ("current", "motor_speed", "wheel_speed")
STATE_NAMES = ("w1", "w2", "alpha", "m")
SAMPLE_OUTPUTS = (
    "w1",
    "w2",
    "alpha",
    "m",
    "w1_3sigma",
    "w2_3sigma",
    "alpha_3sigma",
    "m_3sigma",
    "dn",
    "dn_lower",
    "dn_upper",
    "innovation_w1",
    "innovation_w2",
    "innovation_w1_3sigma",
    "innovation_w2_3sigma",
    "nis",
    "r_w1",
    "r_w2",
    "gated",
)
LEVELS: tuple[Status, ...] = ("ok", "watch", "alert")
MIN_WINDOW = 100

# Central 95 % interval of a chi-square variable with 1 and 2 degrees of freedom (the per-sample
# NIS): 1 dof: squares of the 2.5 % and 97.5 % normal quantiles of |z|, i.e. z = 0.0313 and
# 2.2414; 2 dof: -2 ln(1 - p), p = 0.025, 0.975.
NIS_BOUNDS_95 = (
    0.0009820691171752583,
    5.023886187314888,
    -2.0 * math.log(0.975),
    -2.0 * math.log(0.025),
)
# seed section 5.2: R = diag(1.0063e-8, 1.0083e-10); Q = diag(0, 0, 0, sigma_m^2) and
# P0 = sigma_m^2 I with sigma_m^2 = (0.02 - 0)^2 / 12 = 3.3333e-5 (eq. 27)
SIGMA_M2 = 0.02**2 / 12.0


# ----------------------------------------------------------------------------- configuration
FiniteFloat = Annotated[float, Strict(), AllowInfNan(False)]
PositiveFloat = Annotated[FiniteFloat, Field(gt=0.0)]
NonNegativeFloat = Annotated[FiniteFloat, Field(ge=0.0)]
Fraction = Annotated[FiniteFloat, Field(gt=0.0, lt=1.0)]
_PLANT = FrictionDriveParams()


class PlantConfig(EstimatorConfigModel):
    """Physical parameters of the friction drive (seed Table 1)."""

    r1_m: PositiveFloat = Field(default=_PLANT.r1_m, description="external radius of the motor roller, m")
    r2_m: PositiveFloat = Field(default=_PLANT.r2_m, description="external radius of the wheel, m")
    b1_nm_s: PositiveFloat = Field(default=_PLANT.b1_nm_s, description="motor viscous damping, N m s/rad")
    b2_nm_s: PositiveFloat = Field(default=_PLANT.b2_nm_s, description="wheel viscous damping, N m s/rad")
    j1_kg_m2: PositiveFloat = Field(default=_PLANT.j1_kg_m2, description="motor inertia, kg m^2")
    j2_kg_m2: PositiveFloat = Field(default=_PLANT.j2_kg_m2, description="wheel inertia, kg m^2")
    km_nm_a: PositiveFloat = Field(default=_PLANT.km_nm_a, description="motor torque constant, N m/A")

    def params(self) -> FrictionDriveParams:
        """The same values as the simulator's parameter record."""
        return FrictionDriveParams(**self.model_dump())


class DekfConfig(EstimatorConfigModel):
    """Configuration of the deterioration EKF and its prognosis (validated, immutable).

    ``parse_config`` builds it from a JSON-like mapping; the derived kernel vectors are built
    once per config (cached properties, not fields).
    """

    plant: PlantConfig = Field(default=PlantConfig(), description="seed Table 1 values")
    r_diag: tuple[PositiveFloat, PositiveFloat] = Field(
        default=(1.0063e-8, 1.0083e-10),
        description="measurement noise variances of w1, w2, (rad/s)^2 (seed section 5.2); the "
        "starting value when noise_adaptation is on, the fixed value otherwise",
    )
    q_diag: tuple[NonNegativeFloat, NonNegativeFloat, NonNegativeFloat, NonNegativeFloat] = Field(
        default=(0.0, 0.0, 0.0, 0.0),
        description="per-sample process noise variances of w1 (rad/s)^2, w2 (rad/s)^2, alpha "
        "(N s/m)^2 and m (seed eq. 15); added to the m_walk_rel random walk",
    )
    m_walk_rel: NonNegativeFloat = Field(
        default=1e-3,
        description="random walk of the wear rate m, relative to m-hat, per sqrt(s): adds "
        "(m_walk_rel max(m-hat, 0.1 m0))^2 dt to the variance of m each step (seed assumption "
        "iii, a slowly varying m); rate-independent, unlike q_diag",
    )
    current_var: NonNegativeFloat = Field(
        default=0.0, description="variance of the current measurement, A^2 (propagated through Gamma B)"
    )
    input_model: Literal["edge", "interval", "hold"] = Field(
        default="edge",
        description="current over a sample interval: 'edge' = a change between two samples is a "
        "step at an unknown instant, uniform over the interval, whose response has an exact "
        "mean and covariance (changes too small to matter: as 'interval'); 'interval' = the mean "
        "of the two samples bounding it, with the rank-one variance (dI)^2 / 12 of the edge "
        "instant; both plus input_timing_s; 'hold' = the earlier sample held (the seed's eq. "
        "16, exact only when the current changes on the sample grid)",
    )
    input_timing_s: NonNegativeFloat = Field(
        default=0.001,
        description="largest expected offset between the current and the speed channels "
        "(skew and jitter), s; widens the input variance of the intervals next to a change",
    )
    noise_adaptation: bool = Field(
        default=True,
        description="estimate the noise online, so no datasheet R is needed: the sensor noise "
        "of each speed from the running median of its third differences, and the process "
        "noise of the speeds (model, timing and discretization error) by covariance matching "
        "of the innovations",
    )
    noise_memory_s: PositiveFloat = Field(
        default=20.0, description="memory of the noise estimate (exponential forgetting), s"
    )
    gate_sigma: PositiveFloat | None = Field(
        default=5.0,
        description="innovation gate: an update whose NIS exceeds the chi-square quantile of the "
        "tail probability of a normal |z| > gate_sigma is down-weighted (its S scaled up to the "
        "gate, Huber-like) and counted; None: no gating",
    )
    p0_diag: tuple[PositiveFloat, PositiveFloat, PositiveFloat, PositiveFloat] = Field(
        default=(SIGMA_M2, SIGMA_M2, SIGMA_M2, SIGMA_M2),
        description="initial variances of w1, w2, alpha, m (seed section 5.2); the alpha entry "
        "is replaced by (alpha0_prior_rel_std alpha0_prior)^2 when alpha0 is estimated",
    )
    alpha0: PositiveFloat | None = Field(
        default=10.0,
        description="contact quality at Dn = 0, N s/m (default: the seed's section 5.1 value); "
        "null: estimated over the first alpha0_calibration_s seconds of the stream (the unit "
        "must start healthy)",
    )
    alpha0_prior: PositiveFloat = Field(
        default=10.0, description="initial guess of alpha while alpha0 is estimated, N s/m"
    )
    alpha0_prior_rel_std: PositiveFloat = Field(
        default=0.5, description="relative standard deviation of alpha0_prior"
    )
    alpha0_calibration_s: PositiveFloat = Field(
        default=20.0,
        description="length of the segment alpha0 is estimated over, s: the unit must start "
        "healthy, and the current must vary over it (alpha is seen in the transients)",
    )
    plant_calibration: bool = Field(
        default=True,
        description="over the first alpha0_calibration_s seconds (the unit healthy), fit the "
        "motor friction B1, the inertias J1, J2 and the time offset of the motor-speed channel "
        "after the wheel-speed channel to the intervals that hold no current change "
        "(instrumental-variable regression of the sampled plant); a fit that passes its checks "
        "replaces the configured values for the rest of the stream and for the prognosis",
    )
    plant_calibration_tolerance: Annotated[FiniteFloat, Field(gt=0.0, le=0.1)] = Field(
        default=0.001,
        description="current change tolerated inside a calibration interval, relative to the "
        "largest |current| seen in the segment",
    )
    covariance_scaling: bool = Field(
        default=True,
        description="scale the reported bands (the *_3sigma outputs, the Dn bounds, the "
        "diagnosis) by NIS / dof of the last health window when it is above 1: innovations "
        "larger than their predicted covariance mean a covariance too small by that factor",
    )
    alpha_max_rel: NonNegativeFloat = Field(
        default=0.1,
        description="projection bound: alpha-hat <= alpha0 (1 + alpha_max_rel) (with nonnegative)",
    )
    m0: FiniteFloat = Field(default=0.01, description="initial estimate of m (seed section 5.1)")
    w1_0: FiniteFloat | None = Field(default=None, description="initial w1, rad/s; None: first measurement")
    w2_0: FiniteFloat | None = Field(default=None, description="initial w2, rad/s; None: first measurement")
    f44: FiniteFloat = Field(
        default=0.0, description="F44 of the Jacobian (seed section 5.2 uses -100), covariance only, 1/s"
    )
    nonnegative: bool = Field(
        default=True,
        description="physical projection of the estimate: m-hat >= 0, 0 <= alpha-hat <= alpha0 "
        "(1 + alpha_max_rel), wear predicted at max(m-hat, 0) (seed section 3.2)",
    )
    bound_sigma: PositiveFloat = Field(default=3.0, description="c of the bounds c sqrt(P_ii) (eq. 24)")
    expm_tol: Fraction = Field(default=1e-9, description="remainder bound of the discretization series")
    sample_period_s: PositiveFloat | None = Field(
        default=None,
        description="nominal sample period, s: a spacing within 0.1 % of it is taken as exactly "
        "it (absolute time stamps then do not jitter the discretization); None: actual spacing",
    )
    health_window_samples: StrictInt = Field(
        default=2_000, ge=MIN_WINDOW, le=100_000_000, description="health window length, stream samples"
    )
    consistency_sigma: PositiveFloat = Field(
        default=3.0, description="z of the innovation tests (NIS mean, bias, whiteness)"
    )
    consistency_tolerance: NonNegativeFloat = Field(
        default=0.25,
        description="model-error allowance of the consistency tests: the window NIS mean may "
        "exceed its chi-square bound by this fraction and the lag-1 autocorrelation of the "
        "normalized innovations may reach this value before the window is rejected",
    )
    dn_watch: Fraction = Field(default=0.5, description="Dn level of the watch status")
    dn_alert: Fraction = Field(default=0.7, description="Dn level of the alert status")
    dn_hysteresis: NonNegativeFloat = Field(default=0.01, description="Dn drop needed to leave a level")
    rul_every_s: PositiveFloat | Literal["every_batch"] | None = Field(
        default=10.0, description="prognosis period, stream s; 'every_batch'; None: no prognosis"
    )
    rul_failure_dn: Fraction = Field(default=0.9, description="Dn at which the drive is failed")
    rul_load: rulmod.LoadAssumption = Field(
        default=rulmod.SquareWaveLoad(), description="future-load assumption"
    )
    rul_trajectories: StrictInt = Field(default=1000, ge=10, le=1_000_000, description="Monte Carlo size")
    rul_horizon_s: PositiveFloat = Field(default=1.0e7, description="longest RUL looked for, s")
    rul_seed: StrictInt = Field(default=0, ge=0, le=2**63 - 1, description="base seed of the draws")
    rul_watch_s: NonNegativeFloat = Field(default=86_400.0, description="RUL 5 % quantile level, watch, s")
    rul_alert_s: NonNegativeFloat = Field(default=3_600.0, description="RUL 5 % quantile level, alert, s")
    rul_segment_tol: Fraction = Field(default=0.01, description="largest ln(alpha) change per step")
    rul_jump_tol: Fraction = Field(default=0.25, description="ln(alpha) change per cycle jump")
    rul_model_error: bool = Field(
        default=True,
        description="widen the RUL distribution by the stream's own record of predicted "
        "against realized wear (the relative rate errors the filter's covariance does not "
        "explain)",
    )
    rul_converged_m_rel_std: PositiveFloat = Field(
        default=0.2,
        description="the prognosis reports 'learning' until the standard deviation of m-hat is "
        "below this fraction of m-hat (and alpha0 is known)",
    )
    status_hysteresis_windows: StrictInt = Field(
        default=2,
        ge=1,
        le=100,
        description="consecutive health windows that must agree before the consistency verdict "
        "of the status changes (against flapping)",
    )

    @model_validator(mode="after")
    def _levels_in_order(self) -> DekfConfig:
        if self.dn_alert < self.dn_watch:
            raise ValueError("dn_alert must not be below dn_watch")
        if self.rul_failure_dn <= self.dn_alert:
            raise ValueError("rul_failure_dn must be above dn_alert")
        if self.rul_alert_s > self.rul_watch_s:
            raise ValueError("rul_alert_s must not be above rul_watch_s")
        return self

    @cached_property
    def plant_params(self) -> FrictionDriveParams:
        """The plant as the simulator's parameter record."""
        return self.plant.params()

    @cached_property
    def plant_vector(self) -> FloatArray:
        """``[r1, r2, B1, B2, J1, J2, Km]``, the layout of the compiled kernels."""
        plant = self.plant_params.as_array()
        plant.setflags(write=False)
        return plant

    @cached_property
    def kernel_vector(self) -> FloatArray:
        """The flat configuration vector of the compiled kernel (``CFG_*`` layout)."""
        return _kernel_config(self)

    @property
    def observed_bins(self) -> int:
        """Bins of the observed-load ring kept in the state (0 unless the load is observed)."""
        return self.rul_load.bins if isinstance(self.rul_load, rulmod.ObservedLoad) else 0

    @property
    def prognosis(self) -> rulmod.PrognosisSettings:
        """The settings handed to :func:`estimators.rul.prognose`."""
        return rulmod.PrognosisSettings(
            failure_dn=self.rul_failure_dn,
            n_trajectories=self.rul_trajectories,
            horizon_s=self.rul_horizon_s,
            seed=self.rul_seed,
            bound_c=self.bound_sigma,
            eps_seg=self.rul_segment_tol,
            eps_jump=self.rul_jump_tol,
        )


CONFIG_MODEL = DekfConfig


def gate_thresholds(gate_sigma: float | None) -> tuple[float, float]:
    """NIS gates for 1 and 2 measured channels: the chi-square quantiles of the tail
    probability ``p = P(|Z| > gate_sigma)`` of a standard normal (1 dof: ``z^2``; 2 dof:
    ``-2 ln p``). Infinite when gating is off."""
    if gate_sigma is None:
        return math.inf, math.inf
    p = math.erfc(gate_sigma / math.sqrt(2.0))
    return gate_sigma * gate_sigma, -2.0 * math.log(max(p, 1e-300))


def _kernel_config(config: DekfConfig) -> FloatArray:
    """The flat configuration vector of the compiled kernel."""
    cfg = np.zeros(kern.CFG_LEN, dtype=np.float64)
    cfg[kern.CFG_R1 : kern.CFG_R1 + 7] = config.plant_vector
    cfg[kern.CFG_RV : kern.CFG_RV + 2] = config.r_diag
    cfg[kern.CFG_Q : kern.CFG_Q + 4] = config.q_diag
    cfg[kern.CFG_P0 : kern.CFG_P0 + 4] = config.p0_diag
    cfg[kern.CFG_W0] = np.nan if config.w1_0 is None else config.w1_0
    cfg[kern.CFG_W0 + 1] = np.nan if config.w2_0 is None else config.w2_0
    cfg[kern.CFG_ALPHA0] = np.nan if config.alpha0 is None else config.alpha0
    cfg[kern.CFG_M0] = config.m0
    cfg[kern.CFG_F44] = config.f44
    cfg[kern.CFG_BOUND_C] = config.bound_sigma
    cfg[kern.CFG_HEALTH_WINDOW] = config.health_window_samples
    cfg[kern.CFG_EXPM_TOL] = config.expm_tol
    cfg[kern.CFG_DN_WATCH] = config.dn_watch
    cfg[kern.CFG_DN_ALERT] = config.dn_alert
    cfg[kern.CFG_DN_HYST] = config.dn_hysteresis
    every = config.rul_every_s
    cfg[kern.CFG_RUL_EVERY] = every if isinstance(every, float) else np.nan
    if isinstance(config.rul_load, rulmod.ObservedLoad):
        cfg[kern.CFG_OBS_BIN_SAMPLES] = config.rul_load.bin_samples
        cfg[kern.CFG_OBS_BINS] = config.rul_load.bins
    cfg[kern.CFG_NIS_BOUNDS : kern.CFG_NIS_BOUNDS + 4] = NIS_BOUNDS_95
    cfg[kern.CFG_PROJECT] = 1.0 if config.nonnegative else 0.0
    cfg[kern.CFG_CURRENT_VAR] = config.current_var
    cfg[kern.CFG_INV_J1] = 1.0 / config.plant.j1_kg_m2
    cfg[kern.CFG_INV_J2] = 1.0 / config.plant.j2_kg_m2
    cfg[kern.CFG_DT_NOMINAL] = config.sample_period_s or 0.0
    cfg[kern.CFG_INPUT_INTERVAL] = {"edge": 2.0, "interval": 1.0, "hold": 0.0}[config.input_model]
    cfg[kern.CFG_INPUT_TIMING] = config.input_timing_s
    cfg[kern.CFG_ADAPT_MEMORY] = config.noise_memory_s if config.noise_adaptation else 0.0
    g1, g2 = gate_thresholds(config.gate_sigma)
    cfg[kern.CFG_GATE] = g1
    cfg[kern.CFG_GATE + 1] = g2
    cfg[kern.CFG_ALPHA_MAX] = 1.0 + config.alpha_max_rel
    cfg[kern.CFG_M_WALK] = config.m_walk_rel
    cfg[kern.CFG_CALIB_S] = config.alpha0_calibration_s
    cfg[kern.CFG_ALPHA_PRIOR] = config.alpha0_prior
    cfg[kern.CFG_ALPHA_PRIOR_VAR] = (config.alpha0_prior_rel_std * config.alpha0_prior) ** 2
    cfg[kern.CFG_SKEW] = 0.0
    cfg[kern.CFG_PCAL] = 1.0 if config.plant_calibration else 0.0
    cfg[kern.CFG_PCAL_TOL] = config.plant_calibration_tolerance
    cfg[kern.CFG_COV_SCALE] = 1.0 if config.covariance_scaling else 0.0
    cfg.setflags(write=False)
    return cfg


def calibrated_plant(config: DekfConfig, vec: FloatArray) -> FloatArray | None:
    """``[B1, B2, J1, J2, skew]`` in use after an applied plant calibration, else None."""
    if vec[kern.ST_PCAL_OK] != 1.0:
        return None
    return vec[kern.ST_PLANT : kern.ST_PLANT + 5].copy()


def plant_vector_of(config: DekfConfig, vec: FloatArray, t_s: float = math.inf) -> FloatArray:
    """``[r1, r2, B1, B2, J1, J2, Km]`` in use at stream time ``t_s``: the calibrated one from
    the calibration's end on, the configured one before (or without a calibration)."""
    cal = calibrated_plant(config, vec)
    if cal is None or t_s < vec[kern.ST_PCAL_T]:
        return config.plant_vector
    plant = config.plant_vector.copy()
    plant[2:6] = cal[:4]
    plant.setflags(write=False)  # as the configured vector: one compiled signature
    return plant


def _state_kernel_config(config: DekfConfig, vec: FloatArray) -> FloatArray:
    """The kernel configuration for a state: the configured one, with the calibrated plant and
    skew once a calibration has been applied."""
    cal = calibrated_plant(config, vec)
    if cal is None:
        return config.kernel_vector
    cfg = config.kernel_vector.copy()
    cfg[kern.CFG_B1] = cal[0]
    cfg[kern.CFG_B2] = cal[1]
    cfg[kern.CFG_J1] = cal[2]
    cfg[kern.CFG_J2] = cal[3]
    cfg[kern.CFG_INV_J1] = 1.0 / cal[2]
    cfg[kern.CFG_INV_J2] = 1.0 / cal[3]
    cfg[kern.CFG_SKEW] = cal[4]
    cfg[kern.CFG_ALPHA_FLOOR] = float(vec[kern.ST_PCAL_ALPHA_REL])
    # read-only as the configured vector, so that the kernels are compiled for one signature
    cfg.setflags(write=False)
    return cfg


def _apply_calibration(
    config: DekfConfig, events: list[EstimatorEvent], st: FloatArray, cfg: FloatArray, t_end: float
) -> FloatArray:
    """End of the plant-calibration segment (called by the kernel driver): fit the plant to the
    sums in ``st``; if the fit is applied, restart alpha-hat from the fitted alpha (its
    covariance from the fit, its correlations dropped: they were built with the wrong plant),
    give m-hat its prior variance back, and, when alpha0 is estimated, carry the fitted alpha
    back over the wear to the stream start (eq. 7). Returns the kernel configuration to go on
    with."""
    vec = st
    x2 = float(vec[kern.ST_X + 2])
    a_mid = float(vec[kern.ST_PCAL_ALPHA_MID])
    fit = cal.fit_plant(vec, config.plant_vector, a_mid if math.isfinite(a_mid) else x2)
    vec[kern.ST_PCAL_T] = t_end
    vec[kern.ST_PCAL_OK] = 1.0 if fit.applied else 0.0
    detail = fit.as_dict()
    if fit.applied:
        vec[kern.ST_PCAL_ALPHA_REL] = fit.alpha_rel_std
        vec[kern.ST_PLANT : kern.ST_PLANT + 5] = (
            fit.b1, config.plant.b2_nm_s, fit.j1, fit.j2, fit.skew_s
        )  # fmt: skip
        # the fit is alpha at the segment centre; the wear over the second half, unknown (the
        # filter's m-hat was built with the wrong plant), enters as variance at the prior m0
        wear2 = abs(config.m0) * max(float(vec[kern.ST_PCAL_INT] - vec[kern.ST_PCAL_INT_MID]), 0.0)
        alpha_now = fit.alpha
        m_hat = max(float(vec[kern.ST_X + 3]), 0.0)
        p = kern.ST_P
        for i in (2, 3, 5, 6, 8):  # alpha and m rows/columns: p02 p03 p12 p13 p23
            vec[p + i] = 0.0
        vec[p + 7] = (fit.alpha_rel_std**2 + wear2 * wear2) * alpha_now * alpha_now
        # m-hat restarts from its prior: the wear it learnt was that of the wrong plant
        vec[kern.ST_X + 3] = config.m0
        vec[p + 9] = config.p0_diag[3]
        # the innovation record of the wrong plant, and the speed process noise that covariance
        # matching learnt from it, say nothing about the calibrated plant
        vec[kern.ST_NIS_RATIO] = math.nan
        vec[kern.ST_NIS_N] = 0.0
        vec[kern.ST_QW] = 0.0
        vec[kern.ST_QW + 1] = 0.0
        vec[kern.ST_N_ADAPT] = 0.0
        # the health window under way starts afresh: its innovations so far are the wrong
        # plant's (the verdict restarts in step(), in time order with the windows)
        vec[kern.ST_W_COUNT] = 0.0
        vec[kern.ST_W_N_UPD : kern.ST_W_N_E + 1] = 0.0
        vec[kern.ST_W_CH : kern.ST_W_CH + 2 * kern.CH_LEN] = 0.0
        vec[kern.ST_W_N_GATED] = 0.0
        vec[kern.ST_NU_PREV : kern.ST_NU_PREV + 2] = math.nan
        if config.alpha0 is None:
            lf = min(m_hat * float(vec[kern.ST_PCAL_INT_MID]), kern.CALIB_MAX_LOG)  # eq. 7
            vec[kern.ST_ALPHA0] = fit.alpha * math.exp(lf)
            vec[kern.ST_A0_VAR] = fit.alpha_rel_std**2 + (
                float(vec[kern.ST_PCAL_INT_MID]) ** 2 * float(vec[p + 9])
            )
        a0 = float(vec[kern.ST_ALPHA0])
        if config.nonnegative and math.isfinite(a0):
            alpha_now = min(alpha_now, a0 * (1.0 + config.alpha_max_rel))
        vec[kern.ST_X + 2] = alpha_now
        detail["alpha0"] = _none_if_nan(a0)
    events.append(
        EstimatorEvent(
            t_s=t_end,
            kind="plant_calibrated" if fit.applied else "plant_calibration_rejected",
            detail=detail,
        )
    )
    return _state_kernel_config(config, vec)


def parse_config(raw: Mapping[str, Any]) -> DekfConfig:
    """Validate a JSON-like mapping into a :class:`DekfConfig`.

    Raises:
        ConfigError: unknown keys, wrong types or lengths, non-positive plant parameters or
            variances, levels out of order (``dn_watch <= dn_alert < rul_failure_dn``,
            ``rul_alert_s <= rul_watch_s``), counts out of range, an invalid load assumption;
            the message names each offending field.
    """
    try:
        return DekfConfig.model_validate(raw)
    except ValidationError as exc:
        raise config_error(NAME, exc) from None


def config_to_dict(config: DekfConfig) -> dict[str, Any]:
    """The full configuration with defaults filled in, JSON-serializable."""
    return config.model_dump(mode="json")


def required_channels(config: DekfConfig) -> tuple[str, ...]:
    """Motor current (A), motor speed w1 and wheel speed w2 (rad/s)."""
    return CHANNELS


# ----------------------------------------------------------------------------- state
@dataclass(frozen=True)
class DekfState:
    """Everything the filter carries between batches.

    The compiled kernel takes one flat float64 vector; the named, read-only accessors below are
    the layout table (``ST_*`` constants of ``estimators.kernels.dekf_kernels``), so no code
    outside the kernel boundary indexes it by number.

    Attributes:
        version: schema version (``STATE_VERSION``).
        t_last_s: time of the last sample seen (-inf before any).
        vector: FloatArray  # (ST_BASE_LEN + 2 bins,), never modified in place.
    """

    version: int
    t_last_s: float
    vector: FloatArray

    def _get(self, index: int) -> float:
        return float(self.vector[index])

    @property
    def x(self) -> FloatArray:
        """Posterior ``[w1, w2, alpha, m]``: FloatArray  # (4,)."""
        return self.vector[kern.ST_X : kern.ST_X + 4].copy()

    @property
    def P(self) -> FloatArray:  # noqa: N802 - the usual name of the covariance
        """Posterior covariance: FloatArray  # (4, 4), symmetric by construction."""
        return _unpack_cov(self.vector[kern.ST_P : kern.ST_P + 10])

    @property
    def n_samples(self) -> int:
        """Samples seen since the stream start."""
        return int(self.vector[kern.ST_N_SEEN])

    @property
    def initialized(self) -> bool:
        """The prior has been set by a first sample."""
        return self._get(kern.ST_INIT) == 1.0

    @property
    def held_current_a(self) -> float:
        """Last valid current measurement, A."""
        return self._get(kern.ST_U_HELD)

    @property
    def noise_variances(self) -> FloatArray:
        """Measurement noise variances in use, (rad/s)^2: FloatArray  # (2,) (NaN: configured)."""
        return self.vector[kern.ST_R_HAT : kern.ST_R_HAT + 2].copy()

    @property
    def alpha0(self) -> float:
        """alpha0 in use (NaN while it is being estimated)."""
        return self._get(kern.ST_ALPHA0)

    @property
    def dn_level(self) -> int:
        """Index in ``LEVELS`` of the Dn level."""
        return int(self.vector[kern.ST_DN_LEVEL])

    @property
    def gated_updates(self) -> int:
        """Updates down-weighted by the innovation gate since the stream start."""
        return int(self.vector[kern.ST_N_GATED])

    @property
    def consistency_verdict(self) -> bool | None:
        """Innovation consistency after hysteresis (None: no health window yet)."""
        v = self._get(kern.ST_VERDICT)
        return None if not math.isfinite(v) else v == 1.0

    @property
    def failed(self) -> bool:
        """Dn-hat has reached the failure threshold (latched)."""
        return self._get(kern.ST_FAILED) == 1.0

    @property
    def rul_error_record(self) -> tuple[int, float, float]:
        """(count, sum of squared log-rate errors, sum of what the covariance explains)."""
        return (
            int(self.vector[kern.ST_ERR_N]),
            self._get(kern.ST_ERR_SUM2),
            self._get(kern.ST_ERR_SUMV),
        )


_TRIU = np.triu_indices(4)


def _unpack_cov(upper: FloatArray) -> FloatArray:
    cov = np.zeros((4, 4), dtype=np.float64)
    cov[_TRIU] = upper
    return cov + np.triu(cov, 1).T


#: Entries of a fresh state that are not zero (the rest of the vector is zero).
_FRESH_NAN = (
    kern.ST_T_NEXT_RUL,
    kern.ST_NU_PREV,
    kern.ST_NU_PREV + 1,
    kern.ST_LAST_CONSISTENT,
    kern.ST_RUL_Q05,
    kern.ST_R_HAT,
    kern.ST_R_HAT + 1,
    kern.ST_ALPHA0,
    kern.ST_CALIB_T_END,
    kern.ST_VERDICT,
    kern.ST_HIST_T,
    kern.ST_HIST_ELL,
    kern.ST_HIST_RATE,
    kern.ST_HIST_VAR,
    kern.ST_HIST_W,
    kern.ST_HIST_W + 1,
    kern.ST_HIST_M,
    kern.ST_RUL_STATUS,
    *range(kern.ST_Y_HIST, kern.ST_Y_HIST + 6),
    kern.ST_Y_RES,
    kern.ST_Y_RES + 1,
    kern.ST_A0_BEST,
    kern.ST_A0_VAR,
    kern.ST_PCAL_END,
    kern.ST_PCAL_T,
    *range(kern.ST_PCAL_HIST, kern.ST_PCAL_HIST + kern.PCAL_HIST_LEN),
    kern.ST_PCAL_ALPHA_MID,
    kern.ST_PCAL_INT_MID,
    *range(kern.ST_PLANT, kern.ST_PLANT + 5),
    kern.ST_PCAL_OK,
    kern.ST_NIS_RATIO,
    kern.ST_DW_T,
    kern.ST_DW_LEVEL,
    kern.ST_DW_RUN,
)


def initial_state(config: DekfConfig) -> DekfState:
    """State before the first sample (the prior is set by the first sample)."""
    vec = np.zeros(kern.ST_BASE_LEN + 2 * config.observed_bins, dtype=np.float64)
    vec[kern.ST_T_LAST] = -math.inf
    vec[list(_FRESH_NAN)] = np.nan
    vec.setflags(write=False)
    return DekfState(version=STATE_VERSION, t_last_s=-math.inf, vector=vec)


def dump_state(state: DekfState) -> bytes:
    """Versioned byte form of the state (exact round trip; see :func:`dump_vector_state`)."""
    return dump_vector_state(NAME, state.version, state.t_last_s, state.vector)


def _upgrade_v1(doc: dict[str, Any]) -> dict[str, Any]:
    """Version 1 -> 2: the version-2 entries (noise estimate, input change, alpha0, gating,
    status hysteresis, prognosis record) are inserted before the observed-load ring, set as a
    fresh state has them. alpha0 stays NaN with no calibration under way: a version-1 filter
    always ran with a configured alpha0, and the kernel takes the configured one for such a
    state (its alpha-hat if the configuration no longer gives one)."""
    return _insert_fresh(doc, kern.ST_BASE_LEN_V1, kern.ST_BASE_LEN_V2, 2)


def _upgrade_v2(doc: dict[str, Any]) -> dict[str, Any]:
    """Version 2 -> 3: the plant-calibration entries are inserted before the observed-load
    ring, as a fresh state has them. The end of the calibration segment stays NaN: the stream
    is past its start, so no calibration runs and the configured plant stays in use."""
    return _insert_fresh(doc, kern.ST_BASE_LEN_V2, kern.ST_BASE_LEN_V3, 3)


def _insert_fresh(doc: dict[str, Any], old_len: int, new_len: int, version: int) -> dict[str, Any]:
    """Insert the entries ``old_len .. new_len`` of a fresh state before the ring."""
    vec = [float.fromhex(v) for v in doc["vector"]]
    base, ring = vec[:old_len], vec[old_len:]
    fresh = [0.0] * (new_len - old_len)
    for i in _FRESH_NAN:
        if old_len <= i < new_len:
            fresh[i - old_len] = math.nan
    out = dict(doc)
    out["version"] = version
    out["vector"] = [float(v).hex() for v in base + fresh + ring]
    return out


def _upgrade_v3(doc: dict[str, Any]) -> dict[str, Any]:
    """Version 3 -> 4: the entries of the one-step-residual noise estimate (the last posterior
    residuals, NaN, and their running medians, not started) are inserted before the
    observed-load ring; until they have samples the third-difference estimate alone is used,
    as before."""
    return _insert_fresh(doc, kern.ST_BASE_LEN_V3, kern.ST_BASE_LEN_V4, 4)


def _upgrade_v4(doc: dict[str, Any]) -> dict[str, Any]:
    """Version 4 -> 5: the dwell record of an observed load (nothing counted yet) is inserted
    before the observed-load ring; the next prognosis counts the ring's bins into it, its first
    run censored, as after a gap."""
    return _insert_fresh(doc, kern.ST_BASE_LEN_V4, kern.ST_BASE_LEN_V5, 5)


def _upgrade_v5(doc: dict[str, Any]) -> dict[str, Any]:
    """Version 5 -> 6: the last prognosis' speeds and m-hat (NaN) are inserted before the
    observed-load ring; the next comparison of the prognosis record is skipped (nothing to
    predict its span from) and the record goes on from the prognosis after."""
    return _insert_fresh(doc, kern.ST_BASE_LEN_V5, kern.ST_BASE_LEN, 6)


_UPGRADES: dict[int, Callable[[dict[str, Any]], dict[str, Any]]] = {
    1: _upgrade_v1,
    2: _upgrade_v2,
    3: _upgrade_v3,
    4: _upgrade_v4,
    5: _upgrade_v5,
}


def load_state(data: bytes) -> DekfState:
    """Inverse of :func:`dump_state`; older versions are upgraded (``_upgrade_vN``).

    Raises:
        StateVersionError: a version that is neither ``STATE_VERSION`` nor upgradable.
        EstimatorError: the bytes are not a state of this estimator.
    """
    try:
        doc = json.loads(data)
    except (ValueError, UnicodeDecodeError) as exc:
        raise EstimatorError(f"not a {NAME} state: {exc}") from exc
    if isinstance(doc, dict) and doc.get("kind", NAME) == NAME:
        version = doc.get("version")
        try:
            while isinstance(version, int) and version in _UPGRADES:
                doc = _UPGRADES[version](doc)
                version = doc["version"]
        except (KeyError, TypeError, ValueError) as exc:
            raise EstimatorError(f"not a {NAME} state: {exc}") from exc
        data = json.dumps(doc, separators=(",", ":")).encode("ascii")
    t_last, vec = load_vector_state(data, NAME, STATE_VERSION, f"a {NAME}")
    if vec.shape[0] < kern.ST_BASE_LEN or (vec.shape[0] - kern.ST_BASE_LEN) % 2:
        raise EstimatorError(f"not a {NAME} state: vector of length {vec.shape[0]}")
    return DekfState(version=STATE_VERSION, t_last_s=t_last, vector=vec)


# ----------------------------------------------------------------------------- health
def _none_if_nan(value: float) -> float | None:
    v = float(value)
    return v if math.isfinite(v) else None


def chi2_mean_bounds(dof: float, n: float, z: float) -> tuple[float, float]:
    """Two-sided bounds of the mean of ``n`` NIS values whose sum is chi-square with ``dof``
    degrees of freedom, at the probability of a normal |Z| <= z (Wilson-Hilferty
    approximation: relative error below 1e-3 for dof >= 100, the smallest window)."""
    c = 2.0 / (9.0 * dof)
    lo = dof * max(1.0 - c - z * math.sqrt(c), 0.0) ** 3
    hi = dof * (1.0 - c + z * math.sqrt(c)) ** 3
    return float(lo / n), float(hi / n)


def _grade_dn(dn: float | None, config: DekfConfig, reasons: list[str], what: str) -> Status:
    if dn is None:
        return "ok"
    if dn >= config.dn_alert:
        reasons.append(f"{what} {dn:.3f} >= dn_alert {config.dn_alert:g}")
        return "alert"
    if dn >= config.dn_watch:
        reasons.append(f"{what} {dn:.3f} >= dn_watch {config.dn_watch:g}")
        return "watch"
    return "ok"


def _channel_tests(
    row: FloatArray, ch: int, z: float, tol: float
) -> tuple[float | None, float | None, float | None, list[str]]:
    """(bias z-score, lag-1 autocorrelation, its z-score, failures) of one channel's normalized
    innovations nu over the window: bias ``sum(nu) / sqrt(n)``, whiteness
    ``rho = sum(nu_k nu_{k-1}) / sum(nu^2)`` and ``rho sqrt(pairs)``; each ~N(0, 1) when the
    filter is consistent. A test fails when its z-score exceeds ``z`` AND the effect exceeds
    the model-error allowance ``tol`` (mean of nu beyond ``tol``, |rho| beyond ``tol``): long
    windows make any tiny model error statistically significant, which is not a reason to
    distrust the estimate."""
    base = kern.WIN_CH + ch * kern.CH_LEN
    n = row[base + kern.CH_N]
    pairs = row[base + kern.CH_N_LAG]
    sum2 = row[base + kern.CH_SUM2]
    fails: list[str] = []
    name = STATE_NAMES[ch]
    if n < 2.0 or sum2 <= 0.0:
        return None, None, None, fails
    bias_z = float(row[base + kern.CH_SUM] / math.sqrt(n))
    if abs(bias_z) > z and abs(row[base + kern.CH_SUM] / n) > tol:
        fails.append(f"innovation of {name} biased (z {bias_z:.2f})")
    rho = float(row[base + kern.CH_LAG] / sum2)
    rho_z = float(rho * math.sqrt(pairs)) if pairs > 0.0 else None
    if rho_z is not None and abs(rho_z) > z and abs(rho) > tol:
        fails.append(f"innovation of {name} not white (lag-1 autocorrelation {rho:.3f})")
    return bias_z, rho, rho_z, fails


def _dn_of(alpha: float, alpha0: float) -> float | None:
    return _none_if_nan(1.0 - alpha / alpha0) if math.isfinite(alpha0) else None


def _health(row: FloatArray, config: DekfConfig) -> tuple[HealthWindow, bool | None]:
    """The health window of one kernel row, and its consistency verdict (None: no update)."""
    z = config.consistency_sigma
    tol = config.consistency_tolerance
    n = row[kern.WIN_N]
    n_upd = row[kern.WIN_N_UPD]
    x = row[kern.WIN_X : kern.WIN_X + 4]
    sig = row[kern.WIN_SIGMA : kern.WIN_SIGMA + 4]
    alpha0 = float(row[kern.WIN_ALPHA0])
    c = config.bound_sigma
    dn = _dn_of(x[2], alpha0)
    duration = row[kern.WIN_T1] - row[kern.WIN_T0]
    dn0 = row[kern.WIN_DN0]
    ind: dict[str, float | None] = {
        "dn": dn,
        "dn_lower": _dn_of(x[2] + c * sig[2], alpha0),
        "dn_upper": _dn_of(x[2] - c * sig[2], alpha0),
        "dn_rate_per_s": _none_if_nan((dn - dn0) / duration)
        if duration > 0.0 and dn is not None
        else None,
        "alpha": _none_if_nan(x[2]),
        "alpha_3sigma": _none_if_nan(c * sig[2]),
        "alpha0": _none_if_nan(alpha0),
        "m": _none_if_nan(x[3]),
        "m_3sigma": _none_if_nan(c * sig[3]),
        "valid_fraction": float(n_upd / n),
        "gated_fraction": float(row[kern.WIN_N_GATED] / n_upd) if n_upd > 0.0 else None,
        "noise_var_w1": _none_if_nan(row[kern.WIN_R]),
        "noise_var_w2": _none_if_nan(row[kern.WIN_R + 1]),
        "covariance_scale": float(row[kern.WIN_COV_SCALE]),
    }
    fails: list[str] = []
    consistent: bool | None = None
    if n_upd > 0.0:
        dof = row[kern.WIN_SUM_DOF]
        nis_mean = row[kern.WIN_SUM_NIS] / n_upd
        lo, hi = chi2_mean_bounds(dof, n_upd, z)
        ind["nis_mean"] = float(nis_mean)
        ind["nis_mean_lower"] = lo
        ind["nis_mean_upper"] = hi
        ind["nis_out_fraction"] = float(row[kern.WIN_N_NIS_OUT] / n_upd)
        ind["innovation_out_fraction"] = float(row[kern.WIN_N_E_OUT] / row[kern.WIN_N_E])
        if not lo * (1.0 - tol) <= nis_mean <= hi * (1.0 + tol):
            fails.append(
                f"NIS mean {nis_mean:.3g} outside [{lo:.3g}, {hi:.3g}] (allowance {tol:g})"
            )
        for ch, label in ((0, "w1"), (1, "w2")):
            bias_z, rho, rho_z, ch_fails = _channel_tests(row, ch, z, tol)
            ind[f"bias_z_{label}"] = bias_z
            ind[f"whiteness_{label}"] = rho
            ind[f"whiteness_z_{label}"] = rho_z
            fails.extend(ch_fails)
        consistent = not fails
        ind["consistent"] = 1.0 if consistent else 0.0
    else:
        for key in (
            "nis_mean",
            "nis_mean_lower",
            "nis_mean_upper",
            "nis_out_fraction",
            "innovation_out_fraction",
            "bias_z_w1",
            "bias_z_w2",
            "whiteness_w1",
            "whiteness_w2",
            "whiteness_z_w1",
            "whiteness_z_w2",
            "consistent",
        ):
            ind[key] = None
    reasons: list[str] = []
    status: Status
    if dn is None:
        status = "learning"
        reasons.append("alpha0 is being estimated (calibration segment)")
    else:
        status = _grade_dn(dn, config, reasons, "Dn")
        if dn >= config.rul_failure_dn:
            status = "failed"
            reasons.append(f"Dn {dn:.3f} >= rul_failure_dn {config.rul_failure_dn:g}")
        elif consistent is False:
            status = worst_status([status, "unknown"])
            reasons.append("innovations inconsistent: " + "; ".join(fails))
    window = HealthWindow(
        t_start_s=float(row[kern.WIN_T0]),
        t_end_s=float(row[kern.WIN_T1]),
        n_samples=int(n),
        indicators=ind,
        status=status,
        reasons=tuple(reasons),
    )
    return window, consistent


def _apply_verdict(vec: FloatArray, consistent: bool | None, hysteresis: int) -> None:
    """Consistency verdict with asymmetric hysteresis: one rejecting window makes it
    inconsistent at once (never ok while the test rejects); ``hysteresis`` consecutive passing
    windows are needed to make it consistent again (no flapping)."""
    if consistent is None:
        return
    if consistent:
        vec[kern.ST_GOOD_STREAK] += 1.0
        vec[kern.ST_BAD_STREAK] = 0.0
        verdict = vec[kern.ST_VERDICT]
        if not math.isfinite(verdict) or vec[kern.ST_GOOD_STREAK] >= hysteresis:
            vec[kern.ST_VERDICT] = 1.0
    else:
        vec[kern.ST_BAD_STREAK] += 1.0
        vec[kern.ST_GOOD_STREAK] = 0.0
        vec[kern.ST_VERDICT] = 0.0


# ----------------------------------------------------------------------------- RUL
#: A RUL level is left only once the 5 % quantile is this factor above it (hysteresis).
RUL_LEVEL_HYSTERESIS = 1.2


def _rul_level(q05: float | None, config: DekfConfig, previous: Status | None) -> int:
    """0 ok, 1 watch, 2 alert from the 5 % quantile, with hysteresis on the way down."""

    def level(q: float) -> int:
        if q <= config.rul_alert_s:
            return 2
        if q <= config.rul_watch_s:
            return 1
        return 0

    if q05 is None:
        return 0
    target = level(q05)
    prev = {"watch": 1, "alert": 2}.get(previous or "ok", 0)
    if target < prev:
        target = max(target, level(q05 / RUL_LEVEL_HYSTERESIS))
    return target


def serving_status(
    vec: FloatArray,
    config: DekfConfig,
    dn: float | None,
    q05: float | None,
    m: float,
    var_m: float,
) -> tuple[Status, tuple[str, ...]]:
    """The status of the estimator as served (prognoses and the end-of-batch report).

    In order: ``failed`` once Dn-hat has reached ``rul_failure_dn`` (latched); ``learning``
    while alpha0 is being estimated or before the first health-window verdict; ``unknown``
    while the consistency verdict (with its hysteresis) rejects; ``learning`` while m-hat is not
    known to ``rul_converged_m_rel_std``; otherwise the worst of the Dn and RUL levels."""
    reasons: list[str] = []
    if vec[kern.ST_FAILED] == 1.0:
        return "failed", (f"Dn reached rul_failure_dn {config.rul_failure_dn:g}",)
    if dn is None:
        return "learning", ("alpha0 is being estimated (calibration segment)",)
    verdict = vec[kern.ST_VERDICT]
    if not math.isfinite(verdict):
        return "learning", ("no health window completed yet",)
    if verdict == 0.0:
        return "unknown", ("innovations inconsistent in the latest health window(s)",)
    s_m = math.sqrt(max(var_m, 0.0))
    if not (m > 0.0 and s_m <= config.rul_converged_m_rel_std * m):
        return "learning", (
            f"wear rate not converged (m {m:.3g} +- {s_m:.2g}, needs relative std "
            f"<= {config.rul_converged_m_rel_std:g})",
        )
    statuses: list[Status] = [_grade_dn(dn, config, reasons, "Dn")]
    prev_i = vec[kern.ST_RUL_STATUS]
    prev = STATUSES[int(prev_i)] if math.isfinite(prev_i) else None
    lvl = _rul_level(q05, config, prev)
    if lvl:
        statuses.append(LEVELS[lvl])
        limit = config.rul_alert_s if lvl == 2 else config.rul_watch_s
        reasons.append(f"RUL 5 % quantile {q05:.4g} s <= {limit:g} s (with hysteresis)")
    return worst_status(statuses), tuple(reasons)


def _observed_profile(row: FloatArray, bins: int) -> tuple[FloatArray, FloatArray] | None:
    """(durations, currents) of the filled bins of a snapshot row, oldest first."""
    if bins == 0:
        return None
    filled = int(row[kern.RS_FILLED])
    currents = row[kern.RS_RING + bins - filled : kern.RS_RING + bins]
    durations = row[kern.RS_RING + 2 * bins - filled : kern.RS_RING + 2 * bins]
    return durations.copy(), currents.copy()


def dwell_record_of(vec: FloatArray) -> rulmod.DwellRecord:
    """The dwell record of an observed load kept in the state (``ST_DW_*``)."""

    def pair(i: int) -> tuple[float, float]:
        return float(vec[i]), float(vec[i + 1])

    return rulmod.DwellRecord(
        t_s=float(vec[kern.ST_DW_T]),
        level=float(vec[kern.ST_DW_LEVEL]),
        run_s=float(vec[kern.ST_DW_RUN]),
        exposure_s=pair(kern.ST_DW_EXPO),
        switches=pair(kern.ST_DW_SWITCH),
        n=pair(kern.ST_DW_N),
        sum_s=pair(kern.ST_DW_SUM),
        sum2_s2=pair(kern.ST_DW_SUM2),
        restarts=float(vec[kern.ST_DW_RESTARTS]),
        hist=(
            tuple(float(v) for v in vec[kern.ST_DW_HIST : kern.ST_DW_HIST + kern.DW_HIST_BINS]),
            tuple(float(v) for v in vec[kern.ST_DW_HIST + kern.DW_HIST_BINS : kern.ST_DW_HIST + 2 * kern.DW_HIST_BINS]),
        ),
    )


def _store_dwell_record(vec: FloatArray, record: rulmod.DwellRecord) -> None:
    vec[kern.ST_DW_T] = record.t_s
    vec[kern.ST_DW_LEVEL] = record.level
    vec[kern.ST_DW_RUN] = record.run_s
    for i, v in (
        (kern.ST_DW_EXPO, record.exposure_s),
        (kern.ST_DW_SWITCH, record.switches),
        (kern.ST_DW_N, record.n),
        (kern.ST_DW_SUM, record.sum_s),
        (kern.ST_DW_SUM2, record.sum2_s2),
    ):
        vec[i : i + 2] = v
    vec[kern.ST_DW_RESTARTS] = record.restarts
    vec[kern.ST_DW_HIST : kern.ST_DW_HIST + 2 * kern.DW_HIST_BINS] = np.concatenate([record.hist[0], record.hist[1]])


def _observed_dwells(
    load: rulmod.ObservedLoad, row: FloatArray, vec: FloatArray, observed: tuple[FloatArray, FloatArray]
) -> rulmod.DwellLoad | None:
    """The dwell load of a snapshot row (a full ring); with ``dwell_record`` the ring's new bins
    are first counted into the stream's dwell record in ``vec`` (in time order, so the record
    does not depend on the batch split)."""
    record = None
    if load.dwell_record:
        t_end = float(row[kern.RS_T]) - float(row[kern.RS_OB_PARTIAL])
        record = rulmod.update_dwell_record(
            dwell_record_of(vec), observed[0], observed[1], t_end, load.merge_tolerance_a,
            load.dwell_memory_s,
        )  # fmt: skip
        _store_dwell_record(vec, record)
    return rulmod.dwell_load(observed[0], observed[1], load.dwell_pairs, load.merge_tolerance_a, record)


def _predicted_rate(
    config: DekfConfig,
    plant: FloatArray,
    segments: tuple[FloatArray, FloatArray],
    alpha: float,
    m: float,
) -> float:
    """Rate of ``-ln alpha`` (1/s) now, under the assumed load, on its periodic trajectory."""
    seg_d = np.ascontiguousarray(segments[0], dtype=np.float64)
    seg_c = np.ascontiguousarray(segments[1], dtype=np.float64)
    if not (alpha > 0.0 and m > 0.0):
        return math.nan
    memo = np.zeros((seg_d.shape[0], kern.MAX_SUB + 2))
    _, change, _, _ = kern.drifting_probe(
        plant, seg_d, seg_c, math.log(alpha), m, config.rul_segment_tol, memo
    )
    return float(-change / seg_d.sum())


def _predicted_span_wear(
    config: DekfConfig, plant: FloatArray, vec: FloatArray, t_s: float, rate_now: float
) -> float:
    """The wear (``-d ln alpha``) the previous prognosis' model predicts for the span from it to
    ``t_s`` (NaN: no prediction, m-hat had not converged then). A law of the load
    (:func:`rulmod.span_wear`): propagated from that prognosis' state through the law's
    current over the span. An observed load, whose current over the span was not the assumed
    one: the span times the trapezoid of the rates predicted then and now (so that the drift
    of the rate as alpha wears is not counted as an error)."""
    t0 = float(vec[kern.ST_HIST_T])
    rate = float(vec[kern.ST_HIST_RATE])
    if not (math.isfinite(t0) and math.isfinite(rate) and rate > 0.0 and t_s > t0):
        return math.nan
    load = config.rul_load
    if not isinstance(load, rulmod.ObservedLoad):
        segments = rulmod.load_segments(load, t0)
        state = (
            float(vec[kern.ST_HIST_W]),
            float(vec[kern.ST_HIST_W + 1]),
            float(vec[kern.ST_HIST_ELL]),
            float(vec[kern.ST_HIST_M]),
        )
        if segments is None or not all(math.isfinite(v) for v in state):
            return math.nan
        return rulmod.span_wear(plant, segments, state, t_s - t0, config.rul_segment_tol)
    if math.isfinite(rate_now) and rate_now > 0.0:
        rate = 0.5 * (rate + rate_now)
    return rate * (t_s - t0)


def _record_rate_error(
    vec: FloatArray, t_s: float, ell: float, var_ell: float, predicted: float, renewal_var_s: float = 0.0
) -> None:
    """Compare the wear (``-d ln alpha``) realized since the previous prognosis with the
    ``predicted`` one (:func:`_predicted_span_wear`), and add the relative error, the part of
    its square the filter's variances explain, and both changes to the stream's record."""
    t0 = vec[kern.ST_HIST_T]
    if not (math.isfinite(predicted) and predicted > 0.0 and t_s > t0):
        return
    realized = vec[kern.ST_HIST_ELL] - ell
    if not (math.isfinite(realized) and math.isfinite(var_ell)):
        return
    err = (realized - predicted) / predicted
    # the filter's variances of both ln(alpha-hat), and the random cycles of a switching load
    # over the span (its share of the spread is already in the prognosis' interval)
    explained = (var_ell + vec[kern.ST_HIST_VAR]) / (predicted * predicted) + renewal_var_s / (
        t_s - t0
    )
    # exponential forgetting: the record follows changes (a converging m-hat early on, a
    # changing load) over about 1 / (1 - RECORD_FORGETTING) comparisons
    for i in (
        kern.ST_ERR_N,
        kern.ST_ERR_SUM,
        kern.ST_ERR_SUM2,
        kern.ST_ERR_SUMV,
        kern.ST_ERR_REAL,
        kern.ST_ERR_PRED,
    ):
        vec[i] *= RECORD_FORGETTING
    vec[kern.ST_ERR_N] += 1.0
    vec[kern.ST_ERR_SUM] += err
    vec[kern.ST_ERR_SUM2] += err * err
    vec[kern.ST_ERR_SUMV] += explained
    vec[kern.ST_ERR_REAL] += realized
    vec[kern.ST_ERR_PRED] += predicted


#: Weight of the record kept per new comparison.
RECORD_FORGETTING = 0.8
#: Comparisons (forgetting-weighted) needed before the record recalibrates the prognosis;
#: bounds of the ratio.
MIN_RECORD = 2.5
RATIO_BOUNDS = (0.2, 5.0)


def rate_ratio(vec: FloatArray) -> float:
    """Realized over predicted wear, summed over the stream's record (the sums telescope, so
    the noise of alpha-hat and the load phase between prognoses do not accumulate); 1 before
    ``MIN_RECORD`` comparisons or while it is within two standard errors of 1. Reported with
    each prognosis, not applied: dividing the times by it was tried and made the validation
    worse, since the record of a filter whose m-hat is still converging (over-confidently, the
    usual EKF start) says more about the convergence than about the model."""
    pred = vec[kern.ST_ERR_PRED]
    n = vec[kern.ST_ERR_N]
    if n < MIN_RECORD or not pred > 0.0:
        return 1.0
    ratio = min(max(vec[kern.ST_ERR_REAL] / pred, RATIO_BOUNDS[0]), RATIO_BOUNDS[1])
    # applied only where it stands out of the record's own scatter (two standard errors): a
    # random load (telegraph) makes the short-term ratio noisy without any bias to correct
    c = ratio - 1.0
    scatter = (vec[kern.ST_ERR_SUM2] - 2.0 * c * vec[kern.ST_ERR_SUM] + n * c * c) / n
    if c * c <= 4.0 * max(scatter, 0.0) / n:
        return 1.0
    return float(ratio)


def rate_error_var(vec: FloatArray) -> float:
    """Mean square of the relative wear-rate errors (bias included) that the covariance does
    not explain, from the stream's record (0 before ``MIN_RECORD`` comparisons)."""
    n = vec[kern.ST_ERR_N]
    if n < MIN_RECORD:
        return 0.0
    return float(max(0.0, (vec[kern.ST_ERR_SUM2] - vec[kern.ST_ERR_SUMV]) / n))


def prognosis_at(config: DekfConfig, row: FloatArray, vec: FloatArray) -> RulEstimate | None:
    """The RUL estimate of one snapshot row (``RS_*`` layout), with the status as served;
    updates the prognosis record and status in ``vec``. None when alpha0 or the observed load
    is not available yet."""
    t_s = float(row[kern.RS_T])
    x = row[kern.RS_X : kern.RS_X + 4].copy()
    cov = _unpack_cov(row[kern.RS_P : kern.RS_P + 10])
    alpha0 = float(row[kern.RS_ALPHA0])
    t_cal = float(vec[kern.ST_PCAL_T])
    if vec[kern.ST_PCAL_OK] == 1.0 and float(vec[kern.ST_HIST_T]) < t_cal <= t_s:
        # the record compared the predictions of the plant the calibration replaced (checked
        # here, in time order, so that it does not depend on the batch split)
        vec[kern.ST_HIST_T] = math.nan
        for i in (
            kern.ST_ERR_N, kern.ST_ERR_SUM2, kern.ST_ERR_SUMV, kern.ST_ERR_SUM,
            kern.ST_ERR_REAL, kern.ST_ERR_PRED,
        ):  # fmt: skip
            vec[i] = 0.0
    observed = _observed_profile(row, config.observed_bins)
    load = config.rul_load
    dwells: rulmod.DwellLoad | None = None
    if (
        isinstance(load, rulmod.ObservedLoad)
        and load.model == "dwells"
        and observed is not None
        and observed[0].shape[0] >= load.bins
    ):
        dwells = _observed_dwells(load, row, vec, observed)
    segments = (
        (dwells.durations_s, dwells.currents_a)
        if dwells is not None
        else rulmod.load_segments(load, t_s, observed)
    )
    if segments is None or not math.isfinite(alpha0):
        return None
    c = config.bound_sigma
    cov_scale = float(row[kern.RS_COV_SCALE]) if config.covariance_scaling else 1.0
    # the calibrated alpha's own uncertainty is a floor no later data reduce (a plant error)
    floor = float(vec[kern.ST_PCAL_ALPHA_REL]) if t_s >= vec[kern.ST_PCAL_T] else 0.0
    cov[2, 2] += (floor * x[2]) ** 2
    s_alpha = math.sqrt(max(float(cov[2, 2]) * cov_scale, 0.0))
    dn = 1.0 - x[2] / alpha0
    if dn >= config.rul_failure_dn:
        vec[kern.ST_FAILED] = 1.0
    ell = math.log(x[2]) if x[2] > 0.0 else math.nan
    var_ell = float(cov[2, 2]) / (x[2] * x[2]) if x[2] > 0.0 else math.nan
    # the record compares only predictions made once m-hat has converged (the wear rate of a
    # converging filter says nothing about the model's error)
    converged = x[3] > 0.0 and math.sqrt(max(cov[3, 3], 0.0)) <= config.rul_converged_m_rel_std * x[3]
    plant = plant_vector_of(config, vec, t_s)
    rate_now = _predicted_rate(config, plant, segments, x[2], x[3]) if converged else math.nan
    if config.rul_model_error:
        _record_rate_error(
            vec, t_s, ell, var_ell, _predicted_span_wear(config, plant, vec, t_s, rate_now),
            dwells.renewal_var_s if dwells is not None else 0.0,
        )  # fmt: skip
    extra_var = rate_error_var(vec) if config.rul_model_error else 0.0
    ratio = rate_ratio(vec) if config.rul_model_error else 1.0
    # an estimated alpha0 moves the failure level alpha0 (1 - Dn_f): a relative error eps of
    # alpha0 changes the remaining ln(alpha) to go, ln(alpha / alpha_f), by -eps
    a0_var = float(row[kern.RS_A0_VAR])
    to_go = math.log(x[2] / (alpha0 * (1.0 - config.rul_failure_dn))) if x[2] > 0.0 else 0.0
    if math.isfinite(a0_var) and a0_var > 0.0 and to_go > 0.0:
        extra_var += a0_var / (to_go * to_go)
    # a random switching load: the sampling error of the observed mean cycle, and (per
    # trajectory, below) the randomness of the future cycles
    if dwells is not None:
        extra_var += dwells.estimate_rel_var
    settings = config.prognosis
    result = rulmod.prognose(
        plant,
        alpha0,
        x,
        cov,
        t_s,
        segments,
        settings,
        log_time_var=extra_var,
        walk_rel_var_per_s=config.m_walk_rel**2,
        renewal_var_s=dwells.renewal_var_s if dwells is not None else 0.0,
    )
    status, reasons = serving_status(
        vec, config, _none_if_nan(dn), result.q05_s, float(x[3]), float(cov[3, 3])
    )
    vec[kern.ST_HIST_T] = t_s
    vec[kern.ST_HIST_ELL] = ell
    vec[kern.ST_HIST_VAR] = var_ell
    vec[kern.ST_HIST_RATE] = rate_now
    vec[kern.ST_HIST_W : kern.ST_HIST_W + 2] = x[:2]
    vec[kern.ST_HIST_M] = x[3]
    vec[kern.ST_RUL_STATUS] = STATUSES.index(status)
    assumption: dict[str, Any] = {
        "load": rulmod.load_to_dict(config.rul_load),
        "load_segments": {
            "durations_s": [float(v) for v in segments[0]],
            "current_a": [float(v) for v in segments[1]],
        },
        "m_constant": config.m_walk_rel == 0.0,
        "m_walk_rel_per_sqrt_s": config.m_walk_rel,
        "model_error_rel_std": math.sqrt(extra_var),
        "wear_rate_ratio": ratio,
        "model_error_comparisons": int(vec[kern.ST_ERR_N]),
        "failure_dn": config.rul_failure_dn,
        "alpha0": alpha0,
        "plant": {
            "calibrated": bool(plant is not config.plant_vector),
            "b1_nm_s": float(plant[2]),
            "b2_nm_s": float(plant[3]),
            "j1_kg_m2": float(plant[4]),
            "j2_kg_m2": float(plant[5]),
        },
        "alpha_failure": result.alpha_failure,
        "n_trajectories": settings.n_trajectories,
        "horizon_s": settings.horizon_s,
        "seed": settings.seed,
        "seed_entropy": list(result.entropy),
        "reached_fraction": result.reached_fraction,
        "bounds_sigma": c,
    }
    if isinstance(load, rulmod.ObservedLoad) and load.model == "dwells":
        assumption["dwells"] = (
            {
                "low_a": dwells.low_a,
                "high_a": dwells.high_a,
                "observed": {"low": dwells.dwells[0], "high": dwells.dwells[1]},
                "cycle_mean_s": dwells.cycle_mean_s,
                "cycle_std_s": math.sqrt(dwells.cycle_var_s2),
                "estimate_rel_std": math.sqrt(dwells.estimate_rel_var),
                "source": dwells.source,
                "record_restarts": int(vec[kern.ST_DW_RESTARTS]),
            }
            if dwells is not None
            else "too few completed dwells at two levels: the ring is repeated"
        )
    if result.reached_fraction < 1.0:
        assumption["not_reached"] = (
            f"{100.0 * (1.0 - result.reached_fraction):.1f} % of the trajectories do not reach "
            f"Dn = {config.rul_failure_dn:g} within {settings.horizon_s:g} s (or have m <= 0); "
            "statistics they leave undefined are None"
        )
    if len(segments[0]) > 64:
        assumption["load_segments"] = {"count": len(segments[0])}
    return RulEstimate(
        t_s=t_s,
        mean_s=result.mean_s,
        std_s=result.std_s,
        q05_s=result.q05_s,
        q50_s=result.q50_s,
        q95_s=result.q95_s,
        optimistic_s=result.optimistic_s,
        pessimistic_s=result.pessimistic_s,
        threshold=config.rul_failure_dn,
        health={
            "dn": _none_if_nan(dn),
            "dn_lower": _none_if_nan(1.0 - (x[2] + c * s_alpha) / alpha0),
            "dn_upper": _none_if_nan(1.0 - (x[2] - c * s_alpha) / alpha0),
            "alpha": _none_if_nan(x[2]),
            "m": _none_if_nan(x[3]),
        },
        assumption=assumption,
        status=status,
        reasons=reasons,
    )


def covariance_scale(config: DekfConfig, vec: FloatArray) -> float:
    """The factor on the filter's covariance in the reported bands: max(1, NIS / dof of the
    last health window) with ``covariance_scaling``, else 1."""
    ratio = float(vec[kern.ST_NIS_RATIO])
    if not config.covariance_scaling or not math.isfinite(ratio):
        return 1.0
    return max(ratio, 1.0)


def _end_snapshot(vec: FloatArray, t_s: float, bins: int) -> FloatArray:
    """A snapshot row (``RS_*``) of the state at the end of a batch ("every_batch")."""
    row = np.empty(kern.RS_BASE_LEN + 2 * bins, dtype=np.float64)
    row[kern.RS_T] = t_s
    row[kern.RS_X : kern.RS_X + 4] = vec[kern.ST_X : kern.ST_X + 4]
    row[kern.RS_P : kern.RS_P + 10] = vec[kern.ST_P : kern.ST_P + 10]
    row[kern.RS_FILLED] = vec[kern.ST_OB_FILLED]
    row[kern.RS_ALPHA0] = vec[kern.ST_ALPHA0]
    row[kern.RS_A0_VAR] = vec[kern.ST_A0_VAR]
    ok = float(vec[kern.ST_NIS_RATIO])
    row[kern.RS_COV_SCALE] = max(ok, 1.0) if math.isfinite(ok) else 1.0
    row[kern.RS_OB_PARTIAL] = vec[kern.ST_OB_SUM_DT]
    if bins:
        order = (int(vec[kern.ST_OB_HEAD]) + np.arange(bins)) % bins
        row[kern.RS_RING : kern.RS_RING + bins] = vec[kern.ST_RING + order]
        row[kern.RS_RING + bins :] = vec[kern.ST_RING + bins + order]
    return row


# ----------------------------------------------------------------------------- step
def _channel_array(batch: Batch, name: str, n: int) -> FloatArray:
    try:
        values = batch.channels[name]
    except KeyError:
        raise EstimatorError(f"batch has no channel {name!r}") from None
    arr = np.ascontiguousarray(values, dtype=np.float64)
    if arr.shape != (n,):
        raise EstimatorError(f"channel {name!r} has shape {arr.shape}, expected ({n},)")
    return arr


def _dn_event(row: FloatArray, config: DekfConfig) -> EstimatorEvent:
    old = int(row[kern.EV_FROM])
    new = int(row[kern.EV_TO])
    levels = {1: config.dn_watch, 2: config.dn_alert}
    return EstimatorEvent(
        t_s=float(row[kern.EV_T]),
        kind="dn_threshold_crossed",
        detail={
            "from": LEVELS[old],
            "to": LEVELS[new],
            "direction": "up" if new > old else "down",
            "level": levels[max(old, new)] if new > old else levels[old],
            "dn": float(row[kern.EV_DN]),
            "dn_lower": float(row[kern.EV_DN_LO]),
            "dn_upper": float(row[kern.EV_DN_HI]),
            "hysteresis": config.dn_hysteresis,
        },
    )


def _consistency_event(
    window: HealthWindow, consistent: bool | None, vec: FloatArray
) -> EstimatorEvent | None:
    """An event where the raw consistency verdict of the windows changes; updates ``vec``."""
    if consistent is None:
        return None
    last = vec[kern.ST_LAST_CONSISTENT]
    vec[kern.ST_LAST_CONSISTENT] = 1.0 if consistent else 0.0
    if math.isfinite(last) and bool(last) == consistent:
        return None
    if not math.isfinite(last) and consistent:
        return None
    return EstimatorEvent(
        t_s=window.t_end_s,
        kind="innovations_consistent" if consistent else "innovations_inconsistent",
        detail={
            "window_start_s": window.t_start_s,
            "nis_mean": window.indicators["nis_mean"],
            "reasons": list(window.reasons),
        },
    )


def _status_event(est: RulEstimate, previous: Status | None) -> EstimatorEvent | None:
    """``rul_threshold_crossed`` where the served status of successive prognoses changes (any
    of the six statuses, not only the RUL levels)."""
    if previous == est.status:
        return None
    return EstimatorEvent(
        t_s=est.t_s,
        kind="rul_threshold_crossed",
        detail={
            "from": previous,
            "to": est.status,
            "q05_s": est.q05_s,
            "q50_s": est.q50_s,
            "q95_s": est.q95_s,
            "reasons": list(est.reasons),
        },
    )


def _status(vec: FloatArray, config: DekfConfig) -> StatusReport:
    """The served status at the end of a batch (:func:`serving_status`), the latest RUL 5 %
    quantile standing for the RUL level; Dn-hat past the threshold latches ``failed``."""
    alpha0 = float(vec[kern.ST_ALPHA0])
    dn = _dn_of(float(vec[kern.ST_X + 2]), alpha0)
    if dn is not None and dn >= config.rul_failure_dn:
        vec[kern.ST_FAILED] = 1.0
    q05 = _none_if_nan(vec[kern.ST_RUL_Q05])
    status, reasons = serving_status(
        vec, config, dn, q05, float(vec[kern.ST_X + 3]), float(vec[kern.ST_P + 9])
    )
    return StatusReport(status=status, reasons=reasons)


def _diagnosis(vec: FloatArray, t_s: float, config: DekfConfig) -> Diagnosis:
    x = vec[kern.ST_X : kern.ST_X + 4]
    sig = np.sqrt(np.clip(np.diag(_unpack_cov(vec[kern.ST_P : kern.ST_P + 10])), 0.0, None))
    scale = covariance_scale(config, vec)
    sig = sig * math.sqrt(scale)
    c = config.bound_sigma
    alpha0 = float(vec[kern.ST_ALPHA0])
    detail: dict[str, Any] = {"covariance_scale": scale}
    for i, name in enumerate(STATE_NAMES):
        detail[name] = _none_if_nan(x[i])
        detail[f"{name}_3sigma"] = _none_if_nan(c * sig[i])
    detail["alpha0"] = _none_if_nan(alpha0)
    detail["dn"] = _dn_of(x[2], alpha0)
    detail["dn_lower"] = _dn_of(x[2] + c * sig[2], alpha0)
    detail["dn_upper"] = _dn_of(x[2] - c * sig[2], alpha0)
    detail["dn_level"] = LEVELS[int(vec[kern.ST_DN_LEVEL])]
    last = vec[kern.ST_LAST_CONSISTENT]
    detail["innovations_consistent"] = None if not math.isfinite(last) else bool(last)
    verdict = vec[kern.ST_VERDICT]
    detail["consistency_verdict"] = None if not math.isfinite(verdict) else bool(verdict)
    detail["noise_var_w1"] = _none_if_nan(vec[kern.ST_R_HAT])
    detail["noise_var_w2"] = _none_if_nan(vec[kern.ST_R_HAT + 1])
    detail["gated_updates"] = int(vec[kern.ST_N_GATED])
    detail["rul_q05_s"] = _none_if_nan(vec[kern.ST_RUL_Q05])
    served = vec[kern.ST_RUL_STATUS]
    detail["rul_level"] = STATUSES[int(served)] if math.isfinite(served) else None
    detail["rul_model_error_rel_std"] = math.sqrt(rate_error_var(vec))
    ok = vec[kern.ST_PCAL_OK]
    cal_plant = calibrated_plant(config, vec)
    detail["plant_calibration"] = (
        None
        if not math.isfinite(ok)
        else {
            "applied": bool(ok == 1.0),
            "t_s": _none_if_nan(vec[kern.ST_PCAL_T]),
            "b1_nm_s": None if cal_plant is None else float(cal_plant[0]),
            "j1_kg_m2": None if cal_plant is None else float(cal_plant[2]),
            "j2_kg_m2": None if cal_plant is None else float(cal_plant[3]),
            "skew_s": None if cal_plant is None else float(cal_plant[4]),
        }
    )
    return Diagnosis(t_s=t_s, detail=detail)


def step(config: DekfConfig, state: DekfState, batch: Batch) -> tuple[DekfState, StepOutputs]:
    """Advance the filter over a whole batch (the per-sample loop runs compiled).

    Per-sample outputs (float64, aligned with ``batch.t_s``): the posterior ``w1``, ``w2``,
    ``alpha``, ``m`` and their half-widths ``c sqrt(P_ii)`` (``*_3sigma``, eq. 24), ``dn`` and
    its bounds ``dn_lower``/``dn_upper`` (from alpha +- c sigma; NaN while alpha0 is being
    estimated), the innovations ``innovation_w1``/``innovation_w2`` (NaN where the speed is
    missing) with their bounds ``c sqrt(S_jj)`` (eq. 26), ``nis`` (``e^T S^-1 e`` over the
    measured channels), the noise variances in use ``r_w1``/``r_w2`` and ``gated`` (1 where the
    update was down-weighted).

    Health windows, consistency events and prognoses are processed in time order, so each
    prognosis is served with the consistency verdict of the windows completed before it
    (whatever the batch split).

    Raises:
        OutOfOrderError: the batch starts at or before ``state.t_last_s``, or its times are not
            strictly increasing.
        EstimatorError: a channel is missing or has the wrong length, or the state does not
            match the configuration (observed-load ring size).
    """
    t = np.ascontiguousarray(batch.t_s, dtype=np.float64)
    n = int(t.shape[0])
    if n == 0:
        empty = np.empty(0, dtype=np.float64)
        return state, StepOutputs(samples={name: empty for name in SAMPLE_OUTPUTS})
    if not t[0] > state.t_last_s:
        raise OutOfOrderError(
            f"batch starts at t={float(t[0])!r} s, not after the last sample t={state.t_last_s!r} s"
        )
    if state.vector.shape[0] != kern.ST_BASE_LEN + 2 * config.observed_bins:
        raise EstimatorError("state does not match the configuration (observed-load bins)")
    cur = _channel_array(batch, "current", n)
    w1 = _channel_array(batch, "motor_speed", n)
    w2 = _channel_array(batch, "wheel_speed", n)
    vec = state.vector.copy()
    cal_events: list[EstimatorEvent] = []
    out, win_rows, ev_rows, snap_rows, status = kern.ekf_batch(
        _state_kernel_config(config, vec),
        vec,
        t,
        cur,
        w1,
        w2,
        calibrate=lambda st, cfg, t_end: _apply_calibration(config, cal_events, st, cfg, t_end),
    )
    if status != 0:
        raise OutOfOrderError("batch times are not strictly increasing")
    samples = {name: out[i] for i, name in enumerate(SAMPLE_OUTPUTS)}
    windows = [_health(row, config) for row in win_rows]
    events = [_dn_event(row, config) for row in ev_rows]
    events.extend(cal_events)
    if config.rul_every_s == "every_batch":
        snap_rows = _end_snapshot(vec, float(t[n - 1]), config.observed_bins)[None, :]
    # windows and prognoses in time order (a window ending at a prognosis time comes first)
    queue: list[tuple[float, int, int]] = [(w.t_end_s, 0, i) for i, (w, _) in enumerate(windows)]
    queue.extend((float(row[kern.RS_T]), 1, i) for i, row in enumerate(snap_rows))
    # an applied plant calibration restarts the consistency verdict: the windows before it
    # tested the configured plant, not the one in use
    queue.extend((e.t_s, 2, 0) for e in cal_events if e.kind == "plant_calibrated")
    queue.sort()
    estimates: list[RulEstimate] = []
    for _, what, i in queue:
        if what == 2:
            vec[kern.ST_VERDICT] = math.nan
            vec[kern.ST_GOOD_STREAK] = 0.0
            vec[kern.ST_BAD_STREAK] = 0.0
            continue
        if what == 0:
            window, consistent = windows[i]
            _apply_verdict(vec, consistent, config.status_hysteresis_windows)
            if (ev := _consistency_event(window, consistent, vec)) is not None:
                events.append(ev)
            continue
        prev_i = vec[kern.ST_RUL_STATUS]
        previous: Status | None = STATUSES[int(prev_i)] if math.isfinite(prev_i) else None
        est = prognosis_at(config, snap_rows[i], vec)
        if est is None:
            continue
        estimates.append(est)
        vec[kern.ST_RUL_Q05] = np.nan if est.q05_s is None else est.q05_s
        if (ev2 := _status_event(est, previous)) is not None:
            events.append(ev2)
    events.sort(key=lambda e: e.t_s)
    report = _status(vec, config)
    vec.setflags(write=False)
    new_state = DekfState(version=STATE_VERSION, t_last_s=float(t[n - 1]), vector=vec)
    outputs = StepOutputs(
        samples=samples,
        health=[w for w, _ in windows],
        events=events,
        rul=estimates,
        diagnosis=_diagnosis(vec, float(t[n - 1]), config),
        status=report,
    )
    return new_state, outputs


def warm_up() -> None:
    """Compile (or load from numba's cache) every kernel on tiny inputs."""
    n = 300
    t = np.arange(n, dtype=np.float64) * 1e-3
    rng = np.random.default_rng(0)
    channels = {
        "current": np.where(np.arange(n) < n // 2, 20.0, 0.0),
        "motor_speed": 1e-4 * rng.standard_normal(n),
        "wheel_speed": 1e-5 * rng.standard_normal(n),
    }
    channels["motor_speed"][5] = np.nan
    for raw in (
        {"alpha0": 10.0, "f44": -100.0},
        {"alpha0": None, "alpha0_calibration_s": 0.05, "input_model": "hold", "noise_adaptation": False},
    ):
        config = parse_config(
            {
                "health_window_samples": 100,
                "rul_every_s": 0.1,
                "rul_trajectories": 10,
                "rul_horizon_s": 10.0,
                **raw,
            }
        )
        step(config, initial_state(config), Batch(t_s=t, channels=channels))
