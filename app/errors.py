"""Domain errors. Each carries its HTTP status; one handler turns them into
``{"error": "<Name>", "detail": "<message>"}``."""

from __future__ import annotations

from typing import Any, ClassVar

import orjson
from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import Response


class DomainError(Exception):
    status_code: ClassVar[int] = 400

    def __init__(self, detail: str) -> None:
        super().__init__(detail)
        self.detail = detail

    @property
    def name(self) -> str:
        return type(self).__name__


class InvalidBatch(DomainError):
    status_code = 400


class Unauthorized(DomainError):
    status_code = 401


class Forbidden(DomainError):
    status_code = 403


class NotFound(DomainError):
    status_code = 404


class AlreadyExists(DomainError):
    status_code = 409


class StaleBatch(DomainError):
    status_code = 409


class IdempotencyConflict(DomainError):
    status_code = 409


class Gone(DomainError):
    """The aircraft or actuator was deleted (its data is kept until it is purged)."""

    status_code = 410


class MaintenancePending(DomainError):
    """A repair or replacement is recorded but the batches before it are not applied yet."""

    status_code = 409


class InvalidCursor(DomainError):
    """A pagination cursor that this endpoint did not issue, or for another order."""

    status_code = 400


class PayloadTooLarge(DomainError):
    status_code = 413


class UnsupportedMediaType(DomainError):
    status_code = 415


class InvalidConfig(DomainError):
    status_code = 422


class InvalidQuery(DomainError):
    """A query string that is well-formed but asks for something that does not fit together."""

    status_code = 400


class StreamFailed(DomainError):
    """The stream is marked failed: its batches are logged but no longer applied."""

    status_code = 409


ERROR_SCHEMA = {
    "type": "object",
    "properties": {"error": {"type": "string"}, "detail": {"type": "string"}},
    "required": ["error", "detail"],
}


def error_responses(*codes: int) -> dict[int | str, dict[str, Any]]:
    """OpenAPI declarations of the error responses an endpoint can give."""
    text = {
        400: "Invalid input",
        401: "Missing or unknown API key",
        403: "The key lacks the needed scope",
        404: "Not found (or owned by another operator)",
        409: "Conflict",
        410: "Deleted (kept until purged)",
        413: "Body too large",
        415: "Unsupported content type",
        422: "Invalid payload or configuration",
    }
    return {
        c: {
            "description": text.get(c, "Error"),
            "content": {"application/json": {"schema": ERROR_SCHEMA}},
        }
        for c in codes
    }


def install_handlers(app: FastAPI) -> None:
    @app.exception_handler(DomainError)
    async def _domain(_: Request, exc: DomainError) -> Response:
        headers = {"WWW-Authenticate": "Bearer"} if exc.status_code == 401 else None
        return json_response(
            {"error": exc.name, "detail": exc.detail}, status_code=exc.status_code, headers=headers
        )

    @app.exception_handler(RequestValidationError)
    async def _validation(_: Request, exc: RequestValidationError) -> Response:
        parts = []
        for e in exc.errors():
            loc = ".".join(str(x) for x in e.get("loc", ()) if x != "body")
            parts.append(f"{loc}: {e.get('msg')}" if loc else str(e.get("msg")))
        return json_response(
            {"error": "ValidationError", "detail": "; ".join(parts)}, status_code=422
        )


def json_response(
    content: Any, status_code: int = 200, headers: dict[str, str] | None = None
) -> Response:
    """A JSON response encoded by orjson (NaN-free content only)."""
    return Response(
        orjson.dumps(content), status_code=status_code, headers=headers, media_type="application/json"
    )
