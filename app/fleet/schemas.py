"""Request and response models of aircraft, actuators, kinds and the fleet board."""

from __future__ import annotations

from datetime import datetime
from typing import Any, Literal

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    ModelWrapValidatorHandler,
    ValidationError,
    create_model,
    model_validator,
)

from app.errors import InvalidConfig
from app.pagination import CURSOR_DOC
from app.status import HealthStatus
from app.telemetry.validation import Identifier
from estimators.base import config_error
from estimators.registry import ESTIMATORS, config_model

Name = Field(min_length=1, max_length=64, pattern=r"^[A-Za-z0-9][A-Za-z0-9._\-]*$")


class _EstimatorConfigsBase(BaseModel):
    model_config = ConfigDict(extra="forbid")

    @model_validator(mode="wrap")
    @classmethod
    def _config_errors_are_invalid_config(cls, value: Any, handler: ModelWrapValidatorHandler[Any]) -> Any:
        # An estimator's settings are configuration: their problems answer InvalidConfig (422)
        # naming each field, like the checks the service makes itself.
        try:
            return handler(value)
        except ValidationError as exc:
            raise InvalidConfig(str(config_error("estimators", exc))) from None


def _estimator_configs_model() -> type[BaseModel]:
    """``{estimator name: config}`` with one optional field per estimator kind, typed by that
    kind's config model (its settings, types, defaults and units appear in the OpenAPI)."""
    fields: dict[str, Any] = {}
    for name in sorted(ESTIMATORS):
        fields[name] = (config_model(name) | None, Field(default=None, description=f"Configuration of {name}"))
    return create_model(
        "EstimatorConfigs",
        __base__=_EstimatorConfigsBase,
        __doc__="Estimator name -> its configuration; omitted settings take their defaults.",
        **fields,
    )


EstimatorConfigs = _estimator_configs_model()


class AircraftCreate(BaseModel):
    model_config = ConfigDict(extra="forbid")
    tail: str = Field(min_length=1, max_length=32, pattern=r"^[A-Za-z0-9][A-Za-z0-9\-]*$")
    description: Identifier | None = Field(default=None, max_length=500)


class AircraftPublic(BaseModel):
    model_config = ConfigDict(from_attributes=True)
    tail: str
    description: str | None
    created_at: datetime


class AircraftList(BaseModel):
    items: list[AircraftPublic]
    next_cursor: str | None = Field(default=None, description=CURSOR_DOC)


class AircraftUpdate(BaseModel):
    """Editable fields of an aircraft (the tail is its identity and cannot change)."""

    model_config = ConfigDict(extra="forbid")
    description: Identifier | None = Field(default=None, max_length=500)


class Deleted(BaseModel):
    deleted_at: datetime
    purge_after: datetime = Field(description="When the data is removed for good")


class ActuatorCreate(BaseModel):
    model_config = ConfigDict(extra="forbid")
    actuator_id: str = Name
    kind: str = Field(description="Actuator kind, e.g. ema_voltage")
    channels: list[Identifier] | None = Field(
        default=None, description="Channel names the telemetry carries (default: the kind's)"
    )
    estimators: EstimatorConfigs | None = Field(  # type: ignore[valid-type]
        default=None,
        description="Estimator name -> configuration (default: the kind's estimators with defaults)",
    )

    def estimator_dicts(self) -> dict[str, dict[str, Any]] | None:
        """The estimators given, as JSON-like dicts of the settings given (None: the kind's)."""
        if self.estimators is None:
            return None
        out: dict[str, dict[str, Any]] = {}
        for name in self.estimators.model_fields_set:
            cfg = getattr(self.estimators, name)
            if cfg is None:
                continue
            out[name] = cfg.model_dump(mode="json", exclude_unset=True) if isinstance(cfg, BaseModel) else cfg
        return out


class ActuatorPublic(BaseModel):
    actuator_id: str
    kind: str
    channels: list[str]
    estimators: dict[str, dict[str, Any]] = Field(
        description="Estimator name -> its configuration with every default filled in"
    )
    config_versions: dict[str, int] = Field(
        default_factory=dict, description="Estimator name -> its config version in force"
    )
    baseline: int = Field(
        default=1, description="Baseline (epoch of the physical part) the estimators are in"
    )
    created_at: datetime


class ActuatorList(BaseModel):
    items: list[ActuatorPublic]
    next_cursor: str | None = Field(default=None, description=CURSOR_DOC)


class ActuatorUpdate(BaseModel):
    """New settings for attached estimators: a new config version each, from the next batch."""

    model_config = ConfigDict(extra="forbid")
    estimators: dict[Identifier, dict[str, Any]] = Field(
        description="Estimator name -> the settings to change (merged onto the current ones, "
        "nested settings member by member; see EstimatorConfigs for each kind's settings)",
    )
    reset_state: bool = Field(
        default=False,
        description="Restart the estimators from their initial state instead of carrying their "
        "state over (needed when the change alters the state's layout)",
    )
    comment: Identifier | None = Field(default=None, max_length=2000)


class ConfigVersionPublic(BaseModel):
    model_config = ConfigDict(from_attributes=True)
    estimator: str
    version: int
    config: dict[str, Any]
    from_seq: int = Field(description="First batch (stream seq) applied with this version")
    state: Literal["kept", "reset"] = Field(description="Whether the estimator kept its state")
    comment: str | None
    created_at: datetime


class ConfigVersionList(BaseModel):
    items: list[ConfigVersionPublic]
    next_cursor: str | None = Field(default=None, description=CURSOR_DOC)


class ActuatorUpdated(BaseModel):
    actuator: ActuatorPublic
    versions: list[ConfigVersionPublic] = Field(description="The config versions created")


MaintenanceKind = Literal["inspection", "repair", "replacement"]


class MaintenanceCreate(BaseModel):
    model_config = ConfigDict(extra="forbid")
    action: MaintenanceKind = Field(
        description="`inspection` records only; `repair` and `replacement` start a new baseline: "
        "the estimators restart from their initial state (RUL starts again, `failed` clears)"
    )
    performed_by: Identifier = Field(min_length=1, max_length=200, description="Who did the work")
    performed_at: datetime | None = Field(
        default=None, description="When the work was done, with a time zone (default: now)"
    )
    comment: Identifier | None = Field(default=None, max_length=2000)

    @model_validator(mode="after")
    def _aware(self) -> MaintenanceCreate:
        if self.performed_at is not None and self.performed_at.utcoffset() is None:
            raise ValueError("performed_at needs a time zone (e.g. 2026-12-02T08:00:00Z)")
        return self


class MaintenancePublic(BaseModel):
    model_config = ConfigDict(from_attributes=True)
    id: int
    action: MaintenanceKind
    performed_by: str
    performed_at: datetime
    comment: str | None
    baseline: int = Field(description="Baseline in force after the action")
    from_seq: int | None = Field(
        description="First batch (stream seq) of the new baseline; null for an inspection"
    )
    status_before: HealthStatus
    recorded_at: datetime


class MaintenanceList(BaseModel):
    items: list[MaintenancePublic]
    next_cursor: str | None = Field(default=None, description=CURSOR_DOC)


class KindPublic(BaseModel):
    name: str
    description: str
    channels: list[str]
    default_estimators: dict[str, dict[str, Any]]


class KindList(BaseModel):
    items: list[KindPublic]


class FleetActuator(BaseModel):
    actuator_id: str
    kind: str
    status: HealthStatus
    failure: str | None = Field(
        default=None, description="Why the stream is no longer applied (status failed), if so"
    )
    t_last_s: float | None
    last_logged_seq: int
    last_applied_seq: int
    updated_at: datetime | None
    rul_q05_s: float | None = Field(
        default=None, description="5 % quantile of the latest RUL prognosis, seconds of stream time"
    )
    rul_q50_s: float | None = Field(default=None, description="Median of the latest RUL prognosis")
    rul_t_s: float | None = Field(default=None, description="Stream time of the latest RUL prognosis")
    active_faults: list[str] = Field(
        default_factory=list, description="Components with a detected, not yet cleared, fault"
    )
    open_alarms: int = Field(default=0, description="Active and acknowledged alarms (GET /v1/alarms)")


class FleetAircraft(BaseModel):
    tail: str
    status: HealthStatus
    updated_at: datetime | None
    open_alarms: int = Field(default=0, description="Open alarms of all its actuators")
    actuators: list[FleetActuator]


class FleetHealth(BaseModel):
    aircraft: list[FleetAircraft]
    next_cursor: str | None = Field(default=None, description=CURSOR_DOC)
