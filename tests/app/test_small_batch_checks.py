"""A small batch's checks are first tried in plain Python (app.ingest._validate,
app.telemetry.validation.check_times / check_values); whatever that quick test lets through or
sends on, a batch is refused exactly as a large one is, with the same message."""

from __future__ import annotations

import math

import numpy as np
import pyarrow as pa
import pytest

from app.errors import InvalidBatch
from app.ingest import (
    ARROW_TYPES,
    SMALL_CHECK_MAX,
    SMALL_LIST_MAX,
    ParsedBatch,
    TimeParams,
    parse_body,
)
from app.telemetry.validation import BatchLimits, _bounds, check_batch

NOW_S = 1.8e9
LIMITS = BatchLimits(max_abs_value=1e6, max_time_s=1e10, max_future_s=60.0)
SMALL = 10
LARGE = max(SMALL_LIST_MAX, SMALL_CHECK_MAX) + 36


def _arrow(t: np.ndarray, a: np.ndarray, b: np.ndarray) -> bytes:
    table = pa.table({"t": t, "a": a, "b": b})
    sink = pa.BufferOutputStream()
    with pa.ipc.new_stream(sink, table.schema) as writer:
        writer.write_table(table)
    return bytes(sink.getvalue().to_pybytes())


def _outcome(n: int, fault: str) -> str:
    """``"ok"`` or the refusal's message for a batch of ``n`` samples with ``fault`` at index 3."""
    t = 1000.0 + np.arange(n) / 100.0
    a = np.sin(np.arange(n, dtype=np.float64))
    b = np.cos(np.arange(n, dtype=np.float64))
    k = 3
    if fault == "t nan":
        t[k] = math.nan
    elif fault == "t inf":
        t[-1] = math.inf
    elif fault == "t -inf first":
        t[0] = -math.inf
    elif fault == "t repeats":
        t[k] = t[k - 1]
    elif fault == "t goes back":
        t[k] = t[k - 1] - 0.5
    elif fault == "value inf":
        b[k] = -math.inf
    elif fault == "value over":
        a[k] = 2e6
    elif fault == "nan then over":
        a[0], a[k] = math.nan, -2e6
    elif fault == "nan samples":
        a[0], b[k] = math.nan, math.nan
    elif fault == "t out of range":
        t += 2e10
    elif fault == "t ahead":
        t += NOW_S + 3600.0
    elif fault == "t epoch now":
        t += NOW_S - 2000.0
    try:
        parsed: ParsedBatch = parse_body(_arrow(t, a, b), ARROW_TYPES[0], TimeParams("b1", None, None),
                                         ["a", "b"], 10_000)
        check_batch(parsed, LIMITS, now_s=NOW_S)
    except InvalidBatch as exc:
        return str(exc)
    return "ok"


FAULTS = ["none", "nan samples", "t epoch now", "t nan", "t inf", "t -inf first", "t repeats",
          "t goes back", "value inf", "value over", "nan then over", "t out of range", "t ahead"]


@pytest.mark.parametrize("fault", FAULTS)
def test_a_small_batch_is_refused_as_a_large_one(fault: str) -> None:
    small, large = _outcome(SMALL, fault), _outcome(LARGE, fault)
    if fault in ("none", "nan samples", "t epoch now"):
        assert small == large == "ok"
    else:
        assert small != "ok"
        # The message names the position and value, which are those of both sizes but the
        # last time (t inf is at the end) and the shifted times.
        if fault not in ("t inf", "t out of range", "t ahead"):
            assert small == large
        else:
            assert large != "ok" and small.split("[")[0] == large.split("[")[0]


def test_the_named_faults() -> None:
    assert _outcome(SMALL, "t nan") == "t[3] is not a finite number"
    assert _outcome(SMALL, "t -inf first") == "t[0] is not a finite number"
    assert _outcome(SMALL, "t repeats").startswith("timestamps must increase strictly: t[3]=")
    assert _outcome(SMALL, "value inf") == "channel 'b' holds an infinite value at index 3"
    assert _outcome(SMALL, "nan then over").startswith("channel 'a' value -2000000.0 at index 3 exceeds")
    assert "FLEETHEALTH_MAX_TIME_S" in _outcome(SMALL, "t out of range")
    assert "FLEETHEALTH_MAX_FUTURE_S" in _outcome(SMALL, "t ahead")


@pytest.mark.parametrize(
    ("values", "expected"),
    [([1.0], (1.0, 1.0)), ([3.0, -2.0, 5.0], (-2.0, 5.0)), ([2.0, math.nan, -7.0, 9.0], (-7.0, 9.0))],
)
def test_bounds_of_values(values: list[float], expected: tuple[float, float]) -> None:
    assert _bounds(values) == expected


def test_bounds_with_a_leading_nan_fail_every_comparison() -> None:
    lo, hi = _bounds([math.nan, 1e30, -1e30])
    assert not (lo >= -1.0) and not (hi <= 1.0)


def test_a_record_batch_header_is_read_once_per_shape_and_a_bad_one_always_refused() -> None:
    from app.ingest import _record_batch_header

    t = 1000.0 + np.arange(SMALL) / 100.0
    reader = pa.ipc.MessageReader.open_stream(pa.py_buffer(_arrow(t, t, t)))
    reader.read_next_message()  # the schema
    metadata = reader.read_next_message().metadata.to_pybytes()
    first = _record_batch_header(metadata)
    hits = _record_batch_header.cache_info().hits
    assert _record_batch_header(bytes(bytearray(metadata))) == first  # equal bytes, another object
    assert _record_batch_header.cache_info().hits == hits + 1
    assert first[:2] == (3, SMALL) and len(first[2]) == 6 and not first[3]
    for _ in range(2):
        with pytest.raises(ValueError, match="out of range"):
            _record_batch_header(metadata[:12])
