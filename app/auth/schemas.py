"""Request and response models of API keys."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

from app.telemetry.validation import Identifier


class KeyCreate(BaseModel):
    model_config = ConfigDict(extra="forbid")
    name: Identifier = Field(default="", max_length=100)
    scopes: list[Literal["ingest", "read", "admin"]] = Field(min_length=1)


class KeyCreated(BaseModel):
    id: int
    name: str
    prefix: str
    scopes: list[str]
    key: str = Field(description="The key itself; shown once, stored only as a digest")
