"""Turn a request body (JSON, CSV or Arrow IPC) into a validated block of samples.

Missing samples are data: ``null`` in JSON, an empty cell or ``NaN`` in CSV, a null or NaN in
Arrow all become NaN, which the estimators predict through. Everything else that is not a finite
number is refused with :class:`~app.errors.InvalidBatch` naming the channel and position.
"""

from __future__ import annotations

import hashlib
import io
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import orjson
import pyarrow as pa
import pyarrow.csv as pacsv

from app.errors import InvalidBatch, UnsupportedMediaType

JSON_TYPES = ("application/json",)
CSV_TYPES = ("text/csv",)
ARROW_TYPES = ("application/vnd.apache.arrow.stream",)
SUPPORTED_TYPES = JSON_TYPES + CSV_TYPES + ARROW_TYPES
TIME_COLUMN = "t"
MAX_BATCH_ID_LEN = 128


@dataclass(frozen=True)
class ParsedBatch:
    """A validated block of samples; ``end_of_run`` marks the last batch of a run."""

    batch_id: str
    t_s: np.ndarray
    channels: dict[str, np.ndarray]
    end_of_run: bool = False

    @property
    def n_samples(self) -> int:
        return int(self.t_s.shape[0])

    def content_hash(self) -> str:
        """Digest of the decoded samples, so a retry in another format or spacing still matches."""
        h = hashlib.blake2b(digest_size=16)
        h.update(np.ascontiguousarray(self.t_s).tobytes())
        for name in sorted(self.channels):
            h.update(name.encode())
            h.update(np.ascontiguousarray(self.channels[name]).tobytes())
        if self.end_of_run:
            # Part of the batch's identity; only when set, so digests of batches logged before
            # the marker existed stay the same.
            h.update(b"\x00end_of_run")
        return h.hexdigest()


@dataclass(frozen=True)
class TimeParams:
    batch_id: str | None
    t0: float | None
    sample_rate_hz: float | None
    end_of_run: bool = False


def media_type(content_type: str | None) -> str:
    mt = (content_type or "").split(";")[0].strip().lower()
    if mt not in SUPPORTED_TYPES:
        raise UnsupportedMediaType(
            f"content type {mt or '(none)'!r} is not supported; use one of "
            + ", ".join(SUPPORTED_TYPES)
        )
    return mt


def parse_body(
    body: bytes, mt: str, params: TimeParams, expected_channels: Sequence[str], max_samples: int
) -> ParsedBatch:
    if not body:
        raise InvalidBatch("empty body")
    end_of_run = params.end_of_run
    if mt in JSON_TYPES:
        doc = _json_object(body)
        batch_id, t_s, columns = _parse_json_doc(doc, params)
        end_of_run = _end_of_run(doc.get("end_of_run", end_of_run))
    elif mt in CSV_TYPES:
        batch_id, t_s, columns = _parse_table(_read_csv(body), params)
    else:
        batch_id, t_s, columns = _parse_table(_read_arrow(body), params)
    return _validate(batch_id, t_s, columns, expected_channels, max_samples, end_of_run)


def _end_of_run(value: Any) -> bool:
    if not isinstance(value, bool):
        raise InvalidBatch("end_of_run must be true or false")
    return value


def _batch_id(value: Any, *, frame: bool = False) -> str:
    if not isinstance(value, str) or not value.strip():
        raise InvalidBatch("batch_id is required: a non-empty string (JSON field, query parameter "
                           "batch_id or header Idempotency-Key)")
    if len(value) > MAX_BATCH_ID_LEN:
        raise InvalidBatch(f"batch_id is longer than {MAX_BATCH_ID_LEN} characters")
    if not frame and value.startswith(FRAME_ID_PREFIX):
        raise InvalidBatch(f"batch ids starting with {FRAME_ID_PREFIX!r} are reserved for streamed frames")
    return value


# ----------------------------------------------------------------------------- streamed frames
FRAME_ID_PREFIX = "ws-"


def frame_batch_id(client_seq: int) -> str:
    """The log's batch id of a streamed frame: retries of a frame are idempotent like batches."""
    return f"{FRAME_ID_PREFIX}{client_seq}"


def client_seq_of(batch_id: str) -> int | None:
    if batch_id.startswith(FRAME_ID_PREFIX) and batch_id[len(FRAME_ID_PREFIX):].isdigit():
        return int(batch_id[len(FRAME_ID_PREFIX):])
    return None


class UnsupportedFrame(InvalidBatch):
    """A message that is not a frame of samples (the stream closes with 1003)."""


def _client_seq(value: Any) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < 1 or value >= 2**63:
        raise InvalidBatch("client_seq must be an integer >= 1, increasing by frame")
    return value


def parse_frame(
    data: str | bytes, expected_channels: Sequence[str], max_samples: int
) -> tuple[int, ParsedBatch]:
    """A WebSocket frame of samples -> (client_seq, batch).

    Text frames are JSON: ``{"type": "samples", "client_seq": n, "t": [...] | "t0" +
    "sample_rate_hz", "channels": {...}, "end_of_run": false}``. Binary frames are an Arrow IPC
    stream whose schema metadata holds ``client_seq`` (and ``t0`` / ``sample_rate_hz`` when
    there is no ``t`` column, ``end_of_run`` = ``"true"`` on the last frame of a run).
    """
    if isinstance(data, str):
        try:
            doc = orjson.loads(data)
        except orjson.JSONDecodeError as exc:
            raise InvalidBatch(f"frame is not valid JSON (send null for a missing sample): {exc}") from None
        if not isinstance(doc, dict):
            raise InvalidBatch("a frame must be a JSON object")
        if doc.get("type") != "samples":
            raise UnsupportedFrame(f"unexpected message type {doc.get('type')!r}; frames have type 'samples'")
        seq = _client_seq(doc.get("client_seq"))
        body = {k: v for k, v in doc.items() if k not in ("type", "client_seq")}
        if "batch_id" in body:
            raise InvalidBatch("frames carry client_seq, not batch_id")
        batch_id, t_s, columns = _parse_json_doc(body, TimeParams(frame_batch_id(seq), None, None), frame=True)
        end_of_run = _end_of_run(body.get("end_of_run", False))
    else:
        table = _read_arrow(data)
        meta = {k.decode(): v.decode() for k, v in (table.schema.metadata or {}).items()}
        try:
            seq = _client_seq(int(meta["client_seq"]))
            t0 = float(meta["t0"]) if "t0" in meta else None
            rate = float(meta["sample_rate_hz"]) if "sample_rate_hz" in meta else None
            end_of_run = meta.get("end_of_run", "false").lower() == "true"
        except KeyError:
            raise InvalidBatch("the Arrow schema metadata must hold client_seq") from None
        except ValueError as exc:
            raise InvalidBatch(f"bad Arrow schema metadata: {exc}") from None
        table = table.replace_schema_metadata(None)
        batch_id, t_s, columns = _parse_table(table, TimeParams(frame_batch_id(seq), t0, rate), frame=True)
    return seq, _validate(batch_id, t_s, columns, expected_channels, max_samples, end_of_run)


def _to_float_array(values: Any, name: str) -> np.ndarray:
    if not isinstance(values, list):
        raise InvalidBatch(f"channel {name!r} must be a list of numbers or nulls")
    try:
        arr = pa.array(values)
    except (pa.ArrowInvalid, pa.ArrowTypeError, OverflowError) as exc:
        raise InvalidBatch(f"channel {name!r} holds a value that is not a number: {exc}") from None
    if not (pa.types.is_floating(arr.type) or pa.types.is_integer(arr.type) or pa.types.is_null(arr.type)):
        raise InvalidBatch(f"channel {name!r} must hold numbers or nulls, not {arr.type}")
    return _arrow_to_float(arr, name)


def _arrow_to_float(arr: pa.Array | pa.ChunkedArray, name: str) -> np.ndarray:
    if pa.types.is_null(arr.type):
        return np.full(len(arr), np.nan)
    if not (pa.types.is_floating(arr.type) or pa.types.is_integer(arr.type)):
        raise InvalidBatch(f"column {name!r} has type {arr.type}; numbers are needed")
    arr = arr.cast(pa.float64())
    if isinstance(arr, pa.ChunkedArray):
        arr = arr.combine_chunks()
    # Read-only views are fine: nothing downstream writes into the samples.
    return np.asarray(arr.to_numpy(zero_copy_only=False))


def _json_object(body: bytes) -> dict[str, Any]:
    try:
        doc = orjson.loads(body)
    except orjson.JSONDecodeError as exc:
        raise InvalidBatch(f"body is not valid JSON (NaN and Infinity are not JSON; send null "
                           f"for a missing sample): {exc}") from None
    if not isinstance(doc, dict):
        raise InvalidBatch("body must be a JSON object with batch_id and channels")
    return doc


def _parse_json_doc(
    doc: dict[str, Any], params: TimeParams, *, frame: bool = False
) -> tuple[str, np.ndarray | None, dict[str, np.ndarray]]:
    unknown = set(doc) - {"batch_id", "t", "t0", "sample_rate_hz", "channels", "end_of_run"}
    if unknown:
        raise InvalidBatch(f"unknown fields: {', '.join(sorted(unknown))}")
    batch_id = _batch_id(doc.get("batch_id", params.batch_id), frame=frame)
    chans = doc.get("channels")
    if not isinstance(chans, dict) or not chans:
        raise InvalidBatch("channels must be a non-empty object {name: [values]}")
    columns = {str(k): _to_float_array(v, str(k)) for k, v in chans.items()}
    t_s = None
    if doc.get("t") is not None:
        if "t0" in doc or "sample_rate_hz" in doc:
            raise InvalidBatch("give either t or t0 with sample_rate_hz, not both")
        t_s = _to_float_array(doc["t"], "t")
    else:
        t0 = doc.get("t0", params.t0)
        rate = doc.get("sample_rate_hz", params.sample_rate_hz)
        n = len(next(iter(columns.values())))
        t_s = _regular_time(t0, rate, n)
    return batch_id, t_s, columns


def _regular_time(t0: Any, rate: Any, n: int) -> np.ndarray:
    if t0 is None or rate is None:
        raise InvalidBatch("timestamps are required: a t column, or t0 and sample_rate_hz")
    if isinstance(t0, bool) or not isinstance(t0, int | float) or not math.isfinite(t0):
        raise InvalidBatch("t0 must be a finite number of seconds")
    if isinstance(rate, bool) or not isinstance(rate, int | float) or not (math.isfinite(rate) and rate > 0):
        raise InvalidBatch("sample_rate_hz must be a positive finite number")
    return float(t0) + np.arange(n, dtype=np.float64) / float(rate)


def _read_csv(body: bytes) -> pa.Table:
    try:
        return pacsv.read_csv(
            io.BytesIO(body),
            convert_options=pacsv.ConvertOptions(
                null_values=["", "NaN", "nan", "NA", "null"], strings_can_be_null=True
            ),
        )
    except (pa.ArrowInvalid, pa.ArrowTypeError) as exc:
        raise InvalidBatch(f"CSV could not be read: {exc}") from None


def _read_arrow(body: bytes) -> pa.Table:
    try:
        return pa.ipc.open_stream(pa.py_buffer(body)).read_all()
    except (pa.ArrowInvalid, pa.ArrowTypeError, OSError) as exc:
        raise InvalidBatch(f"body is not an Arrow IPC stream: {exc}") from None


def _parse_table(
    table: pa.Table, params: TimeParams, *, frame: bool = False
) -> tuple[str, np.ndarray | None, dict[str, np.ndarray]]:
    batch_id = _batch_id(params.batch_id, frame=frame)
    names = table.column_names
    if len(set(names)) != len(names):
        raise InvalidBatch("column names repeat")
    columns = {
        name: _arrow_to_float(table.column(name), name) for name in names if name != TIME_COLUMN
    }
    if TIME_COLUMN in names:
        if params.t0 is not None or params.sample_rate_hz is not None:
            raise InvalidBatch("give either a t column or t0 with sample_rate_hz, not both")
        t_s = _arrow_to_float(table.column(TIME_COLUMN), TIME_COLUMN)
    else:
        t_s = _regular_time(params.t0, params.sample_rate_hz, table.num_rows)
    return batch_id, t_s, columns


def _validate(
    batch_id: str,
    t_s: np.ndarray | None,
    columns: Mapping[str, np.ndarray],
    expected: Sequence[str],
    max_samples: int,
    end_of_run: bool = False,
) -> ParsedBatch:
    assert t_s is not None
    unknown = sorted(set(columns) - set(expected))
    missing = [c for c in expected if c not in columns]
    if unknown:
        raise InvalidBatch(f"unknown channels: {', '.join(unknown)} (this actuator has: "
                           f"{', '.join(expected)})")
    if missing:
        raise InvalidBatch(f"missing channels: {', '.join(missing)} (send NaN/null for samples "
                           "the sensor did not give)")
    n = t_s.shape[0]
    for name, col in columns.items():
        if col.shape[0] != n:
            raise InvalidBatch(f"channel {name!r} has {col.shape[0]} samples but t has {n}")
    if n == 0:
        raise InvalidBatch("empty batch: no samples")
    if n > max_samples:
        raise InvalidBatch(f"batch has {n} samples; the limit is {max_samples}: split it")
    if not np.all(np.isfinite(t_s)):
        k = int(np.argmin(np.isfinite(t_s)))
        raise InvalidBatch(f"t[{k}] is not a finite number")
    if n > 1:
        d = np.diff(t_s)
        if not np.all(d > 0):
            k = int(np.argmin(d > 0))
            raise InvalidBatch(f"timestamps must increase strictly: t[{k + 1}]={t_s[k + 1]!r} "
                               f"follows t[{k}]={t_s[k]!r}")
    for name, col in columns.items():
        bad = np.isinf(col)
        if bad.any():
            k = int(np.argmax(bad))
            raise InvalidBatch(f"channel {name!r} holds an infinite value at index {k}")
    ordered = {c: np.ascontiguousarray(columns[c], dtype=np.float64) for c in expected}
    return ParsedBatch(
        batch_id=batch_id,
        t_s=np.ascontiguousarray(t_s, dtype=np.float64),
        channels=ordered,
        end_of_run=end_of_run,
    )
