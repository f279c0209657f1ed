"""Response models of the telemetry read-back."""

from __future__ import annotations

from pydantic import BaseModel, Field

from app.pagination import CURSOR_DOC


class DroppedBatch(BaseModel):
    seq: int
    t_first_s: float
    t_last_s: float


class TelemetryPage(BaseModel):
    t_s: list[float] = Field(description="Sample times, seconds, in the order asked for (newest first by default)")
    channels: dict[str, list[float | None]] = Field(description="Channel -> values; null = no sample")
    dropped: list[DroppedBatch] = Field(
        default_factory=list,
        description="Batches met by this page whose samples retention dropped (FLEETHEALTH_LOG_RETENTION_S), "
        "at most 1000",
    )
    next_cursor: str | None = Field(default=None, description=CURSOR_DOC)
