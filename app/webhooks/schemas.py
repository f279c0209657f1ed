"""Request and response models of webhooks."""

from __future__ import annotations

from datetime import datetime
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

from app.telemetry.validation import Identifier

DeliveryStatus = Literal["pending", "delivered", "failed"]


class WebhookCreate(BaseModel):
    model_config = ConfigDict(extra="forbid")
    url: Identifier = Field(
        min_length=1,
        max_length=2000,
        description="http(s) URL within the operator's allowed targets",
    )
    event_types: list[Identifier] = Field(
        default_factory=list,
        max_length=50,
        description="Logged event types to deliver (empty: all)",
    )
    tails: list[Identifier] | None = Field(
        default=None, max_length=1000, description="Only these tails (null: all)"
    )
    secret: Identifier | None = Field(
        default=None,
        min_length=16,
        max_length=200,
        description="Signing secret (default: generated)",
    )
    description: Identifier | None = Field(default=None, max_length=500)


class WebhookPublic(BaseModel):
    id: int
    url: str
    event_types: list[str]
    tails: list[str] | None
    description: str | None
    active: bool
    created_at: datetime


class WebhookCreated(WebhookPublic):
    secret: str = Field(description="The signing secret: shown here only")


class WebhookList(BaseModel):
    items: list[WebhookPublic]


class WebhookTargets(BaseModel):
    prefixes: list[str] = Field(description="URL prefixes the operator's webhooks may deliver to")


class DeliveryAttempt(BaseModel):
    attempt: int
    at: datetime
    status_code: int | None
    error: str | None
    duration_ms: float


class DeliveryPublic(BaseModel):
    id: int
    event_id: int | None = Field(description="The logged event delivered (null: a test delivery)")
    event_type: str
    idempotency_key: str = Field(
        description="Sent as the Idempotency-Key header, the same on every attempt"
    )
    status: DeliveryStatus
    attempts: int
    next_attempt_at: datetime | None
    last_attempt_at: datetime | None
    last_status_code: int | None
    last_error: str | None
    delivered_at: datetime | None
    created_at: datetime
    log: list[DeliveryAttempt]


class DeliveryList(BaseModel):
    items: list[DeliveryPublic]
    next_before: int | None = Field(
        description="Pass as `before` for the next (older) page; null at the end"
    )
