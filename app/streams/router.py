"""Stream rewinds over HTTP (admin scope to rewind, read scope to see the record)."""

from __future__ import annotations

from fastapi import APIRouter, BackgroundTasks

from app.deps import AdminDep, ProcessorDep, ReadDep, ReadSessionDep, WriteSessionDep
from app.errors import error_responses
from app.fleet import service as fleet
from app.models import StreamRewind
from app.streams import schemas, service

router = APIRouter(prefix="/v1", tags=["telemetry"])


def _public(row: StreamRewind) -> schemas.RewindPublic:
    return schemas.RewindPublic.model_validate(row, from_attributes=True)


@router.post(
    "/aircraft/{tail}/actuators/{actuator_id}/rewind",
    response_model=schemas.RewindPublic,
    responses=error_responses(401, 403, 404, 409, 422),
)
def rewind_stream(
    tail: str, actuator_id: str, body: schemas.RewindCreate, s: WriteSessionDep, p: AdminDep,
    processor: ProcessorDep, after: BackgroundTasks,
) -> schemas.RewindPublic:
    """Discard every batch after `to_seq` from the actuator's log (admin scope), recorded with
    who, when, why and which batches. When the estimators had applied a discarded batch they
    restart and re-apply batches 1..`to_seq`. The way out for a stream blocked by a bad batch
    (every later batch `StaleBatch`). Stop the stream's senders first."""
    act = fleet.get_actuator(s, p.operator_id, tail, actuator_id, lock=True)
    row = service.rewind(s, act, body.to_seq, body.reason, actor=f"api key {p.key_id}", key_id=p.key_id)
    # After the commit (background tasks run once the response is sent): this process's
    # memory of how far the stream was applied is stale now.
    after.add_task(processor.forget, act.id)
    return _public(row)


@router.get(
    "/aircraft/{tail}/actuators/{actuator_id}/rewinds",
    response_model=schemas.RewindList,
    responses=error_responses(401, 403, 404),
)
def list_rewinds(tail: str, actuator_id: str, s: ReadSessionDep, p: ReadDep) -> schemas.RewindList:
    """Every rewind of the actuator's stream, oldest first."""
    act = fleet.get_actuator(s, p.operator_id, tail, actuator_id)
    return schemas.RewindList(items=[_public(r) for r in service.rewinds(s, act)])
