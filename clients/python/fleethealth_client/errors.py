"""Errors raised by the client: an error answer of the REST API, a refusal on a WebSocket."""

from __future__ import annotations

import httpx
import orjson

__all__ = ["ApiError", "StreamRefused"]

#: Characters of a non-API error body kept in :attr:`ApiError.detail`.
MAX_DETAIL_CHARS = 500


class ApiError(Exception):
    """An error answer of the API.

    Attributes:
        status: HTTP status code.
        error: error type name from the body (e.g. ``"StaleBatch"``), or ``"HTTPError"`` when the
            body is not the API's error shape.
        detail: human-readable message from the body.
    """

    def __init__(self, status: int, error: str, detail: str) -> None:
        super().__init__(f"{status} {error}: {detail}")
        self.status = status
        self.error = error
        self.detail = detail

    @classmethod
    def from_response(cls, response: httpx.Response) -> ApiError:
        """Read the API's error body ``{"error": ..., "detail": ...}`` (or keep the raw text)."""
        error, detail = "HTTPError", response.text[:MAX_DETAIL_CHARS]
        try:
            body = orjson.loads(response.content)
        except orjson.JSONDecodeError:
            body = None
        if isinstance(body, dict):
            error = str(body.get("error") or error)
            raw_detail = body.get("detail", detail)
            detail = (
                raw_detail if isinstance(raw_detail, str) else orjson.dumps(raw_detail).decode()
            )
        return cls(response.status_code, error, detail)


class StreamRefused(Exception):
    """The server refused a WebSocket frame or the connection (error message and close code).

    Sending the same frame again cannot succeed, so it is not retried.

    Attributes:
        code: WebSocket close code, or None when the refusal came before a close.
        error: error type name from the server's error message.
        detail: human-readable message.
    """

    def __init__(self, code: int | None, error: str, detail: str) -> None:
        super().__init__(f"{error}: {detail} (close code {code})")
        self.code = code
        self.error = error
        self.detail = detail
