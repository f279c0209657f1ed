"""Request and response models of aircraft, actuators, kinds and the fleet board."""

from __future__ import annotations

from datetime import datetime
from typing import Any

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
    created_at: datetime


class ActuatorList(BaseModel):
    items: list[ActuatorPublic]


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
