"""Aircraft, actuators, actuator kinds and API keys."""

from __future__ import annotations

from fastapi import APIRouter
from starlette.concurrency import run_in_threadpool

from app import schemas
from app.api.deps import AdminDep, DbDep, ReadDep
from app.errors import error_responses
from app.models import Actuator
from app.security import create_key
from app.services import fleet
from estimators.registry import ACTUATOR_KINDS

router = APIRouter(prefix="/v1", tags=["fleet"])


def _actuator_public(act: Actuator, configs: dict) -> schemas.ActuatorPublic:  # type: ignore[type-arg]
    return schemas.ActuatorPublic(
        actuator_id=act.actuator_id,
        kind=act.kind,
        channels=act.channels,
        estimators=configs,
        created_at=act.created_at,
    )


@router.post(
    "/aircraft",
    status_code=201,
    response_model=schemas.AircraftPublic,
    responses=error_responses(401, 403, 409, 422),
)
async def create_aircraft(body: schemas.AircraftCreate, db: DbDep, p: AdminDep) -> schemas.AircraftPublic:
    """Register an aircraft by tail number (admin scope)."""

    def _do() -> schemas.AircraftPublic:
        with db.write() as s:
            ac = fleet.create_aircraft(s, p.operator_id, body.tail, body.description)
            return schemas.AircraftPublic(tail=ac.tail, description=ac.description, created_at=ac.created_at)

    return await run_in_threadpool(_do)


@router.get("/aircraft", response_model=schemas.AircraftList, responses=error_responses(401, 403))
async def list_aircraft(db: DbDep, p: ReadDep) -> schemas.AircraftList:
    def _do() -> schemas.AircraftList:
        with db.read() as s:
            return schemas.AircraftList(
                items=[
                    schemas.AircraftPublic(tail=a.tail, description=a.description, created_at=a.created_at)
                    for a in fleet.list_aircraft(s, p.operator_id)
                ]
            )

    return await run_in_threadpool(_do)


@router.get("/aircraft/{tail}", response_model=schemas.AircraftPublic, responses=error_responses(401, 403, 404))
async def get_aircraft(tail: str, db: DbDep, p: ReadDep) -> schemas.AircraftPublic:
    def _do() -> schemas.AircraftPublic:
        with db.read() as s:
            a = fleet.get_aircraft(s, p.operator_id, tail)
            return schemas.AircraftPublic(tail=a.tail, description=a.description, created_at=a.created_at)

    return await run_in_threadpool(_do)


@router.post(
    "/aircraft/{tail}/actuators",
    status_code=201,
    response_model=schemas.ActuatorPublic,
    responses=error_responses(401, 403, 404, 409, 422),
)
async def create_actuator(
    tail: str, body: schemas.ActuatorCreate, db: DbDep, p: AdminDep
) -> schemas.ActuatorPublic:
    """Register an actuator with its kind, channels and estimators (admin scope).

    Omitted channels and estimators take the kind's defaults; each estimator configuration is
    validated and stored with every default filled in (422 names the problem).
    """

    def _do() -> schemas.ActuatorPublic:
        with db.write() as s:
            ac = fleet.get_aircraft(s, p.operator_id, tail)
            act, configs = fleet.create_actuator(
                s, ac, body.actuator_id, body.kind, body.channels, body.estimators
            )
            return _actuator_public(act, configs)

    return await run_in_threadpool(_do)


@router.get(
    "/aircraft/{tail}/actuators", response_model=schemas.ActuatorList, responses=error_responses(401, 403, 404)
)
async def list_actuators(tail: str, db: DbDep, p: ReadDep) -> schemas.ActuatorList:
    def _do() -> schemas.ActuatorList:
        with db.read() as s:
            ac = fleet.get_aircraft(s, p.operator_id, tail)
            return schemas.ActuatorList(
                items=[
                    _actuator_public(a, fleet.estimator_configs(s, a.id))
                    for a in fleet.list_actuators(s, ac)
                ]
            )

    return await run_in_threadpool(_do)


@router.get(
    "/aircraft/{tail}/actuators/{actuator_id}",
    response_model=schemas.ActuatorPublic,
    responses=error_responses(401, 403, 404),
)
async def get_actuator(tail: str, actuator_id: str, db: DbDep, p: ReadDep) -> schemas.ActuatorPublic:
    def _do() -> schemas.ActuatorPublic:
        with db.read() as s:
            a = fleet.get_actuator(s, p.operator_id, tail, actuator_id)
            return _actuator_public(a, fleet.estimator_configs(s, a.id))

    return await run_in_threadpool(_do)


@router.get("/kinds", response_model=schemas.KindList, responses=error_responses(401, 403))
async def list_kinds(p: ReadDep) -> schemas.KindList:
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


@router.post("/keys", status_code=201, response_model=schemas.KeyCreated, responses=error_responses(401, 403, 422))
async def create_api_key(body: schemas.KeyCreate, db: DbDep, p: AdminDep) -> schemas.KeyCreated:
    """Create another API key for the caller's operator (admin scope). The key is shown once."""

    def _do() -> schemas.KeyCreated:
        with db.write() as s:
            row, plaintext = create_key(s, p.operator, list(body.scopes), name=body.name)
            return schemas.KeyCreated(
                id=row.id, name=row.name, prefix=row.prefix, scopes=row.scopes.split(","), key=plaintext
            )

    return await run_in_threadpool(_do)
