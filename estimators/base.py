"""The contract every estimator kind implements.

An estimator is a pure function over an explicit state::

    state, outputs = kind.step(config, state, batch)

* ``config`` is an immutable, validated configuration built by ``kind.parse_config(raw_dict)``.
* ``state`` is immutable; ``kind.dump_state`` / ``kind.load_state`` give a versioned byte form.
  Loading an unknown version raises :class:`StateVersionError`.
* ``batch`` holds whole arrays; a NaN in a channel means "the sensor gave nothing at this time"
  and the estimator predicts through it.
* Feeding a series in one batch or split into any batches gives the same outputs: per-sample
  outputs are per sample, and health indicators are computed over fixed windows of stream samples
  whose partial accumulators live in the state, so a window that spans two batches is reported
  once, by the batch that completes it.

This module holds only plain Python and numpy: the service (``app``) depends on it, never the
reverse.
"""

from __future__ import annotations

import base64
import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Literal, Protocol

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, ValidationError

Status = Literal["learning", "ok", "watch", "alert", "unknown", "failed"]
"""What an estimator (and, taking the worst, an actuator) reports:

* ``learning``: no model yet, calibrating, or not converged; nothing to vouch for.
* ``ok``, ``watch``, ``alert``: graded evidence against the configured levels.
* ``unknown``: the estimator's own consistency checks reject its outputs; the reasons say which.
  Never ``ok`` while inconsistent.
* ``failed``: past the failure threshold; stays until a maintenance action resets the estimator.
"""
STATUSES: tuple[Status, ...] = ("learning", "ok", "watch", "alert", "unknown", "failed")
# Severity for "worst first": an estimator that cannot vouch for its outputs (unknown) ranks
# above graded concern (watch) but below positive evidence of degradation (alert, failed).
STATUS_ORDER: dict[str, int] = {
    "ok": 0,
    "learning": 1,
    "watch": 2,
    "unknown": 3,
    "alert": 4,
    "failed": 5,
}

FloatArray = NDArray[np.float64]


class EstimatorError(ValueError):
    """Base class for errors an estimator reports about its inputs."""


class ConfigError(EstimatorError):
    """The estimator configuration is invalid (the service answers 422)."""


class StateVersionError(EstimatorError):
    """A serialized state has a schema version this code does not know."""


class OutOfOrderError(EstimatorError):
    """A batch starts at or before the time of the state's last sample (the service answers 409)."""


@dataclass(frozen=True)
class Batch:
    """A block of consecutive samples of one stream.

    Attributes:
        t_s: sample times in seconds, shape (n,), strictly increasing.
        channels: channel name -> values, each shape (n,), float64; NaN marks a missing sample.
        end_of_run: the client closed the run after this batch's last sample: estimators close
            their partial health windows (and any per-run accumulators) so every sample of a
            closed run is scored. Split invariance holds when the marker rides on the last batch.
    """

    t_s: FloatArray
    channels: Mapping[str, FloatArray]
    end_of_run: bool = False

    def __len__(self) -> int:
        return int(self.t_s.shape[0])


@dataclass(frozen=True)
class HealthWindow:
    """Health indicators over one completed window of stream samples.

    Attributes:
        t_start_s: time of the window's first sample.
        t_end_s: time of the window's last sample.
        n_samples: samples in the window.
        indicators: indicator name -> value (None when undefined, e.g. no valid sample).
        status: worst status of the indicators against the configured thresholds.
        reasons: human-readable reasons for a non-ok status.
    """

    t_start_s: float
    t_end_s: float
    n_samples: int
    indicators: dict[str, float | None]
    status: Status
    reasons: tuple[str, ...] = ()


@dataclass(frozen=True)
class EstimatorEvent:
    """Something that happened once in a stream (identification done or failed, fault detected).

    Attributes:
        t_s: stream time of the event.
        kind: short machine name, e.g. ``"identified"``, ``"identification_failed"``.
        detail: JSON-serializable details.
    """

    t_s: float
    kind: str
    detail: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class RulEstimate:
    """A remaining-useful-life prognosis made at stream time ``t_s``.

    Times are seconds of stream time from ``t_s`` until the health quantity reaches
    ``threshold``; None when the threshold is not reached within the prediction horizon by
    enough trajectories to define the statistic.

    Attributes:
        t_s: stream time the prognosis was made at.
        mean_s, std_s: mean and standard deviation of the Monte Carlo RUL.
        q05_s, q50_s, q95_s: 5, 50 and 95 % quantiles.
        optimistic_s, pessimistic_s: deterministic bounds (e.g. from the +-3 sigma states).
        threshold: failure threshold on the health quantity.
        health: the health quantity now, with bounds, e.g. ``{"dn": .., "dn_lower": ..}``.
        assumption: the future-load assumption and Monte Carlo settings, JSON-serializable.
        status: status implied by this prognosis against the configured RUL / health levels.
        reasons: human-readable reasons for a non-ok status.
    """

    t_s: float
    mean_s: float | None
    std_s: float | None
    q05_s: float | None
    q50_s: float | None
    q95_s: float | None
    optimistic_s: float | None
    pessimistic_s: float | None
    threshold: float
    health: dict[str, float | None]
    assumption: dict[str, Any]
    status: Status = "ok"
    reasons: tuple[str, ...] = ()


@dataclass(frozen=True)
class Diagnosis:
    """The estimator's current diagnostic picture; each one replaces the previous.

    ``detail`` is JSON-serializable and estimator-specific: hypothesis probabilities and active
    faults (filter banks), residual status, coherence vector, candidate fault sets and parameter
    estimates with bounds (residual-based isolation).
    """

    t_s: float
    detail: dict[str, Any]


@dataclass(frozen=True)
class StatusReport:
    """The estimator's status at the end of a batch, when it reports one directly."""

    status: Status
    reasons: tuple[str, ...] = ()


@dataclass(frozen=True)
class StepOutputs:
    """What one ``step`` produced.

    Attributes:
        samples: per-sample outputs, name -> array of shape (n,) aligned with ``batch.t_s``.
        health: windows completed during this batch, in time order.
        events: events raised during this batch, in time order. Fault isolation uses the kinds
            ``"fault_detected"`` and ``"fault_cleared"``; their ``detail`` names the faulty
            component (``"component"``) and what is known of the fault.
        rul: RUL prognoses made during this batch, in time order.
        diagnosis: the diagnostic picture at the end of this batch (None: unchanged).
        status: the estimator's status at the end of this batch. None means the status of the
            last health window (or RUL estimate) stands.
    """

    samples: dict[str, FloatArray]
    health: Sequence[HealthWindow] = ()
    events: Sequence[EstimatorEvent] = ()
    rul: Sequence[RulEstimate] = ()
    diagnosis: Diagnosis | None = None
    status: StatusReport | None = None


class EstimatorConfigModel(BaseModel):
    """Base of every kind's public configuration model.

    Each kind declares its settings as a subclass (types, defaults and units in each field's
    description), so the service validates them with clear errors and the OpenAPI documents them.
    Unknown keys are refused; a validated config is immutable.
    """

    model_config = ConfigDict(frozen=True, extra="forbid")


def config_error(label: str, exc: ValidationError) -> ConfigError:
    """A :class:`ConfigError` naming each invalid field of a config, one clause per problem."""
    parts = []
    for err in exc.errors(include_url=False):
        where = ".".join(str(p) for p in err["loc"]) or "config"
        parts.append(f"{where}: {err['msg']}")
    return ConfigError(f"{label}: " + "; ".join(parts))


class EstimatorKind(Protocol):
    """What a module in ``estimators`` exposes to be registered as an estimator kind.

    ``load_state`` reads the current ``STATE_VERSION`` and every older version the kind still
    knows how to upgrade; it raises :class:`StateVersionError` for any other version, and the
    service then replays the stream from its telemetry log or marks it ``failed``.
    """

    NAME: str
    STATE_VERSION: int

    @property
    def CONFIG_MODEL(self) -> type[EstimatorConfigModel]:  # noqa: N802 (a module constant)
        """The kind's public configuration model (read-only, so a subclass satisfies it)."""

    def parse_config(self, raw: Mapping[str, Any]) -> Any:
        """Validate a JSON-like mapping; raise :class:`ConfigError` naming the problem."""

    def config_to_dict(self, config: Any) -> dict[str, Any]:
        """The full configuration with defaults filled in, JSON-serializable."""

    def required_channels(self, config: Any) -> tuple[str, ...]:
        """Names of the stream channels this estimator reads."""

    def initial_state(self, config: Any) -> Any:
        """State before the first sample."""

    def step(self, config: Any, state: Any, batch: Batch) -> tuple[Any, StepOutputs]:
        """Advance over a whole batch."""

    def dump_state(self, state: Any) -> bytes:
        """Versioned byte form of the state."""

    def load_state(self, data: bytes) -> Any:
        """Inverse of :meth:`dump_state`; raise :class:`StateVersionError` on unknown versions."""

    def warm_up(self) -> None:
        """Compile (or load from cache) the kernels so that no request pays a compile."""


def worst_status(statuses: Sequence[str]) -> Status:
    """The most severe of a sequence of statuses ("ok" for an empty one)."""
    worst: Status = "ok"
    for s in statuses:
        if STATUS_ORDER[s] > STATUS_ORDER[worst]:
            worst = s  # type: ignore[assignment]
    return worst


# ----------------------------------------------------------------------------- state codec
def dump_vector_state(kind: str, version: int, t_last_s: float, vector: FloatArray) -> bytes:
    """The byte form of a state held as one float vector: JSON with the kind and version, the
    time as ``float.hex`` and the vector as base64 of its little-endian float64 bytes (both an
    exact round trip, NaN and infinities included; the base64 form costs a seventh of a
    ``float.hex`` list to write and to read)."""
    doc = {
        "version": version,
        "kind": kind,
        "t_last_s": float(t_last_s).hex(),
        "vector64": base64.b64encode(np.ascontiguousarray(vector, dtype="<f8").tobytes()).decode("ascii"),
    }
    return json.dumps(doc, separators=(",", ":")).encode("ascii")


def load_vector_state(data: bytes, kind: str, version: int, label: str) -> tuple[float, FloatArray]:
    """Inverse of :func:`dump_vector_state`: ``(t_last_s, read-only vector)``. States written
    before the base64 form (the vector as a list of ``float.hex`` strings) read the same.

    Raises:
        StateVersionError: the version is not ``version``.
        EstimatorError: the bytes are not a state of ``kind`` (``label`` names it in messages).
    """
    try:
        doc = json.loads(data)
    except (ValueError, UnicodeDecodeError) as exc:
        raise EstimatorError(f"not {label} state: {exc}") from exc
    if not isinstance(doc, dict) or "version" not in doc:
        raise EstimatorError(f"not {label} state: no version")
    if doc["version"] != version:
        raise StateVersionError(
            f"{label} state version {doc['version']!r} is not supported (expected {version})"
        )
    if doc.get("kind", kind) != kind:
        raise EstimatorError(f"not {label} state: kind {doc.get('kind')!r}")
    try:
        if "vector64" in doc:
            raw = base64.b64decode(doc["vector64"], validate=True)
            if len(raw) % 8:
                raise ValueError(f"{len(raw)} bytes is not a whole number of float64 values")
            vec = np.frombuffer(raw, dtype="<f8").astype(np.float64)
        else:
            vec = np.array([float.fromhex(v) for v in doc["vector"]], dtype=np.float64)
        t_last = float.fromhex(doc["t_last_s"])
    except (KeyError, TypeError, ValueError) as exc:  # binascii.Error is a ValueError
        raise EstimatorError(f"not {label} state: {exc}") from exc
    if vec.ndim != 1:
        raise EstimatorError(f"not {label} state: vector of shape {vec.shape}")
    vec.setflags(write=False)
    return t_last, vec
