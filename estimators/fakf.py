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
  ``identification_failed`` event, health windows (and the step) report "unknown" with the
  reason until a model is found (a refusal says nothing about the actuator's health, only that
  the estimator cannot vouch for any output), and identification is retried on the next window of the same size (no outputs
  meanwhile);
* ``q = r = "auto"``: half the variance of the identification's one-step residual each, so that
  the steady innovation variance S is close to the residual variance and NIS is near 1 on data
  like those of the identification window;
* a NaN voltage: predict only (estimate = prior, P grows, innovation NaN);
  a NaN current: the last valid current is held (0 before any);
* health indicators over fixed windows of ``health_window_samples`` stream samples, with the
  model re-identified on each window from the same Gram accumulation (``coef_drift`` against
  the first identified model, static gain and dominant pole of the window model);
* status ``learning`` while no model exists (never ``ok`` before one).

Beyond the seed (docs/methods.md): optional voltage rails (a sample at or beyond a rail is
censored: not scored, not in any least-squares row, a pseudo-measurement at the rail; the state
and the model-only recursion are clamped to the rails); a persistence baseline (repeat the last
sample) scored against the one-step prior in every window, with re-identification from the
window just closed when the prior loses (``unknown`` for that window); segments closed by
``Batch.end_of_run`` or by a gap in stream time longer than ``idle_close_s`` (the partial
window is reported, the lags cleared, the filter restarted on the next usable voltage).
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from functools import cached_property
from typing import Any, Literal, NamedTuple

import numpy as np
from pydantic import ConfigDict, Field, ValidationError, field_validator, model_validator

from estimators.base import (
    STATUSES,
    Batch,
    EstimatorConfigModel,
    EstimatorError,
    EstimatorEvent,
    FloatArray,
    HealthWindow,
    OutOfOrderError,
    Status,
    StatusReport,
    StepOutputs,
    config_error,
    dump_vector_state,
    load_vector_state,
    worst_status,
)
from estimators.checks import finite_or_none as _finite_or_none
from estimators.kernels import fakf_kernels as kern

NAME = "fakf"
STATE_VERSION = 2

SAMPLE_OUTPUTS = ("voltage_estimate", "voltage_model", "innovation", "innovation_var")
COEFFICIENT_NAMES = ("a0", "a1", "b0", "b1", "b2")
MIN_ROWS = 10
_REASON_NAMES = {
    kern.FIT_TOO_FEW_ROWS: "too_few_rows",
    kern.FIT_LOW_CURRENT_STD: "low_current_excitation",
    kern.FIT_ILL_CONDITIONED: "ill_conditioned",
    kern.FIT_UNSTABLE: "unstable_model",
    kern.FIT_NOT_BETTER: "not_better_than_persistence",
}


# ----------------------------------------------------------------------------- configuration
class ArxCoefficients(EstimatorConfigModel):
    """Coefficients of the eq. 15 model ``V[k] = -a0 V[k-1] - a1 V[k-2] + b0 I[k] + b1 I[k-1]
    + b2 I[k-2]`` (a0, a1 dimensionless; b0, b1, b2 in V/A)."""

    model_config = ConfigDict(frozen=True, extra="forbid", strict=True)

    a0: float = Field(
        description="eq. 15 denominator coefficient of z^-1 (dimensionless)", allow_inf_nan=False
    )
    a1: float = Field(
        description="eq. 15 denominator coefficient of z^-2 (dimensionless)", allow_inf_nan=False
    )
    b0: float = Field(description="eq. 15 numerator coefficient of z^0 (V/A)", allow_inf_nan=False)
    b1: float = Field(description="eq. 15 numerator coefficient of z^-1 (V/A)", allow_inf_nan=False)
    b2: float = Field(description="eq. 15 numerator coefficient of z^-2 (V/A)", allow_inf_nan=False)

    @model_validator(mode="after")
    def _stable(self) -> ArxCoefficients:
        if kern.max_pole_modulus(self.a0, self.a1) >= 1.0:
            raise ValueError("coefficients: the model 1 + a0 z^-1 + a1 z^-2 is not stable")
        return self

    def as_array(self) -> FloatArray:
        """``[a0, a1, b0, b1, b2]``, shape (5,)."""
        return np.array([self.a0, self.a1, self.b0, self.b1, self.b2], dtype=np.float64)


class FakfThresholds(EstimatorConfigModel):
    """Status thresholds applied to each health window (a value above "watch" gives "watch",
    above "alert" gives "alert")."""

    model_config = ConfigDict(frozen=True, extra="forbid", strict=True)

    nis_mean_watch: float = Field(
        default=2.0,
        gt=0,
        description="mean normalized innovation squared (expected 1), watch level",
        allow_inf_nan=False,
    )
    nis_mean_alert: float = Field(
        default=4.0, gt=0, description="same, alert level", allow_inf_nan=False
    )
    innovation_ratio_watch: float = Field(
        default=1.5,
        gt=0,
        description="innovation RMS over the identification residual RMS, watch level",
        allow_inf_nan=False,
    )
    innovation_ratio_alert: float = Field(
        default=2.0, gt=0, description="same, alert level", allow_inf_nan=False
    )
    coef_drift_watch: float = Field(
        default=0.3,
        gt=0,
        description="relative RMS difference of the window model's and the reference model's "
        "one-step predictions on the window's data (dimensionless), watch level",
        allow_inf_nan=False,
    )
    coef_drift_alert: float = Field(
        default=0.6, gt=0, description="same, alert level", allow_inf_nan=False
    )

    @model_validator(mode="after")
    def _ordered(self) -> FakfThresholds:
        for base in ("nis_mean", "innovation_ratio", "coef_drift"):
            if getattr(self, f"{base}_alert") < getattr(self, f"{base}_watch"):
                raise ValueError(f"thresholds.{base}_alert: must not be below {base}_watch")
        return self


class ReidentificationConfig(EstimatorConfigModel):
    """When the model in use is replaced because it predicts worse than persistence."""

    model_config = ConfigDict(frozen=True, extra="forbid", strict=True)

    enabled: bool = Field(
        default=True,
        description="re-identify when the one-step prior loses to persistence (repeating the "
        "last sample); never with fixed coefficients",
    )
    margin: float = Field(
        default=0.05,
        ge=0,
        le=10,
        description="a full window loses when its prior RMS exceeds (1 + margin) times the "
        "persistence RMS on the same samples (dimensionless)",
        allow_inf_nan=False,
    )
    windows: int = Field(
        default=1,
        ge=1,
        le=1000,
        description="consecutive losing full windows before re-identifying (a window that does "
        "not lose resets the count)",
    )


class FakfConfig(EstimatorConfigModel):
    """Validated FAKF configuration (build it with :func:`parse_config`)."""

    model_config = ConfigDict(frozen=True, extra="forbid", strict=True)

    current_channel: str = Field(
        default="current", min_length=1, description="motor current channel (A)"
    )
    voltage_channel: str = Field(
        default="voltage", min_length=1, description="measured motor voltage channel (V)"
    )
    identification_samples: int = Field(
        default=1000,
        ge=MIN_ROWS,
        le=100_000_000,
        description="length of the identification window (stream samples)",
    )
    coefficients: ArxCoefficients | None = Field(
        default=None, description="fixed eq. 15 coefficients; when given, no identification is run"
    )
    q: float | Literal["auto"] = Field(
        default="auto",
        description='process noise variance of V (V^2), or "auto": half the identification '
        "residual variance",
    )
    r: float | Literal["auto"] = Field(
        default="auto",
        description='measurement noise variance (V^2), or "auto": half the identification '
        "residual variance",
    )
    p0: float = Field(
        default=100.0,
        gt=0,
        description="initial variance of both state components (V^2)",
        allow_inf_nan=False,
    )
    health_window_samples: int = Field(
        default=1000,
        ge=MIN_ROWS,
        le=100_000_000,
        description="length of a health window (stream samples)",
    )
    condition_limit: float = Field(
        default=1.0e6,
        gt=0,
        description="largest accepted condition number of the unit-diagonal Gram matrix",
        allow_inf_nan=False,
    )
    min_current_std: float = Field(
        default=0.05,
        gt=0,
        description="smallest accepted current standard deviation in a fit (A)",
        allow_inf_nan=False,
    )
    voltage_rail_low_v: float | None = Field(
        default=None,
        description="lower rail of the measured voltage (V): a sample at or below it is "
        "censored, and no estimate goes below it; None: no rail",
        allow_inf_nan=False,
    )
    voltage_rail_high_v: float | None = Field(
        default=None,
        description="upper rail of the measured voltage (V): a sample at or above it is "
        "censored, and no estimate goes above it; None: no rail",
        allow_inf_nan=False,
    )
    idle_close_s: float | None = Field(
        default=None,
        gt=0,
        description="a gap in stream time longer than this (s) closes the segment before the "
        "next sample: partial health window reported, filter restarted; None: never",
        allow_inf_nan=False,
    )
    min_graded_samples: int = Field(
        default=30,
        ge=1,
        le=100_000_000,
        description="fewest scored samples for a window to be graded; a shorter window (a "
        "closed segment's tail) carries the status of the previous graded window",
    )
    reidentification: ReidentificationConfig = Field(
        default=ReidentificationConfig(),
        description="re-identification when the prior loses to persistence",
    )
    thresholds: FakfThresholds = Field(
        default=FakfThresholds(), description="status thresholds of the health windows"
    )

    @field_validator("q", "r")
    @classmethod
    def _positive_noise(cls, value: float | str) -> float | str:
        if isinstance(value, float) and not (math.isfinite(value) and value > 0.0):
            raise ValueError("expected a positive finite number or 'auto'")
        return value

    @model_validator(mode="after")
    def _consistent(self) -> FakfConfig:
        if self.coefficients is not None and (self.q == "auto" or self.r == "auto"):
            raise ValueError('q: "auto" needs identification; give q and r with fixed coefficients')
        lo, hi = self.voltage_rail_low_v, self.voltage_rail_high_v
        if lo is not None and hi is not None and not lo < hi:
            raise ValueError("voltage_rail_low_v: must be below voltage_rail_high_v")
        return self

    @cached_property
    def kernel_vector(self) -> FloatArray:
        """The flat configuration vector the compiled kernel reads (built once)."""
        return _kernel_config(self)


CONFIG_MODEL = FakfConfig


def parse_config(raw: Mapping[str, Any]) -> FakfConfig:
    """Validate a JSON-like mapping into a :class:`FakfConfig`.

    Raises:
        ConfigError: unknown keys, wrong types, non-positive q/r/p0, window sizes out of range,
            coefficients that are not exactly {a0, a1, b0, b1, b2} or unstable, thresholds not
            increasing, rails not ordered, or ``r``/``q`` "auto" together with fixed
            coefficients (no residuals to use). The message names the field.
    """
    if isinstance(raw, FakfConfig):
        return raw
    try:
        return FakfConfig.model_validate(raw)
    except ValidationError as exc:
        raise config_error(NAME, exc) from None


def config_to_dict(config: FakfConfig) -> dict[str, Any]:
    """The full configuration with defaults filled in, JSON-serializable."""
    return config.model_dump(mode="json")


def required_channels(config: FakfConfig) -> tuple[str, ...]:
    """The current and voltage channels."""
    return (config.current_channel, config.voltage_channel)


def _nan_if_none(value: float | None) -> float:
    return math.nan if value is None else value


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
    cfg[kern.CFG_RAIL_LO] = _nan_if_none(config.voltage_rail_low_v)
    cfg[kern.CFG_RAIL_HI] = _nan_if_none(config.voltage_rail_high_v)
    cfg[kern.CFG_IDLE_CLOSE] = _nan_if_none(config.idle_close_s)
    reid = config.reidentification
    cfg[kern.CFG_REIDENT] = 1.0 if reid.enabled else 0.0
    cfg[kern.CFG_REIDENT_MARGIN] = reid.margin
    cfg[kern.CFG_REIDENT_WINDOWS] = reid.windows
    cfg[kern.CFG_MIN_SCORED] = config.min_graded_samples
    cfg.setflags(write=False)
    return cfg


# ----------------------------------------------------------------------------- state
# Named parts of the packed state vector: name -> (offset, length). Only the accessors of
# FakfState and the kernel boundary read the vector by position.
STATE_LAYOUT: dict[str, tuple[int, int]] = {
    "model_ready": (kern.ST_READY, 1),
    "coefficients": (kern.ST_COEF, 5),
    "q": (kern.ST_Q, 1),
    "r": (kern.ST_R, 1),
    "reference_rms": (kern.ST_REF_RMS, 1),
    "x": (kern.ST_X, 2),
    "covariance_upper": (kern.ST_P, 3),
    "model_history": (kern.ST_M, 2),
    "current_lags": (kern.ST_I_LAG, 2),
    "voltage_lags": (kern.ST_V_LAG, 2),
    "held_current_lags": (kern.ST_IH_LAG, 2),
    "n_seen": (kern.ST_N_SEEN, 1),
    "identification_count": (kern.ST_ID_COUNT, 1),
    "last_failure_code": (kern.ST_LAST_FAIL, 1),
    "window_sums": (kern.ST_W_COUNT, kern.ST_W_N_MODEL - kern.ST_W_COUNT + 1),
    "identification_gram": (kern.ST_ID, kern.ACC_LEN),
    "window_gram": (kern.ST_WG, kern.ACC_LEN),
    "reference_coefficients": (kern.ST_BASE_COEF, 5),
    "t_last_s": (kern.ST_T_LAST, 1),
    "restart_pending": (kern.ST_RESTART, 1),
    "persistence_voltage": (kern.ST_V_PERSIST, 1),
    "window_persistence_sums": (
        kern.ST_W_SUM_PRIOR2_PAIRED,
        kern.ST_W_N_CENSORED - kern.ST_W_SUM_PRIOR2_PAIRED + 1,
    ),
    "losing_windows": (kern.ST_LOSE_COUNT, 1),
    "n_reidentifications": (kern.ST_N_REIDENT, 1),
    "previous_status_index": (kern.ST_PREV_STATUS, 1),
    "reference_x": (kern.ST_XR, 2),
    "reference_covariance_upper": (kern.ST_PR, 3),
    "reference_q": (kern.ST_BASE_Q, 1),
    "reference_r": (kern.ST_BASE_R, 1),
}


@dataclass(frozen=True)
class FakfState:
    """Everything the filter carries between batches.

    Attributes:
        version: schema version (``STATE_VERSION``).
        t_last_s: time of the last sample seen (-inf before any).
        vector: flat float64 vector, shape (``fakf_kernels.ST_LEN``,), whose parts are named in
            :data:`STATE_LAYOUT` and read through the properties below. Never modified in
            place: ``step`` works on a copy.
    """

    version: int
    t_last_s: float
    vector: FloatArray

    def part(self, name: str) -> FloatArray:
        """A read-only copy of one named part of the state (see :data:`STATE_LAYOUT`)."""
        off, length = STATE_LAYOUT[name]
        out = self.vector[off : off + length].copy()
        out.setflags(write=False)
        return out

    def _scalar(self, name: str) -> float:
        return float(self.vector[STATE_LAYOUT[name][0]])

    @property
    def model_ready(self) -> bool:
        """True once a model (identified or fixed) is in use."""
        return self._scalar("model_ready") == 1.0

    @property
    def coefficients(self) -> ArxCoefficients | None:
        """The model in use, None while identifying."""
        if not self.model_ready:
            return None
        return _coefficients(self.part("coefficients"))

    @property
    def reference_coefficients(self) -> ArxCoefficients | None:
        """The first identified model, reference of ``coef_drift`` (None before it)."""
        c = self.part("reference_coefficients")
        return _coefficients(c) if bool(np.all(np.isfinite(c))) else None

    @property
    def x(self) -> FloatArray:
        """Posterior state ``[V_k, V_{k-1}]``, shape (2,)."""
        return self.part("x")

    @property
    def P(self) -> FloatArray:  # noqa: N802 - the usual name of the covariance
        """Posterior covariance, shape (2, 2)."""
        p00, p01, p11 = self.part("covariance_upper")
        return np.array([[p00, p01], [p01, p11]], dtype=np.float64)

    @property
    def q(self) -> float:
        """Process noise variance in use (NaN before identification)."""
        return self._scalar("q")

    @property
    def r(self) -> float:
        """Measurement noise variance in use (NaN before identification)."""
        return self._scalar("r")

    @property
    def n_samples(self) -> int:
        """Samples seen since the stream start."""
        return int(self._scalar("n_seen"))

    @property
    def n_reidentifications(self) -> int:
        """Times the model in use was replaced because it lost to persistence."""
        return int(self._scalar("n_reidentifications"))

    @property
    def restart_pending(self) -> bool:
        """True after a closed segment, until the filter restarts on a usable voltage."""
        return self._scalar("restart_pending") == 1.0

    @property
    def samples_in_open_window(self) -> int:
        """Samples of the health window not closed yet."""
        return int(self.part("window_sums")[0])


def _coefficients(c: FloatArray) -> ArxCoefficients:
    return ArxCoefficients.model_construct(
        a0=float(c[0]), a1=float(c[1]), b0=float(c[2]), b1=float(c[3]), b2=float(c[4])
    )


def _fresh_vector(config: FakfConfig) -> FloatArray:
    vec = np.zeros(kern.ST_LEN, dtype=np.float64)
    vec[kern.ST_Q] = np.nan
    vec[kern.ST_R] = np.nan
    vec[kern.ST_REF_RMS] = np.nan
    vec[kern.ST_I_LAG : kern.ST_I_LAG + 2] = np.nan
    vec[kern.ST_V_LAG : kern.ST_V_LAG + 2] = np.nan
    vec[kern.ST_COEF : kern.ST_COEF + 5] = np.nan
    vec[kern.ST_BASE_COEF : kern.ST_BASE_COEF + 5] = np.nan
    vec[kern.ST_T_LAST] = -math.inf
    vec[kern.ST_V_PERSIST] = np.nan
    vec[kern.ST_PREV_STATUS] = -1.0
    vec[kern.ST_XR : kern.ST_XR + 2] = np.nan
    vec[kern.ST_PR : kern.ST_PR + 3] = np.nan
    vec[kern.ST_BASE_Q] = np.nan
    vec[kern.ST_BASE_R] = np.nan
    if config.coefficients is not None:
        assert not isinstance(config.q, str) and not isinstance(config.r, str)
        vec[kern.ST_READY] = 1.0
        vec[kern.ST_COEF : kern.ST_COEF + 5] = config.coefficients.as_array()
        vec[kern.ST_BASE_COEF : kern.ST_BASE_COEF + 5] = config.coefficients.as_array()
        vec[kern.ST_Q] = config.q
        vec[kern.ST_R] = config.r
        # With no identification residuals, the expected innovation scale is sqrt(q + r).
        vec[kern.ST_REF_RMS] = math.sqrt(config.q + config.r)
        vec[kern.ST_BASE_Q] = config.q
        vec[kern.ST_BASE_R] = config.r
        vec[kern.ST_P] = config.p0
        vec[kern.ST_P + 2] = config.p0
    return vec


def initial_state(config: FakfConfig) -> FakfState:
    """State before the first sample: identifying, or with the fixed model and x = 0."""
    vec = _fresh_vector(config)
    vec.setflags(write=False)
    return FakfState(version=STATE_VERSION, t_last_s=-math.inf, vector=vec)


def dump_state(state: FakfState) -> bytes:
    """Versioned byte form of the state (exact round trip; see :func:`dump_vector_state`)."""
    return dump_vector_state(NAME, state.version, state.t_last_s, state.vector)


def _hex(v: float) -> str:
    return float(v).hex()


def _upgrade_v1(doc: dict[str, Any]) -> dict[str, Any]:
    """Version 1 -> 2: the v1 vector is kept as it is and the v2 parts are appended, set as a
    state would have them had v2 run from the start: the reference model of ``coef_drift`` is
    the model in use (v1 never re-identified), the last sample time comes from the document,
    the persistence prediction is the last measured voltage, no restart pending, the window's
    persistence sums start empty (the open window is compared on its remaining samples)."""
    vec = [float.fromhex(v) for v in doc["vector"]]
    if len(vec) != kern.ST_LEN_V1:
        raise EstimatorError(f"not a FAKF v1 state: vector of length {len(vec)}")
    ready = vec[kern.ST_READY] == 1.0
    coef = vec[kern.ST_COEF : kern.ST_COEF + 5] if ready else [math.nan] * 5
    extra = [
        *coef,
        float.fromhex(doc["t_last_s"]),  # ST_T_LAST
        0.0,  # ST_RESTART
        vec[kern.ST_V_LAG],  # ST_V_PERSIST
        0.0,  # ST_W_SUM_PRIOR2_PAIRED
        0.0,  # ST_W_SUM_PERSIST2
        0.0,  # ST_W_N_PAIRED
        0.0,  # ST_W_N_CENSORED
        0.0,  # ST_LOSE_COUNT
        0.0,  # ST_N_REIDENT
        -1.0,  # ST_PREV_STATUS
        *vec[kern.ST_X : kern.ST_X + 2],  # ST_XR: v1 never re-identified; the reference
        *vec[kern.ST_P : kern.ST_P + 3],  # ST_PR   filter is the filter in use
        vec[kern.ST_Q],  # ST_BASE_Q
        vec[kern.ST_R],  # ST_BASE_R
    ]
    assert kern.ST_LEN_V1 + len(extra) == kern.ST_LEN
    return {**doc, "version": 2, "vector": [_hex(v) for v in vec + extra]}


_UPGRADES: dict[int, Callable[[dict[str, Any]], dict[str, Any]]] = {1: _upgrade_v1}


def load_state(data: bytes) -> FakfState:
    """Inverse of :func:`dump_state`; reads the current version and upgrades older ones.

    Raises:
        StateVersionError: the version is neither ``STATE_VERSION`` nor one with an upgrade.
        EstimatorError: the bytes are not a state of this estimator.
    """
    try:
        doc = json.loads(data)
    except (ValueError, UnicodeDecodeError) as exc:
        raise EstimatorError(f"not a FAKF state: {exc}") from exc
    if isinstance(doc, dict) and doc.get("kind", NAME) == NAME:
        try:
            while doc.get("version") in _UPGRADES:
                doc = _UPGRADES[doc["version"]](doc)
        except (KeyError, TypeError, ValueError) as exc:
            raise EstimatorError(f"not a FAKF state: {exc}") from exc
        data = json.dumps(doc, separators=(",", ":")).encode("ascii")
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
        coefficients=_coefficients(coef) if bool(np.all(np.isfinite(coef))) else None,
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
    condition_limit: float = 1.0e6,
    min_current_std: float = 0.05,
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
    fit = kern.acc_solve(acc, float(condition_limit), float(min_current_std), float(MIN_ROWS))
    return _fit_from_vector(fit)


# ----------------------------------------------------------------------------- step
def _reason_text(code: int, fit: FloatArray | None, config: FakfConfig) -> str:
    if code == kern.FIT_TOO_FEW_ROWS:
        rows = "?" if fit is None else str(int(fit[kern.FIT_ROWS]))
        return f"too few usable rows ({rows} < {MIN_ROWS}) in the fit window"
    if code == kern.FIT_LOW_CURRENT_STD:
        std = "?" if fit is None else f"{fit[kern.FIT_I_STD]:.4g}"
        return f"current std {std} A below min_current_std {config.min_current_std:g} A"
    if code == kern.FIT_ILL_CONDITIONED:
        cond = "?" if fit is None else f"{fit[kern.FIT_COND]:.4g}"
        return f"condition number {cond} above condition_limit {config.condition_limit:g}"
    if code == kern.FIT_UNSTABLE:
        pole = "?" if fit is None else f"{fit[kern.FIT_POLE]:.4g}"
        return f"unstable model: max pole modulus {pole} >= 1"
    if code == kern.FIT_NOT_BETTER:
        return "the window's own model does not beat persistence in-sample"
    return "unknown"


def _coef_dict(c: ArxCoefficients | None) -> dict[str, float] | None:
    return None if c is None else {n: getattr(c, n) for n in COEFFICIENT_NAMES}


def _event(row: FloatArray, config: FakfConfig) -> EstimatorEvent:
    fit = row[kern.EV_FIT : kern.EV_FIT + kern.FIT_LEN]
    parsed = _fit_from_vector(fit)
    detail: dict[str, Any] = {
        "residual_rms": parsed.residual_rms,
        "condition_number": parsed.condition_number,
        "max_pole_modulus": parsed.max_pole_modulus,
        "current_std": parsed.current_std,
        "rows": parsed.rows,
        "coefficients": _coef_dict(parsed.coefficients),
    }
    t = float(row[kern.EV_T])
    kind_code = row[kern.EV_KIND]
    code = int(fit[kern.FIT_REASON])
    if kind_code in (kern.EV_REIDENTIFIED, kern.EV_REIDENT_FAILED):
        prior = float(row[kern.EV_PRIOR_RMS])
        persist = float(row[kern.EV_PERSIST_RMS])
        detail["prior_rms"] = prior
        detail["persistence_rms"] = persist
        detail["why"] = (
            f"prior RMS {prior:.3g} V above persistence RMS {persist:.3g} V in "
            f"{config.reidentification.windows} consecutive full window(s) "
            f"(margin {config.reidentification.margin:g})"
        )
        if kind_code == kern.EV_REIDENTIFIED:
            detail["q"] = float(row[kern.EV_Q])
            detail["r"] = float(row[kern.EV_R])
            return EstimatorEvent(t_s=t, kind="reidentified", detail=detail)
        detail["reason"] = _reason_text(code, fit, config)
        detail["reason_code"] = _REASON_NAMES.get(code, "unknown")
        detail["retry"] = "the model in use is kept; the next losing window tries again"
        return EstimatorEvent(t_s=t, kind="reidentification_failed", detail=detail)
    if kind_code == kern.EV_IDENTIFIED:
        detail["q"] = float(row[kern.EV_Q])
        detail["r"] = float(row[kern.EV_R])
        return EstimatorEvent(t_s=t, kind="identified", detail=detail)
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


CLOSED_BY_CODES = {
    "full": kern.CLOSE_FULL,
    "end_of_run": kern.CLOSE_END_OF_RUN,
    "idle_gap": kern.CLOSE_IDLE,
}
"""Values of the ``closed_by`` indicator: why a window ended (indicators are numbers)."""


def _health(row: FloatArray, config: FakfConfig, previous: Status | None) -> HealthWindow:
    """One health window from its kernel row.

    Status: ``learning`` before a model exists (``unknown`` after a refused identification);
    with a model, the worst of the graded indicators and ``unknown`` when the prior lost to
    persistence; a window with fewer than ``min_graded_samples`` scored samples is not graded
    and carries ``previous`` (the last graded window's status), saying so.
    """

    def val(i: int) -> float | None:
        return _finite_or_none(row[i])

    innov_rms = val(kern.WIN_INNOV_RMS)
    ref = val(kern.WIN_REF_RMS)
    ratio = None if innov_rms is None or ref is None or ref <= 0.0 else innov_rms / ref
    persist_rms = val(kern.WIN_PERSIST_RMS)
    prior_paired = val(kern.WIN_PRIOR_RMS_PAIRED)
    persist_ratio = (
        None
        if persist_rms is None or prior_paired is None or persist_rms <= 0.0
        else prior_paired / persist_rms
    )
    ref_resid = val(kern.WIN_REF_RESID_RMS)
    base_resid = ref
    ref_resid_ratio = (
        None
        if ref_resid is None or base_resid is None or base_resid <= 0.0
        else ref_resid / base_resid
    )
    n_innov = int(row[kern.WIN_N_INNOV])
    n_paired = int(row[kern.WIN_N_PAIRED])
    indicators: dict[str, float | None] = {
        "innovation_rms": innov_rms,
        "innovation_rms_ratio": ratio,
        "nis_mean": val(kern.WIN_NIS_MEAN),
        "nis_in_bounds": val(kern.WIN_NIS_IN),
        "mae": val(kern.WIN_MAE),
        "rmse": val(kern.WIN_RMSE),
        "model_mae": val(kern.WIN_MODEL_MAE),
        "coef_drift": val(kern.WIN_DRIFT),
        "reference_residual_rms": ref_resid,
        "reference_residual_ratio": ref_resid_ratio,
        "prior_rms_paired": prior_paired,
        "persistence_rms": persist_rms,
        "prior_to_persistence_rms_ratio": persist_ratio,
        "scored_samples": float(n_innov),
        "censored_samples": float(row[kern.WIN_N_CENSORED]),
        "closed_by": float(row[kern.WIN_CLOSED_BY]),
        "static_gain_v_per_a": val(kern.WIN_GAIN),
        "dominant_pole": val(kern.WIN_POLE),
    }
    for i, name in enumerate(COEFFICIENT_NAMES):
        indicators[name] = val(kern.WIN_COEF + i)
    reasons: list[str] = []
    statuses: list[Status] = []
    if row[kern.WIN_READY] != 1.0:
        fail = int(row[kern.WIN_LAST_FAIL])
        if fail:
            statuses.append("unknown")
            reasons.append("identification failed: " + _reason_text(fail, None, config))
        else:
            statuses.append("learning")
            reasons.append("no model yet: identifying")
    elif n_innov < config.min_graded_samples:
        carried: Status = "learning" if previous is None else previous
        statuses.append(carried)
        reasons.append(
            f"{n_innov} scored samples < min_graded_samples {config.min_graded_samples}: "
            f"not graded, status of the previous graded window ({carried}) carried"
        )
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
        limit = 1.0 + config.reidentification.margin
        if (
            persist_ratio is not None
            and n_paired >= config.min_graded_samples
            and persist_ratio > limit
        ):
            statuses.append("unknown")
            reasons.append(
                f"prior RMS {prior_paired:.3g} V is {persist_ratio:.3g} x the persistence RMS "
                f"{persist_rms:.3g} V (> {limit:g}): the model predicts worse than repeating "
                "the last sample"
            )
    reid = row[kern.WIN_REIDENT]
    if reid == kern.REID_DONE:
        reasons.append("model re-identified on this window")
    elif reid == kern.REID_REFUSED:
        code = int(row[kern.WIN_REIDENT_CODE])
        reasons.append("re-identification refused: " + _reason_text(code, None, config))
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
    V_k, eq. 10, within the rails), ``voltage_model`` (eq. 15 driven by current alone, fed back
    its own outputs), ``innovation`` (V_k minus the prior; NaN when V_k is missing or censored)
    and ``innovation_var`` (S_k = H P-_k H^T + r).

    ``batch.end_of_run`` closes the segment after the batch's last sample (an empty batch may
    carry it): the partial health window is reported and the filter restarts on the next
    usable voltage. While no model exists the step reports ``learning`` (``unknown`` after a
    refused identification), so a stream is never ``ok`` before it has a model.

    Raises:
        OutOfOrderError: the batch starts at or before ``state.t_last_s``, or its times are not
            strictly increasing.
        EstimatorError: a channel is missing or has the wrong length.
    """
    t = np.ascontiguousarray(batch.t_s, dtype=np.float64)
    n = int(t.shape[0])
    if n == 0 and not batch.end_of_run:
        empty = np.empty(0, dtype=np.float64)
        return state, StepOutputs(
            samples={name: empty for name in SAMPLE_OUTPUTS}, status=_learning_status(state)
        )
    if n > 0 and not t[0] > state.t_last_s:
        raise OutOfOrderError(
            f"batch starts at t={float(t[0])!r} s, not after the last sample t={state.t_last_s!r} s"
        )
    if n == 0:  # an empty batch that only closes the run may carry no channels
        cur = volt = np.empty(0, dtype=np.float64)
    else:
        cur = _channel_array(batch, config.current_channel, n)
        volt = _channel_array(batch, config.voltage_channel, n)
    vec = state.vector.copy()
    est, mod, inn, svar, windows, events, status = kern.fakf_batch(
        config.kernel_vector, vec, t, cur, volt, bool(batch.end_of_run)
    )
    if status != 0:
        raise OutOfOrderError("batch times are not strictly increasing")
    health = []
    prev_idx = int(vec[kern.ST_PREV_STATUS])
    for row in windows:
        previous = STATUSES[prev_idx] if prev_idx >= 0 else None
        window = _health(row, config, previous)
        health.append(window)
        if int(row[kern.WIN_N_INNOV]) >= config.min_graded_samples and row[kern.WIN_READY] == 1.0:
            prev_idx = STATUSES.index(window.status)
    vec[kern.ST_PREV_STATUS] = prev_idx
    vec.setflags(write=False)
    t_last = float(t[n - 1]) if n > 0 else state.t_last_s
    new_state = FakfState(version=STATE_VERSION, t_last_s=t_last, vector=vec)
    outputs = StepOutputs(
        samples={
            "voltage_estimate": est,
            "voltage_model": mod,
            "innovation": inn,
            "innovation_var": svar,
        },
        health=health,
        events=[_event(row, config) for row in events],
        status=_learning_status(new_state),
    )
    return new_state, outputs


def _learning_status(state: FakfState) -> StatusReport | None:
    """``learning`` (or ``unknown`` after a refused identification) while no model exists; None
    once a model is in use (the health windows' statuses stand)."""
    if state.model_ready:
        return None
    fail = int(state.part("last_failure_code")[0])
    if fail:
        return StatusReport(
            "unknown",
            (f"identification failed ({_REASON_NAMES.get(fail, 'unknown')}); retrying",),
        )
    seen = int(state.part("identification_count")[0])
    return StatusReport("learning", (f"no model yet: identifying ({seen} samples seen)",))


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
    state, _ = step(config, initial_state(config), batch)
    step(config, state, Batch(t_s=np.empty(0), channels={}, end_of_run=True))
