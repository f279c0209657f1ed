"""HTTP clients for the fleethealth API (synchronous and asyncio).

Usage::

    from fleethealth_client import FleetHealthClient

    with FleetHealthClient("http://127.0.0.1:8000", api_key) as client:
        client.create_aircraft("FH-001")
        client.create_actuator("FH-001", "ema-left")
        ack = client.post_batch(
            "FH-001", "ema-left", "b-0001",
            {"current": current_a, "voltage": voltage_v},
            t0=1283532701.0, sample_rate_hz=100.0, fmt="json",
        )
        health = client.wait_applied("FH-001", "ema-left", ack["seq"], timeout_s=30)

Telemetry encodings are described in :mod:`fleethealth_client.encoding`; ``fmt="arrow"`` (the
default, the most compact) and ``fmt="csv"`` need pyarrow (the ``arrow`` extra).

Retries: connection errors, timeouts, 429 and 5xx answers are retried a bounded number of times with
exponential backoff, or after the server's ``Retry-After`` (:class:`~fleethealth_client.retry.RetryPolicy`), always with the same request
(and so the same batch id): the server applies a batch id once and answers a repeat with the first
answer. 4xx answers raise :class:`~fleethealth_client.errors.ApiError` at once.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, cast

import httpx
import orjson
from numpy.typing import ArrayLike

from fleethealth_client.encoding import EncodedBatch, encode_batch
from fleethealth_client.errors import ApiError
from fleethealth_client.paths import actuator_path, aircraft_path
from fleethealth_client.retry import RetryPolicy

__all__ = ["AsyncFleetHealthClient", "FleetHealthClient"]

USER_AGENT = "fleethealth-client/0.1"
#: Longest ``wait`` the server accepts on a telemetry post (seconds).
MAX_SERVER_WAIT_S = 60.0
#: Extra seconds of client timeout beyond a server-side wait, for the answer to travel.
WAIT_MARGIN_S = 10.0
#: Cap on the polling interval of ``wait_applied`` (it grows by half each poll).
MAX_POLL_S = 1.0
#: HTTP status of a registration that already exists.
CONFLICT = 409

JsonObject = dict[str, Any]


# --------------------------------------------------------------------------------------------
# Request building shared by both clients
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Request:
    method: str
    path: str
    json: Any = None
    content: bytes | None = None
    content_type: str | None = None
    params: Mapping[str, Any] | None = None
    timeout_s: float | None = None
    ok_statuses: tuple[int, ...] = (200, 201, 202)


def _drop_none(params: Mapping[str, Any]) -> dict[str, Any]:
    return {key: value for key, value in params.items() if value is not None}


class _Core:
    """Builds requests and reads answers; knows nothing about I/O."""

    def __init__(self, base_url: str, api_key: str, retry: RetryPolicy | None) -> None:
        self.base_url = base_url.rstrip("/")
        self.headers = {"Authorization": f"Bearer {api_key}", "User-Agent": USER_AGENT}
        self.retry = retry or RetryPolicy()

    @staticmethod
    def create_aircraft(tail: str, description: str | None) -> _Request:
        return _Request("POST", "/v1/aircraft", json={"tail": tail, "description": description})

    @staticmethod
    def create_actuator(
        tail: str,
        actuator_id: str,
        kind: str,
        channels: Sequence[str] | None,
        estimators: Mapping[str, Any] | None,
    ) -> _Request:
        body: dict[str, Any] = {"actuator_id": actuator_id, "kind": kind}
        if channels is not None:
            body["channels"] = list(channels)
        if estimators is not None:
            body["estimators"] = dict(estimators)
        return _Request("POST", f"{aircraft_path(tail)}/actuators", json=body)

    @staticmethod
    def post_batch(
        tail: str,
        actuator_id: str,
        encoded: EncodedBatch,
        wait_s: float,
        timeout_s: float,
    ) -> _Request:
        if not 0.0 <= wait_s <= MAX_SERVER_WAIT_S:
            raise ValueError(f"wait_s must be within [0, {MAX_SERVER_WAIT_S:g}]")
        params = dict(encoded.params)
        if wait_s > 0:
            params["wait"] = repr(float(wait_s))
        return _Request(
            "POST",
            f"{actuator_path(tail, actuator_id)}/telemetry",
            content=encoded.content,
            content_type=encoded.content_type,
            params=params,
            # The server may hold the answer for up to wait_s: never time out before it.
            timeout_s=max(timeout_s, wait_s + WAIT_MARGIN_S),
        )

    @staticmethod
    def health_history(
        tail: str,
        actuator_id: str,
        estimator: str,
        from_s: float | None,
        to_s: float | None,
        limit: int | None,
    ) -> _Request:
        params = _drop_none(
            {"estimator": estimator, "from_s": from_s, "to_s": to_s, "limit": limit, "order": "asc"}
        )
        return _Request("GET", f"{actuator_path(tail, actuator_id)}/health/history", params=params)

    @staticmethod
    def outputs(
        tail: str, actuator_id: str, estimator: str, from_s: float | None, to_s: float | None
    ) -> _Request:
        params = _drop_none({"estimator": estimator, "from_s": from_s, "to_s": to_s, "order": "asc"})
        return _Request("GET", f"{actuator_path(tail, actuator_id)}/outputs", params=params)

    @staticmethod
    def rul(
        tail: str, actuator_id: str, estimator: str | None, from_s: float | None, to_s: float | None
    ) -> _Request:
        params = _drop_none({"estimator": estimator, "from_s": from_s, "to_s": to_s, "order": "asc"})
        return _Request("GET", f"{actuator_path(tail, actuator_id)}/rul", params=params)

    @staticmethod
    def faults(tail: str, actuator_id: str) -> _Request:
        return _Request("GET", f"{actuator_path(tail, actuator_id)}/faults")

    def kwargs(self, request: _Request, default_timeout_s: float) -> dict[str, Any]:
        headers = dict(self.headers)
        if request.content_type:
            headers["Content-Type"] = request.content_type
        kwargs: dict[str, Any] = {
            "method": request.method,
            "url": self.base_url + request.path,
            "headers": headers,
            "params": request.params,
            "timeout": request.timeout_s or default_timeout_s,
        }
        if request.json is not None:
            kwargs["content"] = orjson.dumps(request.json)
            headers["Content-Type"] = "application/json"
        elif request.content is not None:
            kwargs["content"] = request.content
        return kwargs

    @staticmethod
    def parse(request: _Request, response: httpx.Response) -> JsonObject:
        if response.status_code in request.ok_statuses:
            body = orjson.loads(response.content) if response.content else {}
            return cast(JsonObject, body if isinstance(body, dict) else {"value": body})
        raise ApiError.from_response(response)


def _items(body: JsonObject) -> list[JsonObject]:
    return cast(list[JsonObject], body["items"])


def _is_already_exists(exc: ApiError) -> bool:
    return exc.status == CONFLICT


# --------------------------------------------------------------------------------------------
# Synchronous client
# --------------------------------------------------------------------------------------------


class FleetHealthClient:
    """Synchronous client; a context manager that closes its connection pool.

    Args:
        base_url: e.g. ``"http://127.0.0.1:8000"``.
        api_key: key sent as ``Authorization: Bearer <key>``.
        timeout: seconds for one request (connect, read, write, pool).
        retry: retry policy for connection errors and 5xx answers.
        transport: optional httpx transport (tests).
    """

    def __init__(
        self,
        base_url: str,
        api_key: str,
        timeout: float = 30.0,
        *,
        retry: RetryPolicy | None = None,
        transport: httpx.BaseTransport | None = None,
    ) -> None:
        self._core = _Core(base_url, api_key, retry)
        self.timeout = timeout
        self._http = httpx.Client(transport=transport, timeout=timeout)

    def __enter__(self) -> FleetHealthClient:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    def close(self) -> None:
        self._http.close()

    def _send(self, request: _Request) -> JsonObject:
        retry = self._core.retry
        for attempt in range(retry.max_retries + 1):
            last = attempt == retry.max_retries
            retry_after = None
            try:
                response = self._http.request(**self._core.kwargs(request, self.timeout))
            except httpx.TransportError:
                if last:
                    raise
            else:
                status = response.status_code
                if last or status in request.ok_statuses or not retry.should_retry_status(status):
                    return self._core.parse(request, response)
                retry_after = response.headers.get("retry-after")
            time.sleep(retry.delay_s(attempt, retry_after))
        raise AssertionError("unreachable")  # pragma: no cover

    # -- probes -------------------------------------------------------------------------------

    def healthz(self) -> JsonObject:
        return self._send(_Request("GET", "/healthz"))

    def readyz(self) -> JsonObject:
        return self._send(_Request("GET", "/readyz"))

    def readiness(self) -> JsonObject:
        """The ``/readyz`` body whether ready (200) or not yet (503), at once (no retry): its
        ``checks`` say whether telemetry is accepted, ``kernels`` how each kind's warm-up stands."""
        return self._send(_Request("GET", "/readyz", ok_statuses=(200, 503)))

    # -- fleet --------------------------------------------------------------------------------

    def create_aircraft(
        self, tail: str, description: str | None = None, exist_ok: bool = True
    ) -> dict[str, Any]:
        """Register an aircraft; with ``exist_ok`` an existing one is returned instead of a 409."""
        try:
            return self._send(_Core.create_aircraft(tail, description))
        except ApiError as exc:
            if exist_ok and _is_already_exists(exc):
                return self.get_aircraft(tail)
            raise

    def list_aircraft(self) -> list[dict[str, Any]]:
        return _items(self._send(_Request("GET", "/v1/aircraft")))

    def get_aircraft(self, tail: str) -> dict[str, Any]:
        return self._send(_Request("GET", aircraft_path(tail)))

    def create_actuator(
        self,
        tail: str,
        actuator_id: str,
        kind: str = "ema_voltage",
        channels: Sequence[str] | None = None,
        estimators: Mapping[str, Any] | None = None,
        exist_ok: bool = True,
    ) -> dict[str, Any]:
        """Register an actuator; with ``exist_ok`` an existing one is returned instead of a 409."""
        try:
            return self._send(_Core.create_actuator(tail, actuator_id, kind, channels, estimators))
        except ApiError as exc:
            if exist_ok and _is_already_exists(exc):
                return self.get_actuator(tail, actuator_id)
            raise

    def list_actuators(self, tail: str) -> list[dict[str, Any]]:
        return _items(self._send(_Request("GET", f"{aircraft_path(tail)}/actuators")))

    def get_actuator(self, tail: str, actuator_id: str) -> dict[str, Any]:
        return self._send(_Request("GET", actuator_path(tail, actuator_id)))

    # -- telemetry ----------------------------------------------------------------------------

    def post_batch(
        self,
        tail: str,
        actuator_id: str,
        batch_id: str,
        channels: Mapping[str, ArrayLike],
        t_s: ArrayLike | None = None,
        *,
        t0: float | None = None,
        sample_rate_hz: float | None = None,
        fmt: str = "arrow",
        wait_s: float = 0.0,
    ) -> dict[str, Any]:
        """Send one batch; returns the acknowledgement ``{"batch_id", "seq", ...}``.

        Times are either ``t_s`` (seconds, one per sample) or ``t0`` and ``sample_rate_hz``.
        A retried request carries the same ``batch_id``, so the batch is applied once.
        """
        encoded = encode_batch(
            fmt, batch_id, channels, t_s=t_s, t0=t0, sample_rate_hz=sample_rate_hz
        )
        return self.post_encoded(tail, actuator_id, encoded, wait_s=wait_s)

    def post_encoded(
        self, tail: str, actuator_id: str, encoded: EncodedBatch, *, wait_s: float = 0.0
    ) -> dict[str, Any]:
        """Send a batch encoded beforehand with :func:`encode_batch`."""
        return self._send(_Core.post_batch(tail, actuator_id, encoded, wait_s, self.timeout))

    # -- health -------------------------------------------------------------------------------

    def health(self, tail: str, actuator_id: str) -> dict[str, Any]:
        return self._send(_Request("GET", f"{actuator_path(tail, actuator_id)}/health"))

    def health_history(
        self,
        tail: str,
        actuator_id: str,
        estimator: str = "fakf",
        from_s: float | None = None,
        to_s: float | None = None,
        limit: int | None = None,
    ) -> list[dict[str, Any]]:
        request = _Core.health_history(tail, actuator_id, estimator, from_s, to_s, limit)
        return _items(self._send(request))

    def outputs(
        self,
        tail: str,
        actuator_id: str,
        estimator: str = "fakf",
        from_s: float | None = None,
        to_s: float | None = None,
    ) -> dict[str, Any]:
        return self._send(_Core.outputs(tail, actuator_id, estimator, from_s, to_s))

    def rul(
        self,
        tail: str,
        actuator_id: str,
        estimator: str | None = None,
        from_s: float | None = None,
        to_s: float | None = None,
    ) -> dict[str, Any]:
        """Latest RUL prognosis per estimator and those made in [from_s, to_s]."""
        return self._send(_Core.rul(tail, actuator_id, estimator, from_s, to_s))

    def faults(self, tail: str, actuator_id: str) -> dict[str, Any]:
        """Diagnoses, active faults and fault events."""
        return self._send(_Core.faults(tail, actuator_id))

    def fleet_health(self, sort: str = "status") -> dict[str, Any]:
        return self._send(_Request("GET", "/v1/fleet/health", params={"sort": sort}))

    def wait_applied(
        self, tail: str, actuator_id: str, seq: int, timeout_s: float = 30.0, poll_s: float = 0.05
    ) -> dict[str, Any]:
        """Poll the health until ``last_applied_seq >= seq``; return that health.

        Raises:
            TimeoutError: not applied within ``timeout_s``.
        """
        deadline = time.monotonic() + timeout_s
        delay = poll_s
        while True:
            health = self.health(tail, actuator_id)
            applied = health.get("last_applied_seq")
            if applied is not None and applied >= seq:
                return health
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise TimeoutError(
                    f"{tail}/{actuator_id}: seq {seq} not applied within {timeout_s:g} s "
                    f"(last applied {applied})"
                )
            time.sleep(min(delay, remaining))
            delay = min(delay * 1.5, MAX_POLL_S)


# --------------------------------------------------------------------------------------------
# Asynchronous client
# --------------------------------------------------------------------------------------------


class AsyncFleetHealthClient:
    """asyncio twin of :class:`FleetHealthClient` (same methods, awaited).

    Args:
        base_url: e.g. ``"http://127.0.0.1:8000"``.
        api_key: key sent as ``Authorization: Bearer <key>``.
        timeout: seconds for one request.
        retry: retry policy for connection errors and 5xx answers.
        max_connections: connection pool size (bounds concurrency towards the server).
        transport: optional httpx transport (tests).
    """

    def __init__(
        self,
        base_url: str,
        api_key: str,
        timeout: float = 30.0,
        *,
        retry: RetryPolicy | None = None,
        max_connections: int = 32,
        transport: httpx.AsyncBaseTransport | None = None,
    ) -> None:
        self._core = _Core(base_url, api_key, retry)
        self.timeout = timeout
        self._http = httpx.AsyncClient(
            transport=transport,
            timeout=timeout,
            limits=httpx.Limits(
                max_connections=max_connections, max_keepalive_connections=max_connections
            ),
        )

    async def __aenter__(self) -> AsyncFleetHealthClient:
        return self

    async def __aexit__(self, *exc_info: object) -> None:
        await self.aclose()

    async def aclose(self) -> None:
        await self._http.aclose()

    async def _send(self, request: _Request) -> JsonObject:
        retry = self._core.retry
        for attempt in range(retry.max_retries + 1):
            last = attempt == retry.max_retries
            retry_after = None
            try:
                response = await self._http.request(**self._core.kwargs(request, self.timeout))
            except httpx.TransportError:
                if last:
                    raise
            else:
                status = response.status_code
                if last or status in request.ok_statuses or not retry.should_retry_status(status):
                    return self._core.parse(request, response)
                retry_after = response.headers.get("retry-after")
            await asyncio.sleep(retry.delay_s(attempt, retry_after))
        raise AssertionError("unreachable")  # pragma: no cover

    async def healthz(self) -> JsonObject:
        return await self._send(_Request("GET", "/healthz"))

    async def readyz(self) -> JsonObject:
        return await self._send(_Request("GET", "/readyz"))

    async def readiness(self) -> JsonObject:
        return await self._send(_Request("GET", "/readyz", ok_statuses=(200, 503)))

    async def create_aircraft(
        self, tail: str, description: str | None = None, exist_ok: bool = True
    ) -> dict[str, Any]:
        try:
            return await self._send(_Core.create_aircraft(tail, description))
        except ApiError as exc:
            if exist_ok and _is_already_exists(exc):
                return await self.get_aircraft(tail)
            raise

    async def list_aircraft(self) -> list[dict[str, Any]]:
        return _items(await self._send(_Request("GET", "/v1/aircraft")))

    async def get_aircraft(self, tail: str) -> dict[str, Any]:
        return await self._send(_Request("GET", aircraft_path(tail)))

    async def create_actuator(
        self,
        tail: str,
        actuator_id: str,
        kind: str = "ema_voltage",
        channels: Sequence[str] | None = None,
        estimators: Mapping[str, Any] | None = None,
        exist_ok: bool = True,
    ) -> dict[str, Any]:
        try:
            return await self._send(
                _Core.create_actuator(tail, actuator_id, kind, channels, estimators)
            )
        except ApiError as exc:
            if exist_ok and _is_already_exists(exc):
                return await self.get_actuator(tail, actuator_id)
            raise

    async def list_actuators(self, tail: str) -> list[dict[str, Any]]:
        return _items(await self._send(_Request("GET", f"{aircraft_path(tail)}/actuators")))

    async def get_actuator(self, tail: str, actuator_id: str) -> dict[str, Any]:
        return await self._send(_Request("GET", actuator_path(tail, actuator_id)))

    async def post_batch(
        self,
        tail: str,
        actuator_id: str,
        batch_id: str,
        channels: Mapping[str, ArrayLike],
        t_s: ArrayLike | None = None,
        *,
        t0: float | None = None,
        sample_rate_hz: float | None = None,
        fmt: str = "arrow",
        wait_s: float = 0.0,
    ) -> dict[str, Any]:
        encoded = encode_batch(
            fmt, batch_id, channels, t_s=t_s, t0=t0, sample_rate_hz=sample_rate_hz
        )
        return await self.post_encoded(tail, actuator_id, encoded, wait_s=wait_s)

    async def post_encoded(
        self, tail: str, actuator_id: str, encoded: EncodedBatch, *, wait_s: float = 0.0
    ) -> dict[str, Any]:
        return await self._send(_Core.post_batch(tail, actuator_id, encoded, wait_s, self.timeout))

    async def health(self, tail: str, actuator_id: str) -> dict[str, Any]:
        return await self._send(_Request("GET", f"{actuator_path(tail, actuator_id)}/health"))

    async def health_history(
        self,
        tail: str,
        actuator_id: str,
        estimator: str = "fakf",
        from_s: float | None = None,
        to_s: float | None = None,
        limit: int | None = None,
    ) -> list[dict[str, Any]]:
        request = _Core.health_history(tail, actuator_id, estimator, from_s, to_s, limit)
        return _items(await self._send(request))

    async def outputs(
        self,
        tail: str,
        actuator_id: str,
        estimator: str = "fakf",
        from_s: float | None = None,
        to_s: float | None = None,
    ) -> dict[str, Any]:
        return await self._send(_Core.outputs(tail, actuator_id, estimator, from_s, to_s))

    async def rul(
        self,
        tail: str,
        actuator_id: str,
        estimator: str | None = None,
        from_s: float | None = None,
        to_s: float | None = None,
    ) -> dict[str, Any]:
        """Latest RUL prognosis per estimator and those made in [from_s, to_s]."""
        return await self._send(_Core.rul(tail, actuator_id, estimator, from_s, to_s))

    async def faults(self, tail: str, actuator_id: str) -> dict[str, Any]:
        """Diagnoses, active faults and fault events."""
        return await self._send(_Core.faults(tail, actuator_id))

    async def fleet_health(self, sort: str = "status") -> dict[str, Any]:
        return await self._send(_Request("GET", "/v1/fleet/health", params={"sort": sort}))

    async def wait_applied(
        self, tail: str, actuator_id: str, seq: int, timeout_s: float = 30.0, poll_s: float = 0.05
    ) -> dict[str, Any]:
        deadline = time.monotonic() + timeout_s
        delay = poll_s
        while True:
            health = await self.health(tail, actuator_id)
            applied = health.get("last_applied_seq")
            if applied is not None and applied >= seq:
                return health
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise TimeoutError(
                    f"{tail}/{actuator_id}: seq {seq} not applied within {timeout_s:g} s "
                    f"(last applied {applied})"
                )
            await asyncio.sleep(min(delay, remaining))
            delay = min(delay * 1.5, MAX_POLL_S)
