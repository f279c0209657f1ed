"""Health, per-sample outputs, events and the fleet overview."""

from __future__ import annotations

from typing import Annotated, Literal

from fastapi import APIRouter, Query
from starlette.concurrency import run_in_threadpool

from app import schemas
from app.api.deps import DbDep, ReadDep
from app.errors import error_responses
from app.services import fleet, queries

router = APIRouter(prefix="/v1", tags=["health"])
ACT = "/aircraft/{tail}/actuators/{actuator_id}"


@router.get(f"{ACT}/health", response_model=schemas.ActuatorHealth, responses=error_responses(401, 403, 404))
async def actuator_health(tail: str, actuator_id: str, db: DbDep, p: ReadDep) -> schemas.ActuatorHealth:
    """Latest health indicators of each estimator, with status (ok / watch / alert)."""

    def _do() -> schemas.ActuatorHealth:
        with db.read() as s:
            act = fleet.get_actuator(s, p.operator_id, tail, actuator_id)
            return schemas.ActuatorHealth.model_validate(queries.latest_health(s, tail, act))

    return await run_in_threadpool(_do)


@router.get(
    f"{ACT}/health/history", response_model=schemas.HealthHistory, responses=error_responses(401, 403, 404)
)
async def actuator_health_history(
    tail: str,
    actuator_id: str,
    db: DbDep,
    p: ReadDep,
    estimator: str | None = None,
    from_s: Annotated[float | None, Query(description="Stream time, seconds")] = None,
    to_s: Annotated[float | None, Query(description="Stream time, seconds")] = None,
    limit: Annotated[int, Query(ge=1, le=100_000)] = 10_000,
) -> schemas.HealthHistory:
    """Health windows whose time span meets [from_s, to_s], oldest first."""

    def _do() -> schemas.HealthHistory:
        with db.read() as s:
            act = fleet.get_actuator(s, p.operator_id, tail, actuator_id)
            items = queries.health_history(s, act, estimator, from_s, to_s, limit)
            return schemas.HealthHistory.model_validate({"items": items})

    return await run_in_threadpool(_do)


@router.get(f"{ACT}/outputs", response_model=schemas.SampleOutputs, responses=error_responses(401, 403, 404))
async def actuator_outputs(
    tail: str,
    actuator_id: str,
    db: DbDep,
    p: ReadDep,
    estimator: str,
    from_s: float | None = None,
    to_s: float | None = None,
    max_samples: Annotated[int, Query(ge=1, le=1_000_000)] = 100_000,
) -> schemas.SampleOutputs:
    """Per-sample estimator outputs (e.g. the FAKF voltage estimate) over a time range."""

    def _do() -> schemas.SampleOutputs:
        with db.read() as s:
            act = fleet.get_actuator(s, p.operator_id, tail, actuator_id)
            return schemas.SampleOutputs.model_validate(
                queries.sample_outputs(s, act, estimator, from_s, to_s, max_samples)
            )

    return await run_in_threadpool(_do)


@router.get(f"{ACT}/events", response_model=schemas.EventList, responses=error_responses(401, 403, 404))
async def actuator_events(
    tail: str,
    actuator_id: str,
    db: DbDep,
    p: ReadDep,
    from_s: float | None = None,
    to_s: float | None = None,
    limit: Annotated[int, Query(ge=1, le=100_000)] = 1000,
) -> schemas.EventList:
    """Estimator events (model identified, identification failed, ...), oldest first."""

    def _do() -> schemas.EventList:
        with db.read() as s:
            act = fleet.get_actuator(s, p.operator_id, tail, actuator_id)
            return schemas.EventList.model_validate({"items": queries.events(s, act, from_s, to_s, limit)})

    return await run_in_threadpool(_do)


@router.get(f"{ACT}/rul", response_model=schemas.ActuatorRul, responses=error_responses(401, 403, 404))
async def actuator_rul(
    tail: str,
    actuator_id: str,
    db: DbDep,
    p: ReadDep,
    estimator: str | None = None,
    from_s: Annotated[float | None, Query(description="Stream time, seconds")] = None,
    to_s: Annotated[float | None, Query(description="Stream time, seconds")] = None,
    limit: Annotated[int, Query(ge=1, le=100_000)] = 1000,
) -> schemas.ActuatorRul:
    """Remaining useful life: the latest prognosis of each estimator, and the prognoses made in
    [from_s, to_s] (oldest first). Times are seconds of stream time; a null RUL means the failure
    threshold is not reached within the prediction horizon."""

    def _do() -> schemas.ActuatorRul:
        with db.read() as s:
            act = fleet.get_actuator(s, p.operator_id, tail, actuator_id)
            return schemas.ActuatorRul.model_validate(
                queries.rul(s, tail, act, estimator, from_s, to_s, limit)
            )

    return await run_in_threadpool(_do)


@router.get(f"{ACT}/faults", response_model=schemas.ActuatorFaults, responses=error_responses(401, 403, 404))
async def actuator_faults(
    tail: str,
    actuator_id: str,
    db: DbDep,
    p: ReadDep,
    limit: Annotated[int, Query(ge=1, le=100_000, description="Most recent fault events")] = 1000,
) -> schemas.ActuatorFaults:
    """Fault isolation: each estimator's current diagnosis (hypothesis probabilities, residual
    status, coherence vector, candidate fault sets, parameter estimates with bounds), the faults
    detected and not yet cleared, and the fault events."""

    def _do() -> schemas.ActuatorFaults:
        with db.read() as s:
            act = fleet.get_actuator(s, p.operator_id, tail, actuator_id)
            return schemas.ActuatorFaults.model_validate(queries.faults(s, tail, act, limit))

    return await run_in_threadpool(_do)


@router.get("/fleet/health", response_model=schemas.FleetHealth, responses=error_responses(401, 403, 422))
async def fleet_health(
    db: DbDep, p: ReadDep, sort: Literal["status", "tail", "updated", "rul"] = "status"
) -> schemas.FleetHealth:
    """Every aircraft of the operator with its actuators, worst status, latest RUL and active
    faults.

    `sort=status` lists the worst first; `tail` alphabetically; `updated` most recent first;
    `rul` the shortest remaining useful life first (by the 5 % quantile of the latest prognosis;
    actuators without one last): the actuators to replace first.
    """

    def _do() -> schemas.FleetHealth:
        with db.read() as s:
            return schemas.FleetHealth.model_validate({"aircraft": queries.fleet_health(s, p.operator_id, sort)})

    return await run_in_threadpool(_do)
