"""Request and response models of the public API."""

from __future__ import annotations

from datetime import datetime
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field

Name = Field(min_length=1, max_length=64, pattern=r"^[A-Za-z0-9][A-Za-z0-9._\-]*$")
StatusT = Literal["ok", "watch", "alert"]


class AircraftCreate(BaseModel):
    model_config = ConfigDict(extra="forbid")
    tail: str = Field(min_length=1, max_length=32, pattern=r"^[A-Za-z0-9][A-Za-z0-9\-]*$")
    description: str | None = Field(default=None, max_length=500)


class AircraftPublic(BaseModel):
    tail: str
    description: str | None
    created_at: datetime


class AircraftList(BaseModel):
    items: list[AircraftPublic]


class ActuatorCreate(BaseModel):
    model_config = ConfigDict(extra="forbid")
    actuator_id: str = Name
    kind: str = Field(description="Actuator kind, e.g. ema_voltage")
    channels: list[str] | None = Field(
        default=None, description="Channel names the telemetry carries (default: the kind's)"
    )
    estimators: dict[str, dict[str, Any]] | None = Field(
        default=None,
        description="Estimator name -> configuration (default: the kind's estimators with defaults)",
    )


class ActuatorPublic(BaseModel):
    actuator_id: str
    kind: str
    channels: list[str]
    estimators: dict[str, dict[str, Any]]
    created_at: datetime


class ActuatorList(BaseModel):
    items: list[ActuatorPublic]


class BatchAck(BaseModel):
    batch_id: str
    seq: int = Field(description="Position of the batch in the actuator's stream (1, 2, ...)")
    n_samples: int
    t_first_s: float
    t_last_s: float
    received_at: datetime


class HealthWindowPublic(BaseModel):
    estimator: str
    seq: int = Field(description="Stream sequence number of the batch that completed the window")
    t_start_s: float
    t_end_s: float
    n_samples: int
    indicators: dict[str, float | None]
    status: StatusT
    reasons: list[str]


class EstimatorHealth(BaseModel):
    status: StatusT
    reasons: list[str]
    window: HealthWindowPublic | None


class ActuatorHealth(BaseModel):
    tail: str
    actuator_id: str
    kind: str
    status: StatusT
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


class FleetActuator(BaseModel):
    actuator_id: str
    kind: str
    status: StatusT
    t_last_s: float | None
    last_logged_seq: int
    last_applied_seq: int
    updated_at: datetime | None
    rul_q05_s: float | None = Field(
        default=None, description="5 % quantile of the latest RUL prognosis, seconds of stream time"
    )
    rul_q50_s: float | None = Field(default=None, description="Median of the latest RUL prognosis")
    rul_t_s: float | None = Field(default=None, description="Stream time of the latest RUL prognosis")
    active_faults: list[str] = Field(
        default_factory=list, description="Components with a detected, not yet cleared, fault"
    )


class FleetAircraft(BaseModel):
    tail: str
    status: StatusT
    updated_at: datetime | None
    actuators: list[FleetActuator]


class FleetHealth(BaseModel):
    aircraft: list[FleetAircraft]


class KeyCreate(BaseModel):
    model_config = ConfigDict(extra="forbid")
    name: str = Field(default="", max_length=100)
    scopes: list[Literal["ingest", "read", "admin"]] = Field(min_length=1)


class KeyCreated(BaseModel):
    id: int
    name: str
    prefix: str
    scopes: list[str]
    key: str = Field(description="The key itself; shown once, stored only as a digest")


class KindPublic(BaseModel):
    name: str
    description: str
    channels: list[str]
    default_estimators: dict[str, dict[str, Any]]


class KindList(BaseModel):
    items: list[KindPublic]


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
    status: StatusT
    reasons: list[str]


class ActuatorRul(BaseModel):
    tail: str
    actuator_id: str
    latest: dict[str, RulEstimatePublic] = Field(description="Estimator -> its latest prognosis")
    items: list[RulEstimatePublic] = Field(description="Prognoses in [from_s, to_s], oldest first")
    truncated: bool


class EstimatorDiagnosis(BaseModel):
    status: StatusT
    reasons: list[str]
    t_s: float | None = Field(description="Stream time of the diagnosis")
    diagnosis: dict[str, Any] | None = Field(
        description="Estimator-specific: hypothesis probabilities, residuals, coherence vector, "
        "candidate fault sets, parameter estimates with bounds"
    )


class ActuatorFaults(BaseModel):
    tail: str
    actuator_id: str
    status: StatusT
    active_faults: list[EventPublic] = Field(description="Detections not yet cleared")
    estimators: dict[str, EstimatorDiagnosis]
    events: list[EventPublic] = Field(description="Fault detections and clearances, oldest first")
