"""Telemetry encodings of a batch (the body of ``POST .../telemetry``).

* ``json``  -- ``{"batch_id", "t" | "t0" + "sample_rate_hz", "channels": {name: [...]}}``, NaN
  written as ``null``.
* ``csv``   -- header row of column names (``t`` first when times are given), one row per sample,
  an empty cell for NaN; batch id, ``t0`` and ``sample_rate_hz`` go in the query string.
* ``arrow`` -- an Arrow IPC stream of float64 columns (``t`` first when given), NaN kept as a
  float NaN; batch id, ``t0`` and ``sample_rate_hz`` go in the query string.

JSON needs numpy and orjson only; CSV and Arrow need pyarrow (the ``arrow`` extra).
"""

from __future__ import annotations

import io
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

import orjson
from numpy.typing import ArrayLike

from fleethealth_client.arrow import ipc_stream, require_pyarrow
from fleethealth_client.columns import as_float_columns, query_params, table_columns, time_params

__all__ = [
    "ARROW_STREAM_MEDIA_TYPE",
    "BATCH_FORMATS",
    "EncodedBatch",
    "encode_batch",
    "encode_batch_arrow",
    "encode_batch_csv",
    "encode_batch_json",
]

ARROW_STREAM_MEDIA_TYPE = "application/vnd.apache.arrow.stream"
BATCH_FORMATS: tuple[str, ...] = ("arrow", "json", "csv")


@dataclass(frozen=True)
class EncodedBatch:
    """A telemetry batch ready to send: body, content type and query parameters."""

    content: bytes
    content_type: str
    params: dict[str, str]


def encode_batch_json(
    batch_id: str,
    channels: Mapping[str, ArrayLike],
    *,
    t_s: ArrayLike | None = None,
    t0: float | None = None,
    sample_rate_hz: float | None = None,
) -> EncodedBatch:
    """JSON body ``{"batch_id", "t" | "t0"+"sample_rate_hz", "channels"}``; NaN becomes null."""
    t_arr, columns = as_float_columns(channels, t_s)
    body: dict[str, Any] = {"batch_id": batch_id}
    if t_arr is not None:
        body["t"] = t_arr
    body.update(time_params(t_arr, t0, sample_rate_hz))
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
    """CSV with a header row (``t`` first when given) and an empty cell for each NaN.

    Raises:
        ImportError: pyarrow is not installed (it writes the rows).
    """
    names, arrays, timing = table_columns(channels, t_s, t0, sample_rate_hz)
    pa = require_pyarrow("CSV encoding")
    import pyarrow.csv as pa_csv

    # from_pandas=True turns NaN into null, which the CSV writer leaves as an empty cell.
    table = pa.table(
        [pa.array(arr, type=pa.float64(), from_pandas=True) for arr in arrays], names=names
    )
    sink = io.BytesIO()
    sink.write((",".join(names) + "\n").encode())
    pa_csv.write_csv(table, sink, pa_csv.WriteOptions(include_header=False))
    return EncodedBatch(sink.getvalue(), "text/csv", query_params(batch_id, timing))


def encode_batch_arrow(
    batch_id: str,
    channels: Mapping[str, ArrayLike],
    *,
    t_s: ArrayLike | None = None,
    t0: float | None = None,
    sample_rate_hz: float | None = None,
) -> EncodedBatch:
    """Arrow IPC stream, one record batch of float64 columns (``t`` first when given).

    Raises:
        ImportError: pyarrow is not installed.
    """
    names, arrays, timing = table_columns(channels, t_s, t0, sample_rate_hz)
    return EncodedBatch(
        ipc_stream(names, arrays), ARROW_STREAM_MEDIA_TYPE, query_params(batch_id, timing)
    )


Encoder = Callable[..., EncodedBatch]
_ENCODERS: dict[str, Encoder] = {
    "json": encode_batch_json,
    "csv": encode_batch_csv,
    "arrow": encode_batch_arrow,
}


def encode_batch(
    fmt: str,
    batch_id: str,
    channels: Mapping[str, ArrayLike],
    *,
    t_s: ArrayLike | None = None,
    t0: float | None = None,
    sample_rate_hz: float | None = None,
) -> EncodedBatch:
    """Encode a batch in ``fmt`` (``"arrow"``, ``"json"`` or ``"csv"``).

    Raises:
        ValueError: unknown format, empty batch id, or an invalid batch (see
            :func:`fleethealth_client.columns.as_float_columns`).
        ImportError: ``"arrow"`` or ``"csv"`` without pyarrow installed.
    """
    try:
        encoder = _ENCODERS[fmt]
    except KeyError:
        raise ValueError(f"unknown format {fmt!r}; use one of {', '.join(BATCH_FORMATS)}") from None
    if not batch_id:
        raise ValueError("batch_id must not be empty")
    return encoder(batch_id, channels, t_s=t_s, t0=t0, sample_rate_hz=sample_rate_hz)
