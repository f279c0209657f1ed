"""Which faults are open, and each estimator's diagnosis."""

from __future__ import annotations

from typing import Any

from sqlalchemy.orm import Session

from app.faults import repository
from app.health import repository as health_repository
from app.models import Actuator, EstimatorEventRow
from app.processing.messages import event_public


def open_faults(rows: list[EstimatorEventRow]) -> list[EstimatorEventRow]:
    """Detections with no later clearance of the same component by the same estimator.

    A detection marked ``"update": true`` revises the estimator's open detections (e.g. more
    residuals joined) and replaces them; a clearance naming no open component clears all of
    that estimator's, unless it hands a group's episode to one of its halves
    (``"isolated_as"``).
    """
    open_: dict[tuple[str, str], EstimatorEventRow] = {}
    for r in rows:
        key = (r.estimator, str(r.detail.get("component")))
        if r.kind == "fault_detected":
            if r.detail.get("update"):
                for k in [k for k in open_ if k[0] == r.estimator]:
                    del open_[k]
            open_[key] = r
        elif key in open_:
            del open_[key]
        elif r.detail.get("isolated_as"):
            pass  # a group's episode handed to its half, whose own detection stays open
        else:
            for k in [k for k in open_ if k[0] == r.estimator]:
                del open_[k]
    return sorted(open_.values(), key=lambda r: (r.t_s, r.id))


def open_fault_components(session: Session, actuator_pks: list[int]) -> dict[int, list[str]]:
    """Per actuator, the components with a detected and not yet cleared fault."""
    return {
        pk: sorted({str(r.detail.get("component")) for r in open_faults(rows)})
        for pk, rows in repository.fault_events(session, actuator_pks).items()
    }


def faults(session: Session, tail: str, act: Actuator, limit: int) -> dict[str, Any]:
    stream = health_repository.stream(session, act.id)
    rows = repository.fault_events(session, [act.id])[act.id]
    estimators = {
        er.estimator: {
            "status": er.status,
            "reasons": er.reasons,
            "t_s": er.diagnosis_t_s,
            "diagnosis": er.diagnosis,
        }
        for er in health_repository.estimators(session, act.id)
    }
    return {
        "tail": tail,
        "actuator_id": act.actuator_id,
        "status": stream.status,
        "active_faults": [event_public(r) for r in open_faults(rows)],
        "estimators": estimators,
        "events": [event_public(r) for r in rows[-limit:]],
    }
