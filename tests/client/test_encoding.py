"""The client's telemetry encoders and its retry / error handling (no server needed)."""

from __future__ import annotations

import csv
import io
import sys
from urllib.parse import parse_qs

import httpx
import numpy as np
import orjson
import pyarrow as pa
import pyarrow.csv as pa_csv
import pytest
from fleethealth_client import (
    ARROW_STREAM_MEDIA_TYPE,
    ApiError,
    AsyncFleetHealthClient,
    FleetHealthClient,
    RetryPolicy,
    encode_batch,
    encode_frame,
)

NO_WAIT_RETRY = RetryPolicy(max_retries=3, backoff_s=0.0, max_backoff_s=0.0)


def _channels(seed: int, n: int = 257) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    rng = np.random.default_rng(seed)
    t = 1283532701.0 + np.arange(n) * 0.01 + rng.uniform(0, 1e-4, n)
    current = rng.normal(0.0, 2.0, n)
    voltage = rng.normal(0.0, 10.0, n) * 10.0 ** rng.integers(-12, 12, n)
    current[rng.choice(n, 7, replace=False)] = np.nan
    voltage[[0, n - 1]] = np.nan
    return t, {"current": current, "voltage": voltage}


def _assert_same(decoded: np.ndarray, expected: np.ndarray) -> None:
    # NaN in the same places, every other value bit-exact.
    np.testing.assert_array_equal(np.isnan(decoded), np.isnan(expected))
    np.testing.assert_array_equal(decoded, expected)


def _from_json(values: list[float | None]) -> np.ndarray:
    return np.array([np.nan if v is None else v for v in values], dtype=np.float64)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_json_round_trip_with_times(seed: int) -> None:
    t, channels = _channels(seed)
    encoded = encode_batch("json", "b-1", channels, t_s=t)
    assert encoded.content_type == "application/json"
    assert encoded.params == {}
    body = orjson.loads(encoded.content)
    assert body["batch_id"] == "b-1"
    assert "t0" not in body and "sample_rate_hz" not in body
    _assert_same(np.array(body["t"]), t)
    assert list(body["channels"]) == ["current", "voltage"]
    for name, values in channels.items():
        assert None in body["channels"][name]
        _assert_same(_from_json(body["channels"][name]), values)


def test_json_nan_is_null_and_t0_rate() -> None:
    encoded = encode_batch(
        "json", "b-2", {"current": [1.0, np.nan, 3.0]}, t0=1283532701.0, sample_rate_hz=100.0
    )
    assert b"NaN" not in encoded.content and b"nan" not in encoded.content
    body = orjson.loads(encoded.content)
    assert body == {
        "batch_id": "b-2",
        "t0": 1283532701.0,
        "sample_rate_hz": 100.0,
        "channels": {"current": [1.0, None, 3.0]},
    }


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_csv_round_trip_with_times(seed: int) -> None:
    t, channels = _channels(seed)
    encoded = encode_batch("csv", "b-3", channels, t_s=t)
    assert encoded.content_type == "text/csv"
    assert encoded.params == {"batch_id": "b-3"}
    text = encoded.content.decode()
    assert text.splitlines()[0] == "t,current,voltage"
    assert "nan" not in text.lower()
    table = pa_csv.read_csv(
        io.BytesIO(encoded.content),
        convert_options=pa_csv.ConvertOptions(
            column_types={name: pa.float64() for name in ("t", "current", "voltage")}
        ),
    )
    assert table.column_names == ["t", "current", "voltage"]
    _assert_same(table.column("t").to_numpy(), t)
    for name, values in channels.items():
        assert table.column(name).null_count == int(np.isnan(values).sum())
        decoded = table.column(name).to_numpy(zero_copy_only=False)
        _assert_same(decoded, values)


def test_csv_missing_cells_are_empty_and_time_goes_to_query() -> None:
    encoded = encode_batch(
        "csv",
        "b-4",
        {"current": [1.5, np.nan, -2.0], "voltage": [np.nan, 0.25, 1e-300]},
        t0=1283532701.01,
        sample_rate_hz=100.0,
    )
    rows = list(csv.reader(io.StringIO(encoded.content.decode())))
    assert rows == [["current", "voltage"], ["1.5", ""], ["", "0.25"], ["-2", "1e-300"]]
    assert encoded.params == {"batch_id": "b-4", "t0": "1283532701.01", "sample_rate_hz": "100.0"}
    assert float(encoded.params["t0"]) == 1283532701.01


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_arrow_round_trip_with_times(seed: int) -> None:
    t, channels = _channels(seed)
    encoded = encode_batch("arrow", "b-5", channels, t_s=t)
    assert encoded.content_type == ARROW_STREAM_MEDIA_TYPE
    assert encoded.params == {"batch_id": "b-5"}
    table = pa.ipc.open_stream(encoded.content).read_all()
    assert table.column_names == ["t", "current", "voltage"]
    assert all(field.type == pa.float64() for field in table.schema)
    _assert_same(table.column("t").to_numpy(), t)
    for name, values in channels.items():
        # NaN travels as a float NaN, not as a null: the column converts without a copy.
        assert table.column(name).null_count == 0
        _assert_same(table.column(name).to_numpy(), values)


def test_arrow_without_times_puts_t0_in_query() -> None:
    encoded = encode_batch(
        "arrow", "b-6", {"current": np.arange(4.0)}, t0=10.0, sample_rate_hz=1000.0
    )
    table = pa.ipc.open_stream(encoded.content).read_all()
    assert table.column_names == ["current"]
    assert encoded.params == {"batch_id": "b-6", "t0": "10.0", "sample_rate_hz": "1000.0"}


@pytest.mark.parametrize(
    ("channels", "kwargs", "message"),
    [
        ({"current": [1.0, 2.0]}, {}, "give t_s"),
        ({"current": [1.0, 2.0]}, {"t_s": [0.0, 1.0], "t0": 0.0}, "not both"),
        ({"current": [1.0, 2.0]}, {"t_s": [0.0]}, "unequal lengths"),
        ({"current": [1.0], "voltage": [1.0, 2.0]}, {"t_s": [0.0]}, "unequal lengths"),
        ({"current": [1.0, np.inf]}, {"t_s": [0.0, 1.0]}, "infinite"),
        ({"current": [1.0, 2.0]}, {"t_s": [0.0, np.nan]}, "finite"),
        ({"a,b": [1.0]}, {"t_s": [0.0]}, "invalid channel name"),
        ({"t": [1.0]}, {"t_s": [0.0]}, "invalid channel name"),
        ({}, {"t_s": [0.0]}, "at least one channel"),
        ({"current": [1.0]}, {"t0": 0.0, "sample_rate_hz": 0.0}, "positive"),
    ],
)
@pytest.mark.parametrize("fmt", ["json", "csv", "arrow"])
def test_invalid_batches_are_refused_before_sending(
    fmt: str, channels: dict, kwargs: dict, message: str
) -> None:
    with pytest.raises(ValueError, match=message):
        encode_batch(fmt, "b", channels, **kwargs)


def test_unknown_format_is_refused() -> None:
    with pytest.raises(ValueError, match="unknown format"):
        encode_batch("parquet", "b", {"current": [1.0]}, t_s=[0.0])


# ---------------------------------------------------------------------------------------------
# Retries and errors, against an in-process transport
# ---------------------------------------------------------------------------------------------


class _FlakyServer:
    """Fails the first ``failures`` telemetry posts (503, or a dropped connection), then acks."""

    def __init__(self, failures: int, drop_connection: bool = False) -> None:
        self.failures = failures
        self.drop_connection = drop_connection
        self.seen_batch_ids: list[str] = []
        self.seen_auth: list[str | None] = []

    def __call__(self, request: httpx.Request) -> httpx.Response:
        self.seen_auth.append(request.headers.get("authorization"))
        batch_id = parse_qs(request.url.query.decode())["batch_id"][0]
        self.seen_batch_ids.append(batch_id)
        if len(self.seen_batch_ids) <= self.failures:
            if self.drop_connection:
                raise httpx.ConnectError("connection refused", request=request)
            return httpx.Response(503, json={"error": "Unavailable", "detail": "try again"})
        return httpx.Response(202, json={"batch_id": batch_id, "seq": 7, "n_samples": 2})


@pytest.mark.parametrize("drop_connection", [False, True])
def test_post_batch_retries_with_same_batch_id(drop_connection: bool) -> None:
    server = _FlakyServer(failures=2, drop_connection=drop_connection)
    with FleetHealthClient(
        "http://fh.test", "secret", retry=NO_WAIT_RETRY, transport=httpx.MockTransport(server)
    ) as client:
        ack = client.post_batch(
            "FH-001", "ema-1", "b-42", {"current": [1.0, 2.0]}, t_s=[0.0, 0.01], fmt="csv"
        )
    assert ack["seq"] == 7
    assert server.seen_batch_ids == ["b-42", "b-42", "b-42"]
    assert server.seen_auth == ["Bearer secret"] * 3


def test_retries_are_bounded() -> None:
    server = _FlakyServer(failures=100)
    with (
        FleetHealthClient(
            "http://fh.test", "k", retry=NO_WAIT_RETRY, transport=httpx.MockTransport(server)
        ) as client,
        pytest.raises(ApiError) as excinfo,
    ):
        client.post_batch("FH-001", "ema-1", "b-1", {"current": [1.0]}, t_s=[0.0], fmt="arrow")
    assert excinfo.value.status == 503
    assert len(server.seen_batch_ids) == NO_WAIT_RETRY.max_retries + 1


def test_client_error_raises_typed_api_error_without_retry() -> None:
    calls: list[httpx.Request] = []

    def handler(request: httpx.Request) -> httpx.Response:
        calls.append(request)
        return httpx.Response(409, json={"error": "StaleBatch", "detail": "starts before t=5"})

    with (
        FleetHealthClient(
            "http://fh.test", "k", retry=NO_WAIT_RETRY, transport=httpx.MockTransport(handler)
        ) as client,
        pytest.raises(ApiError) as excinfo,
    ):
        client.post_batch("FH-001", "ema-1", "b-1", {"current": [1.0]}, t_s=[0.0], fmt="json")
    assert (excinfo.value.status, excinfo.value.error, excinfo.value.detail) == (
        409,
        "StaleBatch",
        "starts before t=5",
    )
    assert len(calls) == 1


def test_create_aircraft_exist_ok_returns_existing() -> None:
    def handler(request: httpx.Request) -> httpx.Response:
        if request.method == "POST":
            return httpx.Response(409, json={"error": "AlreadyExists", "detail": "FH-001"})
        return httpx.Response(200, json={"tail": "FH-001", "description": "old"})

    with FleetHealthClient("http://fh.test", "k", transport=httpx.MockTransport(handler)) as client:
        assert client.create_aircraft("FH-001")["description"] == "old"
        with pytest.raises(ApiError, match="AlreadyExists"):
            client.create_aircraft("FH-001", exist_ok=False)


def test_wait_applied_polls_until_sequence_is_applied() -> None:
    applied = iter([None, 1, 2, 3])

    def handler(request: httpx.Request) -> httpx.Response:
        assert request.url.raw_path == b"/v1/aircraft/FH%2F1/actuators/ema-1/health"
        return httpx.Response(200, json={"last_applied_seq": next(applied), "status": "ok"})

    with FleetHealthClient("http://fh.test", "k", transport=httpx.MockTransport(handler)) as client:
        health = client.wait_applied("FH/1", "ema-1", seq=3, timeout_s=10.0, poll_s=0.0)
    assert health["last_applied_seq"] == 3


def test_async_client_posts_same_body_as_sync() -> None:
    import asyncio

    bodies: list[tuple[str, bytes, str]] = []

    def handler(request: httpx.Request) -> httpx.Response:
        bodies.append((request.headers["content-type"], request.content, str(request.url)))
        return httpx.Response(202, json={"batch_id": "b-1", "seq": 1})

    t, channels = _channels(3, n=50)
    with FleetHealthClient("http://fh.test", "k", transport=httpx.MockTransport(handler)) as sync:
        sync.post_batch("FH-001", "ema-1", "b-1", channels, t_s=t, fmt="arrow", wait_s=2.5)

    async def post_async() -> dict:
        async with AsyncFleetHealthClient(
            "http://fh.test", "k", transport=httpx.MockTransport(handler)
        ) as client:
            return await client.post_batch(
                "FH-001", "ema-1", "b-1", channels, t_s=t, fmt="arrow", wait_s=2.5
            )

    assert asyncio.run(post_async())["seq"] == 1
    assert bodies[0] == bodies[1]
    assert bodies[0][0] == ARROW_STREAM_MEDIA_TYPE
    assert "wait=2.5" in bodies[0][2] and "batch_id=b-1" in bodies[0][2]


@pytest.mark.parametrize("fmt", ["arrow", "csv"])
def test_arrow_and_csv_without_pyarrow_say_what_to_install(
    fmt: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    # None in sys.modules makes ``import pyarrow`` fail as if it were not installed.
    monkeypatch.setitem(sys.modules, "pyarrow", None)
    with pytest.raises(ImportError, match=r'pip install "fleethealth-client\[arrow\]"'):
        encode_batch(fmt, "b-1", {"current": [1.0]}, t_s=[0.0])
    with pytest.raises(ImportError, match="binary frame needs pyarrow"):
        encode_frame(1, {"current": [1.0]}, t_s=[0.0], binary=True)
    # Invalid batches are still refused for what they are, before pyarrow is asked for.
    with pytest.raises(ValueError, match="infinite"):
        encode_batch(fmt, "b-1", {"current": [np.inf]}, t_s=[0.0])
    body = orjson.loads(encode_batch("json", "b-1", {"current": [np.nan]}, t_s=[0.0]).content)
    assert body["channels"] == {"current": [None]}
