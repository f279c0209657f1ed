"""Improved strong-tracking multiple-model adaptive estimation (STMMAE) of control-surface faults.

A bank of Kalman-type filters runs on a discrete linear(ized) aircraft model given in the
configuration (seed paper: Ma, Ni, Xie, Dong, "Fast fault diagnosis of improved strong tracking
aircraft actuator", Systems Engineering and Electronics 37(11), 2015): one no-fault filter and one
filter per monitored surface, which augments the state with that surface's actual deflection
(a random walk) and drops the surface's command from its input. Each filter is a strong tracking
filter with multiple fading factors; the seed's improvement applies the fading matrix on both
sides of the propagated covariance, ``P- = L Phi P Phi^T L + Q``, keeping P symmetric. The
original one-sided form (``strong_tracking``) and a plain Kalman bank (``emmae``) are selectable.
Hypothesis probabilities follow the Bayes recursion with either the seed's Euclidean-norm
likelihood or the full Gaussian density, floored at ``probability_floor``; a hypothesis held
above ``detect_probability`` for ``hold_s`` is a fault, cleared when below
``clear_probability`` for ``clear_hold_s``.

Equations, choices where the seed is silent and the configuration reference:
``docs/methods-stmmae.md``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, fields
from typing import Any, Literal

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
    Status,
    StatusReport,
    StepOutputs,
    dump_vector_state,
    load_vector_state,
)
from estimators.checks import channel_block
from estimators.checks import finite_or_none as _finite
from estimators.checks import is_number as _is_number
from estimators.kernels import stmmae_kernels as kern
from estimators.models.small_uav import reference_model

NAME = "stmmae"
STATE_VERSION = 2

Variant = Literal["improved", "strong_tracking", "emmae"]
Likelihood = Literal["euclidean", "gaussian"]
VARIANTS: dict[str, int] = {
    "improved": kern.VARIANT_IMPROVED,
    "strong_tracking": kern.VARIANT_STRONG_TRACKING,
    "emmae": kern.VARIANT_EMMAE,
}
LIKELIHOODS: dict[str, int] = {
    "euclidean": kern.LIKELIHOOD_EUCLIDEAN,
    "gaussian": kern.LIKELIHOOD_GAUSSIAN,
}
NOMINAL = "nominal"
MATRIX_KEYS = ("F", "G", "H", "Q", "R", "P0")


# ----------------------------------------------------------------------------- configuration
@dataclass(frozen=True)
class ModelInput:
    """One model input: a monitored surface (rad) or a known, unmonitored input."""

    name: str
    channel: str
    surface: bool


@dataclass(frozen=True)
class ModelMeasurement:
    """One measured model output and the channel carrying it."""

    name: str
    channel: str


@dataclass(frozen=True)
class LinearModel:
    """Discrete deviation model ``x_{k+1} - x* = F (x_k - x*) + G (u_k - u*) + w``,
    ``y_k = H x_k + v``, ``w ~ N(0, Q)``, ``v ~ N(0, R)``, sampled every ``dt_s``.

    Matrices are tuples of row tuples. ``x_trim``/``u_trim`` are ``x*``/``u*``; ``P0`` the
    initial covariance of ``x - x*``. Surface inputs are deflections in rad.
    """

    name: str
    dt_s: float
    states: tuple[str, ...]
    inputs: tuple[ModelInput, ...]
    measurements: tuple[ModelMeasurement, ...]
    F: tuple[tuple[float, ...], ...]  # noqa: N815 - the usual names of the model matrices
    G: tuple[tuple[float, ...], ...]  # noqa: N815
    H: tuple[tuple[float, ...], ...]  # noqa: N815
    Q: tuple[tuple[float, ...], ...]  # noqa: N815
    R: tuple[tuple[float, ...], ...]  # noqa: N815
    P0: tuple[tuple[float, ...], ...]  # noqa: N815
    x_trim: tuple[float, ...]
    u_trim: tuple[float, ...]

    @property
    def surfaces(self) -> tuple[str, ...]:
        """Names of the monitored surfaces, in input order."""
        return tuple(i.name for i in self.inputs if i.surface)

    def matrix(self, key: str) -> FloatArray:
        """One of ``F, G, H, Q, R, P0`` as a float64 array."""
        return np.array(getattr(self, key), dtype=np.float64)


@dataclass(frozen=True)
class StmmaeConfig:
    """Validated configuration (build it with :func:`parse_config`; fields documented in
    ``docs/methods-stmmae.md``, "Configuration")."""

    model: LinearModel
    variant: Variant = "improved"
    likelihood: Likelihood = "gaussian"
    forgetting_factor: float = 0.95
    weakening_factor: float | Literal["auto"] = "auto"
    fading_weights: tuple[float, ...] | None = None
    deflection_fading_weight: float = 1.0
    deflection_diffusion_deg2_s: float = 0.25
    deflection_initial_std_deg: float = 10.0
    probability_floor: float = 0.001
    detect_probability: float = 0.9
    clear_probability: float = 0.05
    hold_s: float = 0.1
    clear_hold_s: float = 0.1
    onset_probability: float = 0.5
    watch_probability: float = 0.5
    deflection_smoothing_s: float = 0.2
    fault_kind_window_s: float = 2.0
    deflection_limit_deg: float = 30.0
    oscillation_swing_deg: float = 2.0
    min_deflection_error_deg: float = 1.0
    nis_watch: float = 3.0
    health_window_samples: int = 1000
    # built once from the above (not part of the configuration's identity)
    kernel_vector: FloatArray = field(init=False, repr=False, compare=False, hash=False)
    arrays: kern.BankArrays = field(init=False, repr=False, compare=False, hash=False)
    surface_inputs: Any = field(init=False, repr=False, compare=False, hash=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "kernel_vector", _kernel_vector(self))
        object.__setattr__(self, "arrays", build_bank(self))
        idx = [i for i, inp in enumerate(self.model.inputs) if inp.surface]
        object.__setattr__(self, "surface_inputs", np.array(idx, dtype=np.int64))

    @property
    def hypotheses(self) -> tuple[str, ...]:
        """``nominal`` then the surfaces."""
        return (NOMINAL, *self.model.surfaces)




def _number(name: str, value: Any, lo: float, hi: float, *, lo_open: bool = False) -> float:
    if not _is_number(value) or not math.isfinite(float(value)):
        raise ConfigError(f"{name}: expected a finite number, got {value!r}")
    v = float(value)
    if v < lo or v > hi or (lo_open and v == lo):
        bracket = "(" if lo_open else "["
        raise ConfigError(f"{name}: expected a number in {bracket}{lo:g}, {hi:g}], got {v:g}")
    return v


def _name(name: str, value: Any) -> str:
    if not isinstance(value, str) or not value:
        raise ConfigError(f"{name}: expected a non-empty string, got {value!r}")
    return value


def _matrix(name: str, value: Any, rows: int, cols: int) -> tuple[tuple[float, ...], ...]:
    if not isinstance(value, Sequence) or isinstance(value, str) or len(value) != rows:
        raise ConfigError(f"{name}: expected {rows} rows of {cols} numbers")
    out = []
    for i, row in enumerate(value):
        if not isinstance(row, Sequence) or isinstance(row, str) or len(row) != cols:
            raise ConfigError(f"{name}[{i}]: expected a row of {cols} numbers")
        vals = []
        for j, v in enumerate(row):
            if not _is_number(v) or not math.isfinite(float(v)):
                raise ConfigError(f"{name}[{i}][{j}]: expected a finite number, got {v!r}")
            vals.append(float(v))
        out.append(tuple(vals))
    return tuple(out)


def _vector(name: str, value: Any, length: int) -> tuple[float, ...]:
    return _matrix(name, [value] if isinstance(value, Sequence) else value, 1, length)[0]


def _check_covariance(name: str, mat: tuple[tuple[float, ...], ...], *, definite: bool) -> None:
    arr = np.array(mat)
    if not np.array_equal(arr, arr.T):
        raise ConfigError(f"{name}: must be symmetric")
    low = float(np.linalg.eigvalsh(arr)[0]) if arr.size else 1.0
    if (definite and not low > 0.0) or low < 0.0:
        kind = "positive definite" if definite else "positive semi-definite"
        raise ConfigError(f"{name}: must be {kind} (smallest eigenvalue {low:.3g})")


def _names(name: str, value: Any) -> tuple[str, ...]:
    if not isinstance(value, Sequence) or isinstance(value, str) or not value:
        raise ConfigError(f"{name}: expected a non-empty list of names")
    names = tuple(_name(f"{name}[{i}]", v) for i, v in enumerate(value))
    if len(set(names)) != len(names):
        raise ConfigError(f"{name}: names must be unique")
    return names


def _inputs(value: Any) -> tuple[ModelInput, ...]:
    if not isinstance(value, Sequence) or isinstance(value, str) or not value:
        raise ConfigError("model.inputs: expected a non-empty list of {name, channel, surface}")
    out = []
    for i, item in enumerate(value):
        where = f"model.inputs[{i}]"
        if not isinstance(item, Mapping) or set(item) - {"name", "channel", "surface"}:
            raise ConfigError(f"{where}: expected an object {{name, channel, surface}}")
        surface = item.get("surface", True)
        if not isinstance(surface, bool):
            raise ConfigError(f"{where}.surface: expected true or false")
        nm = _name(f"{where}.name", item.get("name"))
        out.append(ModelInput(nm, _name(f"{where}.channel", item.get("channel")), surface))
    if not any(i.surface for i in out):
        raise ConfigError("model.inputs: at least one input must be a monitored surface")
    if len({i.name for i in out}) != len(out):
        raise ConfigError("model.inputs: names must be unique")
    if any(i.name == NOMINAL for i in out):
        raise ConfigError(f"model.inputs: {NOMINAL!r} is reserved for the no-fault hypothesis")
    return tuple(out)


def _measurements(value: Any) -> tuple[ModelMeasurement, ...]:
    if not isinstance(value, Sequence) or isinstance(value, str) or not value:
        raise ConfigError("model.measurements: expected a non-empty list of {name, channel}")
    out = []
    for i, item in enumerate(value):
        where = f"model.measurements[{i}]"
        if not isinstance(item, Mapping) or set(item) - {"name", "channel"}:
            raise ConfigError(f"{where}: expected an object {{name, channel}}")
        nm = _name(f"{where}.name", item.get("name"))
        out.append(ModelMeasurement(nm, _name(f"{where}.channel", item.get("channel"))))
    return tuple(out)


def parse_model(raw: Mapping[str, Any]) -> LinearModel:
    """Validate a model mapping (the shape of :func:`small_uav.reference_model`)."""
    if not isinstance(raw, Mapping):
        raise ConfigError("model: expected an object")
    known = {f.name for f in fields(LinearModel)}
    unknown = sorted(set(raw) - known)
    if unknown:
        raise ConfigError(f"model.{unknown[0]}: unknown field (known: {', '.join(sorted(known))})")
    missing = sorted(k for k in known if k not in raw and k != "name")
    if missing:
        raise ConfigError(f"model.{missing[0]}: missing")
    states = _names("model.states", raw["states"])
    inputs = _inputs(raw["inputs"])
    meas = _measurements(raw["measurements"])
    n, m, p = len(states), len(inputs), len(meas)
    channels = [i.channel for i in inputs] + [y.channel for y in meas]
    if len(set(channels)) != len(channels):
        raise ConfigError("model: every input and measurement needs its own channel")
    shapes = {"F": (n, n), "G": (n, m), "H": (p, n), "Q": (n, n), "R": (p, p), "P0": (n, n)}
    mats = {k: _matrix(f"model.{k}", raw[k], *shapes[k]) for k in MATRIX_KEYS}
    _check_covariance("model.Q", mats["Q"], definite=False)
    _check_covariance("model.R", mats["R"], definite=True)
    _check_covariance("model.P0", mats["P0"], definite=True)
    return LinearModel(
        name=_name("model.name", raw.get("name", "custom")),
        dt_s=_number("model.dt_s", raw["dt_s"], 0.0, 3600.0, lo_open=True),
        states=states,
        inputs=inputs,
        measurements=meas,
        x_trim=_vector("model.x_trim", raw["x_trim"], n),
        u_trim=_vector("model.u_trim", raw["u_trim"], m),
        **mats,
    )


def model_to_dict(model: LinearModel) -> dict[str, Any]:
    """JSON-ready form of a model (inverse of :func:`parse_model`)."""
    return {
        "name": model.name,
        "dt_s": model.dt_s,
        "states": list(model.states),
        "inputs": [
            {"name": i.name, "channel": i.channel, "surface": i.surface} for i in model.inputs
        ],
        "measurements": [{"name": y.name, "channel": y.channel} for y in model.measurements],
        **{k: [list(row) for row in getattr(model, k)] for k in MATRIX_KEYS},
        "x_trim": list(model.x_trim),
        "u_trim": list(model.u_trim),
    }


_SCALARS: dict[str, tuple[float, float, bool]] = {
    # name: (low, high, low excluded)
    "forgetting_factor": (0.0, 1.0, True),
    "deflection_fading_weight": (1.0, 1e6, False),
    "deflection_diffusion_deg2_s": (0.0, 1e6, True),
    "deflection_initial_std_deg": (0.0, 180.0, True),
    "probability_floor": (0.0, 0.01, True),
    "detect_probability": (0.5, 1.0, True),
    "clear_probability": (0.0, 0.5, True),
    "hold_s": (0.0, 3600.0, False),
    "clear_hold_s": (0.0, 3600.0, False),
    "onset_probability": (0.0, 1.0, True),
    "watch_probability": (0.0, 1.0, True),
    "deflection_smoothing_s": (0.0, 3600.0, True),
    "fault_kind_window_s": (0.0, 3600.0, True),
    "deflection_limit_deg": (0.0, 180.0, True),
    "oscillation_swing_deg": (0.0, 180.0, True),
    "min_deflection_error_deg": (0.0, 180.0, False),
    "nis_watch": (0.0, 1e6, True),
}


def parse_config(raw: Mapping[str, Any]) -> StmmaeConfig:
    """Validate a JSON-like mapping into a :class:`StmmaeConfig`.

    Raises:
        ConfigError: naming the first bad field (unknown keys, wrong types or shapes, values
            out of range, matrices that are not covariances, inconsistent thresholds).
    """
    if not isinstance(raw, Mapping):
        raise ConfigError(f"config: expected an object, got {type(raw).__name__}")
    known = {f.name for f in fields(StmmaeConfig) if f.init}
    unknown = sorted(set(raw) - known)
    if unknown:
        raise ConfigError(f"{unknown[0]}: unknown field (known: {', '.join(sorted(known))})")
    model = parse_model(raw["model"] if raw.get("model") is not None else reference_model())
    variant = raw.get("variant", "improved")
    if variant not in VARIANTS:
        raise ConfigError(f"variant: expected one of {', '.join(VARIANTS)}, got {variant!r}")
    likelihood = raw.get("likelihood", "gaussian")
    if likelihood not in LIKELIHOODS:
        raise ConfigError(
            f"likelihood: expected one of {', '.join(LIKELIHOODS)}, got {likelihood!r}"
        )
    default = {f.name: f.default for f in fields(StmmaeConfig) if f.init}
    scalars = {
        key: _number(key, raw.get(key, default[key]), lo, hi, lo_open=lo_open)
        for key, (lo, hi, lo_open) in _SCALARS.items()
    }
    beta = raw.get("weakening_factor", "auto")
    if beta != "auto":
        beta = _number("weakening_factor", beta, 1.0, 1e6)
    weights = raw.get("fading_weights")
    if weights is not None:
        weights = _vector("fading_weights", weights, len(model.states))
        if min(weights) < 1.0:
            raise ConfigError("fading_weights: every weight must be >= 1")
    window = raw.get("health_window_samples", default["health_window_samples"])
    if not isinstance(window, int) or isinstance(window, bool) or not 1 <= window <= 10**8:
        raise ConfigError(f"health_window_samples: expected an integer in [1, 1e8], got {window!r}")
    if scalars["clear_probability"] >= scalars["detect_probability"]:
        raise ConfigError("clear_probability: must be below detect_probability")
    if 1.0 - len(model.surfaces) * scalars["probability_floor"] <= 0.5:
        raise ConfigError("probability_floor: too large for the number of hypotheses")
    return StmmaeConfig(
        model=model,
        variant=variant,
        likelihood=likelihood,
        weakening_factor=beta,
        fading_weights=weights,
        health_window_samples=window,
        **scalars,
    )


def config_to_dict(config: StmmaeConfig) -> dict[str, Any]:
    """The full configuration with defaults filled in, JSON-serializable."""
    out: dict[str, Any] = {"model": model_to_dict(config.model)}
    for f in fields(StmmaeConfig):
        if not f.init or f.name == "model":
            continue
        value = getattr(config, f.name)
        out[f.name] = list(value) if isinstance(value, tuple) else value
    return out


def required_channels(config: StmmaeConfig) -> tuple[str, ...]:
    """Measurement channels, then input (command) channels."""
    m = config.model
    return tuple(y.channel for y in m.measurements) + tuple(i.channel for i in m.inputs)


def weakening_factor(config: StmmaeConfig) -> float:
    """The weakening factor in use. "auto": ``1 + 3 sqrt(2 (1 - rho) / (p (1 + rho)))``, three
    standard deviations of the relative fluctuation of ``tr(W V)`` on a consistent filter (an
    exponential average of ``(1 + rho) / (1 - rho)`` samples of a chi-square with p degrees of
    freedom), so that noise alone rarely triggers fading."""
    if config.weakening_factor != "auto":
        return float(config.weakening_factor)
    rho = config.forgetting_factor
    p = len(config.model.measurements)
    return 1.0 + 3.0 * math.sqrt(2.0 * (1.0 - rho) / (p * (1.0 + rho)))


def _kernel_vector(config: StmmaeConfig) -> FloatArray:
    cfg = np.zeros(kern.CFG_LEN)
    cfg[kern.CFG_VARIANT] = VARIANTS[config.variant]
    cfg[kern.CFG_LIKELIHOOD] = LIKELIHOODS[config.likelihood]
    cfg[kern.CFG_RHO] = config.forgetting_factor
    cfg[kern.CFG_BETA] = weakening_factor(config)
    cfg[kern.CFG_FLOOR] = config.probability_floor
    cfg[kern.CFG_DETECT_P] = config.detect_probability
    cfg[kern.CFG_CLEAR_P] = config.clear_probability
    cfg[kern.CFG_HOLD_S] = config.hold_s
    cfg[kern.CFG_CLEAR_HOLD_S] = config.clear_hold_s
    cfg[kern.CFG_ONSET_P] = config.onset_probability
    cfg[kern.CFG_WINDOW] = config.health_window_samples
    cfg[kern.CFG_SMOOTH_S] = config.deflection_smoothing_s
    cfg[kern.CFG_MIN_ERR] = math.radians(config.min_deflection_error_deg)
    cfg[kern.CFG_LIMIT] = math.radians(config.deflection_limit_deg)
    cfg[kern.CFG_KIND_WINDOW_S] = config.fault_kind_window_s
    cfg.setflags(write=False)
    return cfg


def build_bank(config: StmmaeConfig) -> kern.BankArrays:
    """The bank's matrices: filter 0 is the model itself (its extra state fixed at zero);
    filter ``h`` augments the state with surface ``h``'s deflection ``d``:

        [x; d]_{k+1} = [[F, G_h], [0, 1]] [x; d]_k + G_(0,h) (u_k - u*) - G_h u*_h
        Q_h = blkdiag(Q, q_d),  q_d = deflection_diffusion * dt,  P0_h = blkdiag(P0, s_d^2)

    with ``G_h`` the surface's input column and ``G_(0,h)`` the input matrix with that column set
    to zero.
    """
    mdl = config.model
    f, g, h, q, r, p0 = (mdl.matrix(k) for k in MATRIX_KEYS)
    n, m = g.shape
    surf_idx = [i for i, inp in enumerate(mdl.inputs) if inp.surface]
    nh, na = 1 + len(surf_idx), n + 1
    u_trim = np.array(mdl.u_trim)
    x_trim = np.array(mdl.x_trim)
    q_d = math.radians(1.0) ** 2 * config.deflection_diffusion_deg2_s * mdl.dt_s
    s_d2 = math.radians(config.deflection_initial_std_deg) ** 2
    phi = np.zeros((nh, na, na))
    gin = np.zeros((nh, na, m))
    offset = np.zeros((nh, na))
    qa = np.zeros((nh, na, na))
    x0 = np.zeros((nh, na))
    p0a = np.zeros((nh, na, na))
    weights = np.ones(n) if config.fading_weights is None else np.array(config.fading_weights)
    aw = np.ones((nh, na))
    for hyp in range(nh):
        phi[hyp, :n, :n] = f
        gin[hyp, :n, :] = g
        qa[hyp, :n, :n] = q
        p0a[hyp, :n, :n] = p0
        aw[hyp, :n] = weights
        if hyp == 0:
            continue
        col = surf_idx[hyp - 1]
        phi[hyp, :n, n] = g[:, col]
        phi[hyp, n, n] = 1.0
        gin[hyp, :n, col] = 0.0
        offset[hyp, :n] = -g[:, col] * u_trim[col]
        qa[hyp, n, n] = q_d
        p0a[hyp, n, n] = s_d2
        x0[hyp, n] = u_trim[col]
        aw[hyp, n] = config.deflection_fading_weight
    ha = np.zeros((h.shape[0], na))
    ha[:, :n] = h
    hqh = np.einsum("ij,hjk,ik->hi", ha, qa, ha)
    arrays = kern.BankArrays(
        phi=phi,
        gin=gin,
        offset=offset,
        q=qa,
        h=ha,
        r=r,
        **_sparse_rows("hth", (ha.T @ (ha / np.diag(r)[:, None]))[None])[0],
        hqh_diag=np.ascontiguousarray(hqh),
        **_sparse_rows("h", ha[None])[0],
        **_sparse_rows("phi", phi)[1],
        phi_t=np.ascontiguousarray(phi.transpose(0, 2, 1)),
        fading_weights=aw,
        euclid_weights=1.0 / np.diag(r),
        x_trim=x_trim,
        u_trim=u_trim,
        y_trim=h @ x_trim,
        x0=x0,
        p0=p0a,
    )
    for a in arrays:
        a.setflags(write=False)
    return arrays


def _sparse_rows(name: str, mats: FloatArray) -> tuple[dict[str, Any], dict[str, Any]]:
    """Non-zero entries of each row of a stack of matrices ``mats`` (k, rows, cols), as the
    kernel reads them: ``(first, all)`` where ``first`` holds the arrays of ``mats[0]`` alone
    and ``all`` those of the whole stack, keyed ``<name>_cols``, ``<name>_vals``,
    ``<name>_nnz``."""
    nnz = np.count_nonzero(mats, axis=2)
    cols = np.zeros((*mats.shape[:2], max(int(nnz.max()), 1)), dtype=np.int64)
    vals = np.zeros(cols.shape)
    for f in range(mats.shape[0]):
        for i in range(mats.shape[1]):
            c = np.flatnonzero(mats[f, i])
            cols[f, i, : c.size] = c
            vals[f, i, : c.size] = mats[f, i, c]
    nnz = nnz.astype(np.int64)
    keys = (f"{name}_cols", f"{name}_vals", f"{name}_nnz")
    return (
        dict(zip(keys, (cols[0], vals[0], nnz[0]), strict=True)),
        dict(zip(keys, (cols, vals, nnz), strict=True)),
    )


# ----------------------------------------------------------------------------- state
@dataclass(frozen=True)
class StmmaeState:
    """Everything the bank carries between batches.

    Attributes:
        version: schema version (``STATE_VERSION``).
        t_last_s: time of the last sample seen (-inf before any).
        vector: flat float64 vector laid out by ``stmmae_kernels.state_layout`` (filters' x, P
            and innovation covariance estimates, probabilities, last inputs, decision fields,
            health-window accumulators). Never modified in place.
    """

    version: int
    t_last_s: float
    vector: FloatArray


def layout(config: StmmaeConfig) -> kern.Layout:
    """The state layout of a configuration's bank."""
    nh, na = config.arrays.x0.shape
    return kern.state_layout(nh, na, config.arrays.h.shape[0], config.arrays.gin.shape[2])


def initial_state(config: StmmaeConfig) -> StmmaeState:
    """Filters at the trim (fault filters: deflection at its trim), no-fault probability
    ``1 - (number of surfaces) * floor``, each fault hypothesis at the floor."""
    lay = layout(config)
    arr = config.arrays
    vec = np.zeros(lay.length)
    vec[kern.ST_T_PREV] = np.nan
    for f in range(lay.nh):
        off = lay.filt + f * lay.filt_len
        vec[off : off + lay.na] = arr.x0[f]
        vec[off + lay.na : off + lay.na + lay.na * lay.na] = arr.p0[f].ravel()
    floor = config.probability_floor
    vec[lay.probs] = 1.0 - (lay.nh - 1) * floor
    vec[lay.probs + 1 : lay.probs + lay.nh] = floor
    vec[lay.u_last : lay.u_last + lay.m] = arr.u_trim
    for h in range(lay.nh - 1):
        d = lay.decisions + h * kern.D_LEN
        for idx in (kern.D_ABOVE_T, kern.D_ONSET_T, kern.D_BELOW_T, kern.D_DETECTED_T):
            vec[d + idx] = np.nan
    vec.setflags(write=False)
    return StmmaeState(version=STATE_VERSION, t_last_s=-math.inf, vector=vec)


def dump_state(state: StmmaeState) -> bytes:
    """Versioned byte form of the state (exact round trip; see :func:`dump_vector_state`)."""
    return dump_vector_state(NAME, state.version, state.t_last_s, state.vector)


def load_state(data: bytes) -> StmmaeState:
    """Inverse of :func:`dump_state`.

    Raises:
        StateVersionError: the version is not ``STATE_VERSION``.
        EstimatorError: the bytes are not a state of this estimator.
    """
    t_last, vec = load_vector_state(data, NAME, STATE_VERSION, "an STMMAE")
    return StmmaeState(version=STATE_VERSION, t_last_s=t_last, vector=vec)


def filter_estimates(
    config: StmmaeConfig, state: StmmaeState
) -> list[tuple[FloatArray, FloatArray]]:
    """``(x, P)`` of each filter (deviation from trim; fault filters' last entry is the absolute
    deflection), hypothesis order."""
    lay = layout(config)
    out = []
    for f in range(lay.nh):
        off = lay.filt + f * lay.filt_len
        x = state.vector[off : off + lay.na].copy()
        p = state.vector[off + lay.na : off + lay.na + lay.na * lay.na].reshape(lay.na, lay.na)
        out.append((x, p.copy()))
    return out


def probabilities(config: StmmaeConfig, state: StmmaeState) -> dict[str, float]:
    """Hypothesis probabilities at the last sample."""
    lay = layout(config)
    vals = state.vector[lay.probs : lay.probs + lay.nh]
    return {h: float(v) for h, v in zip(config.hypotheses, vals, strict=True)}


# ----------------------------------------------------------------------------- outputs
def sample_output_names(config: StmmaeConfig) -> tuple[str, ...]:
    """Names of the per-sample outputs, in the kernel's row order."""
    return (
        tuple(f"prob_{h}" for h in config.hypotheses)
        + tuple(f"state_{s}" for s in config.model.states)
        + tuple(f"deflection_{s}" for s in config.model.surfaces)
        + ("nis_nominal",)
    )




def _deg(value: float) -> float | None:
    v = _finite(value)
    return None if v is None else round(math.degrees(v), 6)


def _fault_kind(swing_rad: float, config: StmmaeConfig) -> str:
    return "oscillating" if swing_rad > math.radians(config.oscillation_swing_deg) else "stuck"


def _fault_detail(config: StmmaeConfig, hyp: int, d: FloatArray) -> dict[str, Any]:
    """Detail of an active fault from its decision fields."""
    swing = kern.episode_swing(d.reshape(1, -1), 0)
    kind = _fault_kind(swing, config)
    mean = kern.episode_mean(d.reshape(1, -1), 0)
    return {
        "component": config.hypotheses[hyp],
        "fault_kind": kind,
        "stuck_position_deg": _deg(mean) if kind == "stuck" else None,
        "deflection_swing_deg": _deg(swing),
        "onset_s": _finite(d[kern.D_ONSET_T]),
        "detected_s": _finite(d[kern.D_DETECTED_T]),
    }


def _event(row: FloatArray, config: StmmaeConfig) -> EstimatorEvent:
    hyp = int(row[kern.EV_HYP])
    kind = _fault_kind(float(row[kern.EV_SWING]), config)
    detail: dict[str, Any] = {
        "component": config.hypotheses[hyp],
        "fault_kind": kind,
        "stuck_position_deg": _deg(row[kern.EV_MEAN]) if kind == "stuck" else None,
        "deflection_swing_deg": _deg(row[kern.EV_SWING]),
        "onset_s": _finite(row[kern.EV_ONSET_T]),
        "detected_s": _finite(row[kern.EV_DETECTED_T]),
    }
    if row[kern.EV_KIND] == kern.EV_CLEARED:
        detail["cleared_s"] = _finite(row[kern.EV_CLEARED_T])
        return EstimatorEvent(t_s=float(row[kern.EV_T]), kind="fault_cleared", detail=detail)
    return EstimatorEvent(t_s=float(row[kern.EV_T]), kind="fault_detected", detail=detail)


def _fault_reason(f: dict[str, Any]) -> str:
    if f["fault_kind"] == "stuck":
        return f"fault: {f['component']} stuck at {f['stuck_position_deg']:.1f} deg"
    return f"fault: {f['component']} oscillating, swing {f['deflection_swing_deg']:.1f} deg"


def active_faults(config: StmmaeConfig, state: StmmaeState) -> list[dict[str, Any]]:
    """Details of the faults active at the last sample."""
    lay = layout(config)
    out = []
    for h in range(1, lay.nh):
        d = state.vector[lay.decisions + (h - 1) * kern.D_LEN : lay.decisions + h * kern.D_LEN]
        if d[kern.D_ACTIVE] == 1.0:
            out.append(_fault_detail(config, h, d))
    return out


def status_report(config: StmmaeConfig, state: StmmaeState) -> StatusReport:
    """ "alert" while a fault is active, "watch" while a fault hypothesis is above
    ``watch_probability`` without being confirmed, else "ok"."""
    faults = active_faults(config, state)
    if faults:
        return StatusReport("alert", tuple(_fault_reason(f) for f in faults))
    probs = probabilities(config, state)
    watch = [
        f"{h} probability {p:.2f} above {config.watch_probability:g}, not confirmed"
        for h, p in probs.items()
        if h != NOMINAL and p > config.watch_probability
    ]
    return StatusReport("watch", tuple(watch)) if watch else StatusReport("ok")


def diagnosis(config: StmmaeConfig, state: StmmaeState) -> Diagnosis:
    """Probabilities, active faults and deflection estimates at the last sample."""
    lay = layout(config)
    defl = {}
    for h, surface in enumerate(config.model.surfaces, start=1):
        defl[surface] = _deg(state.vector[lay.filt + h * lay.filt_len + lay.na - 1])
    return Diagnosis(
        t_s=float(state.t_last_s),
        detail={
            "probabilities": {h: _finite(p) for h, p in probabilities(config, state).items()},
            "active_faults": active_faults(config, state),
            "deflection_estimates_deg": defl,
            "variant": config.variant,
            "likelihood": config.likelihood,
        },
    )


def _health(row: FloatArray, config: StmmaeConfig) -> HealthWindow:
    max_hyp = int(row[kern.WIN_MAX_FAULT_HYP])
    indicators: dict[str, float | None] = {
        "nominal_probability_mean": _finite(row[kern.WIN_NOMINAL_MEAN]),
        "fault_probability_max": _finite(row[kern.WIN_MAX_FAULT]),
        "nis_nominal_mean": _finite(row[kern.WIN_NIS_MEAN]),
        "active_fault_fraction": _finite(row[kern.WIN_ACTIVE_FRACTION]),
        "covariance_failures": _finite(row[kern.WIN_COV_FAIL]),
    }
    reasons: list[str] = []
    status: Status = "ok"
    active = indicators["active_fault_fraction"] or 0.0
    pmax = indicators["fault_probability_max"] or 0.0
    nis = indicators["nis_nominal_mean"]
    if active > 0.0:
        status = "alert"
        reasons.append(f"fault active during {100 * active:.0f} % of the window")
    elif pmax > config.watch_probability:
        status = "watch"
        reasons.append(
            f"{config.hypotheses[max_hyp]} probability reached {pmax:.2f} "
            f"(watch {config.watch_probability:g})"
        )
    if nis is not None and nis > config.nis_watch and status == "ok":
        status = "watch"
        reasons.append(f"nis_nominal_mean {nis:.3g} > nis_watch {config.nis_watch:g}")
    if (indicators["covariance_failures"] or 0.0) > 0.0:
        status = "alert"
        reasons.append("innovation covariance not positive definite: filter diverging")
    return HealthWindow(
        t_start_s=float(row[kern.WIN_T0]),
        t_end_s=float(row[kern.WIN_T1]),
        n_samples=int(row[kern.WIN_N]),
        indicators=indicators,
        status=status,
        reasons=tuple(reasons),
    )




def step(config: StmmaeConfig, state: StmmaeState, batch: Batch) -> tuple[StmmaeState, StepOutputs]:
    """Advance the bank over a whole batch (the per-sample loop runs compiled).

    Per-sample outputs: ``prob_<hypothesis>``, ``state_<state>`` (probability-blended, absolute),
    ``deflection_<surface>`` (rad, from the surface's filter), ``nis_nominal`` (NIS of the
    no-fault filter per measurement used; NaN when no measurement).

    Raises:
        OutOfOrderError: the batch starts at or before ``state.t_last_s``, or its times are not
            strictly increasing.
        EstimatorError: a channel is missing or has the wrong length, or the state does not
            belong to this configuration.
    """
    names = sample_output_names(config)
    lay = layout(config)
    if state.vector.shape != (lay.length,):
        raise EstimatorError(
            f"state of length {state.vector.shape[0]} does not fit this configuration "
            f"(expected {lay.length})"
        )
    t = np.ascontiguousarray(batch.t_s, dtype=np.float64)
    n = int(t.shape[0])
    if n == 0:
        empty = np.empty(0)
        return state, StepOutputs(samples={name: empty for name in names})
    if not t[0] > state.t_last_s:
        raise OutOfOrderError(
            f"batch starts at t={float(t[0])!r} s, not after the last sample t={state.t_last_s!r} s"
        )
    mdl = config.model
    y = channel_block(batch, [m.channel for m in mdl.measurements], n)
    u = channel_block(batch, [i.channel for i in mdl.inputs], n)
    vec = state.vector.copy()
    samples, windows, events, status = kern.bank_batch(
        config.kernel_vector, config.arrays, vec, t, y, u, config.surface_inputs
    )
    if status != 0:
        raise OutOfOrderError("batch times are not strictly increasing")
    vec.setflags(write=False)
    new_state = StmmaeState(version=STATE_VERSION, t_last_s=float(t[n - 1]), vector=vec)
    outputs = StepOutputs(
        samples={name: samples[i] for i, name in enumerate(names)},
        health=[_health(row, config) for row in windows],
        events=[_event(row, config) for row in events],
        diagnosis=diagnosis(config, new_state),
        status=status_report(config, new_state),
    )
    return new_state, outputs


def warm_up() -> None:
    """Compile (or load from numba's cache) the kernel for every variant and likelihood."""
    n = 8
    for variant in VARIANTS:
        for likelihood in LIKELIHOODS:
            config = parse_config(
                {"variant": variant, "likelihood": likelihood, "health_window_samples": 4}
            )
            names = required_channels(config)
            channels = {name: np.zeros(n) for name in names}
            t_s = np.arange(n, dtype=np.float64) * 0.01
            step(config, initial_state(config), Batch(t_s=t_s, channels=channels))
