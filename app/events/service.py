"""The fleet event log's rules: what an apply logs (with the alarms it raises or clears, in
the apply's transaction), and reading the log after a cursor."""

from __future__ import annotations

from collections.abc import Collection
from typing import TYPE_CHECKING, Any

from sqlalchemy.orm import Session

from app.alarms import service as alarms
from app.db import Database
from app.events import repository
from app.events.log import ALARM_EVENT_TYPES, ASSET_EVENT_TYPES, NewEvent, row_public
from app.websocket.hub import DEFAULT_FLEET_TYPES, StreamMeta, fleet_events

if TYPE_CHECKING:
    from app.processing.service import ApplyResult

# Every type the log holds (``applied``, one per batch, is pushed live only).
LOGGED_TYPES = frozenset({*DEFAULT_FLEET_TYPES, *ALARM_EVENT_TYPES, *ASSET_EVENT_TYPES})
ROUTING_KEYS = frozenset({"_operator_id", "type", "tail", "actuator_id", "seq", "t_s"})


def record_apply(session: Session, result: ApplyResult) -> list[dict[str, Any]]:
    """Log the fleet events of one apply, and the alarms they raise or clear, inside the
    apply's transaction (called by ``processing.service.apply_pending`` before it returns)."""
    # Most applies produce no fleet event: find out before reading the stream's owner.
    if not any(ev["type"] in LOGGED_TYPES for ev in fleet_events(StreamMeta(0, "", ""), result)):
        return []
    operator_id, tail, actuator_id = repository.stream_owner(session, result.actuator_pk)
    events = [
        NewEvent(
            type=ev["type"],
            tail=tail,
            actuator_id=actuator_id,
            actuator_pk=result.actuator_pk,
            seq=ev.get("seq"),
            t_s=ev.get("t_s"),
            body={k: v for k, v in ev.items() if k not in ROUTING_KEYS},
        )
        for ev in fleet_events(StreamMeta(operator_id, tail, actuator_id), result)
        if ev["type"] in LOGGED_TYPES
    ]
    return alarms.log_with_alarms(
        session, operator_id, result.actuator_pk, tail, actuator_id, events
    )


def list_events(
    session: Session,
    operator_id: int,
    after: int,
    limit: int,
    *,
    types: Collection[str] | None = None,
    tails: Collection[str] | None = None,
    actuator_id: str | None = None,
) -> dict[str, Any]:
    """Events after the cursor ``after``, oldest first; ``next_after`` is the cursor of the
    next page (the last id returned, or ``after`` when none)."""
    rows = repository.events_after(
        session, operator_id, after, limit + 1, types=types, tails=tails, actuator_id=actuator_id
    )
    more = len(rows) > limit
    rows = rows[:limit]
    return {
        "items": [row_public(r) for r in rows],
        "next_after": rows[-1].event_id if rows else after,
        "has_more": more,
        "last_event_id": repository.last_event_id(session, operator_id),
    }


def read_after(
    db: Database,
    operator_id: int,
    after: int,
    limit: int,
    types: Collection[str],
    tails: Collection[str] | None,
) -> list[dict[str, Any]]:
    """For a subscriber following the log: the next events after its cursor."""
    with db.read() as s:
        return [
            row_public(r)
            for r in repository.events_after(s, operator_id, after, limit, types=types, tails=tails)
        ]


def head(db: Database, operator_id: int) -> int:
    """The operator's newest event id, where a new subscriber starts."""
    with db.read() as s:
        return repository.last_event_id(s, operator_id)
