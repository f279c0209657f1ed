"""Appending to the fleet event log inside the caller's transaction.

Every fleet event gets the next id of its operator (ids are given in commit order, see
``repository.reserve_ids``), is stored, and is put in the webhook outbox of each matching
subscription, all in the transaction that produced it: an event is either committed with its
cause and its deliveries, or not at all.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from datetime import UTC, datetime
from typing import Any

import orjson
from sqlalchemy.orm import Session

from app.events import repository
from app.models import FleetEventRow, utcnow
from app.webhooks import service as webhooks

# Alarm lifecycle events, logged beside the estimators' fleet events.
ALARM_EVENT_TYPES = frozenset(
    {"alarm_raised", "alarm_updated", "alarm_acknowledged", "alarm_cleared"}
)
# People's actions on an actuator's life: a maintenance action recorded, a new config version.
ASSET_EVENT_TYPES = frozenset({"maintenance_recorded", "config_changed"})


@dataclass(frozen=True)
class NewEvent:
    """An event about to be logged. ``body`` holds the type's own fields."""

    type: str
    tail: str
    actuator_id: str
    actuator_pk: int | None
    seq: int | None = None
    t_s: float | None = None
    body: dict[str, Any] = field(default_factory=dict)


def public(
    event_id: int,
    event: NewEvent | FleetEventRow,
    created_at: datetime,
) -> dict[str, Any]:
    """The event as the API, the WebSocket and webhooks show it."""
    return {
        "id": event_id,
        "type": event.type,
        "time": created_at.astimezone(UTC).isoformat().replace("+00:00", "Z"),
        "tail": event.tail,
        "actuator_id": event.actuator_id,
        "seq": event.seq,
        "t_s": event.t_s,
        **event.body,
    }


def row_public(row: FleetEventRow) -> dict[str, Any]:
    return public(row.event_id, row, row.created_at)


def reserve(session: Session, operator_id: int, n: int) -> int:
    """The first of ``n`` consecutive event ids taken for this transaction."""
    return repository.reserve_ids(session, operator_id, n)


def store(
    session: Session, operator_id: int, first_id: int, events: Sequence[NewEvent]
) -> list[dict[str, Any]]:
    """Store events under the ids ``first_id``, ``first_id + 1``, ... (reserved by
    :func:`reserve`) and queue their webhook deliveries; returns them as published."""
    now = utcnow()
    # JSON-safe bodies (times as RFC 3339 strings), stored and published alike.
    events = [
        replace(ev, body=orjson.loads(orjson.dumps(ev.body, option=orjson.OPT_UTC_Z)))
        for ev in events
    ]
    rows = [
        {
            "operator_id": operator_id,
            "event_id": first_id + i,
            "type": ev.type,
            "tail": ev.tail,
            "actuator_id": ev.actuator_id,
            "actuator_pk": ev.actuator_pk,
            "seq": ev.seq,
            "t_s": ev.t_s,
            "body": ev.body,
            "created_at": now,
        }
        for i, ev in enumerate(events)
    ]
    repository.insert_events(session, rows)
    published = [public(first_id + i, ev, now) for i, ev in enumerate(events)]
    webhooks.enqueue_events(session, operator_id, published)
    return published


def append(session: Session, operator_id: int, events: Sequence[NewEvent]) -> list[dict[str, Any]]:
    """Log events in the caller's transaction; returns them as published."""
    if not events:
        return []
    return store(session, operator_id, reserve(session, operator_id, len(events)), events)
