"""SQL of fault events."""

from __future__ import annotations

from sqlalchemy import select
from sqlalchemy.orm import Session

from app.models import EstimatorEventRow

FAULT_EVENT_KINDS = ("fault_detected", "fault_cleared")


def fault_events(session: Session, actuator_pks: list[int]) -> dict[int, list[EstimatorEventRow]]:
    """Fault detections and clearances of each actuator, oldest first."""
    out: dict[int, list[EstimatorEventRow]] = {pk: [] for pk in actuator_pks}
    if not actuator_pks:
        return out
    for r in session.scalars(
        select(EstimatorEventRow)
        .where(EstimatorEventRow.actuator_pk.in_(actuator_pks), EstimatorEventRow.kind.in_(FAULT_EVENT_KINDS))
        .order_by(EstimatorEventRow.t_s, EstimatorEventRow.id)
    ):
        out[r.actuator_pk].append(r)
    return out
