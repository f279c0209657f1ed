"""Turn a request body (JSON, CSV or Arrow IPC) into a validated block of samples.

Missing samples are data: ``null`` in JSON, an empty cell or ``NaN`` in CSV, a null or NaN in
Arrow all become NaN, which the estimators predict through. Everything else that is not a finite
number is refused with :class:`~app.errors.InvalidBatch` naming the channel and position.

Every decoder is bounded before it allocates, whatever the input (a few kilobytes of zstd can
declare tens of millions of rows): an Arrow IPC stream is read message by message and each record
batch's declared row count and decompressed buffer sizes are checked against the limits before
the batch is decoded; a CSV or JSON body's rows / values are counted on the raw bytes before it
is parsed. The limits are the batch's sample limit and a decoded-bytes limit,
:func:`decoded_bytes_limit`.

Each decoder also reserves, before it allocates, the memory it is about to use
(``DecodeLimits.reserve``: the service's share of the process-wide budget,
:class:`app.telemetry.body.IngestMemory`), from the same counts, once for the whole request (its
encoding for the log included, ``LOG_BYTES_PER_VALUE`` per value): the body's length (orjson
parses a copy) and ``JSON_BYTES_PER_VALUE`` per JSON value, ``CSV_BYTES_PER_VALUE`` per CSV cell,
twice an Arrow stream's decoded size. The body
is let go as soon as it is decoded (``release_body``), and JSON lists are turned into arrays one
channel at a time, each list freed once converted.
"""

from __future__ import annotations

import functools
import hashlib
import math
import mmap
import struct
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import orjson
import pyarrow as pa
import pyarrow.csv as pacsv

from app.codec import encode_columns
from app.errors import InvalidBatch, UnsupportedMediaType

JSON_TYPES = ("application/json",)
CSV_TYPES = ("text/csv",)
ARROW_TYPES = ("application/vnd.apache.arrow.stream",)
SUPPORTED_TYPES = JSON_TYPES + CSV_TYPES + ARROW_TYPES
TIME_COLUMN = "t"
MAX_BATCH_ID_LEN = 128
#: Largest integer float64 holds exactly: every integer of magnitude <= 2**53 is exact.
FLOAT64_EXACT_INT = 2**53
# Bytes a decoded sample may take per column: 8 for the float64 value, 1 of allowance for the
# validity bitmap (1 bit) and the alignment padding of Arrow buffers.
DECODED_BYTES_PER_VALUE = 9
# Allowance of JSON values that are not samples: batch_id (at most MAX_BATCH_ID_LEN characters,
# each possibly a comma), t0, sample_rate_hz, end_of_run.
JSON_VALUE_SLACK = MAX_BATCH_ID_LEN + 16
# Memory one parsed JSON value takes until it is a float64 array: the parser's document node (16
# bytes), a Python float (24), its list slot (8) and the float64 it becomes (8); a 73 MB body of
# 4.05 million values peaked at 285 MB of anonymous memory (bench/bench_batch_memory.py --server).
JSON_BYTES_PER_VALUE = 56
# Memory one CSV cell takes while the CSV reader converts it (the parsed text block and the
# column it becomes): 4.05 million cells took 153 MB (bench/bench_batch_memory.py).
CSV_BYTES_PER_VALUE = 40
# Memory encoding a value for the telemetry log takes: the LZ4 output (at most about the float64
# size: 88 % of it on sensor noise) and the float64 it is made from, while the batch waits for
# its commit.
LOG_BYTES_PER_VALUE = 16

#: A request body as the decoders take it: bytes, a bytearray or a read-only map of a spool file.
BodyBytes = bytes | bytearray | mmap.mmap


def _no_reservation(n: int) -> None:
    """The default of :attr:`DecodeLimits.reserve`: nothing is accounted."""


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

    @property
    def nbytes(self) -> int:
        """Bytes of the decoded samples (t and every channel)."""
        return int(self.t_s.nbytes) + sum(int(c.nbytes) for c in self.channels.values())

    @functools.cached_property
    def digest(self) -> str:
        """:meth:`content_hash`, computed once (by :meth:`prepare_log`, outside the log's lock)."""
        return self.content_hash()

    @functools.cached_property
    def log_payload(self) -> bytes:
        """The block the telemetry log stores (``t`` and the channels, :func:`app.codec.encode_columns`),
        encoded once (by :meth:`prepare_log`, outside the log's lock)."""
        return encode_columns({TIME_COLUMN: self.t_s, **self.channels})

    def prepare_log(self) -> None:
        """Compute the digest and the log block now, in the thread that parsed the batch: the
        log writer then only writes them, so neither holds the database's write lock (SQLite)
        nor the writer thread; both release Python's lock while they run (hashlib, LZ4), so on
        a large batch they run beside the processor."""
        _ = self.digest, self.log_payload

    def content_hash(self) -> str:
        """Digest of the decoded samples, so a retry in another format or spacing still matches."""
        h = hashlib.blake2b(digest_size=16)
        # The arrays' own buffers (no copy): the same bytes tobytes() would give.
        h.update(np.ascontiguousarray(self.t_s).data)
        for name in sorted(self.channels):
            h.update(name.encode())
            h.update(np.ascontiguousarray(self.channels[name]).data)
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


@dataclass(frozen=True)
class DecodeLimits:
    """What one batch may decode to: ``max_samples`` rows, ``max_bytes`` decoded bytes; each
    decoder calls ``reserve(n)`` with the bytes it is about to allocate before it allocates."""

    expected_channels: tuple[str, ...]
    max_samples: int
    max_bytes: int
    reserve: Callable[[int], None] = field(default=_no_reservation, compare=False)


def decoded_bytes_limit(n_channels: int, max_samples: int, cap_bytes: int | None = None) -> int:
    """Decoded bytes a batch of ``n_channels`` channels may take.

    ``max_samples * (n_channels + 1) * DECODED_BYTES_PER_VALUE``: every channel and the time
    column at the sample limit, as float64 with validity bitmaps; capped by ``cap_bytes`` (the
    service passes setting ``max_batch_decoded_bytes``) so an actuator with many channels does
    not raise the bound without limit.
    """
    bound = max_samples * (n_channels + 1) * DECODED_BYTES_PER_VALUE
    return bound if cap_bytes is None else min(bound, cap_bytes)


def _limits(
    expected_channels: Sequence[str],
    max_samples: int,
    max_decoded_bytes: int | None,
    reserve: Callable[[int], None] | None = None,
) -> DecodeLimits:
    return DecodeLimits(
        tuple(expected_channels),
        max_samples,
        decoded_bytes_limit(len(expected_channels), max_samples, max_decoded_bytes),
        reserve or _no_reservation,
    )


_COUNT_STEP = 4 * 1024 * 1024


def _count(body: BodyBytes, byte: bytes) -> int:
    """Occurrences of ``byte`` in ``body`` (a map has no ``count``: read in slices)."""
    if not isinstance(body, mmap.mmap):
        return body.count(byte)
    view = memoryview(body)
    return sum(view[i:i + _COUNT_STEP].tobytes().count(byte) for i in range(0, len(view), _COUNT_STEP))


def _too_many_samples(n: int, max_samples: int, *, at_least: bool = False) -> InvalidBatch:
    """The sample-limit error, one message for every decoder and for :func:`_validate`."""
    return InvalidBatch(f"batch has {'at least ' if at_least else ''}{n} samples; the limit is "
                        f"{max_samples}: split it")


def parse_body(
    body: BodyBytes,
    mt: str,
    params: TimeParams,
    expected_channels: Sequence[str],
    max_samples: int,
    max_decoded_bytes: int | None = None,
    *,
    reserve: Callable[[int], None] | None = None,
    release_body: Callable[[], None] | None = None,
) -> ParsedBatch:
    """Decode and validate a REST body; ``max_decoded_bytes`` caps :func:`decoded_bytes_limit`.

    ``reserve(n)`` is called with the bytes each decoder is about to allocate, before it does;
    ``release_body()`` once the body is decoded (the caller drops its last reference there).
    """
    if not len(body):
        raise InvalidBatch("empty body")
    limits = _limits(expected_channels, max_samples, max_decoded_bytes, reserve)
    end_of_run = params.end_of_run
    if mt in JSON_TYPES:
        doc = _json_object(body, limits)
        del body
        if release_body is not None:
            release_body()
        end_of_run = _end_of_run(doc.get("end_of_run", end_of_run))
        batch_id, t_s, columns = _parse_json_doc(doc, params)
    else:
        table = _read_csv(body, limits) if mt in CSV_TYPES else _read_arrow(body, limits)
        del body
        if release_body is not None:
            release_body()
        batch_id, t_s, columns = _parse_table(table, params)
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
    data: str | bytes,
    expected_channels: Sequence[str],
    max_samples: int,
    max_decoded_bytes: int | None = None,
) -> tuple[int, ParsedBatch]:
    """A WebSocket frame of samples -> (client_seq, batch).

    Text frames are JSON: ``{"type": "samples", "client_seq": n, "t": [...] | "t0" +
    "sample_rate_hz", "channels": {...}, "end_of_run": false}``. Binary frames are an Arrow IPC
    stream whose schema metadata holds ``client_seq`` (and ``t0`` / ``sample_rate_hz`` when
    there is no ``t`` column, ``end_of_run`` = ``"true"`` on the last frame of a run).
    Bounded like :func:`parse_body`.
    """
    limits = _limits(expected_channels, max_samples, max_decoded_bytes)
    if isinstance(data, str):
        _check_json_values(data.encode(), limits)
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
        table = _read_arrow(data, limits)
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
        batch_id, t_s, columns = _parse_table(table, TimeParams(frame_batch_id(seq), t0, rate), frame=True)
    return seq, _validate(batch_id, t_s, columns, expected_channels, max_samples, end_of_run)


#: A JSON list up to this length whose values are all floats, exact integers or nulls becomes an
#: array directly (about 1 us against 20 us through Arrow for one value); anything else goes
#: through Arrow, whose refusals are the contract.
SMALL_LIST_MAX = 64


def _small_list(values: list[Any]) -> np.ndarray | None:
    if len(values) > SMALL_LIST_MAX:
        return None
    for v in values:
        t = type(v)
        if t is not float and v is not None and not (t is int and -FLOAT64_EXACT_INT <= v <= FLOAT64_EXACT_INT):
            return None
    return np.array(values, dtype=np.float64)


def _to_float_array(values: Any, name: str) -> np.ndarray:
    if not isinstance(values, list):
        raise InvalidBatch(f"channel {name!r} must be a list of numbers or nulls")
    small = _small_list(values)
    if small is not None:
        return small
    try:
        arr = pa.array(values)
    except (pa.ArrowInvalid, pa.ArrowTypeError, OverflowError) as exc:
        raise InvalidBatch(f"channel {name!r} holds a value that is not a number: {exc}") from None
    if not (pa.types.is_floating(arr.type) or pa.types.is_integer(arr.type) or pa.types.is_null(arr.type)):
        raise InvalidBatch(f"channel {name!r} must hold numbers or nulls, not {arr.type}")
    return _arrow_to_float(arr, name)


_FLOAT64_ID = pa.float64().id


def _arrow_to_float(arr: pa.Array | pa.ChunkedArray, name: str) -> np.ndarray:
    kind = arr.type
    if kind.id != _FLOAT64_ID:  # float64, the usual column, is taken as it is
        if pa.types.is_null(kind):
            return np.full(len(arr), np.nan)
        if not (pa.types.is_floating(kind) or pa.types.is_integer(kind)):
            raise InvalidBatch(f"column {name!r} has type {kind}; numbers are needed")
        arr = arr.cast(pa.float64())
    if isinstance(arr, pa.ChunkedArray):
        # One chunk is used as it is (combine_chunks would copy it); several are joined.
        arr = arr.chunk(0) if arr.num_chunks == 1 else arr.combine_chunks()
    # Read-only views are fine: nothing downstream writes into the samples.
    return np.asarray(arr.to_numpy(zero_copy_only=False))


def _check_json_values(body: BodyBytes, limits: DecodeLimits) -> None:
    """Refuse, before parsing, a JSON document with more values than the limits allow.

    Parsed, each JSON number costs a Python float and a list slot (about 32 bytes) for as little
    as 2 bytes of text, so the body limit alone does not bound memory. The values of a list of
    ``k`` elements are separated by ``k - 1`` commas, so the count of commas bounds the values
    from above: beyond every channel and ``t`` at the sample limit (plus a small allowance for
    the other fields), the batch cannot be valid.
    """
    allowed = limits.max_samples * (len(limits.expected_channels) + 1) + JSON_VALUE_SLACK
    commas = _count(body, b",")
    if commas > allowed:
        raise InvalidBatch(f"batch holds more values than {limits.max_samples} samples of "
                           f"{len(limits.expected_channels)} channels and t; the limit is "
                           f"{limits.max_samples} samples: split it")
    # The parser's own copy of the text, then every value, parsed and encoded for the log: one
    # reservation for the whole request (one that waited holding a part could wait on another).
    limits.reserve(len(body) + (commas + 1) * (JSON_BYTES_PER_VALUE + LOG_BYTES_PER_VALUE))


def _json_object(body: BodyBytes, limits: DecodeLimits) -> dict[str, Any]:
    _check_json_values(body, limits)
    try:
        doc = orjson.loads(memoryview(body) if isinstance(body, mmap.mmap) else body)
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
    if doc.get("t") is not None and ("t0" in doc or "sample_rate_hz" in doc):
        raise InvalidBatch("give either t or t0 with sample_rate_hz, not both")
    # One list at a time, each dropped from the document once converted: the Python floats of
    # a large batch are never all held next to their arrays.
    columns: dict[str, np.ndarray] = {}
    for name in list(chans):
        columns[str(name)] = _to_float_array(chans.pop(name), str(name))
    t_s = None
    if doc.get("t") is not None:
        t_s = _to_float_array(doc.pop("t"), "t")
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


_CSV_NULLS = ["", "NaN", "nan", "NA", "null"]
_CSV_BLOCK_BYTES = 1 << 20


def _too_many_columns(n: int, limits: DecodeLimits) -> InvalidBatch:
    """More columns than the channels and t: refused before any is decoded (each costs memory)."""
    return InvalidBatch(f"batch has {n} columns; this actuator has {len(limits.expected_channels)} "
                        f"channels ({', '.join(limits.expected_channels)}) and {TIME_COLUMN!r}")


def _read_csv(body: BodyBytes, limits: DecodeLimits) -> pa.Table:
    """Read a CSV body, its size checked against ``limits`` before it is decoded whole.

    The header is read from the first block (``_CSV_BLOCK_BYTES``) only: more columns than the
    actuator's channels and ``t`` are refused. Rows are at most the newlines after the header;
    only when that bound is above the sample limit (blank lines or quoted newlines could make it
    loose) are the rows counted exactly, block by block with every column read as text, stopping
    as soon as the limit is passed. The full read then infers each column's type over all rows.
    """
    buf = pa.py_buffer(body)  # the body itself, not a copy (io.BytesIO copies a bytearray)
    try:
        head = pacsv.open_csv(
            pa.BufferReader(buf), read_options=pacsv.ReadOptions(block_size=_CSV_BLOCK_BYTES)
        )
        names = head.schema.names
        head.close()
        if len(names) > len(limits.expected_channels) + 1:
            raise _too_many_columns(len(names), limits)
        lines = _count(body, b"\n")
        if lines > limits.max_samples + 1:
            rows = 0
            reader = pacsv.open_csv(
                pa.BufferReader(buf),
                read_options=pacsv.ReadOptions(block_size=_CSV_BLOCK_BYTES),
                convert_options=pacsv.ConvertOptions(
                    column_types={name: pa.string() for name in names}
                ),
            )
            for block in reader:
                rows += block.num_rows
                if rows > limits.max_samples:
                    raise _too_many_samples(rows, limits.max_samples, at_least=True)
            lines = rows
        limits.reserve((lines + 1) * len(names) * (CSV_BYTES_PER_VALUE + LOG_BYTES_PER_VALUE))
        return pacsv.read_csv(
            pa.BufferReader(buf),
            convert_options=pacsv.ConvertOptions(null_values=_CSV_NULLS, strings_can_be_null=True),
        )
    except (pa.ArrowInvalid, pa.ArrowTypeError) as exc:
        raise InvalidBatch(f"CSV could not be read: {exc}") from None


# Arrow IPC flatbuffer layout (format/Message.fbs, format/Schema.fbs of Apache Arrow): the
# message header is a union whose type 3 is RecordBatch and 2 DictionaryBatch; RecordBatch's
# fields are length (0), nodes (1), buffers (2, structs {offset: int64, length: int64}),
# compression (3).
_HEADER_DICTIONARY_BATCH = 2
_HEADER_RECORD_BATCH = 3


class _Flat:
    """Bounds-checked reads of a flatbuffer: a malformed one raises ``ValueError``."""

    _FORMATS = {fmt: struct.Struct("<" + fmt) for fmt in "BHIiq"}

    def __init__(self, buf: bytes) -> None:
        self.buf = buf
        self.size = len(buf)

    def scalar(self, fmt: str, pos: int) -> int:
        form = self._FORMATS[fmt]
        if pos < 0 or pos + form.size > self.size:
            raise ValueError("flatbuffer offset out of range")
        value: int = form.unpack_from(self.buf, pos)[0]
        return value

    def scalars(self, fmt: str, pos: int, count: int) -> tuple[int, ...]:
        """``count`` consecutive scalars of ``fmt`` from ``pos``."""
        form = self._FORMATS[fmt]
        if pos < 0 or pos + count * form.size > self.size:
            raise ValueError("flatbuffer offset out of range")
        return struct.unpack_from(f"<{count}{fmt}", self.buf, pos)

    def field(self, table: int, index: int) -> int | None:
        """Absolute position of a table's field, None when absent."""
        vtable = table - self.scalar("i", table)
        vsize = self.scalar("H", vtable)
        slot = 4 + 2 * index
        if slot + 2 > vsize:
            return None
        off = self.scalar("H", vtable + slot)
        return table + off if off else None

    def deref(self, pos: int) -> int:
        return pos + self.scalar("I", pos)


#: Record batch headers remembered: the frames of a stream share their shape, so the same
#: metadata bytes come again frame after frame (the client_seq is in the schema message).
HEADER_CACHE_SIZE = 1024


@functools.lru_cache(maxsize=HEADER_CACHE_SIZE)
def _record_batch_header(metadata: bytes) -> tuple[int, int, tuple[tuple[int, int], ...], bool]:
    """``(header type, declared rows, buffers (offset, length), compressed)`` of a message.

    For a message that is not a record batch (schema, dictionary), only its header type is read.
    A pure function of the bytes, remembered (a malformed header raises, and is not).
    """
    fb = _Flat(metadata)
    message = fb.deref(0)
    type_pos = fb.field(message, 1)
    header_type = fb.scalar("B", type_pos) if type_pos is not None else 0
    if header_type != _HEADER_RECORD_BATCH:
        return (header_type, 0, (), False)
    header_pos = fb.field(message, 2)
    if header_pos is None:
        raise ValueError("record batch message without header")
    batch = fb.deref(header_pos)
    length_pos = fb.field(batch, 0)
    rows = fb.scalar("q", length_pos) if length_pos is not None else 0
    buffers: tuple[tuple[int, int], ...] = ()
    buffers_pos = fb.field(batch, 2)
    if buffers_pos is not None:
        vec = fb.deref(buffers_pos)
        n = fb.scalar("I", vec)
        if 4 + 16 * n > len(metadata):
            raise ValueError("buffer vector out of range")
        if n:
            # The whole vector at once: (offset, length) pairs of int64.
            flat = fb.scalars("q", vec + 4, 2 * n)
            buffers = tuple(zip(flat[0::2], flat[1::2], strict=True))
    compressed = fb.field(batch, 3) is not None
    return (header_type, rows, buffers, compressed)


def _decoded_bytes(body: pa.Buffer | None, buffers: Sequence[tuple[int, int]], compressed: bool) -> int:
    """Bytes a record batch's buffers take once decoded.

    A compressed buffer starts with its uncompressed length (int64, -1 when stored as is), the
    size Arrow allocates before it decompresses; a lie about it fails decompression.
    """
    size = body.size if body is not None else 0
    view = memoryview(body) if body is not None else memoryview(b"")
    total = 0
    for offset, length in buffers:
        if offset < 0 or length < 0 or offset + length > size:
            raise ValueError("record batch buffer out of range of the message body")
        if not compressed or length == 0:
            total += length
            continue
        if length < 8:
            raise ValueError("compressed buffer shorter than its length prefix")
        declared: int = struct.unpack_from("<q", view, offset)[0]
        if declared == -1:
            total += length - 8
        elif declared < 0:
            raise ValueError("negative uncompressed buffer length")
        else:
            total += declared
    return total


def _read_arrow(body: BodyBytes, limits: DecodeLimits) -> pa.Table | pa.RecordBatch:
    """Read an Arrow IPC stream record batch by record batch, bounded before each is decoded.

    Each message's metadata is read first: a record batch whose declared rows take the total
    above the sample limit, or whose buffers (decompressed sizes, for zstd / lz4 bodies) take
    the decoded total above ``limits.max_bytes``, is refused before it is decompressed; so is a
    schema with more columns than the channels and ``t`` (each is cast to float64). Dictionary
    batches are refused (the columns must be numbers).
    """
    messages: list[pa.ipc.Message] = []
    rows = 0
    decoded = 0
    try:
        reader = pa.ipc.MessageReader.open_stream(pa.py_buffer(body))
        schema = pa.ipc.read_schema(reader.read_next_message())
        if len(schema) > len(limits.expected_channels) + 1:
            raise _too_many_columns(len(schema), limits)
        # First every message's header (the bodies are slices of the request body, nothing is
        # decompressed), then one reservation for the whole batch, then the decoding.
        while True:
            try:
                message = reader.read_next_message()
            except StopIteration:
                break
            header_type, n, buffers, compressed = _record_batch_header(message.metadata.to_pybytes())
            if header_type == _HEADER_DICTIONARY_BATCH:
                raise InvalidBatch("dictionary-encoded columns are not supported; numbers are needed")
            if header_type != _HEADER_RECORD_BATCH:
                raise InvalidBatch(f"unexpected Arrow IPC message {message.type!r} in the stream")
            if n < 0:
                raise ValueError("negative record batch length")
            rows += n
            if rows > limits.max_samples:
                raise _too_many_samples(rows, limits.max_samples, at_least=True)
            decoded += _decoded_bytes(message.body, buffers, compressed)
            if decoded > limits.max_bytes:
                raise InvalidBatch(f"batch decodes to more than {limits.max_bytes} bytes, the limit "
                                   f"for {limits.max_samples} samples of "
                                   f"{len(limits.expected_channels)} channels and t: split it")
            messages.append(message)
        # The decoded size, once more for a float64 cast or chunks joined, and the log encoding.
        limits.reserve(2 * decoded + rows * len(schema) * LOG_BYTES_PER_VALUE)
        batches = []
        for message in messages:
            batch = pa.ipc.read_record_batch(message, schema)
            batch.validate()  # buffer sizes consistent with the declared length (cheap, no scan)
            batches.append(batch)
        # One record batch (a frame, a small body) is used as it is: a table of it is the same
        # columns behind one more layer of objects.
        return batches[0] if len(batches) == 1 else pa.Table.from_batches(batches, schema=schema)
    except (pa.ArrowInvalid, pa.ArrowTypeError, OSError, ValueError, StopIteration) as exc:
        raise InvalidBatch(f"body is not an Arrow IPC stream: {exc}") from None


def _parse_table(
    table: pa.Table | pa.RecordBatch, params: TimeParams, *, frame: bool = False
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


#: Up to this many values, a check first tests the values in plain Python (numpy calls on a few
#: values cost more than the whole test); a batch that may fail is then checked as a large one
#: is, so the refusal is the same (here and in ``app.telemetry.validation``).
SMALL_CHECK_MAX = 64


def _finite_increasing(values: list[float]) -> bool:
    """Whether non-empty ``values`` are finite and strictly increasing (False for a NaN
    anywhere: it compares False). Each lies between the first and the last, so finite ends
    are enough."""
    return (-math.inf < values[0] and values[-1] < math.inf
            and all(a < b for a, b in zip(values, values[1:], strict=False)))


def _all_finite(values: list[float]) -> bool:
    """Whether every value is finite (no NaN, no infinity): their sum is then finite, or it
    overflows (False, as for a NaN or an infinity: a quick test, not the check)."""
    total = sum(values)
    return total - total == 0.0


def _validate(
    batch_id: str,
    t_s: np.ndarray | None,
    columns: Mapping[str, np.ndarray],
    expected: Sequence[str],
    max_samples: int,
    end_of_run: bool = False,
) -> ParsedBatch:
    assert t_s is not None
    if len(columns) != len(expected) or columns.keys() != set(expected):
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
        raise _too_many_samples(n, max_samples)
    small = n <= SMALL_CHECK_MAX
    # A small batch is first tested in plain Python (a few numpy calls on tiny arrays cost more
    # than the whole test); only one that may fail goes through the checks that name the fault.
    if not (small and _finite_increasing(t_s.tolist())):
        if not np.all(np.isfinite(t_s)):
            k = int(np.argmin(np.isfinite(t_s)))
            raise InvalidBatch(f"t[{k}] is not a finite number")
        if n > 1:
            d = np.diff(t_s)
            if not np.all(d > 0):
                k = int(np.argmin(d > 0))
                raise InvalidBatch(f"timestamps must increase strictly: t[{k + 1}]={t_s[k + 1]!r} "
                                   f"follows t[{k}]={t_s[k]!r}")
    if not (small and all(_all_finite(col.tolist()) for col in columns.values())):
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
