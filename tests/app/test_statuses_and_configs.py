"""Statuses in the API (a new stream is learning; the board orders by severity) and each
estimator kind's configuration in the OpenAPI."""

from __future__ import annotations

from typing import Any

import pytest
from fastapi.testclient import TestClient
from pydantic import Field
from sqlalchemy import select
from sqlalchemy.orm import Session

from app.db import Database
from app.errors import InvalidConfig
from app.fleet import schemas as fleet_schemas
from app.main import create_app
from app.models import Actuator
from app.processing import repository
from app.status import HealthStatus
from estimators import fakf
from estimators.base import EstimatorConfigModel
from estimators.registry import ESTIMATORS, config_model
from tests.app.conftest import Api, make_settings


def test_new_streams_are_learning_and_the_board_orders_by_severity(api: Api, db_url: str) -> None:
    api.setup_actuator("N1", "a1")
    api.setup_actuator("N1", "a2")
    api.setup_actuator("N2", "b1")
    h = api.health("N1", "a1")
    assert h["status"] == "learning" and h["failure"] is None
    assert {e["status"] for e in h["estimators"].values()} == {"learning"}
    assert api.get("/v1/fleet/health").json()["aircraft"][1]["actuators"][0]["status"] == "learning"

    db = Database(db_url)
    with db.write() as session:  # as the processor does when a stream cannot be applied
        repository.mark_failed(session, actuator_pk(session, "a2"), "test: unreadable state")
    db.dispose()
    board = api.get("/v1/fleet/health").json()["aircraft"]
    assert [a["tail"] for a in board] == ["N1", "N2"]  # failed outranks learning
    assert board[0]["status"] == "failed"
    assert [(x["actuator_id"], x["status"]) for x in board[0]["actuators"]] == [("a2", "failed"), ("a1", "learning")]
    assert board[0]["actuators"][0]["failure"] == "test: unreadable state"


def actuator_pk(session: Session, actuator_id: str) -> int:
    return int(session.scalar(select(Actuator.id).where(Actuator.actuator_id == actuator_id)))


def _schema(doc: dict[str, Any], ref_or_schema: dict[str, Any]) -> dict[str, Any]:
    """Follow a $ref (directly or inside anyOf) to the component schema."""
    for option in ref_or_schema.get("anyOf", [ref_or_schema]):
        if "$ref" in option:
            return doc["components"]["schemas"][option["$ref"].rsplit("/", 1)[-1]]  # type: ignore[no-any-return]
    return ref_or_schema


def test_openapi_names_the_six_statuses() -> None:
    doc = create_app(make_settings("sqlite://")).openapi()
    assert doc["components"]["schemas"]["HealthStatus"]["enum"] == [s.value for s in HealthStatus]
    for name in ("ActuatorHealth", "FleetActuator", "HealthWindowPublic", "RulEstimatePublic", "EstimatorDiagnosis"):
        assert doc["components"]["schemas"][name]["properties"]["status"] == {"$ref": "#/components/schemas/HealthStatus"}


def _documents_config(doc: dict[str, Any], name: str) -> None:
    model = config_model(name)
    configs = doc["components"]["schemas"]["EstimatorConfigs"]["properties"]
    schema = _schema(doc, configs[name])
    assert set(schema["properties"]) == set(model.model_fields)
    for field_name, info in model.model_fields.items():
        prop = schema["properties"][field_name]
        assert {"type", "anyOf", "oneOf", "$ref", "items"} & set(prop), (field_name, prop)
        assert prop.get("description"), f"{name}.{field_name} has no description (units)"
        if info.is_required():
            continue
        if info.default_factory is not None:
            # A nested settings object built by its own defaults: each of its fields documents
            # its default.
            nested = _schema(doc, prop)
            assert nested.get("properties") or nested.get("additionalProperties"), (field_name, prop)
        elif info.default is not None:
            # (A null default is left out of the served document; the schema's null option shows it.)
            assert "default" in prop, (field_name, prop)
        else:
            assert any(o.get("type") == "null" for o in prop.get("anyOf", [])), (field_name, prop)


@pytest.mark.parametrize("name", sorted(ESTIMATORS))
def test_openapi_documents_each_kinds_config(name: str) -> None:
    # The document as served (no lifespan needed: nothing is read from the database).
    doc = TestClient(create_app(make_settings("sqlite://"))).get("/openapi.json").json()
    _documents_config(doc, name)


class _DemoConfig(EstimatorConfigModel):
    forgetting_factor: float = Field(default=0.99, gt=0, le=1, description="Forgetting factor (1)")
    window_samples: int = Field(default=250, gt=0, description="Health window length, samples")


def test_a_declared_config_model_types_the_request_and_its_errors(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # The mechanism, with a stand-in model on one kind: documented field by field, validated
    # with InvalidConfig naming the field.
    monkeypatch.setattr(fakf, "CONFIG_MODEL", _DemoConfig, raising=False)
    model = fleet_schemas._estimator_configs_model()
    monkeypatch.setattr(fleet_schemas, "EstimatorConfigs", model)
    fields = model.model_json_schema()
    prop = fields["properties"]["fakf"]
    assert any("$ref" in o for o in prop["anyOf"])
    demo = fields["$defs"]["_DemoConfig"]["properties"]
    assert demo["window_samples"]["default"] == 250 and "samples" in demo["window_samples"]["description"]
    with pytest.raises(InvalidConfig, match="fakf.forgetting_factor"):
        model.model_validate({"fakf": {"forgetting_factor": 2}})
    ok = model.model_validate({"fakf": {"window_samples": 100}})
    assert ok.fakf.model_dump(exclude_unset=True) == {"window_samples": 100}  # type: ignore[attr-defined]
