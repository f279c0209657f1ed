"""Domain errors. Each carries its HTTP status; the handlers here turn them, and every other
failure (payload validation, routing, storage faults, bugs), into one body shape:
``{"error": "<Name>", "detail": "<message>"}``, where ``detail`` is a list of issues
(``{"loc", "msg", "type"}``) for ``ValidationError`` only. The OpenAPI declares the same
(:func:`document_errors`)."""

from __future__ import annotations

import logging
from typing import Any, ClassVar

import orjson
from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import Response
from sqlalchemy.exc import DisconnectionError, InterfaceError, OperationalError
from sqlalchemy.exc import TimeoutError as PoolTimeout
from starlette.exceptions import HTTPException
from starlette.routing import Match
from starlette.types import ASGIApp, Receive, Scope, Send

log = logging.getLogger("fleethealth")


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


class ActuatorDeleted(StaleBatch):
    """The actuator of an append is deleted (or purged): found by the log writer under the row
    lock, so whatever process deleted it. A ``StaleBatch`` on the wire (a WebSocket closes with
    this detail); a REST append looks the actuator up again to answer 404 or 410."""

    @property
    def name(self) -> str:
        return "StaleBatch"


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


class RewindRefused(DomainError):
    """A stream rewind that would lose what it must re-apply."""

    status_code = 409


class IngestBusy(DomainError):
    """Batch requests being taken in hold the process's whole memory budget for them
    (``FLEETHEALTH_INGEST_MEMORY_BYTES``): nothing was stored; retry after ``Retry-After`` seconds."""

    status_code = 503


class StorageUnavailable(DomainError):
    """The database cannot be reached or cannot write (out of space, connection lost): nothing
    was stored; retry after ``Retry-After`` seconds."""

    status_code = 503


#: Exceptions of the database layer that mean "storage unavailable now", not "bad request":
#: OperationalError covers SQLite's "database or disk is full" / "disk I/O error" / "database
#: is locked" and PostgreSQL's lost connections, shutdowns and DiskFull.
STORAGE_FAULTS: tuple[type[Exception], ...] = (OperationalError, InterfaceError, DisconnectionError, PoolTimeout)

ERROR_SCHEMA: dict[str, Any] = {
    "type": "object",
    "properties": {"error": {"type": "string"}, "detail": {"type": "string"}},
    "required": ["error", "detail"],
}
ISSUE_SCHEMA: dict[str, Any] = {
    "type": "object",
    "properties": {
        "loc": {"type": "array", "items": {"anyOf": [{"type": "string"}, {"type": "integer"}]}},
        "msg": {"type": "string"},
        "type": {"type": "string"},
    },
    "required": ["loc", "msg", "type"],
}
#: 422: ``ValidationError`` (a malformed request) lists its issues; ``InvalidConfig`` (a
#: well-formed request the rules refuse) says why in a string.
VALIDATION_ERROR_SCHEMA: dict[str, Any] = {
    "type": "object",
    "properties": {
        "error": {"type": "string"},
        "detail": {"anyOf": [{"type": "string"}, {"type": "array", "items": ISSUE_SCHEMA}]},
    },
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
        503: "Storage unavailable (database unreachable or out of space); retry after Retry-After",
    }
    return {
        c: {
            "description": text.get(c, "Error"),
            "content": {"application/json": {"schema": VALIDATION_ERROR_SCHEMA if c == 422 else ERROR_SCHEMA}},
            **({"headers": {"Retry-After": {"schema": {"type": "integer"}, "description": "Seconds"}}}
               if c == 503 else {}),
        }
        for c in codes
    }


def document_errors(openapi: dict[str, Any]) -> dict[str, Any]:
    """The OpenAPI as the handlers answer: every 422 in the one error shape (FastAPI's own
    ``HTTPValidationError`` is never sent), a 503 on every operation that reads or writes
    the database, and a 410 on every operation under an aircraft (a deleted aircraft or
    actuator answers 410 ``Gone`` until it is purged)."""
    from app.telemetry.validation import NO_CONTROL_PATTERN

    for path, ops in openapi.get("paths", {}).items():
        for op in ops.values():
            # ControlCharGuard refuses control characters in every path and query value.
            for param in op.get("parameters", ()):
                schema = param.get("schema", {})
                if param.get("in") in ("path", "query") and schema.get("type") == "string":
                    schema.setdefault("pattern", NO_CONTROL_PATTERN)
                for alt in schema.get("anyOf", ()):
                    if param.get("in") in ("path", "query") and alt.get("type") == "string":
                        alt.setdefault("pattern", NO_CONTROL_PATTERN)
            responses = op.setdefault("responses", {})
            if "422" in responses:
                responses["422"] = error_responses(422)[422]
            if path.startswith("/v1/"):
                responses.setdefault("503", error_responses(503)[503])
            if path.startswith("/v1/aircraft/{tail}"):
                responses.setdefault("410", error_responses(410)[410])
    schemas = openapi.get("components", {}).get("schemas", {})
    for name in ("HTTPValidationError", "ValidationError"):
        schemas.pop(name, None)
    return openapi


def validation_issues(errors: Any) -> list[dict[str, Any]]:
    """pydantic / FastAPI errors as ``{"loc", "msg", "type"}`` issues (JSON-safe)."""
    return [
        {
            "loc": [x if isinstance(x, int) else str(x) for x in e.get("loc", ())],
            "msg": str(e.get("msg", "")),
            "type": str(e.get("type", "value_error")),
        }
        for e in errors
    ]


_REASONS = {404: "NotFound", 405: "MethodNotAllowed", 400: "BadRequest", 413: "PayloadTooLarge"}


_METHODS = ("GET", "HEAD", "POST", "PUT", "PATCH", "DELETE")


def allowed_methods(app: ASGIApp, scope: Scope) -> list[str]:
    """Every method some route serves at this path (Starlette's own 405 names only the first
    route's), with OPTIONS always; empty when no route serves the path."""
    methods = {
        method
        for method in _METHODS
        for route in getattr(app, "routes", ())
        if route.matches({**scope, "type": "http", "method": method})[0] == Match.FULL
    }
    return sorted(methods | {"OPTIONS"}) if methods else []


class OptionsAllow:
    """ASGI middleware: ``OPTIONS`` on a path some route serves is answered 204 with ``Allow``
    (404 in the error shape otherwise); other methods pass through."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or scope["method"] != "OPTIONS":
            await self.app(scope, receive, send)
            return
        methods = allowed_methods(scope["app"].router, scope)
        if methods:
            status, body = 204, b""
            headers = [(b"allow", ", ".join(methods).encode())]
        else:
            status = 404
            body = orjson.dumps({"error": "NotFound", "detail": f"no route {scope['path']!r}"})
            headers = [(b"content-type", b"application/json")]
        headers.append((b"content-length", str(len(body)).encode()))
        await send({"type": "http.response.start", "status": status, "headers": headers})
        await send({"type": "http.response.body", "body": body})


def domain_error_response(exc: DomainError, retry_after_s: int) -> Response:
    """The answer to a :class:`DomainError` (``retry_after_s``: the 503s' ``Retry-After``)."""
    headers = {"WWW-Authenticate": "Bearer"} if exc.status_code == 401 else None
    if exc.status_code == 503:
        headers = {"Retry-After": str(retry_after_s)}
    return json_response({"error": exc.name, "detail": exc.detail}, status_code=exc.status_code, headers=headers)


def storage_fault_response(path: str, exc: Exception, retry_after_s: int) -> Response:
    """The answer to one of :data:`STORAGE_FAULTS` (logged, one line)."""
    log.warning("storage unavailable (%s): %s", path, _first_line(exc))
    return json_response(
        {"error": "StorageUnavailable",
         "detail": f"the database is unavailable ({_first_line(exc)}); nothing was stored, retry later"},
        status_code=503, headers={"Retry-After": str(retry_after_s)},
    )


def install_handlers(app: FastAPI) -> None:
    @app.exception_handler(DomainError)
    async def _domain(request: Request, exc: DomainError) -> Response:
        return domain_error_response(exc, request.app.state.settings.storage_retry_after_s)

    @app.exception_handler(RequestValidationError)
    async def _validation(_: Request, exc: RequestValidationError) -> Response:
        return json_response(
            {"error": "ValidationError", "detail": validation_issues(exc.errors())}, status_code=422
        )

    @app.exception_handler(HTTPException)
    async def _http(request: Request, exc: HTTPException) -> Response:
        # Routing (404, 405) and FastAPI's own body parsing, which gives 400 for a body that is
        # not UTF-8 or nests too deeply for the parser: a malformed payload, so 422 here.
        if exc.status_code == 400 and exc.detail == "There was an error parsing the body":
            issue = {"loc": ["body"], "msg": "the body is not valid JSON (not UTF-8, or nested too deeply)",
                     "type": "json_invalid"}
            return json_response({"error": "ValidationError", "detail": [issue]}, status_code=422)
        headers = dict(exc.headers or {})
        if exc.status_code == 405:
            headers["Allow"] = ", ".join(allowed_methods(request.app.router, request.scope))
        name = _REASONS.get(exc.status_code, "HTTPError")
        return json_response({"error": name, "detail": str(exc.detail)}, status_code=exc.status_code,
                             headers=headers or None)

    for fault in STORAGE_FAULTS:
        app.add_exception_handler(fault, _storage_fault)

    @app.exception_handler(Exception)
    async def _internal(_: Request, exc: Exception) -> Response:
        # Logged with its traceback by the server (Starlette re-raises after this answer).
        return json_response({"error": "InternalError", "detail": "internal error; see the server log"},
                             status_code=500)

    app.add_middleware(OptionsAllow)


async def _storage_fault(request: Request, exc: Exception) -> Response:
    return storage_fault_response(request.url.path, exc, request.app.state.settings.storage_retry_after_s)


def _first_line(exc: BaseException) -> str:
    orig = getattr(exc, "orig", None) or exc
    text = str(orig).strip().splitlines()
    return f"{type(orig).__name__}: {text[0] if text else ''}"[:300]


def json_response(
    content: Any, status_code: int = 200, headers: dict[str, str] | None = None
) -> Response:
    """A JSON response encoded by orjson (NaN-free content only)."""
    return Response(
        orjson.dumps(content), status_code=status_code, headers=headers, media_type="application/json"
    )
