"""Property-based requests over the event, alarm and webhook endpoints (schemathesis, from the
OpenAPI document): no input gives a server error, and every answer matches its declared
schema. Bounded: a few examples per operation, positive and negative."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
import schemathesis
from fastapi.testclient import TestClient
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from schemathesis.checks import not_a_server_error
from schemathesis.generation import GenerationMode
from schemathesis.specs.openapi.checks import response_schema_conformance

from app.main import create_app
from app.webhooks import service as webhooks
from tests.app.conftest import ADMIN_KEY, Api, make_settings

PATHS = r"^/v1/(events|alarms|webhooks)"
EXAMPLES_PER_OPERATION = 25


def _seed(api: Api) -> None:
    """Something to find: an alarm, an allowed target with a subscription."""
    api.setup_actuator("N1", "ema1")
    n = 800
    r = api.send_json("N1", "ema1", "flat", np.arange(n) * 0.001, {"current": np.ones(n), "voltage": np.ones(n)})
    assert r.status_code == 202
    with api.app.state.db.write() as s:  # type: ignore[attr-defined]
        webhooks.allow_target(s, "default", "http://127.0.0.1:9/hooks")  # nothing listens there
    assert api.post("/v1/webhooks", json={"url": "http://127.0.0.1:9/hooks/a"}).status_code == 201


def test_new_endpoints_answer_no_server_error(db_url: str) -> None:
    app = create_app(make_settings(db_url, webhook_max_attempts=1, webhook_timeout_s=1.0))
    with TestClient(app) as client:  # runs the lifespan: the database and the threads
        _seed(Api(client))
        schema = schemathesis.openapi.from_asgi("/openapi.json", app).include(path_regex=PATHS)
        operations = [r.ok() for r in schema.get_all_operations()]
        assert len(operations) >= 10, [op.label for op in operations]
        seen: list[tuple[str, int]] = []
        for op in operations:
            strategy = st.one_of(
                op.as_strategy(generation_mode=GenerationMode.POSITIVE),
                op.as_strategy(generation_mode=GenerationMode.NEGATIVE),
            )

            @settings(
                max_examples=EXAMPLES_PER_OPERATION,
                deadline=None,
                database=None,
                derandomize=True,
                suppress_health_check=list(HealthCheck),
            )
            @given(case=strategy)
            def check(case: Any) -> None:
                response = case.call(headers={"Authorization": f"Bearer {ADMIN_KEY}"})
                seen.append((case.operation.label, response.status_code))
                case.validate_response(response, checks=[not_a_server_error, response_schema_conformance])

            check()
        by_op = {label for label, _ in seen}
        assert by_op == {op.label for op in operations}
        assert all(code < 500 for _, code in seen)
        assert any(code == 200 for _, code in seen) and any(400 <= code < 500 for _, code in seen)
        print(f"{len(seen)} requests over {len(by_op)} operations")


pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")
