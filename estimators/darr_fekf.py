"""Distributed analytical redundancy relations (DARR), fault-signature isolation and fuzzy
adaptive EKF (FEKF) for a SHA/EMA dissimilar redundant actuation system (seed paper 003:
"Distributed fault estimation of dissimilar redundant actuation system of more electric
aircraft").

One relation per sensor (seed eqs. 17-23; signs here follow the plant equations 1-13, see
``docs/methods-darr-fekf.md``), evaluated on the stream with a causal smoothing differentiator:

    r1 = K_m U_a - K_m^2 w - L_w J_m w'' - L_w f_m w' - L_w (P/2pi) F_c' + R_w S_e
         - R_w (P/2pi) F_c - J_m R_w w' - f_m R_w w
    r2 = (P/2pi) w - v - F_c' / K_s
    r3 = F_c - F_E - f_r v - m v'
    r4 = F_E' + F_H' - m_r v'' + (m_r/K_1) F_E''' - B_d v' + (B_d/K_1) F_E'' - K_d v
         + (K_d/K_1) F_E'
    r5 = F_E' + F_H' - m_r v_p'' + (m_r/K_2) F_H''' - B_d v_p' + (B_d/K_2) F_H'' - K_d v_p
         + (K_d/K_2) F_H'
    r6 = A_h P_L - m_h v_p' - B_h v_p - F_H
    r7 = K_q x_v - K_c P_L - A_h v_p - P_L / R_il - C_hj P_L'

A residual above its threshold for ``min_duration_s`` sets its bit of the coherence vector
(latched until the fault clears); the fault signature matrix (which parameter enters which
relation) is derived from these term tables; the candidate fault sets are the sets of
parameters (set gains excluded) whose signatures together give exactly the coherence vector.
Each implicated subsystem with a configured estimator then runs an EKF or FEKF on its own
relation (subsystem 6: A_h, m_h, B_h; subsystem 7: A_h, R_il, C_hj; others by
configuration), on relative parameters ``rho = theta / theta_nom``, in one of two forms: the
relation itself as a pseudo-measurement of zero (default), or the seed's form, the state
measured by the subsystem's sensor with the relation integrated as its model. Equations and
every choice where the seed is silent: ``docs/methods-darr-fekf.md``.
"""

from __future__ import annotations

import base64
import functools
import itertools
import json
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Annotated, Any, Literal, NamedTuple

import numpy as np
from pydantic import Field, ValidationError, ValidationInfo, field_validator, model_validator

from estimators.base import (
    Batch,
    ConfigError,
    Diagnosis,
    EstimatorConfigModel,
    EstimatorError,
    EstimatorEvent,
    FloatArray,
    HealthWindow,
    OutOfOrderError,
    StateVersionError,
    StatusReport,
    StepOutputs,
    config_error,
)
from estimators.checks import channel_block
from estimators.checks import finite_or_none as _finite_or_none
from estimators.kernels import darr_kernels as kern

NAME = "darr_fekf"
STATE_VERSION = 3

# ----------------------------------------------------------------------------- the model
CHANNELS: tuple[str, ...] = ("w", "f_c", "v", "f_e", "f_h", "v_p", "p_l", "x_v", "u_a")
CHANNEL_UNITS: dict[str, str] = {
    "w": "rad/s",
    "f_c": "N",
    "v": "m/s",
    "f_e": "N",
    "f_h": "N",
    "v_p": "m/s",
    "p_l": "Pa",
    "x_v": "m",
    "u_a": "V",
}
RESIDUALS: tuple[str, ...] = ("r1", "r2", "r3", "r4", "r5", "r6", "r7")
RESIDUAL_UNITS: dict[str, str] = {
    "r1": "V N m / A",
    "r2": "m/s",
    "r3": "N",
    "r4": "N/s",
    "r5": "N/s",
    "r6": "N",
    "r7": "m^3/s",
}
SUBSYSTEM_SENSOR: dict[str, str] = {f"s{i + 1}": ch for i, ch in enumerate(CHANNELS[:7])}

# seed Table 3 (SI units)
NOMINAL: dict[str, float] = {
    "k_q": 2.7,
    "k_c": 1.75e-11,
    "c_hj": 4.59e-14,
    "r_il": 5.0e11,
    "a_h": 1.47e-3,
    "b_h": 1.0e4,
    "m_h": 55.0,
    "k_2": 1.0e8,
    "m_r": 600.0,
    "b_d": 2300.0,
    "f_m": -4.0e-4,
    "f_r": 1.0e4,
    "r_w": 1.5,
    "k_m": 0.2,
    "j_m": 0.0012,
    "s_e": -0.01,
    "lead": 0.00254,
    "k_s": 3.0e8,
    "k_1": 1.0e8,
    "m_screw": 1.0,
    "l_w": 0.0025,
    "k_d": 4.57e5,
}
PARAMETER_NAMES: tuple[str, ...] = tuple(NOMINAL)


class Term(NamedTuple):
    """One term ``coefficient * prod(theta_p ** e_p) * d^order(channel)/dt^order`` of a DARR.

    ``channel`` None is the constant 1.
    """

    coefficient: float
    powers: tuple[tuple[str, int], ...]
    channel: str | None
    order: int


def _t(coefficient: float, params: str, channel: str | None, order: int = 0) -> Term:
    """Term from a space-separated parameter list, ``name`` or ``name^e``."""
    powers: list[tuple[str, int]] = []
    for tok in params.split():
        name, _, exp = tok.partition("^")
        powers.append((name, int(exp) if exp else 1))
    return Term(coefficient, tuple(powers), channel, order)


_TP = 1.0 / (2.0 * math.pi)
DARR_TERMS: dict[str, tuple[Term, ...]] = {
    "r1": (
        _t(1.0, "k_m", "u_a"),
        _t(-1.0, "k_m^2", "w"),
        _t(-1.0, "l_w j_m", "w", 2),
        _t(-1.0, "l_w f_m", "w", 1),
        _t(-_TP, "l_w lead", "f_c", 1),
        _t(1.0, "r_w s_e", None),
        _t(-_TP, "r_w lead", "f_c"),
        _t(-1.0, "j_m r_w", "w", 1),
        _t(-1.0, "f_m r_w", "w"),
    ),
    "r2": (
        _t(_TP, "lead", "w"),
        _t(-1.0, "", "v"),
        _t(-1.0, "k_s^-1", "f_c", 1),
    ),
    "r3": (
        _t(1.0, "", "f_c"),
        _t(-1.0, "", "f_e"),
        _t(-1.0, "f_r", "v"),
        _t(-1.0, "m_screw", "v", 1),
    ),
    "r4": (
        _t(1.0, "", "f_e", 1),
        _t(1.0, "", "f_h", 1),
        _t(-1.0, "m_r", "v", 2),
        _t(1.0, "m_r k_1^-1", "f_e", 3),
        _t(-1.0, "b_d", "v", 1),
        _t(1.0, "b_d k_1^-1", "f_e", 2),
        _t(-1.0, "k_d", "v"),
        _t(1.0, "k_d k_1^-1", "f_e", 1),
    ),
    "r5": (
        _t(1.0, "", "f_e", 1),
        _t(1.0, "", "f_h", 1),
        _t(-1.0, "m_r", "v_p", 2),
        _t(1.0, "m_r k_2^-1", "f_h", 3),
        _t(-1.0, "b_d", "v_p", 1),
        _t(1.0, "b_d k_2^-1", "f_h", 2),
        _t(-1.0, "k_d", "v_p"),
        _t(1.0, "k_d k_2^-1", "f_h", 1),
    ),
    "r6": (
        _t(1.0, "a_h", "p_l"),
        _t(-1.0, "m_h", "v_p", 1),
        _t(-1.0, "b_h", "v_p"),
        _t(-1.0, "", "f_h"),
    ),
    "r7": (
        _t(1.0, "k_q", "x_v"),
        _t(-1.0, "k_c", "p_l"),
        _t(-1.0, "a_h", "v_p"),
        _t(-1.0, "r_il^-1", "p_l"),
        _t(-1.0, "c_hj", "p_l", 1),
    ),
}
MAX_ORDER = kern.MAX_ORDER


def signature_matrix() -> dict[str, tuple[int, ...]]:
    """Fault signature matrix derived from the term tables: parameter -> (7,) 0/1 row, 1 where
    the parameter enters the relation."""
    rows: dict[str, tuple[int, ...]] = {}
    for name in PARAMETER_NAMES:
        rows[name] = tuple(
            int(any(p == name for term in DARR_TERMS[res] for p, _ in term.powers))
            for res in RESIDUALS
        )
    return rows


SIGNATURES: dict[str, tuple[int, ...]] = signature_matrix()

SENSOR_FAULT_KINDS: tuple[str, ...] = ("bias", "drift", "stuck", "noise")
SIGNAL_CHECKED_KINDS: tuple[str, ...] = ("stuck", "noise")  # seen in the sensor's own signal


def sensor_fault_name(channel: str, kind: str) -> str:
    """Name of a sensor fault in candidate sets, e.g. ``"sensor:p_l:bias"``."""
    return f"sensor:{channel}:{kind}"


def sensor_signature_matrix() -> dict[str, tuple[int, ...]]:
    """Fault signature columns of the sensor faults, derived from the term tables.

    A sensor enters a relation through the terms that read its channel, each with a
    derivative order. A constant bias passes only the order-0 terms (derivatives remove it); a
    drift (a ramp) the order-0 and order-1 terms; a stuck sensor or increased noise every term.
    So the F_H bias enters r6 only, although F_H is read by r4, r5 and r6.
    """
    rows: dict[str, tuple[int, ...]] = {}
    max_order = {"bias": 0, "drift": 1, "stuck": MAX_ORDER, "noise": MAX_ORDER}
    for channel in CHANNELS:
        for kind in SENSOR_FAULT_KINDS:
            rows[sensor_fault_name(channel, kind)] = tuple(
                int(
                    any(
                        t.channel == channel and t.order <= max_order[kind] for t in DARR_TERMS[res]
                    )
                )
                for res in RESIDUALS
            )
    return rows


SENSOR_SIGNATURES: dict[str, tuple[int, ...]] = sensor_signature_matrix()
ALL_SIGNATURES: dict[str, tuple[int, ...]] = {**SIGNATURES, **SENSOR_SIGNATURES}


def candidate_sets(
    coherence: Sequence[int],
    set_gains: Sequence[str] = (),
    max_size: int = 3,
    max_count: int | None = None,
    sensor_faults: Sequence[str] = (),
) -> list[list[str]]:
    """Fault sets whose signatures together give exactly the coherence vector.

    A set qualifies when the union (logical OR) of its members' signature rows equals
    ``coherence``; members are detectable parameters not in ``set_gains`` and the sensor
    faults ``sensor_faults`` (names from :func:`sensor_fault_name`) whose signature is within
    the coherence vector. Sets are ordered by size, then by name; single and multiple faults
    up to ``max_size`` members, at most ``max_count`` sets (None: all).
    """
    target = tuple(int(bool(c)) for c in coherence)
    found = _candidate_sets(
        target, tuple(sorted(set_gains)), max_size, max_count, tuple(sorted(sensor_faults))
    )
    return [list(s) for s in found]


@functools.lru_cache(maxsize=256)
def _candidate_sets(
    target: tuple[int, ...],
    set_gains: tuple[str, ...],
    max_size: int,
    max_count: int | None,
    sensor_faults: tuple[str, ...] = (),
) -> tuple[tuple[str, ...], ...]:
    if not any(target):
        return ()
    members = [p for p in PARAMETER_NAMES if p not in set_gains] + list(sensor_faults)
    eligible = sorted(
        name
        for name in members
        if any(ALL_SIGNATURES[name])
        and all(s <= c for s, c in zip(ALL_SIGNATURES[name], target, strict=True))
    )
    masks = {
        name: sum(1 << i for i, s in enumerate(ALL_SIGNATURES[name]) if s) for name in eligible
    }
    goal = sum(1 << i for i, c in enumerate(target) if c)
    found: list[tuple[str, ...]] = []
    for size in range(1, max_size + 1):
        for combo in itertools.combinations(eligible, size):
            union = 0
            for p in combo:
                union |= masks[p]
            if union == goal:
                found.append(combo)
                if max_count is not None and len(found) >= max_count:
                    return tuple(found)
    return tuple(found)


DEFAULT_Q_PARAMETER = 1.0e-4
DEFAULT_P0_PARAMETER = 1.0e-2
DEFAULT_SUBSYSTEMS: dict[str, dict[str, Any]] = {
    "s6": {"state": "v_p", "parameters": ["a_h", "m_h", "b_h"]},
    "s7": {"state": "p_l", "parameters": ["a_h", "r_il", "c_hj"]},
}


# ----------------------------------------------------------------------------- configuration
_Finite = Annotated[float, Field(allow_inf_nan=False)]
_Positive = Annotated[float, Field(gt=0.0, allow_inf_nan=False)]
_NonNegative = Annotated[float, Field(ge=0.0, allow_inf_nan=False)]
_Ratio = Annotated[float, Field(gt=1.0, allow_inf_nan=False)]
ResidualName = Literal["r1", "r2", "r3", "r4", "r5", "r6", "r7"]
ChannelName = Literal["w", "f_c", "v", "f_e", "f_h", "v_p", "p_l", "x_v", "u_a"]
ParameterName = Literal[
    "k_q", "k_c", "c_hj", "r_il", "a_h", "b_h", "m_h", "k_2", "m_r", "b_d", "f_m",
    "f_r", "r_w", "k_m", "j_m", "s_e", "lead", "k_s", "k_1", "m_screw", "l_w", "k_d",
]  # fmt: skip


class ResidualValues(EstimatorConfigModel):
    """One positive number per residual, in the residual's unit (``RESIDUAL_UNITS``)."""

    r1: _Positive = Field(description="r1, V N m / A")
    r2: _Positive = Field(description="r2, m/s")
    r3: _Positive = Field(description="r3, N")
    r4: _Positive = Field(description="r4, N/s")
    r5: _Positive = Field(description="r5, N/s")
    r6: _Positive = Field(description="r6, N")
    r7: _Positive = Field(description="r7, m^3/s")

    def as_tuple(self) -> tuple[float, ...]:
        """The seven values in residual order."""
        return (self.r1, self.r2, self.r3, self.r4, self.r5, self.r6, self.r7)


class ChannelValues(EstimatorConfigModel):
    """An optional non-negative number per model channel, in the channel's unit."""

    w: _NonNegative | None = Field(None, description="rad/s")
    f_c: _NonNegative | None = Field(None, description="N")
    v: _NonNegative | None = Field(None, description="m/s")
    f_e: _NonNegative | None = Field(None, description="N")
    f_h: _NonNegative | None = Field(None, description="N")
    v_p: _NonNegative | None = Field(None, description="m/s")
    p_l: _NonNegative | None = Field(None, description="Pa")
    x_v: _NonNegative | None = Field(None, description="m")
    u_a: _NonNegative | None = Field(None, description="V")

    @model_validator(mode="before")
    @classmethod
    def _auto_is_none(cls, data: Any) -> Any:
        """``"auto"`` (calibrated) is the same as leaving the channel out."""
        if isinstance(data, Mapping):
            return {k: (None if v == "auto" else v) for k, v in data.items()}
        return data

    def as_dict(self) -> dict[str, float]:
        """The channels given, by name."""
        return {c: float(v) for c in CHANNELS if (v := getattr(self, c)) is not None}


class ReferenceModel(EstimatorConfigModel):
    """A fault-free reference run's levels (copy them from that run's diagnosis,
    ``detail["calibration"]["reference"]``)."""

    thresholds: ResidualValues = Field(
        description="thresholds used when this stream's calibration is refused"
    )
    residual_rms: ResidualValues = Field(
        description="robust rms of each residual on the reference run; the calibration window "
        "is compared with it instead of the model's expected level"
    )
    noise_std: ChannelValues = Field(
        default_factory=lambda: ChannelValues.model_validate({}),
        description="measurement noise sd by channel on the reference run; a calibration window "
        "noisier than noise_ratio times its variance is refused",
    )


class ThresholdsModel(EstimatorConfigModel):
    """Residual thresholds and the checks of the calibration window."""

    rule: Literal["fixed", "max", "max_margin", "quantile"] = Field(
        "max_margin",
        description="fixed (values), or calibrated on the first window_s of stream time: max "
        "(largest |r|, the seed's rule), max_margin (margin x largest |r|), quantile (margin x "
        "the q quantile of |r|); calibrated statistics exclude outlying segments",
    )
    window_s: _NonNegative = Field(3.0, description="calibration window, s of stream time")
    margin: _Positive = Field(2.0, description="factor on the calibrated statistic")
    q: float = Field(0.999, gt=0.0, lt=1.0, description="quantile level (rule quantile)")
    values: tuple[_Positive, ...] | None = Field(
        None, description="seven thresholds r1..r7 (rule fixed), list or object by residual"
    )
    segments: int = Field(
        6, ge=2, le=kern.MAX_SEGMENTS, strict=True, description="segments of the calibration window"
    )
    segment_outlier_ratio: _Ratio = Field(
        2.0,
        description="a segment whose residual rms exceeds this times the median segment rms is "
        "excluded from the threshold statistic (calibration suspicious)",
    )
    segment_peak_ratio: _Ratio = Field(
        7.0,
        description="a segment whose largest |r| exceeds this times the median segment rms is "
        "excluded (calibration suspicious)",
    )
    suspicious_ratio: _Ratio = Field(
        1.5,
        description="median segment rms over the expected (or reference) rms above which the "
        "calibration is suspicious",
    )
    refuse_ratio: _Ratio = Field(
        3.0,
        description="median segment rms over the expected (or reference) rms above which the "
        "calibration is refused",
    )
    fallback_sigmas: _Positive = Field(
        7.0,
        description="thresholds after a refused calibration without reference: this times the "
        "residual sd expected from the channels' noise",
    )
    reference: ReferenceModel | None = Field(
        None, description="levels of a fault-free reference run (see docs, section 4)"
    )

    @model_validator(mode="before")
    @classmethod
    def _rule_from_values(cls, data: Any) -> Any:
        if isinstance(data, Mapping) and "values" in data and "rule" not in data:
            return {**data, "rule": "fixed"}
        return data

    @field_validator("values", mode="before")
    @classmethod
    def _values_by_name(cls, value: Any) -> Any:
        if isinstance(value, Mapping):
            if set(value) != set(RESIDUALS):
                raise ValueError("give all seven thresholds r1..r7")
            return [value[r] for r in RESIDUALS]
        return value

    @field_validator("values")
    @classmethod
    def _seven(cls, value: tuple[float, ...] | None) -> tuple[float, ...] | None:
        if value is not None and len(value) != len(RESIDUALS):
            raise ValueError("expected seven numbers (r1..r7)")
        return value

    @model_validator(mode="after")
    def _consistent(self) -> ThresholdsModel:
        if self.rule == "fixed" and self.values is None:
            raise ValueError("values: rule fixed needs the seven values")
        if self.rule != "fixed" and self.values is not None:
            raise ValueError("values: only with rule fixed")
        if self.refuse_ratio < self.suspicious_ratio:
            raise ValueError("refuse_ratio: must be >= suspicious_ratio")
        return self


class FuzzyModel(EstimatorConfigModel):
    """Settings of the fuzzy adaptive factor (seed eqs. 38-44)."""

    c: _Positive = Field(1.5, description="robust constant of eq. 41 (seed: 1.0 to 1.5)")
    window_s: _Positive = Field(
        0.05, description="time constant of the innovation variance estimate (eq. 38), s"
    )
    input_levels: tuple[_Finite, _Finite, _Finite] = Field(
        (1.0, 2.0, 3.0),
        description="levels of the input sets ZO, PS, PB on the variance-factor ratio",
    )
    output_levels: tuple[_Finite, _Finite, _Finite] = Field(
        (0.0, 0.5, 1.0), description="alpha of the output sets ZO, PS, PB, each in [0, 1]"
    )
    alpha_min: float = Field(0.05, gt=0.0, le=1.0, description="floor of alpha")

    @field_validator("input_levels")
    @classmethod
    def _increasing(cls, v: tuple[float, float, float]) -> tuple[float, float, float]:
        if not v[0] < v[1] < v[2]:
            raise ValueError("levels must be strictly increasing")
        return v

    @field_validator("output_levels")
    @classmethod
    def _unit(cls, v: tuple[float, float, float]) -> tuple[float, float, float]:
        if not all(0.0 <= x <= 1.0 for x in v):
            raise ValueError("alpha levels must lie in [0, 1]")
        return v


class SubsystemModel(EstimatorConfigModel):
    """A subsystem estimator on the subsystem's DARR (section 6 of the method notes)."""

    state: ChannelName | None = Field(
        None, description="state channel of the state form (default: the subsystem's sensor)"
    )
    parameters: tuple[ParameterName, ...] = Field(
        min_length=1, max_length=kern.MAX_PARAMS, description="parameters of the relation"
    )
    estimator: Literal["ekf", "fekf"] = Field("fekf", description="EKF or fuzzy adaptive EKF")
    measurement: Literal["relation", "state"] = Field(
        "relation",
        description="relation: the relation is a pseudo-measurement of zero; state: the seed's "
        "form (first-order relations only: s2, s3, s6, s7)",
    )
    r: _Positive | Literal["auto"] = Field(
        "auto", description="measurement variance (channel or relation unit squared) or auto"
    )
    q_state: _Positive | Literal["auto"] = Field(
        "auto", description="state process noise variance per sample (state form) or auto"
    )
    p0_state: _Positive | Literal["auto"] = Field(
        "auto", description="initial state variance (state form) or auto (= r)"
    )
    q_parameters: _Positive | dict[str, _Positive] = Field(
        DEFAULT_Q_PARAMETER,
        description="relative random-walk variance rate, 1/s (number, or object by parameter)",
    )
    p0_parameters: _Positive | dict[str, _Positive] = Field(
        DEFAULT_P0_PARAMETER,
        description="initial relative variance (number, or object by parameter)",
    )
    fuzzy: FuzzyModel = Field(
        default_factory=lambda: FuzzyModel.model_validate({}), description="FEKF settings"
    )
    bounds: tuple[_Positive, _Positive] = Field(
        (1.0e-3, 1.0e3), description="parameter limits relative to nominal, low < 1 < high"
    )

    @field_validator("bounds")
    @classmethod
    def _around_one(cls, v: tuple[float, float]) -> tuple[float, float]:
        if not v[0] < 1.0 < v[1]:
            raise ValueError("expected low < 1 < high (relative to nominal)")
        return v

    @model_validator(mode="after")
    def _own_parameters(self) -> SubsystemModel:
        if len(set(self.parameters)) != len(self.parameters):
            raise ValueError("parameters: a parameter is listed twice")
        for name in ("q_parameters", "p0_parameters"):
            value = getattr(self, name)
            if isinstance(value, dict):
                for p in value:
                    if p not in self.parameters:
                        raise ValueError(f"{name}.{p}: not an estimated parameter")
        return self

    def per_parameter(self, name: str, default: float) -> tuple[float, ...]:
        """``q_parameters`` or ``p0_parameters`` as one number per estimated parameter."""
        value = getattr(self, name)
        if isinstance(value, dict):
            return tuple(float(value.get(p, default)) for p in self.parameters)
        return tuple(float(value) for _ in self.parameters)


def _check_subsystem(key: str, sub: SubsystemModel | None) -> SubsystemModel | None:
    """Parameters in the subsystem's relation; the state form only on first-order relations."""
    if sub is None:
        return None
    res = "r" + key[1:]
    in_relation = sorted({p for t in DARR_TERMS[res] for p, _ in t.powers})
    for p in sub.parameters:
        if p not in in_relation:
            raise ValueError(f"parameters: {p!r} is not in {res} (it has {', '.join(in_relation)})")
    state = sub.state or SUBSYSTEM_SENSOR[key]
    if sub.measurement == "state":
        terms = DARR_TERMS[res]
        if not any(t.channel == state and t.order == 1 for t in terms):
            raise ValueError(f"state: {state!r} has no first derivative in {res}")
        for term in terms:
            if term.channel == state and term.order > 1:
                raise ValueError(
                    f"state: {res} holds a derivative of order {term.order} of {state!r}; "
                    "only first-order relations can be integrated"
                )
            if term.channel not in (None, state) and term.order > 0:
                raise ValueError(
                    f"state: {res} holds a derivative of {term.channel!r}; only the state may "
                    "be derived"
                )
    return sub.model_copy(update={"state": state})


class SubsystemsModel(EstimatorConfigModel):
    """Subsystem estimators by subsystem (``s1``..``s7``); default s6 and s7."""

    s1: SubsystemModel | None = Field(None, description="motor circuit (r1)")
    s2: SubsystemModel | None = Field(None, description="screw stiffness (r2)")
    s3: SubsystemModel | None = Field(None, description="screw mass (r3)")
    s4: SubsystemModel | None = Field(None, description="surface via the EMA (r4)")
    s5: SubsystemModel | None = Field(None, description="surface via the SHA (r5)")
    s6: SubsystemModel | None = Field(None, description="piston (r6)")
    s7: SubsystemModel | None = Field(None, description="cylinder (r7)")

    @field_validator("s1", "s2", "s3", "s4", "s5", "s6", "s7")
    @classmethod
    def _relation(cls, v: SubsystemModel | None, info: ValidationInfo) -> SubsystemModel | None:
        return _check_subsystem(str(info.field_name), v)

    def items(self) -> list[tuple[str, SubsystemModel]]:
        """Configured subsystems in order."""
        return [(k, v) for k in SUBSYSTEM_SENSOR if (v := getattr(self, k)) is not None]


class ChannelsModel(EstimatorConfigModel):
    """Stream channel name of each model channel (default: the same name)."""

    w: str = Field("w", min_length=1, description="motor speed, rad/s")
    f_c: str = Field("f_c", min_length=1, description="screw force, N")
    v: str = Field("v", min_length=1, description="screw velocity, m/s")
    f_e: str = Field("f_e", min_length=1, description="EMA output force, N")
    f_h: str = Field("f_h", min_length=1, description="SHA output force, N")
    v_p: str = Field("v_p", min_length=1, description="piston velocity, m/s")
    p_l: str = Field("p_l", min_length=1, description="load pressure, Pa")
    x_v: str = Field("x_v", min_length=1, description="valve spool position, m")
    u_a: str = Field("u_a", min_length=1, description="motor voltage, V")

    @model_validator(mode="after")
    def _distinct(self) -> ChannelsModel:
        if len({getattr(self, c) for c in CHANNELS}) != len(CHANNELS):
            raise ValueError("two model channels map to the same stream channel")
        return self


class ParametersModel(EstimatorConfigModel):
    """Nominal model parameters, SI units (seed Table 3)."""

    k_q: _Finite = Field(NOMINAL["k_q"], description="valve flow gain K_q, m^2/s")
    k_c: _Finite = Field(NOMINAL["k_c"], description="flow-pressure coefficient, m^3/(s Pa)")
    c_hj: _Positive = Field(NOMINAL["c_hj"], description="hydraulic capacitance, m^3/Pa")
    r_il: _Positive = Field(NOMINAL["r_il"], description="leakage resistance, Pa s/m^3")
    a_h: _Finite = Field(NOMINAL["a_h"], description="piston area, m^2")
    b_h: _Finite = Field(NOMINAL["b_h"], description="piston damping, N s/m")
    m_h: _Positive = Field(NOMINAL["m_h"], description="piston mass, kg")
    k_2: _Positive = Field(NOMINAL["k_2"], description="piston rod stiffness, N/m")
    m_r: _Positive = Field(NOMINAL["m_r"], description="surface mass, kg")
    b_d: _Finite = Field(NOMINAL["b_d"], description="surface damping, N s/m")
    f_m: _Finite = Field(NOMINAL["f_m"], description="motor bearing friction, N m s/rad")
    f_r: _Finite = Field(NOMINAL["f_r"], description="screw viscous friction, N s/m")
    r_w: _Finite = Field(NOMINAL["r_w"], description="motor resistance, ohm")
    k_m: _Finite = Field(NOMINAL["k_m"], description="motor torque constant, N m/A")
    j_m: _Positive = Field(NOMINAL["j_m"], description="motor inertia, kg m^2")
    s_e: _Finite = Field(NOMINAL["s_e"], description="motor starting friction, N m")
    lead: _Finite = Field(NOMINAL["lead"], description="screw lead, m")
    k_s: _Positive = Field(NOMINAL["k_s"], description="screw stiffness, N/m")
    k_1: _Positive = Field(NOMINAL["k_1"], description="screw attachment stiffness, N/m")
    m_screw: _Positive = Field(NOMINAL["m_screw"], description="screw mass, kg")
    l_w: _Positive = Field(NOMINAL["l_w"], description="motor inductance, H")
    k_d: _Finite = Field(NOMINAL["k_d"], description="surface load stiffness, N/m")


class SensorChecksModel(EstimatorConfigModel):
    """Checks of each sensor's own signal (stuck, increased noise), section 5 of the notes."""

    enabled: bool = Field(True, description="run the stuck and noise checks")
    stuck_s: _Positive = Field(
        0.1, description="a sensor whose raw value does not change for this long is stuck, s"
    )
    noise_window_s: _Positive = Field(
        0.2, description="time constant of the running noise variance, s"
    )
    noise_persist_s: _Positive = Field(
        1.0,
        description="time the running noise variance must stay over the level before a sensor "
        "is flagged noisy, s (a plant transient raises it for a while)",
    )
    noise_ratio: _Ratio = Field(
        2.5,
        description="running over calibrated noise variance above which a sensor is noisy "
        "(also: calibration noise over reference noise above which calibration is refused)",
    )
    white_noise_ratio: _Ratio = Field(
        1.7,
        description="lower level of the same ratio that applies while the extra noise is white "
        "(see white_noise_correlation); at most noise_ratio",
    )
    white_noise_correlation: float = Field(
        -0.68,
        ge=-0.75,
        le=1.0,
        description="the running lag-1 autocorrelation of the third differences below which "
        "the noise counts as white (white noise: -0.75; a plant resonance at w: about "
        "cos(w dt))",
    )

    @model_validator(mode="after")
    def _levels(self) -> SensorChecksModel:
        if self.white_noise_ratio > self.noise_ratio:
            raise ValueError("white_noise_ratio: must not exceed noise_ratio")
        return self


class IsolationModel(EstimatorConfigModel):
    """The fit that tells sensor from parameter faults among the candidate sets."""

    @model_validator(mode="after")
    def _window(self) -> IsolationModel:
        if self.min_fit_s >= self.window_s:
            raise ValueError("min_fit_s: must be shorter than window_s")
        return self

    fit_decimation: int = Field(
        10, ge=1, le=10_000, strict=True, description="one fit sample in this many stream samples"
    )
    min_fit_s: _Positive = Field(
        0.3, description="fault time before the fit decides between the candidate sets, s"
    )
    window_s: _Positive = Field(
        2.0,
        description="time constant of the fit's exponential forgetting, s: the fit describes "
        "about the last window_s of the fault",
    )
    consistency_ratio: _Ratio = Field(
        1.5,
        description="a candidate set is consistent when its mean squared standardized "
        "residual after the fit is within this factor of the best set's",
    )
    consistency_share: float = Field(
        0.03,
        ge=0.0,
        lt=1.0,
        description="... or within this share of the fault's mean squared residual (no-fault "
        "fit minus best) above the best: a larger set must explain a noticeable part of the "
        "fault, not only the model's small misfit of a large fault",
    )
    consistency_floor: _Positive = Field(
        1.5,
        description="... or below this mean squared standardized residual (1: noise only)",
    )


class DarrFekfConfigModel(EstimatorConfigModel):
    """Configuration of the darr_fekf estimator (``docs/methods-darr-fekf.md``, section 9)."""

    channels: ChannelsModel = Field(
        default_factory=lambda: ChannelsModel.model_validate({}),
        description="model channel -> stream channel name (default: the sha_ema kind's names)",
    )
    sample_period_s: _Positive = Field(1.0e-4, description="nominal sample period, s")
    parameters: ParametersModel = Field(
        default_factory=lambda: ParametersModel.model_validate({}),
        description="nominal model parameters, SI units (default: the seed's Table 1 values)",
    )
    differentiator_window_s: _Positive = Field(
        0.05, description="smoother span, s (the residuals' lag is half of it)"
    )
    max_missing_fraction: float = Field(
        0.1, ge=0.0, lt=1.0, description="most held (missing) samples in a window"
    )
    thresholds: ThresholdsModel = Field(
        default_factory=lambda: ThresholdsModel.model_validate({}),
        description="residual thresholds: fixed, calibrated (checked) or from a reference run",
    )
    min_duration_s: _NonNegative = Field(
        0.002, description="time above threshold before a residual counts, s"
    )
    clear_after_s: _Positive = Field(1.0, description="time all below before a clearance, s")
    set_gains: tuple[ParameterName, ...] = Field(
        ("k_q", "k_c"), description="parameters known to be right (not in candidate sets)"
    )
    noise_std: ChannelValues = Field(
        default_factory=lambda: ChannelValues.model_validate({}),
        description="known noise sd by channel (else calibrated)",
    )
    max_candidate_size: int = Field(3, ge=1, le=6, strict=True, description="largest set")
    max_candidates: int = Field(100, ge=1, le=10_000, strict=True, description="most sets")
    subsystems: SubsystemsModel = Field(
        default_factory=lambda: SubsystemsModel.model_validate(DEFAULT_SUBSYSTEMS),
        description="subsystem estimators (EKF or FEKF) run on implicated subsystems",
    )
    health_window_samples: int = Field(
        10_000, ge=1, le=100_000_000, strict=True, description="health window, samples"
    )
    sensors: SensorChecksModel = Field(
        default_factory=lambda: SensorChecksModel.model_validate({}),
        description="stuck and noisy sensor checks on each channel",
    )
    isolation: IsolationModel = Field(
        default_factory=lambda: IsolationModel.model_validate({}),
        description="the residual-shape fit that tells sensor from parameter faults",
    )

    @model_validator(mode="after")
    def _calibration_window(self) -> DarrFekfConfigModel:
        needs_noise = any(
            s.r == "auto" or (s.measurement == "state" and s.q_state == "auto")
            for _, s in self.subsystems.items()
        )
        if self.thresholds.window_s <= 0.0 and (self.thresholds.rule != "fixed" or needs_noise):
            raise ValueError(
                'thresholds.window_s: a calibration window is needed (calibrated thresholds or "auto" noise)'
            )
        return self


CONFIG_MODEL = DarrFekfConfigModel


@dataclass(frozen=True)
class SubsystemConfig:
    """A subsystem estimator, as the kernel compiler reads it (built from
    :class:`SubsystemModel`; field meanings there)."""

    state: str
    parameters: tuple[str, ...]
    estimator: Literal["ekf", "fekf"] = "fekf"
    measurement: Literal["relation", "state"] = "relation"
    r: float | Literal["auto"] = "auto"
    q_state: float | Literal["auto"] = "auto"
    p0_state: float | Literal["auto"] = "auto"
    q_parameters: tuple[float, ...] = ()
    p0_parameters: tuple[float, ...] = ()
    fuzzy: FuzzyModel = field(default_factory=lambda: FuzzyModel.model_validate({}))
    bounds: tuple[float, float] = (1.0e-3, 1.0e3)


class _Compiled(NamedTuple):
    """Flat arrays of a configuration for the compiled kernel."""

    cfg: FloatArray
    w0: FloatArray
    chan_order: kern.IntArray
    term_res: kern.IntArray
    term_chan: kern.IntArray
    term_order: kern.IntArray
    term_coef: FloatArray
    res_chan: kern.IntArray
    sub_cfg: FloatArray
    sub_kind: kern.IntArray
    sub_chan: kern.IntArray
    sub_order: kern.IntArray
    sub_coef: FloatArray
    sub_exp: FloatArray
    sub_fuse: kern.IntArray
    res_gain2: FloatArray
    term_fit: FloatArray
    sub_reads: FloatArray
    n_window: int
    box: int
    n_hist: int
    cal_capacity: int
    fused: tuple[str, ...]


@dataclass(frozen=True)
class DarrFekfConfig:
    """Validated configuration (build it with :func:`parse_config`); the public form is
    :class:`DarrFekfConfigModel` (``model``), this is what the estimator reads.

    Attributes:
        model: the validated public configuration.
        channels: model channel -> stream channel name.
        sample_period_s: nominal sample period of the stream (the differentiator assumes it).
        parameters: nominal model parameters (SI units).
        differentiator_window_s: length of the smoothing differentiator's window.
        max_missing_fraction: largest fraction of missing samples in a window for which a
            residual is still computed (missing samples hold the last valid value).
        thresholds: residual thresholds and calibration checks.
        min_duration_s: time a residual must stay above its threshold to count as exceeded.
        clear_after_s: time every residual must stay below its threshold to clear a fault.
        set_gains: parameters known to be right (excluded from candidate sets).
        noise_std: known measurement noise standard deviation by model channel.
        max_candidate_size: largest candidate fault set.
        max_candidates: most candidate sets reported.
        subsystems: estimators by subsystem name (``"s1"``..``"s7"``).
        health_window_samples: length of a health window, stream samples.
        sensors: sensor self-checks.
        isolation: the sensor-or-parameter fit.
    """

    model: DarrFekfConfigModel = field(compare=False, hash=False, repr=False)
    channels: dict[str, str] = field(hash=False)
    sample_period_s: float
    parameters: dict[str, float] = field(hash=False)
    differentiator_window_s: float
    max_missing_fraction: float
    thresholds: ThresholdsModel
    min_duration_s: float
    clear_after_s: float
    set_gains: tuple[str, ...]
    noise_std: dict[str, float] = field(hash=False)
    max_candidate_size: int
    max_candidates: int
    subsystems: dict[str, SubsystemConfig] = field(hash=False)
    health_window_samples: int
    sensors: SensorChecksModel
    isolation: IsolationModel
    compiled: _Compiled = field(init=False, repr=False, compare=False, hash=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "compiled", _compile(self))

    @property
    def n_window(self) -> int:
        """Samples in the differentiator's window (odd)."""
        return self.compiled.n_window

    @property
    def lag_s(self) -> float:
        """Lag of the residuals: they describe the time half a window before each sample."""
        return 0.5 * (self.n_window - 1) * self.sample_period_s


def _subsystem_config(sub: SubsystemModel) -> SubsystemConfig:
    assert sub.state is not None  # filled in by _check_subsystem
    return SubsystemConfig(
        state=sub.state,
        parameters=tuple(sub.parameters),
        estimator=sub.estimator,
        measurement=sub.measurement,
        r=sub.r,
        q_state=sub.q_state,
        p0_state=sub.p0_state,
        q_parameters=sub.per_parameter("q_parameters", DEFAULT_Q_PARAMETER),
        p0_parameters=sub.per_parameter("p0_parameters", DEFAULT_P0_PARAMETER),
        fuzzy=sub.fuzzy,
        bounds=sub.bounds,
    )


def parse_config(raw: Mapping[str, Any]) -> DarrFekfConfig:
    """Validate a JSON-like mapping (:data:`CONFIG_MODEL`) into a :class:`DarrFekfConfig`.

    Raises:
        ConfigError: naming each bad field (unknown keys, wrong types, out-of-range values, a
            subsystem whose relation cannot be integrated or whose parameters are not in it,
            "auto" noise with no calibration window, a window too short for the derivatives).
    """
    try:
        model = CONFIG_MODEL.model_validate(raw)
    except ValidationError as exc:
        raise config_error(NAME, exc) from None
    try:
        return DarrFekfConfig(
            model=model,
            channels={c: getattr(model.channels, c) for c in CHANNELS},
            sample_period_s=model.sample_period_s,
            parameters={p: float(getattr(model.parameters, p)) for p in PARAMETER_NAMES},
            differentiator_window_s=model.differentiator_window_s,
            max_missing_fraction=model.max_missing_fraction,
            thresholds=model.thresholds,
            min_duration_s=model.min_duration_s,
            clear_after_s=model.clear_after_s,
            set_gains=tuple(model.set_gains),
            noise_std=model.noise_std.as_dict(),
            max_candidate_size=model.max_candidate_size,
            max_candidates=model.max_candidates,
            subsystems={k: _subsystem_config(s) for k, s in model.subsystems.items()},
            health_window_samples=model.health_window_samples,
            sensors=model.sensors,
            isolation=model.isolation,
        )
    except ValueError as exc:  # from _compile: a window too short for the derivative order
        raise ConfigError(f"{NAME}: differentiator_window_s: {exc}") from exc


def config_to_dict(config: DarrFekfConfig) -> dict[str, Any]:
    """The full configuration with defaults filled in, JSON-serializable."""
    return config.model.model_dump(mode="json")


def required_channels(config: DarrFekfConfig) -> tuple[str, ...]:
    """The nine stream channels (seven sensors and the inputs x_v and U_a)."""
    return tuple(config.channels[c] for c in CHANNELS)


# ----------------------------------------------------------------------------- compilation
def _monomial(term: Term, params: Mapping[str, float]) -> float:
    """Coefficient of ``term`` at the parameters ``params``."""
    value = term.coefficient
    for name, exp in term.powers:
        value *= params[name] ** exp
    return value


def _compile_subsystem(
    sub: SubsystemConfig, key: str, params: Mapping[str, float], sample_period: float
) -> tuple[FloatArray, list[int], list[int], list[int], list[float], FloatArray]:
    """Configuration row and term table (kinds, channels, orders, coefficients at the nominal
    parameters, exponents of the estimated parameters) of one subsystem filter."""
    terms = DARR_TERMS["r" + key[1:]]
    relation = sub.measurement == "relation"
    kinds: list[int] = []
    chans: list[int] = []
    orders: list[int] = []
    coefs: list[float] = []
    exps = np.zeros((len(terms), kern.MAX_PARAMS))
    for j, term in enumerate(terms):
        chans.append(-1 if term.channel is None else CHANNELS.index(term.channel))
        orders.append(term.order)
        if term.channel is None:
            kinds.append(kern.TK_CONST)
        elif term.channel == sub.state and not relation:
            kinds.append(kern.TK_STATE_DOT if term.order == 1 else kern.TK_STATE)
        else:
            kinds.append(kern.TK_INPUT)
        coefs.append(_monomial(term, params))
        for name, exp in term.powers:
            if name in sub.parameters:
                exps[j, sub.parameters.index(name)] += exp
    row = np.zeros(kern.SC_LEN)
    row[kern.SC_RES] = int(key[1:]) - 1
    row[kern.SC_STATE_CHAN] = CHANNELS.index(sub.state)
    row[kern.SC_N_PARAMS] = len(sub.parameters)
    row[kern.SC_FEKF] = 1.0 if sub.estimator == "fekf" else 0.0
    row[kern.SC_N_TERMS] = len(terms)
    row[kern.SC_R] = np.nan if sub.r == "auto" else sub.r
    row[kern.SC_Q_STATE] = np.nan if sub.q_state == "auto" else sub.q_state
    row[kern.SC_P0_STATE] = np.nan if sub.p0_state == "auto" else sub.p0_state
    row[kern.SC_C] = sub.fuzzy.c
    row[kern.SC_LAMBDA] = math.exp(-sample_period / sub.fuzzy.window_s)
    row[kern.SC_WINDOW] = sub.fuzzy.window_s
    row[kern.SC_ALPHA_MIN] = sub.fuzzy.alpha_min
    row[kern.SC_LEVEL_IN : kern.SC_LEVEL_IN + 3] = sub.fuzzy.input_levels
    row[kern.SC_LEVEL_OUT : kern.SC_LEVEL_OUT + 3] = sub.fuzzy.output_levels
    row[kern.SC_RHO_MIN] = sub.bounds[0]
    row[kern.SC_RHO_MAX] = sub.bounds[1]
    row[kern.SC_RELATION] = 1.0 if relation else 0.0
    needs = sub.r == "auto" or (not relation and sub.q_state == "auto")
    row[kern.SC_NEEDS_CAL] = 1.0 if needs else 0.0
    n_par = len(sub.parameters)
    row[kern.SC_Q_PARAM : kern.SC_Q_PARAM + n_par] = sub.q_parameters
    row[kern.SC_P0_PARAM : kern.SC_P0_PARAM + n_par] = sub.p0_parameters
    row[kern.SC_NOMINAL : kern.SC_NOMINAL + n_par] = [params[p] for p in sub.parameters]
    return row, kinds, chans, orders, coefs, exps


def _compile(config: DarrFekfConfig) -> _Compiled:
    """Flat kernel arrays of a configuration (built once per configuration)."""
    box = kern.box_length(config.differentiator_window_s, config.sample_period_s)
    n_window = kern.N_STAGES * (box - 1) + 1
    w0 = kern.smoother_weights(box, config.sample_period_s, 0)[0]
    chan_order = np.zeros(len(CHANNELS), dtype=np.int64)
    for terms in DARR_TERMS.values():
        for t in terms:
            if t.channel is not None:
                c = CHANNELS.index(t.channel)
                chan_order[c] = max(chan_order[c], t.order)
    term_res, term_chan, term_order, term_coef = [], [], [], []
    res_chan = np.zeros((kern.N_RES, kern.N_CHAN), dtype=np.int64)
    for l_idx, res in enumerate(RESIDUALS):
        for term in DARR_TERMS[res]:
            term_res.append(l_idx)
            term_order.append(term.order)
            if term.channel is None:
                term_chan.append(-1)
            else:
                c = CHANNELS.index(term.channel)
                term_chan.append(c)
                res_chan[l_idx, c] = 1
            term_coef.append(_monomial(term, config.parameters))
    thr = config.thresholds
    rule = {
        "fixed": kern.RULE_FIXED,
        "max": kern.RULE_MAX,
        "max_margin": kern.RULE_MAX_MARGIN,
        "quantile": kern.RULE_QUANTILE,
    }[thr.rule]
    cal_capacity = (
        int(math.ceil(thr.window_s / config.sample_period_s * 1.25)) + 16
        if thr.rule == "quantile"
        else 0
    )
    keys = list(config.subsystems)
    n_sub = len(keys)
    max_terms = max((len(DARR_TERMS["r" + k[1:]]) for k in keys), default=1)
    sub_cfg = np.zeros((n_sub, kern.SC_LEN))
    sub_kind = np.zeros((n_sub, max_terms), dtype=np.int64)
    sub_chan = np.zeros((n_sub, max_terms), dtype=np.int64)
    sub_order = np.zeros((n_sub, max_terms), dtype=np.int64)
    sub_coef = np.zeros((n_sub, max_terms))
    sub_exp = np.zeros((n_sub, max_terms, kern.MAX_PARAMS))
    sub_fuse = np.full((n_sub, kern.MAX_PARAMS), -1, dtype=np.int64)
    fused: list[str] = []
    for i, key in enumerate(keys):
        sub = config.subsystems[key]
        row, kinds, chans, orders, coefs, exps = _compile_subsystem(
            sub, key, config.parameters, config.sample_period_s
        )
        sub_cfg[i] = row
        m = len(kinds)
        sub_kind[i, :m] = kinds
        sub_chan[i, :m] = chans
        sub_order[i, :m] = orders
        sub_coef[i, :m] = coefs
        sub_exp[i, :m] = exps
        for p_idx, p in enumerate(sub.parameters):
            if p not in fused:
                fused.append(p)
            sub_fuse[i, p_idx] = fused.index(p)
    cfg = np.zeros(kern.CFG_LEN)
    cfg[kern.CFG_DT] = config.sample_period_s
    cfg[kern.CFG_N_WIN] = n_window
    cfg[kern.CFG_MAX_MISSING] = math.floor(config.max_missing_fraction * n_window)
    cfg[kern.CFG_CAL_S] = thr.window_s
    cfg[kern.CFG_RULE] = rule
    cfg[kern.CFG_MARGIN] = thr.margin
    cfg[kern.CFG_Q] = thr.q
    cfg[kern.CFG_MIN_DUR] = max(1, round(config.min_duration_s / config.sample_period_s))
    cfg[kern.CFG_CLEAR] = max(1, round(config.clear_after_s / config.sample_period_s))
    cfg[kern.CFG_HEALTH_N] = config.health_window_samples
    cfg[kern.CFG_N_SUB] = n_sub
    cfg[kern.CFG_BOX] = box
    cfg[kern.CFG_N_SEG] = thr.segments
    cfg[kern.CFG_SEG_OUTLIER] = thr.segment_outlier_ratio
    cfg[kern.CFG_PEAK_RATIO] = thr.segment_peak_ratio
    cfg[kern.CFG_SUSPICIOUS] = thr.suspicious_ratio
    cfg[kern.CFG_REFUSE] = thr.refuse_ratio
    cfg[kern.CFG_FALLBACK_SIGMAS] = thr.fallback_sigmas
    cfg[kern.CFG_REF_NOISE : kern.CFG_REF_NOISE + kern.N_CHAN] = np.nan
    if thr.reference is not None:
        cfg[kern.CFG_HAS_REF] = 1.0
        cfg[kern.CFG_REF_THR : kern.CFG_REF_THR + kern.N_RES] = thr.reference.thresholds.as_tuple()
        cfg[kern.CFG_REF_RMS : kern.CFG_REF_RMS + kern.N_RES] = (
            thr.reference.residual_rms.as_tuple()
        )
        ref_noise = thr.reference.noise_std.as_dict()
        for c_idx, name in enumerate(CHANNELS):
            if name in ref_noise:
                cfg[kern.CFG_REF_NOISE + c_idx] = ref_noise[name] ** 2
    sens = config.sensors
    cfg[kern.CFG_SENSOR_LAMBDA] = math.exp(-config.sample_period_s / sens.noise_window_s)
    cfg[kern.CFG_STUCK_N] = (
        max(2, round(sens.stuck_s / config.sample_period_s)) if sens.enabled else math.inf
    )
    cfg[kern.CFG_NOISE_RATIO] = sens.noise_ratio if sens.enabled else math.inf
    cfg[kern.CFG_SENSOR_MIN_N] = 3.0 * sens.noise_window_s / config.sample_period_s
    cfg[kern.CFG_NOISE_PERSIST] = max(1, round(sens.noise_persist_s / config.sample_period_s))
    cfg[kern.CFG_WHITE_RATIO] = sens.white_noise_ratio if sens.enabled else math.inf
    cfg[kern.CFG_WHITE_LEVEL] = sens.white_noise_correlation
    cfg[kern.CFG_FIT_DEC] = config.isolation.fit_decimation
    cfg[kern.CFG_FIT_LAMBDA] = math.exp(
        -config.isolation.fit_decimation * config.sample_period_s / config.isolation.window_s
    )
    # expected residual variance per unit channel noise variance: squared norm of the FIR
    # weights each residual puts on each channel (its terms' derivative filters, summed)
    weights = kern.smoother_weights(box, config.sample_period_s, kern.MAX_ORDER)
    res_gain2 = np.zeros((kern.N_RES, kern.N_CHAN))
    for l_idx, res in enumerate(RESIDUALS):
        for c_idx, name in enumerate(CHANNELS):
            g = np.zeros(weights.shape[1])
            for term in DARR_TERMS[res]:
                if term.channel == name:
                    g += _monomial(term, config.parameters) * weights[term.order]
            res_gain2[l_idx, c_idx] = float(g @ g)
    # fit column of parameter p: sum over the terms holding p of e_p c_j s_j
    term_fit = np.zeros((len(term_coef), kern.N_PARAMS_MODEL))
    j = 0
    for res in RESIDUALS:
        for term in DARR_TERMS[res]:
            for name, exp in term.powers:
                term_fit[j, PARAMETER_NAMES.index(name)] += exp * term_coef[j]
            j += 1
    sub_reads = np.zeros((max(n_sub, 1), kern.N_CHAN))
    for i, key in enumerate(keys):
        for term in DARR_TERMS["r" + key[1:]]:
            if term.channel is not None:
                sub_reads[i, CHANNELS.index(term.channel)] = 1.0
    arrays = [cfg, w0, sub_cfg, sub_coef, sub_exp, res_gain2, term_fit, sub_reads]
    for a in arrays:
        a.setflags(write=False)
    return _Compiled(
        cfg=cfg,
        w0=w0,
        chan_order=chan_order,
        term_res=np.array(term_res, dtype=np.int64),
        term_chan=np.array(term_chan, dtype=np.int64),
        term_order=np.array(term_order, dtype=np.int64),
        term_coef=np.array(term_coef, dtype=np.float64),
        res_chan=res_chan,
        sub_cfg=sub_cfg,
        sub_kind=sub_kind,
        sub_chan=sub_chan,
        sub_order=sub_order,
        sub_coef=sub_coef,
        sub_exp=sub_exp,
        sub_fuse=sub_fuse,
        res_gain2=res_gain2,
        term_fit=term_fit,
        sub_reads=sub_reads,
        n_window=n_window,
        box=box,
        n_hist=kern.MAX_ORDER * box + 1,
        cal_capacity=cal_capacity,
        fused=tuple(fused),
    )


# ----------------------------------------------------------------------------- state
# Layout of the scalar block (``DarrFekfState.scalars``): part name -> (offset, length). The
# kernel indexes it by the ``ST_*`` constants; code outside the kernel reads it by these names.
SCALAR_PARTS: dict[str, tuple[int, int]] = {
    "samples_seen": (kern.ST_N_SEEN, 1),
    "t_first_s": (kern.ST_T_FIRST, 1),
    "t_last_s": (kern.ST_T_LAST, 1),
    "ring_position": (kern.ST_POS, 1),
    "calibrated": (kern.ST_CALIBRATED, 1),
    "calibration_buffer_rows": (kern.ST_CAL_BUF_N, 1),
    "fault_active": (kern.ST_FAULT, 1),
    "first_detected_s": (kern.ST_FIRST_T, 1),
    "samples_below": (kern.ST_BELOW, 1),
    "irregular_intervals": (kern.ST_IRREGULAR, 1),
    "window_count": (kern.ST_WIN_COUNT, 1),
    "window_t0_s": (kern.ST_WIN_T0, 1),
    "window_fault": (kern.ST_WIN_FAULT, 1),
    "window_mask": (kern.ST_WIN_MASK, 1),
    "thresholds_ready": (kern.ST_THR_READY, 1),
    "latched": (kern.ST_LATCH, kern.N_RES),
    "samples_above": (kern.ST_ABOVE, kern.N_RES),
    "thresholds": (kern.ST_THR, kern.N_RES),
    "calibration_max": (kern.ST_CAL_MAX, kern.N_RES),
    "last_residuals": (kern.ST_LAST_R, kern.N_RES),
    "window_sum2": (kern.ST_WIN_SUM2, kern.N_RES),
    "window_n": (kern.ST_WIN_N, kern.N_RES),
    "window_peak_ratio": (kern.ST_WIN_MAX, kern.N_RES),
    "last_valid": (kern.ST_LAST_VALID, kern.N_CHAN),
    "missing_in_window": (kern.ST_MISS_COUNT, kern.N_CHAN),
    "noise_sum2": (kern.ST_NOISE_SUM2, kern.N_CHAN),
    "noise_n": (kern.ST_NOISE_N, kern.N_CHAN),
    "noise_var": (kern.ST_NOISE_VAR, kern.N_CHAN),
    "raw_sum2": (kern.ST_MEAN_SQ, kern.N_CHAN),
    "previous_smoothed": (kern.ST_PREV_SMOOTH, kern.N_CHAN),
    "calibration_sum2": (kern.ST_CAL_SUM2, kern.N_RES),
    "calibration_n": (kern.ST_CAL_N, kern.N_RES),
    "residual_var": (kern.ST_RES_VAR, kern.N_RES),
    "calibration_state": (kern.ST_CAL_STATE, 1),
    "calibration_flags": (kern.ST_CAL_FLAGS, 1),
    "fit_samples": (kern.ST_FIT_N, 1),
    "sensor_mask": (kern.ST_SENS_MASK, 1),
    "sensor_check_samples": (kern.ST_SENS_N, 1),
    "expected_residual_sd": (kern.ST_EXP_SD, kern.N_RES),
    "calibration_robust_rms": (kern.ST_CAL_ROBUST, kern.N_RES),
    "calibration_excluded_segments": (kern.ST_CAL_EXCLUDED, kern.N_RES),
    "calibration_level_ratio": (kern.ST_CAL_RATIO, kern.N_RES),
    "calibration_unchanged": (kern.ST_CAL_ZERO, kern.N_CHAN),
    "calibration_compared": (kern.ST_CAL_RAW_N, kern.N_CHAN),
    "sensor_noise_var": (kern.ST_SENS_VAR, kern.N_CHAN),
    "sensor_unchanged_run": (kern.ST_SENS_RUN, kern.N_CHAN),
    "subsystem_withheld": (kern.ST_SUB_WITHHELD, 7),
    "sensor_noise_over": (kern.ST_SENS_ABOVE, kern.N_CHAN),
    "sensor_noise_lag1": (kern.ST_SENS_COV1, kern.N_CHAN),
    "sensor_last_third_difference": (kern.ST_SENS_E_PREV, kern.N_CHAN),
}


@dataclass(frozen=True)
class DarrFekfState:
    """Everything carried between batches (arrays never modified in place: ``step`` copies).

    Attributes:
        version: schema version (``STATE_VERSION``).
        t_last_s: time of the last sample seen (-inf before any).
        scalars: FloatArray  # (ST_LEN,) counters, calibration, detection and sensor-check
            state, health accumulators, thresholds, noise variances: parts in
            :data:`SCALAR_PARTS`, read with :meth:`part`.
        history: FloatArray  # (9, stages, H) ring buffers of the smoother's box stages
            (stage 0: the raw values, missing samples holding the last valid value).
        box_sums: FloatArray  # (9, stages) running sums of the box stages.
        missing: FloatArray  # (9, W) 1 where a sample of the smoother's support was missing.
        subsystems: FloatArray  # (subsystems, SS_LEN) the subsystem filters (SS_* layout).
        calibration_buffer: FloatArray  # (capacity, 8) |r| and segment kept for a quantile
            calibration.
        calibration_segments: FloatArray  # (7, MAX_SEGMENTS, 3) sum of r^2, count, max |r|
            per residual and segment of the calibration window.
        isolation_gram: FloatArray  # (FIT_DIM, FIT_DIM) weighted normal equations of the
            isolation fit of the active fault (upper triangle).
    """

    version: int
    t_last_s: float
    scalars: FloatArray
    history: FloatArray
    box_sums: FloatArray
    missing: FloatArray
    subsystems: FloatArray
    calibration_buffer: FloatArray
    calibration_segments: FloatArray
    isolation_gram: FloatArray

    def part(self, name: str) -> FloatArray:
        """A read-only part of the scalar block by name (:data:`SCALAR_PARTS`)."""
        offset, length = SCALAR_PARTS[name]
        view = self.scalars[offset : offset + length]
        view.setflags(write=False)
        return view

    def value(self, name: str) -> float:
        """A one-number part of the scalar block."""
        return float(self.part(name)[0])

    @property
    def thresholds(self) -> FloatArray:
        """Thresholds in use (NaN before calibration)."""
        return self.part("thresholds").copy()

    @property
    def coherence_vector(self) -> tuple[int, ...]:
        """Latched coherence vector of the active fault (zeros when none)."""
        return tuple(int(v) for v in self.part("latched"))

    @property
    def fault_active(self) -> bool:
        """True between a detection and its clearance."""
        return self.value("fault_active") == 1.0

    @property
    def sensor_flags(self) -> dict[str, str]:
        """Sensors flagged by their own signal during the active fault: channel -> stuck/noisy."""
        mask = int(self.value("sensor_mask"))
        return _sensor_flags(mask)

    @property
    def noise_std(self) -> dict[str, float | None]:
        """Measurement noise standard deviation by model channel (None: not known yet)."""
        var = self.part("noise_var")
        return {
            c: (math.sqrt(v) if math.isfinite(v) else None)
            for c, v in zip(CHANNELS, var, strict=True)
        }


def _sensor_flags(mask: int) -> dict[str, str]:
    flags: dict[str, str] = {}
    for c_idx, c in enumerate(CHANNELS):
        if (mask >> c_idx) & 1:
            flags[c] = "stuck"
        elif (mask >> (kern.N_CHAN + c_idx)) & 1:
            flags[c] = "noisy"
    return flags


def _frozen(a: FloatArray) -> FloatArray:
    a.setflags(write=False)
    return a


def initial_state(config: DarrFekfConfig) -> DarrFekfState:
    """State before the first sample."""
    comp = config.compiled
    sc = np.zeros(kern.ST_LEN)
    sc[kern.ST_T_FIRST] = np.nan
    sc[kern.ST_T_LAST] = -math.inf
    sc[kern.ST_POS] = comp.n_hist - 1
    sc[kern.ST_FIRST_T] = np.nan
    sc[kern.ST_THR : kern.ST_THR + kern.N_RES] = np.nan
    sc[kern.ST_LAST_R : kern.ST_LAST_R + kern.N_RES] = np.nan
    sc[kern.ST_LAST_VALID : kern.ST_LAST_VALID + kern.N_CHAN] = np.nan
    sc[kern.ST_PREV_SMOOTH : kern.ST_PREV_SMOOTH + kern.N_CHAN] = np.nan
    sc[kern.ST_RES_VAR : kern.ST_RES_VAR + kern.N_RES] = np.nan
    noise_var = [config.noise_std[c] ** 2 if c in config.noise_std else np.nan for c in CHANNELS]
    sc[kern.ST_NOISE_VAR : kern.ST_NOISE_VAR + kern.N_CHAN] = noise_var
    sc[kern.ST_SENS_VAR : kern.ST_SENS_VAR + kern.N_CHAN] = noise_var
    sc[kern.ST_SENS_COV1 : kern.ST_SENS_COV1 + kern.N_CHAN] = kern.WHITE_LAG1 * np.asarray(
        noise_var
    )
    sc[kern.ST_SENS_E_PREV : kern.ST_SENS_E_PREV + kern.N_CHAN] = np.nan
    for part in ("expected_residual_sd", "calibration_robust_rms", "calibration_level_ratio"):
        offset, length = SCALAR_PARTS[part]
        sc[offset : offset + length] = np.nan
    if config.thresholds.rule == "fixed":
        assert config.thresholds.values is not None
        sc[kern.ST_THR : kern.ST_THR + kern.N_RES] = config.thresholds.values
        sc[kern.ST_THR_READY] = 1.0
    if config.thresholds.window_s <= 0.0:
        sc[kern.ST_CALIBRATED] = 1.0
        sc[kern.ST_CAL_STATE] = kern.CAL_CALIBRATED
    n_sub = len(config.subsystems)
    return DarrFekfState(
        version=STATE_VERSION,
        t_last_s=-math.inf,
        scalars=_frozen(sc),
        history=_frozen(np.zeros((kern.N_CHAN, kern.N_STAGES, comp.n_hist))),
        box_sums=_frozen(np.zeros((kern.N_CHAN, kern.N_STAGES))),
        missing=_frozen(np.zeros((kern.N_CHAN, comp.n_window))),
        subsystems=_frozen(np.zeros((n_sub, kern.SS_LEN))),
        calibration_buffer=_frozen(np.zeros((comp.cal_capacity, kern.N_RES + 1))),
        calibration_segments=_frozen(np.zeros((kern.N_RES, kern.MAX_SEGMENTS, kern.SEG_LEN))),
        isolation_gram=_frozen(np.zeros((kern.FIT_DIM, kern.FIT_DIM))),
    )


_ARRAYS = (
    "scalars",
    "history",
    "box_sums",
    "missing",
    "subsystems",
    "calibration_buffer",
    "calibration_segments",
    "isolation_gram",
)


def _encode(a: FloatArray) -> dict[str, Any]:
    return {
        "shape": list(a.shape),
        "data": base64.b64encode(np.ascontiguousarray(a, dtype="<f8").tobytes()).decode("ascii"),
    }


def _decode(doc: Any) -> FloatArray:
    shape = tuple(int(s) for s in doc["shape"])
    raw = base64.b64decode(doc["data"].encode("ascii"), validate=True)
    return _frozen(np.frombuffer(raw, dtype="<f8").astype(np.float64).reshape(shape))


def dump_state(state: DarrFekfState) -> bytes:
    """JSON with the version; arrays as little-endian float64 in base64 (exact round trip)."""
    doc = {
        "version": state.version,
        "kind": NAME,
        "t_last_s": float(state.t_last_s).hex(),
        **{name: _encode(getattr(state, name)) for name in _ARRAYS},
    }
    return json.dumps(doc, separators=(",", ":")).encode("ascii")


def _upgrade_v1(doc: dict[str, Any]) -> dict[str, Any]:
    """Version 1 -> 2: the calibration checks, sensor checks and isolation fit appended.

    The new scalar parts start as a fresh state would have them, except the calibration
    state, which is ``calibrated`` (unchecked: its flags are 0 and its ratios unknown) when the
    version-1 state had finished calibrating, and the sensors' running noise variance, which
    starts at the calibrated one. The quantile buffer gets a segment column (all segment 0);
    the segment statistics and the fit start empty (the fit of an active fault then covers the
    samples after the upgrade).
    """
    old = _decode(doc["scalars"])
    if old.shape != (kern.ST_LEN_V1,):
        raise EstimatorError("not a darr_fekf state: wrong scalar block (version 1)")
    sc = np.zeros(kern.ST_LEN_V2)
    sc[: kern.ST_LEN_V1] = old
    for part in ("expected_residual_sd", "calibration_robust_rms", "calibration_level_ratio"):
        offset, length = SCALAR_PARTS[part]
        sc[offset : offset + length] = np.nan
    if old[kern.ST_CALIBRATED] == 1.0:
        sc[kern.ST_CAL_STATE] = kern.CAL_CALIBRATED
    sc[kern.ST_SENS_VAR : kern.ST_SENS_VAR + kern.N_CHAN] = old[
        kern.ST_NOISE_VAR : kern.ST_NOISE_VAR + kern.N_CHAN
    ]
    buf = _decode(doc["calibration_buffer"])
    new_buf = np.zeros((buf.shape[0], kern.N_RES + 1))
    new_buf[:, : kern.N_RES] = buf
    return {
        **doc,
        "version": 2,
        "scalars": _encode(sc),
        "calibration_buffer": _encode(new_buf),
        "calibration_segments": _encode(np.zeros((kern.N_RES, kern.MAX_SEGMENTS, kern.SEG_LEN))),
        "isolation_gram": _encode(np.zeros((kern.FIT_DIM, kern.FIT_DIM))),
    }


def _upgrade_v2(doc: dict[str, Any]) -> dict[str, Any]:
    """Version 2 -> 3: the white-noise test of the sensor checks appended (per channel the
    running lag-1 product of the third differences and the previous third difference). The
    product starts at its white-noise value for the running variance (``-0.75 x`` it), the
    previous difference unknown (the product resumes one sample later)."""
    old = _decode(doc["scalars"])
    if old.shape != (kern.ST_LEN_V2,):
        raise EstimatorError("not a darr_fekf state: wrong scalar block (version 2)")
    sc = np.empty(kern.ST_LEN)
    sc[: kern.ST_LEN_V2] = old
    var = old[kern.ST_SENS_VAR : kern.ST_SENS_VAR + kern.N_CHAN]
    sc[kern.ST_SENS_COV1 : kern.ST_SENS_COV1 + kern.N_CHAN] = kern.WHITE_LAG1 * var
    sc[kern.ST_SENS_E_PREV : kern.ST_SENS_E_PREV + kern.N_CHAN] = np.nan
    return {**doc, "version": 3, "scalars": _encode(sc)}


_UPGRADES = {1: _upgrade_v1, 2: _upgrade_v2}


def load_state(data: bytes) -> DarrFekfState:
    """Inverse of :func:`dump_state`; older versions are upgraded (``_upgrade_vN``).

    Raises:
        StateVersionError: the version is neither ``STATE_VERSION`` nor one that can be
            upgraded.
        EstimatorError: the bytes are not a darr_fekf state.
    """
    try:
        doc = json.loads(data)
    except (ValueError, UnicodeDecodeError) as exc:
        raise EstimatorError(f"not a darr_fekf state: {exc}") from exc
    if not isinstance(doc, dict) or "version" not in doc:
        raise EstimatorError("not a darr_fekf state: no version")
    version = doc["version"]
    if version != STATE_VERSION and version not in _UPGRADES:
        raise StateVersionError(
            f"darr_fekf state version {version!r} is not supported "
            f"(expected {STATE_VERSION} or one of {sorted(_UPGRADES)})"
        )
    try:
        while doc["version"] != STATE_VERSION:
            doc = _UPGRADES[doc["version"]](doc)
        arrays = {name: _decode(doc[name]) for name in _ARRAYS}
        t_last = float.fromhex(doc["t_last_s"])
    except (KeyError, TypeError, ValueError) as exc:
        if isinstance(exc, EstimatorError):
            raise
        raise EstimatorError(f"not a darr_fekf state: {exc}") from exc
    if arrays["scalars"].shape != (kern.ST_LEN,):
        raise EstimatorError("not a darr_fekf state: wrong scalar block")
    return DarrFekfState(version=STATE_VERSION, t_last_s=t_last, **arrays)


def _check_state(config: DarrFekfConfig, state: DarrFekfState) -> None:
    comp = config.compiled
    shapes = {
        "history": (kern.N_CHAN, kern.N_STAGES, comp.n_hist),
        "box_sums": (kern.N_CHAN, kern.N_STAGES),
        "missing": (kern.N_CHAN, comp.n_window),
        "subsystems": (len(config.subsystems), kern.SS_LEN),
        "calibration_buffer": (comp.cal_capacity, kern.N_RES + 1),
        "calibration_segments": (kern.N_RES, kern.MAX_SEGMENTS, kern.SEG_LEN),
        "isolation_gram": (kern.FIT_DIM, kern.FIT_DIM),
    }
    for name, shape in shapes.items():
        if getattr(state, name).shape != shape:
            raise EstimatorError(f"state does not match the configuration ({name} shape)")


# ----------------------------------------------------------------------------- outputs
def sample_output_names(config: DarrFekfConfig) -> tuple[str, ...]:
    """Names of the per-sample outputs, in the kernel's row order."""
    names = list(RESIDUALS)
    for key, sub in config.subsystems.items():
        names += [f"{key}_{p}" for p in sub.parameters]
    names += list(config.compiled.fused)
    names += [f"{key}_alpha" for key in config.subsystems]
    return tuple(names)


def _mask_to_vector(mask: float) -> list[int]:
    m = int(mask)
    return [(m >> i) & 1 for i in range(kern.N_RES)]


def _component(vector: Sequence[int], flags: Mapping[str, str] | None = None) -> str:
    parts = [f"s{i + 1}" for i, c in enumerate(vector) if c]
    parts += [f"sensor:{c}" for c in (flags or {})]
    return "+".join(parts)


def _sensor_members(flags: Mapping[str, str]) -> tuple[str, ...]:
    """Sensor faults allowed in candidate sets: bias and drift of every channel (the residuals
    are their only evidence); stuck and increased noise only for sensors whose own signal
    shows them (the checks see them directly, so an unflagged sensor is neither)."""
    members = [sensor_fault_name(c, k) for c in CHANNELS for k in ("bias", "drift")]
    members += [
        sensor_fault_name(c, "stuck" if kind == "stuck" else "noise") for c, kind in flags.items()
    ]
    return tuple(members)


def _candidates(
    config: DarrFekfConfig, vector: Sequence[int], flags: Mapping[str, str] | None = None
) -> list[list[str]]:
    flags = flags or {}
    found = candidate_sets(
        vector,
        config.set_gains,
        config.max_candidate_size,
        None,
        sensor_faults=_sensor_members(flags),
    )
    if flags:
        # sets holding a sensor fault its own signal shows come first
        flagged = {
            sensor_fault_name(c, "stuck" if k == "stuck" else "noise") for c, k in flags.items()
        }
        found.sort(key=lambda s: (not any(m in flagged for m in s), len(s), s))
    return found[: config.max_candidates]


def _candidate_text(candidates: list[list[str]], limit: int = 6) -> str:
    shown = ["{" + ", ".join(c) + "}" for c in candidates[:limit]]
    more = f" and {len(candidates) - limit} more" if len(candidates) > limit else ""
    return ", ".join(shown) + more if shown else "none consistent"


_CAL_STATES = {
    kern.CAL_CALIBRATING: "calibrating",
    kern.CAL_CALIBRATED: "calibrated",
    kern.CAL_SUSPICIOUS: "suspicious",
    kern.CAL_REFUSED: "refused",
}


def _calibration_reasons(config: DarrFekfConfig, state: DarrFekfState) -> list[str]:
    """Why the calibration window was found suspicious or refused, one sentence each."""
    flags = int(state.value("calibration_flags"))
    thr = config.thresholds
    level = "reference" if thr.reference is not None else "expected from the channels' noise"
    ratio = state.part("calibration_level_ratio")
    excluded = state.part("calibration_excluded_segments")
    reasons: list[str] = []
    if flags & kern.CALF_LEVEL_REFUSED:
        high = [
            f"{r} {ratio[i]:.3g}x" for i, r in enumerate(RESIDUALS) if ratio[i] > thr.refuse_ratio
        ]
        reasons.append(
            f"residual level over the {level} level by more than {thr.refuse_ratio:g}: "
            + ", ".join(high)
            + " (a fault present over the whole window)"
        )
    if flags & kern.CALF_LEVEL:
        high = [
            f"{r} {ratio[i]:.3g}x"
            for i, r in enumerate(RESIDUALS)
            if thr.suspicious_ratio < ratio[i] <= thr.refuse_ratio
        ]
        reasons.append(f"residual level over the {level} level: " + ", ".join(high))
    if flags & kern.CALF_SEGMENT:
        seg = [f"{r} ({int(excluded[i])})" for i, r in enumerate(RESIDUALS) if excluded[i] > 0]
        reasons.append(
            "segments out of line with the rest of the window (a fault starting inside it), "
            "excluded from the thresholds: " + ", ".join(seg)
        )
    if flags & kern.CALF_STUCK:
        unchanged = state.part("calibration_unchanged")
        compared = state.part("calibration_compared")
        stuck = [
            c
            for i, c in enumerate(CHANNELS[: kern.SENSOR_CHANNELS])
            if compared[i] > 0 and unchanged[i] >= 0.99 * compared[i]
        ]
        reasons.append("sensor did not change during the window: " + ", ".join(stuck))
    if flags & kern.CALF_NOISE:
        reasons.append("channel noise above the reference noise")
    return reasons


def calibration_detail(config: DarrFekfConfig, state: DarrFekfState) -> dict[str, Any]:
    """The calibration phase and its checks, JSON-safe (``diagnosis.detail["calibration"]``)."""
    code = state.value("calibration_state")
    name = _CAL_STATES.get(code, "calibrating")
    thr = config.thresholds
    detail: dict[str, Any] = {"state": name, "window_s": thr.window_s, "rule": thr.rule}
    if name == "calibrating":
        t_first = state.value("t_first_s")
        elapsed = state.t_last_s - t_first if math.isfinite(t_first) else 0.0
        detail["elapsed_s"] = max(0.0, elapsed)
        return detail
    reasons = _calibration_reasons(config, state)
    detail["reasons"] = reasons
    detail["reference_used"] = thr.reference is not None
    exp_sd = state.part("expected_residual_sd")
    robust = state.part("calibration_robust_rms")
    detail["residuals"] = {
        r: {
            "robust_rms": _finite_or_none(robust[i]),
            "expected_rms": _finite_or_none(exp_sd[i]),
            "level_ratio": _finite_or_none(state.part("calibration_level_ratio")[i]),
            "excluded_segments": int(state.part("calibration_excluded_segments")[i]),
        }
        for i, r in enumerate(RESIDUALS)
    }
    if name == "refused":
        if thr.rule == "fixed":
            detail["action"] = "thresholds from the configuration kept; the window is not trusted"
        elif thr.reference is not None:
            detail["action"] = "thresholds from the configured fault-free reference"
        else:
            detail["action"] = (
                f"thresholds at {thr.fallback_sigmas:g} x the residual sd expected from the "
                "channels' noise; status unknown until a fault is detected or thresholds are "
                "given (thresholds.reference or rule fixed)"
            )
    elif name == "suspicious":
        detail["action"] = "thresholds from the segments in line with the rest of the window"
    else:
        detail["action"] = "thresholds calibrated"
    if name == "calibrated":
        # what to copy into thresholds.reference of other streams of this actuator
        thresholds = state.part("thresholds")
        noise = state.noise_std
        if all(math.isfinite(v) and v > 0 for v in thresholds) and all(
            math.isfinite(v) and v > 0 for v in robust
        ):
            detail["reference"] = {
                "thresholds": {r: float(thresholds[i]) for i, r in enumerate(RESIDUALS)},
                "residual_rms": {r: float(robust[i]) for i, r in enumerate(RESIDUALS)},
                "noise_std": {c: v for c, v in noise.items() if v is not None and v > 0},
            }
    return detail


def _calibration_events(
    t: float, config: DarrFekfConfig, state: DarrFekfState
) -> list[EstimatorEvent]:
    """``calibration_refused`` or ``calibration_suspicious`` at the end of the window."""
    detail = calibration_detail(config, state)
    if detail["state"] in ("refused", "suspicious"):
        return [EstimatorEvent(t_s=t, kind=f"calibration_{detail['state']}", detail=detail)]
    return []


def _event(row: FloatArray, config: DarrFekfConfig, state: DarrFekfState) -> EstimatorEvent:
    t = float(row[kern.EV_T])
    kind = row[kern.EV_KIND]
    if kind == kern.EV_CALIBRATED:
        thr = config.thresholds
        cal_state = _CAL_STATES.get(float(row[kern.EV_CAL_STATE]), "calibrated")
        detail: dict[str, Any] = {
            "thresholds": {
                r: _finite_or_none(row[kern.EV_THR + i]) for i, r in enumerate(RESIDUALS)
            },
            "source": "config"
            if thr.rule == "fixed"
            else (
                ("reference" if thr.reference is not None else "expected_level")
                if cal_state == "refused"
                else "calibrated"
            ),
            "rule": thr.rule,
            "window_s": thr.window_s,
            "margin": thr.margin,
            "q": thr.q,
            "noise_std": {
                c: _finite_or_none(row[kern.EV_NOISE + i]) for i, c in enumerate(CHANNELS)
            },
            "lag_s": config.lag_s,
            "calibration": cal_state,
        }
        return EstimatorEvent(t_s=t, kind="thresholds_calibrated", detail=detail)
    vector = _mask_to_vector(row[kern.EV_MASK])
    flags = (
        _sensor_flags(int(row[kern.EV_SENS_MASK])) if math.isfinite(row[kern.EV_SENS_MASK]) else {}
    )
    residuals = [r for r, c in zip(RESIDUALS, vector, strict=True) if c]
    base = {
        "component": _component(vector, flags),
        "residuals": residuals,
        "coherence_vector": vector,
        "sensor_flags": flags,
        "first_detected_s": _finite_or_none(row[kern.EV_FIRST_T]),
        "lag_s": config.lag_s,
    }
    if kind == kern.EV_DETECTED:
        prev = _mask_to_vector(row[kern.EV_PREV_MASK])
        prev_flags = _sensor_flags(int(row[kern.EV_PREV_SENS]))
        detail = {
            **base,
            "candidates": _candidates(config, vector, flags),
            "detected_s": t,
            "update": any(prev) or bool(prev_flags),
            "new_residuals": [
                r for r, c, p in zip(RESIDUALS, vector, prev, strict=True) if c and not p
            ],
            "new_sensor_flags": {c: k for c, k in flags.items() if c not in prev_flags},
        }
        return EstimatorEvent(t_s=t, kind="fault_detected", detail=detail)
    if kind == kern.EV_CLEARED:
        detail = {**base, "detected_s": base["first_detected_s"], "cleared_s": t}
        return EstimatorEvent(t_s=t, kind="fault_cleared", detail=detail)
    key = list(config.subsystems)[int(row[kern.EV_SUB])]
    sub = config.subsystems[key]
    detail = {
        **base,
        "subsystem": key,
        "state": sub.state,
        "parameters": list(sub.parameters),
        "estimator": sub.estimator,
        "measurement": sub.measurement,
    }
    return EstimatorEvent(t_s=t, kind="estimation_started", detail=detail)


def _health(row: FloatArray, config: DarrFekfConfig) -> HealthWindow:
    indicators: dict[str, float | None] = {}
    for i, r in enumerate(RESIDUALS):
        indicators[f"{r}_rms"] = _finite_or_none(row[kern.WIN_RMS + i])
        indicators[f"{r}_peak_ratio"] = _finite_or_none(row[kern.WIN_PEAK + i])
    reasons: tuple[str, ...] = ()
    status: Literal["ok", "alert"] = "ok"
    if row[kern.WIN_FAULT] == 1.0:
        vector = _mask_to_vector(row[kern.WIN_MASK])
        status = "alert"
        reasons = (_fault_reason(config, vector),)
    return HealthWindow(
        t_start_s=float(row[kern.WIN_T0]),
        t_end_s=float(row[kern.WIN_T1]),
        n_samples=int(row[kern.WIN_N]),
        indicators=indicators,
        status=status,
        reasons=reasons,
    )


def _fault_reason(
    config: DarrFekfConfig, vector: Sequence[int], flags: Mapping[str, str] | None = None
) -> str:
    parts = []
    residuals = ", ".join(r for r, c in zip(RESIDUALS, vector, strict=True) if c)
    if residuals:
        parts.append(f"residuals {residuals} over threshold")
    if flags:
        parts.append("sensor " + ", ".join(f"{c} {k}" for c, k in flags.items()))
    return (
        "fault: "
        + "; ".join(parts)
        + "; candidate fault sets "
        + _candidate_text(_candidates(config, vector, flags))
    )


# ----------------------------------------------------------------------------- isolation fit
def _fit_columns(member: str) -> list[int]:
    """Fit columns of a candidate member: a parameter's relative change and its ramp; a
    sensor's bias, or bias and ramp for a drift. Stuck and noisy sensors have no parametric
    form (empty)."""
    if not member.startswith("sensor:"):
        p = PARAMETER_NAMES.index(member)
        return [p, kern.FIT_PRAMP + p]
    _, channel, kind = member.split(":")
    c = CHANNELS.index(channel)
    if kind == "bias":
        return [kern.FIT_BIAS + c]
    if kind == "drift":
        return [kern.FIT_BIAS + c, kern.FIT_RAMP + c]
    return []


def _hypothesis_pool(config: DarrFekfConfig, vector: Sequence[int]) -> list[tuple[str, ...]]:
    """Sets the fit compares: sets of members (parameters outside the set gains, sensor bias
    and drift), each member touching the coherence vector, whose signatures together cover it,
    up to ``min(max_candidate_size, 2)`` members. Unlike the exact-match candidate sets, a
    member may predict a relation that stayed below its threshold (a sensor bias whose effect
    on one relation is small): the fit judges by magnitude."""
    target = [bool(c) for c in vector]
    members = [p for p in PARAMETER_NAMES if p not in config.set_gains] + [
        sensor_fault_name(c, k) for c in CHANNELS for k in ("bias", "drift")
    ]
    touching = [
        m for m in members if any(s and t for s, t in zip(ALL_SIGNATURES[m], target, strict=True))
    ]
    pool: list[tuple[str, ...]] = []
    for size in range(1, min(config.max_candidate_size, 2) + 1):
        for combo in itertools.combinations(touching, size):
            covered = [False] * kern.N_RES
            for m in combo:
                covered = [a or bool(b) for a, b in zip(covered, ALL_SIGNATURES[m], strict=True)]
            if all(c or not t for c, t in zip(covered, target, strict=True)):
                pool.append(combo)
    return pool


def isolation_detail(config: DarrFekfConfig, state: DarrFekfState) -> dict[str, Any] | None:
    """Sensor or parameter: the fit of the active fault's residuals on each candidate set.

    Over the samples since detection (one in ``fit_decimation``) the kernel accumulates the
    normal equations of ``r_l(t) ~ sum_h theta_h phi_(h,l)(t)``, weighted by the residuals'
    expected variance, for the columns: relative change of each parameter p (``phi =
    -sum_(terms with p) e_p c_j s_j``, so a relative change eps gives ``theta = -eps``) and its
    ramp ``phi t``; a bias b of each channel (``phi = sum_(order-0 terms) c_j``, theta = b) and
    a drift (ramp: ``sum_(order 0) c_j t + sum_(order 1) c_j``). For each set S the residual sum
    of squares after the least-squares fit on S's columns gives its mean squared standardized
    residual ``m_S`` (1: noise only). S is within the level when ``m_S <= max(consistency_floor,
    consistency_ratio * min m, min m + consistency_share * (m_0 - min m))`` (``m_0``: no fault
    set), and consistent when, besides, no proper subset of it is (parsimony: {A_h} within the
    level makes {A_h, P_L bias} add nothing). Explanation, over the consistent sets:
    ``sensor`` when a sensor's own signal is flagged, or when every consistent set holds a
    sensor fault; ``parameter`` when none does; ``ambiguous`` otherwise; ``pending`` before
    ``min_fit_s`` of fault.
    """
    if not state.fault_active:
        return None
    flags = state.sensor_flags
    vector = state.coherence_vector
    n_fit = state.value("fit_samples")  # effective count under the forgetting
    fit_s = n_fit * config.isolation.fit_decimation * config.sample_period_s
    detail: dict[str, Any] = {"fit_s": fit_s, "sensor_flags": dict(flags)}
    if flags:
        detail["explanation"] = "sensor"
        detail["basis"] = (
            "the sensor's own signal (" + ", ".join(f"{c} {k}" for c, k in flags.items()) + ")"
        )
        detail["hypotheses"] = []
        return detail
    if n_fit < 2 or not any(vector):
        detail["explanation"] = "pending"
        detail["hypotheses"] = []
        return detail
    upper = np.array(state.isolation_gram)
    gram = np.triu(upper) + np.triu(upper, 1).T
    r_col = kern.FIT_R
    total = float(gram[r_col, r_col])
    denom = n_fit * kern.N_RES
    results: list[dict[str, Any]] = []
    for combo in _hypothesis_pool(config, vector):
        cols = sorted({c for m in combo for c in _fit_columns(m)})
        g = gram[np.ix_(cols, cols)]
        b = gram[cols, r_col]
        scale = np.sqrt(np.maximum(np.diag(g), 0.0))
        keep = scale > 0.0
        if not keep.any():
            continue
        cols_k = [c for c, k in zip(cols, keep, strict=True) if k]
        gs = g[np.ix_(keep, keep)] / np.outer(scale[keep], scale[keep])
        bs = b[keep] / scale[keep]
        coef_s, *_ = np.linalg.lstsq(gs + 1e-10 * np.eye(len(bs)), bs, rcond=None)
        sse = max(total - float(bs @ coef_s), 0.0)
        coef = dict(zip(cols_k, (coef_s / scale[keep]).tolist(), strict=True))
        results.append(
            {
                "set": list(combo),
                "mean_sq": sse / denom,
                "estimates": _fit_estimates(combo, coef, config),
            }
        )
    results.sort(key=lambda h: (h["mean_sq"], len(h["set"]), h["set"]))
    best = results[0]["mean_sq"] if results else math.inf
    iso = config.isolation
    no_fault = total / denom
    level = max(
        iso.consistency_floor,
        iso.consistency_ratio * best,
        best + iso.consistency_share * max(no_fault - best, 0.0),
    )
    within = {tuple(h["set"]) for h in results if h["mean_sq"] <= level}
    for h in results:
        # parsimony: a set within the level whose proper subset is within it too adds nothing
        h["within_level"] = tuple(h["set"]) in within
        h["consistent"] = h["within_level"] and not any(
            sub in within
            for size in range(1, len(h["set"]))
            for sub in itertools.combinations(h["set"], size)
        )
    consistent = [h for h in results if h["consistent"]]
    results.sort(key=lambda h: (not h["consistent"], h["mean_sq"], len(h["set"]), h["set"]))
    detail["no_fault_mean_sq"] = total / denom
    detail["consistency_level"] = level
    if fit_s < iso.min_fit_s or not consistent:
        detail["explanation"] = "pending" if fit_s < iso.min_fit_s else "none_consistent"
    else:
        # a sensor fault in every consistent set: the sensor fault is established, and
        # estimates computed through that sensor would absorb its error (withheld)
        with_sensor = [any(m.startswith("sensor:") for m in h["set"]) for h in consistent]
        detail["explanation"] = (
            "sensor" if all(with_sensor) else "parameter" if not any(with_sensor) else "ambiguous"
        )
    detail["basis"] = "fit of the residuals since detection"
    detail["hypotheses"] = results[:20]
    return detail


def _fit_estimates(
    combo: Sequence[str], coef: Mapping[int, float], config: DarrFekfConfig
) -> dict[str, Any]:
    """The fitted fault sizes of a set: relative parameter change (at detection, and its rate),
    sensor bias (channel unit) and drift rate (channel unit per s)."""
    out: dict[str, Any] = {}
    for m in combo:
        if m.startswith("sensor:"):
            _, channel, kind = m.split(":")
            c = CHANNELS.index(channel)
            entry = {"bias": coef.get(kern.FIT_BIAS + c), "unit": CHANNEL_UNITS[channel]}
            if kind == "drift":
                entry["drift_per_s"] = coef.get(kern.FIT_RAMP + c)
            out[m] = entry
        else:
            p = PARAMETER_NAMES.index(m)
            c0 = coef.get(p)
            c1 = coef.get(kern.FIT_PRAMP + p)
            out[m] = {
                "relative_change": None if c0 is None else -c0,
                "relative_change_per_s": None if c1 is None else -c1,
                "nominal": config.parameters[m],
            }
    return out


def _parameters(config: DarrFekfConfig, state: DarrFekfState) -> dict[str, Any]:
    """Running subsystems' estimates: per subsystem and fused (inverse-variance weighted)."""
    per_sub: dict[str, Any] = {}
    fused: dict[str, list[tuple[float, float]]] = {}
    withheld = state.part("subsystem_withheld")
    for i, (key, sub) in enumerate(config.subsystems.items()):
        row = state.subsystems[i]
        if withheld[i] == 1.0:
            per_sub[key] = {"withheld": True, "parameters": {}}
            continue
        if row[kern.SS_RUNNING] != 1.0:
            continue
        entries: dict[str, Any] = {}
        for p_idx, p in enumerate(sub.parameters):
            nominal = config.parameters[p]
            q = p_idx + (0 if sub.measurement == "relation" else 1)
            est = float(row[kern.SS_Z + q]) * nominal
            var = float(row[kern.SS_P + q * (kern.MAX_DIM + 1)]) * nominal * nominal
            entries[p] = _bounds(est, var, nominal)
            fused.setdefault(p, []).append((est, var))
        per_sub[key] = {
            "state": sub.state,
            "estimator": sub.estimator,
            "measurement": sub.measurement,
            "started_s": float(row[kern.SS_T_START]),
            "updates": int(row[kern.SS_N_UPDATES]),
            "alpha": _finite_or_none(row[kern.SS_ALPHA]),
            "parameters": entries,
        }
    params: dict[str, Any] = {}
    for p, pairs in fused.items():
        den = sum(1.0 / v for _, v in pairs if v > 0.0)
        if den > 0.0:
            est = sum(e / v for e, v in pairs if v > 0.0) / den
            params[p] = _bounds(est, 1.0 / den, config.parameters[p])
    return {"parameters": params, "subsystems": per_sub}


def _bounds(est: float, var: float, nominal: float) -> dict[str, float | None]:
    """Estimate with +-3 standard deviation bounds and the change from nominal."""
    sd = math.sqrt(var) if var > 0.0 else 0.0
    return {
        "estimate": _finite_or_none(est),
        "lower": _finite_or_none(est - 3.0 * sd),
        "upper": _finite_or_none(est + 3.0 * sd),
        "nominal": nominal,
        "relative_change": _finite_or_none(est / nominal - 1.0),
    }


def diagnosis_detail(config: DarrFekfConfig, state: DarrFekfState) -> dict[str, Any]:
    """The diagnostic picture of a state, JSON-safe (NaN becomes None)."""
    vector = list(state.coherence_vector)
    thr_ready = state.value("thresholds_ready") == 1.0
    thresholds = state.part("thresholds")
    last_r = state.part("last_residuals")
    residuals = {
        r: {
            "value": _finite_or_none(last_r[i]),
            "threshold": _finite_or_none(thresholds[i]) if thr_ready else None,
            "exceeded": bool(vector[i]),
            "unit": RESIDUAL_UNITS[r],
        }
        for i, r in enumerate(RESIDUALS)
    }
    flags = state.sensor_flags
    detail: dict[str, Any] = {
        "residuals": residuals,
        "coherence_vector": vector,
        "signature_matrix": {p: list(row) for p, row in SIGNATURES.items()},
        "sensor_signature_matrix": {s: list(row) for s, row in SENSOR_SIGNATURES.items()},
        "candidates": _candidates(config, vector, flags),
        "detectable": {p: any(row) for p, row in SIGNATURES.items()},
        "set_gains": list(config.set_gains),
        "fault_active": state.fault_active,
        "first_detected_s": _finite_or_none(state.value("first_detected_s"))
        if state.fault_active
        else None,
        "sensor_flags": dict(flags),
        "calibrated": state.value("calibrated") == 1.0,
        "calibration": calibration_detail(config, state),
        "thresholds_ready": bool(thr_ready),
        "noise_std": state.noise_std,
        "lag_s": config.lag_s,
        "irregular_intervals": int(state.value("irregular_intervals")),
    }
    detail.update(_parameters(config, state))
    isolation = isolation_detail(config, state)
    detail["isolation"] = isolation
    withheld_subs = [k for k, v in detail["subsystems"].items() if v.get("withheld")]
    reason = None
    if isolation is not None and isolation["explanation"] == "sensor":
        reason = (
            "a sensor fault is the only consistent explanation ("
            + isolation["basis"]
            + "): the parameter estimates would absorb the sensor error"
        )
    elif withheld_subs:
        reason = "subsystems " + ", ".join(withheld_subs) + " read a flagged sensor"
    if reason is not None:
        detail["parameters"] = {}
        for v in detail["subsystems"].values():
            v["parameters"] = {}
            v["withheld"] = True
        detail["parameters_withheld"] = reason
    else:
        detail["parameters_withheld"] = None
    return detail


def _status(
    config: DarrFekfConfig, state: DarrFekfState, detail: Mapping[str, Any]
) -> StatusReport:
    """Status at the end of a batch: ``alert`` while a fault is active; otherwise by the
    calibration phase: ``learning`` while calibrating, ``unknown`` after a refused calibration
    (thresholds not from this stream's fault-free data), ``watch`` after a suspicious one,
    ``ok`` after a clean one."""
    cal = detail["calibration"]
    cal_note: str | None = None
    if cal["state"] == "refused":
        cal_note = "calibration refused: " + "; ".join(cal["reasons"]) + "; " + cal["action"]
    elif cal["state"] == "suspicious":
        cal_note = "calibration suspicious: " + "; ".join(cal["reasons"])
    if state.fault_active:
        reasons = [_fault_reason(config, state.coherence_vector, state.sensor_flags)]
        iso = detail["isolation"]
        if iso is not None and iso["explanation"] in (
            "sensor",
            "parameter",
            "ambiguous",
        ):
            best = iso["hypotheses"][0]["set"] if iso["hypotheses"] else None
            text = f"isolation: {iso['explanation']}"
            if best:
                text += " (best fit {" + ", ".join(best) + "})"
            reasons.append(text)
        if detail["parameters_withheld"]:
            reasons.append("parameter estimates withheld: " + detail["parameters_withheld"])
        if cal_note:
            reasons.append(cal_note)
        return StatusReport("alert", tuple(reasons))
    if cal["state"] == "calibrating":
        return StatusReport(
            "learning",
            (
                f"calibrating thresholds: {cal.get('elapsed_s', 0.0):.3g} of "
                f"{config.thresholds.window_s:g} s of stream time",
            ),
        )
    if cal["state"] == "refused":
        assert cal_note is not None
        if config.thresholds.reference is not None or config.thresholds.rule == "fixed":
            return StatusReport("watch", (cal_note,))
        return StatusReport("unknown", (cal_note,))
    if cal["state"] == "suspicious":
        assert cal_note is not None
        return StatusReport("watch", (cal_note,))
    return StatusReport("ok")


# ----------------------------------------------------------------------------- step


def _close_run(state: DarrFekfState) -> tuple[DarrFekfState, FloatArray]:
    """The run is closed (``end_of_run``): its partial health window, if any, is scored now
    (rows ``(0 or 1, WIN_LEN)``); residuals, thresholds, filters and decisions carry on."""
    if not state.scalars[kern.ST_WIN_COUNT] > 0.0:
        return state, np.empty((0, kern.WIN_LEN))
    scalars = state.scalars.copy()
    rows = np.empty((1, kern.WIN_LEN))
    kern.close_health_window(scalars, state.t_last_s, rows[0])
    return replace(state, scalars=_frozen(scalars)), rows


def step(
    config: DarrFekfConfig, state: DarrFekfState, batch: Batch
) -> tuple[DarrFekfState, StepOutputs]:
    """Advance over a whole batch (the per-sample loop runs compiled).

    Per-sample outputs (float64, aligned with ``batch.t_s``): residuals ``r1``..``r7`` (each
    describes the time ``lag_s`` before its sample; NaN while the differentiator fills or when
    too many samples of a window are missing), ``<subsystem>_<parameter>`` estimates of each
    subsystem filter, ``<parameter>`` fused over the subsystems that estimate it, and
    ``<subsystem>_alpha`` (the FEKF factor; 1 for an EKF), NaN while the filter is not running.

    Raises:
        OutOfOrderError: the batch starts at or before ``state.t_last_s``, or its times are not
            strictly increasing.
        EstimatorError: a channel is missing or has the wrong length, or the state does not
            match the configuration.
    """
    names = sample_output_names(config)
    t = np.ascontiguousarray(batch.t_s, dtype=np.float64)
    n = int(t.shape[0])
    if n == 0:
        empty = np.empty(0, dtype=np.float64)
        if batch.end_of_run:
            _check_state(config, state)
            state, rows = _close_run(state)
            return state, StepOutputs(
                samples={name: empty for name in names},
                health=[_health(row, config) for row in rows],
            )
        return state, StepOutputs(samples={name: empty for name in names})
    if not t[0] > state.t_last_s:
        raise OutOfOrderError(
            f"batch starts at t={float(t[0])!r} s, not after the last sample t={state.t_last_s!r} s"
        )
    _check_state(config, state)
    data = channel_block(batch, [config.channels[c] for c in CHANNELS], n)
    arrays = {name: getattr(state, name).copy() for name in _ARRAYS}
    comp = config.compiled
    out = np.empty((len(names), n))
    events, windows, status = kern.darr_batch(
        comp.cfg,
        comp.w0,
        comp.chan_order,
        comp.term_res,
        comp.term_chan,
        comp.term_order,
        comp.term_coef,
        comp.res_chan,
        comp.sub_cfg,
        comp.sub_kind,
        comp.sub_chan,
        comp.sub_order,
        comp.sub_coef,
        comp.sub_exp,
        comp.sub_fuse,
        len(comp.fused),
        comp.res_gain2,
        comp.term_fit,
        comp.sub_reads,
        arrays["scalars"],
        arrays["history"],
        arrays["box_sums"],
        arrays["missing"],
        arrays["subsystems"],
        arrays["calibration_buffer"],
        arrays["calibration_segments"],
        arrays["isolation_gram"],
        t,
        data,
        out,
    )
    if status != 0:
        raise OutOfOrderError("batch times are not strictly increasing")
    new_state = DarrFekfState(
        version=STATE_VERSION,
        t_last_s=float(t[n - 1]),
        **{name: _frozen(a) for name, a in arrays.items()},
    )
    if batch.end_of_run:
        new_state, closed = _close_run(new_state)
        windows = np.concatenate([windows, closed]) if closed.shape[0] else windows
    detail = diagnosis_detail(config, new_state)
    event_list: list[EstimatorEvent] = []
    for row in events:
        event_list.append(_event(row, config, new_state))
        if row[kern.EV_KIND] == kern.EV_CALIBRATED:
            event_list += _calibration_events(float(row[kern.EV_T]), config, new_state)
    outputs = StepOutputs(
        samples={name: out[i] for i, name in enumerate(names)},
        health=[_health(row, config) for row in windows],
        events=event_list,
        diagnosis=Diagnosis(t_s=float(t[n - 1]), detail=detail),
        status=_status(config, new_state, detail),
    )
    return new_state, outputs


def warm_up() -> None:
    """Compile (or load from numba's cache) the kernels on a tiny stream."""
    config = parse_config(
        {
            "differentiator_window_s": 0.0015,
            "thresholds": {"rule": "quantile", "window_s": 0.003},
            "health_window_samples": 20,
        }
    )
    n = 200
    t = np.arange(n, dtype=np.float64) * config.sample_period_s
    rng = np.random.default_rng(0)
    channels = {c: rng.standard_normal(n) for c in CHANNELS}
    channels["v_p"][150:] += 1.0e3  # forces a detection and the subsystem filters
    channels["p_l"][150:] += 1.0e9
    step(config, initial_state(config), Batch(t_s=t, channels=channels))
