"""Request and response models of alarms."""

from __future__ import annotations

from datetime import datetime
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field

from app.telemetry.validation import Identifier

Severity = Literal["critical", "major", "minor", "warning"]
AlarmStatus = Literal["active", "acknowledged", "cleared"]
Cause = Literal["status", "fault", "rul", "dn"]


class AlarmAction(BaseModel):
    model_config = ConfigDict(extra="forbid")
    comment: Identifier | None = Field(default=None, max_length=2000)
    by: Identifier | None = Field(
        default=None, max_length=100, description="Who acts (recorded with the key's name)"
    )


class AlarmPublic(BaseModel):
    id: int
    tail: str
    actuator_id: str
    cause: Cause
    subject: str = Field(
        description="What the cause is about (the component of a fault); empty otherwise"
    )
    estimator: str | None
    severity: Severity
    status: AlarmStatus
    message: str
    occurrences: int = Field(description="Events that raised or re-triggered it while open")
    raised_event_id: int = Field(description="The logged event that raised it (GET /v1/events)")
    last_event_id: int
    raised_at: datetime
    raised_t_s: float | None = Field(description="Stream time of the raising event, seconds")
    updated_at: datetime
    acknowledged_at: datetime | None
    acknowledged_by: str | None
    acknowledge_comment: str | None
    cleared_at: datetime | None
    cleared_by: str | None = Field(description="`rule` when its cause ended, else who cleared it")
    clear_comment: str | None
    cleared_event_id: int | None
    detail: dict[str, Any] = Field(description="The raising event's type and fields")


class AlarmCounts(BaseModel):
    status: dict[str, int] = Field(description="Alarms per status (every filter but `status`)")
    open: int = Field(description="Active and acknowledged alarms")
    open_by_severity: dict[str, int]


class AlarmList(BaseModel):
    items: list[AlarmPublic]
    next_before: int | None = Field(
        description="Pass as `before` for the next (older) page; null at the end"
    )
    counts: AlarmCounts
