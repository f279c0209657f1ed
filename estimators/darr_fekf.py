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
from dataclasses import dataclass, field
from typing import Any, Literal, NamedTuple

import numpy as np

from estimators.base import (
    Batch,
    ConfigError,
    Diagnosis,
    EstimatorError,
    EstimatorEvent,
    FloatArray,
    HealthWindow,
    OutOfOrderError,
    StateVersionError,
    StatusReport,
    StepOutputs,
)
from estimators.checks import channel_block
from estimators.checks import finite as _finite
from estimators.checks import finite_or_none as _finite_or_none
from estimators.checks import is_number as _is_number
from estimators.checks import non_negative as _non_negative
from estimators.checks import positive as _positive
from estimators.kernels import darr_kernels as kern

NAME = "darr_fekf"
STATE_VERSION = 1

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


def candidate_sets(
    coherence: Sequence[int],
    set_gains: Sequence[str] = (),
    max_size: int = 3,
    max_count: int | None = None,
) -> list[list[str]]:
    """Parameter sets whose signatures together give exactly the coherence vector.

    A set qualifies when the union (logical OR) of its members' signature rows equals
    ``coherence``; members are detectable parameters not in ``set_gains`` whose signature is
    within the coherence vector. Sets are ordered by size, then by name; single and multiple
    faults up to ``max_size`` members, at most ``max_count`` sets (None: all).
    """
    target = tuple(int(bool(c)) for c in coherence)
    found = _candidate_sets(target, tuple(sorted(set_gains)), max_size, max_count)
    return [list(s) for s in found]


@functools.lru_cache(maxsize=256)
def _candidate_sets(
    target: tuple[int, ...], set_gains: tuple[str, ...], max_size: int, max_count: int | None
) -> tuple[tuple[str, ...], ...]:
    if not any(target):
        return ()
    eligible = sorted(
        name
        for name in PARAMETER_NAMES
        if name not in set_gains
        and any(SIGNATURES[name])
        and all(s <= c for s, c in zip(SIGNATURES[name], target, strict=True))
    )
    masks = {name: sum(1 << i for i, s in enumerate(SIGNATURES[name]) if s) for name in eligible}
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


# ----------------------------------------------------------------------------- configuration
@dataclass(frozen=True)
class ThresholdConfig:
    """Residual thresholds.

    Attributes:
        rule: ``"fixed"`` (``values``), or calibrated on the first ``window_s`` seconds of
            stream time, assumed fault-free: ``"max"`` (largest |r|, the seed's rule),
            ``"max_margin"`` (``margin`` times the largest |r|) or ``"quantile"`` (``margin``
            times the ``q`` quantile of |r|).
        window_s: calibration window (s of stream time); it also calibrates the channels'
            noise when a filter needs it.
        margin: factor applied to the calibrated statistic (rules max_margin and quantile).
        q: quantile level (rule quantile).
        values: the seven thresholds (rule fixed), in the residuals' units.
    """

    rule: Literal["fixed", "max", "max_margin", "quantile"] = "max_margin"
    window_s: float = 3.0
    margin: float = 2.0
    q: float = 0.999
    values: tuple[float, ...] | None = None


@dataclass(frozen=True)
class FuzzyConfig:
    """Settings of the fuzzy adaptive factor (seed eqs. 38-44).

    Attributes:
        c: robust constant of eq. 41 (seed: 1.0 to 1.5).
        window_s: time constant of the innovation variance estimate (eq. 38).
        input_levels: levels of the input sets ZO, PS, PB on the ratio of the predicted-state
            to the observation variance factor.
        output_levels: alpha of the output sets ZO, PS, PB (seed: 0, 0.5, 1).
        alpha_min: floor of alpha (alpha is the prior's weight over ``window_s``; 0 would
            discard the prior at once).
    """

    c: float = 1.5
    window_s: float = 0.05
    input_levels: tuple[float, float, float] = (1.0, 2.0, 3.0)
    output_levels: tuple[float, float, float] = (0.0, 0.5, 1.0)
    alpha_min: float = 0.05


@dataclass(frozen=True)
class SubsystemConfig:
    """A subsystem estimator on the subsystem's DARR.

    Attributes:
        state: model channel measured by the subsystem's sensor, whose first derivative the
            relation holds (e.g. ``"v_p"``); used by the ``"state"`` measurement.
        parameters: parameters of the relation to estimate (the others stay nominal).
        estimator: ``"ekf"`` or ``"fekf"``.
        measurement: ``"relation"`` (the relation itself is a pseudo-measurement, zero when
            the parameters are right; the filter state is the parameters) or ``"state"`` (the
            seed's form: the state is [y, parameters], the model is integrated and the measured
            state updates it).
        r: measurement variance (state channel variance, or the relation's variance per
            sample), or "auto" (calibrated on the fault-free window).
        q_state: process noise variance of the state per sample, or "auto" (the inputs'
            calibrated noise propagated through the model); state measurement only.
        p0_state: initial variance of the state, or "auto" (= r); state measurement only.
        q_parameters: relative variance rate of each parameter's random walk (1/s).
        p0_parameters: initial relative variance of each parameter.
        fuzzy: FEKF settings.
        bounds: limits of each parameter relative to its nominal value.
    """

    state: str
    parameters: tuple[str, ...]
    estimator: Literal["ekf", "fekf"] = "fekf"
    measurement: Literal["relation", "state"] = "relation"
    r: float | Literal["auto"] = "auto"
    q_state: float | Literal["auto"] = "auto"
    p0_state: float | Literal["auto"] = "auto"
    q_parameters: tuple[float, ...] = ()
    p0_parameters: tuple[float, ...] = ()
    fuzzy: FuzzyConfig = field(default_factory=FuzzyConfig)
    bounds: tuple[float, float] = (1.0e-3, 1.0e3)


DEFAULT_Q_PARAMETER = 1.0e-4
DEFAULT_P0_PARAMETER = 1.0e-2
DEFAULT_SUBSYSTEMS: dict[str, dict[str, Any]] = {
    "s6": {"state": "v_p", "parameters": ["a_h", "m_h", "b_h"]},
    "s7": {"state": "p_l", "parameters": ["a_h", "r_il", "c_hj"]},
}


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
    n_window: int
    box: int
    n_hist: int
    cal_capacity: int
    fused: tuple[str, ...]


@dataclass(frozen=True)
class DarrFekfConfig:
    """Validated configuration (build it with :func:`parse_config`).

    Attributes:
        channels: model channel -> stream channel name.
        sample_period_s: nominal sample period of the stream (the differentiator assumes it).
        parameters: nominal model parameters (SI units).
        differentiator_window_s: length of the smoothing differentiator's window.
        max_missing_fraction: largest fraction of missing samples in a window for which a
            residual is still computed (missing samples hold the last valid value).
        thresholds: residual thresholds.
        min_duration_s: time a residual must stay above its threshold to count as exceeded.
        clear_after_s: time every residual must stay below its threshold to clear a fault.
        set_gains: parameters known to be right (excluded from candidate sets).
        noise_std: known measurement noise standard deviation by model channel (the others
            are calibrated when a filter needs them).
        max_candidate_size: largest candidate fault set.
        max_candidates: most candidate sets reported.
        subsystems: estimators by subsystem name (``"s1"``..``"s7"``).
        health_window_samples: length of a health window, stream samples.
    """

    channels: dict[str, str] = field(default_factory=lambda: {c: c for c in CHANNELS}, hash=False)
    sample_period_s: float = 1.0e-4
    parameters: dict[str, float] = field(default_factory=lambda: dict(NOMINAL), hash=False)
    differentiator_window_s: float = 0.05
    max_missing_fraction: float = 0.1
    thresholds: ThresholdConfig = field(default_factory=ThresholdConfig)
    min_duration_s: float = 0.002
    clear_after_s: float = 1.0
    set_gains: tuple[str, ...] = ("k_q", "k_c")
    noise_std: dict[str, float] = field(default_factory=dict, hash=False)
    max_candidate_size: int = 3
    max_candidates: int = 100
    subsystems: dict[str, SubsystemConfig] = field(default_factory=dict, hash=False)
    health_window_samples: int = 10_000
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


# --------------------------------------------------------------------- parsing helpers


def _auto_or_positive(name: str, value: Any) -> float | Literal["auto"]:
    if value == "auto":
        return "auto"
    return _positive(name, value)


def _object(name: str, value: Any, known: Sequence[str]) -> Mapping[str, Any]:
    if not isinstance(value, Mapping):
        raise ConfigError(f"{name}: expected an object, got {type(value).__name__}")
    unknown = sorted(set(map(str, value)) - set(known))
    if unknown:
        prefix = f"{name}." if name else ""
        raise ConfigError(f"{prefix}{unknown[0]}: unknown field (known: {', '.join(known)})")
    return value


def _levels(name: str, value: Any, *, increasing: bool) -> tuple[float, float, float]:
    if not isinstance(value, Sequence) or isinstance(value, str) or len(value) != 3:
        raise ConfigError(f"{name}: expected three numbers")
    levels = tuple(_finite(f"{name}[{i}]", v) for i, v in enumerate(value))
    if increasing and not levels[0] < levels[1] < levels[2]:
        raise ConfigError(f"{name}: levels must be strictly increasing")
    return levels  # type: ignore[return-value]


def _per_parameter(
    name: str, value: Any, parameters: tuple[str, ...], default: float
) -> tuple[float, ...]:
    """A number for all parameters, or an object by parameter name (missing: default)."""
    if _is_number(value):
        v = _positive(name, value)
        return tuple(v for _ in parameters)
    obj = _object(name, value, parameters)
    return tuple(_positive(f"{name}.{p}", obj.get(p, default)) for p in parameters)


_THRESHOLD_FIELDS = ("rule", "window_s", "margin", "q", "values")


def _parse_thresholds(raw: Any) -> ThresholdConfig:
    obj = _object("thresholds", raw, _THRESHOLD_FIELDS)
    d = ThresholdConfig()
    rule = obj.get("rule", "fixed" if "values" in obj else d.rule)
    if rule not in ("fixed", "max", "max_margin", "quantile"):
        raise ConfigError(
            f"thresholds.rule: expected fixed, max, max_margin or quantile, got {rule!r}"
        )
    values: tuple[float, ...] | None = None
    if rule == "fixed":
        raw_values = obj.get("values")
        if isinstance(raw_values, Mapping):
            _object("thresholds.values", raw_values, RESIDUALS)
            if set(raw_values) != set(RESIDUALS):
                raise ConfigError("thresholds.values: give all seven thresholds r1..r7")
            raw_values = [raw_values[r] for r in RESIDUALS]
        if not isinstance(raw_values, Sequence) or len(raw_values) != len(RESIDUALS):
            raise ConfigError("thresholds.values: expected seven numbers (r1..r7)")
        values = tuple(_positive(f"thresholds.values[{i}]", v) for i, v in enumerate(raw_values))
    elif "values" in obj:
        raise ConfigError("thresholds.values: only with rule fixed")
    q = _finite("thresholds.q", obj.get("q", d.q))
    if not 0.0 < q < 1.0:
        raise ConfigError(f"thresholds.q: expected a number in (0, 1), got {q!r}")
    return ThresholdConfig(
        rule=rule,
        window_s=_non_negative("thresholds.window_s", obj.get("window_s", d.window_s)),
        margin=_positive("thresholds.margin", obj.get("margin", d.margin)),
        q=q,
        values=values,
    )


_FUZZY_FIELDS = ("c", "window_s", "input_levels", "output_levels", "alpha_min")


def _parse_fuzzy(name: str, raw: Any) -> FuzzyConfig:
    obj = _object(name, raw, _FUZZY_FIELDS)
    d = FuzzyConfig()
    out = _levels(
        f"{name}.output_levels", obj.get("output_levels", d.output_levels), increasing=False
    )
    if not all(0.0 <= v <= 1.0 for v in out):
        raise ConfigError(f"{name}.output_levels: alpha levels must lie in [0, 1]")
    return FuzzyConfig(
        c=_positive(f"{name}.c", obj.get("c", d.c)),
        window_s=_positive(f"{name}.window_s", obj.get("window_s", d.window_s)),
        input_levels=_levels(
            f"{name}.input_levels", obj.get("input_levels", d.input_levels), increasing=True
        ),
        output_levels=out,
        alpha_min=_alpha_min(name, obj.get("alpha_min", d.alpha_min)),
    )


def _alpha_min(name: str, value: Any) -> float:
    v = _finite(f"{name}.alpha_min", value)
    if not 0.0 < v <= 1.0:
        raise ConfigError(f"{name}.alpha_min: expected a number in (0, 1], got {value!r}")
    return v


_SUBSYSTEM_FIELDS = (
    "state",
    "parameters",
    "estimator",
    "measurement",
    "r",
    "q_state",
    "p0_state",
    "q_parameters",
    "p0_parameters",
    "fuzzy",
    "bounds",
)


def _subsystem_structure(key: str, state: str) -> None:
    """Raise ConfigError unless the relation of subsystem ``key`` is first order in ``state``
    with every other signal underived (what the subsystem filter can integrate)."""
    terms = DARR_TERMS["r" + key[1:]]
    if not any(t.channel == state and t.order == 1 for t in terms):
        raise ConfigError(
            f"subsystems.{key}.state: {state!r} has no first derivative in r{key[1:]}"
        )
    for term in terms:
        if term.channel == state and term.order > 1:
            raise ConfigError(
                f"subsystems.{key}.state: r{key[1:]} holds a derivative of order "
                f"{term.order} of {state!r}; only first-order relations can be integrated"
            )
        if term.channel not in (None, state) and term.order > 0:
            raise ConfigError(
                f"subsystems.{key}.state: r{key[1:]} holds a derivative of {term.channel!r}; "
                "only the state may be derived"
            )


def _parse_subsystem(key: str, raw: Any) -> SubsystemConfig:
    name = f"subsystems.{key}"
    if key not in SUBSYSTEM_SENSOR:
        raise ConfigError(f"{name}: unknown subsystem (known: {', '.join(SUBSYSTEM_SENSOR)})")
    obj = _object(name, raw, _SUBSYSTEM_FIELDS)
    state = obj.get("state", SUBSYSTEM_SENSOR[key])
    if state not in CHANNELS:
        raise ConfigError(f"{name}.state: unknown channel {state!r}")
    measurement = obj.get("measurement", "relation")
    if measurement not in ("relation", "state"):
        raise ConfigError(f"{name}.measurement: expected relation or state, got {measurement!r}")
    if measurement == "state":
        _subsystem_structure(key, state)
    params = obj.get("parameters")
    in_relation = sorted({p for t in DARR_TERMS["r" + key[1:]] for p, _ in t.powers})
    if (
        not isinstance(params, Sequence)
        or isinstance(params, str)
        or not params
        or len(params) > kern.MAX_PARAMS
    ):
        raise ConfigError(f"{name}.parameters: expected 1 to {kern.MAX_PARAMS} parameter names")
    for p in params:
        if p not in in_relation:
            raise ConfigError(
                f"{name}.parameters: {p!r} is not in r{key[1:]} (it has {', '.join(in_relation)})"
            )
    if len(set(params)) != len(params):
        raise ConfigError(f"{name}.parameters: a parameter is listed twice")
    parameters = tuple(str(p) for p in params)
    estimator = obj.get("estimator", "fekf")
    if estimator not in ("ekf", "fekf"):
        raise ConfigError(f"{name}.estimator: expected ekf or fekf, got {estimator!r}")
    bounds_raw = obj.get("bounds", SubsystemConfig.bounds)
    if not isinstance(bounds_raw, Sequence) or isinstance(bounds_raw, str) or len(bounds_raw) != 2:
        raise ConfigError(f"{name}.bounds: expected [low, high]")
    bounds = (
        _positive(f"{name}.bounds[0]", bounds_raw[0]),
        _positive(f"{name}.bounds[1]", bounds_raw[1]),
    )
    if not bounds[0] < 1.0 < bounds[1]:
        raise ConfigError(f"{name}.bounds: expected low < 1 < high (relative to nominal)")
    return SubsystemConfig(
        state=state,
        parameters=parameters,
        estimator=estimator,
        measurement=measurement,
        r=_auto_or_positive(f"{name}.r", obj.get("r", "auto")),
        q_state=_auto_or_positive(f"{name}.q_state", obj.get("q_state", "auto")),
        p0_state=_auto_or_positive(f"{name}.p0_state", obj.get("p0_state", "auto")),
        q_parameters=_per_parameter(
            f"{name}.q_parameters",
            obj.get("q_parameters", DEFAULT_Q_PARAMETER),
            parameters,
            DEFAULT_Q_PARAMETER,
        ),
        p0_parameters=_per_parameter(
            f"{name}.p0_parameters",
            obj.get("p0_parameters", DEFAULT_P0_PARAMETER),
            parameters,
            DEFAULT_P0_PARAMETER,
        ),
        fuzzy=_parse_fuzzy(f"{name}.fuzzy", obj.get("fuzzy", {})),
        bounds=bounds,
    )


_CONFIG_FIELDS = (
    "channels",
    "sample_period_s",
    "parameters",
    "differentiator_window_s",
    "max_missing_fraction",
    "thresholds",
    "min_duration_s",
    "clear_after_s",
    "set_gains",
    "noise_std",
    "max_candidate_size",
    "max_candidates",
    "subsystems",
    "health_window_samples",
)


def _int_in(name: str, value: Any, lo: int, hi: int) -> int:
    if not isinstance(value, int) or isinstance(value, bool) or not lo <= value <= hi:
        raise ConfigError(f"{name}: expected an integer in [{lo}, {hi}], got {value!r}")
    return value


def _parse_channels(raw: Any) -> dict[str, str]:
    obj = _object("channels", raw, CHANNELS)
    channels = {c: c for c in CHANNELS}
    for key, value in obj.items():
        if not isinstance(value, str) or not value:
            raise ConfigError(f"channels.{key}: expected a non-empty string, got {value!r}")
        channels[key] = value
    if len(set(channels.values())) != len(CHANNELS):
        raise ConfigError("channels: two model channels map to the same stream channel")
    return channels


def _parse_parameters(raw: Any) -> dict[str, float]:
    obj = _object("parameters", raw, PARAMETER_NAMES)
    params = dict(NOMINAL)
    for key, value in obj.items():
        params[key] = _finite(f"parameters.{key}", value)
    for key in ("c_hj", "r_il", "m_h", "m_r", "m_screw", "l_w", "j_m", "k_s", "k_1", "k_2"):
        if params[key] <= 0.0:
            raise ConfigError(f"parameters.{key}: must be positive")
    return params


def parse_config(raw: Mapping[str, Any]) -> DarrFekfConfig:
    """Validate a JSON-like mapping into a :class:`DarrFekfConfig`.

    Raises:
        ConfigError: naming the first bad field (unknown keys, wrong types, non-positive
            values, a subsystem whose relation cannot be integrated or whose parameters are not
            in it, "auto" noise with no calibration window, ...).
    """
    obj = _object("", raw, _CONFIG_FIELDS) if isinstance(raw, Mapping) else None
    if obj is None:
        raise ConfigError(f"config: expected an object, got {type(raw).__name__}")
    thresholds = _parse_thresholds(obj.get("thresholds", {}))
    set_gains_raw = obj.get("set_gains", ["k_q", "k_c"])
    if not isinstance(set_gains_raw, Sequence) or isinstance(set_gains_raw, str):
        raise ConfigError("set_gains: expected a list of parameter names")
    for p in set_gains_raw:
        if p not in PARAMETER_NAMES:
            raise ConfigError(f"set_gains: unknown parameter {p!r}")
    noise_raw = _object("noise_std", obj.get("noise_std", {}), CHANNELS)
    noise = {
        str(k): _non_negative(f"noise_std.{k}", v) for k, v in noise_raw.items() if v != "auto"
    }
    subs_raw = obj.get("subsystems", DEFAULT_SUBSYSTEMS)
    if not isinstance(subs_raw, Mapping):
        raise ConfigError("subsystems: expected an object by subsystem name")
    subsystems = {str(k): _parse_subsystem(str(k), v) for k, v in sorted(subs_raw.items())}
    sample_period = _positive("sample_period_s", obj.get("sample_period_s", 1.0e-4))
    window_s = _positive("differentiator_window_s", obj.get("differentiator_window_s", 0.05))
    missing = _finite("max_missing_fraction", obj.get("max_missing_fraction", 0.1))
    if not 0.0 <= missing < 1.0:
        raise ConfigError(f"max_missing_fraction: expected a number in [0, 1), got {missing!r}")
    needs_noise = any(
        s.r == "auto" or (s.measurement == "state" and s.q_state == "auto")
        for s in subsystems.values()
    )
    if thresholds.window_s <= 0.0 and (thresholds.rule != "fixed" or needs_noise):
        raise ConfigError(
            "thresholds.window_s: a calibration window is needed (calibrated thresholds or "
            '"auto" noise)'
        )
    try:
        return DarrFekfConfig(
            channels=_parse_channels(obj.get("channels", {})),
            sample_period_s=sample_period,
            parameters=_parse_parameters(obj.get("parameters", {})),
            differentiator_window_s=window_s,
            max_missing_fraction=missing,
            thresholds=thresholds,
            min_duration_s=_non_negative("min_duration_s", obj.get("min_duration_s", 0.002)),
            clear_after_s=_positive("clear_after_s", obj.get("clear_after_s", 1.0)),
            set_gains=tuple(str(p) for p in set_gains_raw),
            noise_std=noise,
            max_candidate_size=_int_in(
                "max_candidate_size", obj.get("max_candidate_size", 3), 1, 6
            ),
            max_candidates=_int_in("max_candidates", obj.get("max_candidates", 100), 1, 10_000),
            subsystems=subsystems,
            health_window_samples=_int_in(
                "health_window_samples", obj.get("health_window_samples", 10_000), 1, 100_000_000
            ),
        )
    except ValueError as exc:  # from _compile: a window too short for the derivative order
        if isinstance(exc, ConfigError):
            raise
        raise ConfigError(f"differentiator_window_s: {exc}") from exc


def config_to_dict(config: DarrFekfConfig) -> dict[str, Any]:
    """The full configuration with defaults filled in, JSON-serializable."""
    thr = config.thresholds
    return {
        "channels": dict(config.channels),
        "sample_period_s": config.sample_period_s,
        "parameters": dict(config.parameters),
        "differentiator_window_s": config.differentiator_window_s,
        "max_missing_fraction": config.max_missing_fraction,
        "thresholds": {
            "rule": thr.rule,
            "window_s": thr.window_s,
            "margin": thr.margin,
            "q": thr.q,
            **({"values": list(thr.values)} if thr.values is not None else {}),
        },
        "min_duration_s": config.min_duration_s,
        "clear_after_s": config.clear_after_s,
        "set_gains": list(config.set_gains),
        "noise_std": dict(config.noise_std),
        "max_candidate_size": config.max_candidate_size,
        "max_candidates": config.max_candidates,
        "subsystems": {
            key: {
                "state": s.state,
                "parameters": list(s.parameters),
                "estimator": s.estimator,
                "measurement": s.measurement,
                "r": s.r,
                "q_state": s.q_state,
                "p0_state": s.p0_state,
                "q_parameters": dict(zip(s.parameters, s.q_parameters, strict=True)),
                "p0_parameters": dict(zip(s.parameters, s.p0_parameters, strict=True)),
                "fuzzy": {
                    "c": s.fuzzy.c,
                    "window_s": s.fuzzy.window_s,
                    "input_levels": list(s.fuzzy.input_levels),
                    "output_levels": list(s.fuzzy.output_levels),
                    "alpha_min": s.fuzzy.alpha_min,
                },
                "bounds": list(s.bounds),
            }
            for key, s in config.subsystems.items()
        },
        "health_window_samples": config.health_window_samples,
    }


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
    arrays = [cfg, w0, sub_cfg, sub_coef, sub_exp]
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
        n_window=n_window,
        box=box,
        n_hist=kern.MAX_ORDER * box + 1,
        cal_capacity=cal_capacity,
        fused=tuple(fused),
    )


# ----------------------------------------------------------------------------- state
@dataclass(frozen=True)
class DarrFekfState:
    """Everything carried between batches (arrays never modified in place: ``step`` copies).

    Attributes:
        version: schema version (``STATE_VERSION``).
        t_last_s: time of the last sample seen (-inf before any).
        scalars: (``darr_kernels.ST_LEN``,) counters, calibration and detection state, health
            accumulators, thresholds and noise variances (``ST_*`` layout).
        history: (9, stages, H) ring buffers of the smoother's box stages (stage 0: the raw
            values, missing samples holding the last valid value).
        box_sums: (9, stages) running sums of the box stages.
        missing: (9, W) 1 where a sample of the smoother's support was missing.
        subsystems: (subsystems, ``SS_LEN``) the subsystem filters (``SS_*`` layout).
        calibration_buffer: (capacity, 7) |r| kept during a quantile calibration.
    """

    version: int
    t_last_s: float
    scalars: FloatArray
    history: FloatArray
    box_sums: FloatArray
    missing: FloatArray
    subsystems: FloatArray
    calibration_buffer: FloatArray

    @property
    def thresholds(self) -> FloatArray:
        """Thresholds in use (NaN before calibration)."""
        return self.scalars[kern.ST_THR : kern.ST_THR + kern.N_RES].copy()

    @property
    def coherence_vector(self) -> tuple[int, ...]:
        """Latched coherence vector of the active fault (zeros when none)."""
        return tuple(int(v) for v in self.scalars[kern.ST_LATCH : kern.ST_LATCH + kern.N_RES])

    @property
    def fault_active(self) -> bool:
        """True between a detection and its clearance."""
        return bool(self.scalars[kern.ST_FAULT] == 1.0)

    @property
    def noise_std(self) -> dict[str, float | None]:
        """Measurement noise standard deviation by model channel (None: not known yet)."""
        var = self.scalars[kern.ST_NOISE_VAR : kern.ST_NOISE_VAR + kern.N_CHAN]
        return {
            c: (math.sqrt(v) if math.isfinite(v) else None)
            for c, v in zip(CHANNELS, var, strict=True)
        }


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
    sc[kern.ST_NOISE_VAR : kern.ST_NOISE_VAR + kern.N_CHAN] = [
        config.noise_std[c] ** 2 if c in config.noise_std else np.nan for c in CHANNELS
    ]
    if config.thresholds.rule == "fixed":
        assert config.thresholds.values is not None
        sc[kern.ST_THR : kern.ST_THR + kern.N_RES] = config.thresholds.values
        sc[kern.ST_THR_READY] = 1.0
    if config.thresholds.window_s <= 0.0:
        sc[kern.ST_CALIBRATED] = 1.0
    n_sub = len(config.subsystems)
    return DarrFekfState(
        version=STATE_VERSION,
        t_last_s=-math.inf,
        scalars=_frozen(sc),
        history=_frozen(np.zeros((kern.N_CHAN, kern.N_STAGES, comp.n_hist))),
        box_sums=_frozen(np.zeros((kern.N_CHAN, kern.N_STAGES))),
        missing=_frozen(np.zeros((kern.N_CHAN, comp.n_window))),
        subsystems=_frozen(np.zeros((n_sub, kern.SS_LEN))),
        calibration_buffer=_frozen(np.zeros((comp.cal_capacity, kern.N_RES))),
    )


_ARRAYS = ("scalars", "history", "box_sums", "missing", "subsystems", "calibration_buffer")


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


def load_state(data: bytes) -> DarrFekfState:
    """Inverse of :func:`dump_state`.

    Raises:
        StateVersionError: the version is not ``STATE_VERSION``.
        EstimatorError: the bytes are not a darr_fekf state.
    """
    try:
        doc = json.loads(data)
    except (ValueError, UnicodeDecodeError) as exc:
        raise EstimatorError(f"not a darr_fekf state: {exc}") from exc
    if not isinstance(doc, dict) or "version" not in doc:
        raise EstimatorError("not a darr_fekf state: no version")
    if doc["version"] != STATE_VERSION:
        raise StateVersionError(
            f"darr_fekf state version {doc['version']!r} is not supported "
            f"(expected {STATE_VERSION})"
        )
    try:
        arrays = {name: _decode(doc[name]) for name in _ARRAYS}
        t_last = float.fromhex(doc["t_last_s"])
    except (KeyError, TypeError, ValueError) as exc:
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
        "calibration_buffer": (comp.cal_capacity, kern.N_RES),
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


def _component(vector: Sequence[int]) -> str:
    return "+".join(f"s{i + 1}" for i, c in enumerate(vector) if c)


def _candidates(config: DarrFekfConfig, vector: Sequence[int]) -> list[list[str]]:
    return candidate_sets(
        vector, config.set_gains, config.max_candidate_size, config.max_candidates
    )


def _candidate_text(candidates: list[list[str]], limit: int = 6) -> str:
    shown = ["{" + ", ".join(c) + "}" for c in candidates[:limit]]
    more = f" and {len(candidates) - limit} more" if len(candidates) > limit else ""
    return ", ".join(shown) + more if shown else "none consistent"


def _event(row: FloatArray, config: DarrFekfConfig) -> EstimatorEvent:
    t = float(row[kern.EV_T])
    kind = row[kern.EV_KIND]
    if kind == kern.EV_CALIBRATED:
        thr = config.thresholds
        detail: dict[str, Any] = {
            "thresholds": {
                r: _finite_or_none(row[kern.EV_THR + i]) for i, r in enumerate(RESIDUALS)
            },
            "source": "config" if thr.rule == "fixed" else "calibrated",
            "rule": thr.rule,
            "window_s": thr.window_s,
            "margin": thr.margin,
            "q": thr.q,
            "noise_std": {
                c: _finite_or_none(row[kern.EV_NOISE + i]) for i, c in enumerate(CHANNELS)
            },
            "lag_s": config.lag_s,
        }
        return EstimatorEvent(t_s=t, kind="thresholds_calibrated", detail=detail)
    vector = _mask_to_vector(row[kern.EV_MASK])
    residuals = [r for r, c in zip(RESIDUALS, vector, strict=True) if c]
    base = {
        "component": _component(vector),
        "residuals": residuals,
        "coherence_vector": vector,
        "first_detected_s": _finite_or_none(row[kern.EV_FIRST_T]),
        "lag_s": config.lag_s,
    }
    if kind == kern.EV_DETECTED:
        prev = _mask_to_vector(row[kern.EV_PREV_MASK])
        detail = {
            **base,
            "candidates": _candidates(config, vector),
            "detected_s": t,
            "update": any(prev),
            "new_residuals": [
                r for r, c, p in zip(RESIDUALS, vector, prev, strict=True) if c and not p
            ],
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


def _fault_reason(config: DarrFekfConfig, vector: Sequence[int]) -> str:
    residuals = ", ".join(r for r, c in zip(RESIDUALS, vector, strict=True) if c)
    return f"fault: residuals {residuals} over threshold; candidate fault sets " + _candidate_text(
        _candidates(config, vector)
    )


def _parameters(config: DarrFekfConfig, state: DarrFekfState) -> dict[str, Any]:
    """Running subsystems' estimates: per subsystem and fused (inverse-variance weighted)."""
    per_sub: dict[str, Any] = {}
    fused: dict[str, list[tuple[float, float]]] = {}
    for i, (key, sub) in enumerate(config.subsystems.items()):
        row = state.subsystems[i]
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
    sc = state.scalars
    vector = list(state.coherence_vector)
    thr_ready = sc[kern.ST_THR_READY] == 1.0
    residuals = {
        r: {
            "value": _finite_or_none(sc[kern.ST_LAST_R + i]),
            "threshold": _finite_or_none(sc[kern.ST_THR + i]) if thr_ready else None,
            "exceeded": bool(vector[i]),
            "unit": RESIDUAL_UNITS[r],
        }
        for i, r in enumerate(RESIDUALS)
    }
    detail: dict[str, Any] = {
        "residuals": residuals,
        "coherence_vector": vector,
        "signature_matrix": {p: list(row) for p, row in SIGNATURES.items()},
        "candidates": _candidates(config, vector),
        "detectable": {p: any(row) for p, row in SIGNATURES.items()},
        "set_gains": list(config.set_gains),
        "fault_active": state.fault_active,
        "first_detected_s": _finite_or_none(sc[kern.ST_FIRST_T]) if state.fault_active else None,
        "calibrated": bool(sc[kern.ST_CALIBRATED] == 1.0),
        "thresholds_ready": bool(thr_ready),
        "noise_std": state.noise_std,
        "lag_s": config.lag_s,
        "irregular_intervals": int(sc[kern.ST_IRREGULAR]),
    }
    detail.update(_parameters(config, state))
    return detail


# ----------------------------------------------------------------------------- step


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
        arrays["scalars"],
        arrays["history"],
        arrays["box_sums"],
        arrays["missing"],
        arrays["subsystems"],
        arrays["calibration_buffer"],
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
    if new_state.fault_active:
        report = StatusReport("alert", (_fault_reason(config, new_state.coherence_vector),))
    else:
        report = StatusReport("ok")
    outputs = StepOutputs(
        samples={name: out[i] for i, name in enumerate(names)},
        health=[_health(row, config) for row in windows],
        events=[_event(row, config) for row in events],
        diagnosis=Diagnosis(t_s=float(t[n - 1]), detail=diagnosis_detail(config, new_state)),
        status=report,
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
