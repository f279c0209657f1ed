"""Time series read back in pages and exported in files, block by block.

The telemetry log and the per-sample outputs are stored as blocks (one per batch) of columns
with a time column ``t``. Both read paths here walk the blocks lazily: a page stops after
``max_samples`` samples; an export writes each block as soon as it is read, so memory holds
one block, never the whole series. Times are strictly increasing along a stream, so a page's
cursor is the time of its last sample.
"""

from __future__ import annotations

import io
from collections.abc import Iterable, Iterator, Mapping, Sequence
from contextlib import ExitStack
from typing import Any, Literal

import numpy as np
import pyarrow as pa
import pyarrow.csv as pacsv
import pyarrow.parquet as pq
from fastapi.responses import StreamingResponse

from app.ingest import TIME_COLUMN
from app.pagination import Order

ExportFormat = Literal["arrow", "csv", "parquet"]
MEDIA_TYPES: dict[str, str] = {
    "arrow": "application/vnd.apache.arrow.stream",
    "csv": "text/csv",
    "parquet": "application/vnd.apache.parquet",
}
EXTENSIONS = {"arrow": "arrows", "csv": "csv", "parquet": "parquet"}


def clip(
    cols: Mapping[str, np.ndarray],
    from_s: float | None,
    to_s: float | None,
    after_t: float | None,
    order: Order,
) -> dict[str, np.ndarray]:
    """The samples of one block in [from_s, to_s] and after ``after_t`` in ``order``, in that
    order (reversed for ``desc``)."""
    t = cols[TIME_COLUMN]
    keep = np.ones(t.shape, dtype=bool)
    if from_s is not None:
        keep &= t >= from_s
    if to_s is not None:
        keep &= t <= to_s
    if after_t is not None:
        keep &= (t > after_t) if order == "asc" else (t < after_t)
    out = {k: v[keep] for k, v in cols.items()}
    return {k: v[::-1] for k, v in out.items()} if order == "desc" else out


def page(
    blocks: Iterable[Mapping[str, np.ndarray]],
    from_s: float | None,
    to_s: float | None,
    after_t: float | None,
    order: Order,
    max_samples: int,
) -> tuple[dict[str, np.ndarray], float | None]:
    """Up to ``max_samples`` samples from ``blocks`` (given in ``order``), joined, and the
    time to continue after when more follow (None on the last page)."""
    parts: list[dict[str, np.ndarray]] = []
    n = 0
    more = False
    for cols in blocks:
        part = clip(cols, from_s, to_s, after_t, order)
        m = len(part[TIME_COLUMN])
        if m == 0:
            continue
        if n >= max_samples:
            more = True
            break
        take = min(m, max_samples - n)
        parts.append({k: v[:take] for k, v in part.items()})
        n += take
        if take < m:
            more = True
            break
    names = list(parts[0]) if parts else [TIME_COLUMN]
    joined = {k: np.concatenate([p[k] for p in parts]) if parts else np.empty(0) for k in names}
    last = float(joined[TIME_COLUMN][-1]) if more else None
    return joined, last


def _array(values: np.ndarray) -> pa.Array:
    if np.issubdtype(values.dtype, np.floating):
        # A missing sample is NaN in the store and null in an export (as it was at ingest).
        return pa.array(values, type=pa.float64(), from_pandas=True)
    return pa.array(values, type=pa.int64())


def schema_of(names: Sequence[str], int_columns: Sequence[str] = ()) -> pa.Schema:
    return pa.schema(
        [pa.field(n, pa.int64() if n in int_columns else pa.float64()) for n in names]
    )


class _Drain(io.RawIOBase):
    """A write-only file whose bytes are taken out after each block."""

    def __init__(self) -> None:
        self._chunks: list[bytes] = []
        self._pos = 0

    def writable(self) -> bool:
        return True

    def write(self, b: Any) -> int:
        data = bytes(b)
        self._chunks.append(data)
        self._pos += len(data)
        return len(data)

    def tell(self) -> int:
        return self._pos

    def take(self) -> bytes:
        out = b"".join(self._chunks)
        self._chunks.clear()
        return out


def export(blocks: Iterable[Mapping[str, np.ndarray]], schema: pa.Schema, fmt: ExportFormat) -> Iterator[bytes]:
    """The bytes of an Arrow IPC stream, a CSV file or a Parquet file holding ``blocks``, one
    record batch (CSV rows, Parquet row group) per block, yielded as each block is written.
    A block lacking a column of ``schema`` has nulls there."""
    sink = _Drain()
    writer: Any
    if fmt == "arrow":
        writer = pa.ipc.new_stream(sink, schema)
    elif fmt == "parquet":
        writer = pq.ParquetWriter(sink, schema, compression="zstd")
    else:
        writer = pacsv.CSVWriter(sink, schema)
    for cols in blocks:
        n = len(cols[TIME_COLUMN])
        if n == 0:
            continue
        arrays = [
            _array(cols[f.name]) if f.name in cols else pa.nulls(n, type=f.type) for f in schema
        ]
        writer.write_batch(pa.record_batch(arrays, schema=schema))
        chunk = sink.take()
        if chunk:
            yield chunk
    writer.close()
    tail = sink.take()
    if tail:
        yield tail


EXPORT_RESPONSES: dict[int | str, dict[str, Any]] = {
    200: {
        "description": "The file, streamed",
        "content": {
            MEDIA_TYPES["arrow"]: {"schema": {"type": "string", "format": "binary"}},
            MEDIA_TYPES["csv"]: {"schema": {"type": "string"}},
            MEDIA_TYPES["parquet"]: {"schema": {"type": "string", "format": "binary"}},
        },
    }
}


def export_response(stack: ExitStack, chunks: Iterator[bytes], fmt: ExportFormat, stem: str) -> StreamingResponse:
    """A streamed file download; ``stack`` (the read transaction the chunks come from) closes
    when the body ends or the client goes away."""

    def body() -> Iterator[bytes]:
        with stack:
            yield from chunks

    return StreamingResponse(
        body(),
        media_type=MEDIA_TYPES[fmt],
        headers={"Content-Disposition": f'attachment; filename="{stem}.{EXTENSIONS[fmt]}"'},
    )
