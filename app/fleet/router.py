"""Aircraft, actuators, actuator kinds and the fleet board over HTTP."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter
from sqlalchemy.orm import Session

from app.deps import AdminDep, ReadDep, ReadSessionDep, WriteSessionDep
from app.errors import error_responses
from app.fleet import schemas, service
from app.fleet.service import FleetSort
from app.models import Actuator
from estimators.registry import ACTUATOR_KINDS

router = APIRouter(prefix="/v1", tags=["fleet"])


def _actuator_public(act: Actuator, configs: dict[str, dict[str, Any]]) -> schemas.ActuatorPublic:
    return schemas.ActuatorPublic(
        actuator_id=act.actuator_id,
        kind=act.kind,
        channels=act.channels,
        estimators=configs,
        created_at=act.created_at,
    )


def _with_configs(s: Session, act: Actuator) -> schemas.ActuatorPublic:
    return _actuator_public(act, service.estimator_configs(s, act.id))


@router.post(
    "/aircraft",
    status_code=201,
    response_model=schemas.AircraftPublic,
    responses=error_responses(401, 403, 409, 422),
)
def create_aircraft(body: schemas.AircraftCreate, s: WriteSessionDep, p: AdminDep) -> schemas.AircraftPublic:
    """Register an aircraft by tail number (admin scope)."""
    ac = service.create_aircraft(s, p.operator_id, body.tail, body.description)
    return schemas.AircraftPublic.model_validate(ac)


@router.get("/aircraft", response_model=schemas.AircraftList, responses=error_responses(401, 403))
def list_aircraft(s: ReadSessionDep, p: ReadDep) -> schemas.AircraftList:
    return schemas.AircraftList(
        items=[schemas.AircraftPublic.model_validate(a) for a in service.list_aircraft(s, p.operator_id)]
    )


@router.get("/aircraft/{tail}", response_model=schemas.AircraftPublic, responses=error_responses(401, 403, 404))
def get_aircraft(tail: str, s: ReadSessionDep, p: ReadDep) -> schemas.AircraftPublic:
    return schemas.AircraftPublic.model_validate(service.get_aircraft(s, p.operator_id, tail))


@router.post(
    "/aircraft/{tail}/actuators",
    status_code=201,
    response_model=schemas.ActuatorPublic,
    responses=error_responses(401, 403, 404, 409, 422),
)
def create_actuator(
    tail: str, body: schemas.ActuatorCreate, s: WriteSessionDep, p: AdminDep
) -> schemas.ActuatorPublic:
    """Register an actuator with its kind, channels and estimators (admin scope).

    Omitted channels and estimators take the kind's defaults; each estimator configuration is
    validated and stored with every default filled in (422 names the problem).
    """
    ac = service.get_aircraft(s, p.operator_id, tail)
    act, configs = service.create_actuator(
        s, ac, body.actuator_id, body.kind, body.channels, body.estimator_dicts()
    )
    return _actuator_public(act, configs)


@router.get(
    "/aircraft/{tail}/actuators", response_model=schemas.ActuatorList, responses=error_responses(401, 403, 404)
)
def list_actuators(tail: str, s: ReadSessionDep, p: ReadDep) -> schemas.ActuatorList:
    ac = service.get_aircraft(s, p.operator_id, tail)
    return schemas.ActuatorList(items=[_with_configs(s, a) for a in service.list_actuators(s, ac)])


@router.get(
    "/aircraft/{tail}/actuators/{actuator_id}",
    response_model=schemas.ActuatorPublic,
    responses=error_responses(401, 403, 404),
)
def get_actuator(tail: str, actuator_id: str, s: ReadSessionDep, p: ReadDep) -> schemas.ActuatorPublic:
    return _with_configs(s, service.get_actuator(s, p.operator_id, tail, actuator_id))


@router.get("/kinds", response_model=schemas.KindList, responses=error_responses(401, 403))
def list_kinds(p: ReadDep) -> schemas.KindList:
    """Actuator kinds, their default channels and estimators."""
    return schemas.KindList(
        items=[
            schemas.KindPublic(
                name=k.name,
                description=k.description,
                channels=list(k.channels),
                default_estimators=k.default_estimators,
            )
            for k in ACTUATOR_KINDS.values()
        ]
    )


@router.get(
    "/fleet/health", tags=["health"], response_model=schemas.FleetHealth, responses=error_responses(401, 403, 422)
)
def fleet_health(s: ReadSessionDep, p: ReadDep, sort: FleetSort = "status") -> schemas.FleetHealth:
    """Every aircraft of the operator with its actuators, worst status, latest RUL and active
    faults.

    `sort=status` lists the worst first (failed, alert, unknown, watch, learning, ok); `tail`
    alphabetically; `updated` most recent first; `rul` the shortest remaining useful life first
    (by the 5 % quantile of the latest prognosis; actuators without one last): the actuators to
    replace first. A stream that can no longer be applied shows `failed` with its `failure`.
    """
    return schemas.FleetHealth.model_validate({"aircraft": service.fleet_board(s, p.operator_id, sort)})
