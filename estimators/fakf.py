"""Feature-aided Kalman filter (FAKF) for EMA motor voltage, with health indicators.

The measured motor voltage of an electro-mechanical actuator carries electromagnetic
interference, and no state equation of voltage over time is known. The FAKF (seed paper,
"Feature-aided Kalman filter for EMA motor voltage estimation", Sensors) uses a second measured
feature, the motor current, and the second-order current-to-voltage model of the DC motor as the
Kalman transition:

    V(z) / I(z) = (b0 + b1 z^-1 + b2 z^-2) / (1 + a0 z^-1 + a1 z^-2)                   (eq. 15)

identified by least squares on the first samples of the stream; the model driven by measured
current gives the prior and the measured voltage updates it (eqs. 7-11, 16). State space used
here (the seed does not write one out):

    x_k = [V_k, V_{k-1}],  F = [[-a0, -a1], [1, 0]],  x-_k = F x_{k-1} + [u_k, 0],
    u_k = b0 I_k + b1 I_{k-1} + b2 I_{k-2},  Q = diag(q, 0),  H = [1, 0],  R = r.

Choices where the seed is silent (see docs/methods.md, "FAKF"):

* identification window: the first ``identification_samples`` stream samples (default 1000);
  a fit is refused when the regressors are nearly collinear (condition number of the
  unit-diagonal Gram matrix above ``condition_limit``), when the current hardly varies
  (std below ``min_current_std``), with fewer than 10 usable rows, or when the fitted model is
  unstable (a pole of ``1 + a0 z^-1 + a1 z^-2`` on or outside the unit circle). A refusal is an
  ``identification_failed`` event, health windows report "alert" until a model is found, and
  identification is retried on the next window of the same size (no outputs meanwhile);
* ``q = r = "auto"``: half the variance of the identification's one-step residual each, so that
  the steady innovation variance S is close to the residual variance and NIS is near 1 on data
  like those of the identification window;
* a NaN voltage: predict only (estimate = prior, P grows, innovation NaN);
  a NaN current: the last valid current is held (0 before any);
* health indicators over fixed windows of ``health_window_samples`` stream samples, with the
  model re-identified on each window from the same Gram accumulation (``coef_drift``).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field, fields
from typing import Any, Literal, NamedTuple

import numpy as np

from estimators.base import (
    Batch,
    ConfigError,
    EstimatorError,
    EstimatorEvent,
    FloatArray,
    HealthWindow,
    OutOfOrderError,
    Status,
    StepOutputs,
    dump_vector_state,
    load_vector_state,
    worst_status,
)
from estimators.checks import finite_or_none as _finite_or_none
from estimators.checks import is_number as _is_number
from estimators.kernels import fakf_kernels as kern

NAME = "fakf"
STATE_VERSION = 1

SAMPLE_OUTPUTS = ("voltage_estimate", "voltage_model", "innovation", "innovation_var")
COEFFICIENT_NAMES = ("a0", "a1", "b0", "b1", "b2")
MIN_ROWS = 10
_REASON_NAMES = {
    kern.FIT_TOO_FEW_ROWS: "too_few_rows",
    kern.FIT_LOW_CURRENT_STD: "low_current_excitation",
    kern.FIT_ILL_CONDITIONED: "ill_conditioned",
    kern.FIT_UNSTABLE: "unstable_model",
}


# ----------------------------------------------------------------------------- configuration
@dataclass(frozen=True)
class ArxCoefficients:
    """Coefficients of the eq. 15 model ``V[k] = -a0 V[k-1] - a1 V[k-2] + b0 I[k] + b1 I[k-1]
    + b2 I[k-2]``."""

    a0: float
    a1: float
    b0: float
    b1: float
    b2: float

    def as_array(self) -> FloatArray:
        """``[a0, a1, b0, b1, b2]``, shape (5,)."""
        return np.array([self.a0, self.a1, self.b0, self.b1, self.b2], dtype=np.float64)


@dataclass(frozen=True)
class FakfThresholds:
    """Status thresholds applied to each health window (a value above "watch" gives "watch",
    above "alert" gives "alert").

    Attributes:
        nis_mean_watch: mean normalized innovation squared (expected 1 on healthy data).
        nis_mean_alert: same, alert level.
        innovation_ratio_watch: innovation RMS over the identification residual RMS.
        innovation_ratio_alert: same, alert level.
        coef_drift_watch: relative RMS difference of the window model's and the baseline
            model's one-step predictions on the window's data.
        coef_drift_alert: same, alert level.
    """

    nis_mean_watch: float = 2.0
    nis_mean_alert: float = 4.0
    innovation_ratio_watch: float = 1.5
    innovation_ratio_alert: float = 2.0
    coef_drift_watch: float = 0.3
    coef_drift_alert: float = 0.6


@dataclass(frozen=True)
class FakfConfig:
    """Validated FAKF configuration (build it with :func:`parse_config`).

    Attributes:
        current_channel: channel holding the motor current (A).
        voltage_channel: channel holding the measured motor voltage (V).
        identification_samples: length of the identification window, stream samples.
        coefficients: fixed model coefficients; when given, no identification is run.
        q: process noise variance of V (V^2), or "auto" (half the identification residual
            variance).
        r: measurement noise variance (V^2), or "auto" (half the identification residual
            variance).
        p0: initial variance of both state components (V^2).
        health_window_samples: length of a health window, stream samples.
        condition_limit: largest accepted condition number of the unit-diagonal Gram matrix.
        min_current_std: smallest accepted current standard deviation in a fit window (A).
        thresholds: status thresholds.
    """

    current_channel: str = "current"
    voltage_channel: str = "voltage"
    identification_samples: int = 1000
    coefficients: ArxCoefficients | None = None
    q: float | Literal["auto"] = "auto"
    r: float | Literal["auto"] = "auto"
    p0: float = 100.0
    health_window_samples: int = 1000
    condition_limit: float = 1.0e6
    min_current_std: float = 0.05
    thresholds: FakfThresholds = field(default_factory=FakfThresholds)
    # the flat vector the kernel reads, built once (not part of the configuration's identity)
    kernel_vector: FloatArray = field(init=False, repr=False, compare=False, hash=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "kernel_vector", _kernel_config(self))




def _positive_float(name: str, value: Any) -> float:
    if not _is_number(value) or not math.isfinite(float(value)) or float(value) <= 0.0:
        raise ConfigError(f"{name}: expected a positive finite number, got {value!r}")
    return float(value)


def _window_int(name: str, value: Any) -> int:
    if not isinstance(value, int) or isinstance(value, bool):
        raise ConfigError(f"{name}: expected an integer, got {value!r}")
    if value < MIN_ROWS or value > 100_000_000:
        raise ConfigError(f"{name}: expected an integer in [{MIN_ROWS}, 1e8], got {value}")
    return value


def _noise(name: str, value: Any) -> float | Literal["auto"]:
    if value == "auto":
        return "auto"
    return _positive_float(name, value)


def _channel(name: str, value: Any) -> str:
    if not isinstance(value, str) or not value:
        raise ConfigError(f"{name}: expected a non-empty string, got {value!r}")
    return value


def parse_config(raw: Mapping[str, Any]) -> FakfConfig:
    """Validate a JSON-like mapping into a :class:`FakfConfig`.

    Raises:
        ConfigError: unknown keys, wrong types, non-positive q/r/p0, window sizes out of range,
            coefficients that are not exactly {a0, a1, b0, b1, b2}, thresholds not increasing,
            or ``r``/``q`` "auto" together with fixed coefficients (no residuals to use).
    """
    if not isinstance(raw, Mapping):
        raise ConfigError(f"config: expected an object, got {type(raw).__name__}")
    known = {f.name for f in fields(FakfConfig) if f.init}
    unknown = sorted(set(raw) - known)
    if unknown:
        raise ConfigError(f"{unknown[0]}: unknown field (known: {', '.join(sorted(known))})")
    d = FakfConfig()
    coefficients: ArxCoefficients | None = None
    raw_coef = raw.get("coefficients")
    if raw_coef is not None:
        if not isinstance(raw_coef, Mapping):
            raise ConfigError("coefficients: expected an object {a0, a1, b0, b1, b2}")
        if set(raw_coef) != set(COEFFICIENT_NAMES):
            raise ConfigError(
                f"coefficients: expected exactly the keys {', '.join(COEFFICIENT_NAMES)}, "
                f"got {', '.join(sorted(map(str, raw_coef)))}"
            )
        values = {}
        for key in COEFFICIENT_NAMES:
            v = raw_coef[key]
            if not _is_number(v) or not math.isfinite(float(v)):
                raise ConfigError(f"coefficients.{key}: expected a finite number, got {v!r}")
            values[key] = float(v)
        coefficients = ArxCoefficients(**values)
        if kern.max_pole_modulus(coefficients.a0, coefficients.a1) >= 1.0:
            raise ConfigError("coefficients: the model 1 + a0 z^-1 + a1 z^-2 is not stable")
    q = _noise("q", raw.get("q", d.q))
    r = _noise("r", raw.get("r", d.r))
    if coefficients is not None and (q == "auto" or r == "auto"):
        raise ConfigError('q: "auto" needs identification; give q and r with fixed coefficients')
    raw_thr = raw.get("thresholds", {})
    if not isinstance(raw_thr, Mapping):
        raise ConfigError("thresholds: expected an object")
    thr_known = {f.name for f in fields(FakfThresholds)}
    thr_unknown = sorted(set(raw_thr) - thr_known)
    if thr_unknown:
        raise ConfigError(f"thresholds.{thr_unknown[0]}: unknown field")
    thr_default = FakfThresholds()
    thr_values = {
        name: _positive_float(f"thresholds.{name}", raw_thr.get(name, getattr(thr_default, name)))
        for name in sorted(thr_known)
    }
    thresholds = FakfThresholds(**thr_values)
    for base in ("nis_mean", "innovation_ratio", "coef_drift"):
        if getattr(thresholds, f"{base}_alert") < getattr(thresholds, f"{base}_watch"):
            raise ConfigError(f"thresholds.{base}_alert: must not be below {base}_watch")
    return FakfConfig(
        current_channel=_channel("current_channel", raw.get("current_channel", d.current_channel)),
        voltage_channel=_channel("voltage_channel", raw.get("voltage_channel", d.voltage_channel)),
        identification_samples=_window_int(
            "identification_samples", raw.get("identification_samples", d.identification_samples)
        ),
        coefficients=coefficients,
        q=q,
        r=r,
        p0=_positive_float("p0", raw.get("p0", d.p0)),
        health_window_samples=_window_int(
            "health_window_samples", raw.get("health_window_samples", d.health_window_samples)
        ),
        condition_limit=_positive_float(
            "condition_limit", raw.get("condition_limit", d.condition_limit)
        ),
        min_current_std=_positive_float(
            "min_current_std", raw.get("min_current_std", d.min_current_std)
        ),
        thresholds=thresholds,
    )


def config_to_dict(config: FakfConfig) -> dict[str, Any]:
    """The full configuration with defaults filled in, JSON-serializable."""
    coef = config.coefficients
    return {
        "current_channel": config.current_channel,
        "voltage_channel": config.voltage_channel,
        "identification_samples": config.identification_samples,
        "coefficients": None
        if coef is None
        else {name: getattr(coef, name) for name in COEFFICIENT_NAMES},
        "q": config.q,
        "r": config.r,
        "p0": config.p0,
        "health_window_samples": config.health_window_samples,
        "condition_limit": config.condition_limit,
        "min_current_std": config.min_current_std,
        "thresholds": {f.name: getattr(config.thresholds, f.name) for f in fields(FakfThresholds)},
    }


def required_channels(config: FakfConfig) -> tuple[str, ...]:
    """The current and voltage channels."""
    return (config.current_channel, config.voltage_channel)


def _kernel_config(config: FakfConfig) -> FloatArray:
    """The flat configuration vector of the compiled kernel."""
    cfg = np.zeros(kern.CFG_LEN, dtype=np.float64)
    cfg[kern.CFG_N_IDENT] = config.identification_samples
    cfg[kern.CFG_HEALTH_WINDOW] = config.health_window_samples
    cfg[kern.CFG_Q] = np.nan if config.q == "auto" else config.q
    cfg[kern.CFG_R] = np.nan if config.r == "auto" else config.r
    cfg[kern.CFG_P0] = config.p0
    cfg[kern.CFG_COND_LIMIT] = config.condition_limit
    cfg[kern.CFG_MIN_CURRENT_STD] = config.min_current_std
    cfg[kern.CFG_MIN_ROWS] = MIN_ROWS
    if config.coefficients is not None:
        cfg[kern.CFG_FIXED] = 1.0
        cfg[kern.CFG_COEF : kern.CFG_COEF + 5] = config.coefficients.as_array()
    cfg.setflags(write=False)
    return cfg


# ----------------------------------------------------------------------------- state
@dataclass(frozen=True)
class FakfState:
    """Everything the filter carries between batches.

    Attributes:
        version: schema version (``STATE_VERSION``).
        t_last_s: time of the last sample seen (-inf before any).
        vector: flat float64 vector, shape (``fakf_kernels.ST_LEN``,), laid out as the
            ``ST_*`` constants of ``estimators.kernels.fakf_kernels``: model flag and
            coefficients, q and r in use, x (2), P (3, symmetric), model-only history (2),
            current/voltage lags, identification and health-window accumulators, counters.
            Never modified in place: ``step`` works on a copy.
    """

    version: int
    t_last_s: float
    vector: FloatArray

    @property
    def model_ready(self) -> bool:
        """True once a model (identified or fixed) is in use."""
        return bool(self.vector[kern.ST_READY] == 1.0)

    @property
    def coefficients(self) -> ArxCoefficients | None:
        """The baseline model, None while identifying."""
        if not self.model_ready:
            return None
        c = self.vector[kern.ST_COEF : kern.ST_COEF + 5]
        return ArxCoefficients(*(float(v) for v in c))

    @property
    def x(self) -> FloatArray:
        """Posterior state ``[V_k, V_{k-1}]``, shape (2,)."""
        return self.vector[kern.ST_X : kern.ST_X + 2].copy()

    @property
    def P(self) -> FloatArray:  # noqa: N802 - the usual name of the covariance
        """Posterior covariance, shape (2, 2)."""
        p00, p01, p11 = self.vector[kern.ST_P : kern.ST_P + 3]
        return np.array([[p00, p01], [p01, p11]], dtype=np.float64)

    @property
    def q(self) -> float:
        """Process noise variance in use (NaN before identification)."""
        return float(self.vector[kern.ST_Q])

    @property
    def r(self) -> float:
        """Measurement noise variance in use (NaN before identification)."""
        return float(self.vector[kern.ST_R])

    @property
    def n_samples(self) -> int:
        """Samples seen since the stream start."""
        return int(self.vector[kern.ST_N_SEEN])


def initial_state(config: FakfConfig) -> FakfState:
    """State before the first sample: identifying, or with the fixed model and x = 0."""
    vec = np.zeros(kern.ST_LEN, dtype=np.float64)
    vec[kern.ST_Q] = np.nan
    vec[kern.ST_R] = np.nan
    vec[kern.ST_REF_RMS] = np.nan
    vec[kern.ST_I_LAG : kern.ST_I_LAG + 2] = np.nan
    vec[kern.ST_V_LAG : kern.ST_V_LAG + 2] = np.nan
    vec[kern.ST_COEF : kern.ST_COEF + 5] = np.nan
    if config.coefficients is not None:
        assert not isinstance(config.q, str) and not isinstance(config.r, str)
        vec[kern.ST_READY] = 1.0
        vec[kern.ST_COEF : kern.ST_COEF + 5] = config.coefficients.as_array()
        vec[kern.ST_Q] = config.q
        vec[kern.ST_R] = config.r
        # With no identification residuals, the expected innovation scale is sqrt(q + r).
        vec[kern.ST_REF_RMS] = math.sqrt(config.q + config.r)
        vec[kern.ST_P] = config.p0
        vec[kern.ST_P + 2] = config.p0
    vec.setflags(write=False)
    return FakfState(version=STATE_VERSION, t_last_s=-math.inf, vector=vec)


def dump_state(state: FakfState) -> bytes:
    """Versioned byte form of the state (exact round trip; see :func:`dump_vector_state`)."""
    return dump_vector_state(NAME, state.version, state.t_last_s, state.vector)


def load_state(data: bytes) -> FakfState:
    """Inverse of :func:`dump_state`.

    Raises:
        StateVersionError: the version is not ``STATE_VERSION``.
        EstimatorError: the bytes are not a state of this estimator.
    """
    t_last, vec = load_vector_state(data, NAME, STATE_VERSION, "a FAKF")
    if vec.shape != (kern.ST_LEN,):
        raise EstimatorError(f"not a FAKF state: vector of length {vec.shape[0]}")
    return FakfState(version=STATE_VERSION, t_last_s=t_last, vector=vec)


# ----------------------------------------------------------------------------- identification
class ArxFit(NamedTuple):
    """Least-squares fit of the eq. 15 model.

    Attributes:
        coefficients: fitted model, None when the fit was refused before solving.
        residual_rms: RMS of the one-step residual ``V_k - phi_k^T theta`` (V).
        condition_number: of the unit-diagonal Gram matrix.
        max_pole_modulus: largest |pole| of ``1 + a0 z^-1 + a1 z^-2``.
        current_std: standard deviation of I_k over the rows used (A).
        rows: regression rows used (rows with a NaN skipped).
        reason: None when accepted, else the refusal reason.
    """

    coefficients: ArxCoefficients | None
    residual_rms: float | None
    condition_number: float | None
    max_pole_modulus: float | None
    current_std: float | None
    rows: int
    reason: str | None




def _fit_from_vector(fit: FloatArray) -> ArxFit:
    code = int(fit[kern.FIT_REASON])
    coef = fit[kern.FIT_COEF : kern.FIT_COEF + 5]
    return ArxFit(
        coefficients=ArxCoefficients(*(float(v) for v in coef))
        if bool(np.all(np.isfinite(coef)))
        else None,
        residual_rms=_finite_or_none(fit[kern.FIT_RESID_RMS]),
        condition_number=_finite_or_none(fit[kern.FIT_COND]),
        max_pole_modulus=_finite_or_none(fit[kern.FIT_POLE]),
        current_std=_finite_or_none(fit[kern.FIT_I_STD]),
        rows=int(fit[kern.FIT_ROWS]),
        reason=_REASON_NAMES.get(code),
    )


def identify_arx(
    current_a: FloatArray,
    voltage_v: FloatArray,
    *,
    condition_limit: float = FakfConfig.condition_limit,
    min_current_std: float = FakfConfig.min_current_std,
) -> ArxFit:
    """Least-squares identification of eq. 15 on whole arrays (rows k = 2..n-1; a row with a
    NaN in any regressor or target is skipped), with the same checks as the streaming filter.

    Args:
        current_a: motor current, shape (n,).
        voltage_v: measured motor voltage, shape (n,).
        condition_limit: largest accepted condition number.
        min_current_std: smallest accepted current standard deviation (A).
    """
    cur = np.ascontiguousarray(current_a, dtype=np.float64)
    volt = np.ascontiguousarray(voltage_v, dtype=np.float64)
    if cur.shape != volt.shape or cur.ndim != 1:
        raise EstimatorError("current and voltage must be 1-D arrays of the same length")
    acc = np.zeros(kern.ACC_LEN, dtype=np.float64)
    kern.acc_accumulate(acc, cur, volt)
    fit = kern.acc_solve(acc, 0, float(condition_limit), float(min_current_std), float(MIN_ROWS))
    return _fit_from_vector(fit)


# ----------------------------------------------------------------------------- step
def _reason_text(code: int, fit: FloatArray | None, config: FakfConfig) -> str:
    if code == kern.FIT_TOO_FEW_ROWS:
        rows = "?" if fit is None else str(int(fit[kern.FIT_ROWS]))
        return f"too few usable rows ({rows} < {MIN_ROWS}) in the identification window"
    if code == kern.FIT_LOW_CURRENT_STD:
        std = "?" if fit is None else f"{fit[kern.FIT_I_STD]:.4g}"
        return f"current std {std} A below min_current_std {config.min_current_std:g} A"
    if code == kern.FIT_ILL_CONDITIONED:
        cond = "?" if fit is None else f"{fit[kern.FIT_COND]:.4g}"
        return f"condition number {cond} above condition_limit {config.condition_limit:g}"
    if code == kern.FIT_UNSTABLE:
        pole = "?" if fit is None else f"{fit[kern.FIT_POLE]:.4g}"
        return f"unstable model: max pole modulus {pole} >= 1"
    return "unknown"


def _event(row: FloatArray, config: FakfConfig) -> EstimatorEvent:
    fit = row[kern.EV_FIT : kern.EV_FIT + kern.FIT_LEN]
    parsed = _fit_from_vector(fit)
    detail: dict[str, Any] = {
        "residual_rms": parsed.residual_rms,
        "condition_number": parsed.condition_number,
        "max_pole_modulus": parsed.max_pole_modulus,
        "current_std": parsed.current_std,
        "rows": parsed.rows,
        "coefficients": None
        if parsed.coefficients is None
        else {n: getattr(parsed.coefficients, n) for n in COEFFICIENT_NAMES},
    }
    t = float(row[kern.EV_T])
    if row[kern.EV_KIND] == kern.EV_IDENTIFIED:
        detail["q"] = float(row[kern.EV_Q])
        detail["r"] = float(row[kern.EV_R])
        return EstimatorEvent(t_s=t, kind="identified", detail=detail)
    code = int(fit[kern.FIT_REASON])
    detail["reason"] = _reason_text(code, fit, config)
    detail["reason_code"] = _REASON_NAMES.get(code, "unknown")
    detail["retry"] = "identification restarts on the next window"
    return EstimatorEvent(t_s=t, kind="identification_failed", detail=detail)


def _grade(
    name: str, value: float | None, watch: float, alert: float, reasons: list[str]
) -> Status:
    if value is None:
        return "ok"
    if value > alert:
        reasons.append(f"{name} {value:.3g} > alert {alert:g}")
        return "alert"
    if value > watch:
        reasons.append(f"{name} {value:.3g} > watch {watch:g}")
        return "watch"
    return "ok"


def _health(row: FloatArray, config: FakfConfig) -> HealthWindow:
    def val(i: int) -> float | None:
        return _finite_or_none(row[i])

    innov_rms = val(kern.WIN_INNOV_RMS)
    ref = val(kern.WIN_REF_RMS)
    ratio = None if innov_rms is None or ref is None or ref <= 0.0 else innov_rms / ref
    indicators: dict[str, float | None] = {
        "innovation_rms": innov_rms,
        "innovation_rms_ratio": ratio,
        "nis_mean": val(kern.WIN_NIS_MEAN),
        "nis_in_bounds": val(kern.WIN_NIS_IN),
        "mae": val(kern.WIN_MAE),
        "rmse": val(kern.WIN_RMSE),
        "model_mae": val(kern.WIN_MODEL_MAE),
        "coef_drift": val(kern.WIN_DRIFT),
    }
    for i, name in enumerate(COEFFICIENT_NAMES):
        indicators[name] = val(kern.WIN_COEF + i)
    reasons: list[str] = []
    statuses: list[Status] = []
    if row[kern.WIN_READY] != 1.0:
        fail = int(row[kern.WIN_LAST_FAIL])
        if fail:
            statuses.append("alert")
            reasons.append("identification failed: " + _reason_text(fail, None, config))
    else:
        thr = config.thresholds
        statuses.append(
            _grade(
                "nis_mean", indicators["nis_mean"], thr.nis_mean_watch, thr.nis_mean_alert, reasons
            )
        )
        statuses.append(
            _grade(
                "innovation_rms_ratio",
                ratio,
                thr.innovation_ratio_watch,
                thr.innovation_ratio_alert,
                reasons,
            )
        )
        statuses.append(
            _grade(
                "coef_drift",
                indicators["coef_drift"],
                thr.coef_drift_watch,
                thr.coef_drift_alert,
                reasons,
            )
        )
    return HealthWindow(
        t_start_s=float(row[kern.WIN_T0]),
        t_end_s=float(row[kern.WIN_T1]),
        n_samples=int(row[kern.WIN_N]),
        indicators=indicators,
        status=worst_status(statuses),
        reasons=tuple(reasons),
    )


def _channel_array(batch: Batch, name: str, n: int) -> FloatArray:
    try:
        values = batch.channels[name]
    except KeyError:
        raise EstimatorError(f"batch has no channel {name!r}") from None
    arr = np.ascontiguousarray(values, dtype=np.float64)
    if arr.shape != (n,):
        raise EstimatorError(f"channel {name!r} has shape {arr.shape}, expected ({n},)")
    return arr


def step(config: FakfConfig, state: FakfState, batch: Batch) -> tuple[FakfState, StepOutputs]:
    """Advance the filter over a whole batch (the per-sample loop runs compiled).

    Per-sample outputs (NaN before a model is available): ``voltage_estimate`` (posterior
    V_k, eq. 10), ``voltage_model`` (eq. 15 driven by current alone, fed back its own outputs),
    ``innovation`` (V_k minus the prior; NaN when V_k is missing) and ``innovation_var``
    (S_k = H P-_k H^T + r).

    Raises:
        OutOfOrderError: the batch starts at or before ``state.t_last_s``, or its times are not
            strictly increasing.
        EstimatorError: a channel is missing or has the wrong length.
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
    cur = _channel_array(batch, config.current_channel, n)
    volt = _channel_array(batch, config.voltage_channel, n)
    vec = state.vector.copy()
    est, mod, inn, svar, windows, events, status = kern.fakf_batch(
        config.kernel_vector, vec, t, cur, volt
    )
    if status != 0:
        raise OutOfOrderError("batch times are not strictly increasing")
    vec.setflags(write=False)
    new_state = FakfState(version=STATE_VERSION, t_last_s=float(t[n - 1]), vector=vec)
    outputs = StepOutputs(
        samples={
            "voltage_estimate": est,
            "voltage_model": mod,
            "innovation": inn,
            "innovation_var": svar,
        },
        health=[_health(row, config) for row in windows],
        events=[_event(row, config) for row in events],
    )
    return new_state, outputs


def warm_up() -> None:
    """Compile (or load from numba's cache) every kernel on tiny inputs."""
    rng = np.random.default_rng(0)
    n = 24
    current = rng.standard_normal(n)
    voltage = np.convolve(current, [0.5, 1.0, -0.3])[:n] + 0.1 * rng.standard_normal(n)
    identify_arx(current, voltage)
    config = parse_config({"identification_samples": 10, "health_window_samples": 10})
    batch = Batch(
        t_s=np.arange(n, dtype=np.float64),
        channels={"current": current, "voltage": voltage},
    )
    step(config, initial_state(config), batch)
