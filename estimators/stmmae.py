"""Improved strong-tracking multiple-model adaptive estimation (STMMAE) of control-surface faults.

A bank of Kalman-type filters runs on a discrete linear(ized) aircraft model given in the
configuration (seed paper: Ma, Ni, Xie, Dong, "Fast fault diagnosis of improved strong tracking
aircraft actuator", Systems Engineering and Electronics 37(11), 2015): one no-fault filter and one
filter per monitored surface, which augments the state with that surface's actual deflection
(a random walk) and drops the surface's command from its input; with ``pair_hypotheses`` (not in
the seed) also one filter per pair of surfaces, so that two overlapping faults have a hypothesis
that explains them. Each filter is a strong tracking filter with multiple fading factors; the
seed's improvement applies the fading matrix on both sides of the propagated covariance,
``P- = L Phi P Phi^T L + Q``, keeping P symmetric. The original one-sided form
(``strong_tracking``) and a plain Kalman bank (``emmae``) are selectable. Hypothesis
probabilities follow the Bayes recursion with either the seed's Euclidean-norm likelihood or the
full Gaussian density, floored per hypothesis. Each step is driven by the inputs applied after
the previous sample: its commands passed through a first-order servo model
(``servo_time_constant_s``) for the surfaces, as commanded for the known inputs.

Decisions are per surface, on its marginal fault probability: a detection needs the probability
and the isolation odds (its probability of being the only new fault against the strongest other
surface's) above ``detect_probability``, the deflection estimate off its command and the
log-likelihood ratio between "this surface and a subset of the active faults" and "a subset of
the active faults" summed over the run above ``min_log_likelihood_ratio``, held ``hold_s``
(``hold_while_active_s`` while another surface is in fault, ``hold_while_twin_active_s`` while
its twin is), and none is made outside the model's operating range, less than
``operating_range_settle_s`` back inside it, or while a detected fault ends
(``hold_while_fault_ends``); the fault kind (stuck or oscillating) is judged from the
autocorrelation of the deflection history over ``fault_kind_window_s`` (samples with the
surface's probability at or below ``onset_probability``, or outside the operating range,
skipped; cut before the onset of a
fault detected during it, ``fault_kind_cut``, its end waiting for the detection of a fault
whose onset lies inside it, ``fault_kind_wait_s``; the estimate conditioned on a twin half's known
position, ``fault_kind_twin_correction``); clearance needs the surface back at its command with
a low probability for ``clear_hold_s``. The two halves of a split surface are also detected
together as their group (``group_detection``); while it is detected, a half is named on the
stronger odds ``group_isolation_odds``, taken also from the two halves' single-fault filters'
log-likelihoods summed since the detection (``group_half_evidence``).

Equations, choices where the seed is silent, the configuration reference and what was measured:
``docs/methods-stmmae.md``.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from functools import cached_property
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import Field, ValidationError, field_validator, model_validator

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
    Status,
    StatusReport,
    StepOutputs,
    config_error,
    dump_vector_state,
    load_vector_state,
)
from estimators.checks import channel_block
from estimators.checks import finite_or_none as _finite
from estimators.kernels import stmmae_kernels as kern
from estimators.kernels.stmmae_kernels import IntArray
from estimators.models.small_uav import reference_model

NAME = "stmmae"
STATE_VERSION = 9

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
Number = Annotated[float, Field(strict=True, allow_inf_nan=False)]
"""A finite JSON number (an integer is accepted; a boolean or a string is not)."""
Matrix = tuple[tuple[Number, ...], ...]


class ModelInput(EstimatorConfigModel):
    """One model input: a monitored surface (rad) or a known, unmonitored input."""

    name: str = Field(min_length=1, description="input name; a surface's name names its hypothesis")
    channel: str = Field(min_length=1, description="stream channel carrying the command")
    surface: bool = Field(
        True,
        strict=True,
        description="true: a monitored control surface (rad, gets a fault hypothesis); "
        "false: a known input (e.g. throttle) the model needs",
    )


class ModelMeasurement(EstimatorConfigModel):
    """One measured model output and the channel carrying it."""

    name: str = Field(min_length=1, description="measurement name")
    channel: str = Field(min_length=1, description="stream channel carrying it (model units)")


class LinearModel(EstimatorConfigModel):
    """Discrete deviation model ``x_{k+1} - x* = F (x_k - x*) + G (u_k - u*) + w``,
    ``y_k = H x_k + v``, ``w ~ N(0, Q)``, ``v ~ N(0, R)``, sampled every ``dt_s``.

    Matrices are tuples of row tuples (nested JSON lists). ``x_trim``/``u_trim`` are
    ``x*``/``u*``; ``P0`` the initial covariance of ``x - x*``. Surface inputs are deflections
    in rad.
    """

    name: str = Field("custom", min_length=1, description="model name (recorded, not used)")
    dt_s: Number = Field(gt=0.0, le=3600.0, description="sample period of the model, s")
    states: tuple[str, ...] = Field(min_length=1, description="state names (n)")
    inputs: tuple[ModelInput, ...] = Field(min_length=1, description="inputs (m), G's columns")
    measurements: tuple[ModelMeasurement, ...] = Field(
        min_length=1, description="measured outputs (p), H's rows"
    )
    F: Matrix = Field(description="(n, n) state transition of the deviation from trim")  # noqa: N815
    G: Matrix = Field(description="(n, m) input matrix, per rad of deflection")  # noqa: N815
    H: Matrix = Field(description="(p, n) measurement matrix")  # noqa: N815
    Q: Matrix = Field(description="(n, n) process noise covariance per step, PSD")  # noqa: N815
    R: Matrix = Field(description="(p, p) measurement noise covariance, PD, model units^2")  # noqa: N815
    P0: Matrix = Field(description="(n, n) initial covariance of x - x*, PD")  # noqa: N815
    x_trim: tuple[Number, ...] = Field(description="(n,) trim state x*")
    u_trim: tuple[Number, ...] = Field(description="(m,) trim inputs u* (surfaces in rad)")
    operating_range: dict[str, tuple[Number, Number]] = Field(
        default_factory=dict,
        description="where the model holds: [low, high] of a measurement (by name, model units) "
        "smoothed over operating_range_smoothing_s; while one is outside, no new fault is "
        "detected and the status is 'unknown' (empty: no bound)",
    )

    @model_validator(mode="after")
    def _consistent(self) -> LinearModel:
        for label, names in (
            ("states", self.states),
            ("inputs", [i.name for i in self.inputs]),
            ("measurements", [y.name for y in self.measurements]),
        ):
            if len(set(names)) != len(names):
                raise ValueError(f"model.{label}: names must be unique")
        if not any(i.surface for i in self.inputs):
            raise ValueError("model.inputs: at least one input must be a monitored surface")
        if any(i.name == NOMINAL for i in self.inputs):
            raise ValueError(f"model.inputs: {NOMINAL!r} is reserved for the no-fault hypothesis")
        channels = [i.channel for i in self.inputs] + [y.channel for y in self.measurements]
        if len(set(channels)) != len(channels):
            raise ValueError("model: every input and measurement needs its own channel")
        n, m, p = len(self.states), len(self.inputs), len(self.measurements)
        shapes = {"F": (n, n), "G": (n, m), "H": (p, n), "Q": (n, n), "R": (p, p), "P0": (n, n)}
        for key, (rows, cols) in shapes.items():
            mat = getattr(self, key)
            if len(mat) != rows or any(len(row) != cols for row in mat):
                raise ValueError(f"model.{key}: expected {rows} rows of {cols} numbers")
        for key, length in (("x_trim", n), ("u_trim", m)):
            if len(getattr(self, key)) != length:
                raise ValueError(f"model.{key}: expected {length} numbers")
        _check_covariance("model.Q", self.Q, definite=False)
        _check_covariance("model.R", self.R, definite=True)
        _check_covariance("model.P0", self.P0, definite=True)
        names = [y.name for y in self.measurements]
        for key, (low, high) in self.operating_range.items():
            if key not in names:
                raise ValueError(f"model.operating_range: {key!r} is not a measurement")
            if not low < high:
                raise ValueError(f"model.operating_range.{key}: low must be below high")
        return self

    @property
    def surfaces(self) -> tuple[str, ...]:
        """Names of the monitored surfaces, in input order."""
        return tuple(i.name for i in self.inputs if i.surface)

    def matrix(self, key: str) -> FloatArray:
        """One of ``F, G, H, Q, R, P0`` as a float64 array."""
        return np.array(getattr(self, key), dtype=np.float64)


def _check_covariance(name: str, mat: Matrix, *, definite: bool) -> None:
    arr = np.array(mat, dtype=np.float64)
    if not np.array_equal(arr, arr.T):
        raise ValueError(f"{name}: must be symmetric")
    low = float(np.linalg.eigvalsh(arr)[0]) if arr.size else 1.0
    if (definite and not low > 0.0) or low < 0.0:
        kind = "positive definite" if definite else "positive semi-definite"
        raise ValueError(f"{name}: must be {kind} (smallest eigenvalue {low:.3g})")


def _reference() -> LinearModel:
    return LinearModel.model_validate(reference_model())


class StmmaeConfig(EstimatorConfigModel):
    """Configuration of the bank (``docs/methods-stmmae.md``, "Configuration").

    Derived arrays (the bank's matrices, the kernel's scalar vector) are computed once per
    configuration and cached on the instance; they are not part of its identity.
    """

    model: LinearModel = Field(
        default_factory=_reference,
        description="the discrete linear(ized) aircraft model; null or absent: the reference "
        "Aerosonde model at 25 m/s, 100 Hz (estimators/models/small_uav.py)",
    )
    variant: Variant = Field(
        "improved",
        description="'improved': two-sided fading L A L (seed); 'strong_tracking': one-sided "
        "L A; 'emmae': plain Kalman bank",
    )
    likelihood: Likelihood = Field(
        "gaussian", description="'gaussian': full density; 'euclidean': the seed's 1-D norm form"
    )
    forgetting_factor: Number = Field(
        0.95, gt=0.0, le=1.0, description="rho of the innovation covariance estimate"
    )
    weakening_factor: Annotated[Number, Field(ge=1.0, le=1e6)] | Literal["auto"] = Field(
        "auto",
        description="beta >= 1 of the fading factor, or 'auto': the level that tr(W V) / p "
        "of a consistent filter exceeds with probability fading_tail_probability per sample",
    )
    fading_tail_probability: Number = Field(
        1e-5,
        gt=0.0,
        lt=0.5,
        description="'auto' weakening factor: per-sample probability that noise alone triggers "
        "fading on a consistent filter",
    )
    fading_weights: tuple[Annotated[Number, Field(ge=1.0, le=1e6)], ...] | None = Field(
        None,
        description="prior-knowledge weights a_j of the fading factors, one per model "
        "state, each >= 1 (null: all 1)",
    )
    deflection_fading_weight: Number = Field(
        1.0, ge=1.0, le=1e6, description="a_j of the deflection state(s)"
    )
    deflection_diffusion_deg2_s: Number = Field(
        25.0, gt=0.0, le=1e6, description="random-walk intensity of a deflection state, deg^2/s"
    )
    deflection_initial_std_deg: Number = Field(
        10.0,
        gt=0.0,
        le=180.0,
        description="initial std of a deflection state, deg; also the largest std a filter "
        "contributes to a surface's posterior variance in the deflection gate "
        "(min_deflection_error_std)",
    )
    probability_floor: Number = Field(
        0.001, gt=0.0, le=0.01, description="floor of every single-fault hypothesis probability"
    )
    detect_probability: Number = Field(
        0.9, gt=0.5, le=1.0, description="detection level of a surface's fault probability"
    )
    clear_probability: Number = Field(
        0.05, gt=0.0, le=0.5, description="clearance level of a surface's fault probability"
    )
    hold_s: Number = Field(
        0.05, ge=0.0, le=3600.0, description="detection hold time while no fault is active, s"
    )
    hold_while_active_s: Number = Field(
        0.1,
        ge=0.0,
        le=3600.0,
        description="detection hold time of a surface while another surface is in fault, s "
        "(0.5 s outlasts the transient a pair filter absorbs at an abrupt change of the "
        "active fault: fewer wrong-surface detections, but some second faults missed; "
        "docs/methods-stmmae.md)",
    )
    hold_while_twin_active_s: Number = Field(
        0.3,
        ge=0.0,
        le=3600.0,
        description="detection hold time of a half of a split surface while its twin is in "
        "fault, s (in place of hold_while_active_s: the pair filter of two halves absorbs the "
        "transient of a fault's abrupt change longest, and most wrong-surface detections named "
        "the twin of a half in fault; docs/methods-stmmae.md)",
    )
    clear_hold_s: Number = Field(
        1.0,
        ge=0.0,
        le=3600.0,
        description="clearance hold time, s: the clearance condition must hold this long",
    )
    min_log_likelihood_ratio: Number = Field(
        6.0,
        ge=0.0,
        le=1e6,
        description="smallest log-likelihood ratio, summed over the detection run, of the best "
        "filter holding the surface (and a subset of the active faults) against the best filter "
        "holding a subset of the active faults, for a detection (nats)",
    )
    pair_hypotheses: bool = Field(
        True,
        strict=True,
        description="add one filter per pair of surfaces (both deflections free) so that two "
        "overlapping faults have a hypothesis that explains them; decisions then use each "
        "surface's marginal fault probability",
    )
    pair_probability_floor: Number = Field(
        1e-6,
        gt=0.0,
        le=0.01,
        description="probability floor of each pair hypothesis (a double fault is rarer)",
    )
    rebase_on_detection: bool = Field(
        False,
        strict=True,
        description="on detection every other filter takes the faulty surface at its fault "
        "filter's estimate (a second fault is then isolated against the first); clearance "
        "then needs the surface to follow its command again",
    )
    clear_deflection_deg: Number = Field(
        1.5,
        gt=0.0,
        le=180.0,
        description="rebased bank: clearance band of the smoothed |deflection estimate - "
        "command|, deg",
    )
    clear_smoothing_s: Number = Field(
        0.5,
        gt=0.0,
        le=3600.0,
        description="time constant of the smoothed deflection error of the clearance test, s",
    )
    oscillation_correlation: Number = Field(
        -0.5,
        gt=-1.0,
        lt=0.0,
        description="a fault is oscillating when the autocorrelation of its deflection history "
        "(0.05 s block means over the kind span) falls below this at some lag",
    )
    onset_probability: Number = Field(
        0.5, gt=0.0, le=1.0, description="level whose crossing marks a fault's onset"
    )
    watch_probability: Number = Field(
        0.5, gt=0.0, le=1.0, description="'watch' level of an unconfirmed fault probability"
    )
    deflection_smoothing_s: Number = Field(
        0.2, gt=0.0, le=3600.0, description="time constant of the smoothed deflection estimate, s"
    )
    fault_kind_window_s: Number = Field(
        5.0,
        ge=1.0,
        le=kern.KIND_BLOCKS * kern.KIND_BLOCK_S,
        description="span from the start of the detection hold over which the fault kind is "
        "judged, s (longer than half the slowest oscillation period to be recognised)",
    )
    fault_kind_cut: bool = Field(
        True,
        description="a detection cuts the open kind spans of the faults already active at "
        "its onset (less 0.5 s): their kind is judged on the history before the new fault "
        "began, when at least 1 s of it is left",
    )
    fault_kind_wait_s: Number = Field(
        1.0,
        ge=0.0,
        le=kern.KIND_BLOCKS * kern.KIND_BLOCK_S,
        description="longest wait of the end of a fault's kind span for the detection of a "
        "surface or group whose onset lies inside the span, s (with fault_kind_cut; 0: no "
        "wait): that detection then cuts the span instead of the kind being judged on a "
        "history into which the other fault's effect has leaked",
    )
    fault_kind_twin_correction: bool = Field(
        True,
        description="a fault's kind history records its deflection estimate conditioned on "
        "its twin half's known position (the twin's stuck position while it is in fault and "
        "judged stuck, its command while it is not in fault): only the sum of two halves' "
        "deflections is well determined, and a filter freeing both splits the fault between "
        "them (docs/methods-stmmae.md, 'Fault kind and stuck position')",
    )
    group_detection: bool = Field(
        True,
        description="the two halves of a split surface (each the other's most collinear "
        "surface) are also detected together, as 'one of the two', while neither half is in "
        "fault: a fault_detected event names the group and both candidates as soon as the "
        "group's conditions hold, before the data tell the halves apart (while another surface "
        "is in fault, after group_hold_while_active_s; none while as many surfaces are in fault "
        "as a hypothesis frees); the half's own detection follows and ends the group's episode "
        "(docs/methods-stmmae.md, 'Group detection')",
    )
    group_hold_s: Number = Field(
        0.1,
        ge=0.0,
        le=3600.0,
        description="detection hold time of a group of two halves, s (twice hold_s: the "
        "group's probability sums three hypotheses, so the same data pass its level sooner)",
    )
    group_hold_while_active_s: Number = Field(
        0.5,
        ge=0.0,
        le=3600.0,
        description="detection hold time of a group of two halves while another surface is in "
        "fault, s: a second fault on a split surface is raised as its group when the data do "
        "not tell its halves apart beside the first fault; longer than group_hold_s because "
        "the end of the first fault leaves its filter lagging for a few tenths of a second, "
        "which filters holding the first fault and a half explain better "
        "(docs/methods-stmmae.md, 'Group detection')",
    )
    hold_while_fault_ends: bool = Field(
        True,
        description="no new surface or group is detected while a detected fault is ending: its "
        "surface's fault probability below clear_probability and its deflection estimate back "
        "within clear_deflection_deg of its command, its clearance pending; the filters "
        "re-converge after the surface's return, and those freeing another surface fit that "
        "transient better, which detected a surface wrongly 0.3-2 s after a fault's end; "
        "only with pair_hypotheses (without pair filters the probability of a fault that "
        "persists collapses too when a second one begins) (docs/methods-stmmae.md, 'A fault "
        "that is ending holds new detections')",
    )
    group_onset_window_s: Number = Field(
        3.0,
        gt=0.0,
        le=3600.0,
        description="a group of two halves is detected only within this time of its onset "
        "(its probability's first rise above onset_probability since it was last below "
        "clear_probability), s: a fault shows "
        "its deflection soon after its probability rises, while a group probability held high "
        "with both halves' estimates near their commands is what a model mismatch gives (both "
        "halves' filters absorbing the error alike); a half is still detected by its own "
        "conditions",
    )
    noise_ratio_unknown: Number = Field(
        2.0,
        gt=1.0,
        le=1e6,
        description="'unknown' level of innovation_noise_ratio, the no-fault filter's innovation "
        "energy in units of the model's sensor noise R averaged over a health window (about 1 "
        "when R is the sensors' noise): above it the sensors are noisier than the model says, "
        "or the model does not fit, and faults may go undetected",
    )
    operating_range_smoothing_s: Number = Field(
        10.0,
        gt=0.0,
        le=3600.0,
        description="time constant over which the measurements bounded by the model's "
        "operating_range are smoothed before they are compared with it, s",
    )
    operating_range_settle_s: Number = Field(
        2.0,
        ge=0.0,
        le=3600.0,
        description="no new detection until the aircraft has been back inside the model's "
        "operating_range for this long, s (0: from the first sample inside)",
    )
    group_isolation_odds: Number = Field(
        0.99,
        gt=0.0,
        lt=1.0,
        description="while a group of two halves is detected and no other surface is in fault, "
        "a half is named only when its isolation odds against the other surfaces exceed this "
        "level (detect_probability otherwise, and beside another fault): the group has raised "
        "the alert, so the choice of the half can wait for stronger evidence",
    )
    half_needs_group_odds: bool = Field(
        True,
        strict=True,
        description="with no surface in fault, a half of a split surface whose strongest "
        "competitor is its twin is named only at group_isolation_odds before its group is "
        "detected too (off: at detect_probability until the group is detected): a half's odds "
        "against its twin rest on the small term that separates the halves, and the first "
        "tenths of a second of a fault can favour the wrong one; the group raises the alert "
        "meanwhile",
    )
    group_half_evidence: bool = Field(
        True,
        strict=True,
        description="while a group of two halves is detected and no other surface is in "
        "fault, a half's isolation odds are also taken from the log-likelihood of its "
        "single-fault filter against its twin's, summed since the group's detection (the "
        "larger odds count): while the filter freeing both halves holds the mass, as it does "
        "for a fast oscillation of one half (which that half's own filter follows worse), "
        "both single filters sit at their probability floor and the floors erase the evidence "
        "between them (docs/methods-stmmae.md, 'Group detection')",
    )
    deflection_limit_deg: Number = Field(
        30.0, gt=0.0, le=180.0, description="clip of the deflection estimate, deg"
    )
    oscillation_swing_deg: Number = Field(
        2.0,
        gt=0.0,
        le=180.0,
        description="swing (2 std of the deflection estimate) an oscillating fault must also "
        "exceed, deg",
    )
    oscillation_small_swing_deg: Number = Field(
        3.0,
        gt=0.0,
        le=180.0,
        description="below this swing (2 std of the deflection estimate, deg) an oscillating "
        "fault needs the deeper lobe oscillation_small_swing_correlation: a stuck surface's "
        "estimate, kept lively by the fading factors, swings up to about this much from "
        "estimation noise alone, and the noise's autocorrelation can dip below "
        "oscillation_correlation",
    )
    oscillation_small_swing_correlation: Number = Field(
        -0.7,
        gt=-1.0,
        lt=0.0,
        description="autocorrelation level an oscillating fault's deflection history must fall "
        "below when its swing is under oscillation_small_swing_deg (at most "
        "oscillation_correlation)",
    )
    min_deflection_error_deg: Number = Field(
        1.0,
        ge=0.0,
        le=180.0,
        description="smallest |deflection estimate - command| for a detection, deg",
    )
    min_deflection_error_std: Number = Field(
        1.5,
        ge=0.0,
        le=10.0,
        description="smallest |deflection estimate - command| for a detection in posterior "
        "standard deviations of the estimate (0: off; the larger of the two gates applies)",
    )
    servo_time_constant_s: Number = Field(
        0.02,
        ge=0.0,
        le=10.0,
        description="time constant of the first-order lag through which a healthy surface "
        "follows its command, s (0: none); the model is driven by the commands through it",
    )
    nis_watch: Number = Field(
        3.0,
        gt=0.0,
        le=1e6,
        description="'watch' level of the no-fault filter's mean NIS per measurement",
    )
    health_window_samples: int = Field(
        1000, strict=True, ge=1, le=10**8, description="health window length, stream samples"
    )

    @field_validator("model", mode="before")
    @classmethod
    def _default_model(cls, value: Any) -> Any:
        return reference_model() if value is None else value

    @model_validator(mode="after")
    def _consistent(self) -> StmmaeConfig:
        if self.clear_probability >= self.detect_probability:
            raise ValueError("clear_probability: must be below detect_probability")
        if self.oscillation_small_swing_correlation > self.oscillation_correlation:
            raise ValueError(
                "oscillation_small_swing_correlation: must be at or below oscillation_correlation "
                "(the lobe a small swing needs is the deeper one)"
            )
        s = len(self.model.surfaces)
        pairs = s * (s - 1) // 2 if self.pair_hypotheses else 0
        if 1.0 - s * self.probability_floor - pairs * self.pair_probability_floor <= 0.5:
            raise ValueError(
                "probability_floor: too large for the number of hypotheses (the floors of all "
                "fault hypotheses must sum to less than 0.5)"
            )
        if self.fading_weights is not None and len(self.fading_weights) != len(self.model.states):
            raise ValueError(
                f"fading_weights: expected {len(self.model.states)} numbers (one per model state)"
            )
        return self

    @cached_property
    def hypotheses(self) -> tuple[str, ...]:
        """``nominal``, the surfaces, then (with ``pair_hypotheses``) each pair ``a+b``."""
        names = self.model.surfaces
        return tuple(
            "+".join(names[i] for i in members) if members else NOMINAL
            for members in hypothesis_members(self)
        )

    @cached_property
    def kernel_vector(self) -> FloatArray:
        """The kernel's scalar configuration (``CFG_*``), read-only."""
        return _kernel_vector(self)

    @cached_property
    def arrays(self) -> kern.BankArrays:
        """The bank's matrices (:func:`build_bank`), read-only."""
        return build_bank(self)

    @cached_property
    def surface_inputs(self) -> IntArray:
        """Input index of each monitored surface."""
        idx = [i for i, inp in enumerate(self.model.inputs) if inp.surface]
        out = np.array(idx, dtype=np.int64)
        out.setflags(write=False)
        return out


CONFIG_MODEL = StmmaeConfig


def parse_config(raw: Mapping[str, Any]) -> StmmaeConfig:
    """Validate a JSON-like mapping into a :class:`StmmaeConfig`.

    Raises:
        ConfigError: naming each bad field (unknown keys, wrong types or shapes, values out of
            range, matrices that are not covariances, inconsistent thresholds).
    """
    if not isinstance(raw, Mapping):
        raise ConfigError(f"{NAME}: config: expected an object, got {type(raw).__name__}")
    try:
        return StmmaeConfig.model_validate(dict(raw))
    except ValidationError as exc:
        raise config_error(NAME, exc) from exc


def parse_model(raw: Mapping[str, Any]) -> LinearModel:
    """Validate a model mapping (the shape of :func:`small_uav.reference_model`)."""
    try:
        return LinearModel.model_validate(raw)
    except ValidationError as exc:
        raise config_error(f"{NAME} model", exc) from exc


def model_to_dict(model: LinearModel) -> dict[str, Any]:
    """JSON-ready form of a model (inverse of :func:`parse_model`)."""
    return model.model_dump(mode="json")


def config_to_dict(config: StmmaeConfig) -> dict[str, Any]:
    """The full configuration with defaults filled in, JSON-serializable."""
    return config.model_dump(mode="json")


def required_channels(config: StmmaeConfig) -> tuple[str, ...]:
    """Measurement channels, then input (command) channels."""
    m = config.model
    return tuple(y.channel for y in m.measurements) + tuple(i.channel for i in m.inputs)


def weakening_factor(config: StmmaeConfig) -> float:
    """The weakening factor in use. "auto": the ``1 - fading_tail_probability`` quantile of
    ``tr(W V) / p`` on a consistent filter, so that noise alone triggers fading with that
    probability per sample. ``V`` weighs the innovation of ``j`` samples ago by
    ``rho^j / (1 + rho)^(j + 1)`` (sum 1, sum of squares ``1 / (1 + 2 rho)``), so ``tr(W V)`` is
    a weighted sum of chi-square variables with ``p`` degrees of freedom; it is taken as a
    scaled chi-square with ``nu = p (1 + 2 rho)`` degrees of freedom (same mean and variance):
    ``beta = chi2.ppf(1 - tail, nu) / nu`` (3.14 for p = 6, rho = 0.95, tail 1e-5)."""
    if config.weakening_factor != "auto":
        return float(config.weakening_factor)
    from scipy.stats import chi2  # here: scipy.stats costs most of a second to import

    rho = config.forgetting_factor
    nu = len(config.model.measurements) * (1.0 + 2.0 * rho)
    return max(1.0, float(chi2.ppf(1.0 - config.fading_tail_probability, nu)) / nu)


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
    cfg[kern.CFG_HOLD_ACTIVE_S] = config.hold_while_active_s
    cfg[kern.CFG_HOLD_TWIN_S] = config.hold_while_twin_active_s
    cfg[kern.CFG_CLEAR_HOLD_S] = config.clear_hold_s
    cfg[kern.CFG_ONSET_P] = config.onset_probability
    cfg[kern.CFG_WINDOW] = config.health_window_samples
    cfg[kern.CFG_SMOOTH_S] = config.deflection_smoothing_s
    cfg[kern.CFG_MIN_ERR] = math.radians(config.min_deflection_error_deg)
    cfg[kern.CFG_MIN_ERR_STD] = config.min_deflection_error_std
    cfg[kern.CFG_DEFL_VAR_CAP] = math.radians(config.deflection_initial_std_deg) ** 2
    cfg[kern.CFG_LIMIT] = math.radians(config.deflection_limit_deg)
    cfg[kern.CFG_KIND_WINDOW_S] = config.fault_kind_window_s
    cfg[kern.CFG_REBASE] = 1.0 if config.rebase_on_detection else 0.0
    cfg[kern.CFG_KIND_CUT] = 1.0 if config.fault_kind_cut else 0.0
    cfg[kern.CFG_KIND_WAIT_S] = config.fault_kind_wait_s
    cfg[kern.CFG_KIND_TWIN] = 1.0 if config.fault_kind_twin_correction else 0.0
    cfg[kern.CFG_GROUP] = 1.0 if config.group_detection else 0.0
    cfg[kern.CFG_GROUP_ISO] = config.group_isolation_odds
    cfg[kern.CFG_HALF_GROUP_ODDS] = 1.0 if config.half_needs_group_odds else 0.0
    cfg[kern.CFG_GROUP_HALF_EVIDENCE] = 1.0 if config.group_half_evidence else 0.0
    cfg[kern.CFG_GROUP_HOLD_S] = config.group_hold_s
    cfg[kern.CFG_GROUP_HOLD_ACTIVE_S] = config.group_hold_while_active_s
    # the rule reads a collapse of an active fault's probability as its end: with pair filters a
    # fault that persists keeps its probability through them when a second one begins; without
    # them it does not, so the rule is off
    ending = config.hold_while_fault_ends and config.pair_hypotheses
    cfg[kern.CFG_HOLD_ENDING] = 1.0 if ending else 0.0
    cfg[kern.CFG_GROUP_WINDOW_S] = config.group_onset_window_s
    cfg[kern.CFG_RANGE_SMOOTH_S] = config.operating_range_smoothing_s
    cfg[kern.CFG_RANGE_SETTLE_S] = config.operating_range_settle_s
    cfg[kern.CFG_CLEAR_DEFL] = math.radians(config.clear_deflection_deg)
    cfg[kern.CFG_CLEAR_SMOOTH_S] = config.clear_smoothing_s
    cfg[kern.CFG_MIN_LLR] = config.min_log_likelihood_ratio
    cfg[kern.CFG_OSC_CORR] = config.oscillation_correlation
    cfg[kern.CFG_OSC_SWING] = math.radians(config.oscillation_swing_deg)
    cfg[kern.CFG_OSC_SMALL_SWING] = math.radians(config.oscillation_small_swing_deg)
    cfg[kern.CFG_OSC_SMALL_CORR] = config.oscillation_small_swing_correlation
    tau = config.servo_time_constant_s
    cfg[kern.CFG_SERVO_A] = 1.0 - math.exp(-config.model.dt_s / tau) if tau > 0.0 else 1.0
    cfg.setflags(write=False)
    return cfg


def hypothesis_members(config: StmmaeConfig) -> tuple[tuple[int, ...], ...]:
    """Surfaces (indices among the monitored surfaces) each hypothesis declares faulty:
    ``()`` for the no-fault filter, ``(i,)`` for each surface, then ``(i, j)``, ``i < j``,
    for each pair when ``pair_hypotheses`` is set."""
    s = len(config.model.surfaces)
    out: list[tuple[int, ...]] = [(), *((i,) for i in range(s))]
    if config.pair_hypotheses:
        out += [(i, j) for i in range(s) for j in range(i + 1, s)]
    return tuple(out)


def _collinearity(
    phi: FloatArray, h: FloatArray, r: FloatArray, slot_surface: IntArray, n: int, ns: int
) -> FloatArray:
    """Cosine between the surfaces' effects on the measurements, each whitened by the
    measurement noise (``R^-1/2 H Phi^k e_slot``, ``k = 1..COLLINEAR_STEPS``, stacked), taken from
    the pair filter freeing both: near 1 when the data determine mainly a combination of the
    two deflections (0.997 and 0.96 for the aileron and elevator halves of the reference model,
    0.91 for an aileron half and the rudder, under 0.2 for the other pairs)."""
    out = np.eye(ns)
    if slot_surface.shape[1] < 2:  # no pair hypotheses
        return out
    w = 1.0 / np.sqrt(np.diag(r))
    for f in range(slot_surface.shape[0]):
        a, b = int(slot_surface[f, 0]), int(slot_surface[f, 1])
        if a < 0 or b < 0:
            continue
        m = np.eye(phi.shape[1])
        ea, eb = [], []
        for _ in range(kern.COLLINEAR_STEPS):
            m = phi[f] @ m
            ea.append(w * (h @ m[:, n]))
            eb.append(w * (h @ m[:, n + 1]))
        va, vb = np.concatenate(ea), np.concatenate(eb)
        den = float(np.linalg.norm(va) * np.linalg.norm(vb))
        out[a, b] = out[b, a] = float(va @ vb) / den if den > 0.0 else 0.0
    return out


def build_bank(config: StmmaeConfig) -> kern.BankArrays:
    """The bank's matrices: filter 0 is the model itself (its extra states fixed at zero);
    a fault filter augments the state with the deflection ``d_i`` of each surface it declares
    faulty (one, or two for a pair), in slots ``n, n + 1``:

        [x; d]_{k+1} = [[F, G_S], [0, I]] [x; d]_k + G_(0,S) (u_k - u*) - G_S u*_S
        Q_S = blkdiag(Q, q_d I),  q_d = deflection_diffusion * dt,  P0_S = blkdiag(P0, s_d^2 I)

    with ``G_S`` the input columns of the surfaces ``S`` and ``G_(0,S)`` the input matrix with
    those columns set to zero. Unused slots stay identically zero.
    """
    mdl = config.model
    f, g, h, q, r, p0 = (mdl.matrix(k) for k in MATRIX_KEYS)
    n, m = g.shape
    surf_idx = [i for i, inp in enumerate(mdl.inputs) if inp.surface]
    members = hypothesis_members(config)
    n_slots = max(len(mem) for mem in members)
    nh, na = len(members), n + n_slots
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
    slot_surface = np.full((nh, n_slots), -1, dtype=np.int64)
    floors = np.empty(nh)
    for hyp, mem in enumerate(members):
        phi[hyp, :n, :n] = f
        gin[hyp, :n, :] = g
        qa[hyp, :n, :n] = q
        p0a[hyp, :n, :n] = p0
        aw[hyp, :n] = weights
        floors[hyp] = config.pair_probability_floor if len(mem) > 1 else config.probability_floor
        for e, surface in enumerate(mem):
            col, slot = surf_idx[surface], n + e
            slot_surface[hyp, e] = surface
            phi[hyp, :n, slot] = g[:, col]
            phi[hyp, slot, slot] = 1.0
            gin[hyp, :n, col] = 0.0
            offset[hyp, :n] -= g[:, col] * u_trim[col]
            qa[hyp, slot, slot] = q_d
            p0a[hyp, slot, slot] = s_d2
            x0[hyp, slot] = u_trim[col]
            aw[hyp, slot] = config.deflection_fading_weight
    ha = np.zeros((h.shape[0], na))
    ha[:, :n] = h
    hqh = np.einsum("ij,hjk,ik->hi", ha, qa, ha)
    unbounded = (-math.inf, math.inf)
    bounds = np.array(
        [mdl.operating_range.get(y.name, unbounded) for y in mdl.measurements], dtype=np.float64
    )
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
        slot_surface=slot_surface,
        floors=floors,
        collinear=_collinearity(phi, ha, r, slot_surface, n, len(surf_idx)),
        range_lo=bounds[:, 0].copy(),
        range_hi=bounds[:, 1].copy(),
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

    The compiled loop reads and writes one flat float64 vector; this object holds it read-only
    and :func:`state_parts` gives every part a name and a shape (the layout table of
    ``stmmae_kernels.state_layout``), so no code outside the kernel boundary indexes it by
    number.

    Attributes:
        version: schema version (``STATE_VERSION``).
        t_last_s: time of the last sample seen (-inf before any).
        vector: FloatArray  # (layout.length,) packed parts, never modified in place.
        layout_version: the layout ``vector`` has: ``STATE_VERSION``, or 2 to 8 for a
            state of that version just loaded, whose new parts need the configuration and are
            added by the first :func:`state_parts` or :func:`step` (see
            :func:`_upgrade_layout_v2` to :func:`_upgrade_layout_v8`).
    """

    version: int
    t_last_s: float
    vector: FloatArray
    layout_version: int = STATE_VERSION


@dataclass(frozen=True)
class StateParts:
    """Named, read-only views of a state's vector (shapes for ``nh`` hypotheses of ``na``
    states, ``p`` measurements, ``m`` inputs, ``s = nh - 1`` surfaces).

    Attributes:
        samples_seen: samples stepped so far.
        covariance_failures: samples where some filter's S was not positive definite.
        t_prev_s: time of the previous sample (NaN before any).
        x: FloatArray  # (nh, na) filter states (deviation from trim; last entry of a fault
            filter: the surface's absolute deflection, rad).
        P: FloatArray  # (nh, na, na) filter covariances.
        V: FloatArray  # (nh, p, p) innovation covariance estimates of the fading factors.
        V_started: FloatArray  # (nh,) 1 once V holds a first innovation.
        probabilities: FloatArray  # (nh,) hypothesis probabilities.
        u_last: FloatArray  # (m,) last valid inputs (commands).
        decisions: FloatArray  # (s, kern.D_LEN) decision fields per surface (``D_*``).
        kind_blocks: FloatArray  # (s, kern.KIND_BLOCKS) 0.05 s block means of the deflection
            estimate over the kind span (rad).
        window: FloatArray  # (kern.W_LEN,) accumulators of the open health window (``W_*``).
        applied: FloatArray  # (m,) inputs applied over the step into the next sample (the
            servo model's output; version 4).
        groups: FloatArray  # (s, kern.G_LEN) group decision fields (``G_*``) on the row of
            the first half of each pair of twin halves (version 5; ``G_HALF_LLR`` version 7).
        operating: FloatArray  # (p,) measurements smoothed for the operating range (NaN until
            a first value, and for measurements without bounds; version 6).
        outside_samples: FloatArray  # (1,) samples outside the operating range in the open
            health window (version 6).
        noise_sums: FloatArray  # (2,) sum and count of the no-fault filter's innovation energy
            in units of the model's R over the open health window (version 6).
        noise_smoothed: FloatArray  # (1,) that energy smoothed over operating_range_smoothing_s
            (NaN before a first value; version 6).
        last_outside_s: FloatArray  # (1,) time of the last sample outside the operating range
            (NaN: none yet; version 8).
        group_kinds: FloatArray  # (s, kern.D_LEN) kind spans of the groups, one row per half
            (the kind fields of ``D_*``; version 9).
        group_kind_blocks: FloatArray  # (s, kern.KIND_BLOCKS) their block histories (rad;
            version 9).
    """

    samples_seen: float
    covariance_failures: float
    t_prev_s: float
    x: FloatArray
    P: FloatArray  # noqa: N815 - the usual name of a covariance
    V: FloatArray  # noqa: N815
    V_started: FloatArray  # noqa: N815
    probabilities: FloatArray
    u_last: FloatArray
    decisions: FloatArray
    kind_blocks: FloatArray
    window: FloatArray
    applied: FloatArray
    groups: FloatArray
    operating: FloatArray
    outside_samples: FloatArray
    noise_sums: FloatArray
    noise_smoothed: FloatArray
    last_outside_s: FloatArray
    group_kinds: FloatArray
    group_kind_blocks: FloatArray


def layout(config: StmmaeConfig) -> kern.Layout:
    """The state layout of a configuration's bank."""
    nh, na = config.arrays.x0.shape
    arr = config.arrays
    return kern.state_layout(nh, na, arr.h.shape[0], arr.gin.shape[2], len(config.model.surfaces))


def state_parts(config: StmmaeConfig, state: StmmaeState) -> StateParts:
    """The named parts of ``state`` under ``config``'s layout (read-only views, no copies).

    Raises:
        EstimatorError: the state does not belong to this configuration.
    """
    lay = layout(config)
    vec = _current_vector(config, state)
    if vec.shape != (lay.length,):
        raise EstimatorError(
            f"state of length {vec.shape[0]} does not fit this configuration "
            f"(expected {lay.length})"
        )
    nh, na, p, m = lay.nh, lay.na, lay.p, lay.m
    blocks = vec[lay.filt : lay.filt + nh * lay.filt_len].reshape(nh, lay.filt_len)
    checks = vec[lay.checks : lay.group_kinds]
    v_off = na + na * na
    return StateParts(
        samples_seen=float(vec[kern.ST_N_SEEN]),
        covariance_failures=float(vec[kern.ST_COV_FAIL]),
        t_prev_s=float(vec[kern.ST_T_PREV]),
        x=blocks[:, :na],
        P=blocks[:, na:v_off].reshape(nh, na, na),
        V=blocks[:, v_off : v_off + p * p].reshape(nh, p, p),
        V_started=blocks[:, v_off + p * p],
        probabilities=vec[lay.probs : lay.probs + nh],
        u_last=vec[lay.u_last : lay.u_last + m],
        decisions=vec[lay.decisions : lay.kind_blocks].reshape(lay.s, kern.D_LEN),
        kind_blocks=vec[lay.kind_blocks : lay.window].reshape(lay.s, kern.KIND_BLOCKS),
        window=vec[lay.window : lay.window + kern.W_LEN],
        applied=vec[lay.applied : lay.applied + m],
        groups=vec[lay.groups : lay.operating].reshape(lay.s, kern.G_LEN),
        operating=vec[lay.operating : lay.checks],
        outside_samples=checks[kern.CK_OUTSIDE : kern.CK_OUTSIDE + 1],
        noise_sums=checks[kern.CK_NOISE_SUM : kern.CK_NOISE_N + 1],
        noise_smoothed=checks[kern.CK_NOISE_SMOOTH : kern.CK_NOISE_SMOOTH + 1],
        last_outside_s=checks[kern.CK_LAST_OUTSIDE_T : kern.CK_LAST_OUTSIDE_T + 1],
        group_kinds=vec[lay.group_kinds : lay.group_kind_blocks].reshape(lay.s, kern.D_LEN),
        group_kind_blocks=vec[lay.group_kind_blocks : lay.length].reshape(lay.s, kern.KIND_BLOCKS),
    )


def initial_state(config: StmmaeConfig) -> StmmaeState:
    """Filters at the trim (fault filters: deflections at their trim), each fault hypothesis at
    its floor, the no-fault hypothesis the rest."""
    lay = layout(config)
    arr = config.arrays
    vec = np.zeros(lay.length)
    vec[kern.ST_T_PREV] = np.nan
    for f in range(lay.nh):
        off = lay.filt + f * lay.filt_len
        vec[off : off + lay.na] = arr.x0[f]
        vec[off + lay.na : off + lay.na + lay.na * lay.na] = arr.p0[f].ravel()
    vec[lay.probs + 1 : lay.probs + lay.nh] = arr.floors[1:]
    vec[lay.probs] = 1.0 - float(arr.floors[1:].sum())
    vec[lay.u_last : lay.u_last + lay.m] = arr.u_trim
    vec[lay.applied : lay.applied + lay.m] = arr.u_trim
    for h in range(lay.s):
        for d in (lay.decisions + h * kern.D_LEN, lay.group_kinds + h * kern.D_LEN):
            for idx in kern.D_TIMES:
                vec[d + idx] = np.nan
            vec[d + kern.D_BLK_IDX] = -1.0
            vec[d + kern.D_KIND_CORR] = np.nan
            vec[d + kern.D_DEFL] = np.nan
        g = lay.groups + h * kern.G_LEN
        for idx in kern.G_TIMES:
            vec[g + idx] = np.nan
    vec[lay.operating : lay.checks] = np.nan
    vec[lay.checks + kern.CK_NOISE_SMOOTH] = np.nan
    vec[lay.checks + kern.CK_LAST_OUTSIDE_T] = np.nan
    vec.setflags(write=False)
    return StmmaeState(version=STATE_VERSION, t_last_s=-math.inf, vector=vec)


def dump_state(state: StmmaeState) -> bytes:
    """Versioned byte form of the state (exact round trip; see :func:`dump_vector_state`). A
    loaded version-2, -3, -4, -5 or -6 state not stepped yet is written back as the state it
    is."""
    return dump_vector_state(NAME, state.layout_version, state.t_last_s, state.vector)


def _upgrade_v1(doc: dict[str, Any]) -> dict[str, Any]:
    """Version 1 -> 2: same layout; the three episode sums (``D_EP_*``) changed meaning from
    equal-weight sums of the smoothed deflection to precision-weighted sums of the clipped
    estimate. Equal weights are one valid weighting, so a version-1 episode's mean and swing
    read the same under version 2 (later samples then carry their precision weights): the
    vector is kept as it is."""
    return {**doc, "version": 2}


_V2_D_LEN = 10  # decision fields per surface in versions 1 and 2


def _upgrade_layout_v2(config: StmmaeConfig, vector: FloatArray) -> FloatArray:
    """Version 2 -> 3 (needs the configuration, so it runs at the first use of a loaded state,
    not in :func:`load_state`). Version 2 had the no-fault and single-fault filters with one
    deflection slot and ten decision fields per surface. Kept: every filter's x, P, V (a second
    deflection slot, if any, starts as in a fresh filter: zero, uncorrelated), their
    probabilities, the last inputs, the header and the health-window accumulators; each
    surface's ten decision fields. New parts start as a fresh state has them: pair filters
    (at their initial state, probability at the pair floor, the others scaled to sum to one),
    the new decision fields (except that an active fault's kind span restarts at the last
    sample, so its kind is judged ``fault_kind_window_s`` later, and the clearance smoothing
    starts from the last smoothed estimate minus the last command), an empty kind history."""
    lay = layout(config)
    s = lay.s
    n = len(config.model.states)
    na_old, nh_old = n + 1, s + 1
    p, m = lay.p, lay.m
    flen_old = na_old + na_old * na_old + p * p + 1
    probs_old = kern.ST_HEADER + nh_old * flen_old
    dec_old = probs_old + nh_old + m
    length_old = dec_old + s * _V2_D_LEN + kern.W_LEN
    if vector.shape != (length_old,):
        raise EstimatorError(
            f"version-2 state of length {vector.shape[0]} does not fit this configuration "
            f"(expected {length_old})"
        )
    fresh = initial_state(config).vector[: lay.applied].copy()  # the version-3 layout
    fresh[: kern.ST_HEADER] = vector[: kern.ST_HEADER]
    for f in range(nh_old):
        old = vector[kern.ST_HEADER + f * flen_old : kern.ST_HEADER + (f + 1) * flen_old]
        off = lay.filt + f * lay.filt_len
        fresh[off : off + na_old] = old[:na_old]
        p_new = fresh[off + lay.na : off + lay.na + lay.na * lay.na].reshape(lay.na, lay.na)
        p_new[:na_old, :na_old] = old[na_old : na_old + na_old * na_old].reshape(na_old, na_old)
        v_new = off + lay.na + lay.na * lay.na
        fresh[v_new : v_new + p * p + 1] = old[na_old + na_old * na_old :]
    probs = fresh[lay.probs : lay.probs + lay.nh]
    pairs_mass = float(probs[nh_old:].sum())
    probs[:nh_old] = vector[probs_old : probs_old + nh_old] * (1.0 - pairs_mass)
    fresh[lay.u_last : lay.u_last + m] = vector[probs_old + nh_old : dec_old]
    old_dec = vector[dec_old : dec_old + s * _V2_D_LEN].reshape(s, _V2_D_LEN)
    dec = fresh[lay.decisions : lay.kind_blocks].reshape(s, kern.D_LEN)
    dec[:, :_V2_D_LEN] = old_dec
    u_last = fresh[lay.u_last : lay.u_last + m]
    t_prev = vector[kern.ST_T_PREV]
    for h, col in enumerate(config.surface_inputs):
        if old_dec[h, kern.D_SMOOTH_SET] == 1.0:
            dec[h, kern.D_CSMOOTH] = old_dec[h, kern.D_SMOOTH] - u_last[col]
        if old_dec[h, kern.D_ACTIVE] == 1.0:
            dec[h, kern.D_KIND_T0] = t_prev
        dec[h, kern.D_DEFL] = vector[kern.ST_HEADER + (h + 1) * flen_old + na_old - 1]
        dec[h, kern.D_PROB] = probs[h + 1]
    fresh[lay.window :] = vector[length_old - kern.W_LEN :]
    fresh.setflags(write=False)
    return fresh


def _upgrade_layout_v3(config: StmmaeConfig, vector: FloatArray) -> FloatArray:
    """Version 3 -> 4 (needs the configuration for the number of inputs): version 4 appends
    the inputs applied over the step into the next sample (the servo model's output). A
    version-3 state drove its filters with the last command itself, so that command is the
    applied input it leaves: the appended part is a copy of the last inputs."""
    lay = layout(config)
    if vector.shape != (lay.applied,):
        raise EstimatorError(
            f"version-3 state of length {vector.shape[0]} does not fit this configuration "
            f"(expected {lay.applied})"
        )
    fresh = np.concatenate([vector, vector[lay.u_last : lay.u_last + lay.m]])
    fresh.setflags(write=False)
    return fresh


_V6_G_LEN = 6  # group decision fields per surface in versions 5 and 6
_V7_CK_LEN = 4  # status checks in versions 6 and 7


def _upgrade_layout_v4(config: StmmaeConfig, vector: FloatArray) -> FloatArray:
    """Version 4 -> 5: version 5 appends the group decision fields (its six per surface),
    which start as a fresh state has them (no group detected, no run open): a group is judged
    from the next sample."""
    lay = layout(config)
    if vector.shape != (lay.groups,):
        raise EstimatorError(
            f"version-4 state of length {vector.shape[0]} does not fit this configuration "
            f"(expected {lay.groups})"
        )
    groups = initial_state(config).vector[lay.groups : lay.operating].reshape(lay.s, kern.G_LEN)
    fresh = np.concatenate([vector, groups[:, :_V6_G_LEN].ravel()])
    fresh.setflags(write=False)
    return fresh


def _upgrade_layout_v5(config: StmmaeConfig, vector: FloatArray) -> FloatArray:
    """Version 5 -> 6: version 6 appends the operating range's smoothed measurements (unset:
    the next valid values start them) and the status checks: the open window's count of
    samples outside the range and its innovation-energy sums (0: the window's earlier samples
    were not checked), and the smoothed innovation energy (unset: the next value starts it)."""
    lay = layout(config)
    end = lay.groups + lay.s * _V6_G_LEN
    if vector.shape != (end,):
        raise EstimatorError(
            f"version-5 state of length {vector.shape[0]} does not fit this configuration "
            f"(expected {end})"
        )
    tail = initial_state(config).vector[lay.operating : lay.checks + _V7_CK_LEN]
    fresh = np.concatenate([vector, tail])
    fresh.setflags(write=False)
    return fresh


def _upgrade_layout_v6(config: StmmaeConfig, vector: FloatArray) -> FloatArray:
    """Version 6 -> 7: version 7 adds a seventh group decision field, the summed evidence of
    a detected group's first half against its second (``G_HALF_LLR``). It starts at 0, as at
    a group's detection: a group detected when the state was dumped weighs its halves from
    the next sample on."""
    lay = layout(config)
    end = lay.groups + lay.s * _V6_G_LEN
    expected = end + lay.checks + _V7_CK_LEN - lay.operating
    if vector.shape != (expected,):
        raise EstimatorError(
            f"version-6 state of length {vector.shape[0]} does not fit this configuration "
            f"(expected {expected})"
        )
    groups = np.zeros((lay.s, kern.G_LEN))
    groups[:, :_V6_G_LEN] = vector[lay.groups : end].reshape(lay.s, _V6_G_LEN)
    fresh = np.concatenate([vector[: lay.groups], groups.ravel(), vector[end:]])
    fresh.setflags(write=False)
    return fresh


def _upgrade_layout_v7(config: StmmaeConfig, vector: FloatArray) -> FloatArray:
    """Version 7 -> 8: version 8 appends a status check, the time of the last sample outside
    the operating range (``CK_LAST_OUTSIDE_T``), unset: a state dumped less than
    ``operating_range_settle_s`` after leaving the range does not wait out the rest of it."""
    lay = layout(config)
    expected = lay.checks + _V7_CK_LEN
    if vector.shape != (expected,):
        raise EstimatorError(
            f"version-7 state of length {vector.shape[0]} does not fit this configuration "
            f"(expected {expected})"
        )
    fresh = np.concatenate([vector, initial_state(config).vector[expected : lay.group_kinds]])
    fresh.setflags(write=False)
    return fresh


def _upgrade_layout_v8(config: StmmaeConfig, vector: FloatArray) -> FloatArray:
    """Version 8 -> 9: version 9 appends the groups' kind spans (:func:`kern._group_kind`),
    which start as a fresh state has them (none open): a group detected when the state was
    dumped keeps a pending kind until it ends; the next group episode has its kind judged."""
    lay = layout(config)
    if vector.shape != (lay.group_kinds,):
        raise EstimatorError(
            f"version-8 state of length {vector.shape[0]} does not fit this configuration "
            f"(expected {lay.group_kinds})"
        )
    fresh = np.concatenate([vector, initial_state(config).vector[lay.group_kinds :]])
    fresh.setflags(write=False)
    return fresh


def _current_vector(config: StmmaeConfig, state: StmmaeState) -> FloatArray:
    """The state's vector in the current layout (older layouts upgraded step by step)."""
    vector = state.vector
    if state.layout_version == 2:
        vector = _upgrade_layout_v2(config, vector)
    if state.layout_version <= 3:
        vector = _upgrade_layout_v3(config, vector)
    if state.layout_version <= 4:
        vector = _upgrade_layout_v4(config, vector)
    if state.layout_version <= 5:
        vector = _upgrade_layout_v5(config, vector)
    if state.layout_version <= 6:
        vector = _upgrade_layout_v6(config, vector)
    if state.layout_version <= 7:
        vector = _upgrade_layout_v7(config, vector)
    if state.layout_version <= 8:
        vector = _upgrade_layout_v8(config, vector)
    return vector


_UPGRADES: dict[int, Callable[[dict[str, Any]], dict[str, Any]]] = {1: _upgrade_v1}
_LAYOUT_VERSIONS = (
    2,
    3,
    4,
    5,
    6,
    7,
    8,
    STATE_VERSION,
)  # versions whose vector this code reads directly


def load_state(data: bytes) -> StmmaeState:
    """Inverse of :func:`dump_state`; older versions are upgraded step by step
    (``_upgrade_vN``: version N -> N + 1).

    Raises:
        StateVersionError: a version this code neither reads nor upgrades.
        EstimatorError: the bytes are not a state of this estimator.
    """
    try:
        doc = json.loads(data)
    except (ValueError, UnicodeDecodeError) as exc:
        raise EstimatorError(f"not an STMMAE state: {exc}") from exc
    if not isinstance(doc, dict) or not isinstance(doc.get("version"), int):
        raise EstimatorError("not an STMMAE state: no version")
    if doc["version"] not in _LAYOUT_VERSIONS and doc["version"] not in _UPGRADES:
        raise StateVersionError(
            f"an STMMAE state version {doc['version']!r} is not supported "
            f"(reads {list(_LAYOUT_VERSIONS)}, upgrades {sorted(_UPGRADES)})"
        )
    while doc["version"] not in _LAYOUT_VERSIONS:
        doc = _UPGRADES[doc["version"]](doc)
    version = int(doc["version"])
    blob = json.dumps(doc, separators=(",", ":")).encode("ascii")
    t_last, vec = load_vector_state(blob, NAME, version, "an STMMAE")
    return StmmaeState(version=STATE_VERSION, t_last_s=t_last, vector=vec, layout_version=version)


def filter_estimates(
    config: StmmaeConfig, state: StmmaeState
) -> list[tuple[FloatArray, FloatArray]]:
    """``(x, P)`` of each filter (deviation from trim; fault filters' last entry is the absolute
    deflection), hypothesis order (copies)."""
    parts = state_parts(config, state)
    return [(parts.x[f].copy(), parts.P[f].copy()) for f in range(parts.x.shape[0])]


def surface_probabilities(config: StmmaeConfig, state: StmmaeState) -> dict[str, float | None]:
    """Each surface's marginal fault probability (the sum over the hypotheses that declare it
    faulty) at the last sample; None before any sample."""
    parts = state_parts(config, state)
    if parts.samples_seen == 0.0:
        return {s: None for s in config.model.surfaces}
    return {
        s: _finite(parts.decisions[h, kern.D_PROB]) for h, s in enumerate(config.model.surfaces)
    }


def probabilities(config: StmmaeConfig, state: StmmaeState) -> dict[str, float]:
    """Hypothesis probabilities at the last sample."""
    vals = state_parts(config, state).probabilities
    return {h: float(v) for h, v in zip(config.hypotheses, vals, strict=True)}


# ----------------------------------------------------------------------------- outputs
def sample_output_names(config: StmmaeConfig) -> tuple[str, ...]:
    """Names of the per-sample outputs, in the kernel's row order."""
    return (
        tuple(f"prob_{h}" for h in config.hypotheses)
        + tuple(f"state_{s}" for s in config.model.states)
        + tuple(f"deflection_{s}" for s in config.model.surfaces)
        + tuple(f"fault_probability_{s}" for s in config.model.surfaces)
        + ("nis_nominal",)
    )


def _deg(value: float) -> float | None:
    v = _finite(value)
    return None if v is None else round(math.degrees(v), 6)


FAULT_KINDS: dict[float, str] = {
    kern.KIND_PENDING: "pending",
    kern.KIND_STUCK: "stuck",
    kern.KIND_OSCILLATING: "oscillating",
}


def _detail(
    component: str,
    candidates: list[str],
    code: float,
    mean_rad: float,
    swing_rad: float,
    corr: float,
    onset_s: float,
    detected_s: float,
) -> dict[str, Any]:
    """Detail of a fault (events, diagnosis and status reasons share it, so they agree).

    ``fault_kind`` is ``"pending"`` until the kind span closes (``fault_kind_window_s`` after
    the start of the detection hold, or earlier when another surface is detected during it;
    a ``fault_classified`` event then gives the judgement),
    ``"stuck"`` (with ``stuck_position_deg``) or ``"oscillating"``. ``candidates``: the
    surfaces the fault may be in (the component itself, or both halves of a group)."""
    kind = FAULT_KINDS[float(code)]
    return {
        "component": component,
        "candidates": candidates,
        "fault_kind": kind,
        "stuck_position_deg": _deg(mean_rad) if kind == "stuck" else None,
        "deflection_swing_deg": _deg(swing_rad),
        "deflection_autocorrelation_min": _finite(corr),
        "onset_s": _finite(onset_s),
        "detected_s": _finite(detected_s),
    }


def _fault_detail(config: StmmaeConfig, h: int, d: FloatArray) -> dict[str, Any]:
    """Detail of the active fault of surface ``h`` from its decision fields."""
    dec = d.reshape(1, -1)
    return _detail(
        *_component(config, h, -1),
        d[kern.D_KIND],
        kern.episode_mean(dec, 0),
        kern.episode_swing(dec, 0),
        d[kern.D_KIND_CORR],
        d[kern.D_ONSET_T],
        d[kern.D_DETECTED_T],
    )


EVENT_KINDS: dict[int, str] = {
    kern.EV_DETECTED: "fault_detected",
    kern.EV_CLASSIFIED: "fault_classified",
    kern.EV_CLEARED: "fault_cleared",
}


def group_name(a: str, b: str) -> str:
    """Name of the group of twin halves ``a`` and ``b``: their common stem before the last
    ``_`` ("elevator" for ``elevator_left`` and ``elevator_right``), else ``"a|b"``."""
    stem_a, _, _ = a.rpartition("_")
    stem_b, _, _ = b.rpartition("_")
    return stem_a if stem_a and stem_a == stem_b else f"{a}|{b}"


def _component(config: StmmaeConfig, h: int, twin: int) -> tuple[str, list[str]]:
    """Name and candidate surfaces of surface ``h``, or of the group of ``h`` and its twin
    (surface indices; ``twin`` -1 for a single surface)."""
    surfaces = config.model.surfaces
    if twin < 0:
        return surfaces[h], [surfaces[h]]
    return group_name(surfaces[h], surfaces[twin]), [surfaces[h], surfaces[twin]]


def _event(row: FloatArray, config: StmmaeConfig) -> EstimatorEvent:
    """An event from its kernel row (a group's row: the kind of the group's own span)."""
    kind = EVENT_KINDS[int(row[kern.EV_KIND])]
    twin = int(row[kern.EV_TWIN]) - 1
    detail = _detail(
        *_component(config, int(row[kern.EV_HYP]) - 1, twin),
        row[kern.EV_FAULT_KIND],
        row[kern.EV_MEAN],
        row[kern.EV_SWING],
        row[kern.EV_CORR],
        row[kern.EV_ONSET_T],
        row[kern.EV_DETECTED_T],
    )
    if kind == "fault_detected":
        detail["log_likelihood_ratio"] = _finite(round(float(row[kern.EV_LLR]), 3))
    if kind == "fault_cleared":
        detail["cleared_s"] = _finite(row[kern.EV_CLEARED_T])
        if twin >= 0:
            half = int(row[kern.EV_ISOLATED_AS]) - 1
            detail["isolated_as"] = config.model.surfaces[half] if half >= 0 else None
    return EstimatorEvent(t_s=float(row[kern.EV_T]), kind=kind, detail=detail)


def _events(config: StmmaeConfig, state: StmmaeState, rows: FloatArray) -> list[EstimatorEvent]:
    """The batch's events from their kernel rows, in order, each with ``kind_beside``: the
    faults in place at that moment (those of ``state``, the state before the batch, then
    opened and closed by the events before it) that were detected before its onset, as
    :func:`active_faults` gives them in the diagnosis."""
    if len(rows) == 0:
        return []
    in_fault = {f["component"]: f for f in active_faults(config, state)}
    events = []
    for row in rows:
        ev = _event(row, config)
        d = ev.detail
        now = list(in_fault.values())
        d["kind_beside"] = kind_beside(now, d)
        d["twin_in_fault"] = twin_in_fault(config, now, d)
        if ev.kind == "fault_detected":
            in_fault[d["component"]] = d
        elif ev.kind == "fault_cleared":
            in_fault.pop(d["component"], None)
        events.append(ev)
    return events


def _fault_reason(f: dict[str, Any]) -> str:
    """Status reason of an active fault, from the same detail as its events."""
    which = " or ".join(f["candidates"])
    notes = " (which one: not isolated yet)" if len(f["candidates"]) > 1 else ""
    if f.get("kind_beside"):
        notes += f" (kind judged beside {' and '.join(f['kind_beside'])} in fault: less certain)"
    if f.get("twin_in_fault"):
        notes += (
            f" (its twin {f['twin_in_fault']} in fault too: the data determine mainly the sum of"
            " the two halves' deflections, so one of the two may not be in fault)"
        )
    if f["fault_kind"] == "stuck":
        pos = f["stuck_position_deg"]
        where = "unknown position" if pos is None else f"{pos:.1f} deg"
        return f"fault: {which} stuck at {where}{notes}"
    if f["fault_kind"] == "oscillating":
        swing = f["deflection_swing_deg"]
        return f"fault: {which} oscillating, swing {swing:.1f} deg{notes}"
    if len(f["candidates"]) > 1:
        return f"fault: {which} not following its command (which one: not isolated yet)"
    return (
        f"fault: {f['component']} not following its command (stuck or oscillating: pending){notes}"
    )


def active_faults(config: StmmaeConfig, state: StmmaeState) -> list[dict[str, Any]]:
    """Details of the faults active at the last sample."""
    parts = state_parts(config, state)
    faults = [
        _fault_detail(config, h, d)
        for h, d in enumerate(parts.decisions)
        if d[kern.D_ACTIVE] == 1.0
    ]
    arr = config.arrays
    gkd = parts.group_kinds
    for h, g in enumerate(parts.groups):
        if g[kern.G_ACTIVE] == 1.0:
            a = kern.twin_index(arr.collinear, h)
            r = kern.group_kind_row(gkd, h, a)
            nan = math.nan  # no kind, position or swing before the group's kind is judged
            faults.append(
                _detail(
                    *_component(config, h, a),
                    gkd[r, kern.D_KIND] if r >= 0 else kern.KIND_PENDING,
                    kern.episode_mean(gkd, r) if r >= 0 else nan,
                    kern.episode_swing(gkd, r) if r >= 0 else nan,
                    gkd[r, kern.D_KIND_CORR] if r >= 0 else nan,
                    g[kern.G_ONSET_T],
                    g[kern.G_DETECTED_T],
                )
            )
    for f in faults:
        f["kind_beside"] = kind_beside(faults, f)
        f["twin_in_fault"] = twin_in_fault(config, faults, f)
    return faults


def twin_in_fault(
    config: StmmaeConfig, in_fault: list[dict[str, Any]], f: dict[str, Any]
) -> str | None:
    """The twin half of fault ``f`` when ``f`` names one half of a split surface and its twin
    is in ``in_fault`` too (details with ``component``), else None. The data determine mainly the
    sum of two twin halves' deflections: with both in fault, one of them often is not
    (docs/methods-stmmae.md, "Outputs")."""
    surfaces = config.model.surfaces
    if len(f["candidates"]) != 1 or f["component"] not in surfaces:
        return None
    a = kern.twin_index(config.arrays.collinear, surfaces.index(f["component"]))
    if a < 0:
        return None
    twin = surfaces[a]
    return twin if any(o["component"] == twin for o in in_fault) else None


def kind_beside(in_fault: list[dict[str, Any]], f: dict[str, Any]) -> list[str]:
    """The other faults in ``in_fault`` (details with ``component``, ``candidates`` and
    ``detected_s``) that were detected before the onset of fault ``f``, a group and its own
    halves left out: ``f``'s kind is judged on an estimate into which their deflections leak,
    and is less certain (docs/methods-stmmae.md, "Outputs")."""
    onset = f["onset_s"]
    if onset is None:
        return []
    mine = set(f["candidates"])
    return sorted(
        o["component"]
        for o in in_fault
        if not mine & set(o["candidates"])
        and o["detected_s"] is not None
        and o["detected_s"] < onset
    )


def outside_operating_range(config: StmmaeConfig, state: StmmaeState) -> list[str]:
    """One reason per measurement whose smoothed value is outside the model's operating range
    at the last sample; inside it, one reason while the aircraft has been back inside for less
    than ``operating_range_settle_s`` (empty: inside and settled, or no bound)."""
    parts = state_parts(config, state)
    smoothed = parts.operating
    reasons = []
    for a, meas in enumerate(config.model.measurements):
        bounds = config.model.operating_range.get(meas.name)
        value = float(smoothed[a])
        if bounds is None or not math.isfinite(value) or bounds[0] <= value <= bounds[1]:
            continue
        reasons.append(
            f"{meas.name} {value:.4g} (smoothed over {config.operating_range_smoothing_s:g} s) "
            f"outside the model's operating range {bounds[0]:g} to {bounds[1]:g}: "
            "no new fault is detected"
        )
    since = state.t_last_s - float(parts.last_outside_s[0])
    if not reasons and since < config.operating_range_settle_s:
        reasons.append(
            f"back inside the model's operating range for {since:.2f} s: no new fault is "
            f"detected before {config.operating_range_settle_s:g} s inside"
        )
    return reasons


def _noise_reason(ratio: float, config: StmmaeConfig) -> str:
    return (
        f"innovations average {ratio:.3g} times the model's sensor noise R (unknown above "
        f"{config.noise_ratio_unknown:g}): the sensors are noisier than the model says, or the "
        "model does not fit; faults may go undetected"
    )


def _noise_reasons(config: StmmaeConfig, state: StmmaeState) -> list[str]:
    """The reason when the innovation energy, smoothed over ``operating_range_smoothing_s``, is
    above ``noise_ratio_unknown``; else none."""
    ratio = float(state_parts(config, state).noise_smoothed[0])
    return [_noise_reason(ratio, config)] if ratio > config.noise_ratio_unknown else []


def status_report(
    config: StmmaeConfig, state: StmmaeState, faults: list[dict[str, Any]] | None = None
) -> StatusReport:
    """ "alert" while a fault is active; "unknown" while a measurement is outside the model's
    operating range or has been back inside for less than ``operating_range_settle_s`` (no new
    fault is detected then) or the innovations, smoothed, are above
    ``noise_ratio_unknown`` times the model's sensor noise; "watch" while a surface's fault
    probability is above ``watch_probability`` without being confirmed; else "ok".
    ``faults``: :func:`active_faults` of ``state`` when the caller has them."""
    if faults is None:
        faults = active_faults(config, state)
    unknown = outside_operating_range(config, state) + _noise_reasons(config, state)
    if faults:
        return StatusReport("alert", tuple(_fault_reason(f) for f in faults) + tuple(unknown))
    if unknown:
        return StatusReport("unknown", tuple(unknown))
    watch = [
        f"{s} fault probability {p:.2f} above {config.watch_probability:g}, not confirmed"
        for s, p in surface_probabilities(config, state).items()
        if p is not None and p > config.watch_probability
    ]
    return StatusReport("watch", tuple(watch)) if watch else StatusReport("ok")


def diagnosis(
    config: StmmaeConfig, state: StmmaeState, faults: list[dict[str, Any]] | None = None
) -> Diagnosis:
    """Probabilities (per hypothesis and per surface), active faults and deflection estimates
    at the last sample (``faults``: :func:`active_faults` of ``state`` when the caller has
    them)."""
    dec = state_parts(config, state).decisions
    defl = {s: _deg(dec[h, kern.D_DEFL]) for h, s in enumerate(config.model.surfaces)}
    return Diagnosis(
        t_s=float(state.t_last_s),
        detail={
            "probabilities": {h: _finite(p) for h, p in probabilities(config, state).items()},
            "surface_fault_probabilities": surface_probabilities(config, state),
            "active_faults": active_faults(config, state) if faults is None else faults,
            "deflection_estimates_deg": defl,
            "outside_operating_range": outside_operating_range(config, state),
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
        "outside_operating_range_fraction": _finite(row[kern.WIN_OUTSIDE_FRACTION]),
        "innovation_noise_ratio": _finite(row[kern.WIN_NOISE_RATIO]),
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
    ratio = indicators["innovation_noise_ratio"]
    if ratio is not None and ratio > config.noise_ratio_unknown:
        if status != "alert":
            status = "unknown"
        reasons.append(_noise_reason(ratio, config))
    outside = indicators["outside_operating_range_fraction"] or 0.0
    if outside > 0.0:
        if status != "alert":
            status = "unknown"
        reasons.append(
            f"outside the model's operating range during {100 * outside:.0f} % of the window: "
            "no new fault detected there"
        )
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

    A batch with ``end_of_run`` closes the partial health window after its last sample (every
    sample of a closed run is in some window); the filters and decisions carry on.

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
    if state.layout_version != STATE_VERSION:
        state = StmmaeState(STATE_VERSION, state.t_last_s, _current_vector(config, state))
    state_parts(config, state)  # raises if the state does not fit the configuration
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
    lay = layout(config)
    wacc = vec[lay.window : lay.window + kern.W_LEN]
    if batch.end_of_run and wacc[kern.W_COUNT] > 0.0:
        # the run is closed: its partial health window is scored now
        row = np.empty((1, kern.WIN_LEN))
        kern._close_window(wacc, vec[lay.checks : lay.group_kinds], float(t[n - 1]), row[0])
        windows = np.concatenate([windows, row])
    vec.setflags(write=False)
    new_state = StmmaeState(version=STATE_VERSION, t_last_s=float(t[n - 1]), vector=vec)
    faults = active_faults(config, new_state)
    outputs = StepOutputs(
        samples={name: samples[i] for i, name in enumerate(names)},
        health=[_health(row, config) for row in windows],
        events=_events(config, state, events),
        diagnosis=diagnosis(config, new_state, faults),
        status=status_report(config, new_state, faults),
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
