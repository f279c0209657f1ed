"""One error body everywhere: payload validation, bodies that are not JSON, routing, OPTIONS,
and bugs (500) all answer ``{"error", "detail"}`` in JSON, as the OpenAPI declares."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import pytest
from fastapi import APIRouter
from fastapi.testclient import TestClient

from app.main import create_app
from tests.app.conftest import ADMIN_KEY, make_settings

H = {"Authorization": f"Bearer {ADMIN_KEY}", "content-type": "application/json"}


@pytest.fixture
def client(db_url: str) -> Iterator[TestClient]:
    app = create_app(make_settings(db_url, warm_kernels=False, processor_enabled=False))
    boom = APIRouter()

    @boom.get("/v1/boom")
    def _boom() -> None:
        raise RuntimeError("a bug")

    app.include_router(boom)
    with TestClient(app, raise_server_exceptions=False) as c:
        yield c


def _shape(r: Any, status: int, error: str) -> Any:
    assert r.status_code == status, r.text
    assert r.headers["content-type"] == "application/json"
    body = r.json()
    assert set(body) == {"error", "detail"} and body["error"] == error, body
    return body["detail"]


@pytest.mark.parametrize(
    "body",
    [b'{"tail": "\xff\xfe"}', b"[" * 50_000 + b"]" * 50_000, b"{not json", b'{"tail": 5}', b'{"tail": "A", "x": 1}'],
    ids=["invalid-utf8", "deeply-nested", "not-json", "wrong-type", "extra-field"],
)
@pytest.mark.parametrize("path", ["/v1/aircraft", "/v1/keys", "/v1/aircraft/N1/actuators"])
def test_malformed_bodies_are_422_with_a_list_of_issues(client: TestClient, path: str, body: bytes) -> None:
    client.post("/v1/aircraft", json={"tail": "N1"}, headers=H)
    detail = _shape(client.post(path, content=body, headers=H), 422, "ValidationError")
    assert isinstance(detail, list) and detail
    for issue in detail:
        assert set(issue) == {"loc", "msg", "type"} and isinstance(issue["loc"], list)


def test_query_validation_and_config_errors(client: TestClient) -> None:
    detail = _shape(client.get("/v1/fleet/health?sort=nope", headers=H), 422, "ValidationError")
    assert detail[0]["loc"] == ["query", "sort"]
    client.post("/v1/aircraft", json={"tail": "N1"}, headers=H)
    r = client.post("/v1/aircraft/N1/actuators", json={"actuator_id": "a", "kind": "warp_drive"}, headers=H)
    assert r.status_code == 422 and r.json()["error"] in ("InvalidConfig", "ValidationError")


def test_routing_errors_and_options(client: TestClient) -> None:
    _shape(client.get("/v1/nowhere", headers=H), 404, "NotFound")
    r = client.delete("/v1/aircraft", headers=H)
    _shape(r, 405, "MethodNotAllowed")
    assert set(r.headers["allow"].split(", ")) == {"GET", "POST", "OPTIONS"}
    r = client.options("/v1/aircraft")
    assert r.status_code == 204 and set(r.headers["allow"].split(", ")) == {"GET", "POST", "OPTIONS"}
    r = client.options("/v1/aircraft/N1/actuators/a/telemetry")
    # POST logs a batch, GET reads the logged samples back
    assert r.status_code == 204 and set(r.headers["allow"].split(", ")) == {"GET", "POST", "OPTIONS"}
    _shape(client.options("/v1/nowhere"), 404, "NotFound")


def test_a_bug_is_a_json_500(client: TestClient) -> None:
    detail = _shape(client.get("/v1/boom", headers=H), 500, "InternalError")
    assert "a bug" not in detail  # no internals in the answer; the server log has them


def test_openapi_declares_the_one_shape(client: TestClient) -> None:
    doc = client.get("/openapi.json").json()
    assert "HTTPValidationError" not in doc["components"]["schemas"]
    for path, ops in doc["paths"].items():
        for op in ops.values():
            if "422" in op["responses"]:
                schema = op["responses"]["422"]["content"]["application/json"]["schema"]
                assert schema["required"] == ["error", "detail"], path
            if path.startswith("/v1/"):
                assert "Retry-After" in op["responses"]["503"]["headers"], path
