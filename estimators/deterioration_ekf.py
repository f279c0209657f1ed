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
* the input over ``[t_{k-1}, t_k]`` is the current of sample k-1 (zero-order hold); a NaN current
  holds the last valid one (0 before any); a NaN speed drops that row of the update (both NaN:
  predict only);
* ``F44`` (the seed's optional ``-100``) enters the covariance propagation only; the state
  prediction keeps ``dm/dt = 0`` (applied to the state it biases ``m`` toward 0);
* the covariance update is in Joseph form (as filterpy's EKF) and stored as its upper triangle;
* alpha and m are non-negative (seed section 3.2): with ``nonnegative`` (default) the updated
  alpha is clipped at 0 and the prediction wears alpha at the rate ``max(m, 0)``; m-hat itself
  is not clipped (that would bias it). Without this the filter diverges once alpha nears 0 and
  m becomes unobservable;
* the first sample initializes the prior: speeds from the configuration or the first
  measurement, ``alpha0``, ``m0`` and ``P0``, and is then used as a measurement.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field, fields
from typing import Any, Literal

import numpy as np

from estimators import rul as rulmod
from estimators.base import (
    Batch,
    ConfigError,
    Diagnosis,
    EstimatorError,
    EstimatorEvent,
    FloatArray,
    HealthWindow,
    OutOfOrderError,
    RulEstimate,
    Status,
    StatusReport,
    StepOutputs,
    dump_vector_state,
    load_vector_state,
    worst_status,
)
from estimators.checks import finite as _finite
from estimators.checks import non_negative as _non_negative
from estimators.checks import positive as _positive
from estimators.kernels import dekf_kernels as kern
from estimators.simulators.friction_drive import FrictionDriveParams

NAME = "deterioration_ekf"
STATE_VERSION = 1
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
@dataclass(frozen=True)
class DekfConfig:
    """Validated configuration (build it with :func:`parse_config`).

    Attributes:
        plant: radii, dampings, inertias and motor constant (seed Table 1).
        r_diag: measurement noise variances of w1, w2 ((rad/s)^2; seed section 5.2).
        q_diag: per-sample process noise variances of w1, w2, alpha, m (seed eq. 15, 27).
        current_var: variance of the current measurement (A^2); propagated into P through
            ``Gamma B`` each step (the seed takes the current as exact: 0).
        p0_diag: initial variances (seed section 5.2).
        alpha0: contact quality at Dn = 0, and the initial estimate of alpha.
        m0: initial estimate of m (middle of the seed's interval (0, 0.02)).
        w1_0, w2_0: initial speed estimates; None takes the first measurement.
        f44: ``F44`` of the Jacobian (0: eq. 19; the seed's variant: -100), covariance only.
        nonnegative: clip alpha-hat at 0 and predict with the wear rate max(m-hat, 0).
        bound_sigma: c of the bounds ``c sqrt(P_ii)`` and ``c sqrt(S_jj)`` (eqs. 24, 26).
        expm_tol: remainder bound of the Taylor series of the discretization.
        sample_period_s: nominal sample period (s). A spacing of the sample times within
            0.1 % of it is taken as exactly it, so that the rounding of absolute time stamps
            (about 2e-7 s for POSIX seconds, 0.02 % of a 1 ms period) does not enter the
            discretization as noise. None: the actual spacing of each pair of samples.
        health_window_samples: health window length, stream samples.
        consistency_sigma: z of the innovation tests (NIS mean two-sided, bias, whiteness).
        dn_watch, dn_alert: Dn levels of the status (and of ``dn_threshold_crossed``).
        dn_hysteresis: Dn must fall this far below a level to leave it.
        rul_every_s: prognosis period in stream seconds, "every_batch", or None (no RUL).
        rul_failure_dn: Dn at which the drive is declared failed.
        rul_load: future-load assumption.
        rul_trajectories: Monte Carlo trajectories per prognosis.
        rul_horizon_s: longest RUL looked for.
        rul_seed: base seed of the Monte Carlo draws.
        rul_watch_s, rul_alert_s: RUL levels (on the 5 % quantile) of the status.
        rul_segment_tol: largest change of ln(alpha) per propagation step.
        rul_jump_tol: change of ln(alpha) per cycle jump.
    """

    plant: FrictionDriveParams = field(default_factory=FrictionDriveParams)
    r_diag: tuple[float, float] = (1.0063e-8, 1.0083e-10)
    q_diag: tuple[float, float, float, float] = (0.0, 0.0, 0.0, SIGMA_M2)
    current_var: float = 0.0
    p0_diag: tuple[float, float, float, float] = (SIGMA_M2, SIGMA_M2, SIGMA_M2, SIGMA_M2)
    alpha0: float = 10.0
    m0: float = 0.01
    w1_0: float | None = None
    w2_0: float | None = None
    f44: float = 0.0
    nonnegative: bool = True
    bound_sigma: float = 3.0
    expm_tol: float = 1e-9
    sample_period_s: float | None = None
    health_window_samples: int = 10_000
    consistency_sigma: float = 3.0
    dn_watch: float = 0.5
    dn_alert: float = 0.7
    dn_hysteresis: float = 0.01
    rul_every_s: float | Literal["every_batch"] | None = 10.0
    rul_failure_dn: float = 0.9
    rul_load: rulmod.LoadAssumption = field(default_factory=rulmod.SquareWaveLoad)
    rul_trajectories: int = 1000
    rul_horizon_s: float = 1.0e7
    rul_seed: int = 0
    rul_watch_s: float = 86_400.0
    rul_alert_s: float = 3_600.0
    rul_segment_tol: float = 0.01
    rul_jump_tol: float = 0.25
    # derived, built once (not part of the configuration's identity)
    kernel_vector: FloatArray = field(init=False, repr=False, compare=False, hash=False)
    plant_vector: FloatArray = field(init=False, repr=False, compare=False, hash=False)

    def __post_init__(self) -> None:
        plant = self.plant.as_array()
        plant.setflags(write=False)
        object.__setattr__(self, "plant_vector", plant)
        object.__setattr__(self, "kernel_vector", _kernel_config(self))

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


def _kernel_config(config: DekfConfig) -> FloatArray:
    """The flat configuration vector of the compiled kernel."""
    cfg = np.zeros(kern.CFG_LEN, dtype=np.float64)
    cfg[kern.CFG_R1 : kern.CFG_R1 + 7] = config.plant_vector
    cfg[kern.CFG_RV : kern.CFG_RV + 2] = config.r_diag
    cfg[kern.CFG_Q : kern.CFG_Q + 4] = config.q_diag
    cfg[kern.CFG_P0 : kern.CFG_P0 + 4] = config.p0_diag
    cfg[kern.CFG_W0] = np.nan if config.w1_0 is None else config.w1_0
    cfg[kern.CFG_W0 + 1] = np.nan if config.w2_0 is None else config.w2_0
    cfg[kern.CFG_ALPHA0] = config.alpha0
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
    cfg.setflags(write=False)
    return cfg










def _fraction(name: str, value: Any) -> float:
    v = _finite(name, value)
    if not 0.0 < v < 1.0:
        raise ConfigError(f"{name}: expected a number in (0, 1), got {value!r}")
    return v


def _vector(name: str, value: Any, length: int, *, positive: bool) -> tuple[float, ...]:
    if not isinstance(value, list | tuple) or len(value) != length:
        raise ConfigError(f"{name}: expected a list of {length} numbers, got {value!r}")
    check = _positive if positive else _non_negative
    return tuple(check(f"{name}[{i}]", v) for i, v in enumerate(value))


def _integer(name: str, value: Any, lo: int, hi: int) -> int:
    if not isinstance(value, int) or isinstance(value, bool) or not lo <= value <= hi:
        raise ConfigError(f"{name}: expected an integer in [{lo}, {hi}], got {value!r}")
    return value


def _plant(raw: Any) -> FrictionDriveParams:
    if not isinstance(raw, Mapping):
        raise ConfigError("plant: expected an object")
    defaults = asdict(FrictionDriveParams())
    unknown = sorted(set(raw) - set(defaults))
    if unknown:
        raise ConfigError(f"plant.{unknown[0]}: unknown field (known: {', '.join(defaults)})")
    return FrictionDriveParams(
        **{k: _positive(f"plant.{k}", raw.get(k, v)) for k, v in defaults.items()}
    )


def _rul_every(value: Any) -> float | Literal["every_batch"] | None:
    if value is None or value == "every_batch":
        return value  # type: ignore[no-any-return]
    return _positive("rul_every_s", value)


def _boolean(name: str, value: Any) -> bool:
    if not isinstance(value, bool):
        raise ConfigError(f"{name}: expected true or false, got {value!r}")
    return value


def _optional_positive(name: str, value: Any) -> float | None:
    return None if value is None else _positive(name, value)


def _optional_speed(name: str, value: Any) -> float | None:
    return None if value is None else _finite(name, value)


def parse_config(raw: Mapping[str, Any]) -> DekfConfig:
    """Validate a JSON-like mapping into a :class:`DekfConfig`.

    Raises:
        ConfigError: unknown keys, wrong types or lengths, non-positive plant parameters or
            variances (R and P0 must be positive, Q non-negative), levels out of order
            (``dn_watch <= dn_alert < rul_failure_dn``, ``rul_alert_s <= rul_watch_s``),
            window or trajectory counts out of range, an invalid load assumption.
    """
    if not isinstance(raw, Mapping):
        raise ConfigError(f"config: expected an object, got {type(raw).__name__}")
    known = {f.name for f in fields(DekfConfig) if f.init}
    unknown = sorted(set(raw) - known)
    if unknown:
        raise ConfigError(f"{unknown[0]}: unknown field (known: {', '.join(sorted(known))})")
    d = DekfConfig()
    get = raw.get
    config = DekfConfig(
        plant=_plant(get("plant", {})),
        r_diag=_vector("r_diag", get("r_diag", d.r_diag), 2, positive=True),  # type: ignore[arg-type]
        q_diag=_vector("q_diag", get("q_diag", d.q_diag), 4, positive=False),  # type: ignore[arg-type]
        current_var=_non_negative("current_var", get("current_var", d.current_var)),
        p0_diag=_vector("p0_diag", get("p0_diag", d.p0_diag), 4, positive=True),  # type: ignore[arg-type]
        alpha0=_positive("alpha0", get("alpha0", d.alpha0)),
        m0=_finite("m0", get("m0", d.m0)),
        w1_0=_optional_speed("w1_0", get("w1_0", d.w1_0)),
        w2_0=_optional_speed("w2_0", get("w2_0", d.w2_0)),
        f44=_finite("f44", get("f44", d.f44)),
        nonnegative=_boolean("nonnegative", get("nonnegative", d.nonnegative)),
        bound_sigma=_positive("bound_sigma", get("bound_sigma", d.bound_sigma)),
        expm_tol=_fraction("expm_tol", get("expm_tol", d.expm_tol)),
        sample_period_s=_optional_positive("sample_period_s", get("sample_period_s", d.sample_period_s)),
        health_window_samples=_integer(
            "health_window_samples",
            get("health_window_samples", d.health_window_samples),
            MIN_WINDOW,
            100_000_000,
        ),
        consistency_sigma=_positive(
            "consistency_sigma", get("consistency_sigma", d.consistency_sigma)
        ),
        dn_watch=_fraction("dn_watch", get("dn_watch", d.dn_watch)),
        dn_alert=_fraction("dn_alert", get("dn_alert", d.dn_alert)),
        dn_hysteresis=_non_negative("dn_hysteresis", get("dn_hysteresis", d.dn_hysteresis)),
        rul_every_s=_rul_every(get("rul_every_s", d.rul_every_s)),
        rul_failure_dn=_fraction("rul_failure_dn", get("rul_failure_dn", d.rul_failure_dn)),
        rul_load=rulmod.parse_load(get("rul_load", rulmod.load_to_dict(d.rul_load))),
        rul_trajectories=_integer(
            "rul_trajectories", get("rul_trajectories", d.rul_trajectories), 10, 1_000_000
        ),
        rul_horizon_s=_positive("rul_horizon_s", get("rul_horizon_s", d.rul_horizon_s)),
        rul_seed=_integer("rul_seed", get("rul_seed", d.rul_seed), 0, 2**63 - 1),
        rul_watch_s=_non_negative("rul_watch_s", get("rul_watch_s", d.rul_watch_s)),
        rul_alert_s=_non_negative("rul_alert_s", get("rul_alert_s", d.rul_alert_s)),
        rul_segment_tol=_fraction("rul_segment_tol", get("rul_segment_tol", d.rul_segment_tol)),
        rul_jump_tol=_fraction("rul_jump_tol", get("rul_jump_tol", d.rul_jump_tol)),
    )
    if config.dn_alert < config.dn_watch:
        raise ConfigError("dn_alert: must not be below dn_watch")
    if config.rul_failure_dn <= config.dn_alert:
        raise ConfigError("rul_failure_dn: must be above dn_alert")
    if config.rul_alert_s > config.rul_watch_s:
        raise ConfigError("rul_alert_s: must not be above rul_watch_s")
    return config


def config_to_dict(config: DekfConfig) -> dict[str, Any]:
    """The full configuration with defaults filled in, JSON-serializable."""
    out: dict[str, Any] = {}
    for f in fields(DekfConfig):
        if not f.init:
            continue
        value = getattr(config, f.name)
        if f.name == "plant":
            value = asdict(value)
        elif f.name == "rul_load":
            value = rulmod.load_to_dict(value)
        elif isinstance(value, tuple):
            value = list(value)
        out[f.name] = value
    return out


def required_channels(config: DekfConfig) -> tuple[str, ...]:
    """Motor current (A), motor speed w1 and wheel speed w2 (rad/s)."""
    return CHANNELS


# ----------------------------------------------------------------------------- state
@dataclass(frozen=True)
class DekfState:
    """Everything the filter carries between batches.

    Attributes:
        version: schema version (``STATE_VERSION``).
        t_last_s: time of the last sample seen (-inf before any).
        vector: flat float64 vector laid out as the ``ST_*`` constants of
            ``estimators.kernels.dekf_kernels`` (length ``ST_BASE_LEN + 2 bins``). Never
            modified in place: ``step`` works on a copy.
    """

    version: int
    t_last_s: float
    vector: FloatArray

    @property
    def x(self) -> FloatArray:
        """Posterior ``[w1, w2, alpha, m]``."""
        return self.vector[kern.ST_X : kern.ST_X + 4].copy()

    @property
    def P(self) -> FloatArray:  # noqa: N802 - the usual name of the covariance
        """Posterior covariance, shape (4, 4), symmetric by construction."""
        return _unpack_cov(self.vector[kern.ST_P : kern.ST_P + 10])

    @property
    def n_samples(self) -> int:
        """Samples seen since the stream start."""
        return int(self.vector[kern.ST_N_SEEN])


_TRIU = np.triu_indices(4)


def _unpack_cov(upper: FloatArray) -> FloatArray:
    cov = np.zeros((4, 4), dtype=np.float64)
    cov[_TRIU] = upper
    return cov + np.triu(cov, 1).T


def initial_state(config: DekfConfig) -> DekfState:
    """State before the first sample (the prior is set by the first sample)."""
    vec = np.zeros(kern.ST_BASE_LEN + 2 * config.observed_bins, dtype=np.float64)
    vec[kern.ST_T_LAST] = -math.inf
    vec[kern.ST_T_NEXT_RUL] = np.nan
    vec[kern.ST_NU_PREV : kern.ST_NU_PREV + 2] = np.nan
    vec[kern.ST_LAST_CONSISTENT] = np.nan
    vec[kern.ST_RUL_Q05] = np.nan
    vec.setflags(write=False)
    return DekfState(version=STATE_VERSION, t_last_s=-math.inf, vector=vec)


def dump_state(state: DekfState) -> bytes:
    """Versioned byte form of the state (exact round trip; see :func:`dump_vector_state`)."""
    return dump_vector_state(NAME, state.version, state.t_last_s, state.vector)


def load_state(data: bytes) -> DekfState:
    """Inverse of :func:`dump_state`.

    Raises:
        StateVersionError: the version is not ``STATE_VERSION``.
        EstimatorError: the bytes are not a state of this estimator.
    """
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
    row: FloatArray, ch: int, z: float
) -> tuple[float | None, float | None, float | None, list[str]]:
    """(bias z-score, lag-1 autocorrelation, its z-score, failures) of one channel's normalized
    innovations nu over the window: bias ``sum(nu) / sqrt(n)``, whiteness
    ``rho = sum(nu_k nu_{k-1}) / sum(nu^2)`` and ``rho sqrt(pairs)``; each ~N(0, 1) when the
    filter is consistent."""
    base = kern.WIN_CH + ch * kern.CH_LEN
    n = row[base + kern.CH_N]
    pairs = row[base + kern.CH_N_LAG]
    sum2 = row[base + kern.CH_SUM2]
    fails: list[str] = []
    name = STATE_NAMES[ch]
    if n < 2.0 or sum2 <= 0.0:
        return None, None, None, fails
    bias_z = float(row[base + kern.CH_SUM] / math.sqrt(n))
    if abs(bias_z) > z:
        fails.append(f"innovation of {name} biased (z {bias_z:.2f})")
    rho = float(row[base + kern.CH_LAG] / sum2)
    rho_z = float(rho * math.sqrt(pairs)) if pairs > 0.0 else None
    if rho_z is not None and abs(rho_z) > z:
        fails.append(f"innovation of {name} not white (lag-1 autocorrelation {rho:.3f})")
    return bias_z, rho, rho_z, fails


def _health(row: FloatArray, config: DekfConfig) -> tuple[HealthWindow, bool | None]:
    """The health window of one kernel row, and its consistency verdict (None: no update)."""
    z = config.consistency_sigma
    n = row[kern.WIN_N]
    n_upd = row[kern.WIN_N_UPD]
    x = row[kern.WIN_X : kern.WIN_X + 4]
    sig = row[kern.WIN_SIGMA : kern.WIN_SIGMA + 4]
    c = config.bound_sigma
    dn = 1.0 - x[2] / config.alpha0
    duration = row[kern.WIN_T1] - row[kern.WIN_T0]
    ind: dict[str, float | None] = {
        "dn": _none_if_nan(dn),
        "dn_lower": _none_if_nan(1.0 - (x[2] + c * sig[2]) / config.alpha0),
        "dn_upper": _none_if_nan(1.0 - (x[2] - c * sig[2]) / config.alpha0),
        "dn_rate_per_s": _none_if_nan((dn - row[kern.WIN_DN0]) / duration)
        if duration > 0.0
        else None,
        "alpha": _none_if_nan(x[2]),
        "alpha_3sigma": _none_if_nan(c * sig[2]),
        "m": _none_if_nan(x[3]),
        "m_3sigma": _none_if_nan(c * sig[3]),
        "valid_fraction": float(n_upd / n),
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
        if not lo <= nis_mean <= hi:
            fails.append(f"NIS mean {nis_mean:.3g} outside [{lo:.3g}, {hi:.3g}]")
        for ch, label in ((0, "w1"), (1, "w2")):
            bias_z, rho, rho_z, ch_fails = _channel_tests(row, ch, z)
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
    statuses = [_grade_dn(ind["dn"], config, reasons, "Dn")]
    if consistent is False:
        statuses.append("watch")
        reasons.append("innovations inconsistent: " + "; ".join(fails))
    window = HealthWindow(
        t_start_s=float(row[kern.WIN_T0]),
        t_end_s=float(row[kern.WIN_T1]),
        n_samples=int(n),
        indicators=ind,
        status=worst_status(statuses),
        reasons=tuple(reasons),
    )
    return window, consistent


# ----------------------------------------------------------------------------- RUL
def _rul_status(
    result: rulmod.PrognosisResult, dn: float, config: DekfConfig
) -> tuple[Status, tuple[str, ...]]:
    reasons: list[str] = []
    statuses = [_grade_dn(dn if math.isfinite(dn) else None, config, reasons, "Dn")]
    q05 = result.q05_s
    if q05 is not None and q05 <= config.rul_alert_s:
        statuses.append("alert")
        reasons.append(f"RUL 5 % quantile {q05:.4g} s <= rul_alert_s {config.rul_alert_s:g}")
    elif q05 is not None and q05 <= config.rul_watch_s:
        statuses.append("watch")
        reasons.append(f"RUL 5 % quantile {q05:.4g} s <= rul_watch_s {config.rul_watch_s:g}")
    return worst_status(statuses), tuple(reasons)


def _observed_profile(row: FloatArray, bins: int) -> tuple[FloatArray, FloatArray] | None:
    """(durations, currents) of the filled bins of a snapshot row, oldest first."""
    if bins == 0:
        return None
    filled = int(row[kern.RS_FILLED])
    currents = row[kern.RS_RING + bins - filled : kern.RS_RING + bins]
    durations = row[kern.RS_RING + 2 * bins - filled : kern.RS_RING + 2 * bins]
    return durations.copy(), currents.copy()


def prognosis_at(config: DekfConfig, row: FloatArray) -> RulEstimate | None:
    """The RUL estimate of one snapshot row (``RS_*`` layout); None when the observed load is
    not available yet (fewer than ``bins`` bins recorded)."""
    t_s = float(row[kern.RS_T])
    x = row[kern.RS_X : kern.RS_X + 4].copy()
    cov = _unpack_cov(row[kern.RS_P : kern.RS_P + 10])
    segments = rulmod.load_segments(
        config.rul_load, t_s, _observed_profile(row, config.observed_bins)
    )
    if segments is None:
        return None
    settings = config.prognosis
    result = rulmod.prognose(config.plant_vector, config.alpha0, x, cov, t_s, segments, settings)
    c = config.bound_sigma
    s_alpha = math.sqrt(max(float(cov[2, 2]), 0.0))
    dn = 1.0 - x[2] / config.alpha0
    status, reasons = _rul_status(result, dn, config)
    assumption: dict[str, Any] = {
        "load": rulmod.load_to_dict(config.rul_load),
        "load_segments": {
            "durations_s": [float(v) for v in segments[0]],
            "current_a": [float(v) for v in segments[1]],
        },
        "m_constant": True,
        "failure_dn": config.rul_failure_dn,
        "alpha_failure": result.alpha_failure,
        "n_trajectories": settings.n_trajectories,
        "horizon_s": settings.horizon_s,
        "seed": settings.seed,
        "seed_entropy": list(result.entropy),
        "reached_fraction": result.reached_fraction,
        "bounds_sigma": c,
    }
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
            "dn_lower": _none_if_nan(1.0 - (x[2] + c * s_alpha) / config.alpha0),
            "dn_upper": _none_if_nan(1.0 - (x[2] - c * s_alpha) / config.alpha0),
            "alpha": _none_if_nan(x[2]),
            "m": _none_if_nan(x[3]),
        },
        assumption=assumption,
        status=status,
        reasons=reasons,
    )


def _end_snapshot(vec: FloatArray, t_s: float, bins: int) -> FloatArray:
    """A snapshot row (``RS_*``) of the state at the end of a batch ("every_batch")."""
    row = np.empty(kern.RS_BASE_LEN + 2 * bins, dtype=np.float64)
    row[kern.RS_T] = t_s
    row[kern.RS_X : kern.RS_X + 4] = vec[kern.ST_X : kern.ST_X + 4]
    row[kern.RS_P : kern.RS_P + 10] = vec[kern.ST_P : kern.ST_P + 10]
    row[kern.RS_FILLED] = vec[kern.ST_OB_FILLED]
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


def _consistency_events(
    windows: Sequence[tuple[HealthWindow, bool | None]], vec: FloatArray
) -> list[EstimatorEvent]:
    """Events at the windows where the consistency verdict changes; updates ``vec``."""
    events = []
    for window, consistent in windows:
        if consistent is None:
            continue
        last = vec[kern.ST_LAST_CONSISTENT]
        if math.isfinite(last) and bool(last) == consistent:
            continue
        if math.isfinite(last) or not consistent:
            kind = "innovations_consistent" if consistent else "innovations_inconsistent"
            events.append(
                EstimatorEvent(
                    t_s=window.t_end_s,
                    kind=kind,
                    detail={
                        "window_start_s": window.t_start_s,
                        "nis_mean": window.indicators["nis_mean"],
                        "reasons": list(window.reasons),
                    },
                )
            )
        vec[kern.ST_LAST_CONSISTENT] = 1.0 if consistent else 0.0
    return events


def _rul_events(estimates: Sequence[RulEstimate], vec: FloatArray) -> list[EstimatorEvent]:
    """``rul_threshold_crossed`` where the status of successive prognoses changes."""
    events = []
    for est in estimates:
        level = LEVELS.index(est.status)
        old = int(vec[kern.ST_RUL_LEVEL])
        if level != old:
            events.append(
                EstimatorEvent(
                    t_s=est.t_s,
                    kind="rul_threshold_crossed",
                    detail={
                        "from": LEVELS[old],
                        "to": est.status,
                        "q05_s": est.q05_s,
                        "q50_s": est.q50_s,
                        "q95_s": est.q95_s,
                        "reasons": list(est.reasons),
                    },
                )
            )
        vec[kern.ST_RUL_LEVEL] = level
        vec[kern.ST_RUL_Q05] = np.nan if est.q05_s is None else est.q05_s
    return events


def _status(vec: FloatArray, config: DekfConfig) -> StatusReport:
    """Worst of the Dn level, the latest RUL status and the latest innovation consistency."""
    statuses: list[Status] = []
    reasons: list[str] = []
    dn_level = int(vec[kern.ST_DN_LEVEL])
    dn = 1.0 - vec[kern.ST_X + 2] / config.alpha0
    statuses.append(LEVELS[dn_level])
    if dn_level:
        level = config.dn_alert if dn_level == 2 else config.dn_watch
        reasons.append(f"Dn {dn:.3f} at level {LEVELS[dn_level]} ({level:g})")
    rul_level = int(vec[kern.ST_RUL_LEVEL])
    statuses.append(LEVELS[rul_level])
    if rul_level:
        q05 = vec[kern.ST_RUL_Q05]
        reasons.append(
            f"latest prognosis {LEVELS[rul_level]}"
            + (f" (RUL 5 % quantile {q05:.4g} s)" if math.isfinite(q05) else "")
        )
    if vec[kern.ST_LAST_CONSISTENT] == 0.0:
        statuses.append("watch")
        reasons.append("innovations inconsistent in the latest health window")
    return StatusReport(status=worst_status(statuses), reasons=tuple(reasons))


def _diagnosis(vec: FloatArray, t_s: float, config: DekfConfig) -> Diagnosis:
    x = vec[kern.ST_X : kern.ST_X + 4]
    sig = np.sqrt(np.clip(np.diag(_unpack_cov(vec[kern.ST_P : kern.ST_P + 10])), 0.0, None))
    c = config.bound_sigma
    detail: dict[str, Any] = {}
    for i, name in enumerate(STATE_NAMES):
        detail[name] = _none_if_nan(x[i])
        detail[f"{name}_3sigma"] = _none_if_nan(c * sig[i])
    detail["dn"] = _none_if_nan(1.0 - x[2] / config.alpha0)
    detail["dn_lower"] = _none_if_nan(1.0 - (x[2] + c * sig[2]) / config.alpha0)
    detail["dn_upper"] = _none_if_nan(1.0 - (x[2] - c * sig[2]) / config.alpha0)
    detail["dn_level"] = LEVELS[int(vec[kern.ST_DN_LEVEL])]
    last = vec[kern.ST_LAST_CONSISTENT]
    detail["innovations_consistent"] = None if not math.isfinite(last) else bool(last)
    detail["rul_level"] = LEVELS[int(vec[kern.ST_RUL_LEVEL])]
    detail["rul_q05_s"] = _none_if_nan(vec[kern.ST_RUL_Q05])
    return Diagnosis(t_s=t_s, detail=detail)


def step(config: DekfConfig, state: DekfState, batch: Batch) -> tuple[DekfState, StepOutputs]:
    """Advance the filter over a whole batch (the per-sample loop runs compiled).

    Per-sample outputs (float64, aligned with ``batch.t_s``): the posterior ``w1``, ``w2``,
    ``alpha``, ``m`` and their half-widths ``c sqrt(P_ii)`` (``*_3sigma``, eq. 24), ``dn`` and
    its bounds ``dn_lower``/``dn_upper`` (from alpha +- c sigma), the innovations
    ``innovation_w1``/``innovation_w2`` (NaN where the speed is missing) with their bounds
    ``c sqrt(S_jj)`` (eq. 26), and ``nis`` (``e^T S^-1 e`` over the measured channels).

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
    out, win_rows, ev_rows, snap_rows, status = kern.ekf_batch(
        config.kernel_vector, vec, t, cur, w1, w2
    )
    if status != 0:
        raise OutOfOrderError("batch times are not strictly increasing")
    samples = {name: out[i] for i, name in enumerate(SAMPLE_OUTPUTS)}
    windows = [_health(row, config) for row in win_rows]
    events = [_dn_event(row, config) for row in ev_rows]
    events.extend(_consistency_events(windows, vec))
    if config.rul_every_s == "every_batch":
        snap_rows = _end_snapshot(vec, float(t[n - 1]), config.observed_bins)[None, :]
    estimates = [est for row in snap_rows if (est := prognosis_at(config, row)) is not None]
    events.extend(_rul_events(estimates, vec))
    events.sort(key=lambda e: e.t_s)
    vec.setflags(write=False)
    new_state = DekfState(version=STATE_VERSION, t_last_s=float(t[n - 1]), vector=vec)
    outputs = StepOutputs(
        samples=samples,
        health=[w for w, _ in windows],
        events=events,
        rul=estimates,
        diagnosis=_diagnosis(vec, float(t[n - 1]), config),
        status=_status(vec, config),
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
    config = parse_config(
        {
            "health_window_samples": 100,
            "rul_every_s": 0.1,
            "rul_trajectories": 10,
            "rul_horizon_s": 10.0,
            "f44": -100.0,
        }
    )
    step(config, initial_state(config), Batch(t_s=t, channels=channels))
