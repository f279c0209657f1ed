"""Response models of health, outputs, events, RUL and fault isolation."""

from __future__ import annotations

from datetime import datetime
from typing import Any

from pydantic import BaseModel, Field

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


class EstimatorHealth(BaseModel):
    status: HealthStatus
    reasons: list[str]
    window: HealthWindowPublic | None


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


class SampleOutputs(BaseModel):
    estimator: str
    t_s: list[float]
    series: dict[str, list[float | None]]
    truncated: bool = Field(description="True when more samples matched than max_samples")


class EventPublic(BaseModel):
    estimator: str
    seq: int
    t_s: float
    kind: str
    detail: dict[str, Any]


class EventList(BaseModel):
    items: list[EventPublic]


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


class ActuatorRul(BaseModel):
    tail: str
    actuator_id: str
    latest: dict[str, RulEstimatePublic] = Field(description="Estimator -> its latest prognosis")
    items: list[RulEstimatePublic] = Field(description="Prognoses in [from_s, to_s], oldest first")
    truncated: bool


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
