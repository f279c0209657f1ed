"""HTTP client for the fleethealth API (synchronous and asyncio).

Usage::

    from app.client import FleetHealthClient

    with FleetHealthClient("http://127.0.0.1:8000", api_key) as client:
        client.create_aircraft("FH-001")
        client.create_actuator("FH-001", "ema-left")
        ack = client.post_batch(
            "FH-001", "ema-left", "b-0001",
            {"current": current_a, "voltage": voltage_v},
            t0=1283532701.0, sample_rate_hz=100.0, fmt="arrow",
        )
        health = client.wait_applied("FH-001", "ema-left", ack["seq"], timeout_s=30)

Telemetry encodings (the body of ``POST .../telemetry``):

* ``json``  -- ``{"batch_id", "t" | "t0" + "sample_rate_hz", "channels": {name: [...]}}``, NaN
  written as ``null``.
* ``csv``   -- header row of column names (``t`` first when times are given), one row per sample,
  an empty cell for NaN; batch id, ``t0`` and ``sample_rate_hz`` go in the query string.
* ``arrow`` -- an Arrow IPC stream of float64 columns (``t`` first when given), NaN kept as a
  float NaN; batch id, ``t0`` and ``sample_rate_hz`` go in the query string.

Infinite values are refused before sending (the server would answer 400 for them, and JSON has no
way to write them).

Retries: connection errors, timeouts, 429 and 5xx answers are retried a bounded number of times with
exponential backoff, always with the same request (and so the same batch id): the server applies a
batch id once and answers a repeat with the first answer. 4xx answers raise :class:`ApiError` at once.
"""

from __future__ import annotations

import asyncio
import io
import math
import random
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, cast
from urllib.parse import quote

import httpx
import numpy as np
import orjson
import pyarrow as pa
import pyarrow.csv as pa_csv
from numpy.typing import ArrayLike, NDArray

__all__ = [
    "ARROW_STREAM_MEDIA_TYPE",
    "ApiError",
    "AsyncFleetHealthClient",
    "EncodedBatch",
    "FleetHealthClient",
    "RetryPolicy",
    "encode_batch",
    "encode_batch_arrow",
    "encode_batch_csv",
    "encode_batch_json",
]

ARROW_STREAM_MEDIA_TYPE = "application/vnd.apache.arrow.stream"
BATCH_FORMATS: tuple[str, ...] = ("arrow", "json", "csv")
USER_AGENT = "fleethealth-client/0.1"
MAX_SERVER_WAIT_S = 60.0

FloatArray = NDArray[np.float64]
JsonObject = dict[str, Any]


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
        error, detail = "HTTPError", response.text[:500]
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


@dataclass(frozen=True)
class RetryPolicy:
    """Bounded retries with exponential backoff and jitter.

    Attributes:
        max_retries: retries after the first attempt (0 disables retries).
        backoff_s: delay before the first retry; doubled for each further one.
        max_backoff_s: cap on one delay.
        retry_statuses: HTTP statuses answered by retrying.
    """

    max_retries: int = 4
    backoff_s: float = 0.2
    max_backoff_s: float = 5.0
    retry_statuses: frozenset[int] = field(default_factory=lambda: frozenset({429, 502, 503, 504}))

    def delay_s(self, attempt: int) -> float:
        """Delay before retry number ``attempt`` (0-based), with +-50 % jitter."""
        base = min(self.max_backoff_s, self.backoff_s * (2.0**attempt))
        return base * (0.5 + random.random())

    def should_retry_status(self, status: int) -> bool:
        return status in self.retry_statuses or status >= 500


@dataclass(frozen=True)
class EncodedBatch:
    """A telemetry batch ready to send: body, content type and query parameters."""

    content: bytes
    content_type: str
    params: dict[str, str]


# --------------------------------------------------------------------------------------------
# Encoders
# --------------------------------------------------------------------------------------------


def _as_float_columns(
    channels: Mapping[str, ArrayLike], t_s: ArrayLike | None
) -> tuple[FloatArray | None, dict[str, FloatArray]]:
    if not channels:
        raise ValueError("a batch needs at least one channel")
    columns: dict[str, FloatArray] = {}
    for name, values in channels.items():
        if not name or name == "t" or any(c in name for c in ',"\r\n'):
            raise ValueError(f"invalid channel name {name!r}")
        arr = np.ascontiguousarray(values, dtype=np.float64)
        if arr.ndim != 1:
            raise ValueError(f"channel {name!r} must be one-dimensional, got shape {arr.shape}")
        if np.isinf(arr).any():
            raise ValueError(f"channel {name!r} holds infinite values (use NaN for missing)")
        columns[name] = arr
    lengths = {arr.shape[0] for arr in columns.values()}
    t_arr: FloatArray | None = None
    if t_s is not None:
        t_arr = np.ascontiguousarray(t_s, dtype=np.float64)
        if t_arr.ndim != 1:
            raise ValueError(f"t_s must be one-dimensional, got shape {t_arr.shape}")
        if not np.isfinite(t_arr).all():
            raise ValueError("t_s must be finite")
        lengths.add(t_arr.shape[0])
    if len(lengths) != 1:
        raise ValueError(f"channels (and t_s) have unequal lengths: {sorted(lengths)}")
    return t_arr, columns


def _time_params(
    t_arr: FloatArray | None, t0: float | None, sample_rate_hz: float | None
) -> dict[str, float]:
    if t_arr is not None:
        if t0 is not None or sample_rate_hz is not None:
            raise ValueError("give either t_s or t0 and sample_rate_hz, not both")
        return {}
    if t0 is None or sample_rate_hz is None:
        raise ValueError("give t_s, or both t0 and sample_rate_hz")
    if not (math.isfinite(t0) and math.isfinite(sample_rate_hz) and sample_rate_hz > 0):
        raise ValueError("t0 must be finite and sample_rate_hz positive")
    return {"t0": float(t0), "sample_rate_hz": float(sample_rate_hz)}


def _query_params(batch_id: str, time_params: Mapping[str, float]) -> dict[str, str]:
    params = {"batch_id": batch_id}
    # repr gives the shortest string that reads back to the same float.
    params.update({key: repr(value) for key, value in time_params.items()})
    return params


def _table_columns(
    channels: Mapping[str, ArrayLike],
    t_s: ArrayLike | None,
    t0: float | None,
    sample_rate_hz: float | None,
) -> tuple[list[str], list[FloatArray], dict[str, float]]:
    """Column names and arrays of a table body (``t`` first when given), and the time params."""
    t_arr, columns = _as_float_columns(channels, t_s)
    time_params = _time_params(t_arr, t0, sample_rate_hz)
    names = (["t"] if t_arr is not None else []) + list(columns)
    arrays = ([t_arr] if t_arr is not None else []) + list(columns.values())
    return names, arrays, time_params


def encode_batch_json(
    batch_id: str,
    channels: Mapping[str, ArrayLike],
    *,
    t_s: ArrayLike | None = None,
    t0: float | None = None,
    sample_rate_hz: float | None = None,
) -> EncodedBatch:
    """JSON body ``{"batch_id", "t" | "t0"+"sample_rate_hz", "channels"}``; NaN becomes null."""
    t_arr, columns = _as_float_columns(channels, t_s)
    body: dict[str, Any] = {"batch_id": batch_id}
    if t_arr is not None:
        body["t"] = t_arr
    body.update(_time_params(t_arr, t0, sample_rate_hz))
    body["channels"] = columns
    # orjson writes NaN as null, also inside numpy arrays.
    content = orjson.dumps(body, option=orjson.OPT_SERIALIZE_NUMPY)
    return EncodedBatch(content, "application/json", {})


def encode_batch_csv(
    batch_id: str,
    channels: Mapping[str, ArrayLike],
    *,
    t_s: ArrayLike | None = None,
    t0: float | None = None,
    sample_rate_hz: float | None = None,
) -> EncodedBatch:
    """CSV with a header row (``t`` first when given) and an empty cell for each NaN."""
    names, arrays, time_params = _table_columns(channels, t_s, t0, sample_rate_hz)
    # from_pandas=True turns NaN into null, which the CSV writer leaves as an empty cell.
    table = pa.table(
        [pa.array(arr, type=pa.float64(), from_pandas=True) for arr in arrays], names=names
    )
    sink = io.BytesIO()
    sink.write((",".join(names) + "\n").encode())
    pa_csv.write_csv(table, sink, pa_csv.WriteOptions(include_header=False))
    return EncodedBatch(sink.getvalue(), "text/csv", _query_params(batch_id, time_params))


def encode_batch_arrow(
    batch_id: str,
    channels: Mapping[str, ArrayLike],
    *,
    t_s: ArrayLike | None = None,
    t0: float | None = None,
    sample_rate_hz: float | None = None,
) -> EncodedBatch:
    """Arrow IPC stream, one record batch of float64 columns (``t`` first when given)."""
    names, arrays, time_params = _table_columns(channels, t_s, t0, sample_rate_hz)
    record_batch = pa.record_batch(
        [pa.array(arr, type=pa.float64()) for arr in arrays], names=names
    )
    sink = pa.BufferOutputStream()
    with pa.ipc.new_stream(sink, record_batch.schema) as writer:
        writer.write_batch(record_batch)
    return EncodedBatch(
        sink.getvalue().to_pybytes(),
        ARROW_STREAM_MEDIA_TYPE,
        _query_params(batch_id, time_params),
    )


_ENCODERS = {"json": encode_batch_json, "csv": encode_batch_csv, "arrow": encode_batch_arrow}


def encode_batch(
    fmt: str,
    batch_id: str,
    channels: Mapping[str, ArrayLike],
    *,
    t_s: ArrayLike | None = None,
    t0: float | None = None,
    sample_rate_hz: float | None = None,
) -> EncodedBatch:
    """Encode a batch in ``fmt`` (``"arrow"``, ``"json"`` or ``"csv"``)."""
    try:
        encoder = _ENCODERS[fmt]
    except KeyError:
        raise ValueError(f"unknown format {fmt!r}; use one of {', '.join(BATCH_FORMATS)}") from None
    if not batch_id:
        raise ValueError("batch_id must not be empty")
    return encoder(batch_id, channels, t_s=t_s, t0=t0, sample_rate_hz=sample_rate_hz)


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


def _actuator_path(tail: str, actuator_id: str) -> str:
    return f"/v1/aircraft/{_seg(tail)}/actuators/{_seg(actuator_id)}"


def _seg(value: str) -> str:
    return quote(value, safe="")


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
        return _Request("POST", f"/v1/aircraft/{_seg(tail)}/actuators", json=body)

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
            f"{_actuator_path(tail, actuator_id)}/telemetry",
            content=encoded.content,
            content_type=encoded.content_type,
            params=params,
            # The server may hold the answer for up to wait_s: never time out before it.
            timeout_s=max(timeout_s, wait_s + 10.0),
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
            {"estimator": estimator, "from_s": from_s, "to_s": to_s, "limit": limit}
        )
        return _Request("GET", f"{_actuator_path(tail, actuator_id)}/health/history", params=params)

    @staticmethod
    def outputs(
        tail: str, actuator_id: str, estimator: str, from_s: float | None, to_s: float | None
    ) -> _Request:
        params = _drop_none({"estimator": estimator, "from_s": from_s, "to_s": to_s})
        return _Request("GET", f"{_actuator_path(tail, actuator_id)}/outputs", params=params)

    @staticmethod
    def rul(
        tail: str, actuator_id: str, estimator: str | None, from_s: float | None, to_s: float | None
    ) -> _Request:
        params = _drop_none({"estimator": estimator, "from_s": from_s, "to_s": to_s})
        return _Request("GET", f"{_actuator_path(tail, actuator_id)}/rul", params=params)

    @staticmethod
    def faults(tail: str, actuator_id: str) -> _Request:
        return _Request("GET", f"{_actuator_path(tail, actuator_id)}/faults")

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
    return exc.status == 409


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
            try:
                response = self._http.request(**self._core.kwargs(request, self.timeout))
            except httpx.TransportError:
                if last:
                    raise
            else:
                if last or not retry.should_retry_status(response.status_code):
                    return self._core.parse(request, response)
            time.sleep(retry.delay_s(attempt))
        raise AssertionError("unreachable")  # pragma: no cover

    # -- probes -------------------------------------------------------------------------------

    def healthz(self) -> JsonObject:
        return self._send(_Request("GET", "/healthz"))

    def readyz(self) -> JsonObject:
        return self._send(_Request("GET", "/readyz"))

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
        return self._send(_Request("GET", f"/v1/aircraft/{_seg(tail)}"))

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
        return _items(self._send(_Request("GET", f"/v1/aircraft/{_seg(tail)}/actuators")))

    def get_actuator(self, tail: str, actuator_id: str) -> dict[str, Any]:
        return self._send(_Request("GET", _actuator_path(tail, actuator_id)))

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
        return self._send(_Request("GET", f"{_actuator_path(tail, actuator_id)}/health"))

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
            delay = min(delay * 1.5, 1.0)


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
            try:
                response = await self._http.request(**self._core.kwargs(request, self.timeout))
            except httpx.TransportError:
                if last:
                    raise
            else:
                if last or not retry.should_retry_status(response.status_code):
                    return self._core.parse(request, response)
            await asyncio.sleep(retry.delay_s(attempt))
        raise AssertionError("unreachable")  # pragma: no cover

    async def healthz(self) -> JsonObject:
        return await self._send(_Request("GET", "/healthz"))

    async def readyz(self) -> JsonObject:
        return await self._send(_Request("GET", "/readyz"))

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
        return await self._send(_Request("GET", f"/v1/aircraft/{_seg(tail)}"))

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
        return _items(await self._send(_Request("GET", f"/v1/aircraft/{_seg(tail)}/actuators")))

    async def get_actuator(self, tail: str, actuator_id: str) -> dict[str, Any]:
        return await self._send(_Request("GET", _actuator_path(tail, actuator_id)))

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
        return await self._send(_Request("GET", f"{_actuator_path(tail, actuator_id)}/health"))

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
            delay = min(delay * 1.5, 1.0)
