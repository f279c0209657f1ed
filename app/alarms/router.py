"""Alarms over HTTP: the fleet-wide list with filters and counts, one alarm, acknowledge and
clear."""

from __future__ import annotations

from typing import Annotated, Literal

from fastapi import APIRouter, BackgroundTasks, Path, Query, Request

from app.alarms import schemas, service
from app.alarms.repository import AlarmFilter
from app.deps import ReadDep, ReadSessionDep, WriteSessionDep
from app.errors import error_responses
from app.events.router import wake_fleet_subscribers
from app.telemetry.validation import Identifier

router = APIRouter(prefix="/v1", tags=["alarms"])


AlarmId = Annotated[int, Path(ge=1, le=2**53)]


@router.get("/alarms", response_model=schemas.AlarmList, responses=error_responses(401, 403, 422))
def list_alarms(
    s: ReadSessionDep,
    p: ReadDep,
    status: Literal["open", "active", "acknowledged", "cleared"] | None = None,
    severity: schemas.Severity | None = None,
    tail: Identifier | None = None,
    actuator_id: Identifier | None = None,
    cause: schemas.Cause | None = None,
    before: Annotated[
        int | None, Query(ge=1, le=2**53, description="Cursor: alarms older than this id")
    ] = None,
    limit: Annotated[int, Query(ge=1, le=1000)] = 100,
) -> schemas.AlarmList:
    """The operator's alarms, newest first, with counts per status and per severity of the
    open ones. `status=open` is active and acknowledged together."""
    f = AlarmFilter(
        status=status, severity=severity, tail=tail, actuator_id=actuator_id, cause=cause
    )
    return schemas.AlarmList.model_validate(service.list_alarms(s, p.operator_id, f, before, limit))


@router.get(
    "/alarms/{alarm_id}",
    response_model=schemas.AlarmPublic,
    responses=error_responses(401, 403, 404, 422),
)
def get_alarm(alarm_id: AlarmId, s: ReadSessionDep, p: ReadDep) -> schemas.AlarmPublic:
    return schemas.AlarmPublic.model_validate(service.get_alarm(s, p.operator_id, alarm_id))


@router.post(
    "/alarms/{alarm_id}/acknowledge",
    response_model=schemas.AlarmPublic,
    responses=error_responses(401, 403, 404, 409, 422),
)
def acknowledge_alarm(
    alarm_id: AlarmId,
    request: Request,
    tasks: BackgroundTasks,
    s: WriteSessionDep,
    p: ReadDep,
    body: schemas.AlarmAction | None = None,
) -> schemas.AlarmPublic:
    """active -> acknowledged (409 otherwise), recording who, when and the comment."""
    body = body or schemas.AlarmAction()
    alarm = service.acknowledge(s, p, alarm_id, body.comment, body.by)
    tasks.add_task(wake_fleet_subscribers, request, p.operator_id)
    return schemas.AlarmPublic.model_validate(alarm)


@router.post(
    "/alarms/{alarm_id}/clear",
    response_model=schemas.AlarmPublic,
    responses=error_responses(401, 403, 404, 409, 422),
)
def clear_alarm(
    alarm_id: AlarmId,
    request: Request,
    tasks: BackgroundTasks,
    s: WriteSessionDep,
    p: ReadDep,
    body: schemas.AlarmAction | None = None,
) -> schemas.AlarmPublic:
    """active or acknowledged -> cleared (409 when cleared already), recording who, when and
    the comment. An alarm also clears itself when its cause ends (`cleared_by: rule`)."""
    body = body or schemas.AlarmAction()
    alarm = service.clear(s, p, alarm_id, body.comment, body.by)
    tasks.add_task(wake_fleet_subscribers, request, p.operator_id)
    return schemas.AlarmPublic.model_validate(alarm)
