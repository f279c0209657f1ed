"""Aircraft, actuators, actuator kinds, their lifecycle (changes, deletion, maintenance) and
the fleet board over HTTP."""

from __future__ import annotations

from datetime import timedelta
from typing import Annotated, Any

from fastapi import APIRouter, BackgroundTasks, Query, Request
from sqlalchemy.orm import Session

from app.deps import AdminDep, ReadDep, ReadSessionDep, SettingsDep, WriteSessionDep
from app.errors import error_responses
from app.events.router import wake_fleet_subscribers
from app.fleet import schemas, service
from app.fleet.service import FleetSort
from app.models import Actuator
from app.pagination import CursorQuery, OrderQuery, decode_cursor, encode_cursor, page
from estimators.registry import ACTUATOR_KINDS

router = APIRouter(prefix="/v1", tags=["fleet"])
ACT = "/aircraft/{tail}/actuators/{actuator_id}"
Limit = Annotated[int, Query(ge=1, le=1000, description="Items per page")]


def _actuator_public(act: Actuator, s: Session) -> schemas.ActuatorPublic:
    ests = service.estimator_rows(s, act.id)
    return schemas.ActuatorPublic(
        actuator_id=act.actuator_id,
        kind=act.kind,
        channels=act.channels,
        estimators={er.estimator: er.config for er in ests},
        config_versions={er.estimator: er.config_version for er in ests},
        baseline=max((er.baseline for er in ests), default=1),
        created_at=act.created_at,
    )


def _id_cursor(scope: str, order: Any, items: list[Any], more: bool) -> str | None:
    return encode_cursor(scope, order, [items[-1].id]) if more else None


def _after_id(cursor: str | None, scope: str, order: Any) -> int | None:
    key = decode_cursor(cursor, scope, order, 1)
    return None if key is None else int(key[0])


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


@router.get("/aircraft", response_model=schemas.AircraftList, responses=error_responses(400, 401, 403, 422))
def list_aircraft(
    s: ReadSessionDep, p: ReadDep, limit: Limit = 100, cursor: CursorQuery = None, order: OrderQuery = "desc"
) -> schemas.AircraftList:
    """The operator's aircraft, newest registration first (`order=asc`: oldest first), a page at
    a time (`next_cursor`)."""
    rows, more = page(service.list_aircraft(s, p.operator_id, _after_id(cursor, "aircraft", order), order, limit + 1), limit)
    return schemas.AircraftList(
        items=[schemas.AircraftPublic.model_validate(a) for a in rows],
        next_cursor=_id_cursor("aircraft", order, rows, more),
    )


@router.get(
    "/aircraft/{tail}", response_model=schemas.AircraftPublic, responses=error_responses(401, 403, 404, 410)
)
def get_aircraft(tail: str, s: ReadSessionDep, p: ReadDep) -> schemas.AircraftPublic:
    return schemas.AircraftPublic.model_validate(service.get_aircraft(s, p.operator_id, tail))


@router.patch(
    "/aircraft/{tail}", response_model=schemas.AircraftPublic, responses=error_responses(401, 403, 404, 410, 422)
)
def update_aircraft(
    tail: str, body: schemas.AircraftUpdate, s: WriteSessionDep, p: AdminDep
) -> schemas.AircraftPublic:
    """Change an aircraft's description (admin scope; the tail is its identity)."""
    ac = service.get_aircraft(s, p.operator_id, tail)
    return schemas.AircraftPublic.model_validate(
        service.update_aircraft(s, ac, body.model_dump(exclude_unset=True))
    )


@router.delete("/aircraft/{tail}", response_model=schemas.Deleted, responses=error_responses(401, 403, 404, 410))
def delete_aircraft(tail: str, s: WriteSessionDep, p: AdminDep, settings: SettingsDep) -> schemas.Deleted:
    """Delete an aircraft and its actuators (admin scope): they vanish from every read and
    ingest answers 410; their data is kept for `FLEETHEALTH_DELETED_RETENTION_S`, then purged."""
    at = service.delete_aircraft(s, service.get_aircraft(s, p.operator_id, tail))
    return schemas.Deleted(deleted_at=at, purge_after=at + timedelta(seconds=settings.deleted_retention_s))


@router.post(
    "/aircraft/{tail}/actuators",
    status_code=201,
    response_model=schemas.ActuatorPublic,
    responses=error_responses(401, 403, 404, 409, 410, 422),
)
def create_actuator(
    tail: str, body: schemas.ActuatorCreate, s: WriteSessionDep, p: AdminDep
) -> schemas.ActuatorPublic:
    """Register an actuator with its kind, channels and estimators (admin scope).

    Omitted channels and estimators take the kind's defaults; each estimator configuration is
    validated and stored with every default filled in (422 names the problem).
    """
    ac = service.get_aircraft(s, p.operator_id, tail)
    act, _ = service.create_actuator(s, ac, body.actuator_id, body.kind, body.channels, body.estimator_dicts())
    return _actuator_public(act, s)


@router.get(
    "/aircraft/{tail}/actuators",
    response_model=schemas.ActuatorList,
    responses=error_responses(400, 401, 403, 404, 410, 422),
)
def list_actuators(
    tail: str,
    s: ReadSessionDep,
    p: ReadDep,
    limit: Limit = 100,
    cursor: CursorQuery = None,
    order: OrderQuery = "desc",
) -> schemas.ActuatorList:
    """The aircraft's actuators, newest registration first, a page at a time."""
    ac = service.get_aircraft(s, p.operator_id, tail)
    rows, more = page(service.list_actuators(s, ac, _after_id(cursor, "actuators", order), order, limit + 1), limit)
    return schemas.ActuatorList(
        items=[_actuator_public(a, s) for a in rows], next_cursor=_id_cursor("actuators", order, rows, more)
    )


@router.get(ACT, response_model=schemas.ActuatorPublic, responses=error_responses(401, 403, 404, 410))
def get_actuator(tail: str, actuator_id: str, s: ReadSessionDep, p: ReadDep) -> schemas.ActuatorPublic:
    return _actuator_public(service.get_actuator(s, p.operator_id, tail, actuator_id), s)


@router.patch(ACT, response_model=schemas.ActuatorUpdated, responses=error_responses(401, 403, 404, 410, 422))
def update_actuator(
    tail: str,
    actuator_id: str,
    body: schemas.ActuatorUpdate,
    request: Request,
    tasks: BackgroundTasks,
    s: WriteSessionDep,
    p: AdminDep,
) -> schemas.ActuatorUpdated:
    """Change estimator settings, thresholds included (admin scope).

    The settings given are merged onto each estimator's current configuration and validated by
    its kind's config model (422 names the problem). Each changed estimator gets a new config
    version, in force from the next batch the processor applies (`from_seq`); outputs say which
    version produced them. The estimator carries its state over, unless `reset_state`. Each
    version is logged as a `config_changed` fleet event (and a reset that changes the status as
    `status_changed`).
    """
    act = service.get_actuator(s, p.operator_id, tail, actuator_id)
    versions = service.update_estimators(
        s, act, body.estimators, reset_state=body.reset_state, comment=body.comment, key_id=p.key_id
    )
    tasks.add_task(wake_fleet_subscribers, request, p.operator_id)
    return schemas.ActuatorUpdated(
        actuator=_actuator_public(act, s),
        versions=[schemas.ConfigVersionPublic.model_validate(v) for v in versions],
    )


@router.delete(ACT, response_model=schemas.Deleted, responses=error_responses(401, 403, 404, 410))
def delete_actuator(
    tail: str, actuator_id: str, s: WriteSessionDep, p: AdminDep, settings: SettingsDep
) -> schemas.Deleted:
    """Delete an actuator (admin scope): gone from every read, its ingest answers 410; its data
    is kept for `FLEETHEALTH_DELETED_RETENTION_S`, then purged."""
    at = service.delete_actuator(s, service.get_actuator(s, p.operator_id, tail, actuator_id))
    return schemas.Deleted(deleted_at=at, purge_after=at + timedelta(seconds=settings.deleted_retention_s))


@router.get(
    f"{ACT}/configs", response_model=schemas.ConfigVersionList, responses=error_responses(400, 401, 403, 404, 410, 422)
)
def list_config_versions(
    tail: str,
    actuator_id: str,
    s: ReadSessionDep,
    p: ReadDep,
    estimator: str | None = None,
    limit: Limit = 100,
    cursor: CursorQuery = None,
    order: OrderQuery = "desc",
) -> schemas.ConfigVersionList:
    """Every configuration the actuator's estimators have had, newest first, each with the
    first batch it applied to."""
    act = service.get_actuator(s, p.operator_id, tail, actuator_id)
    rows, more = page(
        service.config_versions(s, act, estimator, _after_id(cursor, "configs", order), order, limit + 1), limit
    )
    return schemas.ConfigVersionList(
        items=[schemas.ConfigVersionPublic.model_validate(v) for v in rows],
        next_cursor=_id_cursor("configs", order, rows, more),
    )


@router.post(
    f"{ACT}/maintenance",
    status_code=201,
    response_model=schemas.MaintenancePublic,
    responses=error_responses(401, 403, 404, 409, 410, 422),
)
def record_maintenance(
    tail: str,
    actuator_id: str,
    body: schemas.MaintenanceCreate,
    request: Request,
    tasks: BackgroundTasks,
    s: WriteSessionDep,
    p: AdminDep,
) -> schemas.MaintenancePublic:
    """Record an inspection, repair or replacement (admin scope).

    A `repair` or `replacement` starts a new baseline with the next batch logged (`from_seq`):
    the estimators restart from their initial state, so RUL starts again and a `failed` status
    of the old part is cleared; outputs before and after carry their baseline number. Batches
    of the old part logged but not yet applied are applied to the old baseline first (a second
    repair or replacement meanwhile answers 409 `MaintenancePending`). An `inspection` changes
    nothing but the record. Every action is logged as a `maintenance_recorded` fleet event (and a
    restart that changes the status at once as `status_changed`).
    """
    row = service.record_maintenance(
        s,
        tail,
        actuator_id,
        p.operator_id,
        action=body.action,
        performed_by=body.performed_by,
        performed_at=body.performed_at,
        comment=body.comment,
        key_id=p.key_id,
    )
    tasks.add_task(wake_fleet_subscribers, request, p.operator_id)
    return schemas.MaintenancePublic.model_validate(row)


@router.get(
    f"{ACT}/maintenance",
    response_model=schemas.MaintenanceList,
    responses=error_responses(400, 401, 403, 404, 410, 422),
)
def list_maintenance(
    tail: str,
    actuator_id: str,
    s: ReadSessionDep,
    p: ReadDep,
    limit: Limit = 100,
    cursor: CursorQuery = None,
    order: OrderQuery = "desc",
) -> schemas.MaintenanceList:
    """The actuator's maintenance actions, most recently recorded first."""
    act = service.get_actuator(s, p.operator_id, tail, actuator_id)
    rows, more = page(
        service.maintenance_actions(s, act, _after_id(cursor, "maintenance", order), order, limit + 1), limit
    )
    return schemas.MaintenanceList(
        items=[schemas.MaintenancePublic.model_validate(m) for m in rows],
        next_cursor=_id_cursor("maintenance", order, rows, more),
    )


@router.get("/kinds", response_model=schemas.KindList, responses=error_responses(401, 403))
def list_kinds(p: ReadDep) -> schemas.KindList:
    """Actuator kinds, their default channels and estimators (a short fixed list, not paged)."""
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
    "/fleet/health",
    tags=["health"],
    response_model=schemas.FleetHealth,
    responses=error_responses(400, 401, 403, 422),
)
def fleet_health(
    s: ReadSessionDep,
    p: ReadDep,
    sort: FleetSort = "status",
    limit: Annotated[int, Query(ge=1, le=1000, description="Aircraft per page")] = 100,
    cursor: CursorQuery = None,
) -> schemas.FleetHealth:
    """Every aircraft of the operator with its actuators, worst status, latest RUL and active
    faults, a page of aircraft at a time (`next_cursor`).

    `sort=status` lists the worst first (failed, alert, unknown, watch, learning, ok); `tail`
    alphabetically; `updated` most recent first; `rul` the shortest remaining useful life first
    (by the 5 % quantile of the latest prognosis; actuators without one last): the actuators to
    replace first. The sort is the board's order (no `order` parameter); a cursor continues
    after the last aircraft's place in it. A stream that can no longer be applied shows
    `failed` with its `failure`.
    """
    scope = f"board-{sort}"
    after = decode_cursor(cursor, scope, "asc", {"status": 2, "tail": 1, "updated": 3, "rul": 3}[sort])
    board, last = service.fleet_board(s, p.operator_id, sort, after, limit)
    return schemas.FleetHealth.model_validate(
        {"aircraft": board, "next_cursor": encode_cursor(scope, "asc", last) if last is not None else None}
    )
