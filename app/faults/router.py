"""Fault isolation over HTTP."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Query

from app.deps import ActuatorDep, ReadSessionDep
from app.errors import error_responses
from app.faults import schemas, service

router = APIRouter(prefix="/v1", tags=["health"])


@router.get(
    "/aircraft/{tail}/actuators/{actuator_id}/faults",
    response_model=schemas.ActuatorFaults,
    responses=error_responses(401, 403, 404),
)
def actuator_faults(
    tail: str,
    act: ActuatorDep,
    s: ReadSessionDep,
    limit: Annotated[int, Query(ge=1, le=100_000, description="Most recent fault events")] = 1000,
) -> schemas.ActuatorFaults:
    """Fault isolation: each estimator's current diagnosis (hypothesis probabilities, residual
    status, coherence vector, candidate fault sets, parameter estimates with bounds), the faults
    detected and not yet cleared, and the fault events."""
    return schemas.ActuatorFaults.model_validate(service.faults(s, tail, act, limit))
