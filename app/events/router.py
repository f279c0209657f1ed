"""The fleet event log over HTTP."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Query, Request

from app.deps import ReadDep, ReadSessionDep
from app.errors import InvalidConfig, error_responses
from app.events import schemas, service
from app.telemetry.validation import Identifier

router = APIRouter(prefix="/v1", tags=["events"])


def wake_fleet_subscribers(request: Request, operator_id: int) -> None:
    """After a request's commit logged events (a background task): this process's fleet
    subscribers read them at once (those of other processes find them at their next poll)."""
    request.app.state.processor.hub.publish_fleet([{"_operator_id": operator_id, "type": "logged"}])


def _split(values: list[str] | None) -> list[str] | None:
    items = [x for v in values or [] for x in v.split(",") if x]
    return items or None


@router.get("/events", response_model=schemas.EventPage, responses=error_responses(401, 403, 422))
def list_events(
    s: ReadSessionDep,
    p: ReadDep,
    after: Annotated[int, Query(ge=0, le=2**53, description="Cursor: events with a larger id")] = 0,
    limit: Annotated[int, Query(ge=1, le=1000)] = 100,
    type: Annotated[
        list[Identifier] | None, Query(description="Event types (repeat or comma-separate)")
    ] = None,
    tail: Annotated[
        list[Identifier] | None, Query(description="Tails (repeat or comma-separate)")
    ] = None,
    actuator_id: Identifier | None = None,
) -> schemas.EventPage:
    """The operator's logged fleet events after the cursor `after`, oldest first.

    Follow the log by passing `next_after` back as `after`; ids increase per operator in
    commit order, so a reader that resumes after the last id it saw misses nothing.
    """
    types = _split(type)
    if types is not None:
        bad = sorted(set(types) - service.LOGGED_TYPES)
        if bad:
            raise InvalidConfig(f"unknown event types {bad}; known: {sorted(service.LOGGED_TYPES)}")
    page = service.list_events(
        s, p.operator_id, after, limit, types=types, tails=_split(tail), actuator_id=actuator_id
    )
    return schemas.EventPage.model_validate(page)
