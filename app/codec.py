"""Compact binary form of column blocks (telemetry log payloads and per-sample outputs):
an Arrow IPC stream of float64 columns, LZ4-compressed from :data:`COMPRESS_MIN_ROWS` rows.

LZ4 rather than zstd: on sensor data zstd (level 1) keeps 73 % of the float64 bytes of a log
block and 63 % of an output block, LZ4 88 % and 73 %, but zstd costs about 4x the CPU both ways
(10,000 samples of 3 columns: 0.8 ms against 0.15 ms to encode, 0.3 against 0.1 ms to decode),
which at a million samples a second was a fifth of a core (docs/benchmarks.md). Blocks written
with zstd before stay readable: the reader takes the codec from each IPC message.

Below that many rows, compression saves a few bytes and costs more than the rest of the encoding
(setting up a codec context per buffer); the reader tells both apart by the IPC message itself."""

from __future__ import annotations

import functools
import io
from collections.abc import Collection, Mapping

import numpy as np
import pyarrow as pa

COMPRESS_MIN_ROWS = 256
#: Rows per record batch of a large block: compressing a column takes a scratch buffer of its
#: size, so a large block is written as record batches of about 0.5 MB per column.
ENCODE_CHUNK_ROWS = 65_536
_COMPRESSED = pa.ipc.IpcWriteOptions(compression="lz4")
#: The end-of-stream marker of an Arrow IPC stream (continuation, then a zero length).
_EOS = b"\xff\xff\xff\xff\x00\x00\x00\x00"


@functools.lru_cache(maxsize=256)
def _schema_message(names: tuple[str, ...]) -> bytes:
    """The IPC schema message of float64 columns of these names."""
    return bytes(pa.schema([(name, pa.float64()) for name in names]).serialize().to_pybytes())


@functools.lru_cache(maxsize=1024)
def _batch_header(n_columns: int, rows: int) -> bytes:
    """The IPC message of a record batch of ``n_columns`` float64 columns of ``rows`` values, up
    to its body. It depends on that shape alone: a float64 column from NumPy has no validity
    buffer (NaN is a value, not a null) and its values fill whole 8-byte words, so the body is
    the columns' values one after the other, unpadded."""
    zeros = pa.array(np.zeros(rows))
    batch = pa.RecordBatch.from_arrays([zeros] * n_columns, names=[f"c{i}" for i in range(n_columns)])
    message = bytes(batch.serialize().to_pybytes())
    return message[: len(message) - n_columns * rows * 8]


def encode_columns(columns: Mapping[str, np.ndarray]) -> bytes:
    values = [np.asarray(col, dtype="<f8") for col in columns.values()]
    rows = len(values[0]) if values else 0
    if 0 < rows < COMPRESS_MIN_ROWS and all(v.ndim == 1 and len(v) == rows for v in values):
        # A small block (a one-sample batch, its outputs): the stream's messages put together
        # from cached headers and the values (the same bytes as Arrow's stream writer gives,
        # about 10x faster for a one-sample block of 36 columns).
        return b"".join((_schema_message(tuple(columns)), _batch_header(len(values), rows),
                         *(v.tobytes() for v in values), _EOS))
    arrays = [pa.array(v) for v in values]
    table = pa.Table.from_arrays(arrays, names=list(columns))
    if table.num_rows <= ENCODE_CHUNK_ROWS:
        sink = pa.BufferOutputStream()
        with pa.ipc.new_stream(sink, table.schema, options=_COMPRESSED) as writer:
            writer.write_table(table)
        return bytes(sink.getvalue().to_pybytes())
    # A large block goes straight into the bytes it ends as: Arrow's output stream grows by
    # doubling and is then copied out (about 4x the payload at the peak, against 2x here).
    out = io.BytesIO()
    with pa.ipc.new_stream(pa.PythonFile(out, mode="w"), table.schema, options=_COMPRESSED) as writer:
        writer.write_table(table, max_chunksize=ENCODE_CHUNK_ROWS)
    return out.getvalue()


def column_names(data: bytes) -> list[str]:
    """The names of a block's columns (reads the schema only)."""
    return list(pa.ipc.open_stream(pa.py_buffer(data)).schema.names)


def decode_columns(data: bytes, names: Collection[str] | None = None) -> dict[str, np.ndarray]:
    """A block's columns; with ``names``, only those of them the block has (the others are not
    even decompressed: a plot of 2 of 35 outputs reads 2)."""
    buf = pa.py_buffer(data)
    options = None
    if names is not None:
        schema = pa.ipc.open_stream(buf).schema
        options = pa.ipc.IpcReadOptions(included_fields=[i for i, n in enumerate(schema.names) if n in names])
    table = pa.ipc.open_stream(buf, options=options).read_all()
    # Writeable copies: numba compiles read-only arrays as a separate type, which the start-up
    # warm-up does not cover, so a zero-copy view here would make the first apply compile.
    return {
        name: np.array(table.column(name).to_numpy(), dtype=np.float64)
        for name in table.column_names
    }
