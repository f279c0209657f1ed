"""Response models of the fleet event log."""

from __future__ import annotations

from datetime import datetime

from pydantic import BaseModel, ConfigDict, Field


class FleetEvent(BaseModel):
    """One logged fleet event. Besides these fields each type carries its own: ``from``,
    ``to``, ``reasons`` (``status_changed``); ``estimator``, ``detail`` (estimator events);
    ``alarm`` and ``cause_event_id`` (alarm events); ``maintenance_id``, ``action``,
    ``performed_by``, ``performed_at``, ``comment``, ``baseline``, ``from_seq``,
    ``status_before`` (``maintenance_recorded``); ``estimator``, ``version``, ``from_seq``,
    ``state``, ``comment`` (``config_changed``)."""

    model_config = ConfigDict(extra="allow")
    id: int = Field(description="Increasing per operator: the cursor to resume after")
    type: str
    time: datetime = Field(description="When the event was logged (UTC)")
    tail: str
    actuator_id: str
    seq: int | None = Field(
        description="The telemetry batch that produced it (None: a person's action)"
    )
    t_s: float | None = Field(description="Stream time of the event, seconds")


class EventPage(BaseModel):
    items: list[FleetEvent]
    next_after: int = Field(description="Pass as `after` for the next page")
    has_more: bool
    last_event_id: int = Field(description="The operator's newest event id")
