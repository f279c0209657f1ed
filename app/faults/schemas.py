"""Response models of fault isolation."""

from __future__ import annotations

from typing import Any

from pydantic import BaseModel, Field

from app.health.schemas import EventPublic
from app.status import HealthStatus


class EstimatorDiagnosis(BaseModel):
    status: HealthStatus
    reasons: list[str]
    t_s: float | None = Field(description="Stream time of the diagnosis")
    diagnosis: dict[str, Any] | None = Field(
        description="Estimator-specific: hypothesis probabilities, residuals, coherence vector, "
        "candidate fault sets, parameter estimates with bounds"
    )


class ActuatorFaults(BaseModel):
    tail: str
    actuator_id: str
    status: HealthStatus
    active_faults: list[EventPublic] = Field(description="Detections not yet cleared")
    estimators: dict[str, EstimatorDiagnosis]
    events: list[EventPublic] = Field(description="Fault detections and clearances, oldest first")
