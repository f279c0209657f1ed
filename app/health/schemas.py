"""Response models of health, outputs, events, RUL and fault isolation."""

from __future__ import annotations

from datetime import datetime
from typing import Any, Literal

from pydantic import BaseModel, Field

from app.pagination import CURSOR_DOC
from app.status import HealthStatus


class HealthWindowPublic(BaseModel):
    estimator: str
    seq: int = Field(description="Stream sequence number of the batch that completed the window")
    t_start_s: float
    t_end_s: float
    n_samples: int
    indicators: dict[str, float | None]
    status: HealthStatus
    reasons: list[str]
    config_version: int = Field(default=1, description="Config version of the estimator that produced it")
    baseline: int = Field(default=1, description="Baseline (epoch of the physical part) it belongs to")


class EstimatorHealth(BaseModel):
    status: HealthStatus
    reasons: list[str]
    config_version: int = Field(default=1, description="Config version in force")
    baseline: int = Field(default=1, description="Baseline the estimator is in")
    window: HealthWindowPublic | None = Field(description="Latest window of the current baseline")


class ActuatorHealth(BaseModel):
    tail: str
    actuator_id: str
    kind: str
    status: HealthStatus
    failure: str | None = Field(
        default=None, description="Why the stream is no longer applied (status failed), if so"
    )
    last_logged_seq: int
    last_applied_seq: int
    t_last_s: float | None
    updated_at: datetime
    estimators: dict[str, EstimatorHealth]


class HealthHistory(BaseModel):
    items: list[HealthWindowPublic]
    next_cursor: str | None = Field(default=None, description=CURSOR_DOC)


class SampleOutputs(BaseModel):
    estimator: str
    t_s: list[float] = Field(description="Sample times in the order asked for (newest first by default)")
    series: dict[str, list[float | None]]
    truncated: bool = Field(description="True when more samples follow (see next_cursor)")
    next_cursor: str | None = Field(default=None, description=CURSOR_DOC)


class EventPublic(BaseModel):
    estimator: str
    seq: int
    t_s: float
    kind: str
    detail: dict[str, Any]
    config_version: int = Field(default=1, description="Config version of the estimator that produced it")
    baseline: int = Field(default=1, description="Baseline (epoch of the physical part) it belongs to")


class EventList(BaseModel):
    items: list[EventPublic]
    next_cursor: str | None = Field(default=None, description=CURSOR_DOC)


class RulEstimatePublic(BaseModel):
    estimator: str
    seq: int = Field(description="Stream sequence number of the batch that produced it")
    t_s: float = Field(description="Stream time the prognosis was made at")
    mean_s: float | None = Field(description="Mean RUL, seconds (None: threshold beyond the horizon)")
    std_s: float | None
    q05_s: float | None
    q50_s: float | None
    q95_s: float | None
    optimistic_s: float | None
    pessimistic_s: float | None
    threshold: float = Field(description="Failure threshold on the health quantity")
    health: dict[str, float | None] = Field(description="Health quantity now, with bounds")
    assumption: dict[str, Any] = Field(description="Future-load assumption and Monte Carlo settings")
    status: HealthStatus
    reasons: list[str]
    config_version: int = Field(default=1, description="Config version of the estimator that produced it")
    baseline: int = Field(default=1, description="Baseline (epoch of the physical part) it belongs to")


    event_state: float | None = Field(
        default=None,
        description="Normalized health now, 1 = new, 0 = failure threshold met (progpy's event_state); "
        "null for an estimator without a normalized health quantity",
    )
    event_state_lower: float | None = Field(default=None, description="Lower bound of event_state")
    event_state_upper: float | None = Field(default=None, description="Upper bound of event_state")
    threshold_met: bool | None = Field(
        default=None, description="The health quantity has reached the failure threshold (progpy's threshold_met)"
    )
    time_basis: Literal["epoch", "stream"] = Field(
        default="stream",
        description="`epoch`: stream times are epoch seconds, so time_of_event is absolute UTC; "
        "`stream`: the stream's own clock, only time_of_event_t_s is known",
    )
    time_of_event: datetime | None = Field(
        default=None, description="When the threshold is met (median RUL), UTC; null unless time_basis is epoch"
    )
    time_of_event_q05: datetime | None = Field(default=None, description="Earliest (5 % quantile), UTC")
    time_of_event_q95: datetime | None = Field(default=None, description="Latest (95 % quantile), UTC")
    time_of_event_t_s: float | None = Field(default=None, description="t_s + q50_s, stream seconds")
    time_of_event_q05_t_s: float | None = Field(default=None, description="t_s + q05_s, stream seconds")
    time_of_event_q95_t_s: float | None = Field(default=None, description="t_s + q95_s, stream seconds")
    rul_operating_hours: dict[str, float | None] | None = Field(
        default=None,
        description="RUL (mean, q05, q50, q95) in operating hours, when the actuator sends an "
        "`operating_hours` counter channel: seconds x the counter's average rate over the baseline",
    )
    rul_cycles: dict[str, float | None] | None = Field(
        default=None, description="RUL (mean, q05, q50, q95) in cycles, from a `cycles` counter channel"
    )


class ActuatorRul(BaseModel):
    tail: str
    actuator_id: str
    latest: dict[str, RulEstimatePublic] = Field(
        description="Estimator -> its latest prognosis in the current baseline"
    )
    items: list[RulEstimatePublic] = Field(description="Prognoses in [from_s, to_s], in the order asked for")
    truncated: bool = Field(description="True when more prognoses follow (see next_cursor)")
    next_cursor: str | None = Field(default=None, description=CURSOR_DOC)


class SeriesPublic(BaseModel):
    estimator: str | None
    source: str = Field(description="`outputs`, `health` or `telemetry`")
    from_s: float | None = Field(description="Start of the span drawn (the first sample's time by default)")
    to_s: float | None = Field(description="End of the span drawn (the last sample's time by default)")
    n_samples: int = Field(description="Samples (or windows) in the span before downsampling")
    reduced: bool = Field(
        description="True when the span held more than `points` samples and per-bucket minima "
        "and maxima replace them"
    )
    t_s: list[float]
    series: dict[str, list[float | None]]
