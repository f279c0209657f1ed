"""Alarm rules carried out inside the caller's transaction: alarms raised, changed and
cleared from the events of an apply (with those events logged), acknowledged and cleared by
people; lists, counts and the fleet board's open counts."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from sqlalchemy.orm import Session

from app.alarms import repository
from app.alarms.repository import AlarmFilter
from app.alarms.rules import SEVERITIES, Decision, OpenAlarm, RuleEvent, decide
from app.auth.service import Principal
from app.errors import DomainError, NotFound
from app.events import log
from app.events.log import NewEvent
from app.models import AlarmRow, utcnow

STATUSES = ("active", "acknowledged", "cleared")
LIFECYCLE_EVENT = {"raise": "alarm_raised", "update": "alarm_updated", "clear": "alarm_cleared"}


class AlarmTransitionRefused(DomainError):
    """The alarm is not in a state that allows this (acknowledging a cleared alarm...)."""

    status_code = 409


def alarm_public(row: AlarmRow, tail: str, actuator_id: str) -> dict[str, Any]:
    return {
        "id": row.id,
        "tail": tail,
        "actuator_id": actuator_id,
        "cause": row.cause,
        "subject": row.subject,
        "estimator": row.estimator,
        "severity": row.severity,
        "status": row.status,
        "message": row.message,
        "occurrences": row.occurrences,
        "raised_event_id": row.raised_event_id,
        "last_event_id": row.last_event_id,
        "raised_at": row.raised_at,
        "raised_t_s": row.raised_t_s,
        "updated_at": row.updated_at,
        "acknowledged_at": row.acknowledged_at,
        "acknowledged_by": row.acknowledged_by,
        "acknowledge_comment": row.acknowledge_comment,
        "cleared_at": row.cleared_at,
        "cleared_by": row.cleared_by,
        "clear_comment": row.clear_comment,
        "cleared_event_id": row.cleared_event_id,
        "detail": row.detail,
    }


def _rule_event(ev: NewEvent) -> RuleEvent:
    return RuleEvent(ev.type, ev.body)


def log_with_alarms(
    session: Session,
    operator_id: int,
    actuator_pk: int,
    tail: str,
    actuator_id: str,
    events: Sequence[NewEvent],
) -> list[dict[str, Any]]:
    """Log the fleet events of one apply and carry out the alarm rules over them; the alarm
    lifecycle events follow them in the log. Returns every event logged, as published.

    Lock order, the same as acknowledging: the actuator's open alarms, then the event counter.
    """
    if not events:
        return []
    open_rows = {(a.cause, a.subject): a for a in repository.open_alarms(session, actuator_pk)}
    decisions = decide(
        {k: OpenAlarm(a.severity, a.estimator) for k, a in open_rows.items()},
        [_rule_event(ev) for ev in events],
    )
    lifecycle = [d for d in decisions if d.action != "touch"]
    first = log.reserve(session, operator_id, len(events) + len(lifecycle))
    alarm_events: list[NewEvent] = []
    next_id = first + len(events)
    for d in decisions:
        cause_id = first + d.event_index
        row = _carry_out(
            session,
            operator_id,
            actuator_pk,
            open_rows,
            d,
            events[d.event_index],
            cause_id,
            next_id,
        )
        if d.action == "touch":
            continue
        trigger = events[d.event_index]
        alarm_events.append(
            NewEvent(
                type=LIFECYCLE_EVENT[d.action],
                tail=tail,
                actuator_id=actuator_id,
                actuator_pk=actuator_pk,
                seq=trigger.seq,
                t_s=trigger.t_s,
                body={"cause_event_id": cause_id, "alarm": alarm_public(row, tail, actuator_id)},
            )
        )
        next_id += 1
    return log.store(session, operator_id, first, [*events, *alarm_events])


def _carry_out(
    session: Session,
    operator_id: int,
    actuator_pk: int,
    open_rows: dict[tuple[str, str], AlarmRow],
    d: Decision,
    trigger: NewEvent,
    cause_id: int,
    lifecycle_id: int,
) -> AlarmRow:
    now = utcnow()
    key = (d.cause, d.subject)
    if d.action == "raise":
        row = repository.add_alarm(
            session,
            AlarmRow(
                operator_id=operator_id,
                actuator_pk=actuator_pk,
                cause=d.cause,
                subject=d.subject,
                estimator=d.estimator,
                severity=d.severity,
                status="active",
                message=d.message[:500],
                raised_event_id=cause_id,
                last_event_id=cause_id,
                occurrences=1,
                detail={"type": trigger.type, **trigger.body},
                raised_at=now,
                raised_t_s=trigger.t_s,
                updated_at=now,
            ),
        )
        open_rows[key] = row
        return row
    row = open_rows[key]
    row.last_event_id = cause_id
    row.updated_at = now
    if d.action == "clear":
        row.status = "cleared"
        row.cleared_at = now
        row.cleared_by = "rule"
        row.clear_comment = d.message[:2000]
        row.cleared_event_id = lifecycle_id
        del open_rows[key]
    else:
        row.occurrences += 1
        if d.action == "update":
            row.severity = d.severity
            row.message = d.message[:500]
    session.flush()
    return row


# ----------------------------------------------------------------------------- by people
def _by(session: Session, principal: Principal, by: str | None) -> str:
    label = repository.key_label(session, principal.key_id)
    return f"{by} (key {label})" if by else f"key {label}"


def _person_event(
    session: Session,
    principal: Principal,
    row: AlarmRow,
    tail: str,
    actuator_id: str,
    kind: str,
    event_id: int,
) -> dict[str, Any]:
    ev = NewEvent(
        type=kind,
        tail=tail,
        actuator_id=actuator_id,
        actuator_pk=row.actuator_pk,
        body={"alarm": alarm_public(row, tail, actuator_id)},
    )
    return log.store(session, principal.operator_id, event_id, [ev])[0]


def _locked(session: Session, principal: Principal, alarm_id: int) -> tuple[AlarmRow, str, str]:
    found = repository.alarm_of(session, principal.operator_id, alarm_id, lock=True)
    if found is None:
        raise NotFound(f"alarm {alarm_id} not found")
    return found


def acknowledge(
    session: Session, principal: Principal, alarm_id: int, comment: str | None, by: str | None
) -> dict[str, Any]:
    """active -> acknowledged, with who, when and a comment; logs ``alarm_acknowledged``."""
    row, tail, actuator_id = _locked(session, principal, alarm_id)
    if row.status != "active":
        raise AlarmTransitionRefused(
            f"alarm {alarm_id} is {row.status}; only an active alarm can be acknowledged"
        )
    event_id = log.reserve(session, principal.operator_id, 1)
    now = utcnow()
    row.status = "acknowledged"
    row.acknowledged_at = now
    row.acknowledged_by = _by(session, principal, by)[:200]
    row.acknowledge_comment = comment
    row.last_event_id = event_id
    row.updated_at = now
    session.flush()
    _person_event(session, principal, row, tail, actuator_id, "alarm_acknowledged", event_id)
    return alarm_public(row, tail, actuator_id)


def clear(
    session: Session, principal: Principal, alarm_id: int, comment: str | None, by: str | None
) -> dict[str, Any]:
    """active or acknowledged -> cleared by a person; logs ``alarm_cleared``. The next event of
    the same cause raises a new alarm."""
    row, tail, actuator_id = _locked(session, principal, alarm_id)
    if row.status == "cleared":
        raise AlarmTransitionRefused(f"alarm {alarm_id} is cleared already")
    event_id = log.reserve(session, principal.operator_id, 1)
    now = utcnow()
    row.status = "cleared"
    row.cleared_at = now
    row.cleared_by = _by(session, principal, by)[:200]
    row.clear_comment = comment
    row.cleared_event_id = event_id
    row.last_event_id = event_id
    row.updated_at = now
    session.flush()
    _person_event(session, principal, row, tail, actuator_id, "alarm_cleared", event_id)
    return alarm_public(row, tail, actuator_id)


# ----------------------------------------------------------------------------- reading
def get_alarm(session: Session, operator_id: int, alarm_id: int) -> dict[str, Any]:
    found = repository.alarm_of(session, operator_id, alarm_id)
    if found is None:
        raise NotFound(f"alarm {alarm_id} not found")
    return alarm_public(*found)


def list_alarms(
    session: Session, operator_id: int, f: AlarmFilter, before: int | None, limit: int
) -> dict[str, Any]:
    """Alarms newest first with a cursor, and counts by status and by severity (of the open
    ones) over every filter but the status."""
    rows = repository.list_alarms(session, operator_id, f, before, limit + 1)
    more = len(rows) > limit
    rows = rows[:limit]
    by_status = dict.fromkeys(STATUSES, 0)
    open_by_severity = dict.fromkeys(SEVERITIES, 0)
    for status, severity, n in repository.counts(session, operator_id, f):
        by_status[status] = by_status.get(status, 0) + n
        if status != "cleared":
            open_by_severity[severity] = open_by_severity.get(severity, 0) + n
    return {
        "items": [alarm_public(*r) for r in rows],
        "next_before": rows[-1][0].id if more else None,
        "counts": {
            "status": by_status,
            "open": by_status["active"] + by_status["acknowledged"],
            "open_by_severity": open_by_severity,
        },
    }


def open_counts(session: Session, actuator_pks: Sequence[int]) -> dict[int, int]:
    """Open (active or acknowledged) alarms per actuator, for the fleet board."""
    return repository.open_counts(session, actuator_pks)
