"""Request and response models of stream rewinds."""

from __future__ import annotations

from datetime import datetime

from pydantic import BaseModel, ConfigDict, Field

from app.telemetry.validation import Identifier


class RewindCreate(BaseModel):
    model_config = ConfigDict(extra="forbid")
    to_seq: int = Field(ge=0, le=2**53, description="Keep batches 1..to_seq; discard every later one")
    reason: Identifier = Field(min_length=1, max_length=500, description="Why (kept in the record)")


class DiscardedBatch(BaseModel):
    seq: int
    batch_id: str
    n_samples: int
    t_first_s: float
    t_last_s: float
    received_at: str
    applied: bool = Field(description="The estimators had applied it (so they restarted)")


class RewindPublic(BaseModel):
    id: int
    at: datetime
    actor: str
    reason: str
    to_seq: int
    from_logged_seq: int
    from_applied_seq: int
    estimators_reset: bool = Field(
        description="The estimators restarted from their initial state and re-apply 1..to_seq"
    )
    discarded: list[DiscardedBatch]


class RewindList(BaseModel):
    items: list[RewindPublic]
